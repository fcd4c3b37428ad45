"""Spin images about the gravity axis (slam/spin_images.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from slam.lie import rot_z
from slam.spin_images import vertical_spin_images


def _surface(xy: np.ndarray) -> np.ndarray:
    """Bumpy ground with three boulders of different sizes."""
    z = 0.15 * np.sin(1.7 * xy[:, 0]) * np.cos(1.1 * xy[:, 1]) + 0.05 * np.sin(4.0 * xy[:, 1])
    for cx, cy, r in ((1.0, 0.5, 0.6), (-1.2, -1.0, 0.4), (0.3, -1.6, 0.25)):
        d = np.hypot(xy[:, 0] - cx, xy[:, 1] - cy)
        z += np.where(d < r, np.sqrt(np.maximum(r**2 - d**2, 0)), 0.0)
    return z


def _sample(rng: np.random.Generator, n: int, noise_m: float) -> np.ndarray:
    xy = rng.uniform(-3, 3, (n, 2))
    return np.column_stack([xy, _surface(xy) + rng.normal(0, noise_m, n)])


def _moved(p: np.ndarray, yaw: float, t: np.ndarray) -> np.ndarray:
    return p @ rot_z(yaw).T + t


def test_spin_images_are_invariant_to_yaw_and_translation():
    rng = np.random.default_rng(0)
    cloud = _sample(rng, 8000, 0.0)
    centers = cloud[rng.choice(len(cloud), 60, replace=False)]
    d = vertical_spin_images(cloud, cKDTree(cloud), centers, 0.8, 10, 0.5)
    yaw, t = 1.1, np.array([4.0, -2.0, 0.3])
    moved = _moved(cloud, yaw, t)
    d2 = vertical_spin_images(moved, cKDTree(moved), _moved(centers, yaw, t), 0.8, 10, 0.5)
    np.testing.assert_allclose(d2, d, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    # but not to a tilt: the vertical is the axis
    tilted = cloud @ np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]]).T
    c_t = centers @ np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]]).T
    assert np.median(np.linalg.norm(vertical_spin_images(tilted, cKDTree(tilted), c_t, 0.8, 10, 0.5) - d, axis=1)) > 0.1


def test_spin_images_find_the_same_place_in_two_noisy_samplings():
    """Two independent, noisy samplings of one surface in frames turned and moved against
    each other: for most places the nearest descriptors in the other cloud include the
    same place, far above chance (3 of 150)."""
    rng = np.random.default_rng(1)
    a = _sample(rng, 9000, 0.02)
    b_world = _sample(rng, 9000, 0.02)
    yaw, t = -2.3, np.array([-1.0, 5.0, 0.0])
    b = _moved(b_world, yaw, t)
    xy = rng.uniform(-2, 2, (150, 2))
    places = np.column_stack([xy, _surface(xy)])
    da = vertical_spin_images(a, cKDTree(a), places, 0.8, 10, 0.5)
    db = vertical_spin_images(b, cKDTree(b), _moved(places, yaw, t), 0.8, 10, 0.5)
    _, nearest = cKDTree(db).query(da, k=3)
    hit = (nearest == np.arange(len(places))[:, None]).any(axis=1) | (
        np.linalg.norm(places[nearest] - places[:, None, :], axis=2) < 0.1
    ).any(axis=1)
    assert hit.mean() > 0.8, hit.mean()  # 0.99 here


def test_a_center_with_too_few_neighbours_gets_a_zero_row():
    cloud = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    d = vertical_spin_images(cloud, cKDTree(cloud), np.zeros((1, 3)), 0.8, 4, 0.5)
    assert d.shape == (1, 16) and not d.any()
