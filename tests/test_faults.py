"""Injected failures (sim/run/faults.py, the scenario's ``faults`` section): validation, wrong detections and
wrong matches as the agent sees them (slam.agent.MeasurementFaults), and whole runs: a wrong detection is
wrong against the truth and counted, ``rate: 0`` changes nothing, the same seed gives the same metrics."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sim.run.faults import MEASUREMENT_FAULTS, MeasurementFaultInjector, fault_metrics, measurement_faults
from sim.run.run_folder import run_to_folder
from sim.scenario import ScenarioError, load_scenario
from sim.seeding import RandomStreams
from slam.agent import Agent
from slam.lie import rotation_angle, se3, se3_inv, so3_exp, so3_log
from slam.matcher import MatchResult, Prior
from slam.team_matcher import MatchRecord

QUICKSTART = "scenarios/quickstart.yaml"


def problems(overrides: list[str]) -> list[str]:
    with pytest.raises(ScenarioError) as info:
        load_scenario(QUICKSTART, overrides)
    return info.value.problems


# ---------------------------------------------------------------------------- 1. the faults section


@pytest.mark.parametrize(
    "faults, message",
    [
        ("[{type: wrong_detection, rate: 1.5}]", "faults.0.rate: got 1.5: Input should be less than or equal to 1"),
        ("[{type: wrong_detection, rate: -0.1}]", "faults.0.rate: got -0.1: Input should be greater than or equal to 0"),
        ("[{type: wrong_match}]", "faults.0.rate: required key is missing"),
        ("[{rate: 0.1}]", "faults.0: required key `type` is missing"),
        ("[{type: robot_failure, rate: 0.1}]", "does not match any of the expected tags: 'wrong_detection', 'wrong_match'"),
        (
            "[{type: wrong_match, rate: 0.1, robots: [lru9]}]",
            "faults.0 (wrong_match): robots: no robot named 'lru9'; robots: ['lru1', 'lru2', 'ardea']",
        ),
        ("[{type: wrong_match, rate: 0.1, robots: []}]", "faults.0.robots: got []: List should have at least 1 item"),
        ("[{type: wrong_detection, rate: 0.1, start_s: 5, end_s: 2}]", "faults.0: end_s (2) must be after start_s (5)"),
        ("[{type: wrong_detection, rate: 0.1, rotation_deg: 200}]", "faults.0.rotation_deg: got 200: Input should be less than or equal to 180"),
        ("[{type: wrong_detection, rate: 0.1, sigma_m: 0.1}]", "faults.0.sigma_m: unknown key; allowed keys here: end_s, rate, robots, rotation_deg"),
        ("{type: wrong_detection, rate: 0.1}", "faults: Input should be a valid list"),
    ],
)
def test_faults_section_errors_name_the_entry_and_the_key(faults, message):
    assert any(message in line for line in problems([f"faults={faults}"])), problems([f"faults={faults}"])


def test_faults_section_entries_and_defaults():
    s = load_scenario(QUICKSTART, ["faults=[{type: wrong_detection, rate: 0.2, robots: [lru1], end_s: 30}, {type: wrong_match, rate: 1}]"])
    detection, match = s.faults
    assert (detection.type, detection.rate, detection.robots, detection.start_s, detection.end_s) == ("wrong_detection", 0.2, ["lru1"], 0.0, 30.0)
    assert (detection.translation_m, detection.rotation_deg) == (1.0, 20.0)
    assert (match.type, match.robots, match.sigma_m, match.sigma_deg) == ("wrong_match", None, 0.03, 1.0)
    assert detection.hits("lru1", 0.0) and not detection.hits("lru1", 30.0) and not detection.hits("lru2", 1.0)
    assert load_scenario(QUICKSTART).faults == []
    streams = RandomStreams(0)
    assert measurement_faults(s, "lru2", streams) is not None and measurement_faults(load_scenario(QUICKSTART), "lru1", streams) is None


# ---------------------------------------------------------------------------- 2. wrong measurements


def injector(faults: str, robot: str = "lru1", seed: int = 0) -> MeasurementFaultInjector:
    return measurement_faults(load_scenario(QUICKSTART, [f"faults={faults}", f"seed={seed}"]), robot, RandomStreams(seed))


def test_wrong_detection_is_off_by_the_configured_error_in_a_random_direction():
    T = se3(so3_exp([0.1, -0.2, 0.3]), [2.0, 0.5, 0.1])
    faults = injector("[{type: wrong_detection, rate: 1, translation_m: 0.7, rotation_deg: 25}]")
    wrong = [faults.detection(float(t), "lru2", T) for t in range(20)]
    for W in wrong:
        D = se3_inv(T) @ W
        assert np.linalg.norm(D[:3, 3]) == pytest.approx(0.7) and rotation_angle(D[:3, :3]) == pytest.approx(math.radians(25))
    axes = np.array([so3_log((se3_inv(T) @ W)[:3, :3]) for W in wrong])
    assert np.abs(axes / np.linalg.norm(axes, axis=1, keepdims=True)).max(axis=0).min() > 0.5  # every axis turns up
    assert faults.counts() == {"wrong_detection": 20, "wrong_match": 0}
    assert [e.what for e in faults.events[:2]] == ["lru2", "lru2"] and faults.events[3].t == 3.0 and faults.events[0].entry == 0


def test_rate_window_robots_and_streams():
    T = np.eye(4)
    some = injector("[{type: wrong_detection, rate: 0.3}]")
    hits = sum(some.detection(float(t), "lru2", T) is not None for t in range(1000))
    assert 250 < hits < 350
    assert all(injector("[{type: wrong_detection, rate: 0}]").detection(float(t), "lru2", T) is None for t in range(100))
    window = injector("[{type: wrong_detection, rate: 1, start_s: 10, end_s: 20}]")
    assert [t for t in range(30) if window.detection(float(t), "lru2", T) is not None] == list(range(10, 20))
    assert injector("[{type: wrong_detection, rate: 1, robots: [lru2]}]") is None  # lru1 is not hit
    # the same seed draws the same errors; another seed others
    runs = [[injector("[{type: wrong_detection, rate: 0.5}]", seed=s).detection(float(t), "lru2", T) for t in range(10)] for s in (3, 3, 4)]
    same = all((a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b)) for a, b in zip(runs[0], runs[1]))
    assert same and any((a is None) != (c is None) or (a is not None and not np.array_equal(a, c)) for a, c in zip(runs[0], runs[2]))


def test_wrong_match_is_the_prediction_off_by_yaw_and_a_horizontal_shift_with_a_confident_covariance():
    predicted = se3(so3_exp([0.0, 0.0, 0.4]), [3.0, -1.0, 0.2])
    faults = injector("[{type: wrong_match, rate: 1, translation_m: 0.8, rotation_deg: 12, sigma_m: 0.02, sigma_deg: 0.5}]")
    for matched in (False, True):
        T, cov = faults.match(50.0, ("lru1", 2), ("lru2", 5), predicted, matched)
        D = se3_inv(predicted) @ T
        assert np.linalg.norm(D[:2, 3]) == pytest.approx(0.8) and D[2, 3] == 0.0
        assert abs(so3_log(D[:3, :3])[2]) == pytest.approx(math.radians(12)) and np.allclose(so3_log(D[:3, :3])[:2], 0.0)
        assert np.allclose(np.sqrt(np.diag(cov)), [math.radians(0.5)] * 3 + [0.02] * 3)
    assert faults.counts() == {"wrong_detection": 0, "wrong_match": 2} and faults.events[0].what == "lru1:2 -> lru2:5"
    assert faults.detection(1.0, "lru2", predicted) is None  # a wrong_match entry leaves detections alone


class _Matcher:
    """What Agent.attempt_match and the loop closure handler use of a TeamMatcher: one failed attempt."""

    def __init__(self, prior: Prior):
        self.records, self.prior, self.stale = [], prior, False

    def attempt(self, cand, t):
        record = MatchRecord(t, 2, 5, self.prior, MatchResult(("lru1", 2), ("lru2", 5), reason="too few inliers"))
        self.records.append(record)
        return record


def test_agent_sends_the_wrong_closure_and_keeps_it_marked_in_the_matcher_record():
    """slam.agent: a match attempt the matcher rejected becomes a loop closure at the prediction plus the
    injected error; the attempt's record holds it (so the loop closure evaluation compares it with the truth)."""
    predicted = se3(so3_exp([0.0, 0.0, 0.4]), [3.0, -1.0, 0.2])
    faults = injector("[{type: wrong_match, rate: 1}]")
    agent = Agent("lru1", ["lru1", "lru2"], [], estimator=None, faults=faults)
    agent.matcher = _Matcher(Prior(predicted, np.full(3, 0.2)))
    out, record = agent.attempt_match(SimpleNamespace(pair=(("lru1", 2), ("lru2", 5))), 40.0)
    assert [m.kind for m in out] == ["loop_closure"] and agent.matcher.records == [record]
    assert record.result.success and record.result.reason == "injected"
    assert np.linalg.norm((se3_inv(predicted) @ record.result.T_a_b)[:3, 3]) == pytest.approx(1.0)
    assert agent.graph.pending_count() == 1  # the c factor, waiting for both chains
    assert faults.counts()["wrong_match"] == 1


# ---------------------------------------------------------------------------- 3. whole runs

# tests/test_slam_run.py's encounter, first 8 s: lru1 sees the lander's tag (3.4 s) and lru2's mast (4.6 s).
ENCOUNTER = [
    "duration_s=8",
    "output.recording=false",
    "output.topdown_png=false",
    "robots.lru1.start.xy=[-1.5, 3.5]",
    "robots.lru1.start.yaw_deg=90",
    "robots.lru2.start.xy=[1.5, 3.5]",
    "robots.lru2.start.yaw_deg=90",
    "robots.*.route.waypoints=[]",
    "robots.lru1.route.waypoints=[{xy: [-1.5, 4.5], scan: true}]",
    "robots.lru2.route.waypoints=[{xy: [1.5, 4.5], scan: true}]",
    "robots.*.route.scan_duration_s=12",
]
WRONG = "faults=[{type: wrong_detection, rate: 1.0}]"
ZERO = "faults=[{type: wrong_detection, rate: 0}, {type: wrong_match, rate: 0}]"


def run_metrics(folder: Path, *extra: str) -> dict:
    run_to_folder(load_scenario("scenarios/spacebotcamp_outage.yaml", ENCOUNTER + list(extra)), folder)
    return json.loads((folder / "metrics.json").read_text())


def without_wall_time(value, key: str = ""):
    """The metrics without what measures the computer, not the run: runtime, wall times, iSAM2/GNC milliseconds."""
    if isinstance(value, dict):
        return {k: without_wall_time(v, k) for k, v in value.items() if k != "runtime" and "wall" not in k and not k.endswith("_ms")}
    if isinstance(value, list):
        return [without_wall_time(v) for v in value]
    return value


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folders = {}

    def get(label: str, *extra: str) -> dict:
        if label not in folders:
            folders[label] = run_metrics(tmp_path_factory.mktemp(label), *extra)
        return folders[label]

    return get


def test_wrong_detections_are_wrong_against_truth_counted_and_marked(runs):
    m = runs("wrong", WRONG)
    lru1 = m["robots"]["lru1"]
    used = lru1["slam"]["detections"]["used"]
    assert used >= 2 and lru1["faults"]["injected"] == {"wrong_detection": used, "wrong_match": 0}
    assert sorted({e["what"] for e in lru1["faults"]["events"]}) == ["landmark:0", "lru2"]
    # 1 m and 20 deg off (default error) against the truth, in both evaluations of detections
    errors = lru1["slam"]["detections"]["position_error_m"]
    assert 0.9 < errors["median"] <= errors["max"] < 1.1, errors
    assert m["loop_closures"]["robots"]["lru1"]["detections"]["calibration"]["within_3_sigma"] < 0.7


def test_rate_zero_changes_nothing_against_no_faults_section(runs):
    none, zero = runs("none"), runs("zero", ZERO)
    assert none["robots"]["lru1"]["slam"]["detections"]["used"] >= 2  # there were detections to spare
    assert none["robots"]["lru1"]["faults"] == zero["robots"]["lru1"]["faults"] == {
        "injected": dict.fromkeys(MEASUREMENT_FAULTS, 0),
        "events": [],
        "timeline": [],
        "died_s": None,
    }
    assert without_wall_time(zero) == without_wall_time(none)


@pytest.mark.slow
def test_same_seed_same_wrong_detections_same_metrics(runs, tmp_path):
    again = run_metrics(tmp_path, WRONG)
    assert without_wall_time(again) == without_wall_time(runs("wrong", WRONG))


def test_fault_metrics_without_an_onboard_stack():
    assert fault_metrics(None) == {"injected": {"wrong_detection": 0, "wrong_match": 0}, "events": [], "timeline": [], "died_s": None}
