"""Cascaded multirotor controller: position PID -> desired acceleration -> thrust
vector and attitude -> attitude PD on SO(3) -> body torques -> rotor thrusts.

The attitude law is the geometric controller of Lee, Leok and McClamroch (2010):
``e_R = 1/2 vee(R_d^T R - R^T R_d)``, ``tau = -K_R e_R - K_w w + w x J w``, with
``K_R = J wn^2`` and ``K_w = J 2 zeta wn`` per axis. Collective thrust is the desired
force projected on the current body z axis. Allocation maps
``[T, tau_x, tau_y, tau_z]`` to the rotors with the pseudo-inverse of the mixer and
clamps each thrust to ``[0, max_thrust]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter

from slam.lie import vee

GRAVITY = 9.81


@dataclass(frozen=True)
class HexGains:
    kp_xy: float = 2.5  # 1/s^2
    kd_xy: float = 2.8  # 1/s
    kp_z: float = 6.0
    kd_z: float = 4.5
    ki_z: float = 1.0
    integral_limit: float = 3.0  # m/s^2 of integral action at most
    max_acc_xy: float = 4.0  # m/s^2
    max_acc_z: float = 6.0
    max_tilt: float = math.radians(35)
    att_wn: float = 14.0  # roll/pitch natural frequency, rad/s
    att_zeta: float = 0.9
    yaw_wn: float = 4.0
    yaw_zeta: float = 1.0


def mixer_matrix(rotor_xy: np.ndarray, spin: np.ndarray, yaw_coeff: float) -> np.ndarray:
    """4 x n map from rotor thrusts to [collective thrust, tau_x, tau_y, tau_z] (body frame).

    ``rotor_xy`` are rotor positions relative to the centre of mass; ``spin`` is +1 or -1
    per rotor, the sign of its yaw reaction torque per newton of thrust (``yaw_coeff``).
    """
    rotor_xy = np.asarray(rotor_xy, float)
    return np.vstack([np.ones(len(rotor_xy)), rotor_xy[:, 1], -rotor_xy[:, 0], yaw_coeff * np.asarray(spin, float)])


def _cross(a, b) -> np.ndarray:
    """3-vector cross product (np.cross is slow for single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else min(x, hi)


class HexacopterController:
    def __init__(
        self,
        mass: float,
        inertia: np.ndarray,
        rotor_xy: np.ndarray,
        spin: np.ndarray,
        yaw_coeff: float,
        max_thrust: float,
        gains: HexGains = HexGains(),
    ):
        self.mass = float(mass)
        self.inertia = np.asarray(inertia, float).reshape(3, 3)
        self.mixer = mixer_matrix(rotor_xy, spin, yaw_coeff)
        self.allocation = np.linalg.pinv(self.mixer)
        self.max_thrust = float(max_thrust)
        self.gains = gains
        wn = np.array([gains.att_wn, gains.att_wn, gains.yaw_wn])
        zeta = np.array([gains.att_zeta, gains.att_zeta, gains.yaw_zeta])
        self._kr = self.inertia @ np.diag(wn**2)
        self._kw = self.inertia @ np.diag(2 * zeta * wn)
        self.integral_z = 0.0

    def reset(self) -> None:
        self.integral_z = 0.0

    def desired_acceleration(self, dt: float, p, v, p_ref, v_ref, a_ff=None) -> np.ndarray:
        g = self.gains
        e_p = np.asarray(p_ref, float) - np.asarray(p, float)
        e_v = np.asarray(v_ref, float) - np.asarray(v, float)
        self.integral_z = _clamp(self.integral_z + g.ki_z * float(e_p[2]) * dt, -g.integral_limit, g.integral_limit)
        acc = np.empty(3)
        acc[:2] = g.kp_xy * e_p[:2] + g.kd_xy * e_v[:2]
        acc[2] = g.kp_z * e_p[2] + g.kd_z * e_v[2] + self.integral_z
        if a_ff is not None:
            acc += np.asarray(a_ff, float)
        horiz = math.hypot(acc[0], acc[1])
        if horiz > g.max_acc_xy:
            acc[:2] *= g.max_acc_xy / horiz
        acc[2] = _clamp(float(acc[2]), -0.8 * GRAVITY, g.max_acc_z)
        return acc

    def attitude_setpoint(self, acc: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """Desired force (world) and rotation for a desired acceleration and yaw."""
        force = self.mass * (acc + np.array([0.0, 0.0, GRAVITY]))
        # limit the tilt of the thrust vector
        horiz = math.hypot(force[0], force[1])
        max_h = force[2] * math.tan(self.gains.max_tilt)
        if horiz > max_h:
            force[:2] *= max_h / horiz
        z_b = force / math.sqrt(force @ force)
        x_c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        y_b = _cross(z_b, x_c)
        y_b /= math.sqrt(y_b @ y_b)
        x_b = _cross(y_b, z_b)
        return force, np.column_stack([x_b, y_b, z_b])

    def torques(self, rot: np.ndarray, omega_body: np.ndarray, rot_des: np.ndarray, yaw_rate_ff: float = 0.0) -> np.ndarray:
        e_r = 0.5 * vee(rot_des.T @ rot - rot.T @ rot_des)
        omega_des = rot.T @ np.array([0.0, 0.0, yaw_rate_ff])
        e_w = omega_body - omega_des
        return -self._kr @ e_r - self._kw @ e_w + _cross(omega_body, self.inertia @ omega_body)

    def allocate(self, thrust: float, torque: np.ndarray) -> np.ndarray:
        f = self.allocation[:, 0] * thrust + self.allocation[:, 1:] @ torque
        return np.minimum(np.maximum(f, 0.0), self.max_thrust)

    def update(
        self,
        dt: float,
        p: np.ndarray,
        v: np.ndarray,
        rot: np.ndarray,
        omega_body: np.ndarray,
        p_ref: np.ndarray,
        v_ref: np.ndarray,
        yaw_ref: float,
        yaw_rate_ff: float = 0.0,
    ) -> np.ndarray:
        """Rotor thrusts (N) for one control tick."""
        acc = self.desired_acceleration(dt, p, v, p_ref, v_ref)
        force, rot_des = self.attitude_setpoint(acc, yaw_ref)
        thrust = float(force @ rot[:, 2])
        return self.allocate(max(thrust, 0.0), self.torques(rot, omega_body, rot_des, yaw_rate_ff))


class SmoothedHeight:
    """Box-filtered heightfield (window ``2 * half_window_m``), bilinear lookup at one point.

    Row i of ``heights`` is at y = -size/2 + i * res, column j at x (``sim.world.terrain``'s
    layout); points off the grid are clamped onto its edge.
    """

    def __init__(self, heights: np.ndarray, size_m: float, half_window_m: float):
        n = heights.shape[0]
        self.res = size_m / (n - 1)
        self.half = size_m / 2
        self.n = n
        k = max(0, round(half_window_m / self.res))
        self.grid = uniform_filter(np.asarray(heights, float), size=2 * k + 1, mode="nearest")

    def __call__(self, x: float, y: float) -> float:
        fx = _clamp((float(x) + self.half) / self.res, 0.0, self.n - 1.000001)
        fy = _clamp((float(y) + self.half) / self.res, 0.0, self.n - 1.000001)
        j, i = int(fx), int(fy)
        u, v = fx - j, fy - i
        g = self.grid
        return float((g[i, j] * (1 - u) + g[i, j + 1] * u) * (1 - v) + (g[i + 1, j] * (1 - u) + g[i + 1, j + 1] * u) * v)
