"""SO(3) / SE(3) helpers: the one home of the project's rigid-body geometry.

Pure numpy (scipy's ``Rotation`` for the logarithm and quaternions, numba for the
compiled copies below). Rotation matrices map body coordinates into the parent frame
(``x_parent = R @ x_body``). Euler angles are ZYX (yaw about z, then pitch about the new
y, then roll about the new x): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, the
roll/pitch/yaw of a gravity-aligned frame with z up (thesis 4.1.2). 6D tangent vectors
are ordered [rotation, translation] and perturb on the right, ``T_true = T Exp(xi)``.
Quaternions are (w, x, y, z), MuJoCo's order.

``so3_exp`` is written with plain floats because the filter calls it once per IMU
sample; everything else is called at update rate. ``so3_exp_compiled`` and
``skew_compiled`` are the same functions compiled by numba, for numba kernels
(slam/strapdown.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial.transform import Rotation


def skew(v) -> np.ndarray:
    """The cross-product matrix ``[v]x`` with ``skew(a) @ b == np.cross(a, b)``."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def vee(S: np.ndarray) -> np.ndarray:
    """The vector of a cross-product matrix, inverse of :func:`skew`:
    ``vee(skew(v)) == v``. Reads the lower-triangle entries ``(S[2,1], S[0,2], S[1,0])``
    and does not check that ``S`` is skew-symmetric."""
    return np.array([S[2, 1], S[0, 2], S[1, 0]])


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


so3_exp_compiled = numba.njit(cache=True, nogil=True)(so3_exp)
skew_compiled = numba.njit(cache=True, nogil=True)(skew)


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


def rotation_angle(R: np.ndarray) -> float:
    """The angle of the rotation ``R`` in [0, pi]: the norm of :func:`so3_log`."""
    return float(np.linalg.norm(so3_log(R)))


def rot_z(yaw: float) -> np.ndarray:
    """Rotation by ``yaw`` about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(R: np.ndarray) -> float:
    """Yaw of ``R`` in the ZYX convention, in [-pi, pi]; ``yaw_of(rot_z(y)) == y`` for y
    in (-pi, pi]. The z rotation that makes a gravity-aligned frame (thesis 4.1.2)."""
    return math.atan2(R[1, 0], R[0, 0])


def wrap_angle(a):
    """Angle ``a`` (a float or an array) wrapped into [-pi, pi), equal to ``a`` modulo 2 pi."""
    return (a + math.pi) % (2 * math.pi) - math.pi


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


def roll_pitch(R: np.ndarray) -> tuple[float, float]:
    """Roll and pitch (ZYX Euler) of ``R``, the angles a gravity-aligned frame drops
    (thesis 4.1.2). Pitch is ``-asin(R[2,0])``, which differs from :func:`euler_zyx`'s
    ``atan2`` form only in the last bits."""
    return math.atan2(R[2, 1], R[2, 2]), -math.asin(float(np.clip(R[2, 0], -1.0, 1.0)))


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


def gravity_aligned(T: np.ndarray) -> np.ndarray:
    """The frame with ``T``'s position and yaw, roll and pitch dropped (thesis 4.1.2)."""
    return se3(rot_z(yaw_of(T[:3, :3])), T[:3, 3])


def apply_planar(T: np.ndarray, xy) -> np.ndarray:
    """The horizontal part of a gravity-aligned pose ``T`` (a rotation about z only) applied
    to ground points ``xy``, (2,) or (n, 2): what a 2D map or planner in one such frame
    needs of another (heights play no part in x and y)."""
    xy = np.asarray(xy, float)
    return xy[..., :2] @ T[:2, :2].T + T[:2, 3]


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of ``T = (R, p)`` for tangent order [rotation, translation]:
    ``T Exp(xi) T^-1 = Exp(Ad_T xi)`` with ``Ad_T = [[R, 0], [[p]x R, R]]``."""
    R, p = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = Ad[3:, 3:] = R
    Ad[3:, :3] = skew(p) @ R
    return Ad


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """6D error ``xi`` with ``T_true = T_est Exp(xi)`` to first order, [rotation (rad),
    translation (m)], both in the estimated frame: ``[Log(R_est^T R_true),
    R_est^T (p_true - p_est)]``."""
    R, t = T_est[:3, :3], T_est[:3, 3]
    return np.concatenate([so3_log(R.T @ T_true[:3, :3]), R.T @ (T_true[:3, 3] - t)])


def quat_to_rot(q_wxyz) -> np.ndarray:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    qw, qx, qy, qz = q_wxyz
    return Rotation.from_quat([qx, qy, qz, qw]).as_matrix()


def yaw_quat(yaw: float) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` of :func:`rot_z` ``(yaw)``."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
