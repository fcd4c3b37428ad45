"""The graph-based 2D planner (slam/navigation/planner.py) on synthetic obstacle maps whose
free space is known exactly."""

import itertools
import math

import numpy as np
import pytest

from slam.navigation.planner import PlannerException, PlannerParams, cost_grid, lookahead, plan
from slam.obstacles import HeightMap, RollingObstacleMap

RES = 0.05
N = 200  # a 10 m map
ORIGIN = (-100, -100)  # cells of [-5, 5) x [-5, 5)


def centres():
    c = (np.arange(N) + ORIGIN[0] + 0.5) * RES
    return np.meshgrid(c, c, indexing="ij")  # rows along x, columns along y, as RollingObstacleMap


def wall_map():
    """Free ground with an obstacle block x in (1, 2), |y| < 1.5 and an unknown band x < -3."""
    X, Y = centres()
    trav = np.zeros((N, N))
    trav[(X > 1) & (X < 2) & (np.abs(Y) < 1.5)] = 2.0
    trav[X < -3] = np.nan
    return trav


def clearance_to_block(xy):
    """Distance from points to the block (1, 2) x (-1.5, 1.5)."""
    dx = np.maximum(0, np.maximum(1 - xy[:, 0], xy[:, 0] - 2))
    dy = np.maximum(0, np.abs(xy[:, 1]) - 1.5)
    return np.hypot(dx, dy)


def densify(xy, step=0.01):
    out = [xy[0]]
    for a, b in itertools.pairwise(xy):
        k = max(1, int(np.linalg.norm(b - a) / step))
        out.extend(a + (b - a) * (np.arange(1, k + 1)[:, None] / k))
    return np.array(out)


def test_path_goes_around_the_grown_obstacle_to_the_goal():
    params = PlannerParams(radius_m=0.5, margin_m=0.0)  # the growth alone keeps the path clear
    path = plan(cost_grid(wall_map(), ORIGIN, RES, params), (0.0, 0.0), (4.0, 0.0))
    assert path.reaches_goal
    assert np.linalg.norm(path.xy[-1] - [4.0, 0.0]) < 0.1 and np.linalg.norm(path.xy[0]) < 0.1
    # every point of the polyline keeps the robot's radius from the block (a diagonal step may cut a corner by mm)
    assert clearance_to_block(densify(path.xy)).min() > 0.5 - 0.01
    length = np.linalg.norm(np.diff(path.xy, axis=0), axis=1).sum()
    detour = 2 * math.hypot(1.5, 2.0 + 0.5)  # over the block's corner region and down again, roughly
    assert 4.0 < length < detour + 1.5
    assert path.cost >= length - 1e-9  # every cost factor is at least 1


def test_goal_beyond_the_map_ends_on_its_border_towards_the_goal():
    grid = cost_grid(np.zeros((N, N)), ORIGIN, RES, PlannerParams())
    path = plan(grid, (0.0, 0.0), (20.0, 1.0))
    assert not path.reaches_goal
    end = path.xy[-1]
    assert end[0] > 4.9  # on the +x border
    assert abs(end[1] - 0.25) < 0.3  # where the straight line to the goal leaves the map


def test_goal_in_an_obstacle_is_approached_as_close_as_the_map_allows():
    params = PlannerParams(radius_m=0.5)
    path = plan(cost_grid(wall_map(), ORIGIN, RES, params), (0.0, 0.0), (1.5, 0.0))
    assert not path.reaches_goal
    assert clearance_to_block(path.xy[-1:])[0] == pytest.approx(0.5, abs=0.1)
    assert np.linalg.norm(path.xy[-1] - [1.5, 0.0]) < 1.1


def test_a_walled_in_robot_gets_nowhere_but_a_start_inside_grown_obstacles_leaves_them():
    X, Y = centres()
    ring = np.zeros((N, N))
    r = np.hypot(X, Y)
    ring[(r > 2.0) & (r < 2.3)] = 2.0
    path = plan(cost_grid(ring, ORIGIN, RES, PlannerParams(radius_m=0.5)), (0.0, 0.0), (4.0, 0.0))
    assert not path.reaches_goal and np.hypot(*path.xy[-1]) < 2.0 - 0.5 + 0.1
    # 0.3 m from a rock with a 0.5 m radius: the way out never goes nearer to it
    rock = np.zeros((N, N))
    rock[np.hypot(X - 1.0, Y) < 0.3] = 2.0
    grid = cost_grid(rock, ORIGIN, RES, PlannerParams(radius_m=0.5))
    start = (0.4, 0.0)
    assert not np.isfinite(grid.factor[grid.cell_of(start)])
    path = plan(grid, start, (-3.0, 0.0))
    assert path.reaches_goal
    dist = np.hypot(path.xy[:, 0] - 1.0, path.xy[:, 1])
    assert np.all(np.diff(dist[: np.argmax(dist > 0.8)]) >= -1e-9)


def test_unknown_cells_pass_but_seen_ground_is_preferred():
    _, Y = centres()
    trav = np.full((N, N), np.nan)
    trav[np.abs(Y) > 0.4] = 0.0  # seen ground everywhere but a 0.8 m unknown corridor along y = 0
    params = PlannerParams(unknown_cost=0.5, margin_m=0.0)
    path = plan(cost_grid(trav, ORIGIN, RES, params), (-3.0, 0.0), (3.0, 0.0))
    assert path.reaches_goal  # the unknown is passable ...
    straight = plan(cost_grid(np.zeros((N, N)), ORIGIN, RES, params), (-3.0, 0.0), (3.0, 0.0))
    assert path.cost > straight.cost  # ... at a price
    assert np.abs(path.xy[:, 1]).max() > 0.4  # and the path leaves it for seen ground where that pays


def test_the_rolling_map_plans_in_its_own_frame():
    rolling = RollingObstacleMap(RES, 10.0, rate=1.0, center_xy=(30.0, -12.0))
    X, Y = centres()
    block = (np.abs(X) < 0.5) & (np.abs(Y) < 1.0)
    trav = np.where(block, 5.0, 0.0)
    origin = (ORIGIN[0] + 600, ORIGIN[1] - 240)  # the same map shifted to (30, -12)
    zeros = np.zeros((N, N))
    rolling.update(HeightMap(RES, origin, zeros, zeros, zeros + 0.15, trav), (30.0, -12.0))
    grid = cost_grid(rolling.traversability, rolling.origin, rolling.resolution_m, PlannerParams(radius_m=0.5))
    path = plan(grid, (27.0, -12.0), (33.0, -12.0))
    assert path.reaches_goal
    rel = densify(path.xy) - [30.0, -12.0]
    assert np.all((np.abs(rel[:, 0]) > 0.5 + 0.49) | (np.abs(rel[:, 1]) > 1.0 + 0.49))


def test_lookahead():
    free = cost_grid(np.zeros((N, N)), ORIGIN, RES, PlannerParams())
    path = plan(free, (-2.0, 0.0), (2.0, 0.0))
    carrot = lookahead(path, (-2.0, 0.0), 1.0)
    assert np.linalg.norm(carrot - path.xy[0]) == pytest.approx(1.0, abs=0.08)
    assert np.allclose(lookahead(path, (1.9, 0.0), 5.0), path.xy[-1])


def test_bad_input_is_refused_with_a_reason():
    with pytest.raises(PlannerException, match="whole multiple"):
        cost_grid(np.zeros((10, 10)), (0, 0), 0.03, PlannerParams(cell_m=0.1))
    with pytest.raises(PlannerException, match="non-empty 2D"):
        cost_grid(np.zeros(10), (0, 0), 0.05, PlannerParams())
    with pytest.raises(PlannerException, match="positive"):
        PlannerParams(cell_m=0)
    assert plan(cost_grid(np.zeros((N, N)), ORIGIN, RES, PlannerParams()), (50.0, 0.0), (0.0, 0.0)) is None
