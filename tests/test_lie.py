"""slam.lie: the rigid-body helpers beyond the filter's (those are checked in
test_filter.py): adjoint, pose error, yaw and roll/pitch extraction, angle wrapping,
quaternions and the vee map, each against an independent definition."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from slam.lie import (
    adjoint,
    apply_planar,
    pose_error,
    quat_to_rot,
    roll_pitch,
    rot_z,
    rot_zyx,
    rotation_angle,
    se3,
    se3_inv,
    skew,
    so3_exp,
    vee,
    wrap_angle,
    yaw_of,
    yaw_quat,
)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exp of a twist [rotation, translation] as the matrix exponential of its 4x4 hat."""
    X = np.zeros((4, 4))
    X[:3, :3], X[:3, 3] = skew(xi[:3]), xi[3:]
    return expm(X)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return se3(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3))


def test_adjoint_moves_a_perturbation_across_the_transform():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T, xi = random_pose(rng), rng.normal(0, 0.5, 6)
        np.testing.assert_allclose(T @ se3_exp(xi) @ se3_inv(T), se3_exp(adjoint(T) @ xi), atol=1e-10)


def test_adjoint_is_a_group_homomorphism():
    rng = np.random.default_rng(1)
    A, B = random_pose(rng), random_pose(rng)
    np.testing.assert_allclose(adjoint(A @ B), adjoint(A) @ adjoint(B), atol=1e-12)
    np.testing.assert_allclose(adjoint(se3_inv(A)), np.linalg.inv(adjoint(A)), atol=1e-12)
    np.testing.assert_array_equal(adjoint(np.eye(4)), np.eye(6))


def test_pose_error_inverts_a_right_perturbation():
    rng = np.random.default_rng(2)
    for _ in range(20):
        T, xi = random_pose(rng), rng.normal(0, 0.3, 6)
        xi[3:] *= 1e-4  # first order in the translation: the rotation is exact, the translation to O(|w||v|)
        T_true = T @ se3(so3_exp(xi[:3]), xi[3:])
        np.testing.assert_allclose(pose_error(T, T_true), xi, atol=1e-12)
    np.testing.assert_array_equal(pose_error(T, T), np.zeros(6))


def test_yaw_of_inverts_rot_z_and_ignores_roll_and_pitch():
    for yaw in np.linspace(-math.pi + 1e-9, math.pi, 37):
        assert yaw_of(rot_z(yaw)) == pytest.approx(yaw, abs=1e-12)
        assert yaw_of(rot_zyx(0.3, -0.4, yaw)) == pytest.approx(yaw, abs=1e-12)
    assert yaw_of(np.eye(3)) == 0.0


def test_roll_pitch_inverts_rot_zyx():
    rng = np.random.default_rng(3)
    for roll, pitch, yaw in zip(rng.uniform(-3, 3, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-3, 3, 50)):
        np.testing.assert_allclose(roll_pitch(rot_zyx(roll, pitch, yaw)), (roll, pitch), atol=1e-9)
    assert roll_pitch(rot_z(1.0)) == (0.0, -0.0)


def test_wrap_angle_range_and_identity_modulo_two_pi():
    rng = np.random.default_rng(4)
    a = rng.uniform(-50, 50, 1000)
    w = wrap_angle(a)
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    k = (a - w) / (2 * math.pi)
    np.testing.assert_allclose(k, np.round(k), atol=1e-12)  # a and wrap_angle(a) differ by whole turns
    inside = np.linspace(-3.1, 3.1, 11)
    np.testing.assert_allclose(wrap_angle(inside), inside, atol=1e-15)
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)  # the range is half open
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert isinstance(wrap_angle(0.5), float)
    np.testing.assert_array_equal(wrap_angle(a), [wrap_angle(float(x)) for x in a])  # arrays as floats


def test_quaternions_match_the_rotations():
    for yaw in (-2.5, 0.0, 0.7, math.pi):
        np.testing.assert_allclose(quat_to_rot(yaw_quat(yaw)), rot_z(yaw), atol=1e-15)
    rng = np.random.default_rng(5)
    R = Rotation.random(random_state=rng)
    x, y, z, w = R.as_quat()
    np.testing.assert_allclose(quat_to_rot([w, x, y, z]), R.as_matrix(), atol=1e-15)
    np.testing.assert_allclose(quat_to_rot([2 * w, 2 * x, 2 * y, 2 * z]), R.as_matrix(), atol=1e-15)  # normalised


def test_vee_inverts_skew():
    v = np.array([0.3, -1.2, 2.5])
    np.testing.assert_array_equal(vee(skew(v)), v)
    np.testing.assert_allclose(skew(v) @ [1.0, 2.0, 3.0], np.cross(v, [1.0, 2.0, 3.0]), atol=1e-15)
    R = rot_zyx(0.1, 0.2, 0.3)
    w = np.array([0.3, -0.6, 0.15])  # the antisymmetric part of Exp(w) is sin|w| / |w| [w]x
    D = so3_exp(w)
    t = np.linalg.norm(w)
    np.testing.assert_allclose(vee(0.5 * (D - D.T)), math.sin(t) / t * w, atol=1e-15)
    np.testing.assert_allclose(vee(R.T @ R), np.zeros(3), atol=1e-15)


def test_rotation_angle_is_the_angle_of_the_axis_angle_vector():
    rng = np.random.default_rng(5)
    for _ in range(50):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, math.pi - 1e-6)
        assert rotation_angle(Rotation.from_rotvec(angle * axis).as_matrix()) == pytest.approx(angle, abs=1e-9)
    assert rotation_angle(np.eye(3)) == 0.0


def test_apply_planar_is_the_full_transform_in_x_and_y_for_a_gravity_aligned_pose():
    rng = np.random.default_rng(4)
    T = se3(rot_z(0.7), [1.0, -2.0, 0.5])
    points = rng.normal(size=(20, 3))
    full = points @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(apply_planar(T, points), full[:, :2], atol=1e-12)
    np.testing.assert_allclose(apply_planar(T, points[0, :2]), full[0, :2], atol=1e-12)
    np.testing.assert_allclose(apply_planar(se3_inv(T), apply_planar(T, points[:, :2])), points[:, :2], atol=1e-12)
