"""What every simulated robot is: an MJCF model built once, sensors, markers, a route.

A :class:`Robot` builds its own PyMJCF model in ``__init__`` (model name = robot name,
so every compiled name is ``f"{name}/..."``), is attached to the world with a free
joint (:meth:`Robot.attach`), binds to the compiled model (:meth:`Robot.bind`) and is
then driven by :meth:`Robot.control`, which the runner calls at
``physics.control_rate_hz`` before stepping. Robots move only through their
actuators: no teleporting, no mocap.

Controllers read the simulator's true state (pose, velocities) by default. That is a
choice of the testbed, not of the thesis: in scripted scenarios the robots' guidance is
not what is under test, their SLAM is, and it sees only sensor data. With
``navigation.pose_source: estimate`` a preset that supports it (``navigates_on_estimate``)
steers by :meth:`Robot.guidance_pose`, the robot's own belief, and plans around what it
mapped (sim/robots/path_following.py), so SLAM errors change where it goes (thesis 9.3).

Frames: the robot's body frame is its free base body (x forward, y left, z up) with
the IMU site at its origin, axes aligned, so ``pose()`` is the body pose. Marker
``pos``/``quat`` (``self.markers``, compiled geom names) are in that body frame; all
markers sit on the base body. Camera names in ``self.stereo_rigs`` are compiled names.

Lifecycle, as in dm_control's composer entities: ``__init__`` (build) ->
``attach`` -> (world compiles) -> ``bind`` -> ``control`` every control tick.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np
from dm_control import mjcf

from sim.robots.path_following import GazeSource, GoalSource, OwnEstimate, PathFollower
from sim.robots.route import RouteTracker, WaypointRecord
from sim.world.camera_rig import StereoRig
from sim.world.markers import MarkerSpec, add_marker
from slam.lie import roll_pitch, yaw_of, yaw_quat

if TYPE_CHECKING:  # only needed for types; sim.scenario imports this package to validate robots
    from sim.scenario import RobotConfig
    from sim.world.terrain import Terrain

__all__ = ["TIP_OVER_RAD", "Robot", "RobotError", "WaypointRecord", "WheelState"]

TIP_OVER_RAD = math.radians(60.0)  # roll or pitch beyond this counts as tipped over
START_DROP_M = 0.02  # robots are placed this far above their resting height and settle


class RobotError(ValueError):
    """A robot that cannot be built or used as asked (wrong tag count, not bound, ...)."""


@dataclass
class WheelState:
    """True state of one wheel, for wheel odometry (rovers only)."""

    position_body: np.ndarray  # (3,) wheel centre (on the steering axis) in the body frame
    steer_angle: float  # rad, 0 = rolling along body x, positive turns the wheel to the left
    angular_speed: float  # rad/s about the wheel axle, positive rolls the robot forward
    radius: float  # m


def look_xyaxes(direction: Sequence[float], right: Sequence[float]) -> list[float]:
    """MuJoCo camera ``xyaxes`` for a camera looking along ``direction`` with image-right
    ``right`` (both in the parent frame). MuJoCo cameras look along -z with y up."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    x = np.asarray(right, float)
    x = x - d * (x @ d)
    x /= np.linalg.norm(x)
    z = -d
    y = np.cross(z, x)
    return [*x.round(12).tolist(), *y.round(12).tolist()]


def facing_quat(normal: Sequence[float], up_hint: Sequence[float] = (0.0, 0.0, 1.0)) -> tuple[float, ...]:
    """Quaternion (w, x, y, z) of a frame whose z axis is ``normal`` and whose y axis
    points as close to ``up_hint`` as possible (the tag's top edge towards it)."""
    z = np.asarray(normal, float)
    z /= np.linalg.norm(z)
    y = np.asarray(up_hint, float) - z * (z @ np.asarray(up_hint, float))
    if np.linalg.norm(y) < 1e-9:
        y = np.array([0.0, 1.0, 0.0]) - z * z[1]
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([x, y, z]).ravel())
    return tuple(float(v) for v in quat)


class Robot(ABC):
    """Base of all robot presets. Subclasses implement :meth:`_build`,
    :meth:`_footprint`, :meth:`_bind` and :meth:`_control`, and set the class
    attributes below: what differs between robot types is said here and in the
    presets, and the scenario checks, the run loop and the on-board stack ask the
    robot's class instead of testing which type it is."""

    preset: ClassVar[str] = ""
    default_hfov_deg: ClassVar[float] = 60.0
    #: AprilTags the robot carries (a scenario's ``tag_ids`` must list this many).
    marker_count: ClassVar[int]
    #: Cores of the on-board computer unless ``computer.cores`` says otherwise (thesis 7.1).
    default_cores: ClassVar[int]
    #: IMU model (a key of ``sim.world.sensors.IMU_PRESETS``) unless ``imu.preset`` says otherwise (thesis 7.1).
    default_imu_preset: ClassVar[str]
    #: Names of the stereo rigs it builds (what ``slam.vo_rig`` may name).
    stereo_rig_names: ClassVar[tuple[str, ...]]
    #: Stereo rig whose images feed the visual odometry unless ``slam.vo_rig`` says otherwise.
    default_vo_rig: ClassVar[str]
    #: Fastest ``route.speed_mps`` it can follow (m/s).
    max_speed_mps: ClassVar[float]
    #: Its own motion as white-noise acceleration (m/s^2/sqrt(Hz)) and turn rate
    #: (rad/s/sqrt(Hz)): the filter's process noise while its IMU is stuck
    #: (slam.filter.FilterParams.motion_accel_density, slam/local_estimator.py).
    motion_accel_density: ClassVar[float]
    motion_turn_density: ClassVar[float]
    #: Wheel encoders: the run turns :meth:`wheel_states` into wheel odometry, which the filter fuses.
    has_wheel_odometry: ClassVar[bool] = False
    #: Names of its wheels, in the order of :meth:`wheel_states` (what an ``encoder_failure`` fault names).
    wheel_names: ClassVar[tuple[str, ...]] = ()
    #: Height of the radio antenna above the body origin (m), for the network's line of sight.
    antenna_height_m: ClassVar[float]
    #: Horizontal reach of the robot's geometry around its body origin (m): map points this
    #: close to a robot were seen on it (docs/mapping.md, obstacle scoring).
    body_radius_m: ClassVar[float]
    #: Map only above this height over the take-off point (filter estimate, m); None: always.
    min_mapping_height_m: ClassVar[float | None] = None
    #: Local names of its geoms that touch the ground by design (wheels, skids): their
    #: contacts with rocks are no collisions (sim/run/collisions.py).
    ground_contact_geoms: ClassVar[tuple[str, ...]] = ()
    #: Its guidance can steer by the robot's own estimate (``navigation.pose_source: estimate``,
    #: sim/robots/path_following.py).
    navigates_on_estimate: ClassVar[bool] = False
    #: It can explore a region on its own goals (the scenario's ``exploration``, thesis 9.3): its
    #: controller asks :attr:`goal_source` for a goal whenever its route is done.
    explores: ClassVar[bool] = False
    #: Its cameras sit on a pan-tilt head whose encoders give ``T_body_cam``: pan about the
    #: body's z axis, tilt about the cameras' x axis (their encoder offsets are calibration
    #: errors, sim/world/calibration_errors.py).
    pan_tilt_head: ClassVar[bool] = False

    @classmethod
    def check_config(cls, cfg: RobotConfig) -> None:
        """Raise ``ValueError`` for what the scenario's ``cfg`` asks of this robot type
        that it cannot do (:class:`sim.scenario.RobotConfig` validation calls this)."""
        if cfg.tag_ids is not None and len(cfg.tag_ids) != cls.marker_count:
            raise ValueError(f"preset {cfg.preset} carries {cls.marker_count} markers, got {len(cfg.tag_ids)} tag_ids")
        if cfg.navigation.pose_source == "estimate" and not cls.navigates_on_estimate:
            raise ValueError(f"navigation.pose_source: estimate is not built for preset {cfg.preset} yet; it flies by the simulator's truth")
        if cfg.route.speed_mps > cls.max_speed_mps:
            raise ValueError(f"route.speed_mps: got {cfg.route.speed_mps:g}: preset {cfg.preset} goes at most {cls.max_speed_mps:g} m/s")

    def __init__(self, cfg: RobotConfig, tag_ids: Sequence[int]):
        tag_ids = [int(t) for t in tag_ids]
        if len(tag_ids) != self.marker_count:
            raise RobotError(
                f"robot {cfg.name} (preset {cfg.preset}) carries {self.marker_count} markers, got tag_ids {tag_ids}"
            )
        self.name: str = cfg.name
        self.cfg: RobotConfig = cfg
        self.tag_ids: list[int] = tag_ids
        self.mjcf_model: mjcf.RootElement = mjcf.RootElement(model=cfg.name)
        self.stereo_rigs: list[StereoRig] = []
        self.markers: list[MarkerSpec] = []
        self.imu_site = self._compiled("imu")
        self.accel_sensor = self._compiled("accel")
        self.gyro_sensor = self._compiled("gyro")
        self.route = RouteTracker(cfg.route)
        self.waypoints: list[WaypointRecord] = self.route.records
        self.phase = "idle"
        self.tipped_over = False
        self.dead = False
        #: What the robot's computer believes (set by the run with ``navigation.pose_source: estimate``).
        self.own_estimate: OwnEstimate | None = None
        #: Its path planner and follower, for presets that plan on their own map (set when bound).
        self.follower: PathFollower | None = None
        #: Where an exploring robot's next goals come from once its route is done (set by the run; ``explores``).
        self.goal_source: GoalSource | None = None
        #: Where a robot with a :attr:`pan_tilt_head` points it when it may (set by the run; active mutual observation).
        self.gaze_source: GazeSource | None = None
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._attached = False
        self._build()
        imu = self.mjcf_model.worldbody.add("site", name="imu", pos=[0, 0, 0], size=[0.01], group=4)
        self.mjcf_model.sensor.add("accelerometer", name="accel", site=imu)
        self.mjcf_model.sensor.add("gyro", name="gyro", site=imu)

    # ------------------------------------------------------------------ building

    @property
    def hfov_deg(self) -> float:
        return self.cfg.camera.hfov_deg if self.cfg.camera.hfov_deg is not None else self.default_hfov_deg

    def _compiled(self, local: str) -> str:
        return f"{self.name}/{local}"

    def _add_stereo_pair(
        self,
        body: mjcf.Element,
        rig_name: str,
        centre: Sequence[float],
        direction: Sequence[float],
        right: Sequence[float],
        baseline_m: float,
    ) -> StereoRig:
        """Two cameras at ``centre`` -+ baseline/2 along ``right``, looking along ``direction``."""
        cam = self.cfg.camera
        rig = StereoRig(
            name=rig_name,
            left_camera=self._compiled(f"{rig_name}_left"),
            right_camera=self._compiled(f"{rig_name}_right"),
            baseline_m=baseline_m,
            hfov_deg=self.hfov_deg,
            width=cam.width,
            height=cam.height,
        )
        xyaxes = look_xyaxes(direction, right)
        r = np.asarray(right, float) / np.linalg.norm(right)
        c = np.asarray(centre, float)
        for side, sign in (("left", -0.5), ("right", 0.5)):
            body.add(
                "camera",
                name=f"{rig_name}_{side}",
                pos=(c + sign * baseline_m * r).tolist(),
                xyaxes=xyaxes,
                fovy=rig.vfov_deg,
            )
        self.stereo_rigs.append(rig)
        return rig

    def _add_marker(self, body: mjcf.Element, index: int, size_m: float, pos, normal, up_hint=(0, 0, 1)) -> None:
        """AprilTag ``self.tag_ids[index]`` on ``body`` at ``pos``, facing ``normal``."""
        local = f"tag{index}"
        pos = tuple(float(v) for v in pos)
        quat = facing_quat(normal, up_hint)
        add_marker(body, MarkerSpec(local, self.tag_ids[index], size_m, pos, quat))
        self.markers.append(MarkerSpec(self._compiled(local), self.tag_ids[index], size_m, pos, quat))

    @abstractmethod
    def _build(self) -> None:
        """Fill ``self.mjcf_model`` (geoms on its worldbody form the free base body),
        ``self.stereo_rigs`` and ``self.markers``."""

    @abstractmethod
    def _footprint(self) -> np.ndarray:
        """(k, 3) points of the robot's lowest contact points in the body frame at rest."""

    # ------------------------------------------------------------------ world

    def attach(self, world_root: mjcf.RootElement, terrain: Terrain) -> None:
        """Attach at ``cfg.start`` (xy, yaw), resting on the terrain, with a free joint."""
        if self._attached:
            raise RobotError(f"robot {self.name} is already attached to a world")
        x, y = self.cfg.start.xy
        yaw = math.radians(self.cfg.start.yaw_deg)
        feet = self._footprint()
        c, s = math.cos(yaw), math.sin(yaw)
        fx = x + c * feet[:, 0] - s * feet[:, 1]
        fy = y + s * feet[:, 0] + c * feet[:, 1]
        ground = np.asarray(terrain.height_at(fx, fy), float)
        z = float(np.max(ground - feet[:, 2])) + START_DROP_M
        frame = world_root.attach(self.mjcf_model)
        frame.add("freejoint", name="root")
        frame.pos = [x, y, z]
        frame.quat = yaw_quat(yaw).tolist()
        self._attached = True

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve ids in the compiled model."""
        self.model, self.data = model, data
        self._body_id = model.body(self._compiled("")).id
        self._imu_id = model.site(self.imu_site).id
        joint = model.joint(self._compiled("root/"))
        self._qadr = int(joint.qposadr[0])
        self._vadr = int(joint.dofadr[0])
        self._bind(model, data)

    @abstractmethod
    def _bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Subclass hook: resolve actuator and joint ids."""

    def _require_bound(self) -> mujoco.MjData:
        if self.data is None:
            raise RobotError(f"robot {self.name} is not bound to a compiled model yet (call World/bind first)")
        return self.data

    # ------------------------------------------------------------------ state (truth)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """World position and quaternion (w, x, y, z) of the body frame at the IMU site."""
        data = self._require_bound()
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, data.site_xmat[self._imu_id])
        return data.site_xpos[self._imu_id].copy(), quat

    def rotation(self) -> np.ndarray:
        """3x3 body-to-world rotation (truth)."""
        return self._require_bound().site_xmat[self._imu_id].reshape(3, 3).copy()

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """World linear velocity of the body origin and body-frame angular velocity."""
        data = self._require_bound()
        qv = data.qvel[self._vadr : self._vadr + 6]
        return qv[:3].copy(), qv[3:].copy()

    def roll_pitch_yaw(self) -> tuple[float, float, float]:
        """ZYX Euler angles of the body (IMU site) in the world."""
        R = self._require_bound().site_xmat[self._imu_id].reshape(3, 3)
        return (*roll_pitch(R), yaw_of(R))

    def wheel_states(self) -> list[WheelState]:
        return []

    def guidance_pose(self) -> np.ndarray | None:
        """``T_world_body`` the controller steers by: the truth, or with an :attr:`own_estimate`
        what the robot believes (None until its filter is initialised)."""
        if self.own_estimate is None:
            T = np.eye(4)
            T[:3, :3] = self.rotation()
            T[:3, 3] = self._require_bound().site_xpos[self._imu_id]
            return T
        T_odom_body = self.own_estimate.odometry_pose()
        return None if T_odom_body is None else self.own_estimate.world_from_odometry() @ T_odom_body

    def _is_tipped(self) -> bool:
        roll, pitch, _ = self.roll_pitch_yaw()
        return abs(roll) > TIP_OVER_RAD or abs(pitch) > TIP_OVER_RAD

    # ------------------------------------------------------------------ control

    def control(self, t: float, terrain: Terrain) -> None:
        """Set ``data.ctrl`` for this robot's actuators and advance its route."""
        self._require_bound()
        if not self.tipped_over and not self.dead and self._is_tipped():
            self.tipped_over = True
            self.route.fail_remaining(t, "tipped_over")
            self.phase = "tipped over"
        if self.dead or self.tipped_over or t < self.cfg.route.start_delay_s:
            self._stop()
            return
        self._control(t, terrain)

    def fail(self, t: float) -> None:
        """The robot dies (a ``dies`` fault, sim/run/faults.py): motors off from now on, every waypoint left
        fails as "dead"."""
        self.dead = True
        self.route.fail_remaining(t, "dead")
        self.phase = "dead"

    @abstractmethod
    def _control(self, t: float, terrain: Terrain) -> None:
        """One control tick while the robot is upright."""

    @abstractmethod
    def _stop(self) -> None:
        """Command a safe stop (wheels still, motors off)."""

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "tipped over", "dead")

    @property
    @abstractmethod
    def commands_motion(self) -> bool:
        """Whether the robot's own controller commands motion now (wheels driven, rotors
        spinning): what its computer knows, handed to the estimator's rest test
        (slam/rest.py), since a quiet IMU at constant velocity looks like rest."""

    @property
    def status(self) -> str:
        """Short human state for a progress bar."""
        if self.dead:
            return "dead"
        if self.tipped_over:
            return "tipped over"
        n = len(self.waypoints)
        if self.phase == "done":
            failed = [w for w in self.waypoints if w.status == "failed"]
            if failed and failed[-1].index == n - 1:
                return failed[-1].reason.replace("_", " ") if failed[-1].reason else "failed"
            return f"done ({len(failed)} failed)" if failed else "done"
        if self.phase == "drive" or self.phase == "fly":
            return f"wp {self.route.current + 1}/{n}"
        return self.phase
