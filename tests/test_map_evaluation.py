"""sim.evaluation.map_quality against maps made from the true geometry itself."""

import numpy as np
import pytest

from sim.evaluation.map_quality import MapEvaluationError, map_quality
from sim.scenario import load_scenario
from sim.seeding import RandomStreams
from sim.world.terrain import generate_terrain


@pytest.fixture(scope="module")
def terrain():
    scenario = load_scenario("scenarios/quickstart.yaml")
    return generate_terrain(scenario.terrain, RandomStreams(scenario.seed).rng("terrain"), [])


@pytest.fixture(scope="module")
def rocky():
    scenario = load_scenario("scenarios/obstacles/mars_rocks.yaml")
    return generate_terrain(scenario.terrain, RandomStreams(scenario.seed).rng("terrain"), [])


def true_surface_map(terrain, x0, y0, size, spacing=0.05):
    x, y = np.meshgrid(np.arange(x0, x0 + size, spacing), np.arange(y0, y0 + size, spacing), indexing="ij")
    x, y = x.ravel(), y.ravel()
    return np.column_stack([x, y, terrain.surface_height_at(x, y)])


def test_a_map_of_the_true_surface_is_accurate_and_complete(terrain):
    pts = true_surface_map(terrain, -9.0, -5.0, 4.0)
    q = map_quality(pts, np.zeros(len(pts), bool), terrain).metrics()
    # the true surface is sampled every 2 cm: a perfect map scores within spacing / sqrt(2)
    assert q["accuracy"]["p95_m"] < 0.015 and q["accuracy"]["within_0_1_m"] == 1.0
    assert q["completeness"]["share"] > 0.99
    assert q["completeness"]["explored_area_m2"] == pytest.approx(16.0)


def test_a_lifted_or_partial_map_scores_what_is_wrong_with_it(terrain):
    pts = true_surface_map(terrain, -9.0, -5.0, 4.0)
    lifted = map_quality(pts + [0.0, 0.0, 0.3], np.zeros(len(pts), bool), terrain).metrics()
    assert lifted["accuracy"]["median_m"] == pytest.approx(0.3, abs=0.02)
    assert lifted["completeness"]["share"] < 0.05
    sparse = true_surface_map(terrain, -9.0, -5.0, 4.0, spacing=0.35)  # a disc of 0.1 m per 0.35 m square: ~26 %
    assert map_quality(sparse, np.zeros(len(sparse), bool), terrain).completeness["share"] < 0.4


def test_obstacle_precision_and_recall_around_a_rock(rocky):
    """The tallest rock on ground the robot could drive (no slope above 15 deg around it)."""
    terrain = rocky
    for rock in sorted(terrain.rocks, key=lambda r: -r.radii[2]):
        x0, y0 = rock.center[:2] - 1.0
        pts = true_surface_map(terrain, x0, y0, 2.0)
        ground = terrain.height_at(pts[:, 0], pts[:, 1]).reshape(40, 40)
        if np.all(np.hypot(*np.gradient(ground, 0.05)) < np.tan(np.radians(15))):
            break
    assert rock.radii[2] > 0.2
    tall = pts[:, 2] > terrain.height_at(pts[:, 0], pts[:, 1]) + 0.05  # on the rock
    right = map_quality(pts, tall, terrain).metrics()["obstacles"]
    # true obstacles are the rock's steps (window height difference > 0.15 m) and rims, not its
    # whole top or its low flanks, so flagging the rock is mostly but not entirely right
    assert right["true_cells_seen"] > 0
    assert right["recall"] > 0.5 and right["precision"] > 0.6, right
    wrong = map_quality(pts, ~tall, terrain).metrics()["obstacles"]  # everything but the rock flagged
    assert wrong["precision"] < 0.2, wrong


def test_points_on_robots_are_neither_scored_nor_cover_cells(terrain):
    """A robot parked beside the rock: its points, flagged, would be false obstacles; left
    out as ``on_robots`` they change nothing but their count."""
    rock = max(terrain.rocks, key=lambda r: r.radii[2])
    x0, y0 = rock.center[:2] - 1.5
    pts = true_surface_map(terrain, x0, y0, 3.0)
    tall = pts[:, 2] > terrain.height_at(pts[:, 0], pts[:, 1]) + 0.05
    robot = np.column_stack([pts[:, :2] + [3.0, 0.0], terrain.height_at(pts[:, 0] + 3.0, pts[:, 1]) + 0.5])[::20]
    both = np.concatenate([pts, robot])
    flags = np.concatenate([tall, np.ones(len(robot), bool)])
    alone = map_quality(pts, tall, terrain).obstacles
    unmasked = map_quality(both, flags, terrain).obstacles
    masked = map_quality(both, flags, terrain, on_robots=np.arange(len(both)) >= len(pts)).obstacles
    assert unmasked.precision < alone.precision
    assert (masked.precision, masked.recall, masked.mapped_cells) == (alone.precision, alone.recall, alone.mapped_cells)
    assert masked.points_on_robots == len(robot)
    assert len(masked.tp_xy) + len(masked.fp_xy) == masked.mapped_cells


def test_only_classified_points_count_as_seeing_a_cell(rocky):
    """A map around a rock whose points are classified only on one side of x (as points beyond
    the classification's range are not): the rock's unflagged cells on the other side are
    not misses, and flags there could not come from the classification."""
    terrain = rocky
    rock = max(terrain.rocks, key=lambda r: r.radii[2])
    x0, y0 = rock.center[:2] - 1.5
    pts = true_surface_map(terrain, x0, y0, 3.0)
    tall = pts[:, 2] > terrain.height_at(pts[:, 0], pts[:, 1]) + 0.05
    near = pts[:, 0] < rock.center[0]  # the half nearer a robot coming from -x
    everything = map_quality(pts, tall, terrain).obstacles
    half = map_quality(pts, tall & near, terrain, classified=near).obstacles
    blind = map_quality(pts, tall & near, terrain).obstacles  # the same flags, every point taken as classified
    assert 0 < half.true_cells_seen < everything.true_cells_seen
    assert half.recall > 0.5 and blind.recall < half.recall  # the far half's rock cells count as missed only when unclassified points count
    assert half.mapped_cells == blind.mapped_cells
    with pytest.raises(MapEvaluationError, match="classified must have shape"):
        map_quality(pts, tall, terrain, classified=near[:-1])


def test_bad_maps_are_refused(terrain):
    with pytest.raises(MapEvaluationError, match="points"):
        map_quality(np.zeros((0, 3)), np.zeros(0, bool), terrain)
    with pytest.raises(MapEvaluationError, match="lander"):
        lander = np.array([[*terrain.lander.xy, 1.0]])
        map_quality(lander, np.zeros(1, bool), terrain)
