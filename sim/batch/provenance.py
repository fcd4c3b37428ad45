"""Where a result came from: the commit the code is at and the command that ran it.

Batch indexes (``sim.batch.execute.Index``) and regression baselines
(``sim.batch.regress``) record it, so that a committed report names the commit and the
command that produced it.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
#: The folders whose changes change what a run computes.
CODE = ("sim", "slam", "comms", "scenarios", "assets")


def git_state() -> dict[str, Any]:
    """``git_commit`` (None outside a git checkout) and ``git_dirty``: whether the code
    (:data:`CODE`) differs from that commit."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {"git_commit": git("rev-parse", "HEAD"), "git_dirty": bool(git("status", "--porcelain", "--", *CODE))}
    except (OSError, subprocess.CalledProcessError):
        return {"git_commit": None, "git_dirty": None}


def command_line() -> str:
    """This process's command line as a shell would take it, the program by its name (``marsyard batch ...``)."""
    return shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])
