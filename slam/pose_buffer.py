"""The buffer of a robot's own filter estimates (thesis 4.2.2, robot detections).

A detection at time t connects the two robots' filter poses at t, but the detected
robot learns of it only when the detection message arrives, maybe minutes later after
an outage. So every robot keeps its estimates of the recent past: one entry per
``period_s`` (the thesis keeps a hash map of all of them; at 20 Hz the ten minutes of
the Etna scenario are about 12,000 entries, 5 MB), looked up by time with linear
interpolation on SE(3) between the two entries around t when both lie in the same
local frame, else the nearer one.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from slam.lie import so3_exp, so3_log
from slam.messages import PoseEstimate


class PoseBuffer:
    """Filter poses of one robot over the last ``horizon_s`` seconds."""

    def __init__(self, robot: str, period_s: float = 0.05, horizon_s: float = 900.0):
        if period_s <= 0 or horizon_s <= period_s:
            raise ValueError(f"pose buffer needs 0 < period ({period_s}) < horizon ({horizon_s})")
        self.robot = robot
        self.period_s = period_s
        self.horizon_s = horizon_s
        self._t: deque[float] = deque()
        self._entries: deque[PoseEstimate] = deque()

    def __len__(self) -> int:
        return len(self._t)

    def due(self, t: float) -> bool:
        """True if an estimate at ``t`` is to be stored (one per period)."""
        return not self._t or t >= self._t[-1] + self.period_s - 1e-9

    def add(self, t: float, frame_index: int, T_frame_body: np.ndarray, cov: np.ndarray) -> None:
        if self._t and t <= self._t[-1]:
            raise ValueError(f"pose buffer of {self.robot}: time {t} is not after the last entry {self._t[-1]}")
        self._t.append(t)
        self._entries.append(PoseEstimate(self.robot, t, frame_index, np.array(T_frame_body, float), np.array(cov, float)))
        while self._t[0] < t - self.horizon_s:
            self._t.popleft()
            self._entries.popleft()

    def at(self, t: float, latest: PoseEstimate | None = None) -> PoseEstimate | None:
        """The estimate at ``t``, or None outside the buffered span. ``latest``, the filter's
        current estimate, extends the span to its time: an image captured since the last
        entry (at most one period ago) is interpolated between that entry and ``latest``."""
        if latest is not None and self._t and self._t[-1] + 1e-9 < t <= latest.t + 1e-9:
            return self._between(self._entries[-1], latest, t)
        if not self._t or t < self._t[0] - 1e-9 or t > self._t[-1] + 1e-9:
            return None
        i = bisect.bisect_left(self._t, t - 1e-9)
        after = self._entries[i]
        if abs(after.t - t) <= 1e-9 or i == 0:
            return PoseEstimate(self.robot, t, after.frame_index, after.T_frame_body, after.cov)
        return self._between(self._entries[i - 1], after, t)

    def _between(self, before: PoseEstimate, after: PoseEstimate, t: float) -> PoseEstimate:
        """Linear interpolation on SE(3) at ``before.t < t <= after.t`` within one local frame,
        else the nearer estimate."""
        if before.frame_index != after.frame_index:  # a frame switch in between: no common frame
            near = before if t - before.t <= after.t - t else after
            return PoseEstimate(self.robot, t, near.frame_index, near.T_frame_body, near.cov)
        s = (t - before.t) / (after.t - before.t)
        A, B = before.T_frame_body, after.T_frame_body
        T = np.eye(4)
        T[:3, :3] = A[:3, :3] @ so3_exp(s * so3_log(A[:3, :3].T @ B[:3, :3]))
        T[:3, 3] = (1 - s) * A[:3, 3] + s * B[:3, 3]
        return PoseEstimate(self.robot, t, after.frame_index, T, after.cov)  # the later, larger covariance
