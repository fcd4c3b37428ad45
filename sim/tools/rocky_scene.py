"""Submaps built from rendered stereo on sim.world.terrain's rocky terrain, for the matcher's
tests and benchmark (``sim.tools.match_bench``): a stereo head (LRU mast camera: b = 9 cm, 50.6 deg, 320x240,
1.2 m up, 25 deg down) is moved along straight paths; each pair is rendered, matched
by SGBM, classified (5.1.1) and integrated into a submap (5.1.2) with the true camera
poses, so the submaps carry only stereo and discretisation errors. The submap origin
is the gravity-aligned head pose at the path's start.

Two scenes (:data:`SCENES`): ``rocky``, 300 rocks of 0.3-1.0 m on gently rough ground,
and ``rough``, Etna-like ground (the etna preset's roughness and the Etna scenario's
craters, rock sizes and density: 40 rocks of 0.15-0.8 m on 400 m2) where rocks are few
and the ground itself carries the structure (thesis 9.3)."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cached_property

import mujoco
import numpy as np
from dm_control import mjcf

from sim.scenario import CameraConfig, TerrainConfig
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from sim.world.imaging import CameraImaging, ImagingParams
from sim.world.sensors import StereoRenderer
from sim.world.terrain import add_terrain, generate_terrain
from slam.lie import rot_z, se3
from slam.obstacles import ObstacleParams, classify_depth
from slam.stereo import StereoCalibration, StereoMatcher
from slam.submap import Submap, SubmapBuilder, SubmapParams

WIDTH, HEIGHT = 320, 240
BASELINE_M, HFOV_DEG = 0.09, 50.6
HEAD_HEIGHT_M, PITCH_DEG = 1.2, 25.0


# terrain keys (sim.scenario.TerrainConfig) of the scenes; ``rough`` follows etna_two_rovers.yaml
SCENES: dict[str, dict] = {
    "rocky": {"craters": {"count": 0}, "rocks": {"count": 300, "diameter_m": [0.3, 1.0]}},
    "rough": {
        "preset": "etna",
        "roughness_m": 0.07,
        "craters": {"count": 6, "radius_m": [1.0, 3.0], "depth_ratio": 0.15, "rim_height_ratio": 0.06},
        "rocks": {"count": 40, "diameter_m": [0.15, 0.8], "power_law_exponent": 2.2},
    },
}


class RockyScene:
    """A 20 m terrain of scene ``scene`` (``rocks`` overrides its rock count) and a mocap
    stereo head; with ``imaging`` (sim.world.imaging) its cameras' image formation
    (noise, exposure) acts on each rendered pair before SGBM."""

    def __init__(self, seed: int = 5, rocks: int | None = None, size_m: float = 20.0, scene: str = "rocky", imaging: ImagingParams | None = None):
        keys = SCENES[scene]
        rock_keys = keys["rocks"] | ({} if rocks is None else {"count": rocks})
        cfg = TerrainConfig.model_validate({**keys, "size_m": size_m, "rocks": rock_keys, "texture": {"size_px": 1024}})
        self.terrain = generate_terrain(cfg, np.random.default_rng(seed), [((0.0, 0.0), 0.1)])
        root = mjcf.RootElement(model="rocky")
        add_terrain(root, self.terrain)
        root.statistic.extent = size_m
        glob = getattr(root.visual, "global")
        glob.offwidth, glob.offheight = 640, 480
        self.rig = StereoRig("head", "left", "right", BASELINE_M, HFOV_DEG, WIDTH, HEIGHT)
        p = math.radians(PITCH_DEG)
        look = np.array([math.cos(p), 0.0, -math.sin(p)])
        x = np.array([0.0, -1.0, 0.0])
        y = np.cross(-look, x)
        head = root.worldbody.add("body", name="head", mocap=True)
        for name, sign in ((self.rig.left_camera, -0.5), (self.rig.right_camera, 0.5)):
            head.add("camera", name=name, pos=(sign * BASELINE_M * x).tolist(), xyaxes=[*x, *y], fovy=self.rig.vfov_deg)
        self.model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
        self.data = mujoco.MjData(self.model)
        self.camera = CameraConfig(width=WIDTH, height=HEIGHT)
        self.calibration = StereoCalibration.from_intrinsics(self.rig.intrinsics, BASELINE_M, WIDTH, HEIGHT)
        self.stereo = StereoMatcher(self.calibration)
        self.imaging = None if imaging is None else CameraImaging(
            imaging, WIDTH, HEIGHT, self.calibration.focal_px, np.random.default_rng(seed), flat_field=self.camera.flat_field
        )
        self._left = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, self.rig.left_camera)

    @cached_property
    def renderer(self) -> StereoRenderer:
        return StereoRenderer(self.model, self.rig, self.camera)

    def head_pose(self, xy, yaw: float) -> np.ndarray:
        """Gravity-aligned head pose (world) at ``xy``, ``HEAD_HEIGHT_M`` above the terrain."""
        z = float(self.terrain.height_at(*xy)) + HEAD_HEIGHT_M
        return se3(rot_z(yaw), [xy[0], xy[1], z])

    def view(self, T_world_head: np.ndarray):
        """Grey left image, SGBM depth and the left camera's world pose (OpenCV axes)."""
        left, depth, _, T_world_cam = self.view_with_true_depth(T_world_head, with_true_depth=False)
        return left, depth, T_world_cam

    def view_with_true_depth(self, T_world_head: np.ndarray, with_true_depth: bool = True):
        """:meth:`view` with the rendered z-depth of the left camera (inf: sky) before the pose."""
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, T_world_head[:3, :3].ravel())
        self.data.mocap_pos[0], self.data.mocap_quat[0] = T_world_head[:3, 3], q
        mujoco.mj_forward(self.model, self.data)
        frame = self.renderer.render(self.data, with_depth=with_true_depth)
        left, right = (frame.left, frame.right) if self.imaging is None else self.imaging.expose(frame.left, frame.right)
        depth = self.stereo.depth(left, right)
        T_world_cam = se3(self.data.cam_xmat[self._left].reshape(3, 3) @ MUJOCO_TO_OPENCV, self.data.cam_xpos[self._left])
        return left, depth, frame.depth, T_world_cam

    def submap(self, robot: str, index: int, start_xy, end_xy, images: int = 24, yaw_offset: float = 0.0) -> tuple[Submap, np.ndarray]:
        """A submap of a straight drive from ``start_xy`` to ``end_xy`` (head looking along
        the path, turned by ``yaw_offset``), and its true origin in the world."""
        start, end = np.asarray(start_xy, float), np.asarray(end_xy, float)
        yaw = math.atan2(*(end - start)[::-1]) + yaw_offset
        origin = self.head_pose(start, yaw)
        builder = SubmapBuilder(robot, SubmapParams(), self.calibration, frame_index=index)
        inv = np.linalg.inv(origin)
        for i in range(images):
            xy = start + (end - start) * i / (images - 1)
            image, depth, T_world_cam = self.view(self.head_pose(xy, yaw))
            T_origin_cam = inv @ T_world_cam
            classification = classify_depth(depth, self.calibration, T_origin_cam, ObstacleParams())
            builder.integrate(depth, T_origin_cam, classification.pixel_obstacles, image, 0.2 * i, classified=classification.pixel_classified)
        submap = builder.finish(0.2 * images, index + 1)
        return replace(submap, index=index), origin  # the builder numbers from 0

    def close(self) -> None:
        if "renderer" in self.__dict__:
            self.renderer.close()

