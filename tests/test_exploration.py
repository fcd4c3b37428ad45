"""Frontier exploration on synthetic maps (slam/navigation/exploration.py, explorer.py; thesis 9.3)."""

import numpy as np
import pytest

from sim.scenario import ScenarioError, load_scenario
from slam.lie import rot_z, se3
from slam.navigation.exploration import (
    ExplorationException,
    ExplorationParams,
    RegionGrid,
    choose_goal,
    frontiers,
    information_gain,
)
from slam.navigation.explorer import Explorer
from slam.submap import Submap
from slam.voxels import VoxelGrid

SQUARE = [[0, 0], [10, 0], [10, 10], [0, 10]]


def _disc(grid: RegionGrid, center, radius) -> np.ndarray:
    return np.linalg.norm(grid.centers() - np.asarray(center, float), axis=-1) <= radius


def test_region_grid_holds_the_polygon_and_counts_coverage():
    triangle = RegionGrid([[0, 0], [10, 0], [0, 10]], 0.5)
    assert triangle.shape == (20, 20)
    assert triangle.inside.sum() == pytest.approx(50 / 0.25, rel=0.06)  # 50 m^2 of 0.25 m^2 cells
    explored = triangle.mark(np.array([[1.2, 1.2], [1.3, 1.4], [9.0, 9.0], [-3.0, 2.0]]))  # (9, 9) is off the triangle, (-3, 2) off the grid
    assert explored.sum() == 2
    assert triangle.coverage(explored) == pytest.approx(1 / triangle.inside.sum())
    with pytest.raises(ExplorationException, match="three"):
        RegionGrid([[0, 0], [1, 1]], 0.5)
    with pytest.raises(ExplorationException, match="no whole cell"):
        RegionGrid([[0, 0], [0.2, 0], [0, 0.2]], 0.5)


def test_frontiers_ring_the_explored_disc_and_gain_counts_what_is_unseen():
    grid = RegionGrid(SQUARE, 0.5)
    explored = _disc(grid, (5, 5), 2.0)
    front = frontiers(explored, grid.inside, np.zeros(grid.shape, bool))
    d = np.linalg.norm(grid.centers()[front] - 5.0, axis=-1)
    assert front.sum() >= 16 and np.all(d > 1.4) and np.all(d <= 2.0)  # only the disc's rim
    gain = information_gain(explored, grid.inside, 3.0)
    assert gain[10, 10] == 0 or gain[10, 10] < gain[10, 14]  # the centre sees less unexplored ground than the rim
    i, j = np.indices(grid.shape)
    assert gain[10, 14] == np.sum(((i - 10) ** 2 + (j - 14) ** 2 <= 9) & grid.inside & ~explored)


def test_the_goal_is_the_frontier_towards_the_larger_unexplored_area():
    grid = RegionGrid([[0, 0], [30, 0], [30, 10], [0, 10]], 0.5)
    explored = _disc(grid, (5, 5), 3.0) | (grid.centers()[..., 0] < 4)  # the west end seen: the east is open
    params = ExplorationParams()
    goal = choose_goal(grid, explored, np.zeros(grid.shape, bool), (5, 5), params)
    assert not goal.finished and goal.xy[0] > 7.0 and goal.gain > 0
    assert goal.coverage == pytest.approx(grid.coverage(explored))
    # an obstacle mapped on that frontier: the goal moves off it
    obstacles = _disc(grid, goal.xy, 0.3)
    other = choose_goal(grid, explored, obstacles, (5, 5), params)
    assert np.linalg.norm(other.xy - goal.xy) >= 0.5
    # once there, the goal is not chosen again
    again = choose_goal(grid, explored, np.zeros(grid.shape, bool), (5, 5), params, visited=[goal.xy])
    assert np.linalg.norm(again.xy - goal.xy) >= 1.5


def test_goals_keep_away_from_a_peers_goal_and_fall_back_when_nothing_is_far_enough():
    grid = RegionGrid([[0, 0], [30, 0], [30, 10], [0, 10]], 0.5)
    explored = (grid.centers()[..., 0] > 12) & (grid.centers()[..., 0] < 18)  # a strip across the middle: frontiers west and east
    params = ExplorationParams(goal_separation_m=7.0)
    alone = choose_goal(grid, explored, np.zeros(grid.shape, bool), (15.5, 5), params)
    peer = alone.xy.copy()
    shared = choose_goal(grid, explored, np.zeros(grid.shape, bool), (15.5, 5), params, peer_goals=[peer])
    assert np.linalg.norm(shared.xy - peer) >= 7.0
    assert (shared.xy[0] < 15) != (peer[0] < 15)  # the other side of the strip
    small = RegionGrid([[0, 0], [6, 0], [6, 6], [0, 6]], 0.5)  # smaller than the separation
    seen = _disc(small, (3, 3), 1.5)
    near = ExplorationParams(goal_separation_m=7.0, min_goal_distance_m=0.5)
    fallback = choose_goal(small, seen, np.zeros(small.shape, bool), (3, 3), near, peer_goals=[np.array([1.0, 3.0])])
    assert not fallback.finished and fallback.xy[0] > 3.0  # still a goal, on the side away from the peer's


def test_exploration_ends_on_coverage_or_when_no_frontier_is_left_and_approaches_an_unseen_region():
    grid = RegionGrid(SQUARE, 0.5)
    params = ExplorationParams(coverage_target=0.9)
    nearly = np.ones(grid.shape, bool)
    nearly[:3] = False  # 15 % unexplored
    assert not choose_goal(grid, nearly, np.zeros(grid.shape, bool), (5, 5), params).finished
    nearly[1:3] = True  # 5 % unexplored
    done = choose_goal(grid, nearly, np.zeros(grid.shape, bool), (5, 5), params)
    assert done.finished and done.reason == "coverage" and done.xy is None
    walled = np.ones(grid.shape, bool)
    walled[:2] = False  # unexplored, but every frontier next to it is an obstacle
    wall = np.zeros(grid.shape, bool)
    wall[2] = True
    stuck = choose_goal(grid, walled, wall, (5, 5), ExplorationParams())
    assert stuck.finished and stuck.reason == "no frontier"
    outside = choose_goal(grid, np.zeros(grid.shape, bool), np.zeros(grid.shape, bool), (-6, 5), params)
    assert outside.reason == "approach" and outside.xy[0] < 0.5 and abs(outside.xy[1] - 5) < 0.5


def test_explorer_places_submaps_by_their_origins_and_adds_the_rolling_map():
    params = ExplorationParams()
    explorer = Explorer(SQUARE, params)
    xs, ys = np.meshgrid(np.arange(0, 2, 0.05), np.arange(-1, 1, 0.05))
    points = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    obstacle = (np.abs(points[:, 0] - 1.0) < 0.1) & (np.abs(points[:, 1]) < 0.1)
    submap = Submap("a", 0, 0, 0.0, 1.0, points, obstacle, np.ones(len(points), bool), np.zeros(len(points)), VoxelGrid(0.1), 1, 0.0)
    S = se3(rot_z(np.pi / 2), [0.0, 0.0, 0.0])  # the submap's origin in the robot's map: turned by 90 deg
    T_world_map = se3(np.eye(3), [5.0, 5.0, 0.0])
    explored, obstacles = explorer.grids([(submap, S)], T_world_map)
    # the 2 x 2 m patch ahead of the origin lands north of (5, 5) after the turn
    cells = explorer.grid.centers()[explored]
    assert cells[:, 0].min() > 3.9 and cells[:, 0].max() < 6.1 and cells[:, 1].min() > 4.9 and cells[:, 1].max() < 7.1
    assert explored.sum() == pytest.approx(16, abs=4)
    np.testing.assert_allclose(explorer.grid.centers()[obstacles].mean(axis=0), [5.0, 6.0], atol=0.3)
    trav = np.full((40, 40), np.nan)  # a 2 m rolling map at 0.05 m, seen in its lower half, one obstacle cell
    trav[:20] = 0.2
    trav[5, 5] = 2.0
    explored2, obstacles2 = explorer.grids([], T_world_map, (trav, (0, 0), 0.05), se3(np.eye(3), [6.0, 6.0, 0.0]))
    cells = explorer.grid.centers()[explored2]  # x in [6, 7), y in [6, 8): 2 x 4 cells
    assert cells[:, 0].min() > 5.9 and cells[:, 0].max() < 7.1 and cells[:, 1].max() < 8.1 and explored2.sum() == 8
    assert obstacles2.sum() == 1


# --------------------------------------------------------------------------- the scenario's exploration section


def two_explorers(seed: int = 1, **exploration) -> dict:
    """Two LRUs on their estimates exploring a 16 m x 10 m region of a flat lunar patch."""
    route = {"speed_mps": 0.3, "scan_duration_s": 12, "head_sweep_deg": 30}
    return {
        "name": "explore_small",
        "seed": seed,
        "duration_s": 90,
        "drain_s": 5,
        "terrain": {"preset": "moon", "size_m": 24, "roughness_m": 0.02, "craters": {"count": 0}, "lander": None,
                    "rocks": {"count": 0}},
        "robots": [
            {"name": "lru1", "preset": "lru", "start": {"xy": [-4, -1.5]}, "navigation": {"pose_source": "estimate"}, "route": route},
            {"name": "lru2", "preset": "lru", "start": {"xy": [-4, 1.5]}, "navigation": {"pose_source": "estimate"}, "route": route},
        ],
        "exploration": {"region": [[-6, -5], [10, -5], [10, 5], [-6, 5]], "goal_separation_m": 4.0, **exploration},
        "output": {"recording": False, "topdown_png": False},
    }


@pytest.mark.parametrize(
    ("change", "expect"),
    [
        ({"exploration": {"region": [[0, 0], [1, 0]]}}, "at least 3"),
        ({"exploration": {"region": [[0, 0], [30, 0], [0, 5]]}}, "outside the 24 m terrain"),
        ({"exploration": {"region": [[0, 0], [0.1, 0], [0, 0.1]]}}, "smaller than one"),
        ({"exploration": {"region": [[0, 0], [5, 0], [0, 5]], "robots": ["lru3"]}}, "no robot named 'lru3'"),
        ({"slam": {"graph": {"enabled": False}}}, "slam.graph.enabled"),
        ({"exploration": {"region": [[0, 0], [5, 0], [0, 5]], "coverage_target": 1.5}}, "coverage_target"),
    ],
)
def test_exploration_is_refused_where_it_cannot_work(change, expect):
    raw = two_explorers()
    raw.update(change)
    with pytest.raises(ScenarioError, match=expect):
        load_scenario(raw)


def test_a_hexacopter_cannot_explore():
    raw = two_explorers()
    raw["robots"][1] = {"name": "ardea", "preset": "ardea", "start": {"xy": [-4, 1.5]}}
    assert load_scenario(raw).exploration.explorers(load_scenario(raw).robots) == ["lru1"]
    raw["exploration"]["robots"] = ["lru1", "ardea"]
    with pytest.raises(ScenarioError, match="robot ardea \\(preset ardea\\) cannot explore"):
        load_scenario(raw)


@pytest.fixture(scope="module")
def explored(tmp_path_factory):
    from sim.evaluation import results_folder
    from sim.run.runner import Run

    run = Run(load_scenario(two_explorers()))
    run.execute()
    return run, results_folder.write(run, tmp_path_factory.mktemp("explore"))


def test_two_rovers_explore_the_region_on_their_own_goals(explored):
    _, metrics = explored
    section = metrics["exploration"]
    assert section["region_m2"] == pytest.approx(160.0)
    for name in ("lru1", "lru2"):
        robot = section["robots"][name]
        assert robot["goals_reached"] >= 3  # the first scan and at least two goals of its own choosing
        assert metrics["robots"][name]["navigation"]["collisions"] == 0
        # what it believed explored at its last goal (its map with its peer's submaps once its graph connects
        # them, placed by its estimate) lies between what it had truly mapped itself in finished submaps by
        # then and what the team truly mapped by the end
        truth_then = max([c for t, c in robot["coverage_over_time"] if t <= robot["believed_t"]], default=0.0)
        assert truth_then - 0.1 <= robot["believed_coverage"] <= section["coverage"] + 0.05
    # the team truly explored more than either robot, and most of the region
    assert section["coverage"] > max(r["coverage"] for r in section["robots"].values()) + 0.05
    assert section["coverage"] > 0.6
    times, coverage = np.array(section["coverage_over_time"]).T
    assert np.all(np.diff(coverage) >= 0) and np.all(np.diff(times) >= 0)


def test_exploration_goals_travel_over_the_network_and_stay_apart(explored):
    run, metrics = explored
    one, two = (run.robots[n].onboard for n in ("lru1", "lru2"))
    assert one.agent.peer_goals["lru2"].robot == "lru2" and two.agent.peer_goals["lru1"].robot == "lru1"
    assert metrics["comms"]["by_kind"]["goal"]["delivered_bytes"] > 0
    # both chose their first goals at the same moment: one of them yields, so the first goals in force are apart
    kept = {n: [r for r in run.robots[n].robot.waypoints[1:] if r.reason != "withdrawn"] for n in ("lru1", "lru2")}
    assert np.linalg.norm(np.subtract(kept["lru1"][0].xy, kept["lru2"][0].xy)) >= 4.0
