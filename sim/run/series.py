"""Compact containers for what a run logs for hours: rows of fixed shape and error distributions.

A Python list of small numpy arrays costs about 100 bytes of object overhead per row on top of the data; a
run logs ground truth and estimates at 50 Hz and the IMU at 200 Hz per robot. :class:`Rows` keeps them in one
growing array instead. :class:`LogHistogram` keeps an error distribution (per-pixel stereo depth errors:
about 20,000 values per image) as counts in logarithmic bins, so its memory does not grow with the number
of images; its quantiles are exact to within a bin (:data:`BINS_PER_DECADE`: 0.5 % relative).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np

BINS_PER_DECADE = 200  # bin ratio 10^(1/200) = 1.0116: a quantile is within 0.58 % of the exact one


class Rows:
    """Rows of one shape (the first row's) and ``dtype`` in an array that doubles when full. Reads like a
    sequence of the rows and converts with ``np.asarray``."""

    def __init__(self, capacity: int = 1024, dtype: Any = np.float64):
        self._capacity = capacity
        self._dtype = np.dtype(dtype)
        self._data: np.ndarray | None = None
        self._n = 0

    def append(self, row: Any) -> None:
        row = np.asarray(row, dtype=self._dtype)
        if self._data is None:
            self._data = np.empty((self._capacity, *row.shape), dtype=self._dtype)
        elif self._n == len(self._data):
            grown = np.empty((2 * len(self._data), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._n] = self._data
            self._data = grown
        self._data[self._n] = row
        self._n += 1

    def view(self) -> np.ndarray:
        """The rows as an array without copying (later appends may or may not show in it)."""
        return self._data[: self._n] if self._data is not None else np.zeros(0, dtype=self._dtype)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index):
        return self.view()[index]

    def __iter__(self) -> Iterator[Any]:
        return iter(self.view())

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        """A copy of the rows: what the caller holds does not share the buffer that later appends write."""
        return np.array(self.view(), dtype=dtype)


class LogHistogram:
    """Counts of positive values in logarithmic bins from ``lo`` to ``hi`` (values outside fall into the end
    bins); :meth:`quantile` interpolates geometrically within a bin."""

    def __init__(self, lo: float, hi: float):
        self._log_lo = math.log10(lo)
        self._bins = round((math.log10(hi) - self._log_lo) * BINS_PER_DECADE)
        self.counts = np.zeros(self._bins, dtype=np.int64)

    def add(self, values: np.ndarray) -> None:
        """Count ``values`` (non-finite ones are not counted)."""
        values = np.asarray(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        index = np.floor((np.log10(np.maximum(values, 1e-300)) - self._log_lo) * BINS_PER_DECADE).astype(np.int64)
        self.counts += np.bincount(np.clip(index, 0, self._bins - 1), minlength=self._bins)

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def quantile(self, q: float) -> float | None:
        """The ``q`` quantile (0..1), None when empty."""
        n = self.n
        if n == 0:
            return None
        cumulative = np.cumsum(self.counts)
        target = q * n
        k = int(np.searchsorted(cumulative, target, side="left"))
        below = cumulative[k - 1] if k > 0 else 0
        within = (target - below) / self.counts[k] if self.counts[k] else 0.0
        return float(10 ** (self._log_lo + (k + within) / BINS_PER_DECADE))

    @staticmethod
    def merged(histograms: list[LogHistogram]) -> LogHistogram | None:
        """One histogram of several with the same bins (None for none)."""
        if not histograms:
            return None
        out = LogHistogram.__new__(LogHistogram)
        out._log_lo, out._bins = histograms[0]._log_lo, histograms[0]._bins
        out.counts = sum(h.counts for h in histograms)
        return out
