"""Clustering of correspondences (thesis 6.1.2, ``slam/voting.py``): the yaw sweep finds
the right correspondences among many wrong ones without reference frames; Hough3D finds
them only as far as the two keypoints' frames agree."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam.lie import rot_z, se3, so3_exp_batch
from slam.voting import hough3d, yaw_sweep

TRUE_YAW = math.radians(37.0)
T_TRUE = se3(rot_z(TRUE_YAW), [2.5, -1.2, 0.3])  # maps model points into the scene


@pytest.fixture(scope="module")
def problem():
    """Two keypoint sets of an 8 x 2 m strip seen twice (2 cm noise); 40 right
    correspondences among 3000 wrong ones (FPFH's: most are wrong)."""
    rng = np.random.default_rng(5)
    model = np.column_stack([rng.uniform(-4, 4, 400), rng.uniform(-1, 1, 400), rng.normal(0, 0.2, 400)])
    scene = model @ T_TRUE[:3, :3].T + T_TRUE[:3, 3] + rng.normal(0, 0.02, model.shape)
    right = rng.choice(400, 40, replace=False)
    wrong = rng.integers(0, 400, (3000, 2))
    wrong = wrong[wrong[:, 0] != wrong[:, 1]]
    corr = np.vstack([np.column_stack([right, right]), wrong])
    is_right = np.arange(len(corr)) < len(right)
    return scene, model, corr, is_right


def _best(clusters: list[np.ndarray], is_right: np.ndarray) -> int:
    return max((int(is_right[c].sum()) for c in clusters), default=0)


def test_yaw_sweep_clusters_the_right_correspondences(problem):
    scene, model, corr, is_right = problem
    clusters = yaw_sweep(scene, model, corr, 0.3, math.radians(2.0), 5, 8)
    assert clusters and _best(clusters, is_right) >= 38
    first = clusters[0]  # the largest peak is the right one: a quarter of it right against 1.3 % of all
    assert is_right[first].sum() >= 38 and is_right[first].mean() > 10 * is_right.mean()


def test_yaw_sweep_votes_only_inside_its_window(problem):
    scene, model, corr, is_right = problem
    inside = yaw_sweep(scene, model, corr, 0.3, math.radians(2.0), 5, 8, (TRUE_YAW + math.radians(3.0), math.radians(6.0)))
    assert _best(inside, is_right) >= 38
    outside = yaw_sweep(scene, model, corr, 0.3, math.radians(2.0), 5, 8, (TRUE_YAW + math.radians(90.0), math.radians(10.0)))
    assert _best(outside, is_right) <= 5


def test_yaw_sweep_votes_only_for_translations_inside_its_window(problem):
    """A repeated structure 2 m along (250 correspondences that agree on a wrong translation at
    the true yaw) outvotes the 40 right ones and the wrong ones' background, which peaks at
    the true translation too; inside a window around the true translation only the right
    ones and that background remain to vote."""
    scene, model, corr, is_right = problem
    rng = np.random.default_rng(7)
    decoy = rng.choice(len(model), 250, replace=False)
    T_decoy = se3(T_TRUE[:3, :3], T_TRUE[:3, 3] + [2.0, 0.5, 0.0])
    scene = np.vstack([scene, model[decoy] @ T_decoy[:3, :3].T + T_decoy[:3, 3] + rng.normal(0, 0.02, (250, 3))])
    corr = np.vstack([corr, np.column_stack([len(model) + np.arange(250), decoy])])
    is_right = np.concatenate([is_right, np.zeros(250, bool)])
    (largest,) = yaw_sweep(scene, model, corr, 0.3, math.radians(2.0), 5, 1)
    assert is_right[largest].sum() <= 5 and len(largest) >= 250
    window = (T_TRUE[:3, 3] + [0.3, -0.2, 0.0], np.array([0.9, 0.9, 0.5]))
    (inside,) = yaw_sweep(scene, model, corr, 0.3, math.radians(2.0), 5, 1, None, window)
    assert is_right[inside].sum() >= 38 and is_right[inside].mean() > 10 * is_right.mean()


def test_hough3d_clusters_them_only_with_frames_that_agree(problem):
    """With each scene frame the model frame turned by the true rotation, Hough3D groups the
    right correspondences; with the frames 45 deg apart (random axes) their votes scatter."""
    scene, model, corr, is_right = problem
    rng = np.random.default_rng(6)
    model_frames = so3_exp_batch(rng.normal(0, 1, (len(model), 3)))  # rows x, y, z
    scene_frames = model_frames @ T_TRUE[:3, :3].T
    exact = hough3d(scene, scene_frames, model, model_frames, corr, 0.3, 5, 8)
    assert _best(exact, is_right) >= 38
    axes = rng.normal(0, 1, (len(scene), 3))
    turn = so3_exp_batch(math.radians(45.0) * axes / np.linalg.norm(axes, axis=1, keepdims=True))
    apart = hough3d(scene, np.einsum("nij,njk->nik", scene_frames, turn), model, model_frames, corr, 0.3, 5, 8)
    assert _best(apart, is_right) < 20
