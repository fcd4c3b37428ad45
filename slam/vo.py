"""Keyframe-based stereo visual odometry (thesis 3.2 and 4.1.1, after Hirschmüller et al. 2002).

Pure module: numpy, scipy and OpenCV. Rectified stereo pairs (and optionally a dense
depth image) in, delta poses with covariances out; no simulator, no ground truth.

What it does per stereo pair
----------------------------
1. A keyframe holds corners of its left image (Shi-Tomasi, bucketed on a grid so they
   cover the image) with 3D points from stereo: from the caller's dense depth
   (``slam.stereo.StereoMatcher.depth``) or, without one, from sparse left-to-right
   KLT matches triangulated with ``slam.stereo.triangulate``. Points whose depth error
   (thesis eq. 5.2c) exceeds ``VoParams.max_point_error_m`` are dropped
   (``slam.stereo.max_depth_for_error``), as the thesis drops far stereo points (5.1.1).
2. The keyframe's corners are tracked into the current left image with pyramidal KLT
   straight from the keyframe image (no frame-to-frame drift of the features),
   initialised by projecting the 3D points with a constant-velocity prediction, and
   checked forward-backward.
3. PnP with RANSAC (``cv2.solvePnPRansac``) gives an inlier set; a weighted
   Gauss-Newton refinement then minimises the Mahalanobis reprojection error, where
   each point's 2x2 reprojection covariance holds the pixel noise of the current image
   and the stereo uncertainty of its 3D point (eq. 5.2, full 3x3 covariance from the
   triangulation Jacobian, whose diagonal is eq. 5.2a-c). Points are re-gated by
   chi-square on that Mahalanobis error.
4. The covariance of the delta is the inverse of the final Gauss-Newton information
   matrix, ``(J^T W J)^-1``: it comes from the pixel noise, the point depths and the
   inlier geometry of this very measurement (the "uncertainty estimates stemming from
   propagated measurement noise" of 4.1.1), not from a constant. Pixel noise averages
   out over the points; a calibration error does not, and it errs every delta alike. So
   each delta also carries its sensitivity to the rig's calibration errors (our
   addition): to a disparity offset common to all points
   (:func:`disparity_bias_sensitivity`, ``VoResult.disparity_sensitivity``), to a
   relative focal length error of both cameras (:func:`focal_scale_sensitivity`,
   ``VoResult.focal_sensitivity``: mostly a scale of the delta's rotation) and to the
   camera-IMU extrinsics (:func:`extrinsic_sensitivity`); the filter holds these errors as
   consider parameters (slam.filter, module docstring).
5. Keyframe policy: a history of ``n_keyframes`` (thesis 4.1.1: n = 5). The current
   frame becomes a keyframe when the inliers fall below a share of the keyframe's
   points or a minimum count, when the motion since the keyframe exceeds a translation
   or rotation threshold, or when tracking against the keyframe failed. When the
   active keyframe cannot be matched, the older keyframes of the history are tried
   (newest first); a good match re-activates the old keyframe, which keeps the
   estimate locally drift-free when the robot returns (Schmid et al. 2012 via 4.1.1).
6. The rig's disparity offsets (our addition, slam.stereo_offset): when a keyframe is
   replaced, its last measurement (the widest baseline) and sparse subpixel disparities
   of its corners (KLT along the rows, also with a dense depth) measure the right
   camera's rotation error, which offsets each pixel's disparity by its own amount
   (:func:`two_view_disparity_offset`); the fused estimate is taken off the disparities
   of every later keyframe (``StereoVO.disparity_offset``, for the caller's mapping too).

Failures are reported (``VoResult.ok = False`` with a reason), never papered over with
a pose: the local reference filter then carries on with IMU and wheel odometry (4.1.1).

Deviation from Hirschmüller et al. (2002): they match corners by correlation in both
stereo pairs, reject outliers by the invariance of 3D point distances under rigid
motion (with the distance error of thesis eq. 5.4) and solve 3D-3D. Here the current
frame needs no stereo at all (3D-2D: KLT + PnP-RANSAC), which is cheaper per frame and
weights each point by its own stereo error; the keyframe/history structure is the same.

Conventions
-----------
Camera frames as OpenCV (x right, y down, z forward); ``T_kf_cur`` is the 4x4 pose of
the current left camera in the keyframe's left-camera frame. Tangent vectors are
ordered ``[rotation (rx, ry, rz), translation (tx, ty, tz)]`` with the right
perturbation ``T = T_hat Exp(xi)``: to first order ``R = R_hat (I + [r]x)`` and
``t = t_hat + R_hat t_xi``, i.e. both parts are expressed in the current camera frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import cv2
import numpy as np
from scipy.stats import chi2

from slam.lie import adjoint, se3_inv
from slam.stereo import (
    DEFAULT_PIXEL_ERROR,
    StereoCalibration,
    disparity_offset_sensitivity,
    max_depth_for_error,
    remove_disparity_offset,
    row_offset_sensitivity,
    triangulate,
)
from slam.stereo_offset import DisparityOffsetEstimate
from slam.track_refinement import refine_tracks_affine


class VoException(Exception):
    """Bad input to the visual odometry (image shapes or types, parameters, frame order)."""


# --------------------------------------------------------------------------- parameters and results


class VoFailure(StrEnum):
    """Why a frame gave no delta (``VoResult.reason``); members equal their strings."""

    FIRST_FRAME = "first_frame"  # no keyframe yet: this frame became the first one
    NO_TEXTURE = "no_texture"  # fewer than ``min_features`` corners in the left image
    NO_DEPTH = "no_depth"  # corners, but too few with valid stereo depth for a keyframe
    TOO_FEW_MATCHES = "too_few_matches"  # fewer than ``min_inliers`` keyframe features tracked
    TOO_FEW_INLIERS = "too_few_inliers"  # PnP-RANSAC or the Mahalanobis gate left too few
    DEGENERATE = "degenerate"  # singular information matrix or std above the limits


#: A point's residual in the two-view adjustment has 3 degrees of freedom (two pixel coordinates, a disparity).
CHI2_3_MEDIAN = float(chi2.median(3))

#: What ``VoParams.disparity_offset_model`` may estimate of ``c = f θ`` (slam.stereo_offset): the
#: right camera's yaw alone (two views, :func:`two_view_disparity_offset`; roll and pitch held at
#: zero), or its whole rotation (pitch and roll from the stereo matches' rows as well,
#: :func:`row_offset_measurement`).
DISPARITY_OFFSET_MODELS = ("yaw", "rotation")


@dataclass(frozen=True)
class VoParams:
    """Parameters of :class:`StereoVO`. Pixel values are for the image resolution used."""

    # features (keyframes)
    max_features: int = 300  # corners per keyframe, spread by the grid
    grid_cols: int = 8  # bucketing grid: at most ceil(max_features / cells holding corners) corners per cell
    grid_rows: int = 6
    corner_quality: float = 0.01  # Shi-Tomasi quality level (relative to the best corner)
    min_corner_distance_px: float = 6.0
    border_px: int = 8  # no corners this close to the image border
    min_features: int = 20  # fewer corners than this in an image: "no_texture"
    # stereo points
    max_point_error_m: float = 0.5  # far-point cut by the depth error of eq. 5.2c
    min_depth_m: float = 0.3
    max_depth_jump: float = 0.05  # relative depth range in the 3x3 neighbourhood (dense depth): edges dropped
    stereo_max_row_error_px: float = 1.0  # sparse stereo: rows of a rectified match must agree
    stereo_max_disparity_gap_px: float = 1.0  # sparse stereo beside a dense depth: at most this far from its disparity
    # tracking
    klt_window_px: int = 15
    klt_levels: int = 3
    klt_fb_max_px: float = 0.5  # forward-backward consistency
    # pose
    ransac_threshold_px: float = 2.0
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999
    refine_iterations: int = 6  # weighted Gauss-Newton iterations (split around one re-gating)
    inlier_chi2: float = 9.21  # Mahalanobis gate on the reprojection error, chi-square 2 dof, 99 %
    min_inliers: int = 15  # fewer tracked features: "too_few_matches", fewer inliers: "too_few_inliers"
    max_rotation_std_rad: float = 0.05  # a delta less certain than this is "degenerate"
    max_translation_std_m: float = 0.25
    seed: int = 0  # cv2.setRNGSeed before each RANSAC
    # keyframe policy and history (thesis 4.1.1: n = 5)
    n_keyframes: int = 5
    keyframe_min_inlier_share: float = 0.5  # of the keyframe's 3D points
    keyframe_min_inliers: int = 60
    keyframe_max_translation_m: float = 0.5
    keyframe_max_rotation_deg: float = 10.0
    # noise (thesis 5.1.1: 0.5 px)
    pixel_noise_px: float = DEFAULT_PIXEL_ERROR
    # the rig's disparity offset (slam.stereo_offset): estimated and taken off the keyframes' points
    estimate_disparity_offset: bool = True
    disparity_offset_prior_px: float = 0.25  # the calibration's uncertainty of the offset (std; 0: none, not estimated)
    disparity_offset_gate_sigma: float = 3.0
    disparity_offset_model: str = "rotation"  # the right camera's whole rotation (3 coefficients) or its yaw alone (slam.stereo_offset)
    disparity_offset_pixel_noise_px: float = 0.1  # the offset's tracks, refined (slam.track_refinement): a floor, see two_view_disparity_offset
    disparity_offset_window_px: int = 21  # their affine patches
    disparity_offset_max_tracks: int = 48  # at most this many per keyframe, spread over the detection grid (their cost)

    def __post_init__(self):
        positive = ("max_features", "grid_cols", "grid_rows", "min_features", "max_point_error_m", "klt_window_px",
                    "klt_fb_max_px", "ransac_threshold_px", "ransac_iterations", "refine_iterations",
                    "inlier_chi2", "min_inliers", "n_keyframes", "pixel_noise_px", "disparity_offset_gate_sigma",
                    "disparity_offset_pixel_noise_px", "disparity_offset_max_tracks")
        bad = [f"{k}={getattr(self, k)}" for k in positive if not getattr(self, k) > 0]
        if not self.disparity_offset_prior_px >= 0:
            bad.append(f"disparity_offset_prior_px={self.disparity_offset_prior_px} (must be >= 0)")
        if bad:
            raise VoException(f"VoParams must be positive: {', '.join(bad)}")
        if self.min_inliers < 4:
            raise VoException(f"min_inliers must be >= 4 (PnP with RANSAC), got {self.min_inliers}")
        if self.disparity_offset_model not in DISPARITY_OFFSET_MODELS:
            raise VoException(f"disparity_offset_model must be one of {list(DISPARITY_OFFSET_MODELS)}, got {self.disparity_offset_model!r}")
        if self.disparity_offset_window_px < 5 or self.disparity_offset_window_px % 2 == 0:
            raise VoException(f"disparity_offset_window_px must be odd and at least 5, got {self.disparity_offset_window_px}")
        if not 0 <= self.keyframe_min_inlier_share <= 1:
            raise VoException(f"keyframe_min_inlier_share must be in [0, 1], got {self.keyframe_min_inlier_share}")


@dataclass(frozen=True)
class VoResult:
    """One processed stereo pair. ``T_kf_cur``/``cov`` are None unless ``ok``."""

    t: float  # capture time of the current frame
    frame_id: int  # id given by the caller for this frame
    ok: bool
    reason: VoFailure | None  # when not ok (a StrEnum: equal to "no_texture", "too_few_inliers", ...)
    keyframe_id: int | None  # frame_id of the keyframe the delta refers to
    T_kf_cur: np.ndarray | None  # 4x4 pose of the current left camera in the keyframe's left-camera frame
    cov: np.ndarray | None  # 6x6, tangent [rx, ry, rz, tx, ty, tz], right perturbation T = T_hat Exp(xi)
    inliers: int
    keypoints: np.ndarray  # (n, 2) inlier pixel positions in the current left image
    new_keyframe: bool  # this frame became the (active) keyframe
    keyframe_history: tuple[int, ...]  # frame_ids of the kept keyframes, newest last
    matches: int = 0  # tracked features before PnP (diagnostics)
    disparity_sensitivity: np.ndarray | None = None  # (6,) how T_kf_cur moves per pixel of disparity offset (:func:`disparity_bias_sensitivity`)
    map_cov: np.ndarray | None = None  # 6x6 share of ``cov`` from the keyframe's points, alike in all its deltas (:func:`map_covariance`)
    focal_sensitivity: np.ndarray | None = None  # (6,) how T_kf_cur moves per unit of relative focal error (:func:`focal_scale_sensitivity`)


@dataclass
class _Keyframe:
    frame_id: int
    t: float
    image: np.ndarray  # grey left image, KLT's reference
    uv: np.ndarray  # (n, 2) float32 corners in the left image
    X: np.ndarray  # (n, 3) points in the keyframe's left-camera frame
    cov_X: np.ndarray  # (n, 3, 3) their stereo covariance
    T_odo: np.ndarray  # 4x4 pose in the VO's own chained frame (used for predictions only)
    T_prior: np.ndarray | None = None  # 4x4 pose the caller predicted for it (``StereoVO.process``), predictions only
    disparity: np.ndarray | None = None  # (n,) its corners' disparities by sparse stereo (px), NaN where none


@dataclass
class _Measurement:
    ok: bool
    reason: VoFailure | None
    T: np.ndarray | None = None
    cov: np.ndarray | None = None
    inlier_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    matches: int = 0
    disparity_sensitivity: np.ndarray | None = None
    map_cov: np.ndarray | None = None
    inlier_ids: np.ndarray | None = None  # the inliers' indices among the keyframe's points
    focal_sensitivity: np.ndarray | None = None


# --------------------------------------------------------------------------- geometry helpers
# Rigid-body geometry lives in slam/lie.py. The rotation-vector conversions below stay
# OpenCV's ``cv2.Rodrigues`` (the convention of solvePnP's ``rvec``): it agrees with
# ``lie.so3_exp`` only to the last bit, and its logarithm returns zero below about
# 1e-5 rad, so switching to slam/lie.py would change the refined poses in the last bits.


def delta_in_body_frame(
    T_kf_cur: np.ndarray, cov: np.ndarray, T_body_cam_kf: np.ndarray, T_body_cam_cur: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """A camera delta as the delta of the body frames it was mounted on (e.g. the filter's
    IMU frame): ``T_b = X_kf T_kf_cur X_cur^-1`` with the camera extrinsics ``X`` (4x4
    ``T_body_cam`` at the keyframe's and at the current capture; they differ on a
    moving pan-tilt head). With ``T = T_hat Exp(xi)``, ``T_b = T_b_hat Exp(Ad_{X_cur} xi)``,
    so the covariance becomes ``Ad cov Ad^T`` in the same right-perturbation convention."""
    X_kf = np.asarray(T_body_cam_kf, dtype=float)
    X_cur = X_kf if T_body_cam_cur is None else np.asarray(T_body_cam_cur, dtype=float)
    Ad = adjoint(X_cur)
    return X_kf @ T_kf_cur @ se3_inv(X_cur), Ad @ cov @ Ad.T


def extrinsic_sensitivity(T_kf_cur: np.ndarray, T_body_cam: np.ndarray) -> np.ndarray:
    """How the body delta of :func:`delta_in_body_frame` errs with a fixed error ``e`` of
    the calibrated camera pose ``X_true = X Exp(e)`` (6, ``[rotation, translation]``, camera
    tangent): ``T_b = T_b_true Exp(J e)`` to first order, ``J = -Ad_X (Ad_{T^-1} - I)``
    (6x6). The true body delta is that of ``Exp(e) T Exp(-e) = T Exp((Ad_{T^-1} - I) e)``;
    ``J`` grows with the delta's rotation and translation and vanishes for no motion. The
    filter holds ``e`` as consider parameters (slam.filter, module docstring): one error
    for all deltas, where a covariance per delta would average it out. On a pan-tilt
    head that moved between the two captures, ``e`` is taken as the same in both camera
    frames (the head's own offsets then differ between them: an approximation)."""
    A = adjoint(se3_inv(np.asarray(T_kf_cur, dtype=float))) - np.eye(6)
    return -adjoint(np.asarray(T_body_cam, dtype=float)) @ A


def stereo_point_covariance(X: np.ndarray, calib: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR) -> np.ndarray:
    """Full 3x3 covariances (n, 3, 3) of triangulated points (n, 3), first-order
    propagation of independent pixel noise ``Δp`` on ``(u_l, v_l, u_r, v_r)`` through
    ``slam.stereo.triangulate`` (Hirschmüller 2003). With ``1/d = z/(f b)``, the
    Jacobian rows are ``z/(f b) [b - x, 0, x, 0]``, ``z/(f b) [-y, b/2, y, b/2]`` and
    ``z/(f b) [-z, 0, z, 0]``; its diagonal is thesis eq. 5.2a-c, the off-diagonal
    terms hold the strong x-z and y-z correlation along the viewing ray."""
    X = np.asarray(X, dtype=float)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    b = calib.baseline_m
    zero = np.zeros_like(z)
    A = np.stack([np.stack([b - x, zero, x, zero], -1), np.stack([-y, np.full_like(z, b / 2), y, np.full_like(z, b / 2)], -1),
                  np.stack([-z, zero, z, zero], -1)], axis=1)  # (n, 3, 4)
    k = (pixel_error * z / calib.fb) ** 2
    return k[:, None, None] * np.einsum("nik,njk->nij", A, A)


def _reprojection(T: np.ndarray, X: np.ndarray, cov_X: np.ndarray, uv: np.ndarray, K: np.ndarray, s2: float):
    """Residuals ``r`` (n, 2), Jacobians ``J`` (n, 2, 6) for the right perturbation of ``T``,
    weights ``W`` (n, 2, 2) and ``J_p R^T`` (n, 2, 3, the residual's derivative by ``-X``)
    of keyframe points ``X`` seen at ``uv`` from the camera at ``T`` (see :func:`refine_pose`)."""
    f = K[0, 0]
    R, t = T[:3, :3], T[:3, 3]
    Xc = (X - t) @ R  # R^T (X - t)
    zi = 1.0 / Xc[:, 2]
    r = uv - (f * Xc[:, :2] * zi[:, None] + K[:2, 2])
    Jp = np.zeros((len(X), 2, 3))
    Jp[:, 0, 0] = Jp[:, 1, 1] = f * zi
    Jp[:, :, 2] = -f * Xc[:, :2] * (zi**2)[:, None]
    JpRt = Jp @ R.T  # J_p R^T
    C = JpRt @ cov_X @ JpRt.transpose(0, 2, 1)
    C[:, 0, 0] += s2
    C[:, 1, 1] += s2
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    W = np.empty_like(C)
    W[:, 0, 0], W[:, 1, 1] = C[:, 1, 1] / det, C[:, 0, 0] / det
    W[:, 0, 1] = W[:, 1, 0] = -0.5 * (C[:, 0, 1] + C[:, 1, 0]) / det
    # J = J_p [[X_c]x, -I]: columns of [X_c]x written out
    J = np.zeros((len(X), 2, 6))
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    for k in range(2):
        a, b_, cz = Jp[:, k, 0], Jp[:, k, 1], Jp[:, k, 2]
        J[:, k, 0] = b_ * z - cz * y
        J[:, k, 1] = cz * x - a * z
        J[:, k, 2] = a * y - b_ * x
    J[:, :, 3:] = -Jp
    return r, J, W, JpRt


def _retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T Exp(xi)`` to first order in the translation, as :func:`refine_pose` steps: the
    rotation by OpenCV's Rodrigues (see the note above), the translation ``t + R xi_t``."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.asarray(xi[:3], dtype=float).reshape(3, 1))[0]
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:6]
    return out


def refine_pose(
    T: np.ndarray,
    X: np.ndarray,
    cov_X: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    pixel_noise_px: float,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted Gauss-Newton on the reprojection error of keyframe points ``X`` (n, 3)
    seen at ``uv`` (n, 2) in the current image, starting at ``T`` (current camera in the
    keyframe frame).

    Per point, ``C_i = Δp^2 I + J_p R^T Σ_X R J_p^T`` (pixel noise plus the projected
    stereo covariance ``Σ_X``), ``W_i = C_i^-1``; the step solves
    ``(Σ J_i^T W_i J_i) xi = Σ J_i^T W_i r_i`` with ``J_i = J_p [[X_c]x, -I]`` for the
    right perturbation ``T = T_hat Exp(xi)``. Returns ``(T, H, r, W)``: the refined
    pose, the information matrix ``H = J^T W J`` at it (its inverse is the covariance of
    the delta), residuals (n, 2) and weights (n, 2, 2).
    """
    T = np.array(T, dtype=float)
    s2 = pixel_noise_px**2
    for it in range(iterations + 1):
        r, J, W, _ = _reprojection(T, X, cov_X, uv, K, s2)
        WJ = W @ J  # (n, 2, 6)
        H = J.reshape(-1, 6).T @ WJ.reshape(-1, 6)
        if it == iterations:
            return T, H, r, W
        g = WJ.reshape(-1, 6).T @ r.reshape(-1)
        try:
            xi = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return T, H, r, W
        T = _retract(T, xi)
        if np.linalg.norm(xi) < 1e-10:
            iterations = it + 1  # converged: one more pass for H at the solution
    raise AssertionError("unreachable")


def disparity_bias_sensitivity(
    T: np.ndarray, X: np.ndarray, cov_X: np.ndarray, uv: np.ndarray, K: np.ndarray, pixel_noise_px: float, fb: float, linearised: tuple | None = None
) -> np.ndarray:
    """How the refined pose moves (6-vector, the tangent of :func:`refine_pose`) per pixel of
    a disparity offset common to all keyframe points: a residual yaw of the rectified
    pair, which no per-point noise model averages out. With ``d = f b / z``, an offset
    ``δ`` moves each point by ``dX/dδ = -X z / (f b)``; at the solution the pose moves by
    ``H^-1 Σ J_i^T W_i dr_i/dδ`` with ``dr_i/dδ = J_p R^T X_i z_i / (f b)`` (the
    Gauss-Newton step of the perturbed problem). ``σ_δ^2 s s^T`` is then the delta's
    covariance from the calibration's uncertainty; the offset is the same in every delta,
    so the filter holds it as a consider parameter in Schmidt's sense (the estimate does
    not solve for it). ``linearised``: :func:`_reprojection` at ``T``, when the caller has it."""
    _, J, W, JpRt = linearised or _reprojection(T, X, cov_X, uv, K, pixel_noise_px**2)
    return _pose_shift(J, W, np.einsum("nij,nj->ni", JpRt, X * (X[:, 2] / fb)[:, None]))


def _pose_shift(J: np.ndarray, W: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step ``H^-1 Σ J_i^T W_i dr_i`` by which the refined pose moves when
    every residual moves by ``dr_i`` (n, 2): the pose's sensitivity to a calibration error."""
    H = J.reshape(-1, 6).T @ (W @ J).reshape(-1, 6)
    return np.linalg.solve(H, np.einsum("nki,nkl,nl->i", J, W, dr))


def focal_scale_sensitivity(
    T: np.ndarray, X: np.ndarray, cov_X: np.ndarray, uv: np.ndarray, K: np.ndarray, pixel_noise_px: float, linearised: tuple | None = None
) -> np.ndarray:
    """How the refined pose moves (6-vector, the tangent of :func:`refine_pose`) per unit of
    a relative focal length error ``ε`` common to both cameras (true focal ``f (1 + ε)``, the
    stack's ``f``): a calibration error that, like the disparity offset, errs every delta
    alike. The keyframe's triangulated points come out ``(x, y, z / (1 + ε))`` (lateral
    coordinates exact, depth scaled: ``dX/dε = (0, 0, -z)``) and the current image's pixels
    lie ``ε (u - c)`` further from the principal point, so at the true pose the residuals
    move by ``dr_i/dε = (uv_i - c) + J_p R^T (0, 0, z_i)`` and the pose by ``H^-1 Σ J_i^T W_i
    dr_i/dε`` (the Gauss-Newton step of the perturbed problem, as
    :func:`disparity_bias_sensitivity`). Mostly a scale of the delta's rotation (a turn of
    ``θ`` reads about ``θ (1 + ε)``): a fixed focal error turns a net turn into a heading
    error that no per-delta covariance averages out; the filter holds ``ε`` as a consider
    parameter (slam.filter, module docstring). ``linearised``: :func:`_reprojection` at
    ``T``, when the caller has it."""
    _, J, W, JpRt = linearised or _reprojection(T, X, cov_X, uv, K, pixel_noise_px**2)
    return _pose_shift(J, W, (uv - K[:2, 2]) + JpRt[:, :, 2] * X[:, 2:3])


def two_view_disparity_offset(
    T: np.ndarray, uv0: np.ndarray, disparity: np.ndarray, uv1: np.ndarray, calib: StereoCalibration,
    pixel_noise_px: float, axes: tuple[int, ...] = (0, 1, 2), iterations: int = 5, gate: float = 4.0,
    held: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The rig's disparity offset coefficients ``c = f θ`` (px, (3,): the right camera's
    rotation error, measured disparities exceed the true ones by ``s_i · c``,
    :func:`slam.stereo.disparity_offset_sensitivity`) from one keyframe and one later
    image of the same rig, with their information (3x3, 1 / px^2); None when the pair
    holds none (no translation, too few points). Our addition (slam.stereo_offset).

    A two-view bundle adjustment: unknowns the pose ``T`` of the later camera in the
    keyframe (right perturbation, as :func:`refine_pose`), ``c`` and each point's true
    disparity ``d_i`` on its keyframe ray through ``uv0_i``; measurements the keyframe's
    disparities ``disparity_i = d_i + s_i · c`` (noise ``sqrt 2 Δp``, eq. 5.2's model) and
    the later image's pixels ``uv1_i`` (``Δp``). Only the coefficients in ``axes`` are
    unknowns, the others held at ``held`` (default zero; their rows and columns of the
    information zero, their entries of the returned estimate ``held``'s).
    Gauss-Newton with the points eliminated by their Schur complement (one unknown each),
    the inverse of the reduced ``6 + k`` square system giving ``c``'s information. After
    two iterations, points whose residual exceeds ``gate`` standard deviations are dropped.
    ``pixel_noise_px`` is a floor: when the residuals scatter more (their chi-square over
    its ``2 n - 6 - k`` degrees of freedom above 1, the a-posteriori variance factor), the
    information is divided by that factor. Solving for the disparities matters: the offset
    estimated instead from the reprojection linearised at the measured points (the
    derivative of :func:`disparity_bias_sensitivity`, the pose eliminated) was biased by
    about ``-0.9 σ_d^2`` px (``σ_d`` the disparity noise; synthetic points, while this was
    written), -0.1 to -0.2 px on realistic Etna images, the size of the offsets themselves;
    this one is not (tests/test_vo.py).

    A roll and a pitch are seen only weakly here: on a narrow rig looking at the ground
    they change the points' depths much as a tilted ground would, and on a rendered Etna
    drive (60 s, the LRU's head at 320x240, nominal rig) KLT's and the affine tracks' own
    errors of about 0.01 px made them 0.25 and 0.06 px (3 and 0.5 of their stated
    standard deviations), and a true roll of -0.48 px left out of the model pulled the
    yaw's estimate to -0.18 px against its true 0. The stereo matches' rows show both
    directly (:func:`row_offset_measurement`), so the VO holds them there."""
    f, fb = calib.focal_px, calib.fb
    ray = np.stack([(uv0[:, 0] - calib.cx) / f, (uv0[:, 1] - calib.cy) / f, np.ones(len(uv0))], axis=1)
    d = np.asarray(disparity, dtype=float).copy()
    ok = np.isfinite(d) & (d > 0)
    ray, measured, uv1 = ray[ok], d[ok], np.asarray(uv1, dtype=float)[ok]
    axes = list(axes)
    k = len(axes)
    sens_all = disparity_offset_sensitivity(uv0[ok, 0], uv0[ok, 1], measured, calib)
    fixed = np.zeros(3) if held is None else np.asarray(held, dtype=float).copy()
    fixed[axes] = 0.0
    measured = measured - sens_all @ fixed  # the held coefficients' offsets taken off
    d = measured.copy()
    sens = sens_all[:, axes]
    w_img, w_disp = 1.0 / pixel_noise_px**2, 0.5 / pixel_noise_px**2
    T, c = np.array(T, dtype=float), np.zeros(k)
    K, no_cov = calib.K, np.zeros((len(d), 3, 3))  # the points' errors are unknowns here, not covariances
    S = None
    for it in range(iterations):
        if len(d) < 8 or np.any(d <= 0):
            return None
        X = ray * (fb / d)[:, None]
        if np.any((X - T[:3, 3]) @ T[:3, 2] <= 0):  # behind the later camera
            return None
        r, J, _, JpRt = _reprojection(T, X, no_cov[: len(d)], uv1, K, 1.0)  # r_new = r - J xi
        s = measured - d - sens @ c
        if it == 2:  # gate once the estimate has settled, on the residuals' own scale when wider than the floor's
            e2 = np.sum(r * r, axis=1) * w_img + s * s * w_disp
            keep = e2 < gate**2 * max(1.0, float(np.median(e2)) / CHI2_3_MEDIAN)
            ray, measured, d, uv1, sens, X, s, r, J, JpRt = (v[keep] for v in (ray, measured, d, uv1, sens, X, s, r, J, JpRt))
            if len(d) < 8:
                return None
        a = -np.einsum("nij,nj->ni", JpRt, X / d[:, None])  # d(pixel)/d(d_i): X = ray f b / d
        H_cc = np.zeros((6 + k, 6 + k))
        H_cc[:6, :6] = w_img * np.einsum("nki,nkj->ij", J, J)
        H_cc[6:, 6:] = w_disp * sens.T @ sens
        H_cp = np.empty((len(d), 6 + k))
        H_cp[:, :6] = w_img * np.einsum("nki,nk->ni", J, a)
        H_cp[:, 6:] = w_disp * sens
        H_pp = w_img * np.sum(a * a, axis=1) + w_disp
        g_c = np.empty(6 + k)
        g_c[:6] = w_img * np.einsum("nki,nk->i", J, r)
        g_c[6:] = w_disp * sens.T @ s
        g_p = w_img * np.sum(a * r, axis=1) + w_disp * s
        S = H_cc - (H_cp / H_pp[:, None]).T @ H_cp
        chi_square = w_img * float(np.sum(r * r)) + w_disp * float(s @ s)  # at this iteration's start
        try:
            step = np.linalg.solve(S, g_c - H_cp.T @ (g_p / H_pp))
        except np.linalg.LinAlgError:
            return None
        d = d + (g_p - H_cp @ step) / H_pp
        T = _retract(T, step[:6])
        c = c + step[6:]
    try:
        info = np.linalg.inv(np.linalg.inv(S)[6:, 6:]) / max(1.0, chi_square / (2 * len(d) - 6 - k))
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(info)) and np.trace(info) > 1e-6 and np.linalg.cond(S) < 1e12):
        return None
    full_c, full_info = fixed, np.zeros((3, 3))
    full_c[axes], full_info[np.ix_(axes, axes)] = c, 0.5 * (info + info.T)
    return full_c, full_info


def row_offset_measurement(
    uv: np.ndarray, disparity: np.ndarray, row_offset: np.ndarray, calib: StereoCalibration, pixel_noise_px: float,
    yaw_px: float = 0.0, gate: float = 4.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The right camera's pitch and roll coefficients (``c_x``, ``c_z`` of ``c = f θ``, px)
    from one image's stereo matches, with their information (3x3, 1 / px^2, the yaw's row
    and column zero); None with fewer than 8 matches. Our addition (slam.stereo_offset).

    A match's right row lies ``r · c`` below its left row
    (:func:`slam.stereo.row_offset_sensitivity`): a linear least-squares fit of ``c_x`` and
    ``c_z`` to the measured row offsets ``row_offset`` (right row less left row, px; NaN
    where none) of the left pixels ``uv`` with their ``disparity``, after the yaw's small
    share (``-x y yaw_px``) is taken off. Matches beyond ``gate`` robust standard deviations
    of the residuals are dropped (three passes). The residuals' variance, at least
    ``pixel_noise_px^2``, weighs the fit: on rendered Etna drives (KLT matches at 320x240)
    the residuals scatter by 0.03-0.04 px but the keyframes' estimates by about twice what
    that would give, so the floor (the VO's 0.1 px for refined tracks) keeps the stated
    information near the keyframes' real scatter."""
    uv, disparity, row_offset = np.asarray(uv, float), np.asarray(disparity, float), np.asarray(row_offset, float)
    ok = np.isfinite(row_offset) & np.isfinite(disparity)
    if ok.sum() < 8:
        return None
    r = row_offset_sensitivity(uv[ok, 0], uv[ok, 1], disparity[ok], calib)
    A, b = r[:, [0, 2]], row_offset[ok] - r[:, 1] * yaw_px
    keep = np.ones(len(b), dtype=bool)
    for _ in range(3):
        c = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
        residual = b - A @ c
        sigma = max(pixel_noise_px, 1.4826 * float(np.median(np.abs(residual[keep]))))
        keep = np.abs(residual) < gate * sigma
        if keep.sum() < 8:
            return None
    c = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
    residual = b[keep] - A[keep] @ c
    variance = max(pixel_noise_px**2, float(residual @ residual) / (keep.sum() - 2))
    full_c, full_info = np.zeros(3), np.zeros((3, 3))
    full_c[[0, 2]], full_c[1] = c, yaw_px
    full_info[np.ix_([0, 2], [0, 2])] = A[keep].T @ A[keep] / variance
    return full_c, full_info


def map_covariance(
    T: np.ndarray, X: np.ndarray, cov_X: np.ndarray, uv: np.ndarray, K: np.ndarray, pixel_noise_px: float, linearised: tuple | None = None
) -> np.ndarray:
    """The share of the refined pose's covariance ``H^-1`` (:func:`refine_pose`) that comes
    from the keyframe's 3D points (their stereo covariance ``Σ_X``, eq. 5.2) rather than from
    the pixel noise of the current image: with ``C_i = Δp^2 I + P_i`` (``P_i`` the projected
    ``Σ_X``), the estimate's error is ``H^-1 Σ J_i^T W_i e_i`` and its covariance splits into
    ``Δp^2 H^-1 (Σ J_i^T W_i W_i J_i) H^-1`` (pixel noise, new in every frame) and the rest,
    returned here (6x6, the tangent of :func:`refine_pose`). The points' errors are those of
    the keyframe, the same in every delta measured against it, so that share does not
    average out over the deltas of one keyframe (our addition: thesis 4.1.1 fuses each
    delta with its whole covariance, as if the deltas were independent). ``linearised``: as
    for :func:`disparity_bias_sensitivity`."""
    _, J, W, _ = linearised or _reprojection(T, X, cov_X, uv, K, pixel_noise_px**2)
    WJ = W @ J
    H = J.reshape(-1, 6).T @ WJ.reshape(-1, 6)
    Hinv = np.linalg.inv(H)
    pixel = pixel_noise_px**2 * Hinv @ (WJ.reshape(-1, 6).T @ WJ.reshape(-1, 6)) @ Hinv
    lam, V = np.linalg.eigh(0.5 * ((Hinv - pixel) + (Hinv - pixel).T))
    return (V * np.maximum(lam, 0.0)) @ V.T


# --------------------------------------------------------------------------- the odometry


class StereoVO:
    """Keyframe stereo visual odometry for one rectified rig (see the module docstring).

    Call :meth:`process` once per stereo pair, in capture order. The caller (the local
    reference filter's owner) clones the filter state at each capture and keeps the
    clones of the frames listed in ``VoResult.keyframe_history``; each ``ok`` result is
    a delta pose between the clone of ``keyframe_id`` and the clone of ``frame_id``.
    """

    def __init__(self, calib: StereoCalibration, params: VoParams = VoParams()):
        self.calib = calib
        self.params = params
        self.K = calib.K
        self.history: list[_Keyframe] = []  # oldest first
        self.active: _Keyframe | None = None
        self._T_odo_prev = np.eye(4)  # pose of the last frame in the VO's chained frame
        self._motion = np.eye(4)  # last frame-to-frame motion (constant-velocity prediction)
        self._prev_id: int | None = None  # the last frame, and whether its pose was measured
        self._prev_measured = False
        self._win = (params.klt_window_px, params.klt_window_px)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)
        self._max_depth = min(max_depth_for_error(calib, params.max_point_error_m, params.pixel_noise_px),
                              calib.fb / 0.5)  # at least half a pixel of disparity
        estimate = params.estimate_disparity_offset and params.disparity_offset_prior_px > 0  # a zero prior: exact calibration
        self.offset = DisparityOffsetEstimate(params.disparity_offset_prior_px, params.disparity_offset_gate_sigma) if estimate else None

    @property
    def disparity_offset(self) -> np.ndarray:
        """The coefficients ``c`` (px, (3,), slam.stereo_offset) of the rig's disparity
        offsets the VO takes off its keyframes' points (zeros unless estimated,
        ``VoParams.estimate_disparity_offset``): for the caller's other uses of the depth,
        through :func:`slam.stereo.remove_disparity_offset`."""
        return np.zeros(3) if self.offset is None else self.offset.coefficients

    # ------------------------------------------------------------------ public

    def process(self, frame_id: int, t: float, left: np.ndarray, right: np.ndarray, depth: np.ndarray | None = None,
                T_prior: np.ndarray | None = None) -> VoResult:
        """Estimate the pose of this pair's left camera relative to a keyframe.

        ``left``/``right``: rectified uint8 images (grey, or RGB converted to grey);
        ``depth``: optional z-depth of the left image (NaN invalid), e.g. from
        ``StereoMatcher.depth``; without it, corners are matched into ``right``.
        ``T_prior``: optional 4x4 pose of this left camera in any fixed frame as the
        caller predicts it (the filter's clone at capture with the head's encoders). Where
        the keyframe has one too, their relative pose predicts where its features appear,
        instead of the constant-velocity model of the VO's own deltas: that fails when
        the camera starts or stops turning (a pan-tilt head's slew, a point turn) and,
        after a lost frame, knows no motion at all. It only places KLT's search: the
        delta is measured from the images alone.
        Frame ids must be unique. Outcomes:

        - ``ok``: ``T_kf_cur`` and ``cov`` relative to keyframe ``keyframe_id`` (always in
          ``keyframe_history``); ``new_keyframe`` if the policy made this frame the next
          keyframe (the delta still refers to the old one);
        - not ``ok``: ``reason`` says why; ``new_keyframe`` is True when tracking restarts
          from this frame (first frame, or lost track on a textured image): its filter
          clone becomes a keyframe clone with no delta linking it to the previous ones.
        """
        if frame_id == self._prev_id or any(k.frame_id == frame_id for k in self.history):
            raise VoException(f"frame_id {frame_id} was already processed; ids must be unique")
        grey_l = self._grey(left, "left")
        if depth is not None:
            depth = np.asarray(depth)
            if depth.shape != grey_l.shape:
                raise VoException(f"depth: expected shape {grey_l.shape}, got {depth.shape}")

        # measure against the active keyframe, then (if that fails) the rest of the history
        meas, ref = None, None
        if self.active is not None:
            meas, ref = self._measure(self.active, grey_l, T_prior), self.active
            if not meas.ok:
                for kf in sorted((k for k in self.history if k is not self.active), key=lambda k: -k.frame_id):
                    m = self._measure(kf, grey_l, T_prior)
                    if m.ok:
                        meas, ref = m, kf
                        break

        new_kf = False
        reason = meas.reason if meas is not None else VoFailure.FIRST_FRAME
        if meas is not None and meas.ok:
            T_odo_cur = ref.T_odo @ meas.T
            if not self._keeps(ref, meas):
                self._measure_offset(ref, meas, grey_l)  # its widest baseline: the keyframe's offset measurement
                new_kf = self._make_keyframe(frame_id, t, grey_l, right, depth, T_odo_cur, T_prior, keep=ref) is None
            elif ref is not self.active:
                self.active = ref  # a revisit: back to the older keyframe
        else:
            T_odo_cur = self._T_odo_prev @ self._motion  # unknown: the prediction stands in
            failure = self._make_keyframe(frame_id, t, grey_l, right, depth, T_odo_cur, T_prior)
            new_kf = failure is None
            if failure == VoFailure.NO_TEXTURE or (meas is None and failure is not None):
                reason = failure
        measured = meas is not None and meas.ok
        # the velocity is known when this and the previous pose were measured (or this one against the previous)
        if measured and (self._prev_measured or ref.frame_id == self._prev_id):
            self._motion = se3_inv(self._T_odo_prev) @ T_odo_cur
        else:
            self._motion = np.eye(4)
        self._T_odo_prev, self._prev_id, self._prev_measured = T_odo_cur, frame_id, measured

        history = tuple(k.frame_id for k in self.history)
        if meas is None or not meas.ok:
            return VoResult(t, frame_id, False, reason, None, None, None, 0, np.zeros((0, 2)), new_kf, history,
                            0 if meas is None else meas.matches)
        return VoResult(t, frame_id, True, None, ref.frame_id, meas.T, meas.cov, len(meas.inlier_uv), meas.inlier_uv,
                        new_kf, history, meas.matches, meas.disparity_sensitivity, meas.map_cov, meas.focal_sensitivity)

    # ------------------------------------------------------------------ keyframes

    def _grey(self, image: np.ndarray, which: str) -> np.ndarray:
        image = np.asarray(image)
        if image.ndim == 3 and image.shape[2] == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if image.shape != (self.calib.height, self.calib.width) or image.dtype != np.uint8:
            raise VoException(
                f"{which} image: expected uint8 ({self.calib.height}, {self.calib.width}) grey or (..., 3) RGB, "
                f"got {image.dtype} {image.shape}"
            )
        return image

    def _keeps(self, kf: _Keyframe, m: _Measurement) -> bool:
        """Keyframe policy: may ``kf`` stay the reference after measurement ``m``?"""
        p = self.params
        n = len(m.inlier_uv)
        angle = np.linalg.norm(cv2.Rodrigues(m.T[:3, :3])[0])
        return (n >= p.keyframe_min_inliers and n >= p.keyframe_min_inlier_share * len(kf.X)
                and np.linalg.norm(m.T[:3, 3]) <= p.keyframe_max_translation_m
                and angle <= math.radians(p.keyframe_max_rotation_deg))

    def detect(self, grey: np.ndarray, usable: np.ndarray | None = None) -> np.ndarray:
        """Shi-Tomasi corners (k, 2) float32, spread by the detection grid: the
        ``max_features`` shared among the cells that hold corners, at most
        ``ceil(max_features / cells)`` each, strongest first within a cell (vectorised
        bucketing). ``usable`` (bool, image shape) restricts the search to those pixels,
        e.g. where the stereo depth gives a keyframe point: the quality level is relative
        to the best corner there, so a horizon or a bright robot elsewhere in the image
        does not push the ground's corners below it."""
        p = self.params
        mask = np.zeros_like(grey)
        b = p.border_px
        mask[b:-b, b:-b] = 255
        if usable is not None:
            mask[~usable] = 0
        pts = cv2.goodFeaturesToTrack(grey, 4 * p.max_features, p.corner_quality, p.min_corner_distance_px, mask=mask,
                                      blockSize=3)
        if pts is None:
            return np.zeros((0, 2), np.float32)
        pts = pts.reshape(-1, 2)  # strongest first
        rank, cells = self._rank_in_cell(pts)
        keep = np.flatnonzero(rank < math.ceil(p.max_features / cells))[: p.max_features]
        return np.ascontiguousarray(pts[keep], dtype=np.float32)

    def _rank_in_cell(self, uv: np.ndarray) -> tuple[np.ndarray, int]:
        """Each point's rank (N,) among the points before it in its cell of the detection
        grid (``VoParams.grid_cols`` x ``grid_rows`` over the image), and how many cells
        hold points."""
        p = self.params
        cell = (np.minimum((uv[:, 1] * p.grid_rows / self.calib.height).astype(int), p.grid_rows - 1) * p.grid_cols
                + np.minimum((uv[:, 0] * p.grid_cols / self.calib.width).astype(int), p.grid_cols - 1))
        order = np.argsort(cell, kind="stable")
        sorted_cells = cell[order]
        first = np.searchsorted(sorted_cells, sorted_cells, side="left")
        rank = np.empty(len(uv), int)
        rank[order] = np.arange(len(uv)) - first
        return rank, int(np.count_nonzero(rank == 0))

    def _points_from_depth(self, uv: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """3D points at integer corners from a dense z-depth (as it came: no disparity offset
        taken off); NaN, inf and depth edges dropped."""
        p = self.params
        h, w = depth.shape
        u = np.clip(np.rint(uv[:, 0]).astype(int), 1, w - 2)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 1, h - 2)
        du, dv = np.meshgrid([-1, 0, 1], [-1, 0, 1])
        patch = depth[v[:, None] + dv.ravel(), u[:, None] + du.ravel()].astype(float)  # (n, 9)
        with np.errstate(invalid="ignore"):
            z = patch[:, 4]
            ok = np.all(np.isfinite(patch), axis=1)
            ok &= (np.ptp(np.where(ok[:, None], patch, 0), axis=1) <= p.max_depth_jump * z)
        c = self.calib
        X = np.stack([(uv[:, 0] - c.cx) * z / c.focal_px, (uv[:, 1] - c.cy) * z / c.focal_px, z], axis=1)
        return X, ok

    def _points_from_stereo(self, uv: np.ndarray, grey_l: np.ndarray, right: np.ndarray,
                            dense_z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """3D points by KLT along the rectified rows of the right image, forward-backward
        checked, triangulated with :func:`slam.stereo.triangulate` on the nominal calibration
        (no disparity offset taken off), with each match's row offset (right row less left
        row, NaN where none). ``dense_z``: the corners' depth from a dense depth
        image, when there is one: KLT starts at its disparity and a match more than
        ``stereo_max_disparity_gap_px`` away from it is dropped; else KLT starts at the
        disparity of 3 m."""
        p = self.params
        grey_r = self._grey(right, "right")
        guess = uv.copy()
        with np.errstate(divide="ignore", invalid="ignore"):
            prior = np.full(len(uv), self.calib.fb / 3.0) if dense_z is None else self.calib.fb / dense_z
        guess[:, 0] = np.maximum(guess[:, 0] - np.where(np.isfinite(prior), prior, self.calib.fb / 3.0), 0)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        uv_r, st, _ = cv2.calcOpticalFlowPyrLK(grey_l, grey_r, uv, guess, winSize=self._win, maxLevel=p.klt_levels,
                                               criteria=self._criteria, flags=flags)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(grey_r, grey_l, uv_r, uv.copy(), winSize=self._win, maxLevel=p.klt_levels,
                                                criteria=self._criteria, flags=flags)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - uv, axis=1) < p.klt_fb_max_px)
        ok &= np.abs(uv_r[:, 1] - uv[:, 1]) < p.stereo_max_row_error_px
        ok &= uv[:, 0] - uv_r[:, 0] > 0
        if dense_z is not None:
            with np.errstate(invalid="ignore"):
                ok &= np.abs(uv[:, 0] - uv_r[:, 0] - prior) <= p.stereo_max_disparity_gap_px
        # y from the left row alone: the right row is a noisy copy on a rectified pair,
        # or off by the rig's pitch and roll (the offset's other measurement)
        X = triangulate(uv[:, 0], uv[:, 1], uv_r[:, 0], uv[:, 1], self.calib)
        return X, ok, np.where(ok, uv_r[:, 1] - uv[:, 1], np.nan)

    def _keyframe_points(self, uv: np.ndarray, grey: np.ndarray, right: np.ndarray, depth: np.ndarray | None):
        """The corners' points for a keyframe: ``(uv, X, ok, disparity, rows)``, the
        disparity offset estimated so far taken off ``X``, ``ok`` where the point is valid
        and in range, ``disparity`` and ``rows`` the sparse stereo's disparities and row
        offsets (the offset's measurements; NaN where none, None without an offset
        estimate)."""
        p = self.params
        sparse, rows = None, None  # sparse stereo on the nominal calibration: the offset's measurements
        if depth is not None:
            X, ok = self._points_from_depth(uv, depth)
            if self.offset is not None:
                sparse, sparse_ok, rows = self._points_from_stereo(uv, grey, right, X[:, 2])
        else:
            X, ok, rows = self._points_from_stereo(uv, grey, right)
            sparse, sparse_ok = X, ok.copy()
        offset = self.disparity_offset
        if offset.any():
            with np.errstate(invalid="ignore"):
                X = X * (remove_disparity_offset(X[:, 2], self.calib, offset, uv) / X[:, 2])[:, None]
        with np.errstate(invalid="ignore"):
            ok &= (X[:, 2] >= p.min_depth_m) & (X[:, 2] <= self._max_depth)
        disparity = None
        if sparse is not None and self.offset is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                sparse_ok &= (sparse[:, 2] >= p.min_depth_m) & (sparse[:, 2] <= self._max_depth)
                disparity = np.where(sparse_ok, self.calib.fb / sparse[:, 2], np.nan)
        return uv, X, ok, disparity, rows

    def _make_keyframe(self, frame_id, t, grey, right, depth, T_odo, T_prior, keep: _Keyframe | None = None) -> VoFailure | None:
        """Make the current frame the active keyframe; returns a failure reason or None.
        A full history drops its oldest keyframe other than ``keep`` (the reference of
        this frame's delta, whose filter clone the caller still needs).

        Corners are searched in the whole image first. Where fewer than
        ``keyframe_min_inliers`` of them get a point (the camera looks over the horizon or
        up a slope, a bright robot or the skyline holds the strongest corners), they are
        searched again only where the dense depth is valid (:meth:`detect`'s ``usable``)
        and the better of the two sets is kept."""
        p = self.params
        uv = self.detect(grey)
        if len(uv) < p.min_features:
            return VoFailure.NO_TEXTURE
        uv, X, ok, disparity, rows = self._keyframe_points(uv, grey, right, depth)
        if depth is not None and ok.sum() < p.keyframe_min_inliers:
            with np.errstate(invalid="ignore"):
                usable = (depth >= p.min_depth_m) & (depth <= self._max_depth)
            again = self.detect(grey, usable)
            if len(again) > ok.sum():
                found = self._keyframe_points(again, grey, right, depth)
                if found[2].sum() > ok.sum():
                    uv, X, ok, disparity, rows = found
        if ok.sum() < p.min_features:
            return VoFailure.NO_DEPTH
        X = X[ok]
        disparity = None if disparity is None else disparity[ok]
        if disparity is not None and p.disparity_offset_model == "rotation":
            self._measure_rows(frame_id, uv[ok], disparity, rows[ok])
        kf = _Keyframe(frame_id, t, grey, uv[ok], X, stereo_point_covariance(X, self.calib, p.pixel_noise_px), T_odo.copy(),
                       None if T_prior is None else np.asarray(T_prior, float).copy(), disparity)
        self.history.append(kf)
        if len(self.history) > p.n_keyframes:
            self.history.remove(next(k for k in self.history if k is not keep))
        self.active = kf
        return None

    # ------------------------------------------------------------------ measurement

    def _measure(self, kf: _Keyframe, grey: np.ndarray, T_prior: np.ndarray | None) -> _Measurement:
        """Track ``kf`` into the current image and estimate ``T_kf_cur`` with its covariance."""
        p = self.params
        c = self.calib
        if T_prior is not None and kf.T_prior is not None:  # prediction: the caller's poses
            T_pred = se3_inv(kf.T_prior) @ T_prior
        else:  # constant velocity in the VO's chained frame
            T_pred = se3_inv(kf.T_odo) @ self._T_odo_prev @ self._motion
        R, tp = T_pred[:3, :3], T_pred[:3, 3]
        Xc = (kf.X - tp) @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            guess = (self.K[:2, :2] @ (Xc[:, :2] / Xc[:, 2:3]).T).T + self.K[:2, 2]
        m = p.border_px / 2
        vis = (Xc[:, 2] > p.min_depth_m) & (guess[:, 0] >= m) & (guess[:, 0] < c.width - m)
        vis &= (guess[:, 1] >= m) & (guess[:, 1] < c.height - m)
        idx = np.flatnonzero(vis)
        if len(idx) < p.min_inliers:
            return _Measurement(False, VoFailure.TOO_FEW_MATCHES, matches=len(idx))
        uv0 = np.ascontiguousarray(kf.uv[idx])
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        uv1, st, _ = cv2.calcOpticalFlowPyrLK(kf.image, grey, uv0, np.ascontiguousarray(guess[idx], np.float32),
                                              winSize=self._win, maxLevel=p.klt_levels, criteria=self._criteria, flags=flags)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, kf.image, uv1, uv0.copy(), winSize=self._win, maxLevel=p.klt_levels,
                                                criteria=self._criteria, flags=flags)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - uv0, axis=1) < p.klt_fb_max_px)
        ok &= (uv1[:, 0] >= 0) & (uv1[:, 0] <= c.width - 1) & (uv1[:, 1] >= 0) & (uv1[:, 1] <= c.height - 1)
        idx, uv1 = idx[ok], uv1[ok].astype(float)
        n = len(idx)
        if n < p.min_inliers:
            return _Measurement(False, VoFailure.TOO_FEW_MATCHES, matches=n)
        X, cov_X = kf.X[idx], kf.cov_X[idx]

        cv2.setRNGSeed(p.seed)
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            X, uv1, self.K, None, iterationsCount=p.ransac_iterations, reprojectionError=p.ransac_threshold_px,
            confidence=p.ransac_confidence, flags=cv2.SOLVEPNP_AP3P)
        if not found or inl is None or len(inl) < p.min_inliers:
            return _Measurement(False, VoFailure.TOO_FEW_INLIERS, matches=n)
        R_ck = cv2.Rodrigues(rvec.reshape(3, 1))[0]  # keyframe -> camera
        T = np.eye(4)
        T[:3, :3] = R_ck.T
        T[:3, 3] = -R_ck.T @ tvec.ravel()

        # weighted refinement on the RANSAC inliers, re-gating by Mahalanobis distance, refinement again
        sel = inl.ravel()
        half = max(1, p.refine_iterations // 2)
        T, H, _, _ = refine_pose(T, X[sel], cov_X[sel], uv1[sel], self.K, p.pixel_noise_px, half)
        _, _, r, W = refine_pose(T, X, cov_X, uv1, self.K, p.pixel_noise_px, 0)
        with np.errstate(invalid="ignore"):
            sel = np.flatnonzero(np.einsum("ni,nij,nj->n", r, W, r) < p.inlier_chi2)
        if len(sel) < p.min_inliers:
            return _Measurement(False, VoFailure.TOO_FEW_INLIERS, matches=n)
        T, H, _, _ = refine_pose(T, X[sel], cov_X[sel], uv1[sel], self.K, p.pixel_noise_px, p.refine_iterations - half)
        try:
            cov = np.linalg.inv(H)
            inliers = (T, X[sel], cov_X[sel], uv1[sel], self.K, p.pixel_noise_px)
            lin = _reprojection(*inliers[:5], p.pixel_noise_px**2)  # one linearisation at T for both
            s = disparity_bias_sensitivity(*inliers, c.fb, linearised=lin)
            s_f = focal_scale_sensitivity(*inliers, linearised=lin)
            map_cov = map_covariance(*inliers, linearised=lin)
        except np.linalg.LinAlgError:
            return _Measurement(False, VoFailure.DEGENERATE, matches=n)
        std = np.sqrt(np.diag(cov))
        if (not np.all(np.isfinite(cov)) or not np.all(np.isfinite(s)) or not np.all(np.isfinite(s_f)) or not np.all(np.isfinite(map_cov))
                or np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) <= 0)
                or std[:3].max() > p.max_rotation_std_rad or std[3:].max() > p.max_translation_std_m):
            return _Measurement(False, VoFailure.DEGENERATE, matches=n)
        return _Measurement(True, None, T, 0.5 * (cov + cov.T), uv1[sel], n, s, map_cov, idx[sel], s_f)

    def _measure_offset(self, kf: _Keyframe, m: _Measurement, grey: np.ndarray) -> None:
        """Fuse the rig's disparity offsets as ``kf``'s sparse disparities and ``m``'s inliers
        in ``grey`` show them (:func:`two_view_disparity_offset`), once per keyframe: when the
        keyframe is replaced, its last measurement has the widest baseline. The inliers'
        tracks are refined by affine patches first (slam.track_refinement: KLT's are biased
        over such a baseline); those that are not refined are left out. Two views measure
        the yaw; the pitch and roll are held at their estimate (from the rows, or zero)."""
        if self.offset is None or kf.disparity is None:
            return
        p = self.params
        sel = np.argsort(self._rank_in_cell(m.inlier_uv)[0], kind="stable")[: p.disparity_offset_max_tracks]  # one per cell in turn
        ids = m.inlier_ids[sel]
        uv0 = kf.uv[ids]
        uv1, refined = refine_tracks_affine(kf.image, grey, uv0, m.inlier_uv[sel], p.disparity_offset_window_px)
        found = two_view_disparity_offset(m.T, uv0[refined], kf.disparity[ids][refined], uv1[refined], self.calib,
                                          p.disparity_offset_pixel_noise_px, axes=(1,), held=self.offset.coefficients)
        if found is not None:
            self.offset.add(kf.frame_id, *found)

    def _measure_rows(self, frame_id: int, uv: np.ndarray, disparity: np.ndarray, rows: np.ndarray) -> None:
        """Fuse the rig's pitch and roll as a new keyframe's stereo matches show them in
        their rows (:func:`row_offset_measurement`), the yaw's share taken off at its
        current estimate."""
        p = self.params
        found = row_offset_measurement(uv, disparity, rows, self.calib, p.disparity_offset_pixel_noise_px,
                                       yaw_px=float(self.offset.coefficients[1]))
        if found is not None:
            self.offset.add(frame_id, *found, kind="rows")
