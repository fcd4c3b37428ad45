"""Stereo rig description shared by robot models (which mount cameras) and sensors
(which render them): rectified pinhole pairs, left camera as the reference."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: MuJoCo cameras look along -z with y up; OpenCV cameras along +z with y down: a MuJoCo
#: camera's rotation times this is the same camera in OpenCV axes (its own inverse).
MUJOCO_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class StereoRig:
    name: str  # rig label within the robot, e.g. "head" or "down"
    left_camera: str  # camera names in the compiled MuJoCo model
    right_camera: str
    baseline_m: float  # right camera sits at +baseline along the left camera's x (OpenCV, right)
    hfov_deg: float
    width: int
    height: int

    @property
    def focal_px(self) -> float:
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        """MuJoCo's camera ``fovy`` that gives ``hfov_deg`` with square pixels."""
        return math.degrees(2 * math.atan((self.height / 2) / self.focal_px))

    @property
    def intrinsics(self) -> np.ndarray:
        """3x3 K with the principal point at the image centre (MuJoCo's pinhole)."""
        f = self.focal_px
        return np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1.0]])
