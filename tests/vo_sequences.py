"""Rendered stereo sequences with ground-truth camera poses for the visual-odometry tests.

A robot drives (or flies) its route in a MuJoCo world built the way ``sim.run.runner``
builds it (``load_scenario`` -> ``generate_terrain`` -> ``make_robot`` ->
``build_world``); every ``1 / rate_hz`` seconds one rig is rendered with
``sim.world.sensors.StereoRenderer`` and the true pose of its left camera is recorded in the
OpenCV camera convention (x right, y down, z forward). MuJoCo cameras look along -z
with y up, so ``R_cv = R_mj diag(1, -1, -1)``.

Only the tests see these poses; ``slam.vo`` gets the images.
"""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

from dataclasses import dataclass, field

import sim  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
import numpy as np

from sim.robots import make_robot
from sim.scenario import load_scenario
from sim.world.calibration_errors import CalibrationError, RigError, perturb_cameras
from sim.world.sensors import StereoRenderer
from sim.world.terrain import generate_terrain
from sim.world.compose import build_world
from slam.stereo import StereoCalibration

MJ_TO_CV = np.diag([1.0, -1.0, -1.0])


@dataclass
class StereoSequence:
    name: str
    calib: StereoCalibration
    t: list[float]
    left: list[np.ndarray]
    right: list[np.ndarray]
    T_world_cam: list[np.ndarray]  # 4x4, left camera (OpenCV axes) in the simulator's world frame
    depth: list[np.ndarray] = field(default_factory=list)  # true z-depth of the left camera, when rendered

    def __len__(self) -> int:
        return len(self.t)

    def relative(self, i: int, j: int) -> np.ndarray:
        """True pose of frame j's left camera in frame i's left-camera frame."""
        return np.linalg.inv(self.T_world_cam[i]) @ self.T_world_cam[j]

    def path_length(self, i: int, j: int) -> float:
        p = np.array([T[:3, 3] for T in self.T_world_cam[i : j + 1]])
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def camera_pose(model, data, camera: str) -> np.ndarray:
    cid = model.camera(camera).id
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cid].reshape(3, 3) @ MJ_TO_CV
    T[:3, 3] = data.cam_xpos[cid]
    return T


TERRAIN = {"preset": "moon", "size_m": 24, "roughness_m": 0.05, "craters": {"count": 2, "radius_m": [1.5, 2.5]},
           "rocks": {"count": 10, "diameter_m": [0.15, 0.5]}, "texture": {"size_px": 1024}}

ROVER = {"name": "rover", "preset": "lru", "start": {"xy": [-5, -1], "yaw_deg": 0},
         "route": {"speed_mps": 0.4, "waypoints": [[-2, -1], [-2, 1.5]]}}

ROVER_SCAN = {"name": "rover", "preset": "lru", "start": {"xy": [-5, -1], "yaw_deg": 0},
              "route": {"speed_mps": 0.4, "scan_duration_s": 10, "scan_tilt_deg": 10,
                        "waypoints": [{"xy": [-4.7, -1], "scan": True}]}}

COPTER = {"name": "copter", "preset": "ardea", "start": {"xy": [-5, -2], "yaw_deg": 0},
          "route": {"speed_mps": 0.6, "cruise_altitude_m": 2.0, "waypoints": [[-1, -2], [1, 0.5]]}}


def render_sequence(robot: dict, rig_name: str, *, duration_s: float, rate_hz: float = 5.0, skip_s: float = 0.0,
                    seed: int = 5, terrain: dict | None = None, rig_error: RigError | None = None,
                    with_depth: bool = False) -> StereoSequence:
    """Drive ``robot`` (a scenario robot dict) for ``skip_s + duration_s`` seconds and
    render its rig ``rig_name`` at ``rate_hz`` after the first ``skip_s`` seconds;
    ``rig_error``: the true cameras differ from the nominal ones the sequence's
    calibration holds (sim/world/calibration_errors.py); ``with_depth``: keep the left
    camera's true depth images too."""
    sc = load_scenario({"name": "vo", "duration_s": skip_s + duration_s + 1, "seed": seed,
                        "terrain": terrain or TERRAIN, "robots": [robot]})
    clear = [(tuple(r.start.xy), 2.0) for r in sc.robots]
    clear += [(tuple(w.xy), 1.5) for r in sc.robots for w in r.route.waypoints]
    ter = generate_terrain(sc.terrain, np.random.default_rng(seed), clear)
    tags = sc.assigned_tag_ids()
    world = build_world(sc, ter, [make_robot(c, tags[c.name]) for c in sc.robots])
    bot = world.robots[0]
    rig = next(r for r in bot.stereo_rigs if r.name == rig_name)
    if rig_error is not None:
        perturb_cameras(world.model, bot, CalibrationError({r.name: rig_error if r is rig else RigError() for r in bot.stereo_rigs}))
    calib = StereoCalibration.from_intrinsics(rig.intrinsics, rig.baseline_m, rig.width, rig.height)
    seq = StereoSequence(f"{bot.preset}/{rig_name}", calib, [], [], [], [])
    if skip_s > 0:
        world.advance(skip_s)
    renderer = StereoRenderer(world.model, rig, sc.robots[0].camera, rig_error)
    try:
        for _ in range(round(duration_s * rate_hz)):
            world.advance(1.0 / rate_hz)
            frame = renderer.render(world.data, with_depth=with_depth)
            seq.t.append(float(world.data.time))
            seq.left.append(frame.left)
            seq.right.append(frame.right)
            seq.T_world_cam.append(camera_pose(world.model, world.data, rig.left_camera))
            if with_depth:
                seq.depth.append(frame.depth)
    finally:
        renderer.close()
    return seq
