"""Frontier-based exploration of a target region on the robot's own map (thesis 9.3).

The LRUs of thesis 9.3 ran "a frontier-based exploration algorithm (Yamauchi, 1998)"
on their global maps, "the expected information gain at each new exploration goal
location" ranking the goals (Lehner et al., 2017), and each rover "communicates each
new exploration goal to all other robots and enforces a minimum distance between
exploration goals of different robots of at least 7 m, approximately two times the
sensor range". The thesis gives no more detail; this is the textbook form of each step:

- **Explored cells.** The region is cut into ``cell_m`` cells (2D: the rovers explore a
  surface). A cell is explored once a map point lies in it: points of the robot's own and
  its peers' submaps, placed by its graph (thesis 5.2.2), and the cells its rolling
  obstacle map observed (thesis 5.1.1), which the next submap has not yet delivered.
- **Frontiers** (Yamauchi 1998): explored cells, not obstacles, with an unexplored
  4-neighbour inside the region.
- **Gain**: the unexplored region cells within ``sensor_range_m`` of the frontier cell
  (a disc around the goal, where the rover's 360 deg scan looks), counted with
  :func:`scipy.ndimage.convolve`.
- **Utility** ``U = gain * exp(-distance_weight * d)``, ``d`` the straight-line distance from
  the robot (the form of González-Baños and Latombe 2002 that Lehner et al. 2017 rank
  by); the path planner (slam/navigation/planner.py) sees only the rolling map, so the
  whole path cannot be costed.
- **Separation**: goals within ``goal_separation_m`` of a peer's current goal are left
  out. Where that leaves none (a region too small for the team), the candidates near
  peers stay, their utility scaled by ``(distance to the nearest peer goal /
  goal_separation_m)^2``, so the robot still explores but away from the others.
- A goal the robot already had (reached and scanned, or given up on: stuck, timeout) is
  not chosen again (nor any cell within ``3 * cell_m`` of it): what is left unexplored
  there could not be seen from it. Nor are cells next to mapped obstacles.

**Active loop closing** (``loop_closing_weight`` > 0; beyond the thesis's experiment: its
9.3 found that frontier exploration left "little overlap, resulting in only a single loop
closure from our map matching system", and points to active loop closing that "makes a
trade-off during the selection of goal locations between exploring new areas and
re-visiting [...] already mapped places for re-localization", Lehner et al. 2017;
Stachniss et al. 2004 close loops actively for the same reason). Each place the robot could return to (:class:`RevisitPlace`: the origin of a
finished submap the matcher found suitable, own or a peer's) carries the covariance of its
position relative to the robot now; a match there would shrink it to about the match's own
(``loop_closing_match_sigma_m``). The expected information of the revisit is that entropy
drop of the 2D Gaussian, ``I = 0.5 ln(det Σ / σ_m^4)`` (nats), and its utility
``loop_closing_weight * I * exp(-distance_weight * d)``, with the weight in cells per nat
(one currency with the frontiers' gain). The robot goes where the utility is highest,
frontier or revisit; a place within ``3 * cell_m`` of an earlier revisit goal is not chosen
again. With the weight 0 (the default) the exploration is the thesis's.

A robot that has seen nothing of the region yet (it starts outside it) first drives to its
nearest cell. Exploration ends (:attr:`Goal.finished`) when the robot believes
``coverage_target`` of the region is explored, or when no frontier with a gain of at least
``min_gain_cells`` remains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from matplotlib.path import Path as PolygonPath
from scipy import ndimage

_FOUR = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], bool)


class ExplorationException(ValueError):
    """Bad input to the exploration (region, parameters)."""


@dataclass(frozen=True)
class ExplorationParams:
    """See the module docstring."""

    cell_m: float = 0.5
    sensor_range_m: float = 3.5
    goal_separation_m: float = 7.0
    distance_weight: float = 0.15
    coverage_target: float = 0.95
    min_gain_cells: int = 4
    min_goal_distance_m: float = 1.5
    loop_closing_weight: float = 0.0
    loop_closing_match_sigma_m: float = 0.05
    observe_peers: bool = False  # active mutual observation (slam/navigation/observation.py)
    observe_range_m: float = 6.0  # about the farthest the LRU detects a peer's 0.15 m markers (8 px at f = 338 px)
    observe_interval_s: float = 30.0

    def __post_init__(self):
        if not (self.cell_m > 0 and self.sensor_range_m > 0):
            raise ExplorationException("cell_m and sensor_range_m must be positive")
        if min(self.goal_separation_m, self.distance_weight, self.min_goal_distance_m, self.loop_closing_weight) < 0:
            raise ExplorationException("goal_separation_m, distance_weight, min_goal_distance_m and loop_closing_weight must not be negative")
        if not (self.observe_range_m > 0 and self.observe_interval_s >= 0):
            raise ExplorationException("observe_range_m must be positive and observe_interval_s not negative")
        if not self.loop_closing_match_sigma_m > 0:
            raise ExplorationException(f"loop_closing_match_sigma_m must be positive, got {self.loop_closing_match_sigma_m}")
        if not 0 < self.coverage_target <= 1:
            raise ExplorationException(f"coverage_target must be in (0, 1], got {self.coverage_target}")


class RegionGrid:
    """The target region ``polygon`` ((n, 2), mission frame) on a grid of ``cell_m`` cells
    covering its bounding box; ``inside``: the cells whose centre lies in the polygon."""

    def __init__(self, polygon, cell_m: float):
        poly = np.asarray(polygon, float)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.all(np.isfinite(poly)):
            raise ExplorationException(f"the region must be at least three finite (x, y) vertices, got shape {poly.shape}")
        self.polygon = poly
        self.cell_m = float(cell_m)
        self.lo = poly.min(axis=0)
        self.shape = tuple(int(n) for n in np.maximum(np.ceil((poly.max(axis=0) - self.lo) / cell_m), 1).astype(int))
        self.inside = PolygonPath(poly).contains_points(self.centers().reshape(-1, 2)).reshape(self.shape)
        if not self.inside.any():
            raise ExplorationException("the region holds no whole cell")

    def centers(self) -> np.ndarray:
        """Cell centres (nx, ny, 2)."""
        i, j = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.lo + (np.stack([i, j], axis=-1) + 0.5) * self.cell_m

    def cells(self, xy: np.ndarray) -> np.ndarray:
        """Grid cells (k, 2) of the points ``xy`` (n, 2) that fall on the grid."""
        ij = np.floor((np.asarray(xy, float).reshape(-1, 2) - self.lo) / self.cell_m).astype(np.int64)
        ok = (ij >= 0).all(axis=1) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] < self.shape[1])
        return ij[ok]

    def mark(self, xy: np.ndarray) -> np.ndarray:
        """A boolean grid, true where a point of ``xy`` falls."""
        out = np.zeros(self.shape, bool)
        ij = self.cells(xy)
        out[ij[:, 0], ij[:, 1]] = True
        return out

    def coverage(self, explored: np.ndarray) -> float:
        """Fraction of the region's cells that are explored."""
        return float((explored & self.inside).sum() / self.inside.sum())


@dataclass(frozen=True)
class RevisitPlace:
    """A mapped place to return to for a loop closure: ``xy`` (mission frame, as believed) and
    ``cov_xy``, the 2x2 covariance of its position relative to the robot now."""

    xy: np.ndarray
    cov_xy: np.ndarray

    def information(self, match_sigma_m: float) -> float:
        """Entropy drop (nats) if a match pinned the place to ``match_sigma_m``: ``0.5 ln(det Σ / σ^4)``, at least 0."""
        det = float(np.linalg.det(np.asarray(self.cov_xy, float)))
        return 0.0 if det <= 0 else max(0.0, 0.5 * math.log(det / match_sigma_m**4))


@dataclass(frozen=True)
class Goal:
    """The explorer's answer: a goal ``xy`` (mission frame) with its ``gain`` (cells;
    ``reason`` "approach" for the way into a region not seen yet, "revisit" for a place
    returned to for a loop closure, with its expected ``information`` in nats), or ``finished``
    (``reason``: "coverage" or "no frontier"); ``coverage``: the region's explored fraction
    as the robot believes it."""

    xy: np.ndarray | None
    coverage: float
    gain: int = 0
    finished: bool = False
    reason: str = ""
    information: float = 0.0


def frontiers(explored: np.ndarray, inside: np.ndarray, blocked: np.ndarray) -> np.ndarray:
    """Frontier cells (Yamauchi 1998): explored, not blocked, next to an unexplored region cell."""
    unknown = inside & ~explored
    return explored & ~blocked & ndimage.binary_dilation(unknown, structure=_FOUR)


def information_gain(explored: np.ndarray, inside: np.ndarray, radius_cells: float) -> np.ndarray:
    """Per cell, the unexplored region cells within ``radius_cells`` of it."""
    r = int(np.floor(radius_cells))
    di, dj = np.mgrid[-r : r + 1, -r : r + 1]
    disc = (di**2 + dj**2 <= radius_cells**2).astype(np.int32)
    return ndimage.convolve((inside & ~explored).astype(np.int32), disc, mode="constant", cval=0)


def _near(centers: np.ndarray, points: list[np.ndarray], radius_m: float) -> np.ndarray:
    """Cells whose centre lies within ``radius_m`` of any of ``points``."""
    near = np.zeros(centers.shape[:2], bool)
    for xy in points:
        near |= np.linalg.norm(centers - np.asarray(xy, float)[:2], axis=-1) < radius_m
    return near


def choose_goal(
    grid: RegionGrid,
    explored: np.ndarray,
    obstacles: np.ndarray,
    robot_xy,
    params: ExplorationParams,
    peer_goals: list[np.ndarray] = (),
    visited: list[np.ndarray] = (),
    revisits: list[RevisitPlace] = (),
    revisited: list[np.ndarray] = (),
) -> Goal:
    """The next goal (module docstring). ``explored``, ``obstacles``: boolean grids on
    ``grid``; ``peer_goals``, ``visited`` (the robot's earlier goals), ``revisited`` (its
    earlier revisit goals): points in the mission frame; ``revisits``: places to return to
    (used when ``params.loop_closing_weight`` > 0)."""
    coverage = grid.coverage(explored)
    if coverage >= params.coverage_target:
        return Goal(None, coverage, finished=True, reason="coverage")
    blocked = ndimage.binary_dilation(obstacles, structure=np.ones((3, 3), bool))
    front = frontiers(explored, grid.inside, blocked)
    gain = information_gain(explored, grid.inside, params.sensor_range_m / grid.cell_m)
    centers = grid.centers()
    robot = np.asarray(robot_xy, float)[:2]
    candidate = front & (gain >= params.min_gain_cells)
    candidate &= np.linalg.norm(centers - robot, axis=-1) >= params.min_goal_distance_m
    candidate &= ~_near(centers, visited, 3 * grid.cell_m)
    if not candidate.any() and coverage == 0:  # the region not seen yet (a robot that starts outside it)
        approach = grid.inside & ~blocked & ~_near(centers, visited, 3 * grid.cell_m)
        if approach.any():
            d = np.where(approach, np.linalg.norm(centers - robot, axis=-1), np.inf)
            i, j = np.unravel_index(int(np.argmin(d)), d.shape)
            return Goal(centers[i, j].copy(), coverage, int(gain[i, j]), reason="approach")
    if not candidate.any():
        return Goal(None, coverage, finished=True, reason="no frontier")
    utility = gain * np.exp(-params.distance_weight * np.linalg.norm(centers - robot, axis=-1))
    if len(peer_goals) and params.goal_separation_m > 0:
        nearest = np.min([np.linalg.norm(centers - np.asarray(g, float)[:2], axis=-1) for g in peer_goals], axis=0)
        apart = candidate & (nearest >= params.goal_separation_m)
        if apart.any():
            candidate = apart
        else:
            utility = utility * (nearest / params.goal_separation_m) ** 2
    score = np.where(candidate, utility, -np.inf)
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    revisit = _best_revisit(revisits, revisited, robot, params)
    if revisit is not None and revisit[0] > score[i, j]:
        _, place, info = revisit
        return Goal(np.asarray(place.xy, float)[:2].copy(), coverage, reason="revisit", information=info)
    return Goal(centers[i, j].copy(), coverage, int(gain[i, j]))


def _best_revisit(
    revisits: list[RevisitPlace], revisited: list[np.ndarray], robot: np.ndarray, params: ExplorationParams
) -> tuple[float, RevisitPlace, float] | None:
    """``(utility, place, information)`` of the best place to return to (module docstring), or None."""
    if params.loop_closing_weight <= 0:
        return None
    best = None
    for place in revisits:
        xy = np.asarray(place.xy, float)[:2]
        d = float(np.linalg.norm(xy - robot))
        if d < params.min_goal_distance_m or any(np.linalg.norm(xy - np.asarray(r, float)[:2]) < 3 * params.cell_m for r in revisited):
            continue
        info = place.information(params.loop_closing_match_sigma_m)
        utility = params.loop_closing_weight * info * math.exp(-params.distance_weight * d)
        if utility > 0 and (best is None or utility > best[0]):
            best = (utility, place, info)
    return best
