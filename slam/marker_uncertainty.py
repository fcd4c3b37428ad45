"""The learned uncertainty model of marker detections (thesis 6.2.3, eq. 6.9, 8.1.3): a
lookup table of maximum pose errors over distance and view angle, precomputed from
rendered markers (``sim.tools.marker_lut`` builds it), and the online simulation of corner
errors through the PnP solver; the standard deviations of a detection are the larger
of the two, and detections with a rotational sigma above 75 deg are rejected.

Errors are the components of ``xi`` with ``T_true = T_est Exp(xi)``, [rotation,
translation], rotation as ``Log(R_est^T R_true)`` and translation ``R_est^T (t_true -
t_est)`` (the first-order right perturbation of the covariance convention of
``slam.markers``), in the marker frame: x and y in the tag's plane, z its normal.

The table is built with the tag turned about its vertical axis; a real view can be
tilted about any in-plane axis, so the two in-plane components share the larger of
their two sigmas (rotation and translation alike).

Pure: numpy, scipy and ``slam.markers``.
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import generic_filter

from slam import lie
from slam.markers import MarkerDetection, MarkerDetector, MarkerException, UncertaintyModel

MAX_ROTATION_SIGMA_RAD = math.radians(75.0)  # thesis 8.1.3: detections above are rejected
SIGMA_FLOOR = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])  # keeps a covariance positive definite
DEFAULT_DP_PX = 0.5  # the rectified images' pixel error (thesis 5.1.1, eq. 6.9)

# eq. 6.9: the 2^8 sign patterns of the 8 corner coordinates, fixed order
_SIGNS = np.array(list(itertools.product((1.0, -1.0), repeat=8))).reshape(256, 4, 2)


def corner_perturbations(corners: np.ndarray, dp_px: float) -> np.ndarray:
    """Eq. 6.9: the 256 corner sets with every coordinate moved by ``+dp`` or ``-dp``."""
    c = np.asarray(corners, dtype=float).reshape(4, 2)
    return c[None] + dp_px * _SIGNS


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """|xi| (6,) for ``T_true = T_est Exp(xi)``, [rotation (rad), translation (m)], first
    order: the magnitudes of :func:`slam.lie.pose_error`."""
    return np.abs(lie.pose_error(T_est, T_true))


def _mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """Chordal mean rotation (the SVD projection of the mean matrix) and mean translation."""
    M = np.mean([T[:3, :3] for T in poses], axis=0)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.mean([T[:3, 3] for T in poses], axis=0)
    return T


def online_errors(detector: MarkerDetector, detection: MarkerDetection, dp_px: float = DEFAULT_DP_PX) -> np.ndarray:
    """Thesis 6.2.3, online step: PnP on the detection's corners and on their 256
    perturbations (eq. 6.9); the largest deviation of any of these poses from their mean,
    per component. A flip to the other planar solution under a small perturbation shows
    up as a large rotational error."""
    poses = [detection.T_cam_marker]
    for corners in corner_perturbations(detection.corners, dp_px):
        d = detector.pose_from_corners(detection.tag_id, corners)
        if d is not None:
            poses.append(d.T_cam_marker)
    mean = _mean_pose(poses)
    return np.max([pose_error(mean, T) for T in poses], axis=0)


def symmetric_in_plane(sigma: np.ndarray) -> np.ndarray:
    """The larger of the x and y sigmas for both, for rotation and translation."""
    s = np.array(sigma, dtype=float)
    s[0] = s[1] = max(s[0], s[1])
    s[3] = s[4] = max(s[3], s[4])
    return s


@dataclass(frozen=True)
class MarkerErrorTable:
    """Maximum detection errors (6 components, see the module docstring) over a grid of
    distance and view angle, for one camera (size, focal length) and marker size.
    ``raw`` holds NaN where the rendered tag was not detected; ``errors`` is ``raw``
    after :func:`postprocess`."""

    distances_m: np.ndarray  # (n_d,)
    angles_rad: np.ndarray  # (n_a,) between the marker normal and the line of sight, 0 = frontal
    raw: np.ndarray  # (n_d, n_a, 6)
    errors: np.ndarray  # (n_d, n_a, 6)
    width: int
    height: int
    focal_px: float
    size_m: float
    dp_px: float
    blur_sigma_px: float

    def lookup(self, distance_m: float, angle_rad: float) -> np.ndarray:
        """Bilinear interpolation of ``errors``, clamped to the grid (thesis 6.2.3)."""
        out = np.empty(6)
        d = float(np.clip(distance_m, self.distances_m[0], self.distances_m[-1]))
        a = float(np.clip(angle_rad, self.angles_rad[0], self.angles_rad[-1]))
        i = int(np.clip(np.searchsorted(self.distances_m, d) - 1, 0, len(self.distances_m) - 2))
        j = int(np.clip(np.searchsorted(self.angles_rad, a) - 1, 0, len(self.angles_rad) - 2))
        u = (d - self.distances_m[i]) / (self.distances_m[i + 1] - self.distances_m[i])
        v = (a - self.angles_rad[j]) / (self.angles_rad[j + 1] - self.angles_rad[j])
        e = self.errors
        out[:] = (1 - u) * (1 - v) * e[i, j] + u * (1 - v) * e[i + 1, j] + (1 - u) * v * e[i, j + 1] + u * v * e[i + 1, j + 1]
        return out

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            distances_m=self.distances_m,
            angles_rad=self.angles_rad,
            raw=self.raw,
            errors=self.errors,
            meta=np.array([self.width, self.height, self.focal_px, self.size_m, self.dp_px, self.blur_sigma_px]),
        )

    @classmethod
    def load(cls, path: Path) -> MarkerErrorTable:
        with np.load(path) as z:
            w, h, f, size, dp, blur = z["meta"]
            return cls(z["distances_m"], z["angles_rad"], z["raw"], z["errors"], int(w), int(h), float(f), float(size), float(dp), float(blur))


def table_name(width: int, height: int, focal_px: float, size_m: float) -> str:
    """File name of the table for a camera and a marker size."""
    return f"lut_{width}x{height}_f{focal_px:.1f}_s{size_m:.3f}.npz"


def postprocess(raw: np.ndarray) -> np.ndarray:
    """Thesis 6.2.3's post-processing of a raw table (n_d, n_a, 6), NaN where undetected:
    a 3x3 median filter over (distance, angle) per component (``scipy.ndimage.generic_filter``
    with ``nanmedian``: each median over the detected cells of its window, undetected
    cells stay missing); then the missing cells are filled:
    along each distance row, cells past the last valid angle take that border value (and
    before the first valid angle, the first; holes between valid angles are interpolated
    linearly, which the thesis does not mention); rows with no valid cell beyond the
    first detected distance take, per angle column, the maximum of the last 10 % (at
    least one) of the valid rows before them; rows nearer than the first detected
    distance (a large tag overfilling the image) take that first row, the border value,
    as along the rows (the thesis's tables start where tags are detected)."""
    raw = np.asarray(raw, dtype=float)
    valid = np.isfinite(raw[..., 0])
    n_d, n_a, n_c = raw.shape
    with warnings.catch_warnings():  # windows without a detected cell: NaN, as wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        out = np.stack([generic_filter(raw[..., k], np.nanmedian, size=3, mode="constant", cval=np.nan) for k in range(n_c)], axis=-1)
    out[~valid] = np.nan
    angles = np.arange(n_a)
    for i in range(n_d):
        cols = np.flatnonzero(valid[i])
        if cols.size:
            for k in range(n_c):  # holes between detected angles interpolated, beyond them the border value
                out[i, :, k] = np.interp(angles, cols, out[i, cols, k])
    filled_rows = np.flatnonzero(valid.any(axis=1))
    for i in range(n_d):
        if valid[i].any():
            continue
        if filled_rows.size == 0:
            raise MarkerException("the table has no detected cell to fill from")
        above = filled_rows[filled_rows < i]
        if above.size == 0:
            out[i] = out[filled_rows[0]]
            continue
        last = above[-max(1, math.ceil(0.1 * above.size)) :]
        out[i] = np.max(out[last], axis=0)
    return out


def detection_sigmas(
    model: UncertaintyModel,
    detection: MarkerDetection,
    *,
    table: MarkerErrorTable | None = None,
    detector: MarkerDetector | None = None,
    dp_px: float = DEFAULT_DP_PX,
) -> np.ndarray:
    """Standard deviations (6,) of a detection by the ``lut``, ``online`` or ``lut_online``
    model (thesis 6.2.3: the maximum errors taken as sigmas, the larger of both)."""
    model = UncertaintyModel(model)
    parts = []
    if model in (UncertaintyModel.LUT, UncertaintyModel.LUT_ONLINE):
        if table is None:
            raise MarkerException(f"the {model.value} model needs a lookup table (marsyard marker-lut builds it)")
        parts.append(table.lookup(detection.distance_m, detection.view_angle_rad))
    if model in (UncertaintyModel.ONLINE, UncertaintyModel.LUT_ONLINE):
        if detector is None:
            raise MarkerException(f"the {model.value} model needs the detector for its corner perturbations")
        parts.append(online_errors(detector, detection, dp_px))
    if not parts:
        raise MarkerException(f"{model.value} is not a learned model; use slam.markers.detection_covariance")
    return np.maximum(symmetric_in_plane(np.max(parts, axis=0)), SIGMA_FLOOR)
