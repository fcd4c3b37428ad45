"""What the evaluation reads from a finished run, as typed inputs: the one place that
reaches into the run's objects (:class:`sim.run.runner.Run`, its robots'
:class:`sim.run.onboard.OnboardStack`).

Each section of ``metrics.json`` takes its own input, next to :class:`TeamTruth`, the
simulator's ground truth: :class:`FilterInput` (``robots.<name>.filter``,
:mod:`sim.evaluation.results_folder`), :class:`SlamInput` (``robots.<name>.slam``,
:mod:`sim.evaluation.online_slam`), :class:`MapInput` (``robots.<name>.map``,
:mod:`sim.evaluation.maps`), :class:`ClosureInput` (``loop_closures``,
:mod:`sim.evaluation.loop_closures`) and :class:`ExplorerInput` (``exploration``,
:mod:`sim.evaluation.exploration`). The results folder reads each input inside its
section's guard, so that a failure to read costs that section only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sim.evaluation.trajectory import Trajectory

if TYPE_CHECKING:
    from sim.evaluation.image_classification import ImageCells
    from sim.run.onboard import OnboardStack
    from sim.run.runner import Run
    from sim.run.series import Rows
    from sim.scenario import MappingConfig
    from slam.agent import AgentStats, DetectionRecord
    from slam.graph import MultiRobotGraph
    from slam.navigation.exploration import Goal
    from slam.obstacles import ObstacleParams, RollingObstacleMap
    from slam.submap import Submap
    from slam.team_matcher import TeamMatcher

_EMPTY = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))


@dataclass(frozen=True, eq=False)
class TeamTruth:
    """A run's ground truth in the world frame: each robot's body trajectory (robots with
    at least one sample), the pose of the landmark (the lander's tag; None without), and
    each robot's horizontal reach around its body origin (``Robot.body_radius_m``)."""

    robots: dict[str, Trajectory]
    landmark: np.ndarray | None
    body_radius_m: dict[str, float]

    def of(self, robot: str) -> Trajectory:
        """The robot's trajectory, empty for a robot without ground truth."""
        return self.robots.get(robot, _EMPTY)


@dataclass(frozen=True, eq=False)
class FilterInput:
    """The local reference filter's online log (``sim.run.onboard.EstimateLog``, sampled
    on the ground-truth clock) and its counters."""

    estimate: Trajectory  # in the filter's first frame, frame switches chained
    position_std: np.ndarray  # (N, 3), in the local frame of the time
    observable: np.ndarray  # (N, 5): roll, pitch, body velocity
    observable_true: np.ndarray
    observable_cov: np.ndarray  # (N, 5, 5)
    bias: np.ndarray  # (N, 6): accelerometer, gyro
    bias_true: np.ndarray
    vo: dict  # LocalEstimator.vo_report(): counts, rejections and failures by reason
    vo_deltas: dict  # VoDeltaScores.report(): the deltas against the true camera motion
    rest: dict  # LocalEstimator.rest_report(): zero-velocity updates and their intervals
    frame_switches: int


@dataclass(frozen=True, eq=False)
class SlamInput:
    """A robot's collaborative SLAM as it ended (its ``slam.agent.Agent``) and what it
    believed online (``sim.run.onboard.SlamLog``; thesis ch. 8: never re-optimised)."""

    start_t: float | None  # the filter's first estimate: the time of the map frame's truth
    switch_times: dict[int, float]  # local frame index -> time of the switch into it (submap origins' truth)
    estimate: Trajectory  # its own pose in its map frame (eq. 4.6)
    final_estimate: Trajectory  # the same times by the final graph: its logged filter poses on the final submap origins
    beliefs: dict[str, Rows]  # peer -> rows [t, t of the estimate, the 16 entries of the pose in this map]
    graph: MultiRobotGraph
    marginals: dict[tuple[str, int], np.ndarray]  # submap origin -> 6x6 covariance
    stats: AgentStats
    detections: list[DetectionRecord]
    submaps_received: int


@dataclass(frozen=True, eq=False)
class MapInput:
    """A robot's mapping as it ended, its submaps placed in its map frame: by its graph
    (its peers' submaps included) or, without one, by its filter's chained frame switches."""

    start_t: float | None  # the filter's first estimate: the time of the map frame's truth
    switch_times: dict[int, float]  # local frame index -> time of the switch into it (submap origins' truth)
    mapping: MappingConfig
    obstacle: ObstacleParams  # the classification it ran with (thesis 5.1.1)
    image_cells: ImageCells | None  # its mapped images' obstacle cells at true camera poses
    own_submaps: list[Submap]  # its finished submaps
    active_images: int  # images in the submap under construction
    images_integrated: int
    placed: list[tuple[Submap, np.ndarray]]  # finished submaps with their origins T_map_submap
    current: tuple[Submap, np.ndarray] | None  # the submap under construction with its origin, if it has images
    partitions: list[tuple[float, str]]  # (t, reason) of each new submap
    rolling: RollingObstacleMap  # in the odometry frame (= the map frame)
    T_map_body: np.ndarray | None  # the filter's final pose in the map frame (None before its start)


@dataclass(frozen=True, eq=False)
class ClosureInput:
    """A robot's loop closures (thesis 8.1.2, 8.1.3): its submap matcher (None without
    matching) and its detections, with the times of its local frames, whose true poses
    are its submap origins' truth."""

    start_t: float | None  # the filter's first estimate: local frame 0
    switch_times: dict[int, float]  # the later local frames: index -> time of the switch
    matcher: TeamMatcher | None
    detections: list[DetectionRecord]


@dataclass(frozen=True, eq=False)
class ExplorerInput:
    """An exploring robot (thesis 9.3): its own submaps (finished, and the active one) with
    the times of its local frames, whose true poses are their origins' truth; each answer of
    its explorer with its time; its route's goals; when its head turned to a peer (active
    mutual observation)."""

    start_t: float | None
    switch_times: dict[int, float]
    submaps: list[Submap]
    goals: list[tuple[float, Goal]]
    waypoints: list  # sim.robots.route.WaypointRecord, the scenario's waypoints first
    scripted: int  # how many of them the scenario gave
    observations: list[tuple[float, str]]


def explorer_inputs(run: Run) -> dict[str, ExplorerInput]:
    """Every exploring robot."""
    out = {}
    for name, runtime in run.robots.items():
        onboard = runtime.onboard
        if onboard is None or onboard.explorer is None:
            continue
        builder = onboard.mapper.builder
        active = [builder.current()] if builder.images else []
        out[name] = ExplorerInput(
            start_t=_start_t(onboard),
            switch_times=_switch_times(onboard),
            submaps=list(onboard.mapper.submaps) + active,
            goals=list(onboard.goals),
            waypoints=list(runtime.robot.waypoints),
            scripted=len(runtime.robot.cfg.route.waypoints),
            observations=list(onboard.observations),
        )
    return out


def _stack(rows: list[np.ndarray], *shape: int) -> np.ndarray:
    return np.stack(rows) if rows else np.zeros((0, *shape))


def _start_t(onboard: OnboardStack) -> float | None:
    return onboard.log.t[0] if onboard.log.t else None


def _switch_times(onboard: OnboardStack) -> dict[int, float]:
    return {s.frame_index: s.t for s in onboard.estimator.switches}


def lander_tag_pose(model, data) -> np.ndarray | None:
    """World pose of the lander's tag (the landmark's frame), or None without a lander."""
    for g in range(model.ngeom):
        if model.geom(g).name.endswith("lander_tag"):
            T = np.eye(4)
            T[:3, :3] = data.geom_xmat[g].reshape(3, 3)
            T[:3, 3] = data.geom_xpos[g]
            return T
    return None


def team_truth(run: Run) -> TeamTruth:
    robots = {n: Trajectory.from_pose_rows(r.log.gt_t, r.log.gt_pose) for n, r in run.robots.items() if r.log.gt_pose}
    radii = {n: r.robot.body_radius_m for n, r in run.robots.items()}
    return TeamTruth(robots, lander_tag_pose(run.world.model, run.world.data), radii)


def filter_input(onboard: OnboardStack) -> FilterInput:
    log, estimator = onboard.log, onboard.estimator
    return FilterInput(
        estimate=Trajectory.from_lists(log.t, log.pose_first_frame),
        position_std=_stack(log.position_std, 3),
        observable=_stack(log.observable, 5),
        observable_true=_stack(log.observable_true, 5),
        observable_cov=_stack(log.observable_cov, 5, 5),
        bias=_stack(log.bias, 6),
        bias_true=_stack(log.bias_true, 6),
        vo=estimator.vo_report(),
        vo_deltas=onboard.vo_scores.report(),
        rest=estimator.rest_report(),
        frame_switches=len(estimator.switches),
    )


def health_report(onboard: OnboardStack, t_end: float) -> dict:
    """The estimator's verdict on itself at the end of the run (slam/health.py)."""
    return onboard.estimator.health_report(t_end)


def slam_input(onboard: OnboardStack) -> SlamInput | None:
    """None for a robot without the graph (``slam.graph.enabled`` off)."""
    if not onboard.exchange:
        return None
    agent, slog = onboard.agent, onboard.slam_log
    return SlamInput(
        start_t=_start_t(onboard),
        switch_times=_switch_times(onboard),
        estimate=Trajectory.from_lists(slog.t, slog.pose),
        final_estimate=_final_estimate(onboard),
        beliefs=slog.beliefs,
        graph=agent.graph,
        marginals=agent.marginals,
        stats=agent.stats,
        detections=agent.detections,
        submaps_received=len(agent.peer_submaps),
    )


def final_graph(onboard: OnboardStack) -> MultiRobotGraph | None:
    """The robot's graph as the run ended; None without one (``slam.graph.enabled`` off)."""
    return onboard.agent.graph if onboard.exchange else None


def _final_estimate(onboard: OnboardStack) -> Trajectory:
    """The robot's trajectory by its final graph: each pose its filter logged, in its local frame
    of the time, placed on that frame's origin as the graph holds it at the end, as the online
    pose is (eq. 4.6, :meth:`slam.agent.Agent.pose_in_map`); a pose the graph cannot place is
    left out."""
    log, agent, origins = onboard.log, onboard.agent, onboard.estimator.frame_origins
    t, frames, T_first_body = np.asarray(log.t), np.asarray(log.frame_index), np.asarray(log.pose_first_frame)
    keep, poses = np.zeros(len(t), bool), np.zeros((len(t), 4, 4))
    for j in np.unique(frames):  # one origin per local frame, then all its poses at once
        S = agent.pose_in_map(agent.name, int(j), np.eye(4))
        if S is not None:
            sel = frames == j
            keep[sel] = True
            poses[sel] = S @ np.linalg.solve(origins[int(j)][None], T_first_body[sel])
    return Trajectory(t[keep], poses[keep])


def map_input(onboard: OnboardStack, image_cells: ImageCells | None = None) -> MapInput | None:
    """None for a robot without mapping (``slam.mapping.enabled`` off)."""
    mapper, estimator = onboard.mapper, onboard.estimator
    if mapper is None:
        return None
    if onboard.exchange:
        placed, current = onboard.agent.placed_submaps(), onboard.agent.active_submap()
    else:
        frames = estimator.frame_origins  # T_map_frame of every local frame: the submap origins
        placed = [(s, frames[s.frame_index]) for s in mapper.submaps]
        active = mapper.builder.current()
        current = (active, frames[active.frame_index]) if active.images else None
    return MapInput(
        start_t=_start_t(onboard),
        switch_times=_switch_times(onboard),
        mapping=onboard.slam_cfg.mapping,
        obstacle=mapper.obstacle_params,
        image_cells=image_cells,
        own_submaps=list(mapper.submaps),
        active_images=mapper.builder.images,
        images_integrated=mapper.images,
        placed=placed,
        current=current,
        partitions=list(onboard.partitions),
        rolling=mapper.rolling,
        T_map_body=estimator.T_first_current @ estimator.filter.pose() if estimator.initialised else None,
    )


def closure_inputs(run: Run) -> dict[str, ClosureInput]:
    """Every robot with the graph."""
    out = {}
    for name, runtime in run.robots.items():
        onboard = runtime.onboard
        if onboard is None or not onboard.exchange:
            continue
        agent = onboard.agent
        out[name] = ClosureInput(
            start_t=_start_t(onboard),
            switch_times=_switch_times(onboard),
            matcher=agent.matcher,
            detections=agent.detections,
        )
    return out
