"""Map quality against the simulator's true geometry (docs/mapping.md; the thesis had no
ground-truth maps, so these metrics are ours).

The true surface is the triangulated heightfield (exact, ``Terrain.height_at``) plus the
rock hulls, sampled densely; the lander's footprint is left out of both (its geometry is
a handful of MJCF primitives that the metrics would need to sample separately), and map
points inside it are counted, not scored. Other robots are not part of the true static
surface: map points on them count as errors, as they would for a map user.

- **accuracy**: distance from every map point to the nearest true-surface sample (median,
  p95, share within 0.1 m); the sample spacing bounds the distance's overestimate by
  ``spacing / sqrt(2)``;
- **completeness**: share of the true surface within the explored area that has a map
  point within ``completeness_radius_m``; the explored area is the set of
  ``explored_cell_m`` cells holding at least one map point;
- **obstacles**: the true obstacle cells are those of a 2.5D height map of the true
  surface (top of terrain or rock) that the robot's classification criterion (thesis
  5.1.1, the robot's :class:`slam.obstacles.ObstacleParams`) calls impassable without
  stereo error: a window height difference above the step height ``h_max``, or a cell from
  which the surface drops by more than ``h_max`` at more than the maximal slope (the
  negative-edge rule, eq. 5.1, with its drop condition, on every surface: cliff rims and
  slopes too steep to drive, as the classification tests its visible ground); precision
  of the map's obstacle points' cells against the true cells its points cover, recall
  within the cells its classified points cover (``slam.submap.Submap.classified``: points
  beyond the classification's range carry no verdict), with one cell of tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation, maximum_filter, minimum_filter
from scipy.spatial import ConvexHull, cKDTree

from sim.world.lander import LANDER_RADIUS
from sim.world.terrain import Terrain
from slam.obstacles import ObstacleParams, slope_reach_cells, steep_drops


@dataclass(frozen=True)
class MapQualityParams:
    surface_spacing_m: float = 0.02
    completeness_radius_m: float = 0.1
    explored_cell_m: float = 0.5
    lander_margin_m: float = 0.2
    obstacle: ObstacleParams = field(default_factory=ObstacleParams)  # the robot's classification criterion

    @property
    def robot_margin_m(self) -> float:
        """Beyond a robot's body radius, how far its surroundings are left out of the
        scores: the classification window's half-width and one cell (a ground cell that
        close has the robot in its window and is rightly flagged for it)."""
        return (self.obstacle.window_cells // 2 + 1) * self.obstacle.resolution_m


class MapEvaluationError(ValueError):
    """A map that cannot be scored (no points, points off the terrain)."""


def _rock_surface(terrain: Terrain, spacing: float, bounds: tuple[tuple[float, float], tuple[float, float]]) -> np.ndarray:
    """Points on the rock hulls' faces above the ground, about ``spacing`` apart (world frame),
    of the rocks that reach into ``bounds`` ((x0, y0), (x1, y1))."""
    (x0, y0), (x1, y1) = bounds
    out = []
    for rock in terrain.rocks:
        reach = float(np.linalg.norm(rock.vertices[:, :2], axis=1).max())  # the hull within this of its centre in xy
        if not (x0 - reach <= rock.center[0] <= x1 + reach and y0 - reach <= rock.center[1] <= y1 + reach):
            continue
        hull = ConvexHull(rock.vertices)
        c, s = math.cos(rock.yaw), math.sin(rock.yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        for tri in hull.simplices:
            a, b, d = rock.vertices[tri]
            n = max(1, math.ceil(max(np.linalg.norm(b - a), np.linalg.norm(d - a)) / spacing))
            u, v = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            keep = u + v <= n
            u, v = u[keep] / n, v[keep] / n
            pts = a + u[:, None] * (b - a) + v[:, None] * (d - a)
            out.append(pts @ R.T + rock.center)
    if not out:
        return np.zeros((0, 3))
    pts = np.concatenate(out)
    return pts[pts[:, 2] >= terrain.height_at(pts[:, 0], pts[:, 1]) - 1e-3]  # the buried part is not surface


def _cell_keys(xy: np.ndarray, cell: float) -> np.ndarray:
    """One int64 per ``floor(xy / cell)`` cell (both indices within +-2^31)."""
    c = np.floor(xy / cell).astype(np.int64)
    return (c[:, 0] << 32) + (c[:, 1] + (1 << 31))


def _outside_lander(terrain: Terrain, xy: np.ndarray, margin: float) -> np.ndarray:
    if terrain.lander is None:
        return np.ones(len(xy), bool)
    return np.hypot(*(xy - np.asarray(terrain.lander.xy)).T) > LANDER_RADIUS + margin


class SurfaceTruth:
    """Dense samples of the true static surface within ``bounds`` ((x0, y0), (x1, y1))."""

    def __init__(self, terrain: Terrain, bounds: tuple[tuple[float, float], tuple[float, float]], params: MapQualityParams):
        (x0, y0), (x1, y1) = bounds
        half = terrain.size_m / 2
        x0, y0, x1, y1 = max(x0, -half), max(y0, -half), min(x1, half), min(y1, half)
        if not (x1 > x0 and y1 > y0):
            raise MapEvaluationError(f"map bounds {bounds} do not overlap the {terrain.size_m} m terrain")
        sp = params.surface_spacing_m
        gx, gy = np.meshgrid(np.arange(x0, x1 + sp / 2, sp), np.arange(y0, y1 + sp / 2, sp), indexing="ij")
        gx, gy = gx.ravel(), gy.ravel()
        ground = np.column_stack([gx, gy, terrain.height_at(gx, gy)])
        covered = terrain.surface_height_at(gx, gy) > ground[:, 2] + 1e-3  # under a rock: not visible
        ground = ground[~covered]
        rocks = _rock_surface(terrain, sp, ((x0, y0), (x1, y1)))
        if len(rocks):
            inside = (rocks[:, 0] >= x0) & (rocks[:, 0] <= x1) & (rocks[:, 1] >= y0) & (rocks[:, 1] <= y1)
            rocks = rocks[inside]
        pts = np.concatenate([ground, rocks])
        self.points = pts[_outside_lander(terrain, pts[:, :2], params.lander_margin_m)]
        self.tree = cKDTree(self.points)


def true_step_and_drop(terrain: Terrain, origin: np.ndarray, shape: tuple[int, int], params: ObstacleParams) -> tuple[np.ndarray, np.ndarray]:
    """The classification criterion's two measures on the true surface (terrain or rock top,
    sampled at the cell centres) for the (nx, ny) cells ``origin + (i, j)`` (lattice
    ``floor(xy / cell)``): the window height difference and the steep-drop ratio
    (:func:`slam.obstacles.steep_drops` without a margin). The surface is sampled beyond
    the grid so that drops at its edge see their foot."""
    cell = params.resolution_m
    pad = max(slope_reach_cells(params), params.window_cells)
    i = (origin[0] - pad + np.arange(shape[0] + 2 * pad) + 0.5) * cell
    j = (origin[1] - pad + np.arange(shape[1] + 2 * pad) + 0.5) * cell
    cx, cy = np.meshgrid(i, j, indexing="ij")
    h = terrain.surface_height_at(cx.ravel(), cy.ravel()).reshape(cx.shape)
    k = params.window_cells
    h_diff = maximum_filter(h, size=k, mode="nearest") - minimum_filter(h, size=k, mode="nearest")
    inner = (slice(pad, pad + shape[0]), slice(pad, pad + shape[1]))
    return h_diff[inner], steep_drops(h, params)[inner]


def true_obstacle_cells(terrain: Terrain, origin: np.ndarray, shape: tuple[int, int], params: MapQualityParams) -> np.ndarray:
    """Bool (nx, ny) grid of cells ``origin + (i, j)`` (lattice ``floor(xy / cell)``) that the
    classification criterion calls impassable on the true surface (:func:`true_step_and_drop`):
    a window height difference above the step height, or a drop above the step height
    steeper than the maximal slope; the lander's footprint is an obstacle."""
    o = params.obstacle
    h_diff, drop = true_step_and_drop(terrain, origin, shape, o)
    centres = (np.asarray(origin)[None, None, :] + np.stack(np.indices(shape), axis=-1) + 0.5) * o.resolution_m
    lander = ~_outside_lander(terrain, centres.reshape(-1, 2), 0.0).reshape(shape)
    return (h_diff > o.step_height_m) | (drop > 1) | lander


@dataclass(frozen=True, eq=False)
class ObstacleScore:
    """Obstacle cells of a map against the true ones (cells of the classification's
    ``resolution_m``; centres (k, 2) in the world for the plot): flagged and true (``tp``),
    flagged only (``fp``), true only (``missed``, true cells the map's classified points
    cover that no flagged cell is next to)."""

    precision: float | None
    recall: float | None
    mapped_cells: int
    true_cells_seen: int
    points_on_robots: int
    obstacle_points_on_robots: int
    tp_xy: np.ndarray
    fp_xy: np.ndarray
    missed_xy: np.ndarray

    def metrics(self) -> dict:
        keys = ("precision", "recall", "mapped_cells", "true_cells_seen", "points_on_robots", "obstacle_points_on_robots")
        return {k: getattr(self, k) for k in keys}


@dataclass(frozen=True, eq=False)
class MapQuality:
    accuracy: dict
    completeness: dict
    obstacles: ObstacleScore

    def metrics(self) -> dict:
        return {"accuracy": self.accuracy, "completeness": self.completeness, "obstacles": self.obstacles.metrics()}


def score_obstacles(
    pts: np.ndarray,
    obstacle: np.ndarray,
    terrain: Terrain,
    params: MapQualityParams,
    on_robots: np.ndarray | None = None,
    classified: np.ndarray | None = None,
) -> ObstacleScore:
    """Precision and recall of the obstacle flags of world points (n, 3), with one cell of
    tolerance. Recall counts the true cells that ``classified`` points cover (None: every
    point was classified): beyond the classification's range a point carries no verdict, so
    a true cell only such points saw is not a miss. Precision is judged against the true
    cells any point covers (a flagged cell is classified; its true neighbour may have been
    seen only from farther away). Points ``on_robots`` (seen on a robot, which the static
    truth does not hold) are neither scored nor count as covering a cell."""
    on_robots = np.zeros(len(pts), bool) if on_robots is None else np.asarray(on_robots, bool)
    known = np.ones(len(pts), bool) if classified is None else np.asarray(classified, bool)
    oc = params.obstacle.resolution_m
    cells = np.floor(pts[~on_robots, :2] / oc).astype(np.int64)
    flagged, known = obstacle[~on_robots], known[~on_robots]
    empty = np.zeros((0, 2))
    if len(cells) == 0:
        return ObstacleScore(None, None, 0, 0, int(on_robots.sum()), int((on_robots & obstacle).sum()), empty, empty, empty)
    origin = cells.min(axis=0) - params.obstacle.window_cells
    shape = tuple(int(v) for v in cells.max(axis=0) - origin + params.obstacle.window_cells + 1)

    def grid(of: np.ndarray) -> np.ndarray:
        out = np.zeros(shape, bool)
        out[tuple((cells[of] - origin).T)] = True
        return out

    mapped = grid(flagged)
    true_seen = true_obstacle_cells(terrain, origin, shape, params) & grid(np.ones(len(cells), bool))
    true = true_seen & grid(known)
    one = np.ones((3, 3), bool)
    tp = mapped & binary_dilation(true_seen, one)
    found = true & binary_dilation(mapped, one)

    def centres(mask):
        return (np.argwhere(mask) + origin + 0.5) * oc

    return ObstacleScore(
        precision=float(tp.sum() / mapped.sum()) if mapped.any() else None,
        recall=float(found.sum() / true.sum()) if true.any() else None,
        mapped_cells=int(mapped.sum()),
        true_cells_seen=int(true.sum()),
        points_on_robots=int(on_robots.sum()),
        obstacle_points_on_robots=int((on_robots & obstacle).sum()),
        tp_xy=centres(tp),
        fp_xy=centres(mapped & ~tp),
        missed_xy=centres(true & ~found),
    )


def map_quality(
    points_world: np.ndarray,
    obstacle: np.ndarray,
    terrain: Terrain,
    params: MapQualityParams | None = None,
    on_robots: np.ndarray | None = None,
    classified: np.ndarray | None = None,
) -> MapQuality:
    """Accuracy, completeness and obstacle precision/recall of a map (points in the world
    frame, (n, 3), with their obstacle flags) against the terrain it was built on; points
    ``on_robots`` (bool (n,)) are left out of the obstacle scores, which cover only the
    ``classified`` points (bool (n,); None: all) (:func:`score_obstacles`)."""
    params = params or MapQualityParams()
    pts = np.asarray(points_world, float)
    obstacle = np.asarray(obstacle, bool)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or obstacle.shape != (len(pts),):
        raise MapEvaluationError(f"need (n, 3) points with n >= 1 and (n,) obstacle flags, got {pts.shape} and {obstacle.shape}")
    for name, mask in (("on_robots", on_robots), ("classified", classified)):
        if mask is not None and np.shape(mask) != (len(pts),):
            raise MapEvaluationError(f"{name} must have shape ({len(pts)},), got {np.shape(mask)}")
    scored = _outside_lander(terrain, pts[:, :2], params.lander_margin_m)
    if not scored.any():
        raise MapEvaluationError("every map point lies on the lander")
    lo, hi = pts[:, :2].min(axis=0) - 1.0, pts[:, :2].max(axis=0) + 1.0
    truth = SurfaceTruth(terrain, ((lo[0], lo[1]), (hi[0], hi[1])), params)

    dist, _ = truth.tree.query(pts[scored])
    accuracy = {
        "median_m": float(np.median(dist)),
        "p95_m": float(np.percentile(dist, 95)),
        "within_0_1_m": float(np.mean(dist <= 0.1)),
        "points": int(scored.sum()),
        "points_on_lander": int((~scored).sum()),
    }

    ec = params.explored_cell_m
    explored = np.unique(_cell_keys(pts[:, :2], ec))
    surface = truth.points[np.isin(_cell_keys(truth.points[:, :2], ec), explored)]
    near, _ = cKDTree(pts).query(surface, distance_upper_bound=params.completeness_radius_m)
    completeness = {
        "share": float(np.mean(np.isfinite(near))) if len(surface) else 0.0,
        "explored_area_m2": float(len(explored) * ec * ec),
        "surface_samples": len(surface),
    }
    return MapQuality(accuracy, completeness, score_obstacles(pts, obstacle, terrain, params, on_robots, classified))
