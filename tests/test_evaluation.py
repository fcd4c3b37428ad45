import math

import numpy as np
import pytest

from sim.evaluation.trajectory import gravity_aligned, in_start_frame, trajectory_metrics


def circle(n=200, radius=5.0, z=0.0):
    t = np.linspace(0, 60, n)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    a = t / 60 * math.pi  # half circle
    poses[:, 0, 3] = radius * np.sin(a)
    poses[:, 1, 3] = radius * (1 - np.cos(a))
    poses[:, 2, 3] = z
    for i, yaw in enumerate(a):
        c, s = math.cos(yaw), math.sin(yaw)
        poses[i, :2, :2] = [[c, -s], [s, c]]
    return t, poses


def test_start_frame_drops_roll_and_pitch_but_keeps_yaw():
    T = np.eye(4)
    T[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    T[:3, 3] = [1, 2, 3]
    G = gravity_aligned(T)
    assert np.allclose(G[:3, 2], [0, 0, 1]) and np.allclose(G[:3, 0], [0, 1, 0]) and np.allclose(G[:3, 3], [1, 2, 3])
    local = in_start_frame(np.stack([T, T]))
    assert np.allclose(local[0][:3, 3], 0)


def test_constant_offset_is_the_unaligned_ate_and_vanishes_when_aligned():
    t, gt = circle()
    est = gt.copy()
    est[:, :3, 3] += [0.3, -0.4, 0.0]  # 0.5 m off everywhere
    m = trajectory_metrics(t, est, t, gt)
    assert m["ate_m"]["rmse"] == pytest.approx(0.5, abs=1e-9)
    assert m["ate_aligned_m"]["rmse"] < 1e-6
    assert m["final_error_m"] == pytest.approx(0.5)
    assert m["distance_m"] == pytest.approx(5 * math.pi, rel=1e-3)
    assert m["final_error_percent_of_distance"] == pytest.approx(50 / (5 * math.pi), rel=1e-3)


def test_yaw_drift_shows_in_yaw_error_and_rpe():
    t, gt = circle()
    est = gt.copy()
    drift = np.radians(10) * t / t[-1]  # 10 deg of yaw drift at the end, positions rotated with it
    for i, d in enumerate(drift):
        c, s = math.cos(d), math.sin(d)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        est[i, :3, :3] = R @ gt[i, :3, :3]
        est[i, :3, 3] = R @ gt[i, :3, 3]
    m = trajectory_metrics(t, est, t, gt)
    assert m["yaw_error_deg"]["final"] == pytest.approx(10, abs=1e-6)
    assert m["rpe_per_m"]["mean"] > 0.0
    assert m["ate_m"]["max"] > m["ate_aligned_m"]["max"]
