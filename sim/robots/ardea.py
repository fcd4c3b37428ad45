"""ARDEA, DLR's hexacopter (thesis 7.1): ~3 kg, six rotors, two stereo pairs.

Model (body frame x forward, y left, z up, origin = IMU site at the body centre):

- central box 0.2 x 0.2 x 0.08 m, six arms to rotors on a 0.28 m radius at 0, 60,
  ..., 300 deg (outside the cameras' view). Each rotor is a site
  with a thrust actuator along the body z axis, ``gear = (0, 0, 1, 0, 0, +-k)``: the
  yaw reaction torque is k = 0.016 N m per N of thrust, alternating spin directions.
  Thrust 0..12 N per rotor (hover needs about 4.9 N);
- landing gear: two skids along x at y = +-0.2 m, 0.29 m below the body centre;
- contact geometry: body, arms, rotor discs and skids (what the hexacopter can hit:
  a rover's mast, a rock, the lander); only the thin skid struts are visual;
- stereo: the thesis's four fisheye cameras are two stereo pairs (b = 0.12 m) whose
  optical axes are tilted +60 deg (up) and -60 deg (down) from the horizon; on the
  robot each fisheye image is split and remapped into virtual pinholes. We render one
  rectified pinhole per camera instead, 80 deg horizontal field of view unless
  ``camera.hfov_deg`` says otherwise (rigs ``up`` and ``down``);
- two AprilTag markers (0.12 m) hanging below the body on its left and right sides,
  facing sideways (+-y), in the gaps between the rotors: a rover camera ~2 m away
  sees them past the rotor discs when ARDEA stands on the ground or hovers low.

Route: take off to ``cruise_altitude_m`` above the terrain, fly each leg at
``speed_mps`` holding the height above the (locally averaged) terrain under it
(a waypoint's ``altitude_m`` overrides), yaw along the leg, optionally yaw a full
turn at a waypoint (``scan``), land after the last waypoint if ``route.land``,
otherwise hover there. Without waypoints it stays parked on the ground. Landing
ends when both skids stand level on something; a skid caught on an edge (another
robot, a rock) makes it climb, move aside and try again.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from sim.robots.base import Robot
from sim.robots.hexacopter_control import HexacopterController, HexGains, SmoothedHeight
from slam.lie import wrap_angle
from slam.stereo import DEFAULT_MIN_DEPTH_M

if TYPE_CHECKING:
    from sim.scenario import RobotConfig
    from sim.world.terrain import Terrain

ROTOR_RADIUS_M = 0.28
ROTOR_ANGLES_DEG = (0, 60, 120, 180, 240, 300)
ROTOR_SPIN = (1, -1, 1, -1, 1, -1)
YAW_COEFF_M = 0.016
MAX_THRUST_N = 12.0
SKID_Z_M = -0.28  # landing skids: two tubes along x at y = +-SKID_Y_M
SKID_Y_M = 0.2
SKID_X_M = (-0.16, 0.08)
SKID_RADIUS_M = 0.01
STRUT_X_M = (-0.15, 0.05)
GEAR_HEIGHT_M = -SKID_Z_M + SKID_RADIUS_M  # body origin above ground when landed
MARKER_CENTRE = (-0.05, 0.102, -0.16)  # left tag; the right one is mirrored
STEREO_BASELINE_M = 0.12
CAMERA_TILT_DEG = 60.0
MARKER_SIZE_M = 0.12

CLIMB_RATE = 1.0  # m/s
DESCENT_RATE = 0.5
FINAL_DESCENT_RATE = 0.25  # below 1 m above ground
YAW_RATE = 0.8  # rad/s
ACCEL = 1.0  # m/s^2, carrot acceleration along a leg
TERRAIN_WINDOW_M = 1.0  # half-width of the terrain averaging window under the copter
ALTITUDE_REACHED_M = 0.15
LANDING_TARGET_AGL_M = -0.5  # the descent reference goes below the ground: touch down firmly
# landed: both skids touch something, level within LEVEL_RAD, sinking slower than
# TOUCHDOWN_SPEED, for TOUCHDOWN_HOLD_S; then the motors are cut
TOUCHDOWN_SPEED = 0.15  # m/s
TOUCHDOWN_HOLD_S = 0.5
LEVEL_RAD = math.radians(10)
# a skid caught on an edge tilts the body beyond ABORT_TILT_RAD: climb to RELAND_AGL_M,
# move RELAND_SHIFT_M away from the contact, descend again (at most MAX_RELANDINGS times)
ABORT_TILT_RAD = math.radians(15)
RELAND_AGL_M = 1.2
RELAND_SHIFT_M = 1.0
MAX_RELANDINGS = 3

NO_CONTACT = {"contype": 0, "conaffinity": 0}


class Ardea(Robot):
    preset = "ardea"
    default_hfov_deg = 80.0
    marker_count = 2  # left and right
    default_cores = 2  # dual-core (thesis 7.1)
    default_imu_preset = "adis16407"
    stereo_rig_names = ("up", "down")
    default_vo_rig = "down"
    max_speed_mps = 5.0  # chosen: at the position controller's 4 m/s^2 it brakes from 5 m/s within about 3 m
    # measured: the 99th percentile of its true velocity change (1.34 m/s) and attitude change
    # (43 deg) within one second of flight, at about two sigma (docs/estimation.md's made_stuck)
    motion_accel_density = 0.7
    motion_turn_density = 0.4
    antenna_height_m = 0.3
    ground_contact_geoms = ("skid_l", "skid_r")
    body_radius_m = ROTOR_RADIUS_M + 0.05  # arm ends around the rotor sites
    #: Its downward stereo matches from the matcher's minimum depth on, and closer ground
    #: (standing, taking off, landing) gives SGBM mismatches that put points up to 2 m off.
    #: The margin covers the camera's height on its legs and the terrain's relief below.
    min_mapping_height_m = DEFAULT_MIN_DEPTH_M + 0.3

    @classmethod
    def check_config(cls, cfg: RobotConfig) -> None:
        """The hexacopter's cameras are fixed: no head to tilt or sweep."""
        head = [k for k in ("scan_tilt_deg", "head_sweep_deg", "head_sweep_period_s") if getattr(cfg.route, k) is not None]
        if head:
            raise ValueError(f"route.{', route.'.join(head)} are for rovers with a pan-tilt head, not preset {cfg.preset}")
        super().check_config(cfg)

    def _build(self) -> None:
        root = self.mjcf_model
        base = root.worldbody
        base.add("geom", name="body", type="box", size=[0.1, 0.1, 0.04], mass=1.7, rgba=[0.2, 0.22, 0.25, 1])
        for k, (ang_deg, spin) in enumerate(zip(ROTOR_ANGLES_DEG, ROTOR_SPIN, strict=True)):
            a = math.radians(ang_deg)
            x, y = ROTOR_RADIUS_M * math.cos(a), ROTOR_RADIUS_M * math.sin(a)
            base.add("geom", type="capsule", fromto=[0, 0, 0.02, x, y, 0.02], size=[0.012], mass=0.1,
                     rgba=[0.15, 0.15, 0.15, 1])
            base.add("geom", type="cylinder", pos=[x, y, 0.045], size=[0.11, 0.004], mass=0.05,
                     rgba=[0.5, 0.5, 0.55, 0.5])
            base.add("site", name=f"rotor{k}", pos=[x, y, 0.04], size=[0.01], group=4)
            root.actuator.add("motor", name=f"rotor{k}", site=f"rotor{k}",
                              gear=[0, 0, 1, 0, 0, spin * YAW_COEFF_M],
                              ctrllimited=True, ctrlrange=[0, MAX_THRUST_N])
        for side in (1, -1):
            y = side * SKID_Y_M
            base.add("geom", name=f"skid_{'l' if side > 0 else 'r'}", type="capsule",
                     fromto=[SKID_X_M[0], y, SKID_Z_M, SKID_X_M[1], y, SKID_Z_M], size=[SKID_RADIUS_M], mass=0.06,
                     friction=[1.0, 0.005, 0.0001], rgba=[0.15, 0.15, 0.15, 1])
            for x in STRUT_X_M:
                base.add("geom", type="capsule", fromto=[x, side * 0.08, -0.04, x, y, SKID_Z_M], size=[0.007],
                         mass=0.02, rgba=[0.15, 0.15, 0.15, 1], **NO_CONTACT)

        tilt = math.radians(CAMERA_TILT_DEG)
        for rig, sign, z in (("up", 1, 0.03), ("down", -1, -0.03)):
            direction = [math.cos(tilt), 0, sign * math.sin(tilt)]
            self._add_stereo_pair(base, rig, centre=[0.11, 0, z], direction=direction, right=[0, -1, 0],
                                  baseline_m=STEREO_BASELINE_M)

        for k, side in enumerate((1, -1)):
            x, y, z = MARKER_CENTRE
            self._add_marker(base, k, MARKER_SIZE_M, pos=[x, side * y, z], normal=[0, side, 0])

    def _footprint(self) -> np.ndarray:
        z = SKID_Z_M - SKID_RADIUS_M
        return np.array([[x, side * SKID_Y_M, z] for x in SKID_X_M for side in (1, -1)])

    # ------------------------------------------------------------------ binding

    def _bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        body = self._body_id
        mass = float(model.body_subtreemass[body])
        iquat = model.body_iquat[body]
        ri = np.zeros(9)
        mujoco.mju_quat2Mat(ri, iquat)
        ri = ri.reshape(3, 3)
        inertia = ri @ np.diag(model.body_inertia[body]) @ ri.T
        com = model.body_ipos[body]
        self._skid_geoms = {model.geom(self._compiled(f"skid_{side}")).id for side in "lr"}
        self._rotor_act = np.array([model.actuator(self._compiled(f"rotor{k}")).id for k in range(6)])
        rotor_xy = np.array([model.site(self._compiled(f"rotor{k}")).pos[:2] for k in range(6)]) - com[:2]
        self.controller = HexacopterController(
            mass, inertia, rotor_xy, np.array(ROTOR_SPIN), YAW_COEFF_M, MAX_THRUST_N, HexGains()
        )
        self.mass = mass
        self._smoothed: tuple[Terrain, SmoothedHeight] | None = None
        self.landed = False
        self._last_t: float | None = None
        self._touchdown_t: float | None = None
        self._stop()

    # ------------------------------------------------------------------ helpers

    def ground_height(self, terrain: Terrain, xy) -> float:
        """Terrain height averaged over a 2 x 2 m window under ``xy`` (what the altitude
        is held over: a copter does not follow every pebble)."""
        if self._smoothed is None or self._smoothed[0] is not terrain:
            self._smoothed = (terrain, SmoothedHeight(terrain.heights, terrain.size_m, TERRAIN_WINDOW_M))
        return self._smoothed[1](xy[0], xy[1])

    def altitude(self, terrain: Terrain) -> float:
        """Height of the body origin above the averaged terrain under it (truth)."""
        pos, _ = self.pose()
        return float(pos[2] - self.ground_height(terrain, pos[:2]))

    def _skid_contacts(self) -> tuple[set[int], list[np.ndarray]]:
        """Which skids touch something (ground, rock, another robot), and where."""
        data = self.data
        contact = data.contact
        skids, points = set(), []
        for i in range(data.ncon):
            for g in (int(contact.geom1[i]), int(contact.geom2[i])):
                if g in self._skid_geoms:
                    skids.add(g)
                    points.append(contact.pos[i].copy())
        return skids, points

    def _land(self, t: float, pos: np.ndarray, vel: np.ndarray) -> bool:
        """Touchdown logic; True once landed (motors off).

        Landed: both skids touch something, the body is level within ``LEVEL_RAD`` and
        sinks slower than ``TOUCHDOWN_SPEED``, for ``TOUCHDOWN_HOLD_S``. A skid caught on
        an edge (another robot, a rock) tilts the body beyond ``ABORT_TILT_RAD``: then
        ARDEA climbs back to ``RELAND_AGL_M``, moves ``RELAND_SHIFT_M`` away from the
        contact and descends again (at most ``MAX_RELANDINGS`` times).
        """
        if self._relanding:
            done_moving = math.dist(self._ref_xy, self._goal_xy) < 1e-3
            if done_moving and abs(self._agl_ref - self._agl_target) < 1e-6:
                self._relanding = False
                self._agl_target = LANDING_TARGET_AGL_M
            return False
        skids, points = self._skid_contacts()
        roll, pitch, _ = self.roll_pitch_yaw()
        tilt = max(abs(roll), abs(pitch))
        if skids and tilt > ABORT_TILT_RAD and self._relandings < MAX_RELANDINGS:
            self._relandings += 1
            self._relanding = True
            away = pos[:2] - np.mean(points, axis=0)[:2]
            norm = float(np.hypot(*away))
            away = away / norm if norm > 1e-3 else self.rotation()[:2, 0]
            self._goal_xy = self._ref_xy + RELAND_SHIFT_M * away
            self._agl_target = RELAND_AGL_M
            self._agl_ref = max(self._agl_ref, pos[2] - self.ground_height(self._terrain, self._ref_xy))
            self._touchdown_t = None
            return False
        if len(skids) == len(self._skid_geoms) and tilt < LEVEL_RAD and abs(vel[2]) < TOUCHDOWN_SPEED:
            self._touchdown_t = t if self._touchdown_t is None else self._touchdown_t
            if t - self._touchdown_t > TOUCHDOWN_HOLD_S:
                self.landed = True
                self.phase = "done"
                self._stop()
                return True
        else:
            self._touchdown_t = None
        return False

    def _stop(self) -> None:
        self.data.ctrl[self._rotor_act] = 0.0

    # ------------------------------------------------------------------ control

    def _control(self, t: float, terrain: Terrain) -> None:
        self._terrain = terrain
        dt = 0.0 if self._last_t is None else t - self._last_t
        self._last_t = t
        pos, _ = self.pose()
        vel, omega = self.velocity()
        rot = self.rotation()
        _, _, yaw = self.roll_pitch_yaw()
        route = self.route

        if self.phase == "idle" and not self.route.records:
            self.phase, self.landed = "done", True  # no route: stays parked, motors off
        if self.phase == "idle":
            self.phase = "takeoff"
            self.controller.reset()
            self._ref_xy = pos[:2].copy()
            self._ref_v = np.zeros(2)
            self._agl_ref = pos[2] - self.ground_height(terrain, pos[:2])
            self._yaw_ref = yaw
            self._carrot_speed = 0.0
            self._goal_xy = pos[:2].copy()
            self._z_ref_prev: float | None = None
            self._agl_target = self.cfg.route.cruise_altitude_m
        if self.phase == "done" and self.landed:
            self._stop()
            return

        yaw_rate_ff = 0.0
        if (
            self.phase == "takeoff"
            and abs(self._agl_ref - self._agl_target) < 1e-6
            and abs(self.altitude(terrain) - self._agl_target) < ALTITUDE_REACHED_M
        ):
            self._next(t, pos)
        if self.phase == "fly":
            wp = route.target
            if route.distance(pos) < route.cfg.tolerance_m:
                route.reach(t, pos)
                if wp.scan:
                    self.phase = "scan"
                    self._scan_t0, self._scan_yaw0 = t, self._yaw_ref
                else:
                    self._next(t, pos)
            else:
                reason = route.check(t, pos)
                if reason is not None:
                    route.fail(t, pos, reason)
                    self._goal_xy = self._ref_xy.copy()
                    self._next(t, pos)
        if self.phase in ("fly", "scan", "landing", "done"):
            self._advance_carrot(dt)
        if self.phase == "scan":
            frac = (t - self._scan_t0) / self.cfg.route.scan_duration_s
            if frac >= 1.0:
                self._yaw_ref = wrap_angle(self._scan_yaw0)
                self._next(t, pos)
            else:
                self._yaw_ref = wrap_angle(self._scan_yaw0 + 2 * math.pi * frac)
                yaw_rate_ff = 2 * math.pi / self.cfg.route.scan_duration_s
        if self.phase == "landing" and self._land(t, pos, vel):
            return

        # altitude reference, rate-limited
        rate = CLIMB_RATE if self._agl_target > self._agl_ref else (
            FINAL_DESCENT_RATE if self._agl_ref < 1.0 else DESCENT_RATE)
        step = rate * dt
        self._agl_ref += min(max(self._agl_target - self._agl_ref, -step), step)
        # yaw along the leg
        if self.phase == "fly" and route.leg_length > 0.5 and yaw_rate_ff == 0.0:
            d = route.target_xy - route.leg_start_xy
            err = wrap_angle(math.atan2(d[1], d[0]) - self._yaw_ref)
            self._yaw_ref = wrap_angle(self._yaw_ref + min(max(err, -YAW_RATE * dt), YAW_RATE * dt))

        ground = self.ground_height(terrain, self._ref_xy)
        z_ref = ground + self._agl_ref
        vz_ref = 0.0 if self._z_ref_prev is None or dt <= 0 else (z_ref - self._z_ref_prev) / dt
        self._z_ref_prev = z_ref
        p_ref = np.array([self._ref_xy[0], self._ref_xy[1], z_ref])
        v_ref = np.array([self._ref_v[0], self._ref_v[1], vz_ref])
        thrusts = self.controller.update(max(dt, 1e-3), pos, vel, rot, omega, p_ref, v_ref, self._yaw_ref, yaw_rate_ff)
        self.data.ctrl[self._rotor_act] = thrusts

    def _advance_carrot(self, dt: float) -> None:
        """Move the reference point at up to ``speed_mps`` (accelerating and braking
        at ``ACCEL``) towards the goal: the current waypoint, or after reaching it
        (scan, landing, hover) the waypoint itself."""
        target = self._goal_xy
        delta = target - self._ref_xy
        remaining = math.hypot(delta[0], delta[1])
        if remaining < 1e-6:
            self._ref_v[:] = 0.0
            self._carrot_speed = 0.0
            return
        brake = math.sqrt(2 * ACCEL * remaining)
        speed = min(self.cfg.route.speed_mps, self._carrot_speed + ACCEL * dt, brake)
        self._carrot_speed = speed
        step = min(speed * dt, remaining)
        direction = delta / remaining
        self._ref_xy = self._ref_xy + direction * step
        self._ref_v = direction * speed

    def _next(self, t: float, pos: np.ndarray) -> None:
        if not self.route.done:
            self.phase = "fly"
            self.route.begin_leg(t, pos)
            self._goal_xy = self.route.target_xy.copy()
            altitude = self.route.target.altitude_m
            self._agl_target = self.cfg.route.cruise_altitude_m if altitude is None else altitude
        elif self.cfg.route.land:
            self.phase = "landing"
            self._agl_target = LANDING_TARGET_AGL_M
            self._touchdown_t = None
            self._relanding = False
            self._relandings = 0
        else:
            self.phase = "done"  # hover over the last goal

    @property
    def commands_motion(self) -> bool:
        """Rotors spinning: from take-off until landed (hovering counts)."""
        return self.phase != "idle" and not self.landed and not self.tipped_over

    @property
    def status(self) -> str:
        if self.phase == "done" and not self.tipped_over:
            base = super().status
            return base if self.landed or base != "done" else "done (hovering)"
        return super().status
