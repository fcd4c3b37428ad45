"""Small SO(3) / SE(3) helpers for the on-board estimators.

Pure numpy (and scipy's ``Rotation`` for the logarithm). Rotation matrices map body
coordinates into the parent frame (``x_parent = R @ x_body``). Euler angles are ZYX
(yaw about z, then pitch about the new y, then roll about the new x):
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, the roll/pitch/yaw of a gravity-aligned frame
with z up.

``so3_exp`` is written with plain floats because the filter calls it once per IMU
sample; everything else is called at update rate.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def skew(v) -> np.ndarray:
    """The cross-product matrix ``[v]x`` with ``skew(a) @ b == np.cross(a, b)``."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi) -> np.ndarray:
    """Rotation matrix of the rotation vector ``phi`` (Rodrigues' formula)."""
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    t2 = x * x + y * y + z * z
    if t2 < 1e-16:
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    return np.array(
        [
            [1.0 - b * (y * y + z * z), bxy - a * z, bxz + a * y],
            [bxy + a * z, 1.0 - b * (x * x + z * z), byz - a * x],
            [bxz - a * y, byz + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def so3_exp_batch(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(n, 3, 3)`` of ``n`` rotation vectors ``(n, 3)``."""
    phi = np.asarray(phi, dtype=float)
    t2 = np.einsum("ij,ij->i", phi, phi)
    small = t2 < 1e-16
    t = np.sqrt(t2)
    safe_t, safe_t2 = np.where(small, 1.0, t), np.where(small, 1.0, t2)
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(t) / safe_t)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(t)) / safe_t2)
    K = np.zeros((len(phi), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of the rotation matrix ``R`` (inverse of :func:`so3_exp`, angle in
    [0, pi]); plain floats, scipy's ``Rotation`` within 1e-3 rad of pi."""
    wx, wy, wz = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]  # 2 sin(t) k
    s = 0.5 * math.sqrt(wx * wx + wy * wy + wz * wz)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    t = math.atan2(s, c)
    if t > math.pi - 1e-3:
        return Rotation.from_matrix(R).as_rotvec()
    k = 0.5 if s < 1e-12 else 0.5 * t / s
    return np.array([k * wx, k * wy, k * wz])


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` of ``R = Rz(yaw) Ry(pitch) Rx(roll)``; pitch in [-pi/2, pi/2]."""
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2]))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def euler_zyx_jacobian(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``M`` with ``dtheta = M @ [d_roll, d_pitch, d_yaw]`` for the left (parent-frame)
    perturbation ``R_true = Exp(dtheta) @ R``: the columns are the parent-frame axes of
    the three Euler rotations, ``[Rz Ry e_x, Rz e_y, e_z]``."""
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])


def euler_zyx_jacobian_inv(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Inverse of :func:`euler_zyx_jacobian`: ``[d_roll, d_pitch, d_yaw] = M^-1 @ dtheta``
    (singular at pitch = +-90 deg)."""
    cp, tp = math.cos(pitch), math.tan(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy / cp, sy / cp, 0.0], [-sy, cy, 0.0], [cy * tp, sy * tp, 1.0]])


def se3(R: np.ndarray, p) -> np.ndarray:
    """4x4 homogeneous transform from a rotation matrix and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti
