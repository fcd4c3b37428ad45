"""Condition faults (sim/run/faults.py): a robot dies, a camera goes dark, the IMU sticks or saturates, a wheel
encoder fails, a radio goes silent, the computer slows down. One short run of three robots carries one fault of
each kind, each on its own robot and window; every test checks that fault's effect against what the
simulator knows (truth, modelled compute costs, the network's link events)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.run.faults import ConditionFaults, fault_metrics
from sim.run.runner import Run
from sim.scenario import ScenarioError, StageCosts, load_scenario

DIES_S = 9.0
DARK = (6.0, 9.0)
STUCK = (4.0, 5.0)
SATURATED = (10.0, 12.0)
ENCODER_S = 10.0
SILENT = (6.0, 8.0)
SLOW = (3.0, 5.0, 3.0)  # start, end, factor

SCENARIO = {
    "name": "condition_faults",
    "seed": 4,
    "duration_s": 16,
    "terrain": {"size_m": 24, "rocks": {"count": 4}, "craters": {"count": 2}},
    "robots": [
        {"name": "lru1", "preset": "lru", "start": {"xy": [-6, -4]}, "route": {"waypoints": [[7, -4]]}},
        {"name": "lru2", "preset": "lru_wide", "start": {"xy": [-6, 2]}, "route": {"waypoints": [[7, 2]]}},
        {"name": "ardea", "preset": "ardea", "start": {"xy": [-6, -8]}, "route": {"waypoints": [[7, -8]], "cruise_altitude_m": 2.5}},
    ],
    "slam": {"mapping": {"submap_distance_m": 0.8}},
    # the faults' effects alone: ARDEA's drawn camera-IMU time offset (+2.1 ms) leaves its tilt up
    # to 3.2 deg off after 4 s here even without the IMU faults (docs/realism.md, known limits)
    "realism": {"calibration": {"camera_imu_time_offset_ms": 0.0}},
    "output": {"recording": False, "topdown_png": False},
    "faults": [
        {"kind": "dies", "robot": "lru2", "at_s": DIES_S},
        {"type": "camera_dark", "robots": ["lru1"], "start_s": DARK[0], "end_s": DARK[1], "rigs": ["head"]},
        {"type": "imu_stuck", "robots": ["ardea"], "start_s": STUCK[0], "end_s": STUCK[1]},
        {"type": "imu_saturation", "robots": ["ardea"], "start_s": SATURATED[0], "end_s": SATURATED[1]},
        {"type": "encoder_failure", "robots": ["lru1"], "wheel": "fl", "start_s": ENCODER_S},
        {"type": "radio_silent", "robots": ["ardea"], "start_s": SILENT[0], "end_s": SILENT[1]},
        {"type": "compute_slowdown", "robots": ["lru1"], "start_s": SLOW[0], "end_s": SLOW[1], "factor": SLOW[2]},
    ],
}


@pytest.fixture(scope="module")
def run():
    run = Run(load_scenario(SCENARIO))
    run.vo = {name: [] for name in run.robots}
    for name, runtime in run.robots.items():
        runtime.onboard.on_vo_result = lambda result, n=name: run.vo[n].append(result)
    run.link_events = []
    run.network.subscribe(run.link_events.append)
    run.execute()
    return run


def window(t, span):
    t = np.asarray(t)
    return (t >= span[0]) & (t < span[1])


def test_short_forms_and_errors():
    s = load_scenario(SCENARIO)
    assert s.faults[0].type == "dies" and s.faults[0].robots == ["lru2"] and s.faults[0].start_s == DIES_S
    for faults, message in [
        ([{"type": "dies", "start_s": 3, "end_s": 5}], "a robot that dies stays dead"),
        ([{"type": "encoder_failure", "robots": ["ardea"]}], "wheel 'fl' is not a wheel of ardea"),
        ([{"type": "encoder_failure", "wheel": "middle"}], "wheel 'middle' is not a wheel of lru1, lru2, ardea; wheels per preset: lru fl/fr/rl/rr"),
        ([{"type": "camera_dark", "robots": ["lru1"], "rigs": ["down"]}], "rigs ['down'] are not stereo rigs of lru1"),
        ([{"kind": "dies", "type": "dies"}], "give `type` or its short form `kind`, not both"),
        ([{"type": "compute_slowdown", "factor": 0.5}], "greater than or equal to 1"),
    ]:
        with pytest.raises(ScenarioError) as info:
            load_scenario({**SCENARIO, "faults": faults})
        assert message in str(info.value), (faults, str(info.value))


def test_a_dead_robot_stops_goes_silent_and_the_team_keeps_its_submaps(run):
    lru2 = run.robots["lru2"]
    assert lru2.robot.status == "dead" and lru2.faults.died_s == pytest.approx(DIES_S, abs=0.01)
    assert {(w.status, w.reason) for w in lru2.robot.waypoints} == {("failed", "dead")}
    t, pose = np.asarray(lru2.log.gt_t), np.asarray(lru2.log.gt_pose)
    after = t > DIES_S + 2.0  # coasted to a stop
    assert np.ptp(pose[after, :2], axis=0).max() < 0.02
    assert np.asarray(lru2.onboard.log.t).max() <= DIES_S + 1e-6  # its filter log ends
    assert max(lru2.log.imu_t) <= DIES_S + 1e-6
    started = np.concatenate([q.column("started") for q in lru2.lane._stages.values()])
    assert started.max() <= DIES_S + 1e-6  # its computer is off
    sent = {s.index for s in lru2.onboard.mapper.submaps}
    assert sent, "lru2 finished no submap before it died"
    for name in ("lru1", "ardea"):  # the survivors hold what lru2 sent before it died, and nothing else
        agent = run.robots[name].onboard.agent
        held = {i for (robot, i) in agent.peer_submaps if robot == "lru2"}
        assert held and held <= sent, (name, held, sent)
        assert all(s.t_end <= DIES_S + 1e-6 for (robot, _), s in agent.peer_submaps.items() if robot == "lru2")
    for name in ("lru1", "ardea"):  # the others go on
        assert run.robots[name].robot.status != "dead"
        assert np.asarray(run.robots[name].onboard.log.t).max() > DIES_S + 5.0
    metrics = fault_metrics(lru2.onboard, lru2.faults, run.sim_time)
    assert metrics["died_s"] == pytest.approx(DIES_S, abs=0.01)
    assert metrics["timeline"] == [{"type": "dies", "entry": 0, "start_s": DIES_S, "end_s": None}]


def test_a_dark_camera_loses_visual_odometry_only_in_its_window(run):
    results = run.vo["lru1"]
    dark = [r for r in results if DARK[0] + 0.01 <= r.t < DARK[1]]
    before = [r.ok for r in results if 2.0 <= r.t < DARK[0]]
    after = [r.ok for r in results if r.t >= DARK[1] + 1.5]  # tracking again from a new keyframe
    assert dark and not any(r.ok for r in dark)
    assert np.mean(before) > 0.6 and np.mean(after) > 0.6, (np.mean(before), np.mean(after))


def test_a_stuck_imu_repeats_one_sample_and_a_saturated_one_clips(run):
    log = run.robots["ardea"].log
    t, imu, truth = np.asarray(log.imu_t), np.asarray(log.imu), np.asarray(log.imu_true)
    stuck = window(t, STUCK)
    assert np.all(imu[stuck] == imu[stuck][0]) and np.ptp(truth[stuck], axis=0).max() > 0.01
    before = np.flatnonzero(t < STUCK[0])[-1]
    np.testing.assert_array_equal(imu[stuck][0], imu[before])
    sat = window(t, SATURATED)
    assert np.abs(imu[sat, :3]).max() <= 1.0 and np.abs(imu[sat, 3:]).max() <= math.radians(5.0)
    assert np.median(truth[sat, 2]) > 1.4  # hovering on the Moon: 1.62 m/s^2 upwards, clipped to 1.0
    assert np.abs(imu[~sat & (t > 1.0), 2]).max() > 1.4


def test_the_estimator_bridges_the_stuck_and_the_saturated_imu(run):
    """Both windows are noticed within the 10 ms of STUCK_SAMPLES and bridged by ARDEA's
    motion model while its VO goes on (slam/local_estimator.py): its body velocity stays
    within 0.15 m/s and its tilt within 2 deg of the truth through and after them (the
    frozen or clipped samples integrated drifted 0.6-20 m/s and 4-5 deg off here)."""
    est = run.robots["ardea"].onboard.estimator
    assert len(est.imu_outages) == 2
    for (start, end), span in zip(est.imu_outages, (STUCK, SATURATED), strict=True):
        assert span[0] <= start <= span[0] + 0.011 and span[1] - 0.011 <= end < span[1]
    stuck_since = [t for t, _, r in est.health_history if r == "imu stuck"]
    assert stuck_since == [pytest.approx(s, abs=0.011) for s in (STUCK[0], SATURATED[0])]
    log = run.robots["ardea"].onboard.log
    t, x, truth = np.asarray(log.t), np.asarray(log.observable), np.asarray(log.observable_true)
    after = t >= STUCK[0]
    assert np.linalg.norm(x[after, 2:5] - truth[after, 2:5], axis=1).max() < 0.15
    assert np.abs(x[after, :2] - truth[after, :2]).max() < math.radians(2.0)


def test_a_failed_encoder_is_outvoted_and_wheel_odometry_keeps_the_speed(run):
    """The failed wheel reads zero; with it the fit read three quarters of the speed. The
    on-board odometry's encoder check (sim/world/sensors.py) leaves it out, so wheel
    odometry reads the true speed after the failure as before it, and the check, which
    never fires on healthy wheels here, fires in most driving samples after it."""
    log = run.robots["lru1"].log
    odom_t, odom = np.asarray(log.odom_t), np.asarray(log.odom)
    gt_t, gt = np.asarray(log.gt_t), np.asarray(log.gt_pose)
    speed = np.interp(odom_t, gt_t[1:], np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1) / np.diff(gt_t))
    driving = speed > 0.2
    failed = driving & (odom_t > ENCODER_S + 0.5)
    healthy = driving & (odom_t > 3.0) & (odom_t < ENCODER_S)
    assert failed.sum() > 50 and healthy.sum() > 50
    ratio_failed = odom[failed, 0].mean() / speed[failed].mean()
    ratio_healthy = odom[healthy, 0].mean() / speed[healthy].mean()
    assert 0.9 < ratio_failed < 1.1 and 0.9 < ratio_healthy < 1.1, (ratio_failed, ratio_healthy)
    assert run.robots["lru1"].odometry.outvoted_samples >= 0.7 * failed.sum()
    assert run.robots["lru2"].odometry.outvoted_samples == 0  # its wheels are healthy (it dies at 9 s)


def test_a_silent_radio_takes_every_link_of_the_robot_down_for_its_window(run):
    faulted = [e for e in run.link_events if "ardea" in (e.src, e.dst) and "fault" in e.reasons and e.t < DIES_S]  # then lru2 dies
    links = {(e.src, e.dst) for e in faulted}
    assert links == {(a, b) for a in run.network.nodes for b in run.network.nodes if a != b and "ardea" in (a, b)}
    assert {e.t for e in faulted} == {SILENT[0]}
    back = [e for e in run.link_events if (e.src, e.dst) in links and e.up and e.t > SILENT[0]]
    assert back and min(e.t for e in back) == pytest.approx(SILENT[1])


def test_a_slow_computer_takes_factor_times_the_modelled_compute_time(run):
    lane = run.robots["lru1"].lane
    modelled = StageCosts().filter_update_s
    stage = lane._stages["filter_update"]
    started, compute = stage.column("started"), stage.column("compute_s")
    inside = compute[(started >= SLOW[0]) & (started < SLOW[1])]
    outside = compute[(started < SLOW[0]) | (started >= SLOW[1] + 0.1)]
    assert inside.size and outside.size
    np.testing.assert_allclose(inside, modelled * SLOW[2])
    np.testing.assert_allclose(outside, modelled)


def test_condition_faults_answer_by_robot_window_and_rig():
    s = load_scenario(SCENARIO)
    faults = ConditionFaults("lru1", [(i, f) for i, f in enumerate(s.faults) if f.robots == ["lru1"]])
    assert faults.dark("head", 7.0) and not faults.dark("head", 9.0) and not faults.dark("head", 5.9)
    assert faults.active("compute_slowdown", 4.0) is not None and faults.active("compute_slowdown", 5.0) is None
    assert [e["type"] for e in faults.timeline(5.0)] == ["compute_slowdown"]
