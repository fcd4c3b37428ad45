"""Calibration errors: the true cameras differ from the ones the SLAM stack believes in.

The SLAM stack works with the nominal rig (:class:`sim.world.camera_rig.StereoRig`: a
perfectly rectified pinhole pair) and the camera-body transform its kinematics give
(thesis 4.1; on the LRU the pan-tilt head's encoders, thesis 7.1). A real robot's
calibration leaves residual errors and the rig changes after it (transport,
temperature). This module draws one robot's errors (:func:`draw_calibration_errors`,
from the scenario's ``realism.calibration`` stds, per robot and seed) and applies them
where they act:

- **stereo intrinsics and extrinsics** act on the images: :func:`perturb_cameras`
  changes the compiled MuJoCo cameras themselves (right camera's rotation and baseline,
  both cameras' focal length), so the renderer draws what the true rig sees while the
  stack rectifies and triangulates with the nominal one. A yaw error of the right camera
  shifts every disparity (a depth bias that grows with range, thesis eq. 5.2), a focal
  error scales the rotations VO measures. A principal point error of a rectified pair is,
  to first order, a rotation of the camera and is covered by the rotation; lens
  distortion residuals are not modelled.
- **camera-IMU extrinsics and pan-tilt encoder offsets** act on the transform the stack
  is given: :func:`believed_body_camera` turns the true ``T_body_cam`` into the one the
  robot computes. A pan offset is a rotation about the body's z axis before the head, a
  tilt offset one about the camera's x axis (the LRU's tilt axis), both fixed. The pan
  rotation is taken about the body origin; the LRU's mast stands 0.18 m from it, so the
  camera position error this neglects is 0.3 mm per 0.1 deg of offset.

A camera-IMU time offset is not modelled: the cameras are hardware-triggered with the
IMU (thesis 7.1), and the run samples sensors on the 5 ms control tick, coarser than the
offsets a synchronised rig has.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from sim.robots.base import Robot
from sim.scenario import CalibrationRealism
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from slam.lie import se3, so3_exp, so3_log

__all__ = ["CalibrationError", "RigError", "believed_body_camera", "draw_calibration_errors", "perturb_cameras"]

DEG = math.pi / 180.0


@dataclass(frozen=True)
class RigError:
    """One stereo rig's errors. ``R_right``: the right camera's true orientation in its
    nominal (rectified) frame, OpenCV axes; ``baseline_scale``, ``focal_scale``: true over
    believed; ``T_cam_error``: believed ``T_body_cam`` = true ``T_body_cam @ T_cam_error``."""

    R_right: np.ndarray = field(default_factory=lambda: np.eye(3))
    baseline_scale: float = 1.0
    focal_scale: float = 1.0
    T_cam_error: np.ndarray = field(default_factory=lambda: np.eye(4))

    def disparity_offset_coefficients_px(self, rig: StereoRig) -> np.ndarray:
        """The coefficients ``c = f θ`` (px, (3,)) of the disparity offsets the right
        camera's rotation ``θ`` causes (slam.stereo.disparity_offset_sensitivity; the second,
        ``f θy``, is the offset at the image centre), ``f`` the true focal length."""
        return rig.focal_px * self.focal_scale * so3_log(self.R_right)

    def true_vfov_deg(self, rig: StereoRig) -> float:
        """MuJoCo ``fovy`` of the true cameras."""
        return math.degrees(2 * math.atan((rig.height / 2) / (rig.focal_px * self.focal_scale)))


@dataclass(frozen=True)
class CalibrationError:
    """One robot's calibration errors: per rig, and its pan-tilt encoder offsets (rad)."""

    rigs: dict[str, RigError]
    pan_offset_rad: float = 0.0
    tilt_offset_rad: float = 0.0


def draw_calibration_errors(robot: Robot, cfg: CalibrationRealism, rng: np.random.Generator) -> CalibrationError:
    """Errors of ``robot``'s rigs and head, each component normal with the std ``cfg`` gives."""
    rigs = {}
    for rig in robot.stereo_rigs:
        draws = rng.standard_normal(12)
        rigs[rig.name] = RigError(
            R_right=so3_exp(draws[0:3] * cfg.stereo_rotation_deg * DEG),
            baseline_scale=1.0 + draws[3] * cfg.baseline_error,
            focal_scale=1.0 + draws[4] * cfg.focal_error,
            T_cam_error=se3(so3_exp(draws[5:8] * cfg.camera_imu_rotation_deg * DEG), draws[8:11] * cfg.camera_imu_translation_m),
        )
    pan = tilt = 0.0
    if robot.pan_tilt_head:
        pan, tilt = rng.standard_normal(2) * cfg.pan_tilt_offset_deg * DEG
    return CalibrationError(rigs, float(pan), float(tilt))


def perturb_cameras(model: mujoco.MjModel, robot: Robot, errors: CalibrationError) -> None:
    """Make the compiled model's cameras the true ones: the right camera of each rig turned
    by ``R_right`` and moved to the true baseline along the left camera's x, both
    cameras' ``fovy`` set from the true focal length."""
    for rig in robot.stereo_rigs:
        err = errors.rigs[rig.name]
        left, right = model.camera(rig.left_camera).id, model.camera(rig.right_camera).id
        model.cam_pos[right] = model.cam_pos[left] + (model.cam_pos[right] - model.cam_pos[left]) * err.baseline_scale
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.cam_quat[right])
        R_mj = MUJOCO_TO_OPENCV @ err.R_right @ MUJOCO_TO_OPENCV  # the same rotation in MuJoCo camera axes
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (R.reshape(3, 3) @ R_mj).ravel())
        model.cam_quat[right] = quat
        model.cam_fovy[[left, right]] = err.true_vfov_deg(rig)


def believed_body_camera(T_body_cam: np.ndarray, rig: StereoRig, errors: CalibrationError) -> np.ndarray:
    """The ``T_body_cam`` (OpenCV camera axes) the robot computes for the true one: its
    camera-IMU calibration error, and for a pan-tilt head the encoder offsets (pan about
    the body's z axis, tilt about the camera's x axis)."""
    T = T_body_cam @ errors.rigs[rig.name].T_cam_error
    if errors.pan_offset_rad or errors.tilt_offset_rad:
        T = se3(so3_exp([0.0, 0.0, errors.pan_offset_rad]), np.zeros(3)) @ T @ se3(so3_exp([errors.tilt_offset_rad, 0.0, 0.0]), np.zeros(3))
    return T
