"""The run loop: one SimPy environment drives physics, sensors, controllers and lanes.

The physics process is the master clock (docs/architecture.md, "One run"). Each control tick it lets
every robot's controller set its actuators, steps MuJoCo, and then samples the sensors
that are due on this tick (IMU, wheel odometry, stereo cameras, ground truth).
Sampling from the clock, not from separate SimPy processes, fixes the order of
events within a tick, which keeps runs deterministic. Sensor data becomes jobs in each
robot's lane (:mod:`sim.run.lanes`); the first real job is stereo matching
(:mod:`slam.stereo`), whose depth is scored against rendered ground truth.

When every route is done before ``duration_s``, the run drains (docs/matching.md, "The
end of a run"): physics and sensors stop, each robot finishes its active submap, and the
lanes and the network go on until no job and no message is left, or ``drain_s`` is up.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import mujoco
import numpy as np
import simpy
from scipy.spatial.transform import Rotation

from comms import Network, StereoStream, raw_stereo_load
from sim.evaluation.image_classification import ImageCells, MappedImage
from sim.robots import make_robot
from sim.robots.base import Robot
from sim.run.collisions import CollisionMonitor
from sim.run.dataset import DatasetWriter, EurocDataset
from sim.run.faults import ConditionFaults, condition_faults
from sim.run.lanes import ComputeModel, Device, Lane, Priority
from sim.run.memory import MemoryTrace
from sim.run.onboard import OnboardStack, body_camera_transform, calibration
from sim.run.pipeline import ImagePipeline
from sim.run.recording import Recorder
from sim.run.series import LogHistogram, Rows
from sim.scenario import Scenario, control_ticks
from sim.seeding import RandomStreams
from sim.world.calibration_errors import believed_body_camera, draw_calibration_errors, perturb_cameras
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from sim.world.compose import World, build_world
from sim.world.imaging import CameraImaging, imaging_params
from sim.world.markers import MARKER_MATERIAL_PREFIX
from sim.world.sensors import (
    IMU_PRESETS,
    ImuErrors,
    ImuModel,
    InertialAverager,
    RenderRequest,
    StereoFrame,
    StereoRenderer,
    WheelErrors,
    WheelOdometryModel,
    camera_motion_ahead,
    camera_velocity,
)
from sim.world.terrain import Terrain, generate_terrain
from slam.agent import TeamMarker
from slam.markers import DEFAULT_MIN_SIDE_PX
from slam.stereo import StereoMatcher

GROUND_TRUTH_RATE_HZ = 50.0
#: Simulated seconds of physics before t = 0 in which the robots, placed a little above
#: the ground, come to rest on it (a tilted ARDEA rocks on its legs for most of a second):
#: the run starts with every robot resting, as the filters' initialisation assumes.
SETTLE_S = 2.0
LANDER_ANTENNA_HEIGHT_M = 1.8  # above the lander base; a robot's is its class's ``antenna_height_m``
DEPTH_BINS_M = (0.0, 2.0, 4.0, 6.0, 10.0, math.inf)
DEPTH_SAMPLE_STRIDE = 2  # score every 2nd pixel in each direction
DRAIN_POLL_S = 0.1  # while draining: how often the run checks for work left
TRUTH_HISTORY_S = 0.5  # how far back the truth is kept to score a filter that lags the physics


def _labels() -> list[str]:
    return [f"{lo:g}-{hi:g}m" if math.isfinite(hi) else f">{lo:g}m" for lo, hi in itertools.pairwise(DEPTH_BINS_M)]


DEPTH_BIN_LABELS = _labels()


REL_ERROR_RANGE = (1e-5, 100.0)  # relative depth error histogram bounds
ABS_ERROR_RANGE_M = (1e-5, 1000.0)


class DepthErrorAccumulator:
    """Relative and absolute stereo depth error against rendered ground truth, per range bin, as
    :class:`sim.run.series.LogHistogram` counts: its memory stays the same however many images a run scores."""

    def __init__(self):
        self.relative = {label: LogHistogram(*REL_ERROR_RANGE) for label in DEPTH_BIN_LABELS}
        self.absolute = {label: LogHistogram(*ABS_ERROR_RANGE_M) for label in DEPTH_BIN_LABELS}
        self.truth_pixels: dict[str, int] = dict.fromkeys(DEPTH_BIN_LABELS, 0)
        self.frames = 0

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        est = estimate[::DEPTH_SAMPLE_STRIDE, ::DEPTH_SAMPLE_STRIDE]
        gt = truth[::DEPTH_SAMPLE_STRIDE, ::DEPTH_SAMPLE_STRIDE]
        seen = np.isfinite(gt) & (gt > 0)
        valid = seen & np.isfinite(est) & (est > 0)
        self.frames += 1
        for label, lo, hi in zip(DEPTH_BIN_LABELS, DEPTH_BINS_M, DEPTH_BINS_M[1:]):
            in_bin = (gt >= lo) & (gt < hi)
            self.truth_pixels[label] += int(np.count_nonzero(seen & in_bin))
            sel = valid & in_bin
            if np.any(sel):
                err = np.abs(est[sel] - gt[sel])
                self.absolute[label].add(err)
                self.relative[label].add(err / gt[sel])

    def summary(self, labels: tuple[str, ...]) -> dict:
        """Error statistics over the union of the range bins ``labels``."""
        rel = LogHistogram.merged([self.relative[label] for label in labels])
        truth = sum(self.truth_pixels[label] for label in labels)
        return {
            "range": f"{labels[0].split('-')[0]}-{labels[-1].split('-')[1]}",
            "frames": self.frames,
            "median_rel_error": rel.quantile(0.5),
            "p95_rel_error": rel.quantile(0.95),
            "valid_share": float(rel.n / truth) if truth else 0.0,
        }

    def rows(self, robot: str, rig: str) -> list[dict]:
        out = []
        for label in DEPTH_BIN_LABELS:
            rel, ab = self.relative[label], self.absolute[label]
            truth = self.truth_pixels[label]
            out.append(
                {
                    "robot": robot,
                    "rig": rig,
                    "range": label,
                    "frames": self.frames,
                    "pixels_scored": rel.n,
                    "valid_share": float(rel.n / truth) if truth else 0.0,
                    "median_rel_error": rel.quantile(0.5),
                    "p95_rel_error": rel.quantile(0.95),
                    "median_abs_error_m": ab.quantile(0.5),
                    "p95_abs_error_m": ab.quantile(0.95),
                }
            )
        return out


@dataclass
class RobotLog:
    """What one robot's run produced, in simulated time (rows: :class:`sim.run.series.Rows`)."""

    gt_t: Rows = field(default_factory=Rows)
    gt_pose: Rows = field(default_factory=Rows)  # (7,) x y z qw qx qy qz, world frame
    imu_t: Rows = field(default_factory=Rows)
    imu: Rows = field(default_factory=Rows)  # (6,) accel, gyro (measured)
    imu_true: Rows = field(default_factory=Rows)  # (6,) specific force, angular rate (truth)
    imu_bias: Rows = field(default_factory=Rows)  # (6,) true accel and gyro biases
    odom_t: Rows = field(default_factory=Rows)
    odom: Rows = field(default_factory=Rows)  # (3,) v_x, v_y, yaw rate (measured)
    guidance_t: Rows = field(default_factory=Rows)
    guidance_xy: Rows = field(default_factory=Rows)  # (2,) where the robot believed it was (navigation.pose_source: estimate)
    frames: int = 0
    depth_error: dict[str, DepthErrorAccumulator] = field(default_factory=lambda: defaultdict(DepthErrorAccumulator))
    exposure: dict[str, list[tuple[float, float, float]]] = field(default_factory=lambda: defaultdict(list))  # per rig: s, gain, saturated share


@dataclass
class RobotRuntime:
    robot: Robot
    lane: Lane
    imu: ImuModel
    inertial: InertialAverager
    imu_every: int
    camera_every: int
    camera_phase: int  # control ticks from a period's start to the cameras' trigger (Run._camera_phase)
    renderers: list[StereoRenderer]
    workers: list[int]  # the image pipeline's worker of each renderer (sim/run/pipeline.py)
    imaging: list[CameraImaging | None]  # per rig: image formation, None for ideal images
    matchers: list[StereoMatcher]
    odometry: WheelOdometryModel | None
    odom_every: int
    onboard: OnboardStack | None
    log: RobotLog = field(default_factory=RobotLog)
    faults: ConditionFaults | None = None  # the scenario's condition faults that hit the robot (sim/run/faults.py)
    image_cells: ImageCells | None = None  # mapped images' obstacle cells at true camera poses
    capture_truth: dict[int, tuple] = field(default_factory=dict)  # VO frame -> true T_world_cam, other robots, the pair (its true depth or None)
    recent_truth: deque = field(default_factory=deque)  # (t, R, v, biases) at the latest IMU samples, for OnboardStack.record
    dataset: DatasetWriter | None = None  # output.dataset: the robot's sensor data as it comes (sim/run/dataset.py)
    unscored_depths: deque = field(default_factory=deque)  # (rig, pair, depth) of finished stereo jobs not scored yet (Run._score_depths)


#: Image pipeline threads (sim/run/pipeline.py), unless the environment's ``MARSYARD_IMAGE_WORKERS``
#: says otherwise (0: inline). One: on two cores a second drew no faster (llvmpipe already
#: rasterises each image on both).
IMAGE_WORKERS = int(os.environ.get("MARSYARD_IMAGE_WORKERS", "1"))


def background_thread() -> bool:
    """Whether threaded runs give submap matching and image scoring a thread of their own
    (sim/run/pipeline.py): only with ``MARSYARD_BACKGROUND_THREAD=1``. On two cores it made
    Etna faster in one of three before/after pairs and slower in two (README, "Measured")."""
    return os.environ.get("MARSYARD_BACKGROUND_THREAD", "0") == "1"


class Timers:
    """Wall-clock seconds spent per part of the run (several image workers may add at once)."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self._lock = threading.Lock()

    def add(self, part: str, since: float) -> float:
        now = time.perf_counter()
        with self._lock:
            self.seconds[part] += now - since
        return now


ProgressCallback = Callable[[float, dict[str, str]], None]


class Run:
    """One scenario run. ``execute()`` runs it; afterwards the attributes hold everything
    :mod:`sim.evaluation.results_folder` writes. A failure mid-run leaves what was produced so far in place.
    With a ``dataset`` the run writes every robot's sensor data into it and closes it when it ends.
    An ``image_observer`` receives every mapped image with its truth (``MappedImage``; the
    true depth where the frame rendered it, ``camera.depth_ground_truth_every``)."""

    def __init__(
        self,
        scenario: Scenario,
        recorder: Recorder | None = None,
        dataset: EurocDataset | None = None,
        image_observer: Callable[[MappedImage], None] | None = None,
        image_workers: int | None = None,
    ):
        self.scenario = scenario
        self.image_observer = image_observer
        self.streams = RandomStreams(scenario.seed)
        self.timers = Timers()
        if image_workers is None:  # measured compute times are the jobs' own wall times: inline
            image_workers = 0 if scenario.compute.model == "measured" else IMAGE_WORKERS
        self.images = ImagePipeline(image_workers, Timers() if image_workers else self.timers, background_thread())
        self._renderers = 0  # renderers made so far: each draws on worker (its index modulo the workers)
        self.memory = MemoryTrace()
        self.recorder = recorder
        self.dataset = dataset
        self.env = simpy.Environment()
        self.sim_time = 0.0
        self.mission_s: float | None = None  # when the sensors stopped: every route done, duration_s, or a failure
        self.drain_end: str | None = None  # why the drain ended: "idle", "drain_s" or "duration_s"; None: no drain
        self.wall_s = 0.0
        t0 = time.perf_counter()
        tags = scenario.assigned_tag_ids()
        self.terrain: Terrain = generate_terrain(
            scenario.terrain, self.streams.rng("terrain"), scenario.keep_clear(), scenario.realism.light.albedo_contrast_scale
        )
        robots = [make_robot(cfg, tags[cfg.name]) for cfg in scenario.robots]
        self.world: World = build_world(scenario, self.terrain, robots)
        self.collisions = CollisionMonitor(self.world.model, robots)
        self.calibration_errors = {
            r.name: draw_calibration_errors(r, scenario.realism.calibration, self.streams.rng("calibration", r.name)) for r in robots
        }
        for robot in robots:  # the true cameras; the SLAM stack keeps believing in the nominal ones
            perturb_cameras(self.world.model, robot, self.calibration_errors[robot.name])
        self.tick_s = 1.0 / scenario.physics.control_rate_hz
        self.substeps = round(self.tick_s / scenario.physics.timestep_s)
        self._settle(robots)
        t0 = self.timers.add("setup", t0)
        self.team_markers = self._team_markers(robots)
        self.robots = {r.name: self._runtime(r, k, len(robots)) for k, r in enumerate(robots)}
        self._root_body = {r.name: self._robot_root_body(r) for r in robots}
        model = self.world.model
        materials = [model.material(k).name.rsplit("/", 1)[-1] for k in range(model.nmat)]  # robots' assets are prefixed
        self._marker_geoms = np.array(
            [g for g in range(model.ngeom) if model.geom_matid[g] >= 0 and materials[model.geom_matid[g]].startswith(MARKER_MATERIAL_PREFIX)],
            dtype=int,
        )
        self._marker_roots = model.body_rootid[model.geom_bodyid[self._marker_geoms]]  # the body (robot, lander) each marker is on
        self.network = Network(
            self.env,
            scenario.comms,
            scenario.network_nodes(),
            self.streams.rng("comms"),
            positions=self.antenna_positions,
            line_of_sight=self.line_of_sight,
        )
        for runtime in self.robots.values():
            if runtime.onboard is not None:
                runtime.onboard.connect(self.network)
        for runtime in self.robots.values():
            if runtime.faults is not None:
                self._schedule_faults(runtime, runtime.faults)
        if self.recorder is not None:
            self.recorder.log_world(self.terrain, self.world)
            self.network.subscribe(self.recorder.log_link_event)
        self.timers.add("setup", t0)

    def _team_markers(self, robots: list[Robot]) -> list[TeamMarker]:
        """The markers every robot knows by calibration (thesis 4.2.2): each robot's mast or
        body tags in its body frame, and the lander's tag as landmark ``tag_id``."""
        markers = []
        for robot in robots:
            for spec in robot.markers:
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat(spec.quat, scalar_first=True).as_matrix()
                T[:3, 3] = spec.pos
                markers.append(TeamMarker(spec.tag_id, spec.size_m, robot=robot.name, T_body_marker=T))
        lander = self.terrain.lander
        if lander is not None:  # the landmark frame is the tag's; its up is the lander's z
            up = Rotation.from_quat(lander.marker.quat, scalar_first=True).as_matrix().T[:, 2]
            markers.append(TeamMarker(lander.marker.tag_id, lander.marker.size_m, landmark=lander.marker.tag_id, up=up))
        return markers

    def _settle(self, robots: list[Robot]) -> None:
        """Let the robots come to rest (motors stopped) for :data:`SETTLE_S`, then restart the clock at 0."""
        model, data = self.world.model, self.world.data
        for _ in range(round(SETTLE_S / self.tick_s)):
            for robot in robots:
                robot.control(-SETTLE_S, self.terrain)
            mujoco.mj_step(model, data, nstep=self.substeps)
        data.time = 0.0
        mujoco.mj_forward(model, data)

    def _next_worker(self) -> int:
        """Image workers in turn, one per renderer."""
        self._renderers += 1
        return (self._renderers - 1) % max(1, self.images.workers)

    def _every(self, rate_hz: float) -> int:
        """Control ticks per sample (the scenario checks that the rate divides the control rate)."""
        ticks = control_ticks(self.scenario.physics.control_rate_hz, rate_hz)
        assert ticks is not None, rate_hz
        return ticks

    def _camera_phase(self, robot: Robot, index: int, team: int) -> int:
        """Control ticks into each frame period at which ``robot``'s cameras trigger: its
        ``camera.trigger_phase`` of the period, by default ``index / team`` (the cameras of
        separate robots are not synchronised; staggered, the image pipeline draws one robot's
        pair while another's waits for its trigger instead of all at once), on an IMU sample."""
        cfg = robot.cfg
        every, imu_every = self._every(cfg.camera.rate_hz), self._every(cfg.imu.rate_hz)
        phase = cfg.camera.trigger_phase if cfg.camera.trigger_phase is not None else index / team
        ticks = int(phase * every)
        return ticks - ticks % imu_every

    def _runtime(self, robot: Robot, index: int, team: int) -> RobotRuntime:
        cfg = robot.cfg
        cores = cfg.computer.cores or robot.default_cores
        lane = Lane(
            self.env,
            robot.name,
            cores,
            cfg.computer.fpga,
            ComputeModel(self.scenario.compute),
            self.scenario.compute.max_queue,
            self.images.result,
            self.images.background,
        )
        realism = self.scenario.realism
        preset = cfg.imu.preset or robot.default_imu_preset
        imu_errors = ImuErrors.draw(realism.imu, self.streams.rng("imu_errors", robot.name))
        imu = ImuModel(IMU_PRESETS[preset], cfg.imu.rate_hz, self.streams.rng("imu", robot.name), errors=imu_errors)
        odometry = None
        if robot.has_wheel_odometry:
            wheel_errors = WheelErrors.draw(realism.wheels, self.streams.rng("wheel_errors", robot.name))
            odometry = WheelOdometryModel(cfg.wheel_odometry, self.streams.rng("wheel_odometry", robot.name), wheel_errors)
        calib = self.calibration_errors[robot.name]
        renderers = [StereoRenderer(self.world.model, rig, cfg.camera, calib.rigs[rig.name], calib.time_offset_s) for rig in robot.stereo_rigs]
        imaging = []
        for rig in robot.stereo_rigs:
            params = imaging_params(realism.camera, self.streams.rng("imaging", robot.name, rig.name))
            rng = self.streams.rng("image_noise", robot.name, rig.name)
            flat_field = cfg.camera.flat_field
            imaging.append(None if params is None else CameraImaging(params, rig.width, rig.height, rig.focal_px, rng, flat_field=flat_field))
        matchers = [StereoMatcher(calibration(rig)) for rig in robot.stereo_rigs]
        onboard = None
        if self.scenario.slam.enabled:
            gravity = float(-self.world.model.opt.gravity[2])
            onboard = OnboardStack(self.scenario, robot, lane, IMU_PRESETS[preset], gravity, self.team_markers, self.streams)
            if cfg.navigation.pose_source == "estimate":
                onboard.guide()
            exploration = self.scenario.exploration
            if exploration is not None and robot.name in exploration.explorers(self.scenario.robots):
                onboard.explore(exploration)
            if self.recorder is not None:
                every = self.scenario.output.recording_image_every
                onboard.on_vo_result = lambda result, r=robot, o=onboard, n=every: (
                    self.recorder.log_vo(r.name, o.vo_rig, result) if result.frame_id % n == 0 else None
                )
        runtime = RobotRuntime(
            robot=robot,
            lane=lane,
            imu=imu,
            inertial=InertialAverager(self.world.model, robot.accel_sensor, robot.gyro_sensor),
            imu_every=self._every(cfg.imu.rate_hz),
            camera_every=self._every(cfg.camera.rate_hz),
            camera_phase=self._camera_phase(robot, index, team),
            renderers=renderers,
            workers=[self._next_worker() for _ in renderers],
            imaging=imaging,
            matchers=matchers,
            odometry=odometry,
            odom_every=self._every(cfg.wheel_odometry.rate_hz),
            onboard=onboard,
            faults=condition_faults(self.scenario, robot.name),
            recent_truth=deque(maxlen=max(2, round(TRUTH_HISTORY_S * cfg.imu.rate_hz))),
        )
        if onboard is not None and onboard.mapper is not None:
            runtime.image_cells = ImageCells(calibration(onboard.vo_rig), onboard.mapper.obstacle_params)
            onboard.on_mapped = lambda frame_id, depth, c, r=runtime: self._score_image(r, frame_id, depth, c.pixel_obstacles, c.pixel_classified)
        if self.dataset is not None:  # the cameras' believed transforms at t = 0 (the robots have settled)
            T_body_cam = {rig.name: self._believed_body_camera(robot, rig) for rig in robot.stereo_rigs}
            vo_rig = self.scenario.slam.vo_rig or robot.default_vo_rig
            runtime.dataset = self.dataset.robot(robot, vo_rig, IMU_PRESETS[preset], T_body_cam)
        return runtime

    def _believed_body_camera(self, robot: Robot, rig: StereoRig) -> np.ndarray:
        """``T_body_cam`` of ``rig``'s left camera as the robot computes it now (nominal calibration, head encoders)."""
        T_true = body_camera_transform(self.world.model, self.world.data, robot, rig.left_camera)
        return believed_body_camera(T_true, rig, self.calibration_errors[robot.name])

    # ------------------------------------------------------------------ injected faults

    def _schedule_faults(self, runtime: RobotRuntime, faults: ConditionFaults) -> None:
        """The condition faults that act at their start and end (sim/run/faults.py); the others act where the
        failing part works (:meth:`_sample`, :meth:`_capture`)."""
        for _, entry in faults.entries:
            if entry.type == "dies":
                self.env.process(self._die(runtime, faults, entry.start_s))
            elif entry.type == "radio_silent":
                self.network.radio_fault(runtime.robot.name, entry.start_s, entry.end_s)
            elif entry.type == "compute_slowdown":
                self.env.process(self._slow_down(runtime.lane, entry.start_s, entry.end_s, entry.factor))

    def _die(self, runtime: RobotRuntime, faults: ConditionFaults, at_s: float):
        yield self.env.timeout(max(0.0, at_s - self.env.now))
        if runtime.robot.dead:  # a second ``dies`` entry
            return
        faults.died_s = self.env.now
        runtime.robot.fail(self.env.now)
        runtime.lane.halt()
        self.network.radio_fault(runtime.robot.name, self.env.now)

    def _slow_down(self, lane: Lane, start_s: float, end_s: float | None, factor: float):
        yield self.env.timeout(max(0.0, start_s - self.env.now))
        lane.slowdown *= factor
        if end_s is not None:
            yield self.env.timeout(max(0.0, end_s - self.env.now))
            lane.slowdown /= factor

    # ------------------------------------------------------------------ network geometry

    def _robot_root_body(self, robot: Robot) -> int:
        body = int(self.world.model.site(robot.imu_site).bodyid[0])
        return int(self.world.model.body_rootid[body])

    def antenna_positions(self) -> dict[str, np.ndarray]:
        """World positions of the nodes' antennas: above each robot's body origin, on the lander's deck."""
        out = {}
        for name, runtime in self.robots.items():
            pos, _ = runtime.robot.pose()
            out[name] = pos + np.array([0.0, 0.0, runtime.robot.antenna_height_m])
        lander = self.terrain.lander
        if lander is not None:
            out["lander"] = np.array([*lander.xy, lander.base_z + LANDER_ANTENNA_HEIGHT_M])
        return out

    def line_of_sight(self, a: str, b: str) -> bool:
        """True if no terrain, rock, lander or third robot cuts the line between the antennas (``mj_ray``)."""
        model, data = self.world.model, self.world.data
        pos = self.antenna_positions()
        pa, pb = pos[a], pos[b]
        geom = np.zeros(1, dtype=np.int32)
        exclude = self._root_body.get(a, -1)
        fraction = mujoco.mj_ray(model, data, pa, pb - pa, None, 1, exclude, geom)
        if not 0 <= fraction < 1:
            return True
        hit_root = int(model.body_rootid[model.geom_bodyid[geom[0]]])
        return b in self._root_body and hit_root == self._root_body[b]

    def raw_equivalent_load(self) -> float:
        """Bytes/s the team would need to stream its raw stereo images (thesis 8.4)."""
        streams = []
        for runtime in self.robots.values():
            cam = runtime.robot.cfg.camera
            streams.append(
                StereoStream(
                    width=cam.width,
                    height=cam.height,
                    rate_hz=cam.rate_hz,
                    channels=3 if cam.color == "rgb" else 1,
                    pairs=len(runtime.robot.stereo_rigs),
                )
            )
        return raw_stereo_load(streams)

    # ------------------------------------------------------------------ the loop

    def execute(self, progress: ProgressCallback | None = None, progress_every_s: float = 0.5) -> None:
        start = time.perf_counter()
        process = self.env.process(self._physics(progress, progress_every_s))
        try:
            self.env.run(until=process)
        finally:
            self.sim_time = self.env.now
            self.memory.poll(self.sim_time, force=True)
            if self.mission_s is None:  # the run failed before its routes ended
                self.mission_s = self.sim_time
            try:
                self.close()
            finally:
                self.wall_s = time.perf_counter() - start + self.timers.seconds["setup"]
                self.timers.seconds["waiting"] += self.images.waited_s  # the loop blocked on the image pipeline

    def drain(self, seconds: float) -> None:
        """After :meth:`execute`: let the network deliver what is in flight and the lanes
        process it for ``seconds`` more, with physics and sensors stopped (no new
        measurements). For checks that need a quiet network, e.g. that all robots end
        with the same graph."""
        self.env.run(until=self.env.now + seconds)
        self.sim_time = self.env.now
        for runtime in self.robots.values():
            self._score_depths(runtime, all_of_them=True)

    def close(self) -> None:
        """Finish the image pipeline, release the renderers' GL contexts (in the thread that
        drew) and close the dataset's files (``execute`` does this when it ends)."""
        renderers = [(worker, renderer) for runtime in self.robots.values() for worker, renderer in zip(runtime.workers, runtime.renderers)]
        workers = max(1, self.images.workers)

        def close_drawn_here(k: int) -> None:
            for worker, renderer in renderers:
                if worker % workers == k and renderer.drawing_thread in (None, threading.get_ident()):
                    renderer.close()

        try:
            self.images.close(last=close_drawn_here)
            for _, renderer in renderers:  # those a tool drew with on this thread (sim/tools/render_bench.py)
                renderer.close()
            for runtime in self.robots.values():
                self._score_depths(runtime, all_of_them=True)
        finally:
            if self.dataset is not None:
                self.dataset.close()

    def _physics(self, progress: ProgressCallback | None, progress_every_s: float):
        model, data = self.world.model, self.world.data
        duration = self.scenario.duration_s
        gt_every = max(1, round(self.scenario.physics.control_rate_hz / GROUND_TRUTH_RATE_HZ))
        progress_every = max(1, round(progress_every_s / self.tick_s))
        tick = 0
        self._sample(tick, gt_every)
        while tick * self.tick_s < duration - 1e-9:
            t = time.perf_counter()
            for runtime in self.robots.values():
                runtime.robot.control(self.env.now, self.terrain)
            t = self.timers.add("control", t)
            for _ in range(self.substeps):
                mujoco.mj_step(model, data)
                for runtime in self.robots.values():
                    runtime.inertial.accumulate(data)
            self.timers.add("physics", t)
            tick += 1
            yield self.env.timeout(self.tick_s)
            self._sample(tick, gt_every)
            self.memory.poll(self.env.now)
            if progress is not None and tick % progress_every == 0:
                progress(self.env.now, self.statuses())
            if all(r.robot.finished for r in self.robots.values()):
                break
        self.mission_s = self.env.now
        if progress is not None:
            progress(self.env.now, self.statuses())
        if self.env.now < duration - 1e-9 and self.scenario.drain_s > 0:
            yield from self._drain(min(duration, self.env.now + self.scenario.drain_s), progress, progress_every_s)

    def _drain(self, until: float, progress: ProgressCallback | None, progress_every_s: float):
        """Every route is done: the robots rest, sensors off. Each robot finishes its active
        submap once its lane has no real-time job left (the last images are mapped);
        the lanes and the network run on until no robot has work and no message is in
        flight, or until ``until``."""
        onboard = [r.onboard for r in self.robots.values() if r.onboard is not None]
        unfinished = list(onboard)
        next_progress = self.env.now + progress_every_s
        while True:
            for stack in [s for s in unfinished if not s.lane.busy(Priority.REALTIME)]:
                stack.finish_submap(self.env.now)
                unfinished.remove(stack)
            if not unfinished and not any(s.busy for s in onboard) and self.messages_in_flight() == 0:
                self.drain_end = "idle"
                break
            if self.env.now >= until - 1e-9:
                self.drain_end = "duration_s" if until >= self.scenario.duration_s - 1e-9 else "drain_s"
                break
            yield self.env.timeout(min(DRAIN_POLL_S, until - self.env.now))
            self.memory.poll(self.env.now)
            if progress is not None and self.env.now >= next_progress - 1e-9:
                next_progress += progress_every_s
                progress(self.env.now, self.statuses())
        if progress is not None:
            progress(self.env.now, self.statuses())

    def messages_in_flight(self) -> int:
        """Messages sent and neither delivered nor dropped yet, except those from or to a dead robot (they
        wait for a radio that never comes back)."""
        dead = {name for name, r in self.robots.items() if r.robot.dead}
        return sum(
            f.offered_msgs - f.delivered_msgs - sum(m for m, _ in f.dropped.values())
            for (src, dst, _), f in self.network.accounting.flows.items()
            if src not in dead and dst not in dead
        )

    def statuses(self) -> dict[str, str]:
        return {name: r.robot.status for name, r in self.robots.items()}

    def _sample(self, tick: int, gt_every: int) -> None:
        now = self.env.now
        data = self.world.data
        if tick % gt_every == 0:
            self.collisions.sample(now, data)
        for runtime in self.robots.values():
            robot, log, onboard = runtime.robot, runtime.log, runtime.onboard
            t = time.perf_counter()
            if onboard is not None and tick % runtime.imu_every == 0:
                bias_true = np.concatenate([runtime.imu.accel_bias, runtime.imu.gyro_bias])
                runtime.recent_truth.append((now, robot.rotation(), robot.velocity()[0], bias_true))
            if tick % gt_every == 0:
                pos, quat = robot.pose()
                log.gt_t.append(now)
                log.gt_pose.append(np.concatenate([pos, quat]))
                belief = robot.guidance_pose() if robot.own_estimate is not None else None
                if belief is not None:
                    log.guidance_t.append(now)
                    log.guidance_xy.append(belief[:2, 3])
                if self.recorder is not None:
                    self.recorder.log_pose(robot.name, now, pos, quat)
                if onboard is not None and not robot.dead:
                    onboard.record(runtime.recent_truth)
                if runtime.dataset is not None:
                    runtime.dataset.truth(now, pos, quat, robot.velocity()[0], runtime.imu.gyro_bias, runtime.imu.accel_bias)
            t = self.timers.add("evaluation", t)  # the truth and the estimate logged beside it
            if robot.dead:  # its sensors and computer are off; the truth goes on
                runtime.inertial.take(data)
                continue
            if tick % runtime.imu_every == 0:
                specific_force, rate = runtime.inertial.take(data)
                accel, gyro = runtime.imu.measure(specific_force, rate)
                if runtime.faults is not None:
                    accel, gyro = runtime.faults.imu(now, accel, gyro)
                log.imu_t.append(now)
                log.imu.append(np.concatenate([accel, gyro]))
                log.imu_true.append(np.concatenate([specific_force, rate]))
                log.imu_bias.append(np.concatenate([runtime.imu.accel_bias, runtime.imu.gyro_bias]))
                if onboard is not None:
                    onboard.imu(now, accel, gyro)
                if runtime.dataset is not None:
                    runtime.dataset.imu(now, accel, gyro)
            if runtime.odometry is not None and tick % runtime.odom_every == 0:
                wheels = robot.wheel_states()
                if runtime.faults is not None:
                    wheels = runtime.faults.wheels(now, robot.wheel_names, wheels)
                odom = runtime.odometry.measure(wheels, robot.rotation()[2, 0])
                log.odom_t.append(now)
                log.odom.append(odom)
                if onboard is not None:
                    onboard.wheel_odometry(now, odom)
                if runtime.dataset is not None:
                    runtime.dataset.odometry(now, odom)
            t = self.timers.add("sensors", t)
            frame, at = divmod(tick - runtime.camera_phase, runtime.camera_every)
            if at == 0 and frame >= 0:
                self._capture(runtime, frame, now)

    def _capture(self, runtime: RobotRuntime, frame: int, now: float) -> None:
        """A stereo trigger: each rig's scene is snapshot now; drawing, exposure, marker search
        and SGBM follow on the image pipeline (``sim/run/pipeline.py``; the VO rig's first, the
        loop waits for its depth soonest), the jobs that use them are submitted now, rig by rig."""
        camera = runtime.robot.cfg.camera
        every = camera.depth_ground_truth_every
        with_depth = every > 0 and frame % every == 0
        runtime.log.frames += 1
        images, onboard = self.images, runtime.onboard
        cameras = list(zip(runtime.workers, runtime.renderers, runtime.imaging, runtime.matchers, runtime.robot.stereo_rigs))
        requests = []
        for _, renderer, imaging, _, rig in cameras:
            t = time.perf_counter()
            request = renderer.snapshot(self.world.data, with_depth=with_depth)
            dark = runtime.faults is not None and runtime.faults.dark(rig.name, now)
            rate = self._camera_rate(rig.left_camera) if imaging is not None and imaging.params.motion_blur else None
            requests.append((request, dark, rate))
            self.timers.add("snapshot", t)
        pairs, depths, searches = {}, {}, {}
        for k in sorted(range(len(cameras)), key=lambda k: onboard is None or cameras[k][4] is not onboard.vo_rig):
            worker, renderer, imaging, matcher, rig = cameras[k]
            pairs[k] = images.start(worker, self._develop, runtime, renderer, imaging, rig, *requests[k])
            depths[k] = images.job(worker, self._stereo, matcher, pairs[k])
            if onboard is not None and onboard.detecting and self._markers_in_view(runtime.robot, rig):
                searches[k] = images.job(worker, onboard.find_markers, rig, pairs[k])
        for k, (_, _, _, _, rig) in enumerate(cameras):
            pair = pairs[k]
            if self.recorder is not None and frame % self.scenario.output.recording_image_every == 0:
                stereo = images.result(pair)
                t = time.perf_counter()
                self.recorder.log_frame(runtime.robot.name, rig, now, stereo)
                self.timers.add("recording", t)
            for_vo = onboard is not None and rig is onboard.vo_rig
            if onboard is not None or runtime.dataset is not None:
                T_body_cam = self._believed_body_camera(runtime.robot, rig)
            if runtime.dataset is not None:
                stereo = images.result(pair)
                t = time.perf_counter()
                runtime.dataset.stereo(rig.name, now, stereo.left, stereo.right, T_body_cam)
                self.timers.add("dataset", t)
            if onboard is not None:
                if for_vo:
                    onboard.capture(frame, now, T_body_cam)
                    T_world_cam = self._camera_pose(rig.left_camera, self.calibration_errors[runtime.robot.name].time_offset_s)
                    onboard.vo_scores.capture(frame, T_world_cam)
                    if runtime.image_cells is not None:
                        runtime.capture_truth[frame] = (T_world_cam, self._others(runtime.robot), pair)
                onboard.detection(now, rig, T_body_cam, searches.get(k))
            if for_vo:
                on_done = lambda depth, t_done, r=runtime, p=pair, g=rig, f=frame, t0=now: self._stereo_done(r, g, images.result(p), depth, f, t0)  # noqa: E731
            else:  # the depth is only scored: whenever the worker has it (Run._score_depths)
                on_done = lambda depth, t_done, r=runtime, p=pair, g=rig: r.unscored_depths.append((g.name, p, depth))  # noqa: E731
            job = runtime.lane.submit("stereo", work=depths[k], on_done=on_done, device=Device.FPGA, wait=for_vo)
            if job is None and for_vo:
                onboard.stereo_dropped(frame)
        self._score_depths(runtime)

    def _develop(self, runtime: RobotRuntime, renderer: StereoRenderer, imaging: CameraImaging | None, rig: StereoRig,
                 request: RenderRequest, dark: bool, rate: np.ndarray | None) -> StereoFrame:
        """Draw a captured pair and form its images (image pipeline: in capture order)."""
        timers = self.images.timers
        t = time.perf_counter()
        stereo = renderer.draw(request)
        t = timers.add("rendering", t)
        if dark:
            stereo.left, stereo.right = np.zeros_like(stereo.left), np.zeros_like(stereo.right)
        if imaging is not None:
            exposure_s, gain = imaging.exposure_s, imaging.gain
            stereo.left, stereo.right = imaging.expose(stereo.left, stereo.right, rate)
            runtime.log.exposure[rig.name].append((exposure_s, gain, imaging.saturated_share))
            timers.add("imaging", t)
        return stereo

    def _stereo(self, matcher: StereoMatcher, pair: Future) -> np.ndarray:
        """SGBM depth of a pair (image pipeline)."""
        stereo = pair.result()
        t = time.perf_counter()
        depth = matcher.depth(stereo.left, stereo.right)
        self.images.timers.add("stereo", t)
        return depth

    def _camera_rate(self, camera: str) -> np.ndarray:
        """True angular velocity of a camera in its own OpenCV axes (rad/s), for motion blur."""
        return MUJOCO_TO_OPENCV @ camera_velocity(self.world.model, self.world.data, self.world.model.camera(camera).id, local=True)[:3]

    def _camera_pose(self, camera: str, ahead_s: float = 0.0) -> np.ndarray:
        """True T_world_cam of a camera (OpenCV axes), ``ahead_s`` from now (a pair's true
        pose under a camera-IMU time offset: :func:`sim.world.sensors.camera_motion_ahead`)."""
        data, cam = self.world.data, self.world.model.camera(camera).id
        shift, turn = camera_motion_ahead(self.world.model, data, cam, ahead_s)
        T = np.eye(4)
        T[:3, :3] = turn @ data.cam_xmat[cam].reshape(3, 3) @ MUJOCO_TO_OPENCV
        T[:3, 3] = data.cam_xpos[cam] + shift
        return T

    def _markers_in_view(self, robot: Robot, rig: StereoRig) -> bool:
        """Whether any marker not on ``robot`` may show in the left image of ``rig`` large
        enough to be detected (true poses; conservative: the bounding sphere of the tag with
        its quiet zone against the nominal view, occlusion ignored, the tag's whole width
        against the detector's smallest side ``DEFAULT_MIN_SIDE_PX``)."""
        geoms = self._marker_geoms[self._marker_roots != self._root_body[robot.name]]
        if geoms.size == 0:
            return False
        T = self._camera_pose(rig.left_camera)
        p = (self.world.data.geom_xpos[geoms] - T[:3, 3]) @ T[:3, :3]  # marker centres in camera axes (OpenCV)
        half = self.world.model.geom_size[geoms, 0]
        radius = half * math.sqrt(2.0)
        K = rig.intrinsics
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        x, y, z = p.T
        inside = (
            (fx * x + cx * z >= -radius * math.hypot(fx, cx))
            & ((rig.width - cx) * z - fx * x >= -radius * math.hypot(fx, rig.width - cx))
            & (fy * y + cy * z >= -radius * math.hypot(fy, cy))
            & ((rig.height - cy) * z - fy * y >= -radius * math.hypot(fy, rig.height - cy))
        )
        near = z - radius
        large_enough = (near <= 0) | (fx * 2 * half >= DEFAULT_MIN_SIDE_PX * near)
        return bool(np.any(inside & (z + radius > 0) & large_enough))

    def _others(self, robot: Robot) -> list[tuple[np.ndarray, float]]:
        """The other robots' true xy with their body radii."""
        xpos = self.world.data.xpos
        return [(xpos[body][:2].copy(), self.robots[name].robot.body_radius_m) for name, body in self._root_body.items() if name != robot.name]

    def _score_image(self, runtime: RobotRuntime, frame_id: int, depth: np.ndarray, obstacle: np.ndarray, classified: np.ndarray) -> None:
        """A mapped image's flags at its true camera pose (:mod:`sim.evaluation.image_classification`),
        scored on the pipeline's background thread (in mapping order; nothing in the run reads them)."""
        truth = runtime.capture_truth.pop(frame_id, None)
        for stale in [k for k in runtime.capture_truth if k < frame_id]:  # frames never mapped
            del runtime.capture_truth[stale]
        if truth is not None:
            T_world_cam, others, pair = truth
            true_depth = self.images.result(pair).depth
            t = time.perf_counter()
            cells, observer, name = runtime.image_cells, self.image_observer, runtime.robot.name

            def score() -> None:
                cells.add(depth, obstacle, T_world_cam, others, true_depth, seen=classified)
                if observer is not None:
                    observer(MappedImage(name, frame_id, depth, obstacle, T_world_cam, others, true_depth, cells.calibration, cells.params))

            self.images.background("evaluation", score)
            self.timers.add("evaluation", t)

    def _stereo_done(self, runtime: RobotRuntime, rig: StereoRig, stereo: StereoFrame, depth: np.ndarray, vo_frame: int, t_capture: float):
        if stereo.depth is not None:
            t = time.perf_counter()
            runtime.log.depth_error[rig.name].add(depth, stereo.depth)
            self.timers.add("evaluation", t)
        runtime.onboard.depth_ready(vo_frame, t_capture, stereo.left, stereo.right, depth)

    def _score_depths(self, runtime: RobotRuntime, all_of_them: bool = False) -> None:
        """Score the depth of the finished stereo jobs of rigs other than the VO rig against
        the rendered truth, in the order the jobs finished: those the worker is done with
        (all, when the run ends)."""
        pending = runtime.unscored_depths
        while pending and (all_of_them or not isinstance(pending[0][2], Future) or pending[0][2].done()):
            rig, pair, depth = pending.popleft()
            stereo, depth = self.images.result(pair), self.images.result(depth)
            if stereo.depth is not None:
                t = time.perf_counter()
                runtime.log.depth_error[rig].add(depth, stereo.depth)
                self.timers.add("evaluation", t)
