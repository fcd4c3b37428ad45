"""Graph-based 2D path planning on the rolling obstacle map (thesis 5.1.1 and 9.2.2).

The LRU "used a fast, graph-based 2D path planner to navigate autonomously between
waypoints, taking into account the surrounding obstacles via its local terrain
classification maps" (thesis 9.2.2); the thesis does not describe the planner itself.
This one is the textbook version, written on SciPy: the map's cells are pooled to a
coarser planning grid, obstacles are grown by the robot's radius with a Euclidean
distance transform (``scipy.ndimage``), and Dijkstra's algorithm
(``scipy.sparse.csgraph``) runs on the 8-connected grid, each edge weighted by its length
times a cost that rises near obstacles and through cells never observed.

Pure: a traversability grid (``slam.obstacles.RollingObstacleMap``'s, NaN for unknown, above
1 untraversable) on the lattice ``floor(xy / resolution)`` with its origin cell, and start
and goal in the same gravity-aligned frame, in; a polyline out.

A goal the path cannot reach is approached as far as the map allows. Beyond the map,
the path ends at the reachable cell on the map's border that minimises ``path cost +
straight-line distance to the goal`` (the unknown beyond costs at least its length; only
border cells, since by the triangle inequality the start itself would otherwise always
score best). Inside the map (the goal in an obstacle, or walled in), it ends at the
reachable cell minimising ``path cost + FAR_WEIGHT x distance to the goal``, as close to the
goal as the map allows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_array
from scipy.sparse.csgraph import dijkstra

#: Weight of the straight-line rest to a goal inside the map that the path cannot reach.
FAR_WEIGHT = 20.0

_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))  # half of the 8-neighbourhood; edges are undirected


class PlannerException(ValueError):
    """Bad input to the planner (shapes, parameters, positions)."""


@dataclass(frozen=True)
class PlannerParams:
    """Planning grid and costs. ``radius_m``: obstacles grown by this much (the robot's
    half width and a margin); ``margin_m``: beyond it, a band where the cost rises towards
    obstacles by up to ``margin_cost``; ``unknown_cost``: extra cost through unobserved
    cells, so that seen free ground is preferred but the unknown stays passable."""

    cell_m: float = 0.1
    radius_m: float = 0.5
    margin_m: float = 0.4
    margin_cost: float = 3.0
    unknown_cost: float = 0.5

    def __post_init__(self):
        if not self.cell_m > 0:
            raise PlannerException(f"cell_m must be positive, got {self.cell_m}")
        if self.radius_m < 0 or self.margin_m < 0 or self.margin_cost < 0 or self.unknown_cost < 0:
            raise PlannerException("radius_m, margin_m, margin_cost and unknown_cost must not be negative")


@dataclass(frozen=True)
class Path:
    """A planned polyline ``xy`` (n, 2) from the start's cell centre on; ``reaches_goal``:
    it ends at the goal's cell (else at the best reachable cell towards it); ``cost``: its
    weighted length (m)."""

    xy: np.ndarray
    reaches_goal: bool
    cost: float


@dataclass(frozen=True)
class CostGrid:
    """The planning grid: per cell a cost factor (>= 1 per metre), ``inf`` where blocked;
    ``origin`` is the lattice index of cell (0, 0) at ``cell_m``."""

    factor: np.ndarray
    clearance: np.ndarray  # lower bound of the distance from the cell's centre to an obstacle cell (m), inf without any
    origin: tuple[int, int]
    cell_m: float

    def cell_of(self, xy) -> tuple[int, int]:
        i, j = np.floor(np.asarray(xy, float) / self.cell_m).astype(np.int64)
        return int(i) - self.origin[0], int(j) - self.origin[1]

    def center(self, cells: np.ndarray) -> np.ndarray:
        """Centres (n, 2) of grid cells (n, 2)."""
        return (np.asarray(cells) + np.asarray(self.origin) + 0.5) * self.cell_m

    def inside(self, cell: tuple[int, int]) -> bool:
        return 0 <= cell[0] < self.factor.shape[0] and 0 <= cell[1] < self.factor.shape[1]


def cost_grid(traversability: np.ndarray, origin: tuple[int, int], resolution_m: float, params: PlannerParams) -> CostGrid:
    """Pool a traversability grid (row = x index, column = y index, as
    ``RollingObstacleMap``) to ``params.cell_m`` (a cell is an obstacle if any of its
    map cells is, unknown if all are) and turn it into per-cell cost factors."""
    trav = np.asarray(traversability, float)
    if trav.ndim != 2 or trav.size == 0:
        raise PlannerException(f"traversability must be a non-empty 2D grid, got shape {trav.shape}")
    k = round(params.cell_m / resolution_m)
    if k < 1 or not math.isclose(k * resolution_m, params.cell_m, rel_tol=1e-6):
        raise PlannerException(f"cell_m {params.cell_m} must be a whole multiple of the map's {resolution_m} m cells")
    # pad to whole planning cells on the planning lattice
    lo = np.floor_divide(np.asarray(origin), k)
    pad_lo = np.asarray(origin) - lo * k
    shape = -(-(np.asarray(trav.shape) + pad_lo) // k)
    padded = np.full(tuple(shape * k), np.nan)
    padded[pad_lo[0] : pad_lo[0] + trav.shape[0], pad_lo[1] : pad_lo[1] + trav.shape[1]] = trav
    blocks = padded.reshape(shape[0], k, shape[1], k)
    with np.errstate(invalid="ignore"):
        obstacle = (blocks > 1).any(axis=(1, 3))
    unknown = np.isnan(blocks).all(axis=(1, 3))
    # from a cell's centre to the nearest obstacle cell's nearest point (at least): its centre's distance less half a cell diagonal
    clearance = (ndimage.distance_transform_edt(~obstacle) - math.sqrt(0.5)) * params.cell_m if obstacle.any() else np.full(obstacle.shape, np.inf)
    factor = 1.0 + params.unknown_cost * unknown
    if params.margin_m > 0:
        near = np.clip((params.radius_m + params.margin_m - clearance) / params.margin_m, 0.0, 1.0)
        factor = factor + params.margin_cost * near
    factor[clearance < params.radius_m] = np.inf
    return CostGrid(factor, clearance, (int(lo[0]), int(lo[1])), params.cell_m)


def _edges(factor: np.ndarray) -> coo_array:
    """Undirected 8-connected edges between passable cells, weight = length x mean factor."""
    n0, n1 = factor.shape
    index = np.arange(factor.size).reshape(factor.shape)
    rows, cols, weights = [], [], []
    for di, dj in _STEPS:
        a = (slice(0, n0 - di), slice(max(0, -dj), n1 - max(0, dj)))
        b = (slice(di, n0), slice(max(0, dj), n1 - max(0, -dj)))
        w = math.hypot(di, dj) * 0.5 * (factor[a] + factor[b])
        ok = np.isfinite(w)
        rows.append(index[a][ok])
        cols.append(index[b][ok])
        weights.append(w[ok])
    r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    return coo_array((w, (r, c)), shape=(factor.size, factor.size))


def plan(grid: CostGrid, start_xy, goal_xy) -> Path | None:
    """The cheapest path on ``grid`` from ``start_xy`` towards ``goal_xy`` (module
    docstring); None if the start is off the grid. A start inside grown obstacles (a
    robot that came too close, or a new obstacle seen next to it) may leave them: the
    blocked cells around it that are no nearer to an obstacle than it is pass at a high
    cost."""
    start, goal = grid.cell_of(start_xy), grid.cell_of(goal_xy)
    if not grid.inside(start):
        return None
    factor = grid.factor
    if not np.isfinite(factor[start]):
        factor = _escape(grid, start)
    graph = _edges(factor).tocsr()
    s = start[0] * factor.shape[1] + start[1]
    dist, pred = dijkstra(graph, directed=False, indices=s, return_predecessors=True)
    dist = dist * grid.cell_m
    reachable = np.isfinite(dist)
    g = int(goal[0]) * factor.shape[1] + int(goal[1]) if grid.inside(goal) else -1
    if g >= 0 and reachable[g]:
        end, reaches = g, True
    else:
        centers = grid.center(np.stack(np.unravel_index(np.arange(factor.size), factor.shape), axis=1))
        rest = np.linalg.norm(centers - np.asarray(goal_xy, float)[:2], axis=1)
        if g >= 0:
            score = np.where(reachable, dist + FAR_WEIGHT * rest, np.inf)
        else:
            border = np.zeros(factor.shape, bool)
            border[[0, -1], :] = border[:, [0, -1]] = True
            score = np.where(reachable & border.ravel(), dist + rest, np.inf)
            if not np.isfinite(score).any():  # walled in: as close as the map allows
                score = np.where(reachable, dist + FAR_WEIGHT * rest, np.inf)
        end, reaches = int(np.argmin(score)), False
    cells = [end]
    while cells[-1] != s:
        cells.append(int(pred[cells[-1]]))
    cells.reverse()
    xy = grid.center(np.stack(np.unravel_index(np.asarray(cells), factor.shape), axis=1))
    return Path(xy, reaches, float(dist[end]))


def _escape(grid: CostGrid, start: tuple[int, int]) -> np.ndarray:
    """Cost factors with the blocked cells around ``start`` that are at least as clear as
    it (a way out that never gets closer to the obstacle) passable at a high cost."""
    factor = grid.factor
    way_out = ~np.isfinite(factor) & (grid.clearance >= grid.clearance[start] - 1e-9)
    labels, _ = ndimage.label(way_out, structure=np.ones((3, 3)))
    out = factor.copy()
    finite = factor[np.isfinite(factor)]
    out[labels == labels[start]] = 10.0 * (finite.max() if finite.size else 1.0)
    return out


def lookahead(path: Path, xy, distance_m: float) -> np.ndarray:
    """The point of ``path`` ``distance_m`` beyond its point nearest to ``xy`` (pure
    pursuit's carrot); the path's end if it is nearer."""
    pts = path.xy
    if len(pts) == 1:
        return pts[0].copy()
    nearest = int(np.argmin(np.linalg.norm(pts - np.asarray(xy, float)[:2], axis=1)))
    seg = np.linalg.norm(np.diff(pts[nearest:], axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])
    k = int(np.searchsorted(along, distance_m))
    if k >= len(along):
        return pts[-1].copy()
    f = (distance_m - along[k - 1]) / max(seg[k - 1], 1e-12)
    return pts[nearest + k - 1] + f * (pts[nearest + k] - pts[nearest + k - 1])
