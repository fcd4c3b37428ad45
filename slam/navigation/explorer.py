"""A robot's exploration: what its maps say is explored, and its next goal (thesis 9.3).

:class:`Explorer` turns the robot's maps into the boolean grids of
``slam.navigation.exploration`` on the target region, in the mission frame as the robot
believes it:

- every finished submap it holds (its own and its peers', thesis 5.2.2) on the origin its
  graph gives it now; a submap's footprint (its points' cells at half the region's cell
  size, and which hold obstacle points) is computed once, and only placed again as the
  graph moves it;
- the rolling obstacle map (thesis 5.1.1) in the odometry frame: what the robot saw since
  its last submap ended, and the obstacles it plans around.

Pure: submaps, transforms and grids in, a :class:`~slam.navigation.exploration.Goal` out.
"""

from __future__ import annotations

import numpy as np

from slam.lie import apply_planar
from slam.navigation.exploration import ExplorationParams, Goal, RegionGrid, RevisitPlace, choose_goal
from slam.submap import Submap


def _footprint(points: np.ndarray, cell_m: float) -> np.ndarray:
    """Centres (k, 2) of the ``cell_m`` cells that hold a point of ``points`` (n, 3)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    ij = np.unique(np.floor(np.asarray(points, float)[:, :2] / cell_m).astype(np.int64), axis=0)
    return (ij + 0.5) * cell_m


class Explorer:
    """Explored and obstacle grids of the ``region`` from the robot's maps, and its goals."""

    def __init__(self, region, params: ExplorationParams):
        self.params = params
        self.grid = RegionGrid(region, params.cell_m)
        self._footprints: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    def _submap_cells(self, submap: Submap) -> tuple[np.ndarray, np.ndarray]:
        key = submap.key
        if key not in self._footprints:
            half = self.params.cell_m / 2
            self._footprints[key] = (_footprint(submap.points, half), _footprint(submap.points[submap.obstacle], half))
        return self._footprints[key]

    def grids(
        self,
        placed: list[tuple[Submap, np.ndarray]],
        T_world_map: np.ndarray,
        rolling: tuple[np.ndarray, tuple[int, int], float] | None = None,
        T_world_odom: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(explored, obstacles)`` on the region grid. ``placed``: submaps with their
        origins in the robot's map; ``rolling``: the rolling map's traversability (NaN
        unknown, above 1 obstacle), origin cell and resolution, in the odometry frame."""
        explored = np.zeros(self.grid.shape, bool)
        obstacles = np.zeros(self.grid.shape, bool)
        for submap, S in placed:
            cells, obstacle_cells = self._submap_cells(submap)
            T = T_world_map @ S
            explored |= self.grid.mark(apply_planar(T, cells))
            obstacles |= self.grid.mark(apply_planar(T, obstacle_cells))
        if rolling is not None and T_world_odom is not None:
            trav, origin, resolution = rolling
            seen = ~np.isnan(trav)
            with np.errstate(invalid="ignore"):
                blocked = trav > 1
            ij = np.argwhere(seen)
            xy = apply_planar(T_world_odom, (ij + np.asarray(origin) + 0.5) * resolution)
            explored |= self.grid.mark(xy)
            obstacles |= self.grid.mark(xy[blocked[seen]])
        return explored, obstacles

    def next_goal(
        self,
        explored: np.ndarray,
        obstacles: np.ndarray,
        robot_xy,
        peer_goals: list[np.ndarray] = (),
        visited: list[np.ndarray] = (),
        revisits: list[RevisitPlace] = (),
        revisited: list[np.ndarray] = (),
    ) -> Goal:
        """The next goal from the grids (:func:`slam.navigation.exploration.choose_goal`)."""
        return choose_goal(self.grid, explored, obstacles, robot_xy, self.params, peer_goals, visited, revisits, revisited)
