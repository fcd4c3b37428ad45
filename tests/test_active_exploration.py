"""Exploration beyond the thesis: active loop closing (slam/navigation/exploration.py) and
active mutual observation (slam/navigation/observation.py, the rover's head in sim/robots/lru.py)."""

import math

import numpy as np
import pytest

from sim.evaluation import results_folder
from sim.run.runner import Run
from sim.scenario import ScenarioError, load_scenario
from slam.agent import Agent
from slam.lie import rot_z, se3
from slam.messages import FrameSwitchMessage, PoseEstimate, encode
from slam.navigation.exploration import ExplorationException, ExplorationParams, RegionGrid, RevisitPlace, choose_goal
from slam.navigation.observation import peer_to_observe

SQUARE = [[0, 0], [10, 0], [10, 10], [0, 10]]
MATCH_SIGMA_M = 0.05


def test_a_revisit_is_worth_the_entropy_a_match_would_remove():
    assert RevisitPlace(np.zeros(2), np.eye(2) * MATCH_SIGMA_M**2).information(MATCH_SIGMA_M) == pytest.approx(0.0)
    assert RevisitPlace(np.zeros(2), np.eye(2) * (math.e * MATCH_SIGMA_M) ** 2).information(MATCH_SIGMA_M) == pytest.approx(2.0)
    assert RevisitPlace(np.zeros(2), np.diag([0.2**2, MATCH_SIGMA_M**2])).information(MATCH_SIGMA_M) == pytest.approx(math.log(4.0))
    assert RevisitPlace(np.zeros(2), np.eye(2) * 1e-4).information(MATCH_SIGMA_M) == 0.0  # more certain than a match: nothing to gain


def test_active_loop_closing_returns_to_an_uncertain_place_when_that_is_worth_more_than_new_ground():
    grid = RegionGrid(SQUARE, 0.5)
    explored = np.linalg.norm(grid.centers() - 5.0, axis=-1) <= 2.0
    clear = np.zeros(grid.shape, bool)
    robot = np.array([5.0, 5.0])
    place = RevisitPlace(np.array([2.0, 5.0]), np.eye(2) * 0.5**2)  # 3 m away, 0.5 m uncertain: 2 ln 10 nats
    frontier = choose_goal(grid, explored, clear, robot, ExplorationParams(), revisits=[place])
    assert frontier.reason == "" and frontier.gain > 0  # the thesis's exploration (weight 0) ignores it
    frontier_utility = frontier.gain * math.exp(-0.15 * np.linalg.norm(frontier.xy - robot))
    per_weight = place.information(MATCH_SIGMA_M) * math.exp(-0.15 * 3.0)
    back = choose_goal(grid, explored, clear, robot, ExplorationParams(loop_closing_weight=1.2 * frontier_utility / per_weight), revisits=[place])
    assert back.reason == "revisit" and np.allclose(back.xy, place.xy)
    assert back.information == pytest.approx(2 * math.log(10))
    assert back.coverage == frontier.coverage and not back.finished
    on = ExplorationParams(loop_closing_weight=0.8 * frontier_utility / per_weight)
    assert choose_goal(grid, explored, clear, robot, on, revisits=[place]).reason == ""  # new ground is worth more
    heavy = ExplorationParams(loop_closing_weight=1.2 * frontier_utility / per_weight)
    assert choose_goal(grid, explored, clear, robot, heavy, revisits=[place], revisited=[place.xy + 0.4]).reason == ""  # been there
    certain = RevisitPlace(place.xy, np.eye(2) * MATCH_SIGMA_M**2)
    assert choose_goal(grid, explored, clear, robot, heavy, revisits=[certain]).reason == ""
    near = RevisitPlace(robot + [1.0, 0.0], place.cov_xy)  # nearer than min_goal_distance_m
    assert choose_goal(grid, explored, clear, robot, heavy, revisits=[near]).reason == ""
    done = np.ones(grid.shape, bool)
    assert choose_goal(grid, done, clear, robot, heavy, revisits=[place]).finished  # revisits do not prolong a finished exploration


def test_the_options_are_refused_where_they_cannot_work():
    with pytest.raises(ExplorationException, match="loop_closing_weight"):
        ExplorationParams(loop_closing_weight=-1.0)
    with pytest.raises(ExplorationException, match="loop_closing_match_sigma_m"):
        ExplorationParams(loop_closing_match_sigma_m=0.0)
    with pytest.raises(ExplorationException, match="observe_range_m"):
        ExplorationParams(observe_range_m=0.0)
    raw = looking_pair(observe=True)
    raw["exploration"]["observe_interval_s"] = -1
    with pytest.raises(ScenarioError, match="observe_interval_s"):
        load_scenario(raw)


def test_a_robot_looks_at_the_nearest_peer_in_range_it_has_not_detected_lately():
    peers = {"a": np.array([3.0, 0.0]), "b": np.array([0.0, -2.0]), "c": np.array([10.0, 0.0])}
    assert peer_to_observe((0, 0), peers, {}, 100.0, 6.0, 30.0)[0] == "b"
    name, xy = peer_to_observe((0, 0), peers, {"b": 90.0}, 100.0, 6.0, 30.0)
    assert name == "a" and np.allclose(xy, [3.0, 0.0])
    assert peer_to_observe((0, 0), peers, {"b": 90.0, "a": 50.0}, 100.0, 6.0, 30.0)[0] == "a"  # 50 s ago: look again
    assert peer_to_observe((0, 0), peers, {"b": 90.0, "a": 80.0}, 100.0, 6.0, 30.0) is None  # c is out of range
    assert peer_to_observe((0, 0), {}, {}, 0.0, 6.0, 30.0) is None


def test_a_peer_is_placed_on_its_own_odometry_before_the_graphs_connect():
    agent = Agent("lru1", ["lru1", "lru2"], [], estimator=None)
    T01, T12 = se3(rot_z(0.3), [2.0, 0.5, 0.0]), se3(rot_z(-0.1), [1.5, -0.2, 0.01])
    T_frame_body = se3(rot_z(0.2), [0.7, 0.1, 0.0])
    cov = np.eye(6) * 1e-4
    agent.receive(encode("lru2", 1, FrameSwitchMessage("lru2", 0, 10.0, T01, cov)))
    agent.receive(encode("lru2", 2, PoseEstimate("lru2", 25.0, 2, T_frame_body, cov)))
    assert agent.peer_odometry_pose("lru2") is None  # the switch out of frame 1 has not arrived
    agent.receive(encode("lru2", 3, FrameSwitchMessage("lru2", 1, 20.0, T12, cov)))
    t, T = agent.peer_odometry_pose("lru2")
    assert t == 25.0 and np.allclose(T, T01 @ T12 @ T_frame_body)
    assert agent.belief("lru2") is None  # the graph does not hold lru2
    assert agent.peer_odometry_pose("lru3") is None and agent.last_detection_t("lru2") == -math.inf


def looking_pair(observe: bool) -> dict:
    """Two LRUs 1.5 m apart, back to back, each exploring away from the other without scans:
    they see each other only if they look back. (From 4 m apart the detector found the
    markers in a few frames at most, so whether any frame caught them hung on the moments
    the cameras triggered; from 2 m apart one rover's markers, 10 px tall and seen
    obliquely from behind, decoded in one frame of nine or in none, by the lenses' and the
    noise's draw; from 1.5 m in 4 of 5 and 4 of 7 frames.)"""
    route = {"speed_mps": 0.3}
    return {
        "name": "back_to_back",
        "seed": 2,
        "duration_s": 25,
        "drain_s": 2,
        "terrain": {"preset": "moon", "size_m": 30, "roughness_m": 0.02, "craters": {"count": 0}, "lander": None,
                    "rocks": {"count": 0}},
        "robots": [
            {"name": "lru1", "preset": "lru", "start": {"xy": [0.75, 0], "yaw_deg": 0}, "navigation": {"pose_source": "estimate"}, "route": route},
            {"name": "lru2", "preset": "lru", "start": {"xy": [-0.75, 0], "yaw_deg": 180}, "navigation": {"pose_source": "estimate"},
             "route": route},
        ],
        "exploration": {"region": [[-12, -4], [12, -4], [12, 4], [-12, 4]], "initial_scan": False, "scan_at_goal": False,
                        "observe_peers": observe},
        "slam": {"matching": {"enabled": False}},
        "output": {"recording": False, "topdown_png": False},
    }


@pytest.fixture(scope="module")
def back_to_back(tmp_path_factory):
    out = {}
    for observe in (False, True):
        run = Run(load_scenario(looking_pair(observe)))
        run.execute()
        out[observe] = (run, results_folder.write(run, tmp_path_factory.mktemp(f"observe_{observe}")))
    return out


def test_rovers_that_look_for_each_other_detect_each_other(back_to_back):
    _, blind = back_to_back[False]
    run, looking = back_to_back[True]
    assert blind["loop_closures"]["team"]["detections"] == 0
    assert all(r["observations"] == 0 for r in blind["exploration"]["robots"].values())
    assert looking["loop_closures"]["team"]["detections"] >= 2
    for name, peer in (("lru1", "lru2"), ("lru2", "lru1")):
        onboard = run.robots[name].onboard
        assert looking["exploration"]["robots"][name]["observations"] >= 1
        assert onboard.agent.last_detection_t(peer) > 0  # it saw its peer's markers
        assert looking["robots"][name]["navigation"]["collisions"] == 0
