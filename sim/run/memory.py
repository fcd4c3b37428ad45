"""The run's memory over simulated time: resident set size (RSS) samples and their growth.

A long run must stay bounded: nothing may grow with the number of images. :class:`MemoryTrace` samples the
process's RSS every :data:`SAMPLE_EVERY_S` simulated seconds; ``metrics.json`` ``runtime.memory`` reports the
peak of the samples and the growth rate over the second half of the run (a least-squares slope, MB per
simulated hour), where set-up allocations no longer count. RSS is read from ``/proc/self/statm`` (Linux);
elsewhere from ``resource.getrusage``'s peak, which never falls.
"""

from __future__ import annotations

import os
import resource
import sys
from pathlib import Path
from typing import Any

import numpy as np

SAMPLE_EVERY_S = 10.0
_STATM = Path("/proc/self/statm")
_PAGE_BYTES = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb() -> float:
    """The process's resident set size now (MB)."""
    try:
        return int(_STATM.read_text().split()[1]) * _PAGE_BYTES / 2**20
    except (OSError, IndexError, ValueError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / 2**20 if sys.platform == "darwin" else peak / 2**10  # bytes on macOS, KiB on Linux


class MemoryTrace:
    """RSS samples ``(simulated s, MB)``, one at least every :data:`SAMPLE_EVERY_S`."""

    def __init__(self, every_s: float = SAMPLE_EVERY_S):
        self.every_s = every_s
        self.samples: list[tuple[float, float]] = []

    def poll(self, t: float, force: bool = False) -> None:
        """Take a sample if the last one is ``every_s`` old (or there is none), or ``force``."""
        if force or not self.samples or t >= self.samples[-1][0] + self.every_s - 1e-9:
            self.samples.append((t, rss_mb()))

    def metrics(self) -> dict[str, Any]:
        """``peak_rss_mb`` (of the samples), ``growth_mb_per_h`` over the second half (None under 4 samples
        there) and the samples."""
        if not self.samples:
            return {"peak_rss_mb": None, "growth_mb_per_h": None, "samples": []}
        t, mb = np.array(self.samples).T
        late = t >= t[-1] / 2
        growth = None
        if np.count_nonzero(late) >= 4 and np.ptp(t[late]) > 0:
            growth = float(np.polyfit(t[late], mb[late], 1)[0] * 3600.0)
        return {"peak_rss_mb": float(mb.max()), "growth_mb_per_h": growth, "samples": [[float(a), round(float(b), 1)] for a, b in self.samples]}
