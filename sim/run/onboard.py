"""One robot's on-board SLAM pipeline as lane jobs (docs/architecture.md, "One run").

Sensor data from the run loop become jobs on the robot's lane, in the order its
computer would process them: every IMU sample a ``strapdown`` job, every wheel
odometry sample and every image trigger (filter clone) a ``filter_update`` job; a
stereo pair is matched on the FPGA (``stereo``), then the VO rig's depth goes to a
``vo`` job on a core, whose delta pose is applied by a ``filter_update`` job when
it is done: about 250 ms after capture with the default costs, so estimates appear
when a robot would have them. Real code runs in every job; only its duration is
modelled. The robot's :class:`slam.agent.Agent` holds estimator, mapping and graph:
marker detection runs on every camera image (``detection``), peer messages are
decoded as ``messages`` jobs and the graph is optimised as a background ``graph`` job
whenever factors arrived; what the agent sends goes onto the network. An exploring robot
chooses each goal on its maps in an ``exploration`` job (slam/navigation/explorer.py)
and announces it to the team. What the filter and the graph believe is logged next to
ground truth for evaluation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from comms import Delivery, Network
from sim.evaluation.vo_consistency import VoDeltaScores
from sim.robots.base import Robot
from sim.run.faults import measurement_faults
from sim.run.lanes import Lane, Priority
from sim.run.series import Rows
from sim.scenario import ExplorationConfig, MappingConfig, Scenario, SlamConfig, WaypointConfig, slam_kwargs
from sim.seeding import RandomStreams
from sim.tools.marker_lut import load_tables
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from sim.world.sensors import ImuSpec
from slam.agent import Agent, AgentParams, Outgoing, TeamMarker
from slam.filter import FilterParams
from slam.graph import GraphParams
from slam.health import HealthParams
from slam.lie import roll_pitch, rot_z, se3, se3_inv
from slam.local_estimator import FramePose, LocalEstimator
from slam.local_mapper import LocalMapper
from slam.markers import MarkerDetection
from slam.matcher import MatcherParams, MatchResult
from slam.navigation.exploration import ExplorationParams, Goal, RevisitPlace
from slam.navigation.explorer import Explorer
from slam.navigation.observation import peer_to_observe
from slam.obstacles import Classification, ObstacleParams
from slam.rest import RestParams
from slam.stereo import StereoCalibration, depth_error, remove_disparity_offset
from slam.submap import SubmapParams
from slam.vo import StereoVO, VoParams, VoResult

TRUTH_MATCH_S = 1e-6  # s: a truth sample is at the filter's time within this

#: Tilt error of the resting initialisation beyond the accelerometer bias: the mean of
#: 0.5 s of samples has a noise of a few thousandths of a degree; the rest is margin for
#: a robot that is not perfectly still (motors idling, a settling suspension).
RESTING_TILT_STD = math.radians(0.2)
GAZE_PERIOD_S = 0.5  # the peer to look at is chosen again this often (active mutual observation)
PEER_ESTIMATE_MAX_AGE_S = 5.0  # a peer's periodic estimate older than this places it no more (1.5 m at 0.3 m/s)


def _deployment(start) -> np.ndarray:
    """``T_world_map``: a robot's map frame where it was deployed (the scenario's start; height plays no part)."""
    return se3(rot_z(math.radians(start.yaw_deg)), [start.xy[0], start.xy[1], 0.0])


def filter_params(spec: ImuSpec, gravity: float, cfg: SlamConfig, robot: type[Robot]) -> FilterParams:
    """The filter's noise model from the IMU's datasheet values (what the robot knows), the
    scenario's ``slam`` keys and the robot's own motion (what bridges a stuck IMU).

    Roll and pitch start from the resting accelerometer; the filter's prior correlates
    their error with the accelerometer bias (b / g), so only the small rest of the tilt
    error (:data:`RESTING_TILT_STD`) is independent."""
    return FilterParams(
        **slam_kwargs(FilterParams, cfg),
        initial_roll_pitch_std=RESTING_TILT_STD,
        gyro_noise_density=spec.gyro_noise_density,
        accel_noise_density=spec.accel_noise_density,
        gyro_bias_random_walk=spec.gyro_random_walk,
        accel_bias_random_walk=spec.accel_random_walk,
        initial_accel_bias_std=spec.accel_bias_initial_std,
        initial_gyro_bias_std=spec.gyro_bias_initial_std,
        gravity=gravity,
        motion_accel_density=robot.motion_accel_density,
        motion_turn_density=robot.motion_turn_density,
    )


def local_mapper(robot: str, calib: StereoCalibration, cfg: MappingConfig) -> LocalMapper:
    """The robot's mapping from its scenario section (thesis 5.1)."""
    return LocalMapper(robot, calib, ObstacleParams(**slam_kwargs(ObstacleParams, cfg)), SubmapParams(**slam_kwargs(SubmapParams, cfg)))


def matcher_params(cfg: SlamConfig, calib: StereoCalibration, seed: int) -> MatcherParams | None:
    """Submap matching from ``slam.matching``, eq. 6.3's stereo error by eq. 5.2c at
    ``stereo_error_depth_m`` for the robot's VO rig."""
    m = cfg.matching
    if not (m.enabled and cfg.mapping.enabled and cfg.graph.enabled):
        return None
    return MatcherParams(**slam_kwargs(MatcherParams, m), stereo_error_m=float(depth_error(m.stereo_error_depth_m, calib)), seed=seed)


def _icp_stage(result: MatchResult) -> tuple[str, ...]:
    """A matching attempt's ICP (thesis 8.4: "only computed for almost certain matches")
    costs its own stage, on top of the feature matching and voting every attempt costs; the
    4D+6D mode's second refinement, started from the first's result, is charged with it."""
    return ("icp",) if result.reached_icp else ()


def agent_params(cfg: SlamConfig, matching: MatcherParams | None = None, marker_tables: dict | None = None) -> AgentParams:
    """The agent's parameters from the scenario's ``slam`` section."""
    return AgentParams(
        **slam_kwargs(AgentParams, cfg.graph, cfg.detections),
        matching=matching,
        marker_tables=marker_tables or {},
        graph=GraphParams(**slam_kwargs(GraphParams, cfg.graph)),
    )


def calibration(rig: StereoRig) -> StereoCalibration:
    return StereoCalibration.from_intrinsics(rig.intrinsics, rig.baseline_m, rig.width, rig.height)


def body_camera_transform(model: mujoco.MjModel, data: mujoco.MjData, robot: Robot, camera: str) -> np.ndarray:
    """T_body_cam of a camera (OpenCV axes) from the robot's kinematics: the pan-tilt
    head's joint encoders on the LRU, fixed mounts on ARDEA."""
    site = model.site(robot.imu_site).id
    cam = model.camera(camera).id
    R_wb = data.site_xmat[site].reshape(3, 3)
    R_wc = data.cam_xmat[cam].reshape(3, 3) @ MUJOCO_TO_OPENCV
    T = np.eye(4)
    T[:3, :3] = R_wb.T @ R_wc
    T[:3, 3] = R_wb.T @ (data.cam_xpos[cam] - data.site_xpos[site])
    return T


@dataclass
class EstimateLog:
    """The filter's online estimates, sampled on the ground-truth clock (rows: :class:`sim.run.series.Rows`)."""

    t: Rows = field(default_factory=Rows)
    pose_first_frame: Rows = field(default_factory=Rows)  # 4x4, switches chained
    frame_index: Rows = field(default_factory=lambda: Rows(dtype=np.int64))
    observable: Rows = field(default_factory=Rows)  # [roll, pitch, v_body] estimate
    observable_cov: Rows = field(default_factory=Rows)  # 5x5
    observable_true: Rows = field(default_factory=Rows)
    position_std: Rows = field(default_factory=Rows)  # (3,) in the current local frame
    bias: Rows = field(default_factory=Rows)  # [b_a, b_w] estimate
    bias_true: Rows = field(default_factory=Rows)


@dataclass
class SlamLog:
    """The graph's online estimates (thesis ch. 8: what the robot believed at each moment,
    never re-optimised afterwards), sampled on the ground-truth clock."""

    t: Rows = field(default_factory=Rows)
    pose: Rows = field(default_factory=Rows)  # 4x4 in the robot's map (first submap origin)
    beliefs: dict[str, Rows] = field(default_factory=dict)  # peer -> rows [t, t of the estimate, 16 entries of the pose in this map]


class OnboardStack:
    """Feeds a robot's sensors into its :class:`LocalEstimator` through its lane."""

    def __init__(
        self,
        scenario: Scenario,
        robot: Robot,
        lane: Lane,
        imu_spec: ImuSpec,
        gravity: float,
        markers: list[TeamMarker],
        streams: RandomStreams,
    ):
        cfg = scenario.slam
        self.robot = robot
        self.lane = lane
        self.slam_cfg = cfg
        self.use_odometry = cfg.wheel_odometry and robot.has_wheel_odometry
        self.odometry_noise = slam_kwargs(LocalEstimator.on_wheel_odometry, cfg)  # the std the filter assumes
        self.vo_rig = {rig.name: rig for rig in robot.stereo_rigs}[cfg.vo_rig or robot.default_vo_rig]  # checked by the scenario
        mapping = cfg.mapping
        self.estimator = LocalEstimator(
            filter_params(imu_spec, gravity, cfg, type(robot)),
            StereoVO(calibration(self.vo_rig), VoParams(**slam_kwargs(VoParams, cfg))),
            init_time=robot.cfg.route.start_delay_s,
            rest_window=cfg.initial_rest_s,
            frame_switch_distance=None if mapping.enabled else cfg.frame_switch_distance_m,
            rest_params=RestParams(**slam_kwargs(RestParams, cfg)),
            health_params=HealthParams(**slam_kwargs(HealthParams, cfg.health)),
        )
        self.mapper = local_mapper(robot.name, calibration(self.vo_rig), mapping) if mapping.enabled else None
        team = [r.name for r in scenario.robots]
        matching = matcher_params(cfg, calibration(self.vo_rig), streams.integer_seed("matcher", robot.name))
        tables = None
        if cfg.graph.enabled and cfg.detections.enabled and cfg.detections.uncertainty in ("lut", "lut_online"):
            tables = load_tables(robot.stereo_rigs, {m.size_m for m in markers})
        self.faults = measurement_faults(scenario, robot.name, streams)  # the scenario's wrong detections and matches
        self.agent = Agent(robot.name, team, markers, self.estimator, self.mapper, agent_params(cfg, matching, tables), self.faults)
        self.exchange = cfg.graph.enabled
        self.detect_markers = cfg.graph.enabled and cfg.detections.enabled
        self.network: Network | None = None
        self._graph_queued = False
        self._matching_queued = False
        self.partitions: list[tuple[float, str]] = []  # (t, reason) of each new submap
        self._depth: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (depth, left image) until its VO is applied
        self._switch_pending = False
        self.log = EstimateLog()
        self.slam_log = SlamLog()
        self.vo_scores = VoDeltaScores()  # the VO's deltas against the true camera poses the run captures
        self.on_vo_result = None  # optional callback(result), e.g. the recording
        self.on_mapped = None  # optional callback(frame_id, depth, classification), e.g. the evaluation
        # its map frame is the gravity-aligned frame of its pose at the filter's start, which it believes
        # to be the scenario's start (where it was deployed; height plays no part)
        self._deployments = {r.name: _deployment(r.start) for r in scenario.robots}  # the mission plan, known to all
        self._T_world_map = self._deployments[robot.name]
        self._map_odom: tuple[tuple[int, int], np.ndarray] | None = None
        self.explorer: Explorer | None = None
        self.goals: list[tuple[float, Goal]] = []  # every exploration answer, with its time

    # ------------------------------------------------------------------ the team

    def connect(self, network: Network) -> None:
        """Exchange messages with the team over ``network`` (with ``slam.graph.enabled``)."""
        if self.exchange:
            self.network = network
            network.on_receive(self.robot.name, self._deliver)

    def _send(self, messages: list[Outgoing]) -> None:
        if messages and self.network is not None:
            for m in messages:
                if m.to is None:
                    self.network.broadcast(self.robot.name, m.kind, m.payload, to=self.agent.peers)
                else:
                    self.network.send(self.robot.name, m.to, m.kind, m.payload)
        self._schedule_graph()
        self._schedule_matching()

    def _schedule_matching(self) -> None:
        """Submap matching (thesis 6.1) as one background job at a time: ``pairing`` when
        submaps arrived or the graph changed what pairing sees, else ``matching`` of the
        best queued pair (of those this robot owns)."""
        matcher = self.agent.matcher
        if matcher is None or self._matching_queued or not matcher.has_work:
            return
        self._matching_queued = True
        if matcher.pairing_due:
            self.lane.submit("pairing", work=self.agent.pair_submaps, on_done=self._matching_done, priority=Priority.BACKGROUND)
            return
        cand = matcher.next_candidate()
        started = []  # (pending attempt, job start time)

        def work():  # the pair is taken when the job starts; the matching itself runs beside the loop
            pending = matcher.start(cand)
            started.append((pending, self.lane.env.now))
            return self.lane.offload("matching", pending.run)

        def done(result, t_done: float) -> None:
            pending, t = started[0]
            self._matching_done(self.agent.match_done(matcher.finish(pending, result, t))[0], t_done)

        self.lane.submit("matching", work=work, on_done=done, priority=Priority.BACKGROUND, extra_stages=_icp_stage)

    def _matching_done(self, out, _t: float) -> None:
        self._matching_queued = False
        self._send(out if isinstance(out, list) else [])

    def _deliver(self, delivery: Delivery) -> None:
        payload = delivery.message.payload
        self.lane.submit("messages", work=lambda: self.agent.receive(payload), on_done=lambda out, t: self._send(out), priority=Priority.BACKGROUND)

    def _schedule_graph(self) -> None:
        """One background iSAM2 job at a time, whenever factors arrived."""
        if not self.exchange or self._graph_queued or not self.agent.dirty:
            return
        self._graph_queued = True
        self.lane.submit("graph", work=lambda: self.agent.optimize(self.lane.env.now), on_done=self._graph_done, priority=Priority.BACKGROUND)

    def _graph_done(self, _stats, _t: float) -> None:
        self._graph_queued = False
        self._schedule_graph()
        self._schedule_matching()  # the update may have placed a submap pairing could not

    @property
    def busy(self) -> bool:
        """Whether the robot has work left once its sensors are off: a job on its lane, or
        factors or submap matching no job has been queued for."""
        if self.lane.halted:  # a dead robot's computer
            return False
        matcher = self.agent.matcher
        return self.lane.busy() or self.agent.dirty or (matcher is not None and matcher.has_work)

    def finish_submap(self, now: float) -> None:
        """The end of the mission, once the lane's real-time jobs are done: finish the active
        submap (if it has images) as a ``filter_update`` job, so that it is sent and matched
        like every other."""
        if self.mapper is not None and self.mapper.builder.images:
            self.lane.submit("filter_update", work=lambda: self._end_submap(now), on_done=lambda out, t: self._send(out))

    def _end_submap(self, now: float) -> list[Outgoing]:
        """The end's partition, unless a partition queued before it has already finished the
        submap: with the sensors off the filter no longer propagates, so a second frame switch
        at the filter's time would repeat the first with a zero covariance."""
        est = self.estimator
        if not self.mapper.builder.images or (est.switches and est.switches[-1].t >= est.filter.t):
            return []
        return self._new_submap(now, "end")

    def detection(self, now: float, rig: StereoRig, T_body_cam: np.ndarray, search: Callable[[], Any] | None) -> None:
        """Marker detection in the left image of a pair of any of the robot's rigs (thesis
        6.2.1). ``search`` is the job's work, :meth:`find_markers` of the pair (on the image
        pipeline's worker when it has one, ``sim/run/pipeline.py``); what the robot makes of
        the markers found, with its state then, is done when the job ends. ``search`` None:
        no marker can show in the image (``Run._markers_in_view``, from the true poses) and
        the simulator skips the search, which would find none; the job and its modelled time stay."""
        if self.detecting:
            self.lane.submit(
                "detection",
                work=search or list,
                on_done=lambda found, t: self._send(self.agent.detections_from(now, found, rig.name, T_body_cam)),
            )

    @property
    def detecting(self) -> bool:
        """Whether the robot searches its images for markers now (:meth:`detection`)."""
        return self.detect_markers and self.estimator.initialised

    def find_markers(self, rig: StereoRig, pair: Future) -> list[MarkerDetection]:
        """The team's markers in the left image of ``pair`` (a future :class:`~sim.world.sensors.StereoFrame` of ``rig``)."""
        return self.agent.find_markers(rig.name, rig.intrinsics, pair.result().left)

    # ------------------------------------------------------------------ sensor events

    def imu(self, now: float, accel: np.ndarray, gyro: np.ndarray) -> None:
        moving = self.robot.commands_motion  # the controller's state at the sample, as the robot's computer knows it

        def work():
            self.estimator.on_motion_command(moving)
            return self.agent.on_imu(now, accel, gyro)

        self.lane.submit("strapdown", work=work, on_done=lambda out, t: self._send(out))

    def wheel_odometry(self, now: float, v_body: np.ndarray) -> None:
        if self.use_odometry:
            self.lane.submit("filter_update", work=lambda: self.estimator.on_wheel_odometry(now, v_body, **self.odometry_noise))

    def capture(self, frame_id: int, now: float, T_body_cam: np.ndarray) -> None:
        """Image trigger of the VO rig: the filter clones its state."""
        job = self.lane.submit("filter_update", work=lambda: self.estimator.on_capture(frame_id, now, T_body_cam))
        if job is None:
            self.estimator.abandon(frame_id)

    def depth_ready(self, frame_id: int, now: float, left: np.ndarray, right: np.ndarray, depth: np.ndarray | None) -> None:
        """Stereo matching of the VO rig finished: VO runs as its own job."""
        if frame_id not in self.estimator.pending:
            return  # captured before the filter started, or its clone job was dropped
        job = self.lane.submit(
            "vo",
            work=lambda: self.estimator.process_vo(frame_id, now, left, right, depth),
            on_done=lambda result, t_done: self._vo_done(result),
        )
        if job is None:
            self.lane.submit("filter_update", work=lambda: self.estimator.abandon(frame_id))
        elif self.mapper is not None:
            self._depth[frame_id] = (depth, left)

    def stereo_dropped(self, frame_id: int) -> None:
        self.lane.submit("filter_update", work=lambda: self.estimator.abandon(frame_id))

    def _vo_done(self, result: VoResult) -> None:
        self.vo_scores.score(result)
        if self.on_vo_result is not None:
            self.on_vo_result(result)
        self.lane.submit("filter_update", work=lambda: self._apply_vo(result))

    def _apply_vo(self, result: VoResult) -> None:
        est = self.estimator
        est.on_vo(result)
        images = self._depth.pop(result.frame_id, None)
        for stale in [k for k in self._depth if k < result.frame_id]:  # their VO result was lost with a dropped job
            del self._depth[stale]
        frame = est.last_frame
        if images is None or frame is None or frame.frame_id != result.frame_id:
            return
        floor = self.robot.min_mapping_height_m
        if floor is not None and (est.T_first_current @ est.in_frame(frame.T_local_body, frame.frame_index))[2, 3] < floor:
            return  # e.g. a hexacopter on the ground or taking off: its downward stereo sees the ground closer than it can match
        self.lane.submit("mapping", work=lambda: self._map(frame, *images), on_done=lambda out, t_done: self._mapped(frame, *out, t_done))

    def _map(self, frame: FramePose, depth: np.ndarray, left: np.ndarray) -> tuple[np.ndarray, Classification]:
        """Classify and integrate one depth image, less the VO's estimate of the rig's
        disparity offset (slam/stereo_offset.py), along the filter's pose of its frame,
        expressed in the current local frame (a switch may have happened since)."""
        est = self.estimator
        depth = remove_disparity_offset(depth, est.vo.calib, est.vo.disparity_offset)
        T_local_body = est.in_frame(frame.T_local_body, frame.frame_index)
        return depth, self.mapper.integrate(frame.t, depth, left, T_local_body, frame.T_body_cam, est.T_first_current)

    def _mapped(self, frame: FramePose, depth: np.ndarray, classification: Classification, now: float) -> None:
        """After a mapping job: the evaluation's look at the image (outside the job, whose wall
        time is the robot's compute under ``compute.model: measured``), then the partition check."""
        if self.on_mapped is not None:
            self.on_mapped(frame.frame_id, depth, classification)
        self._check_partition(now)

    def _check_partition(self, now: float) -> None:
        """Thesis 5.1.3's partition. None for the position std while the filter bridges a
        stuck IMU: the std then grows with the motion model between VO updates, and a frame
        switch would freeze the unaided attitude into the new frame (slam/local_estimator.py);
        the distance still partitions, so that an IMU stuck for good does not grow one submap
        without end."""
        est = self.estimator
        std = 0.0 if est.imu_bridged else est.position_std()
        reason = None if self._switch_pending else self.mapper.partition_due(std, est.distance_in_frame)
        if reason is None:
            return
        job = self.lane.submit("filter_update", work=lambda: self._new_submap(now, reason), on_done=lambda out, t: self._send(out))
        self._switch_pending = job is not None

    def _new_submap(self, now: float, reason: str) -> list[Outgoing]:
        """Thesis 5.1.3: a new submap, and with it a frame switch of the filter."""
        out = self.agent.new_submap(now)
        self.partitions.append((now, reason))
        self._switch_pending = False
        return out

    # ------------------------------------------------------------------ guidance (sim/robots/path_following.py)

    def guide(self) -> None:
        """Let the robot steer by this stack's estimate (``navigation.pose_source: estimate``)."""
        self.robot.own_estimate = self

    @property
    def obstacle_map(self):
        return self.mapper.rolling

    def odometry_pose(self) -> np.ndarray | None:
        """``T_odom_body``: the filter's latest estimate in its first local frame."""
        est = self.estimator
        return est.T_first_current @ est.filter.pose() if est.initialised else None

    def world_from_odometry(self) -> np.ndarray:
        """``T_world_odom``: the believed deployment pose composed with the graph's placement
        of the current local frame against the filter's (eq. 4.6); the deployment pose alone
        until the graph holds this robot, or without a graph. Recomputed on graph updates and
        frame switches only."""
        est = self.estimator
        if not (self.exchange and est.initialised):
            return self._T_world_map
        frame = est.filter.frame_index
        key = (frame, len(self.agent.stats.graph_updates))
        if self._map_odom is None or self._map_odom[0] != key:
            S = self.agent.pose_in_map(self.robot.name, frame, np.eye(4))
            T_map_odom = np.eye(4) if S is None else S @ se3_inv(est.T_first_current)
            self._map_odom = (key, self._T_world_map @ T_map_odom)
        return self._map_odom[1]

    # ------------------------------------------------------------------ exploration (slam/navigation/explorer.py)

    def explore(self, cfg: ExplorationConfig) -> None:
        """Let the robot explore ``cfg.region``: it asks this stack for goals (:meth:`next_goal`)."""
        self.explorer = Explorer(cfg.region, ExplorationParams(**slam_kwargs(ExplorationParams, cfg)))
        self._exploration = cfg
        self._goal_ready: Goal | None = None
        self._goal_queued = False
        self._scan_first = cfg.initial_scan
        self._finished = False
        self._known_goals: set[tuple[str, float]] = set()  # the peers' goals it knew when it chose its latest
        self._announced_t = -math.inf
        self.robot.goal_source = self
        self._gaze: tuple[float, np.ndarray | None] | None = None
        self.observations: list[tuple[float, str]] = []  # (t, peer) whenever the head turns to a peer
        if self.explorer.params.observe_peers and self.robot.pan_tilt_head:
            self.robot.gaze_source = self

    @property
    def finished(self) -> bool:
        return self._finished

    def next_goal(self, t: float) -> WaypointConfig | None:
        """The next goal once an ``exploration`` job has chosen it (one is queued if none is);
        the first, with ``initial_scan``, a scan where the robot stands."""
        cfg = self._exploration
        if self._scan_first:
            T = self._believed_pose()
            if T is None:
                return None
            self._scan_first = False
            return WaypointConfig(xy=(float(T[0, 3]), float(T[1, 3])), scan=True)
        goal, self._goal_ready = self._goal_ready, None
        if goal is not None:
            return WaypointConfig(xy=(float(goal.xy[0]), float(goal.xy[1])), scan=cfg.scan_at_goal)
        if not self._goal_queued and not self._finished:
            job = self.lane.submit("exploration", work=self._choose_goal, on_done=self._goal_chosen, priority=Priority.BACKGROUND)
            self._goal_queued = job is not None
        return None

    def yields(self, goal_xy) -> bool:
        """Whether the robot gives up its current goal for a peer's it did not know of when it
        chose its own, announced first (ties by name) and within ``goal_separation_m``: two
        robots that chose at the same moment would otherwise drive to the same place."""
        separation = self.explorer.params.goal_separation_m
        mine = (self._announced_t, self.robot.name)
        for g in self.agent.peer_goals.values():
            if g.finished or (g.robot, g.t) in self._known_goals or (g.t, g.robot) > mine:
                continue
            if math.hypot(g.xy[0] - goal_xy[0], g.xy[1] - goal_xy[1]) < separation:
                return True
        return False

    def look_at(self, t: float) -> np.ndarray | None:
        """The point to point the head at now (slam/navigation/observation.py; mission frame,
        as believed): the centre of the chosen peer's markers, or None; chosen again every
        ``GAZE_PERIOD_S``."""
        if self._gaze is not None and t < self._gaze[0] + GAZE_PERIOD_S:
            return self._gaze[1]
        T = self._believed_pose()
        found = None
        if T is not None:
            poses = {p: T_peer for p in self.agent.peers if (T_peer := self._peer_pose(p, t)) is not None}
            last = {p: self.agent.last_detection_t(p) for p in poses}
            params = self.explorer.params
            found = peer_to_observe(T[:2, 3], {p: T_peer[:2, 3] for p, T_peer in poses.items()}, last, t, params.observe_range_m,
                                    params.observe_interval_s)
        if found is not None and (self._gaze is None or self._gaze[1] is None):
            self.observations.append((t, found[0]))
        if found is None:
            self._gaze = (t, None)
        else:
            T_peer = poses[found[0]]
            self._gaze = (t, T_peer[:3, :3] @ self._marker_centre(found[0]) + T_peer[:3, 3])
        return self._gaze[1]

    def _marker_centre(self, peer: str) -> np.ndarray:
        """The mean position of ``peer``'s markers on its body (its body origin if it has none)."""
        centres = [m.T_body_marker[:3, 3] for m in self.agent.markers.values() if m.robot == peer]
        return np.mean(centres, axis=0) if centres else np.zeros(3)

    def _peer_pose(self, peer: str, t: float) -> np.ndarray | None:
        """Where this robot believes ``peer`` is (``T_world_body``, mission frame): its latest
        periodic estimate on this robot's graph, or, until the graph connects them, in the
        peer's odometry frame on its deployment; None without an estimate of the last
        ``PEER_ESTIMATE_MAX_AGE_S``."""
        belief = self.agent.belief(peer)
        if belief is not None:
            t_estimate, T = belief
            T_world = self._T_world_map @ T
        else:
            odometry = self.agent.peer_odometry_pose(peer)
            if odometry is None:
                return None
            t_estimate, T = odometry
            T_world = self._deployments[peer] @ T
        return T_world if t - t_estimate <= PEER_ESTIMATE_MAX_AGE_S else None

    def _believed_pose(self) -> np.ndarray | None:
        """``T_world_body`` as the robot believes (its online SLAM pose in the mission frame)."""
        T_odom_body = self.odometry_pose()
        return None if T_odom_body is None else self.world_from_odometry() @ T_odom_body

    def _choose_goal(self) -> tuple[Goal | None, list[Outgoing]]:
        T = self._believed_pose()
        if T is None:
            return None, []
        rolling = self.mapper.rolling
        explored, obstacles = self.explorer.grids(
            self.agent.placed_submaps(), self._T_world_map, (rolling.traversability, rolling.origin, rolling.resolution_m), self.world_from_odometry()
        )
        first = len(self.robot.cfg.route.waypoints)
        visited = [np.array(r.xy) for r in self.robot.route.records[first:]]
        self._known_goals = {(g.robot, g.t) for g in self.agent.peer_goals.values()}
        revisits = self._revisit_places() if self.explorer.params.loop_closing_weight > 0 else []
        revisited = [g.xy for _, g in self.goals if g.reason == "revisit"]
        goal = self.explorer.next_goal(explored, obstacles, T[:2, 3], self.agent.current_peer_goals(), visited, revisits, revisited)
        xy = T[:2, 3] if goal.xy is None else goal.xy
        self._announced_t = self.lane.env.now
        return goal, self.agent.announce_goal(self._announced_t, xy, finished=goal.finished)

    def _revisit_places(self) -> list[RevisitPlace]:
        """The matcher's suitable submaps as places to return to (:meth:`Agent.revisit_places`),
        in the mission frame; each one's covariance relative to the robot now adds the
        filter's position covariance in its current frame to the graph's relative one, widened
        by the matcher's ``sigma_scale`` as its pairing widens it (eq. 6.1-6.4), so that the
        explorer and the matcher judge a place's uncertainty alike."""
        if self.agent.matcher is None:
            return []
        est = self.estimator
        R_world_body = (self.world_from_odometry() @ est.T_first_current @ est.filter.pose())[:3, :3]
        filter_cov = R_world_body @ est.filter.pose_covariance()[3:, 3:] @ R_world_body.T
        R_world_map = self._T_world_map[:3, :3]
        scale = self.agent.matcher.params.sigma_scale
        out = []
        for S, cov in self.agent.revisit_places():
            xy = (self._T_world_map @ S)[:2, 3]
            out.append(RevisitPlace(xy, scale**2 * (R_world_map @ cov @ R_world_map.T + filter_cov)[:2, :2]))
        return out

    def _goal_chosen(self, result: tuple[Goal | None, list[Outgoing]], t: float) -> None:
        self._goal_queued = False
        goal, out = result
        if goal is not None:
            self.goals.append((t, goal))
            self._finished = goal.finished
            self._goal_ready = None if goal.finished else goal
        self._send(out)

    # ------------------------------------------------------------------ logging

    def record(self, recent_truth: Sequence[tuple[float, np.ndarray, np.ndarray, np.ndarray]]) -> None:
        """Log the current estimate next to the truth (truth never enters the estimator).
        ``recent_truth``: ``(t, R_world_body, v_world, bias_true)`` of the latest physics
        ticks, newest last. The filter runs behind the physics (its lane takes an IMU sample
        after the tick that measured it: one IMU period, more when the lane is busy), so
        its roll, pitch, velocity and biases are scored against the truth at the filter's
        own time; at the physics' time a jolt (a point turn's start lifts the body at 7 cm/s for a few
        milliseconds) made NEES spikes of 100 and more out of a 5 ms lag. For the same
        reason the poses are logged at the filter's time, not at the physics': ARDEA turning at
        36 deg/s behind by 15 ms at each image trigger showed a yaw error 0.5 deg larger
        there than between them. Nothing is logged while the filter lags more than
        ``recent_truth`` reaches back, nor twice at one filter time."""
        est = self.estimator
        if not est.initialised:
            return
        f = est.filter
        truth = next((s for s in reversed(recent_truth) if abs(s[0] - f.t) < TRUTH_MATCH_S), None)
        log = self.log
        if truth is None or (log.t and f.t <= log.t[-1]):
            return
        _, R_world_body, v_world, bias_true = truth
        t = f.t
        log.t.append(t)
        log.pose_first_frame.append(est.T_first_current @ f.pose())
        log.frame_index.append(f.frame_index)
        x, cov = f.observable_estimate()
        log.observable.append(x)
        log.observable_cov.append(cov)
        log.observable_true.append(np.concatenate([roll_pitch(R_world_body), R_world_body.T @ v_world]))
        log.position_std.append(np.sqrt(np.diag(f.covariance()[:3, :3])))
        log.bias.append(np.concatenate([f.accel_bias, f.gyro_bias]))
        log.bias_true.append(bias_true)
        if self.exchange:
            self._record_slam(t)

    def _record_slam(self, t: float) -> None:
        """The online SLAM pose (eq. 4.6) at the filter's time ``t``, and the beliefs about peers."""
        pose = self.agent.online_pose()
        if pose is None:
            return
        slog = self.slam_log
        slog.t.append(t)
        slog.pose.append(pose)
        for peer in self.agent.peers:
            belief = self.agent.belief(peer)
            if belief is not None:
                t_estimate, pose = belief
                slog.beliefs.setdefault(peer, Rows(64)).append(np.concatenate([[t, t_estimate], pose.ravel()]))
