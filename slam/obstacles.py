"""Obstacle classification in depth images and the rolling local obstacle map (thesis 5.1.1).

Pure module: numpy, on top of ``slam.stereo`` (whose error model of eq. 5.2 and 5.4 it
uses). Depth images, intrinsics and the camera's gravity-aligned pose in; per-pixel obstacle
flags, a per-image 2.5D height map with traversability, and a fused robot-centred map out.

Pipeline per depth image (``classify_depth``)
---------------------------------------------
1. Negative edges, on the depth image itself (``negative_edges``): per column, each valid pixel
   is compared with the previous valid pixel above it. A depth jump of at least
   ``edge_jump_m`` (0.2 m) pairs a near point ``p`` with a far point ``q``; both go to the
   gravity frame and eq. 5.1 gives the minimal slope of the hidden region between them,
   ``s_min = (p_z - q_z) / |q_xy - p_xy|``. If it exceeds ``tan(max_slope_rad)`` the near
   pixel (the rim) is a negative edge. A far side that is higher (an occluding step) gives
   ``s_min < 0`` and is left to the step detection. A drop ``p_z - q_z`` no higher than
   ``step_height_m`` is no cliff, however steep, and a far point beyond the mapping range
   (``max_error_m``, eq. 5.2c) counts as near as its stereo error allows (our additions:
   the thesis checks the slope alone, which on rough ground flagged every small crest with
   a 5-10 cm dip behind it, and crests at the range limit against far points metres off;
   docs/mapping.md).
2. Stereo-error-adaptive steps on a gravity-aligned 2.5D height map (cells of 0.05 m on the
   lattice ``floor(x / resolution)``, mean height of the points per cell as in the thesis;
   ``CellHeight.MAX`` as a variant). Points whose depth error (eq. 5.2c) may exceed
   ``max_error_m`` are dropped first (:func:`classified_pixels`). In a square window of
   ``window_cells`` (3..6) around each cell, ``h_diff`` is the difference of the highest and
   the lowest cell; ``Δd`` is eq. 5.4 (``slam.stereo.distance_error``) for the centre points of
   those two cells, taken back into the camera frame. The cell's traversability is
   ``h_diff / (h_max + Δd)``; above 1 it is an obstacle (``h_diff > h_max + Δd``).
   Cells holding a negative edge's rim get at least ``s_min / tan(max_slope_rad)``, the same
   kind of ratio (> 1), so one map carries both classes. Seen ground that falls by more
   than ``h_max + Δd`` within ``h_max / tan(max_slope_rad)`` gets the ratio of its drop to
   that (``steep_drops``, our addition: eq. 5.1's slope limit for visible ground, which the
   window misses on slopes between 20 and about 37 deg).
3. ``RollingObstacleMap``: a fixed-size grid on the same lattice, centred on the robot, that
   scrolls with it (cells still in view keep their value) and low-pass filters each new
   image's traversability per cell, ``v <- (1 - rate) v + rate * t`` (unknown cells start at
   0, so an obstacle needs repeated observations).

Frames: the camera as OpenCV (x right, y down, z forward); ``T_gravity_cam`` (4x4) maps camera
points to a gravity-aligned frame with z up (e.g. the robot's local map frame). The robot
position given to the rolling map is in that same frame. Depth is z-depth in metres; NaN (or
<= 0) is no data; ``inf`` (zero disparity) is no data unless ``inf_depth_m`` is set, when the
negative-edge search places the point on its ray at that depth (thesis 5.1.1: a lower ground
beyond the stereo range still shows a cliff). The column-wise search assumes small camera roll.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from enum import StrEnum

import numba
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from slam.stereo import DEFAULT_PIXEL_ERROR, StereoCalibration, distance_error, farthest_depth, max_depth_for_error, nearest_depth


class ObstacleException(ValueError):
    """Bad input to the obstacle classification (shapes, poses, parameters)."""


class CellHeight(StrEnum):
    """Height of a 2.5D map cell from the points falling into it."""

    MEAN = "mean"  # thesis 5.1.1
    MAX = "max"


@dataclass(frozen=True)
class ObstacleParams:
    """Parameters of the obstacle classification (thesis 5.1.1; defaults after the thesis where it gives values)."""

    resolution_m: float = 0.05  # 2.5D map cell
    window_cells: int = 5  # edge length of the h_diff neighbourhood, 3..6 cells
    step_height_m: float = 0.15  # h_max: the robot's maximal traversable step
    max_slope_rad: float = math.radians(20.0)  # the robot's maximal traversable slope (negative edges)
    edge_jump_m: float = 0.2  # depth jump between consecutive valid pixels of a column
    max_error_m: float = 0.15  # far cut: points with Δp_z (eq. 5.2c) above this are dropped
    pixel_error: float = DEFAULT_PIXEL_ERROR  # Δp of eq. 5.2 and 5.4
    cell_height: CellHeight = CellHeight.MEAN
    inf_depth_m: float | None = None  # depth assumed for inf pixels in the negative-edge search; None: no data

    def __post_init__(self):
        positive = ("resolution_m", "step_height_m", "edge_jump_m", "max_error_m", "pixel_error")
        bad = [f"{k}={getattr(self, k)}" for k in positive if not getattr(self, k) > 0]
        if bad:
            raise ObstacleException(f"ObstacleParams must be positive: {', '.join(bad)}")
        if not 3 <= self.window_cells <= 6:
            raise ObstacleException(f"window_cells must be 3..6 (thesis 5.1.1), got {self.window_cells}")
        if not 0 < self.max_slope_rad < math.pi / 2:
            raise ObstacleException(f"max_slope_rad must be in (0, pi/2), got {self.max_slope_rad}")
        if self.inf_depth_m is not None and not self.inf_depth_m > 0:
            raise ObstacleException(f"inf_depth_m must be positive or None, got {self.inf_depth_m}")
        if self.cell_height not in tuple(CellHeight):
            raise ObstacleException(f"cell_height must be one of {[c.value for c in CellHeight]}, got {self.cell_height!r}")
        object.__setattr__(self, "cell_height", CellHeight(self.cell_height))


def _lattice_centers(origin: tuple[int, int], shape: tuple[int, int], resolution_m: float) -> np.ndarray:
    """Centres (nx, ny, 2) of the cells ``origin + (i, j)`` of the lattice ``floor(xy / resolution)``."""
    x = (origin[0] + np.arange(shape[0]) + 0.5) * resolution_m
    y = (origin[1] + np.arange(shape[1]) + 0.5) * resolution_m
    return np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1)


@dataclass(frozen=True, eq=False)
class HeightMap:
    """Gravity-aligned 2.5D map of one depth image with its step classification (thesis 5.1.1).

    Cell ``[i, j]`` covers ``[(origin[0] + i) r, (origin[0] + i + 1) r)`` in x and likewise in y
    (``r = resolution_m``). Arrays are (nx, ny); NaN where the cell holds no point.
    """

    resolution_m: float
    origin: tuple[int, int]
    height: np.ndarray  # cell height (mean or max of its points)
    h_diff: np.ndarray  # max - min cell height in the window
    threshold: np.ndarray  # h_max + Δd (eq. 5.4)
    traversability: np.ndarray  # h_diff / threshold, at least the steep-drop ratio and s_min / tan(max slope) at negative edges

    @property
    def obstacles(self) -> np.ndarray:
        """Untraversable cells: traversability above 1."""
        with np.errstate(invalid="ignore"):
            return self.traversability > 1

    def cell_centers(self) -> np.ndarray:
        """Centres (nx, ny, 2) of the cells in the gravity frame."""
        return _lattice_centers(self.origin, self.height.shape, self.resolution_m)


@dataclass(frozen=True, eq=False)
class Classification:
    """Obstacle classification of one depth image (``classify_depth``)."""

    edges: np.ndarray  # (H, W) bool: near-side pixels of negative edges
    edge_min_slope: np.ndarray  # (H, W) s_min (eq. 5.1) at near-side pixels of depth jumps, NaN elsewhere
    height_map: HeightMap
    pixel_obstacles: np.ndarray  # (H, W) bool: negative edge, or the pixel's point lies in an obstacle cell
    pixel_classified: np.ndarray  # (H, W) bool: the pixels the classification read (classified_pixels); flags hold there only


# --------------------------------------------------------------------------- inputs


def _check_inputs(depth: np.ndarray, calibration: StereoCalibration, T_gravity_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth as float32 with non-positive values NaN; rotation and translation of the pose."""
    depth = np.asarray(depth)
    if depth.shape != (calibration.height, calibration.width):
        raise ObstacleException(f"depth: expected shape ({calibration.height}, {calibration.width}) from the calibration, got {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise ObstacleException(f"depth: expected a float image (metres), got {depth.dtype}")
    T = np.asarray(T_gravity_cam, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ObstacleException(f"T_gravity_cam must be a finite 4x4 pose, got shape {T.shape}")
    R = T[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0 and np.allclose(T[3], [0, 0, 0, 1])):
        raise ObstacleException("T_gravity_cam must be a rigid transform: orthonormal rotation with det +1, last row [0, 0, 0, 1]")
    depth = depth.astype(np.float32)
    with np.errstate(invalid="ignore"):
        depth[~(depth > 0)] = np.nan
    return depth, R, T[:3, 3]


def _gravity_points(depth: np.ndarray, calibration: StereoCalibration, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points (3, H, W) in the gravity frame, float32: the back-projection of
    ``slam.stereo.depth_to_points`` (ray ``((u - cx) / f, (v - cy) / f, 1)`` times z-depth),
    rotated per coordinate with broadcasting (1 ms at 640x480; the (H, W, 3) @ (3, 3) product took 8 ms)."""
    f = calibration.focal_px
    xn = ((np.arange(calibration.width) - calibration.cx) / f).astype(np.float32)[None, :]
    yn = ((np.arange(calibration.height) - calibration.cy) / f).astype(np.float32)[:, None]
    Rf, tf = R.astype(np.float32), t.astype(np.float32)
    pts = np.empty((3, *depth.shape), dtype=np.float32)
    with np.errstate(invalid="ignore"):
        for k in range(3):
            pts[k] = depth * (Rf[k, 0] * xn + Rf[k, 1] * yn + Rf[k, 2]) + tf[k]
    return pts


def classified_pixels(depth: np.ndarray, calibration: StereoCalibration, params: ObstacleParams) -> np.ndarray:
    """The pixels the classification reads (bool (H, W)): a depth whose error (eq. 5.2c) is
    within ``max_error_m`` even at the farthest depth its stereo error allows
    (:func:`slam.stereo.farthest_depth`). SGBM's sub-pixel disparities lock to whole pixels
    (on Etna a quarter of them are integers, against a sixteenth if they were spread
    evenly), so a point measured at the cut may lie up to half a pixel of disparity beyond
    it, placed too near; the last 4 cm before the cut held 57 % of the falsely flagged step
    pixels (docs/mapping.md). The cut falls at 2.40 m instead of 2.54 m for the LRU at 320x240."""
    far = farthest_depth(np.asarray(depth, dtype=float), calibration, params.pixel_error)
    return far <= max_depth_for_error(calibration, params.max_error_m, params.pixel_error)  # NaN and inf: False


def _prepare(
    depth: np.ndarray, calibration: StereoCalibration, T_gravity_cam: np.ndarray, params: ObstacleParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Checked inputs: the depth the negative-edge search reads (inf as ``inf_depth_m`` or no
    data), its gravity-frame points (3, H, W), the pixels within the far cut (eq. 5.2c), R, t."""
    depth, R, t = _check_inputs(depth, calibration, T_gravity_cam)
    in_range = classified_pixels(depth, calibration, params)
    inf_depth = np.float32(np.nan if params.inf_depth_m is None else params.inf_depth_m)
    depth_e = np.where(np.isinf(depth), inf_depth, depth)
    return depth_e, _gravity_points(depth_e, calibration, R, t), in_range, R, t


# --------------------------------------------------------------------------- negative edges


@numba.njit(cache=True, nogil=True)
def _previous_valid(depth):
    """Top to bottom in every column (thesis 5.1.1): the row of the previous finite pixel above
    each pixel (-1: none) and its depth (NaN: none)."""
    h, w = depth.shape
    prev = np.empty((h, w), np.int32)
    z_prev = np.empty((h, w), depth.dtype)
    for c in range(w):
        last_row = -1
        last_z = np.nan
        for r in range(h):
            prev[r, c] = last_row
            z_prev[r, c] = last_z
            if np.isfinite(depth[r, c]):
                last_row = r
                last_z = depth[r, c]
    return prev, z_prev


def _negative_edges(
    depth: np.ndarray, pts: np.ndarray, near_ok: np.ndarray, camera: np.ndarray, calibration: StereoCalibration, params: ObstacleParams
) -> tuple[np.ndarray, np.ndarray]:
    """Negative edges of a depth image (NaN: no data) with its gravity-frame points (3, H, W)
    and the camera centre in that frame; only pixels in ``near_ok`` can be the near side."""
    h, w = depth.shape
    valid = np.isfinite(depth)
    prev, z_prev = _previous_valid(depth)
    with np.errstate(invalid="ignore"):
        jump = valid & (np.abs(depth - z_prev) >= params.edge_jump_m)  # NaN where no valid pixel above
    v, c = np.nonzero(jump)
    pv = prev[v, c]
    cur_near = depth[v, c] < z_prev[v, c]
    nv, fv = np.where(cur_near, v, pv), np.where(cur_near, pv, v)
    keep = near_ok[nv, c]
    nv, fv, c = nv[keep], fv[keep], c[keep]
    p, q = pts[:, nv, c].astype(float), pts[:, fv, c].astype(float)
    # a far side beyond the mapping range is as near as its stereo error allows (its depth is
    # uncertain by metres there), and no cliff hides behind a far side that may be no farther
    z_q = depth[fv, c].astype(float)
    z_near = np.where(near_ok[fv, c], z_q, nearest_depth(z_q, calibration, params.pixel_error))
    q = camera[:, None] + (q - camera[:, None]) * (z_near / z_q)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_min = (p[2] - q[2]) / np.hypot(q[0] - p[0], q[1] - p[1])  # eq. 5.1
    # a drop no higher than a step the robot drives over is no cliff, however steep (docs/mapping.md)
    s_min[~((p[2] - q[2] > params.step_height_m) & (z_near > depth[nv, c]))] = np.nan
    min_slope = np.full((h, w), np.nan)
    np.fmax.at(min_slope, (nv, c), s_min)
    with np.errstate(invalid="ignore"):
        edges = min_slope > math.tan(params.max_slope_rad)
    return edges, min_slope


def negative_edges(
    depth: np.ndarray, calibration: StereoCalibration, T_gravity_cam: np.ndarray, params: ObstacleParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Negative edges (cliff rims) in a z-depth image (thesis 5.1.1, eq. 5.1).

    Returns ``(edges, min_slope)``: a bool (H, W) mask of the near-side pixels whose minimal
    hidden slope ``s_min`` exceeds ``tan(max_slope_rad)``, and ``s_min`` itself at the near-side
    pixels of all depth jumps whose drop exceeds ``step_height_m`` (NaN elsewhere; the larger
    value where a pixel is near side twice).
    Near pixels beyond the far cut (``max_error_m``) are not classified.
    """
    params = params or ObstacleParams()
    depth_e, pts, in_range, _, t = _prepare(depth, calibration, T_gravity_cam, params)
    return _negative_edges(depth_e, pts, in_range, t, calibration, params)


# --------------------------------------------------------------------------- steps


def _window_extreme(height: np.ndarray, k: int, highest: bool) -> tuple[np.ndarray, np.ndarray]:
    """Highest (or lowest) cell height in the k x k window of every cell (offsets
    ``-((k - 1) // 2) .. k // 2``) and the (di, dj) offset (nx, ny, 2) of the cell holding it.
    Empty cells (NaN) are skipped; ties go to the first cell in row-major window order."""
    nx, ny = height.shape
    before = (k - 1) // 2
    fill = -np.inf if highest else np.inf
    padded = np.pad(np.where(np.isnan(height), fill, height), ((before, k - 1 - before),) * 2, constant_values=fill)
    windows = sliding_window_view(padded, (k, k)).reshape(nx, ny, k * k)
    best = (np.argmax if highest else np.argmin)(windows, axis=-1)
    value = np.take_along_axis(windows, best[..., None], axis=-1)[..., 0]
    return value, np.stack(np.divmod(best, k), axis=-1) - before


def _step_cells(
    pts: np.ndarray, R: np.ndarray, t: np.ndarray, calibration: StereoCalibration, params: ObstacleParams
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stereo-error-adaptive step classification of gravity-frame points (3, N): the grid's
    origin, cell height, h_diff and threshold h_max + Δd (eq. 5.4), and each point's flat cell index."""
    res = params.resolution_m
    if pts.shape[1] == 0:
        empty = np.zeros((0, 0))
        return (0, 0), empty, empty, empty, np.zeros(0, dtype=np.int64)
    i = np.floor(pts[0] / res).astype(np.int64)
    j = np.floor(pts[1] / res).astype(np.int64)
    lo = np.array([i.min(), j.min()])
    nx, ny = int(i.max() - lo[0] + 1), int(j.max() - lo[1] + 1)
    flat = (i - lo[0]) * ny + (j - lo[1])
    count = np.bincount(flat, minlength=nx * ny)
    if params.cell_height == CellHeight.MEAN:
        with np.errstate(invalid="ignore"):
            height = np.bincount(flat, weights=pts[2], minlength=nx * ny) / count
    else:
        height = np.full(nx * ny, -np.inf)
        np.maximum.at(height, flat, pts[2].astype(float))
    height[count == 0] = np.nan
    height = height.reshape(nx, ny)

    top, top_at = _window_extreme(height, params.window_cells, highest=True)
    bottom, bottom_at = _window_extreme(height, params.window_cells, highest=False)
    has = ~np.isnan(height)
    cells = np.argwhere(has)
    # eq. 5.4 for the centre points of the highest and the lowest cell, back in the camera frame (thesis 5.1.1)
    p = np.column_stack([(lo + cells + top_at[has] + 0.5) * res, top[has]])
    q = np.column_stack([(lo + cells + bottom_at[has] + 0.5) * res, bottom[has]])
    delta_d = distance_error((p - t) @ R, (q - t) @ R, calibration, params.pixel_error)  # NaN for p == q: no step
    h_diff = np.full((nx, ny), np.nan)
    threshold = np.full((nx, ny), np.nan)
    h_diff[has] = top[has] - bottom[has]
    threshold[has] = params.step_height_m + np.nan_to_num(delta_d, nan=0.0)
    return (int(lo[0]), int(lo[1])), height, h_diff, threshold, flat


_ON_LINE_M = 0.002  # ground this close to the line counts as below it (a plane slope lies on it)


def slope_reach_cells(params: ObstacleParams) -> int:
    """Cells within which a drop of ``h_max`` is steeper than the maximal slope:
    ``h_max / tan(max_slope)`` (0.41 m, 8 cells by default)."""
    return int(params.step_height_m / math.tan(params.max_slope_rad) / params.resolution_m)


@functools.cache
def _descent_lines(reach: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets (K, 2) of the cells within ``reach`` cells, the cells (K, reach - 1, 2) that
    the line to each crosses (rounded; unused slots repeat the start) and their place on
    the line (K, reach - 1) as a fraction of its length."""
    offsets = np.array([(di, dj) for di in range(-reach, reach + 1) for dj in range(-reach, reach + 1) if 0 < di * di + dj * dj <= reach * reach])
    between = np.zeros((len(offsets), max(reach - 1, 1), 2), np.int64)
    along = np.zeros(between.shape[:2])
    for k, (di, dj) in enumerate(offsets):
        steps = max(abs(di), abs(dj))
        cells = np.rint(np.outer(np.arange(1, steps) / steps, (di, dj))).astype(np.int64)
        between[k, : steps - 1] = cells
        along[k, : steps - 1] = cells @ (di, dj) / (di * di + dj * dj)
    return offsets, between, along


def steep_drops(height: np.ndarray, params: ObstacleParams, margin: np.ndarray | float = 0.0) -> np.ndarray:
    """Slope ratio (nx, ny) of the cells of a 2.5D height map (NaN: no data) from which the
    surface falls by more than the robot can drive down, where it is seen: eq. 5.1's
    condition (a drop above ``h_max`` at more than the maximal slope) for visible ground,
    which the window's step test (threshold of eq. 5.4) misses for slopes between the
    maximal slope and about ``atan(h_max / window)``. For each cell ``p`` and each cell ``q`` within
    :func:`slope_reach_cells` whose surface between them lies below the line ``pq`` (the
    descent starts at ``p``), the ratio is ``(h_p - h_q) / (h_max + margin_p)``; above 1 the
    cell is untraversable. ``margin`` (a cell array or a number) is the height error the
    test tolerates (the stereo error of eq. 5.4 for measured maps). These are the rims of
    cliffs and the cells of too steep slopes, not the flat before a cliff (the ground between
    it and the drop rises above the line). Our addition to thesis 5.1.1 (docs/mapping.md)."""
    reach = slope_reach_cells(params)
    nx, ny = height.shape
    ratio = np.zeros((nx, ny))
    if reach < 1:  # a drop of h_max is steeper than the maximal slope only within a cell: no test at this resolution
        return ratio
    offsets, between, along = _descent_lines(reach)
    limit = params.step_height_m + np.broadcast_to(np.asarray(margin, float), (nx, ny))
    padded = np.pad(np.asarray(height, float), reach, constant_values=np.nan)
    cells = np.argwhere(np.isfinite(height))
    chunk = max(1, 2_000_000 // len(offsets))
    for start in range(0, len(cells), chunk):
        i, j = cells[start : start + chunk].T
        h, lim = height[i, j], limit[i, j]
        with np.errstate(invalid="ignore"):
            drop = h[:, None] - padded[i[:, None] + reach + offsets[:, 0], j[:, None] + reach + offsets[:, 1]]
            c, k = np.nonzero(drop > lim[:, None])
        if len(c) == 0:
            continue
        ground = padded[i[c, None] + reach + between[k, :, 0], j[c, None] + reach + between[k, :, 1]]
        line = h[c, None] - drop[c, k, None] * along[k] + _ON_LINE_M
        with np.errstate(invalid="ignore"):
            below = np.all(ground <= line, axis=1)
        np.fmax.at(ratio, (i[c[below]], j[c[below]]), drop[c[below], k[below]] / lim[c[below]])
    return ratio


def classify_depth(
    depth: np.ndarray, calibration: StereoCalibration, T_gravity_cam: np.ndarray, params: ObstacleParams | None = None
) -> Classification:
    """Negative edges and stereo-error-adaptive steps of one z-depth image (thesis 5.1.1,
    eq. 5.1-5.4), with the per-pixel obstacle flag for the image's points.

    ``depth`` (H, W) in metres of the left rectified camera described by ``calibration``
    (its baseline sets the stereo error); ``T_gravity_cam`` the camera's pose in a
    gravity-aligned frame (z up). A pixel is an obstacle if it is a negative edge or its point
    falls into a cell with traversability above 1; pixels without a point (no data, beyond the
    far cut) are not, unless they are an edge. ``pixel_classified`` marks the pixels read
    (edges lie among them): beyond them a pixel's flag says nothing.
    """
    params = params or ObstacleParams()
    depth_e, pts, in_range, R, t = _prepare(depth, calibration, T_gravity_cam, params)
    edges, min_slope = _negative_edges(depth_e, pts, in_range, t, calibration, params)

    origin, height, h_diff, threshold, flat = _step_cells(np.compress(in_range.ravel(), pts.reshape(3, -1), axis=1), R, t, calibration, params)
    traversability = np.fmax(h_diff / threshold, steep_drops(height, params, threshold - params.step_height_m))
    edge_cells = np.floor(pts[:2, edges] / params.resolution_m).astype(np.int64) - np.array(origin)[:, None]  # edges lie in range
    np.fmax.at(traversability, tuple(edge_cells), min_slope[edges] / math.tan(params.max_slope_rad))
    traversability = traversability.ravel()
    pixel_obstacles = edges.copy()
    with np.errstate(invalid="ignore"):
        pixel_obstacles[in_range] |= traversability[flat] > 1
    height_map = HeightMap(params.resolution_m, origin, height, h_diff, threshold, traversability.reshape(height.shape))
    return Classification(edges, min_slope, height_map, pixel_obstacles, in_range)


# --------------------------------------------------------------------------- rolling map


class RollingObstacleMap:
    """Robot-centred local obstacle map of fixed size (thesis 5.1.1, "Local Obstacle Maps").

    A square grid of ``size_m`` on the lattice ``floor(xy / resolution_m)`` of the gravity frame,
    always holding the robot's cell at index ``n // 2``. ``update`` scrolls it to the robot
    (cells that stay in view keep their value, the others are forgotten) and fuses a height
    map's traversability by an exponential low-pass ``v <- (1 - rate) v + rate t`` per observed
    cell, starting from 0 (traversable) for unknown cells.
    """

    def __init__(self, resolution_m: float = 0.05, size_m: float = 10.0, rate: float = 0.3, center_xy: tuple[float, float] = (0.0, 0.0)):
        if not (resolution_m > 0 and size_m > 0):
            raise ObstacleException(f"resolution_m and size_m must be positive, got {resolution_m} and {size_m}")
        if not 0 < rate <= 1:
            raise ObstacleException(f"rate must be in (0, 1], got {rate}")
        self.resolution_m = float(resolution_m)
        self.n = round(size_m / resolution_m)
        if self.n < 1:
            raise ObstacleException(f"size_m={size_m} is smaller than one cell of {resolution_m} m")
        self.rate = float(rate)
        self._value = np.full((self.n, self.n), np.nan)
        self.origin = self._origin_for(center_xy)

    def _origin_for(self, xy: tuple[float, float]) -> tuple[int, int]:
        xy = np.asarray(xy, dtype=float)
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ObstacleException(f"robot position must be a finite (x, y), got {xy!r}")
        i, j = np.floor(xy / self.resolution_m).astype(np.int64) - self.n // 2
        return int(i), int(j)

    @property
    def traversability(self) -> np.ndarray:
        """Low-passed traversability (n, n), read-only; NaN for cells never observed since they scrolled in."""
        view = self._value.view()
        view.flags.writeable = False
        return view

    @property
    def obstacles(self) -> np.ndarray:
        """Untraversable cells (n, n): traversability above 1."""
        with np.errstate(invalid="ignore"):
            return self._value > 1

    def cell_centers(self) -> np.ndarray:
        """Centres (n, n, 2) of the cells in the gravity frame."""
        return _lattice_centers(self.origin, (self.n, self.n), self.resolution_m)

    def recenter(self, robot_xy: tuple[float, float]) -> None:
        """Scroll the grid so that the robot's cell is at ``n // 2``."""
        origin = self._origin_for(robot_xy)
        if origin == self.origin:
            return
        value = np.full_like(self._value, np.nan)
        overlap = _overlap(self._value.shape, self.origin, value.shape, origin)
        if overlap is not None:
            value[overlap[1]] = self._value[overlap[0]]
        self._value, self.origin = value, origin

    def update(self, height_map: HeightMap, robot_xy: tuple[float, float]) -> None:
        """Scroll to ``robot_xy`` and low-pass the cells ``height_map`` observed into the map."""
        if not math.isclose(height_map.resolution_m, self.resolution_m):
            raise ObstacleException(f"height map resolution {height_map.resolution_m} m differs from the map's {self.resolution_m} m")
        self.recenter(robot_xy)
        overlap = _overlap(height_map.traversability.shape, height_map.origin, self._value.shape, self.origin)
        if overlap is None:
            return
        obs = height_map.traversability[overlap[0]]
        seen = np.isfinite(obs)
        cells = self._value[overlap[1]]  # a view: written in place
        cells[seen] = (1 - self.rate) * np.nan_to_num(cells[seen], nan=0.0) + self.rate * obs[seen]


def _overlap(
    shape_a: tuple[int, int], origin_a: tuple[int, int], shape_b: tuple[int, int], origin_b: tuple[int, int]
) -> tuple[tuple[slice, ...], tuple[slice, ...]] | None:
    """Slices into grid a and grid b (both on the lattice, given by shape and origin) that cover
    the same cells; None if they share none."""
    slices_a, slices_b = [], []
    for na, oa, nb, ob in zip(shape_a, origin_a, shape_b, origin_b):
        lo, hi = max(oa, ob), min(oa + na, ob + nb)
        if lo >= hi:
            return None
        slices_a.append(slice(lo - oa, hi - oa))
        slices_b.append(slice(lo - ob, hi - ob))
    return tuple(slices_a), tuple(slices_b)
