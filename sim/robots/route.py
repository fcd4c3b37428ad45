"""Route bookkeeping shared by all robots: waypoint records, timeouts, stuck detection.

A waypoint is never skipped silently: it ends "reached" or "failed" with a reason
("stuck": no progress towards it for ``stuck_timeout_s``; "timeout": not reached
within 3 x leg length / speed + 30 s; "tipped_over": the robot tipped over before
reaching it, which also ends the route). An exploring robot's goals (thesis 9.3) are
added to the route as it chooses them (:meth:`RouteTracker.add`), and recorded alike;
one it gives up for a peer's goal fails as "withdrawn".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # sim.scenario imports this package to validate robots
    from sim.scenario import RouteConfig, WaypointConfig

PROGRESS_EPS_M = 0.05  # getting closer by less than this is not progress
PROGRESS_EPS_RAD = math.radians(10)  # nor is turning towards the waypoint by less than this
TIMEOUT_FACTOR = 3.0
TIMEOUT_SLACK_S = 30.0


@dataclass
class WaypointRecord:
    index: int
    xy: tuple[float, float]
    status: str = "pending"  # "pending" | "reached" | "failed"
    reached_t: float | None = None  # time of arrival ("reached" only)
    reason: str | None = None  # failure reason: "stuck", "tipped_over", "timeout", "withdrawn", "dead"
    failed_t: float | None = None  # time of giving up ("failed" only)
    final_xy: tuple[float, float] | None = None  # true robot xy at arrival / when giving up


class RouteTracker:
    def __init__(self, route: RouteConfig):
        self.cfg = route
        self.waypoints = list(route.waypoints)  # the scenario's, then any added
        self.records = [WaypointRecord(i, (float(w.xy[0]), float(w.xy[1]))) for i, w in enumerate(self.waypoints)]
        self.current = 0
        self.leg_start_t = 0.0
        self.leg_start_xy = np.zeros(2)
        self.leg_length = 0.0
        self.deadline = math.inf
        self._best = math.inf
        self._best_t = 0.0

    @property
    def done(self) -> bool:
        return self.current >= len(self.records)

    @property
    def target(self) -> WaypointConfig:
        return self.waypoints[self.current]

    @property
    def target_xy(self) -> np.ndarray:
        return np.asarray(self.records[self.current].xy, float)

    def add(self, waypoint: WaypointConfig) -> None:
        """Append a waypoint (an exploration goal) to the route."""
        self.waypoints.append(waypoint)
        self.records.append(WaypointRecord(len(self.records), (float(waypoint.xy[0]), float(waypoint.xy[1]))))

    def begin_leg(self, t: float, xy) -> None:
        """Start (or restart the clocks of) the leg to the current waypoint."""
        self.leg_start_t = t
        self.leg_start_xy = np.asarray(xy, float)[:2].copy()
        self.leg_length = float(np.linalg.norm(self.target_xy - self.leg_start_xy))
        self.deadline = t + TIMEOUT_FACTOR * self.leg_length / self.cfg.speed_mps + TIMEOUT_SLACK_S
        self._best = math.inf
        self._best_heading = math.inf
        self._best_t = t

    def check(self, t: float, xy, heading_error: float | None = None) -> str | None:
        """Progress bookkeeping for the current leg; returns a failure reason or None.

        Progress is getting closer to the waypoint or, for a robot that turns before it
        drives (``heading_error``: angle between its heading and the waypoint), turning
        towards it.
        """
        d = float(np.linalg.norm(self.target_xy - np.asarray(xy, float)[:2]))
        if d < self._best - PROGRESS_EPS_M:
            self._best = d
            self._best_t = t
        if heading_error is not None and abs(heading_error) < self._best_heading - PROGRESS_EPS_RAD:
            self._best_heading = abs(heading_error)
            self._best_t = t
        if t > self.deadline:
            return "timeout"
        if t - self._best_t > self.cfg.stuck_timeout_s:
            return "stuck"
        return None

    def distance(self, xy) -> float:
        return float(np.linalg.norm(self.target_xy - np.asarray(xy, float)[:2]))

    def reach(self, t: float, xy) -> None:
        rec = self.records[self.current]
        rec.status, rec.reached_t = "reached", t
        rec.final_xy = (float(xy[0]), float(xy[1]))
        self.current += 1

    def fail(self, t: float, xy, reason: str) -> None:
        rec = self.records[self.current]
        rec.status, rec.failed_t, rec.reason = "failed", t, reason
        rec.final_xy = (float(xy[0]), float(xy[1]))
        self.current += 1

    def fail_remaining(self, t: float, reason: str) -> None:
        while not self.done:
            rec = self.records[self.current]
            rec.status, rec.failed_t, rec.reason = "failed", t, reason
            self.current += 1
