"""How a robot got around: collisions, stuck waypoints, how far from a waypoint it truly
was when it believed it had arrived, and how far its guidance's belief was from the truth
(``navigation.pose_source: estimate``; thesis 9.3).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.evaluation.trajectory import Trajectory
from sim.robots.base import Robot
from sim.run.collisions import Collision


def _stats(values: np.ndarray) -> dict[str, float] | None:
    return None if values.size == 0 else {"median": float(np.median(values)), "max": float(values.max())}


def navigation_metrics(
    robot: Robot, collisions: list[Collision], guidance_t: np.ndarray, guidance_xy: np.ndarray, truth: Trajectory
) -> dict[str, Any]:
    """The ``navigation`` section of a robot's metrics. ``guidance_*``: where the robot
    believed it was (empty when it steered by the truth); ``truth``: its true trajectory."""
    reached = [w for w in robot.waypoints if w.status == "reached" and w.final_xy is not None]
    miss = np.array([np.hypot(w.final_xy[0] - w.xy[0], w.final_xy[1] - w.xy[1]) for w in reached])
    out: dict[str, Any] = {
        "pose_source": robot.cfg.navigation.pose_source,
        "collisions": len(collisions),
        "collision_events": [{"t": round(c.t, 3), "with": c.other} for c in collisions],
        "stuck": sum(w.reason == "stuck" for w in robot.waypoints),
        # the true distance to a waypoint on arrival: with estimate guidance, where it believed it was within tolerance_m
        "waypoint_miss_m": _stats(miss),
    }
    if robot.follower is not None:
        out["plans"] = robot.follower.plans
        out["planning_s"] = robot.follower.seconds
    if len(guidance_t) and len(truth):
        at = np.minimum(np.searchsorted(truth.t, np.asarray(guidance_t) - 1e-6), len(truth.t) - 1)  # as Trajectory.at
        err = np.linalg.norm(np.asarray(guidance_xy) - truth.T[at, :2, 3], axis=1)
        out["guidance_error_m"] = {"mean": float(err.mean()), "max": float(err.max()), "final": float(err[-1])}
    return out
