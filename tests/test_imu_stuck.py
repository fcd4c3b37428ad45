"""slam.local_estimator: a stuck IMU (its driver repeats the last sample) on synthetic data
with known truth, no simulator. The estimator must notice the repeated samples, bridge
them with the robot's motion model (slam.filter.LocalReferenceFilter.propagate_without_imu)
while the visual odometry goes on, say so in its health, and end as close to the truth as
without the fault; integrating the frozen samples, as the thesis's filter would, drifts
far off."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from test_local_estimator_rest import DT, INIT_TIME, NoImages, VoFeed, feed, filter_params, noisy_imu, rest_and_moves

from sim.robots.lru import LRU
from sim.world.sensors import IMU_PRESETS
from slam.filter import FilterException, FilterParams, LocalReferenceFilter
from slam.health import HealthParams
from slam.lie import yaw_of
from slam.local_estimator import STUCK_SAMPLES, LocalEstimator

SPEC = IMU_PRESETS["xsens_mti10"]
STUCK = (7.0, 10.0)  # s: within the move's acceleration and turn
NO_BOUNDS = HealthParams(max_position_std_m=None, max_velocity_std_mps=None)
ROVER = dict(motion_accel_density=LRU.motion_accel_density, motion_turn_density=LRU.motion_turn_density)


def run(stuck: bool, motion_model: bool, seed: int = 3):
    """A 3 m move with a 0.8 rad turn from 5 s to 17 s, VO at 5 Hz from the truth; with
    ``stuck`` the IMU repeats its sample before :data:`STUCK` throughout it. Returns the
    estimator and its [t, position error, position NEES (3 dof)] at every VO frame."""
    tr = rest_and_moves(25.0, [(5.0, 12.0, 3.0, 1.0, 0.8)])
    imu = noisy_imu(tr, SPEC, np.random.default_rng(seed))
    if stuck:
        inside = (tr.t >= STUCK[0]) & (tr.t < STUCK[1])
        before = np.flatnonzero(tr.t < STUCK[0])[-1]
        imu.f[inside], imu.w[inside] = imu.f[before], imu.w[before]
    params = replace(filter_params(SPEC), **(ROVER if motion_model else {}))
    est = LocalEstimator(params, NoImages(), init_time=INIT_TIME, rest_window=0.5, health_params=NO_BOUNDS)
    vo = VoFeed(tr, np.random.default_rng(seed + 100))
    trace = []

    def each(k, e):
        vo(k, e)
        if e.initialised and k % vo.every == 0 and tr.t[k] >= 4.0:  # the first frame's position is exact
            err = e.filter.pose()[:3, 3] - tr.p[k]
            trace.append((tr.t[k], float(np.linalg.norm(err)), float(err @ np.linalg.solve(e.filter.covariance()[0:3, 0:3], err))))

    feed(est, tr, imu, each)
    yaw_err = math.degrees(abs(yaw_of(est.filter.pose()[:3, :3]) - yaw_of(tr.R[-1])))
    return est, np.array(trace), yaw_err


@pytest.fixture(scope="module")
def runs():
    return {name: run(*args) for name, args in {"clean": (False, True), "bridged": (True, True), "integrated": (True, False)}.items()}


def test_the_stuck_samples_are_bridged_and_health_says_so(runs):
    est, _, _ = runs["bridged"]
    assert est.imu_outages == [[pytest.approx(STUCK[0] + (STUCK_SAMPLES - 2) * DT), pytest.approx(STUCK[1] - DT)]]
    states = [(round(t, 3), s, r) for t, s, r in est.health_history]
    detected = pytest.approx(STUCK[0] + (STUCK_SAMPLES - 2) * DT)
    assert states == [(INIT_TIME, "ok", ""), (detected, "degraded", "imu stuck"), (pytest.approx(STUCK[1]), "ok", "")]
    assert est.health_report()["imu_stuck"] == est.imu_outages
    assert not est.imu_bridged  # VO deltas captured after the outage have been applied
    assert runs["clean"][0].imu_outages == [] and runs["integrated"][0].imu_outages == []  # noise never repeats; no model, no bridge
    # a frozen IMU looks perfectly still: no zero-velocity update may come of it
    assert not any(a < STUCK[1] and b > STUCK[0] for a, b in est.rest_stats.intervals)


def test_the_bridged_estimate_stays_as_good_as_without_the_fault(runs):
    _, clean, clean_yaw = runs["clean"]
    _, bridged, bridged_yaw = runs["bridged"]
    _, integrated, _ = runs["integrated"]
    assert bridged[-1, 1] < max(2 * clean[-1, 1], clean[-1, 1] + 0.02), (bridged[-1, 1], clean[-1, 1])
    assert bridged_yaw < clean_yaw + 0.2
    assert integrated[-1, 1] > 5 * bridged[-1, 1], (integrated[-1, 1], bridged[-1, 1])  # what the thesis's filter would do
    # and it knows its error while bridging: position NEES (3 dof) within the 99.9 % bound at every VO frame
    window = (bridged[:, 0] >= STUCK[0]) & (bridged[:, 0] < STUCK[1] + 1.0)
    assert bridged[window, 2].max() < 16.3, bridged[window, 2].max()


def test_propagation_without_imu_is_constant_velocity_with_the_motion_noise():
    """Position moves on at the velocity, attitude and velocity stand still; the velocity
    variance grows by ``q^2 dt``, the position's with the velocity's and by ``q^2 dt^3 / 3``,
    the attitude's by the turn density's ``q_w^2 dt``; without the model it refuses."""
    params = FilterParams(gyro_noise_density=1e-4, accel_noise_density=1e-3, gyro_bias_random_walk=1e-6, accel_bias_random_walk=1e-5, **ROVER)
    f = LocalReferenceFilter(params, 0.0, accel_at_rest=np.array([0.0, 0.0, 9.81]), gyro_at_rest=np.zeros(3), rest_duration_s=1.0)
    for k in range(201):  # under way: 1 s of acceleration
        f.propagate(k * DT, [0.3, -0.1, 9.81] if k else [0.0, 0.0, 9.81], [0.0, 0.0, 0.0])
    P0, p0, v0, R0 = f.covariance(), f.pose()[:3, 3].copy(), f.velocity().copy(), f.pose()[:3, :3].copy()
    assert v0[0] > 0.29 and v0[1] < -0.09
    for k in range(201, 601):
        f.propagate_without_imu(k * DT)
    P = f.covariance()
    np.testing.assert_allclose(f.pose()[:3, 3], p0 + 2.0 * v0, atol=1e-12)
    np.testing.assert_array_equal(f.velocity(), v0)
    np.testing.assert_array_equal(f.pose()[:3, :3], R0)
    t, qa, qw = 2.0, ROVER["motion_accel_density"], ROVER["motion_turn_density"]
    np.testing.assert_allclose(np.diag(P)[3:6] - np.diag(P0)[3:6], qa**2 * t, rtol=1e-9)
    # p = p0 + t v0 + the motion noise's integral: P_pp = P0_pp + 2 t P0_pv + t^2 P0_vv + q^2 t^3 / 3
    expected = np.diag(P0[0:3, 0:3] + 2 * t * P0[0:3, 3:6] + t**2 * P0[3:6, 3:6]) + qa**2 * t**3 / 3
    np.testing.assert_allclose(np.diag(P)[0:3], expected, rtol=1e-9)
    np.testing.assert_allclose(np.diag(P)[6:9] - np.diag(P0)[6:9], qw**2 * t, rtol=1e-9)
    plain = LocalReferenceFilter(replace(params, motion_accel_density=None, motion_turn_density=None), 0.0,
                                 accel_at_rest=np.array([0.0, 0.0, 9.81]), gyro_at_rest=np.zeros(3), rest_duration_s=1.0)
    with pytest.raises(FilterException, match="needs FilterParams.motion_accel_density"):
        plain.propagate_without_imu(0.1)
    with pytest.raises(FilterException, match="both be > 0 or both None"):
        replace(params, motion_turn_density=None)
