"""The Lightweight Rover Unit (thesis 7.1): ~40 kg, four individually steered and
driven wheels, a ~1 m mast with a pan-tilt stereo head, three tilted AprilTag markers
around the mast, IMU, wheel encoders.

Model (body frame x forward, y left, z up, origin = IMU site at the chassis centre):

- chassis box 0.64 x 0.40 x 0.16 m; ground clearance about 0.2 m;
- four wheel modules at (+-0.32, +-0.37, -0.14): a steering hinge (z, position
  actuator, +-100 deg) carrying a drive hinge (y, velocity actuator). The wheel's
  contact shape is a sphere of radius 0.15 m (robust on a heightfield: one rounded
  contact, no edge catching); what cameras see is a 0.1 m wide tyre cylinder;
- the front wheel pair sits on a passive rocker axle (hinge about x, +-15 deg, spring
  and damper), so all four wheels keep ground contact on uneven terrain, standing in
  for the real rover's bogie suspension;
- mast to 0.97 m above the chassis centre (about 1.3 m above ground), pan joint
  (+-180 deg) and tilt joint (+-90 deg, positive looks down, default 25 deg down), both
  position-controlled; stereo pair on the tilt head, baseline 0.09 m, looking along the
  head's x axis;
- three AprilTag 36h11 markers (0.15 m) around the mast at 0.5 m above the chassis
  centre (about 0.8 m above ground), 120 deg apart (facing forward, back-left,
  back-right), each tilted back so that its normal points 35 deg above the horizon:
  visible from every side and from above;
- contact geometry: chassis, wheels (spheres), mast and pan-tilt head, so that the rover
  cannot drive under the lander's deck or through a hovering hexacopter; steering
  columns, rocker axle and tyres are visual only;
- a tilt guard: beyond 35 deg of roll or pitch the rover backs off along its track
  instead of driving on (the thesis's rovers would not plan through such slopes);
  against an obstacle it makes no progress and the waypoint fails as "stuck".

The route controller turns towards the waypoint (point turn beyond 60 deg of heading
error) and drives at ``speed_mps``; with ``navigation.pose_source: estimate`` it judges
where it is by its own estimate and steers along a path planned around the obstacles of
its rolling obstacle map (sim/robots/path_following.py), obstacles grown by
``PLANNING_RADIUS_M``; a waypoint is reached within ``tolerance_m``; with
``scan`` the rover stops and pans its head a full turn (-180 -> +180 deg) in
``scan_duration_s`` (plus slewing to and from the start), its head tilted by
``route.scan_tilt_deg`` if set (e.g. up towards a lander's tag or another rover's mast).
An exploring rover (the scenario's ``exploration``) asks its goal source for the next goal
whenever its route is done, and stands (phase "wait") until one is chosen.
While driving, the head can sweep its pan sinusoidally, ``route.head_sweep_deg`` to each
side over ``route.head_sweep_period_s`` (the preset's defaults: none), so that the views
along a leg cover more than the 50 deg strip ahead and see rocks from several sides
without stopping (the LRU looked around while driving, thesis 9.3); every image carries
the head's encoder transform, as during scans.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from sim.robots.base import Robot, WheelState
from sim.robots.path_following import PathFollower
from sim.robots.rover_control import DriveGains, drive_command, wheel_commands
from slam.lie import roll_pitch, wrap_angle, yaw_of
from slam.navigation.planner import PlannerParams

if TYPE_CHECKING:
    from sim.scenario import RobotConfig
    from sim.world.terrain import Terrain

WHEEL_RADIUS_M = 0.15
MAX_WHEEL_RATE_RPS = 15.0  # the drive motors' limit
WHEEL_FRICTION = 0.8  # wheel-regolith traction; with priority=1 it overrides the ground geom's
WHEEL_X_M = 0.32
WHEEL_Y_M = 0.37
WHEEL_Z_M = -0.14
MAST_XY = (0.18, 0.0)
PAN_HEIGHT_M = 0.97
TILT_OFFSET_M = 0.06
TILT_AXIS_BODY = np.array([MAST_XY[0], MAST_XY[1], PAN_HEIGHT_M + TILT_OFFSET_M])  # where the head turns, body frame
STEREO_BASELINE_M = 0.09
DEFAULT_TILT_DEG = 25.0
MARKER_SIZE_M = 0.15
MARKER_HEIGHT_M = 0.5
MARKER_RADIUS_M = 0.11  # tag centres from the mast axis: the three tags just clear each other
MARKER_ELEVATION_DEG = 35.0
MARKER_AZIMUTHS_DEG = (0.0, 120.0, 240.0)
PAN_SLEW_RPS = 1.0  # head pan speed when moving to/from a scan
HEAD_SWEEP_DEG = 0.0  # default pan amplitude while driving: none
HEAD_SWEEP_PERIOD_S = 10.0  # default period of the sweep
#: While driving, the head turns to a peer it looks for (``gaze_source``) only this far from ahead, so that
#: the 50 deg field of view still reaches within 15 deg of the way ahead; standing, it turns any way.
GAZE_MAX_PAN_DRIVING_RAD = math.radians(40)
GAZE_SLEWING_RAD = math.radians(2)  # the head still turns to its gaze: that sways the body (no rest)
TILT_GUARD_RAD = math.radians(35)  # beyond this roll/pitch the rover backs off ...
TILT_GUARD_RELEASE_RAD = math.radians(25)  # ... until it is below this again
BACKOFF_SPEED = 0.15  # m/s
BACKOFF_MIN_S = 1.0
BACKOFF_MAX_S = 5.0
#: Obstacles grown by this much when planning: half the track width (0.42 m) and a margin, since the
#: obstacle map marks a rock where its height steps (its rim), not always out to its foot.
PLANNING_RADIUS_M = 0.6

WHEELS = ("fl", "fr", "rl", "rr")
WHEEL_XY = np.array([[WHEEL_X_M, WHEEL_Y_M], [WHEEL_X_M, -WHEEL_Y_M], [-WHEEL_X_M, WHEEL_Y_M], [-WHEEL_X_M, -WHEEL_Y_M]])

WHEEL_XY_LIST = [tuple(map(float, p)) for p in WHEEL_XY]

NO_CONTACT = {"contype": 0, "conaffinity": 0}


class LRU(Robot):
    """Preset ``lru`` (narrow stereo, 50.6 deg); :class:`LRUWide` is ``lru_wide``."""

    preset = "lru"
    default_hfov_deg = 50.6
    marker_count = len(MARKER_AZIMUTHS_DEG)
    default_cores = 4  # quad-core i7 (thesis 7.1)
    default_imu_preset = "xsens_mti10"
    stereo_rig_names = ("head",)
    default_vo_rig = "head"
    max_speed_mps = MAX_WHEEL_RATE_RPS * WHEEL_RADIUS_M  # 2.25 m/s with the wheels at their limit
    # measured: the 99th percentile of its true velocity change (0.35 m/s) and attitude change
    # (34 deg) within one second, at about two sigma (docs/estimation.md's made_stuck and Etna)
    motion_accel_density = 0.2
    motion_turn_density = 0.3
    has_wheel_odometry = True
    wheel_names = WHEELS
    pan_tilt_head = True
    antenna_height_m = 1.6  # on the mast
    navigates_on_estimate = True
    explores = True
    ground_contact_geoms = tuple(f"wheel_{w}" for w in WHEELS)
    body_radius_m = math.hypot(WHEEL_X_M, WHEEL_Y_M) + WHEEL_RADIUS_M  # wheel corners: 0.64 m

    @classmethod
    def check_config(cls, cfg: RobotConfig) -> None:
        """Waypoint altitudes and landing are for the hexacopter."""
        bad = [i for i, w in enumerate(cfg.route.waypoints) if w.altitude_m is not None]
        if bad:
            raise ValueError(f"altitude_m is for the hexacopter only; rover waypoints {bad} have one")
        if cfg.route.land:
            raise ValueError("route.land is for the hexacopter only")
        super().check_config(cfg)

    def _build(self) -> None:
        root = self.mjcf_model
        root.default.geom.rgba = [0.75, 0.75, 0.78, 1]
        base = root.worldbody
        base.add("geom", name="chassis", type="box", size=[0.32, 0.2, 0.08], mass=26.0, rgba=[0.85, 0.85, 0.88, 1])
        base.add(
            "geom",
            name="mast",
            type="cylinder",
            fromto=[MAST_XY[0], MAST_XY[1], 0.08, MAST_XY[0], MAST_XY[1], PAN_HEIGHT_M - 0.02],
            size=[0.025],
            mass=1.0,
        )

        # pan-tilt head
        pan = base.add("body", name="pan", pos=[MAST_XY[0], MAST_XY[1], PAN_HEIGHT_M])
        pan.add(
            "joint", name="pan", type="hinge", axis=[0, 0, 1], range=[-183, 183], damping=0.5, armature=0.01
        )
        pan.add("geom", type="cylinder", size=[0.03, 0.02], mass=0.5)
        tilt = pan.add("body", name="tilt", pos=[0, 0, TILT_OFFSET_M])
        tilt.add("joint", name="tilt", type="hinge", axis=[0, 1, 0], range=[-90, 90], damping=0.5, armature=0.01)
        tilt.add("geom", type="box", size=[0.04, 0.1, 0.035], mass=1.0, rgba=[0.3, 0.3, 0.32, 1])
        self._add_stereo_pair(tilt, "head", centre=[0.045, 0, 0], direction=[1, 0, 0], right=[0, -1, 0],
                              baseline_m=STEREO_BASELINE_M)

        # markers around the mast
        elev = math.radians(MARKER_ELEVATION_DEG)
        for k, az_deg in enumerate(MARKER_AZIMUTHS_DEG):
            az = math.radians(az_deg)
            normal = [math.cos(az) * math.cos(elev), math.sin(az) * math.cos(elev), math.sin(elev)]
            pos = [MAST_XY[0] + MARKER_RADIUS_M * math.cos(az), MAST_XY[1] + MARKER_RADIUS_M * math.sin(az),
                   MARKER_HEIGHT_M]
            self._add_marker(base, k, MARKER_SIZE_M, pos, normal)

        # wheel modules; the front pair on a passive rocker axle
        rocker = base.add("body", name="rocker", pos=[WHEEL_X_M, 0, WHEEL_Z_M])
        rocker.add("joint", name="rocker", type="hinge", axis=[1, 0, 0], range=[-15, 15], stiffness=300.0,
                   damping=40.0, armature=0.05)
        rocker.add("geom", type="capsule", fromto=[0, -WHEEL_Y_M + 0.08, 0, 0, WHEEL_Y_M - 0.08, 0], size=[0.025],
                   mass=1.0, **NO_CONTACT)
        for name, (wx, wy) in zip(WHEELS, WHEEL_XY, strict=True):
            parent, pos = (rocker, [0, wy, 0]) if wx > 0 else (base, [wx, wy, WHEEL_Z_M])
            steer = parent.add("body", name=f"steer_{name}", pos=pos)
            steer.add("joint", name=f"steer_{name}", type="hinge", axis=[0, 0, 1], range=[-100, 100], damping=8.0,
                      armature=0.02)
            steer.add("geom", type="cylinder", fromto=[0, 0, 0.05, 0, 0, 0.14], size=[0.02], mass=0.5, **NO_CONTACT)
            wheel = steer.add("body", name=f"wheel_{name}")
            wheel.add("joint", name=f"drive_{name}", type="hinge", axis=[0, 1, 0], damping=0.05, armature=0.02)
            wheel.add("geom", name=f"wheel_{name}", type="sphere", size=[WHEEL_RADIUS_M], mass=2.0,
                      friction=[WHEEL_FRICTION, 0.005, 0.0001], priority=1, group=3)
            wheel.add("geom", type="cylinder", size=[WHEEL_RADIUS_M, 0.05], quat=[0.7071068, 0.7071068, 0, 0],
                      mass=0.0, rgba=[0.25, 0.25, 0.25, 1], **NO_CONTACT)
            root.actuator.add("position", name=f"steer_{name}", joint=f"steer_{name}", kp=150.0,
                              forcelimited=True, forcerange=[-60, 60], ctrlrange=[-1.75, 1.75], ctrllimited=True)
            root.actuator.add("velocity", name=f"drive_{name}", joint=f"drive_{name}", kv=25.0,
                              forcelimited=True, forcerange=[-40, 40], ctrlrange=[-MAX_WHEEL_RATE_RPS, MAX_WHEEL_RATE_RPS],
                              ctrllimited=True)
        root.actuator.add("position", name="pan", joint="pan", kp=10.0, forcelimited=True, forcerange=[-10, 10],
                          ctrlrange=[-3.2, 3.2], ctrllimited=True)
        root.actuator.add("position", name="tilt", joint="tilt", kp=10.0, forcelimited=True, forcerange=[-10, 10],
                          ctrlrange=[-1.58, 1.58], ctrllimited=True)

    def _footprint(self) -> np.ndarray:
        return np.array([[x, y, WHEEL_Z_M - WHEEL_RADIUS_M] for x, y in WHEEL_XY])

    # ------------------------------------------------------------------ binding

    def _bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        c = self._compiled
        self._steer_act = [model.actuator(c(f"steer_{w}")).id for w in WHEELS]
        self._drive_act = [model.actuator(c(f"drive_{w}")).id for w in WHEELS]
        self._pan_act = model.actuator(c("pan")).id
        self._tilt_act = model.actuator(c("tilt")).id
        self._steer_q = [int(model.joint(c(f"steer_{w}")).qposadr[0]) for w in WHEELS]
        self._drive_v = np.array([model.joint(c(f"drive_{w}")).dofadr[0] for w in WHEELS])
        self._wheel_body = np.array([model.body(c(f"steer_{w}")).id for w in WHEELS])
        self._pan_q = model.joint(c("pan")).qposadr[0]
        self._tilt_q = model.joint(c("tilt")).qposadr[0]
        self._steer_prev = [0.0] * len(WHEELS)
        self._backoff_t0: float | None = None
        navigation = self.cfg.navigation
        self.follower = PathFollower(navigation, PlannerParams(radius_m=PLANNING_RADIUS_M)) if navigation.pose_source == "estimate" else None
        self.pan_ref = 0.0
        self.tilt_ref = math.radians(DEFAULT_TILT_DEG)
        self._apply(0.0, 0.0)
        data.ctrl[self._tilt_act] = self.tilt_ref

    # ------------------------------------------------------------------ sensors (truth)

    def wheel_states(self) -> list[WheelState]:
        data = self._require_bound()
        pos, _ = self.pose()
        rot = self.rotation()
        out = []
        for k in range(len(WHEELS)):
            p_body = rot.T @ (data.xpos[self._wheel_body[k]] - pos)
            out.append(
                WheelState(
                    position_body=p_body,
                    steer_angle=float(data.qpos[self._steer_q[k]]),
                    angular_speed=float(data.qvel[self._drive_v[k]]),
                    radius=WHEEL_RADIUS_M,
                )
            )
        return out

    def head_angles(self) -> tuple[float, float]:
        """True (pan, tilt) in rad; tilt positive looks down."""
        data = self._require_bound()
        return float(data.qpos[self._pan_q]), float(data.qpos[self._tilt_q])

    # ------------------------------------------------------------------ control

    def _apply(self, v: float, w: float) -> None:
        data = self.data
        steer, omega = wheel_commands(v, w, WHEEL_XY_LIST, WHEEL_RADIUS_M, self._steer_prev)
        self._steer_prev = steer
        for k in range(len(WHEELS)):
            # do not push a wheel that is still turning to its steering angle
            align = max(0.0, math.cos(steer[k] - data.qpos[self._steer_q[k]])) ** 4
            data.ctrl[self._steer_act[k]] = steer[k]
            data.ctrl[self._drive_act[k]] = omega[k] * align
        data.ctrl[self._pan_act] = self.pan_ref
        data.ctrl[self._tilt_act] = self.tilt_ref

    def _stop(self) -> None:
        self._apply(0.0, 0.0)

    @property
    def commands_motion(self) -> bool:
        """Wheels driven, or the pan-tilt head scanning, or turning to its gaze while the rover
        stands: the swinging mast sways the body on its rocker by 1-2 cm/s at the IMU
        (measured on etna_two_rovers.yaml), so that is no rest either."""
        if self.tipped_over:
            return False
        if self.phase in ("drive", "scan"):
            return True
        return self.gaze_source is not None and abs(self.head_angles()[0] - self.pan_ref) > GAZE_SLEWING_RAD

    def _begin_next(self, t: float, xy: np.ndarray) -> None:
        source = self.goal_source
        if self.route.done and source is not None and not source.finished:
            goal = source.next_goal(t)
            if goal is None:
                self.phase = "wait"  # for its next exploration goal
                return
            self.route.add(goal)
        if self.route.done:
            self.phase = "done"
        else:
            self.phase = "drive"
            self.route.begin_leg(t, xy)
            if self.follower is not None:
                self.follower.reset()

    def _control(self, t: float, terrain: Terrain) -> None:
        true_xy = self.pose()[0][:2]  # for the waypoint records only
        estimate = self.own_estimate
        T_odom_body = None if estimate is None else estimate.odometry_pose()
        if estimate is not None and T_odom_body is None:  # its filter is not initialised yet
            self._apply(0.0, 0.0)
            return
        T = self.guidance_pose() if estimate is None else estimate.world_from_odometry() @ T_odom_body
        xy = T[:2, 3]
        roll, pitch = roll_pitch(T[:3, :3])
        yaw = yaw_of(T[:3, :3])
        tilt = max(abs(roll), abs(pitch))
        route = self.route
        v = w = 0.0
        if self.phase in ("idle", "wait"):
            self._begin_next(t, xy)
        if self.phase == "drive":
            if route.distance(xy) < route.cfg.tolerance_m:
                scan = route.target.scan
                route.reach(t, true_xy)
                if scan:
                    self.phase = "scan"
                    self._scan_t0 = t
                else:
                    self._begin_next(t, xy)
            else:
                to_goal = route.target_xy - xy
                reason = route.check(t, xy, wrap_angle(math.atan2(to_goal[1], to_goal[0]) - yaw))
                exploring = self.goal_source is not None and route.current >= len(self.cfg.route.waypoints)
                if reason is None and exploring and self.goal_source.yields(route.target_xy):
                    reason = "withdrawn"
                if reason is not None:
                    route.fail(t, true_xy, reason)
                    self._begin_next(t, xy)
                else:
                    goal = route.target_xy if self.follower is None else self.follower.steer_point(t, estimate, T_odom_body, route.target_xy)
                    v, w = drive_command(xy, yaw, goal, route.cfg.speed_mps, DriveGains())
                    v, w = self._tilt_guard(t, tilt, v, w)
                    gaze = self._gaze(t, T)
                    if gaze is None or abs(gaze[0]) > GAZE_MAX_PAN_DRIVING_RAD:
                        self.pan_ref, self.tilt_ref = self._sweep_pan(t), math.radians(DEFAULT_TILT_DEG)
                    else:
                        self.pan_ref, self.tilt_ref = gaze
        if self.phase == "scan":
            self.pan_ref = self._scan_pan(t - self._scan_t0)
            scan_tilt = self.cfg.route.scan_tilt_deg
            self.tilt_ref = math.radians(DEFAULT_TILT_DEG if scan_tilt is None else scan_tilt)
            if self.pan_ref is None:
                self.pan_ref = 0.0
                self.tilt_ref = math.radians(DEFAULT_TILT_DEG)
                self._begin_next(t, xy)
        if self.phase in ("wait", "done"):
            gaze = self._gaze(t, T)
            if gaze is not None:
                self.pan_ref, self.tilt_ref = gaze
            else:
                self.tilt_ref = math.radians(DEFAULT_TILT_DEG)
        self._apply(v, w)

    def _gaze(self, t: float, T_world_body: np.ndarray) -> tuple[float, float] | None:
        """(pan, tilt) that point the head at :attr:`gaze_source`'s point, from the pose the
        guidance believes, or None if there is none. The tilt puts the point a quarter of
        the image height below its top edge (a peer's markers sit about as high as the
        head: level, they would leave the ground in the lower half only), never below the
        usual ``DEFAULT_TILT_DEG``."""
        target = None if self.gaze_source is None else self.gaze_source.look_at(t)
        if target is None:
            return None
        v = T_world_body[:3, :3].T @ (np.asarray(target, float) - T_world_body[:3, 3]) - TILT_AXIS_BODY
        rig = self.stereo_rigs[0]
        down = math.atan2(-v[2], math.hypot(v[0], v[1])) + math.atan2(rig.height / 4, rig.focal_px)
        return math.atan2(v[1], v[0]), min(down, math.radians(DEFAULT_TILT_DEG))

    def _tilt_guard(self, t: float, tilt: float, v: float, w: float) -> tuple[float, float]:
        """Never drive on into a slope that would tip the rover: beyond ``TILT_GUARD_RAD``
        of roll or pitch it reverses along its track for at least ``BACKOFF_MIN_S`` and
        until the tilt is below ``TILT_GUARD_RELEASE_RAD`` (at most ``BACKOFF_MAX_S``).
        Against an obstacle this repeats without progress, which ends as "stuck"."""
        if self._backoff_t0 is None and tilt > TILT_GUARD_RAD:
            self._backoff_t0 = t
        if self._backoff_t0 is not None:
            elapsed = t - self._backoff_t0
            if elapsed < BACKOFF_MIN_S or (tilt > TILT_GUARD_RELEASE_RAD and elapsed < BACKOFF_MAX_S):
                return -BACKOFF_SPEED, 0.0
            self._backoff_t0 = None
        return v, w

    def _sweep_pan(self, t: float) -> float:
        """Pan reference while driving: ``head_sweep_deg * sin(2 pi t / head_sweep_period_s)``."""
        route = self.cfg.route
        amplitude = math.radians(HEAD_SWEEP_DEG if route.head_sweep_deg is None else route.head_sweep_deg)
        period = HEAD_SWEEP_PERIOD_S if route.head_sweep_period_s is None else route.head_sweep_period_s
        return amplitude * math.sin(2 * math.pi * t / period)

    def _scan_pan(self, dt: float) -> float | None:
        """Pan reference during a scan: slew to -180 deg, sweep a full turn to +180 deg
        in ``scan_duration_s``, slew back to 0; None when finished."""
        slew = math.pi / PAN_SLEW_RPS
        sweep = self.cfg.route.scan_duration_s
        if dt < slew:
            return -math.pi * dt / slew
        if dt < slew + sweep:
            return -math.pi + 2 * math.pi * (dt - slew) / sweep
        if dt < 2 * slew + sweep:
            return math.pi * (1 - (dt - slew - sweep) / slew)
        return None


class LRUWide(LRU):
    """Preset ``lru_wide``: the same rover with the wide-angle stereo (112.8 deg, thesis 7.1)."""

    preset = "lru_wide"
    default_hfov_deg = 112.8


__all__ = ["LRU", "WHEEL_RADIUS_M", "LRUWide"]
