"""slam.local_estimator: the estimator's health (ok, degraded, lost) and the VO counts on
synthetic data with known truth, no simulator: health follows the visual odometry as it
stops and resumes, rejections are counted by reason, and the filter's covariance grows
while the IMU alone is integrated (thesis 4.1: the visual-odometry deltas are what bound
it)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_local_estimator_rest import (
    INIT_TIME,
    NoImages,
    VoFeed,
    circling,
    estimator,
    feed,
    noisy_imu,
    rest_and_moves,
)

from sim.world.sensors import IMU_PRESETS
from slam.health import HealthException, HealthParams, HealthState
from slam.vo import VoFailure, VoResult

SPEC = IMU_PRESETS["xsens_mti10"]
NO_BOUNDS = HealthParams(max_position_std_m=None, max_velocity_std_mps=None)


def drive(truth, vo_modes, health=NO_BOUNDS, seed=0, each=None):
    """Feed ``truth`` with VO per ``vo_modes``: ``[(t_from, mode), ...]`` (see VoFeed)."""
    imu = noisy_imu(truth, SPEC, np.random.default_rng(seed))
    est = estimator(SPEC, NoImages(), health_params=health)
    vo = VoFeed(truth, np.random.default_rng(seed + 100))

    def step(k, e):
        for t_from, mode in vo_modes:
            if truth.t[k] >= t_from:
                vo.mode = mode
        vo(k, e)
        if each is not None:
            each(k, e)

    feed(est, truth, imu, step)
    return est


def test_health_follows_vo_loss_and_recovery():
    """Driving a circle (never at rest): VO ok, then failing from 20 s to 60 s, then ok.
    Health: ok; degraded ("vo lost") 3 s after the last applied delta; lost 30 s later;
    ok again with the first applied delta. The VO failures are counted by reason."""
    tr = circling(70.0, start=INIT_TIME)
    est = drive(tr, [(0.0, "ok"), (20.0, "fail"), (60.0, "ok")])
    hist = est.health_history
    assert [(s, r) for _, s, r in hist] == [("ok", ""), ("degraded", "vo lost"), ("lost", "vo lost"), ("ok", "")], hist
    last_applied = 19.8  # the last frame before 20 s (5 Hz)
    assert hist[1][0] == pytest.approx(last_applied + 3.0, abs=0.11)
    assert hist[2][0] == pytest.approx(last_applied + 33.0, abs=0.11)
    assert hist[3][0] == pytest.approx(60.0)  # the first delta after the VO came back (from the last failed frame, a keyframe)
    assert est.health.state == HealthState.OK and est.health.since == hist[3][0]
    stats = est.vo_stats
    assert stats.failures == {"first_frame": 1, "too_few_inliers": 200}
    assert stats.frames == stats.ok + sum(stats.failures.values()) and stats.ok == stats.applied + stats.rejected
    assert stats.rejected == 0 and est.time_since_vo < 0.25
    report = est.health_report()
    assert report["state"] == "ok" and report["transitions"][1][1:] == ["degraded", "vo lost"]
    assert report["time_s"]["degraded"] == pytest.approx(30.0, abs=0.2)
    assert report["time_s"]["lost"] == pytest.approx(60.0 - 52.8, abs=0.3)
    assert sum(report["time_s"].values()) == pytest.approx(70.0 - INIT_TIME, abs=0.01)


def test_degraded_health_says_why_and_since_when():
    """The reason follows the latest VO outcome: deltas rejected by the filter's gate
    ("vo rejected", detail "gate"), then failing ("vo lost", detail the VO's reason);
    ``since`` stays the time the estimate became degraded."""
    tr = circling(30.0, start=INIT_TIME)
    seen = []

    def each(k, e):
        if k % 20 == 0:
            seen.append((tr.t[k], e.health))

    est = drive(tr, [(0.0, "ok"), (10.0, "outlier"), (16.0, "fail"), (22.0, "ok")], each=each)
    at = {round(t, 1): h for t, h in seen}
    assert at[12.0].state == HealthState.OK
    h = at[15.0]
    assert (h.state, h.reason, h.detail) == (HealthState.DEGRADED, "vo rejected", "gate")
    assert h.since == pytest.approx(9.8 + 3.0, abs=0.11)
    h = at[18.0]
    assert (h.state, h.reason, h.detail) == (HealthState.DEGRADED, "vo lost", "too_few_inliers")
    assert h.since == at[15.0].since  # still degraded since then
    assert est.health.state == HealthState.OK
    stats = est.vo_stats
    assert stats.rejections_by_reason == {"gate": 30} and stats.rejected == 30
    assert stats.failures["too_few_inliers"] == 30
    assert [r for _, _, r in est.health_history] == ["", "vo rejected", "vo lost", ""]


def test_delta_without_clones_is_counted_as_rejected():
    """A delta whose keyframe clone is no longer held cannot be applied: "no clone"."""
    tr = circling(3.0, start=INIT_TIME)
    est = drive(tr, [(0.0, "ok")])
    frame = 10_001
    assert est.on_capture(frame, est.filter.t, np.eye(4))
    result = VoResult(est.filter.t, frame, True, None, 10_000, np.eye(4), np.eye(6) * 1e-4, 50, np.zeros((0, 2)), False, (frame,))
    assert est.on_vo(result) is None
    assert est.vo_stats.rejections_by_reason == {"no clone": 1}


def test_position_covariance_grows_with_the_imu_alone():
    """When the frames stop (no VO results at all) the filter integrates the IMU alone and
    its covariance says so: position and velocity std grow at every step; the health
    degrades ("vo lost", "no results") and, with a 0.5 m bound on the position std, is
    lost when the covariance passes it, long before 30 s."""
    tr = circling(40.0, start=INIT_TIME)
    stds = []

    def each(k, e):
        if k % 100 == 0 and tr.t[k] >= 10.0:
            P = e.filter.covariance()
            stds.append((tr.t[k], math.sqrt(np.linalg.eigvalsh(P[0:3, 0:3])[-1]), math.sqrt(np.linalg.eigvalsh(P[3:6, 3:6])[-1])))

    health = HealthParams(max_position_std_m=0.5, max_velocity_std_mps=None)
    est = drive(tr, [(0.0, "ok"), (10.0, "none")], health=health, each=each)
    pos = np.array([p for _, p, _ in stds])
    vel = np.array([v for _, _, v in stds])
    assert np.all(np.diff(pos[1:]) > 0) and np.all(np.diff(vel[1:]) > 0)
    assert pos[-1] > 20 * pos[1] and vel[-1] > 5 * vel[1]
    hist = est.health_history
    assert [(s, r) for _, s, r in hist] == [("ok", ""), ("degraded", "vo lost"), ("lost", "vo lost")]
    assert hist[1][0] == pytest.approx(9.8 + 3.0, abs=0.11) and hist[2][0] < 9.8 + 33.0 - 5.0
    assert est.health.detail.startswith("position std")
    t_lost = hist[2][0]
    assert next(p for t, p, _ in stds if t >= t_lost) > 0.5 > next(p for t, p, _ in reversed(stds) if t < t_lost - 0.1)


def test_resting_robot_without_vo_stays_ok():
    """A landed hexacopter whose stereo fails near the ground: at rest with zero-velocity
    updates its estimate is aided and health stays ok; when it moves off with the VO
    still failing it degrades 3 s after the last update, and is ok again once it rests."""
    tr = rest_and_moves(32.0, [(20.0, 8.0, 2.0, 0.0, 1.0)])
    est = drive(tr, [(0.0, "ok"), (3.0, "fail")])
    assert est.rest_stats.applied > 150
    hist = est.health_history
    assert [(s, r) for _, s, r in hist] == [("ok", ""), ("degraded", "vo lost"), ("ok", "")]
    assert 20.0 + 3.0 < hist[1][0] < 20.0 + 3.0 + 0.5  # the move is noticed within half a second
    assert 28.0 + 0.5 <= hist[2][0] < 28.0 + 1.0  # rest again: min_rest_s and one window
    assert est.health_report()["time_s"]["degraded"] == pytest.approx(hist[2][0] - hist[1][0])


def test_health_params_are_checked():
    with pytest.raises(HealthException, match="vo_timeout_s"):
        HealthParams(vo_timeout_s=0.0)
    with pytest.raises(HealthException, match="max_position_std_m"):
        HealthParams(max_position_std_m=-1.0)
    assert VoFailure.TOO_FEW_INLIERS == "too_few_inliers"
