"""Dense stereo: SGBM disparity and depth, and the stereo error model of thesis 5.1.1.

Pure module: numpy and OpenCV only. Images in, arrays out; no simulator, no ground truth.

Frames and conventions
----------------------
Rectified pinhole pair, left camera as the reference, camera frame as OpenCV: x right,
y down, z forward. The right camera sits at ``+baseline`` along the left camera's x.
Pixel coordinates ``(u, v)`` are column and row indices (pixel centres at integers);
``cx, cy`` is the principal point in those coordinates. Disparity ``d = u_left - u_right``
in pixels (>= 0 for points in front of the rig). Depth is the z coordinate (z-depth),
not the ray length. Invalid pixels are NaN; a valid disparity of 0 is depth ``inf``
(a point at infinity, thesis 5.1.1: distinguishable from missing data).

Error model (thesis eq. 5.2 and 5.4, after Hirschmüller 2003 and Hirschmüller et al. 2002)
-------------------------------------------------------------------------------------------
First-order propagation of independent Gaussian pixel noise ``Δp`` (default 0.5 px,
thesis 5.1.1) on each of the four image coordinates of a stereo correspondence
``(u_l, v_l, u_r, v_r)`` through triangulation

    z = f b / (u_l - u_r),   x = (u_l - cx) z / f,   y = ((v_l + v_r) / 2 - cy) z / f.

With this model, eq. 5.2a-c follow exactly (y from the mean of both rows gives the
``b^2 / 2`` term of 5.2b). Eq. 5.4 is the same propagation applied to the distance of two
independently triangulated points. The printed thesis has two slips in eq. 5.4b: ``t``
for ``b`` and ``+ (q_z - p_z) q_z`` where the derivation (and the
p <-> q symmetry with eq. 5.4e) gives ``- (q_z - p_z) q_z``. This module uses the derived
form; ``tests/test_stereo.py`` checks it against a Monte-Carlo propagation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

#: Pixel error of the thesis (5.1.1: calibration RMSE up to 0.46 px, 0.5 px assumed).
DEFAULT_PIXEL_ERROR = 0.5
DEFAULT_MIN_DEPTH_M = 0.5  # nearest depth StereoMatcher searches disparities for


class StereoException(Exception):
    """Bad input to the stereo functions (shapes, calibration, parameters)."""


# --------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class StereoCalibration:
    """A rectified pinhole stereo pair: focal length and principal point in pixels, baseline in metres."""

    focal_px: float
    cx: float
    cy: float
    baseline_m: float
    width: int
    height: int

    def __post_init__(self):
        if not (self.focal_px > 0 and self.baseline_m > 0 and self.width > 0 and self.height > 0):
            raise StereoException(
                f"focal_px, baseline_m, width and height must be positive, got "
                f"f={self.focal_px}, b={self.baseline_m}, {self.width}x{self.height}"
            )

    @classmethod
    def from_intrinsics(cls, K: np.ndarray, baseline_m: float, width: int, height: int) -> StereoCalibration:
        """From a 3x3 camera matrix with square pixels and no skew (``K[0,0] == K[1,1]``)."""
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise StereoException(f"K must be 3x3, got shape {K.shape}")
        fx, fy = K[0, 0], K[1, 1]
        if not math.isclose(fx, fy, rel_tol=1e-6) or abs(K[0, 1]) > 1e-9:
            raise StereoException(f"expected square pixels and no skew, got fx={fx}, fy={fy}, skew={K[0, 1]}")
        return cls(float(fx), float(K[0, 2]), float(K[1, 2]), float(baseline_m), int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.focal_px, 0, self.cx], [0, self.focal_px, self.cy], [0, 0, 1.0]])

    @property
    def fb(self) -> float:
        """Focal length times baseline (px m): depth = fb / disparity."""
        return self.focal_px * self.baseline_m


# --------------------------------------------------------------------------- matching


class StereoMatcher:
    """OpenCV semi-global matching (``StereoSGBM``, 3-way mode) with defaults for
    320x240 .. 640x480 grey images.

    ``numDisparities`` covers depths from ``min_depth_m`` to infinity (rounded up to a
    multiple of 16); ``P1 = 8 cn w^2`` and ``P2 = 32 cn w^2`` for block size ``w``
    (OpenCV's recommended smoothness penalties); a uniqueness check, a left-right
    consistency check and a speckle filter remove most mismatches. RGB input is
    converted to grey first (cn = 1), as the thesis's rovers match grey images.

    Disparities outside OpenCV's valid region (``cv2.getValidDisparityROI``: the left
    ``numDisparities`` columns, which have no partner in the right image, and a half block
    at the other borders) are invalid. SGBM still writes values there; on rendered terrain
    the last two columns held 3 % and 12 % of depths more than 0.1 m off within the mapping
    range, against 0.1 % inside, and every such point at the view's edge made a false step
    in the obstacle classification (docs/mapping.md).

    SGBM's prefilter (a 3x3 horizontal Sobel) reads one pixel beyond each block, and at the
    region's edge that pixel is a replicated border: with camera noise the last valid column
    held 1.3 per mille of depths more than 0.1 m off, its neighbours none, so the valid region
    is shrunk by that pixel.

    Textureless pixels are invalid too: SGBM's path aggregation carries the disparity of a
    textured neighbour into a uniform region (the sky above a rover's mast took the mast's
    depth and became a wall of obstacles). A pixel needs a mean horizontal gradient
    ``|dI/du|`` of at least ``min_texture`` grey levels per pixel over the matching block,
    the role of ``textureThreshold`` in OpenCV's block matcher, which SGBM lacks. The
    gradient is taken after a Gaussian blur of ``texture_blur_px``: pixel noise alone
    (sensor shot and read noise, independent per pixel) gives a noisy sky a mean gradient
    above 1 grey level, scene texture is correlated over pixels and keeps most of its
    gradient (docs/mapping.md). The speckle filter runs once more after these masks: they
    can cut a mismatched region into islands smaller than ``speckle_window_size``, which
    SGBM's own filter, run before them, saw connected to the rest.
    """

    def __init__(
        self,
        calibration: StereoCalibration,
        *,
        min_depth_m: float = DEFAULT_MIN_DEPTH_M,
        block_size: int = 5,
        uniqueness_ratio: int = 10,
        speckle_window_size: int = 100,
        speckle_range: int = 2,
        disp12_max_diff: int = 1,
        pre_filter_cap: int = 31,
        mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        min_texture: float = 1.0,
        texture_blur_px: float = 0.8,
    ):
        if min_depth_m <= 0:
            raise StereoException(f"min_depth_m must be > 0, got {min_depth_m}")
        if block_size < 1 or block_size % 2 == 0:
            raise StereoException(f"block_size must be odd and >= 1, got {block_size}")
        if not min_texture >= 0:
            raise StereoException(f"min_texture must be >= 0, got {min_texture}")
        if not texture_blur_px >= 0:
            raise StereoException(f"texture_blur_px must be >= 0, got {texture_blur_px}")
        self.calibration = calibration
        self.block_size = block_size
        self.min_texture = float(min_texture)
        self.texture_blur_px = float(texture_blur_px)
        self.speckle_window_size = speckle_window_size
        self.speckle_range = speckle_range
        self.min_depth_m = float(min_depth_m)
        max_disparity = calibration.fb / min_depth_m
        self.num_disparities = int(16 * math.ceil(max_disparity / 16))
        if self.num_disparities >= calibration.width:
            raise StereoException(
                f"min_depth_m={min_depth_m} needs {self.num_disparities} disparities, "
                f"more than the image width {calibration.width}"
            )
        cn = 1
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=self.num_disparities,
            blockSize=block_size,
            P1=8 * cn * block_size**2,
            P2=32 * cn * block_size**2,
            disp12MaxDiff=disp12_max_diff,
            preFilterCap=pre_filter_cap,
            uniquenessRatio=uniqueness_ratio,
            speckleWindowSize=speckle_window_size,
            speckleRange=speckle_range,
            mode=mode,
        )
        full = (0, 0, calibration.width, calibration.height)
        x, y, w, h = cv2.getValidDisparityROI(full, full, 0, self.num_disparities, block_size)
        self.valid_region = np.zeros((calibration.height, calibration.width), dtype=bool)
        self.valid_region[y + 1 : y + h - 1, x + 1 : x + w - 1] = True  # less the prefilter's pixel

    def _grey(self, image: np.ndarray, which: str) -> np.ndarray:
        image = np.asarray(image)
        if image.ndim == 3 and image.shape[2] == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if image.ndim != 2 or image.shape != (self.calibration.height, self.calibration.width):
            raise StereoException(
                f"{which} image: expected ({self.calibration.height}, {self.calibration.width}) grey "
                f"or (..., 3) RGB, got shape {image.shape}"
            )
        if image.dtype != np.uint8:
            raise StereoException(f"{which} image: expected uint8, got {image.dtype}")
        return image

    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Disparity in pixels (float32, 1/16 px resolution); invalid pixels NaN."""
        grey = self._grey(left, "left")
        raw = self._sgbm.compute(grey, self._grey(right, "right"))
        invalid = np.int16(-16)  # OpenCV marks invalid as (minDisparity - 1) * 16
        raw[~self.valid_region | (self.texture(grey) < self.min_texture)] = invalid
        if self.speckle_window_size > 0:
            cv2.filterSpeckles(raw, invalid, self.speckle_window_size, 16 * self.speckle_range)
        disp = raw.astype(np.float32) * np.float32(1 / 16)
        disp[raw < 0] = np.nan
        return disp

    def texture(self, grey: np.ndarray) -> np.ndarray:
        """Mean ``|dI/du|`` (grey levels per pixel, Sobel, after a Gaussian blur of
        ``texture_blur_px``) over the matching block around each pixel."""
        if self.texture_blur_px > 0:
            grey = cv2.GaussianBlur(grey, (0, 0), self.texture_blur_px)
        gradient = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)) * np.float32(1 / 8)
        return cv2.boxFilter(gradient, -1, (self.block_size, self.block_size))

    def depth(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """z-depth of the left camera in metres (float32); NaN invalid, inf at zero disparity."""
        return disparity_to_depth(self.disparity(left, right), self.calibration)


def disparity_to_depth(disparity: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """``z = f b / d``; NaN stays NaN, ``d <= 0`` gives ``inf``."""
    disparity = np.asarray(disparity)
    dtype = disparity.dtype if np.issubdtype(disparity.dtype, np.floating) else np.float64
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(disparity > 0, calibration.fb / disparity, np.inf).astype(dtype)
    depth[np.isnan(disparity)] = np.nan
    return depth


def disparity_offset_sensitivity(u, v, disparity, calibration: StereoCalibration) -> np.ndarray:
    """How much a measured disparity exceeds the true one per pixel of each coefficient
    ``c = f θ`` of the right camera's rotation error ``θ = (θx, θy, θz)`` (OpenCV axes, the
    true right camera in its rectified frame; slam/stereo_offset.py): ``(..., 3)``, the
    offset being ``s · c``. A turn ``θ`` moves the right image's normalised point ``(x, y)``
    by ``-θy (1 + x^2) + θz y + θx x y`` along its row to first order (the rotation's image
    motion field), so ``s = (-x y, 1 + x^2, -y)``, ``(x, y)`` the right pixel ``(u - d, v)``
    normalised: a yaw offsets every disparity, most at the image's sides, a roll tilts the
    offset from top to bottom row, a pitch twists it. ``u, v, disparity``: the left pixels
    and their measured disparities, broadcast together."""
    x, y = np.broadcast_arrays(*_right_normalised(u, v, disparity, calibration))
    return np.stack([-x * y, 1.0 + x * x, -y], axis=-1)


def row_offset_sensitivity(u, v, disparity, calibration: StereoCalibration) -> np.ndarray:
    """How far the right camera's row of a match lies below the left's per pixel of each
    coefficient ``c = f θ`` (as :func:`disparity_offset_sensitivity`): ``(..., 3)``, the
    row offset being ``r · c``. The same turn moves the right image's normalised point by
    ``θx (1 + y^2) - θy x y - θz x`` across the rows (the motion field's other component),
    so ``r = (1 + y^2, -x y, -x)``: a pitch shifts every row, a roll tilts the rows from
    the left side to the right, a yaw barely shows. Unlike a disparity, a row offset needs
    no depth to be seen: every stereo match measures it."""
    x, y = np.broadcast_arrays(*_right_normalised(u, v, disparity, calibration))
    return np.stack([1.0 + y * y, -x * y, -x], axis=-1)


def disparity_offset(u, v, disparity, calibration: StereoCalibration, coefficients_px) -> np.ndarray:
    """The offset ``s · c`` (px) of each measured disparity, :func:`disparity_offset_sensitivity`
    contracted with the coefficients ``c`` (3,) term by term, without the per-pixel stack
    of sensitivities (a depth image's worth of them is the cost)."""
    x, y = _right_normalised(u, v, disparity, calibration)
    c = coefficients_px
    return c[1] * (1.0 + x * x) - y * (c[0] * x + c[2])


def _right_normalised(u, v, disparity, calibration: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The normalised coordinates ``(x, y)`` of the right pixel ``(u - d, v)`` of left pixels and their disparities."""
    x = (np.asarray(u, dtype=float) - np.asarray(disparity, dtype=float) - calibration.cx) / calibration.focal_px
    y = (np.asarray(v, dtype=float) - calibration.cy) / calibration.focal_px
    return x, y


def remove_disparity_offset(depth, calibration: StereoCalibration, coefficients_px, uv: np.ndarray | None = None):
    """Depth with the right camera's rotation error taken off its disparity,
    ``z' = f b / (d - s · c)`` (:func:`disparity_offset_sensitivity`, ``d = f b / z``),
    through :func:`disparity_to_depth`: NaN stays NaN, a corrected disparity at or below
    zero is ``inf``, the dtype is kept. ``coefficients_px``: ``c = f θ`` (3,); ``uv``: the
    left pixels (N, 2) of the depths (N,), or None for a depth image (H, W) on the pixel
    grid. All-zero coefficients return ``depth`` itself."""
    c = np.asarray(coefficients_px, dtype=float)
    if c.shape != (3,):
        raise StereoException(f"coefficients_px must have shape (3,), got {c.shape}")
    if not c.any():
        return depth
    depth = np.asarray(depth)
    if uv is None:
        if depth.ndim != 2:
            raise StereoException(f"without uv, depth must be a 2-D image, got shape {depth.shape}")
        u, v = np.arange(depth.shape[1])[None, :], np.arange(depth.shape[0])[:, None]
    else:
        u, v = np.asarray(uv)[:, 0], np.asarray(uv)[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = calibration.fb / depth
        offset = disparity_offset(u, v, np.where(np.isfinite(disparity), disparity, 0.0), calibration, c)
        return disparity_to_depth((disparity - offset).astype(depth.dtype), calibration)


def depth_to_points(depth: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """Back-project a z-depth image (H, W) to points (H, W, 3) in the left camera frame
    (OpenCV: x right, y down, z forward). NaN and inf depths give NaN/inf points."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise StereoException(f"depth must be a 2-D image, got shape {depth.shape}")
    h, w = depth.shape
    u, v, dtype = _normalised_grid(depth, calibration)
    out = np.empty((h, w, 3), dtype=dtype)
    out[..., 2] = depth
    with np.errstate(invalid="ignore"):
        out[..., 0] = depth * u[None, :]
        out[..., 1] = depth * v[:, None]
    return out


def _normalised_grid(depth: np.ndarray, calibration: StereoCalibration) -> tuple[np.ndarray, np.ndarray, np.dtype]:
    """The normalised coordinates of a depth image's columns (W,) and rows (H,) in the
    depth's float dtype (float64 for an integer depth), and that dtype."""
    dtype = depth.dtype if np.issubdtype(depth.dtype, np.floating) else np.dtype(np.float64)
    f = dtype.type(calibration.focal_px)
    u = (np.arange(depth.shape[1], dtype=dtype) - dtype.type(calibration.cx)) / f
    v = (np.arange(depth.shape[0], dtype=dtype) - dtype.type(calibration.cy)) / f
    return u, v, dtype


def depth_to_points_at(depth: np.ndarray, mask: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """``depth_to_points(depth, calibration)[mask]``, points (N, 3) of the pixels in ``mask``
    (H, W, row-major order) alone, without the whole image's: the same values bit for bit."""
    depth = np.asarray(depth)
    if depth.ndim != 2 or np.shape(mask) != depth.shape:
        raise StereoException(f"need a 2-D depth and a mask of its shape, got {depth.shape} and {np.shape(mask)}")
    rows, cols = np.nonzero(mask)
    z = depth[rows, cols]
    u, v, dtype = _normalised_grid(depth, calibration)
    out = np.empty((len(z), 3), dtype=dtype)
    out[:, 2] = z
    with np.errstate(invalid="ignore"):
        out[:, 0] = z * u[cols]
        out[:, 1] = z * v[rows]
    return out


def triangulate(
    u_left: np.ndarray, v_left: np.ndarray, u_right: np.ndarray, v_right: np.ndarray, calibration: StereoCalibration
) -> np.ndarray:
    """Triangulate correspondences of a rectified pair, (...,) each -> (..., 3), with
    ``y`` from the mean row of both images (the model behind eq. 5.2b)."""
    c = calibration
    d = np.asarray(u_left, dtype=float) - np.asarray(u_right, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = c.fb / d
    x = (np.asarray(u_left) - c.cx) * z / c.focal_px
    y = ((np.asarray(v_left) + np.asarray(v_right)) / 2 - c.cy) * z / c.focal_px
    return np.stack([x, y, z], axis=-1)


# --------------------------------------------------------------------------- error model


def point_error(points: np.ndarray, calibration: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR) -> np.ndarray:
    """Propagated reconstruction error ``(Δp_x, Δp_y, Δp_z)`` of points (..., 3) in the
    left camera frame, thesis eq. 5.2a-c (Hirschmüller 2003):

        Δp_x = Δp p_z / (f b) sqrt((b - p_x)^2 + p_x^2)      (5.2a)
        Δp_y = Δp p_z / (f b) sqrt(2 p_y^2 + b^2 / 2)        (5.2b)
        Δp_z = Δp p_z^2 / (f b) sqrt(2)                      (5.2c)

    ``f`` focal length in pixels, ``b`` baseline in metres, ``Δp`` pixel error (std).
    """
    p = np.asarray(points, dtype=float)
    if p.shape[-1] != 3:
        raise StereoException(f"points must have shape (..., 3), got {p.shape}")
    b, fb = calibration.baseline_m, calibration.fb
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    k = pixel_error * pz / fb
    out = np.empty_like(p)
    out[..., 0] = k * np.sqrt((b - px) ** 2 + px**2)
    out[..., 1] = k * np.sqrt(2 * py**2 + b**2 / 2)
    out[..., 2] = k * pz * math.sqrt(2)
    return out


def depth_error(depth: np.ndarray | float, calibration: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR):
    """``Δp_z = Δp z^2 sqrt(2) / (f b)``, thesis eq. 5.2c, for a depth (image)."""
    z = np.asarray(depth, dtype=float)
    return pixel_error * z**2 * math.sqrt(2) / calibration.fb


def max_depth_for_error(calibration: StereoCalibration, max_error_m: float, pixel_error: float = DEFAULT_PIXEL_ERROR) -> float:
    """The depth at which ``Δp_z`` (eq. 5.2c) reaches ``max_error_m``: the thesis's
    far-point cut (5.1.1) as a range limit."""
    return math.sqrt(max_error_m * calibration.fb / (pixel_error * math.sqrt(2)))


def nearest_depth(depth: np.ndarray | float, calibration: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR):
    """The nearest depth a z-depth is within its stereo error: the disparity raised by
    ``sqrt(2) Δp`` (the error of eq. 5.2c before linearisation); ``inf`` gives ``fb / (sqrt(2) Δp)``."""
    z = np.asarray(depth, dtype=float)
    return calibration.fb / (calibration.fb / z + math.sqrt(2) * pixel_error)


def farthest_depth(depth: np.ndarray | float, calibration: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR):
    """The farthest depth a z-depth is within its stereo error: the disparity lowered by
    ``sqrt(2) Δp`` (as :func:`nearest_depth` raises it); ``inf`` where that reaches zero."""
    z = np.asarray(depth, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = calibration.fb / z - math.sqrt(2) * pixel_error
        return np.where(disparity > 0, calibration.fb / disparity, np.inf)


def cut_far_points(
    depth: np.ndarray,
    calibration: StereoCalibration,
    max_error_m: float = 0.15,
    pixel_error: float = DEFAULT_PIXEL_ERROR,
) -> np.ndarray:
    """Depth with points whose ``Δp_z`` (eq. 5.2c) exceeds ``max_error_m`` set to NaN
    (thesis 5.1.1: points beyond an error threshold are dropped before mapping; the
    thesis's 2.5 m (wide) .. 5 m (narrow) view limits correspond to about 0.15 m)."""
    depth = np.array(depth, copy=True)
    with np.errstate(invalid="ignore"):
        depth[~(depth <= max_depth_for_error(calibration, max_error_m, pixel_error))] = np.nan
    return depth


def distance_error(
    p: np.ndarray, q: np.ndarray, calibration: StereoCalibration, pixel_error: float = DEFAULT_PIXEL_ERROR
) -> np.ndarray:
    """Mean error ``Δd`` of the distance ``d = |p - q|`` (eq. 5.3) between two points
    (..., 3) in the left camera frame, thesis eq. 5.4 (Hirschmüller et al. 2002):

        Δd = Δp / (d f b) sqrt(q_z^2 (A + B + C) + p_z^2 (C + D + E))          (5.4a)
        A = ((q_x - p_x)(b - q_x) - (q_y - p_y) q_y - (q_z - p_z) q_z)^2        (5.4b)*
        B = ((q_x - p_x) q_x + (q_y - p_y) q_y + (q_z - p_z) q_z)^2             (5.4c)
        C = (b (q_y - p_y))^2 / 2                                                (5.4d)
        D = ((q_x - p_x)(b - p_x) - (q_y - p_y) p_y - (q_z - p_z) p_z)^2        (5.4e)
        E = ((q_x - p_x) p_x + (q_y - p_y) p_y + (q_z - p_z) p_z)^2             (5.4f)

    (*) The thesis prints ``t`` for ``b`` and ``+ (q_z - p_z) q_z`` in 5.4b; both are
    slips: the derivation and the p <-> q symmetry with 5.4e give the form above.
    For ``p == q`` (d = 0) the first-order error is undefined; NaN is returned.
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    if p.shape[-1] != 3 or q.shape[-1] != 3:
        raise StereoException(f"p and q must have shape (..., 3), got {p.shape} and {q.shape}")
    b, fb = calibration.baseline_m, calibration.fb
    w = q - p
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    qx, qy, qz = q[..., 0], q[..., 1], q[..., 2]
    A = (wx * (b - qx) - wy * qy - wz * qz) ** 2
    B = (wx * qx + wy * qy + wz * qz) ** 2
    C = 0.5 * (b * wy) ** 2
    D = (wx * (b - px) - wy * py - wz * pz) ** 2
    E = (wx * px + wy * py + wz * pz) ** 2
    d = np.sqrt(wx**2 + wy**2 + wz**2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d > 0, pixel_error / (d * fb) * np.sqrt(qz**2 * (A + B + C) + pz**2 * (C + D + E)), np.nan)
