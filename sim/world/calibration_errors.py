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
  to first order, a rotation of the camera and is covered by the rotation.
- **lens distortion left after rectification** acts on the images too: each camera's
  residual is a Brown-Conrady field (radial ``k1 r^2 + k2 r^4``, tangential ``p1``,
  ``p2``; the constant and linear terms are the rotation and focal errors above), drawn
  so that its expected RMS over the image is ``lens_distortion_mrad``; it grows towards
  the image's edges, where thesis 5.1.1 expects the calibration's error to be largest.
  :class:`LensDistortion` resamples :class:`sim.world.sensors.StereoRenderer`'s renders (the resampling
  itself is the interpolation error of real rectification, thesis 6.2.1). Left and
  right differ, so disparities err by a smooth field over the image that no single
  rotation of the rig explains.
- **camera-IMU extrinsics and pan-tilt encoder offsets** act on the transform the stack
  is given: :func:`believed_body_camera` turns the true ``T_body_cam`` into the one the
  robot computes. A pan offset is a rotation about the body's z axis before the head, a
  tilt offset one about the camera's x axis (the LRU's tilt axis), both fixed. The pan
  rotation is taken about the body origin; the LRU's mast stands 0.18 m from it, so the
  camera position error this neglects is 0.3 mm per 0.1 deg of offset.

- **a camera-IMU time offset** acts on the images' timing: the stack stamps each pair with
  its trigger time, the cameras take it ``time_offset_s`` later (the thesis's rigs are
  hardware-synchronised left to right, 7.2; how their images are stamped against the
  IMU's clock it does not say). :class:`sim.world.sensors.StereoRenderer` draws each pair
  from the cameras' poses that long after the trigger, extrapolated at their velocity;
  one offset per robot, the same for all its rigs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from sim.robots.base import Robot
from sim.scenario import CalibrationRealism
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from slam.lie import se3, so3_exp, so3_log

__all__ = [
    "CalibrationError",
    "LensDistortion",
    "RigError",
    "believed_body_camera",
    "distortion_term_stds",
    "draw_calibration_errors",
    "perturb_cameras",
]

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
    distortion: np.ndarray = field(default_factory=lambda: np.zeros((2, 4)))  # (k1, k2, p1, p2) of the left and right camera

    def lens_distortions(self, rig: StereoRig) -> tuple[LensDistortion, LensDistortion] | None:
        """The left and right camera's :class:`LensDistortion`; None when there is none."""
        if not np.any(self.distortion):
            return None
        f = rig.focal_px * self.focal_scale
        basis = _distortion_basis(*_normalised_grid(rig, f))
        left, right = (LensDistortion(np.tensordot(coefficients, basis, axes=1) * f) for coefficients in self.distortion)
        return left, right

    def disparity_offset_coefficients_px(self, rig: StereoRig) -> np.ndarray:
        """The coefficients ``c = f θ`` (px, (3,)) of the disparity offsets the right
        camera's rotation ``θ`` causes (slam.stereo.disparity_offset_sensitivity; the second,
        ``f θy``, is the offset at the image centre), ``f`` the true focal length."""
        return rig.focal_px * self.focal_scale * so3_log(self.R_right)

    def true_vfov_deg(self, rig: StereoRig) -> float:
        """MuJoCo ``fovy`` of the true cameras."""
        return math.degrees(2 * math.atan((rig.height / 2) / (rig.focal_px * self.focal_scale)))


class LensDistortion:
    """One camera's residual distortion applied to its renders: pixel ``u`` of the image it
    delivers shows the rendered image at ``u + shift(u)`` (bilinear). ``shift``: (2, H, W)
    in px, x then y.

    Resampled with weights computed once (0.4 ms per 320x240 grey image): ``cv2.remap`` rounds
    positions to 1/32 px, a quarter of the shifts modelled, and
    ``scipy.ndimage.map_coordinates`` computes its weights on every call (1.6 ms).
    """

    def __init__(self, shift: np.ndarray):
        self.shift = shift
        h, w = shift.shape[1:]
        v, u = np.mgrid[0:h, 0:w]
        x = np.clip(u + shift[0], 0, w - 1)
        y = np.clip(v + shift[1], 0, h - 1)
        col = np.minimum(np.floor(x).astype(np.intp), w - 2)
        row = np.minimum(np.floor(y).astype(np.intp), h - 2)
        a, b = (y - row).astype(np.float32).ravel(), (x - col).astype(np.float32).ravel()
        top_left = (row * w + col).ravel()
        self._neighbours = (top_left, top_left + 1, top_left + w, top_left + w + 1)
        self._weights = ((1 - a) * (1 - b), (1 - a) * b, a * (1 - b), a * b)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The distorted image (same shape; greyscale or colour, uint8)."""
        flat = image.reshape(image.shape[0] * image.shape[1], -1) if image.ndim == 3 else image.reshape(-1)
        weights = [w[:, None] for w in self._weights] if image.ndim == 3 else self._weights
        out = weights[0] * flat[self._neighbours[0]]
        for weight, neighbour in zip(weights[1:], self._neighbours[1:]):
            out += weight * flat[neighbour]
        return np.rint(out).astype(np.uint8).reshape(image.shape)


@dataclass(frozen=True)
class CalibrationError:
    """One robot's calibration errors: per rig, its pan-tilt encoder offsets (rad) and the
    time its images are taken after their stamps (s)."""

    rigs: dict[str, RigError]
    pan_offset_rad: float = 0.0
    tilt_offset_rad: float = 0.0
    time_offset_s: float = 0.0


def _normalised_grid(rig: StereoRig, focal_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's normalised image coordinates ``(x, y)``, (H, W) each, for the focal length ``focal_px``."""
    u, v = np.meshgrid(np.arange(rig.width, dtype=np.float64), np.arange(rig.height, dtype=np.float64))
    return (u - rig.intrinsics[0, 2]) / focal_px, (v - rig.intrinsics[1, 2]) / focal_px


def _distortion_basis(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The Brown-Conrady terms ``k1, k2, p1, p2`` at normalised image coordinates: (4, 2, *x.shape)."""
    r2 = x * x + y * y
    return np.stack([
        np.stack([x * r2, y * r2]),
        np.stack([x * r2 * r2, y * r2 * r2]),
        np.stack([2 * x * y, r2 + 2 * y * y]),
        np.stack([r2 + 2 * x * x, 2 * x * y]),
    ])


def distortion_term_stds(rig: StereoRig, rms_rad: float) -> np.ndarray:
    """Stds of ``(k1, k2, p1, p2)`` such that each term adds a quarter of the mean square
    residual over ``rig``'s image, whose expectation is then ``rms_rad ** 2``."""
    mean_square = (_distortion_basis(*_normalised_grid(rig, rig.focal_px)) ** 2).sum(axis=1).mean(axis=(1, 2))
    return rms_rad / np.sqrt(4 * mean_square)


def draw_calibration_errors(robot: Robot, cfg: CalibrationRealism, rng: np.random.Generator) -> CalibrationError:
    """Errors of ``robot``'s rigs and head, each component normal with the std ``cfg`` gives
    (the lens distortion's terms: :func:`distortion_term_stds`)."""
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
    if cfg.lens_distortion_mrad:  # drawn last: the other errors are the same with and without it
        for rig in robot.stereo_rigs:
            stds = distortion_term_stds(rig, cfg.lens_distortion_mrad * 1e-3)
            rigs[rig.name] = replace(rigs[rig.name], distortion=rng.standard_normal((2, 4)) * stds)
    time_offset = 0.0
    if cfg.camera_imu_time_offset_ms:  # after the lenses, for the same reason
        time_offset = float(rng.standard_normal()) * cfg.camera_imu_time_offset_ms * 1e-3
    return CalibrationError(rigs, float(pan), float(tilt), time_offset)


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
