"""Guidance on the robot's own estimate: where it believes it is, and a path around the
obstacles it mapped (``navigation.pose_source: estimate``; thesis 9.2.2 and 9.3).

The robot's computer knows three things (sim/run/onboard.py supplies them as an
:class:`OwnEstimate`): the filter's pose in its odometry frame (its first local frame,
switches chained), the rolling obstacle map in that same frame (thesis 5.1.1), and where
its SLAM map puts that odometry frame (eq. 4.6) in the mission frame, which it knows from
where it was deployed. Local planning runs in the odometry frame, which is smooth and in
which the obstacle map is consistent; goals come from the mission frame through the SLAM
estimate, so that loop closures move the goals, not the map.

:class:`PathFollower` plans with ``slam.navigation.planner`` every ``replan_period_s`` (on
the map as it is then, so new obstacles are avoided within one period) and steers at the
path's point ``lookahead_m`` ahead (pure pursuit).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Protocol

import numpy as np

from slam.lie import apply_planar, se3_inv
from slam.navigation.planner import Path, PlannerParams, cost_grid, plan
from slam.navigation.planner import lookahead as path_lookahead

if TYPE_CHECKING:
    from sim.scenario import NavigationConfig, WaypointConfig
    from slam.obstacles import RollingObstacleMap


class OwnEstimate(Protocol):
    """What the robot's computer believes, as its guidance reads it."""

    @property
    def obstacle_map(self) -> RollingObstacleMap:
        """The rolling obstacle map, in the odometry frame."""

    def odometry_pose(self) -> np.ndarray | None:
        """``T_odom_body`` from the filter; None before it is initialised."""

    def world_from_odometry(self) -> np.ndarray:
        """``T_world_odom``: the odometry frame in the mission frame, as the robot believes."""


class GoalSource(Protocol):
    """Where an exploring robot's goals come from (sim/run/onboard.py, thesis 9.3)."""

    @property
    def finished(self) -> bool:
        """The robot explores no more."""

    def next_goal(self, t: float) -> WaypointConfig | None:
        """The next goal (mission frame) as a waypoint to add to the route; None while it is
        being chosen."""

    def yields(self, goal_xy) -> bool:
        """Whether the robot should give up its goal ``goal_xy`` for a peer's (it then fails
        as "withdrawn" and the robot asks for another)."""


class GazeSource(Protocol):
    """Where a robot with a pan-tilt head should look (sim/run/onboard.py; active mutual
    observation, slam/navigation/observation.py)."""

    def look_at(self, t: float) -> np.ndarray | None:
        """A 3D point (mission frame, as believed) to point the cameras at now, or None."""


class PathFollower:
    """Plans towards a goal in the mission frame and hands the controller the point to steer at."""

    def __init__(self, cfg: NavigationConfig, params: PlannerParams):
        self.cfg = cfg
        self.params = params
        self.path: Path | None = None  # in the odometry frame
        self.plans = 0
        self.seconds = 0.0  # wall time spent planning
        self._next_plan = -np.inf
        self._goal: np.ndarray | None = None

    def steer_point(self, t: float, estimate: OwnEstimate, T_odom_body: np.ndarray, goal_world) -> np.ndarray:
        """The point (mission frame, as believed) to steer at now on the way to ``goal_world``."""
        T_world_odom = estimate.world_from_odometry()
        goal = apply_planar(se3_inv(T_world_odom), goal_world)
        xy = T_odom_body[:2, 3]
        moved_goal = self._goal is None or np.linalg.norm(goal - self._goal) > self.params.cell_m
        if t >= self._next_plan or moved_goal:
            self._replan(estimate.obstacle_map, xy, goal)
            self._next_plan = t + self.cfg.replan_period_s
        if self.path is None:
            return np.asarray(goal_world, float)[:2].copy()
        carrot = path_lookahead(self.path, xy, self.cfg.lookahead_m)
        if self.path.reaches_goal and np.linalg.norm(carrot - self.path.xy[-1]) < 1e-9:
            carrot = goal  # the last stretch: to the goal itself, not its cell centre
        return apply_planar(T_world_odom, carrot)

    def _replan(self, rolling: RollingObstacleMap, xy: np.ndarray, goal: np.ndarray) -> None:
        t0 = time.perf_counter()
        grid = cost_grid(rolling.traversability, rolling.origin, rolling.resolution_m, self.params)
        self.path = plan(grid, xy, goal)
        self._goal = goal
        self.plans += 1
        self.seconds += time.perf_counter() - t0

    def reset(self) -> None:
        """A new goal: plan at the next call."""
        self.path, self._goal, self._next_plan = None, None, -np.inf
