"""Navigation on the robot's own estimate (sim/robots/path_following.py) and collisions
(sim/run/collisions.py), against the simulator's truth."""

import math

import numpy as np
import pytest

from sim.evaluation.navigation import navigation_metrics
from sim.evaluation.trajectory import Trajectory
from sim.run.runner import Run
from sim.scenario import ScenarioError, load_scenario
from sim.seeding import RandomStreams
from sim.world.terrain import generate_terrain

ROCK_DIAMETER_M = 2.0  # semi-axes 1 m x 0.6-1 m x 0.45-0.8 m: too tall to climb, too wide to pass between the wheels


def behind_rock(pose_source: str, seed: int) -> dict:
    """One rover, a 2 m rock on the straight line to its goal 8 m ahead."""
    return {
        "name": "behind_rock",
        "seed": seed,
        "duration_s": 55,
        "terrain": {"preset": "moon", "size_m": 20, "roughness_m": 0.02, "craters": {"count": 0}, "lander": None,
                    "rocks": {"count": 0, "placed": [{"xy": [0, 0], "diameter_m": ROCK_DIAMETER_M}]}},
        "robots": [{"name": "lru1", "preset": "lru", "start": {"xy": [-4, 0.2], "yaw_deg": 0},
                    "navigation": {"pose_source": pose_source}, "route": {"speed_mps": 0.3, "waypoints": [[4, 0]]}}],
        "slam": {"graph": {"enabled": False}},
        "output": {"recording": False},
    }


def truth_of(run: Run, name: str) -> Trajectory:
    log = run.robots[name].log
    return Trajectory.from_pose_rows(log.gt_t, log.gt_pose)


def distance_to_rock_footprint(run: Run, xy: np.ndarray) -> np.ndarray:
    """Horizontal distance from points to the rock's hull outline (negative inside), by sampling the outline."""
    rock = run.terrain.rocks[0]
    c, s = math.cos(rock.yaw), math.sin(rock.yaw)
    v = rock.vertices[:, :2] @ np.array([[c, s], [-s, c]]) + rock.center[:2]
    d = np.linalg.norm(xy[:, None, :] - v[None], axis=2).min(axis=1)
    inside = np.hypot(*(xy - rock.center[:2]).T) < np.linalg.norm(v - rock.center[:2], axis=1).min()
    return np.where(inside, -d, d)


@pytest.fixture(scope="module")
def on_estimate():
    run = Run(load_scenario(behind_rock("estimate", seed=3)))
    run.execute()
    return run


def test_a_rover_on_its_estimate_plans_around_the_rock_to_the_goal_behind_it(on_estimate):
    run = on_estimate
    robot = run.robots["lru1"].robot
    (wp,) = robot.waypoints
    assert wp.status == "reached"
    truth = truth_of(run, "lru1")
    xy = truth.T[:, :2, 3]
    # the wheels (0.42 m either side of the body's centre line) never reached the rock's foot
    assert distance_to_rock_footprint(run, xy).min() > 0.42
    assert np.abs(xy[:, 1]).max() > 1.0  # it went round, not over
    assert np.linalg.norm(xy[-1] - wp.xy) < robot.cfg.route.tolerance_m + 0.3  # truly near the goal it believed it reached
    log = run.robots["lru1"].log
    nav = navigation_metrics(robot, run.collisions.of("lru1"), np.asarray(log.guidance_t), np.asarray(log.guidance_xy), truth)
    assert nav["pose_source"] == "estimate" and nav["collisions"] == 0 and nav["stuck"] == 0
    assert nav["plans"] >= 10  # replanned about once a second on the way
    # the guidance's belief is the filter's own, which is not the truth, but close
    assert 0.0 < nav["guidance_error_m"]["final"] < 0.3
    assert nav["waypoint_miss_m"]["max"] == pytest.approx(np.linalg.norm(np.subtract(wp.final_xy, wp.xy)))


def test_the_same_rover_on_the_truth_drives_straight_at_the_rock_and_gets_stuck():
    run = Run(load_scenario(behind_rock("truth", seed=3), ["duration_s=40"]))
    run.execute()
    robot = run.robots["lru1"].robot
    (wp,) = robot.waypoints
    assert wp.status == "failed" and wp.reason == "stuck"
    xy = truth_of(run, "lru1").T[:, :2, 3]
    assert distance_to_rock_footprint(run, xy).min() < 0.42  # its wheels ran onto the rock
    assert np.abs(xy[:, 1]).max() < 0.5
    assert robot.follower is None and len(run.robots["lru1"].log.guidance_t) == 0


def test_a_rover_driving_into_a_resting_one_is_a_collision_of_both():
    raw = {
        "name": "ram",
        "duration_s": 18,
        "terrain": {"size_m": 20, "rocks": {"count": 0}, "craters": {"count": 0}, "lander": None},
        "robots": [
            {"name": "mover", "preset": "lru", "start": {"xy": [-3, 0]}, "route": {"waypoints": [[3, 0]], "stuck_timeout_s": 5}},
            {"name": "rester", "preset": "lru", "start": {"xy": [0.5, 0.1]}},
        ],
        "slam": {"enabled": False},
        "output": {"recording": False},
    }
    run = Run(load_scenario(raw))
    run.execute()
    mover, rester = run.collisions.of("mover"), run.collisions.of("rester")
    assert mover and rester
    assert {c.other for c in mover} == {"rester"} and {c.other for c in rester} == {"mover"}
    # the first contact is when the two came within reach of each other: 1.28 m between centres at most
    truth = truth_of(run, "mover")
    first = mover[0].t
    gap = np.linalg.norm(truth.at(first)[:2, 3] - [0.5, 0.1])
    assert gap < 2 * 0.64 + 0.05
    assert min(c.t for c in mover) == pytest.approx(min(c.t for c in rester))
    # nothing collides with the ground or itself: a robot alone on flat ground has none
    alone = Run(load_scenario(raw, ["robots.rester.start.xy=[0.5, 6]", "duration_s=12"]))
    alone.execute()
    assert alone.collisions.events == []


def test_estimate_navigation_is_refused_where_it_cannot_work():
    base = behind_rock("estimate", seed=1)
    with pytest.raises(ScenarioError, match="needs slam.enabled and slam.mapping.enabled"):
        load_scenario(base, ["slam.mapping.enabled=false"])
    copter = dict(base, robots=[{"name": "a", "preset": "ardea", "start": {"xy": [-4, 0]}, "navigation": {"pose_source": "estimate"}}])
    with pytest.raises(ScenarioError, match="not built for preset ardea"):
        load_scenario(copter)
    with pytest.raises(ScenarioError, match=r"placed.0: the rock at \[-4.0, 0.5\] lies on robot lru1's start"):
        load_scenario(base, ["terrain.rocks.placed=[{xy: [-4, 0.5], diameter_m: 1}]"])
    with pytest.raises(ScenarioError, match="reaches off the 20 m terrain"):
        load_scenario(base, ["terrain.rocks.placed=[{xy: [9.5, 0], diameter_m: 1}]"])


def test_placed_rocks_stand_where_asked_and_the_random_ones_keep_clear_of_them():
    base = behind_rock("truth", seed=5)
    base["terrain"]["rocks"]["count"] = 40
    scenario = load_scenario(base)
    terrain = generate_terrain(scenario.terrain, RandomStreams(scenario.seed).rng("terrain"), scenario.keep_clear())
    assert len(terrain.rocks) == 41
    placed = terrain.rocks[0]
    assert np.allclose(placed.center[:2], [0, 0])
    assert 2 * np.abs(placed.vertices[:, 0]).max() == pytest.approx(ROCK_DIAMETER_M, rel=0.16)
    reach = np.linalg.norm(placed.vertices[:, :2], axis=1).max()
    for rock in terrain.rocks[1:]:
        assert np.hypot(*rock.center[:2]) > reach + np.linalg.norm(rock.vertices[:, :2], axis=1).max() - 1e-9
