"""The local reference filter's step per IMU sample, compiled (thesis 4.1.1, eq. 4.1-4.2).

:func:`strapdown_step` is the arithmetic of ``slam.filter.LocalReferenceFilter``'s
propagation from one IMU sample to the next: the strapdown integration of attitude,
velocity and position over the interval (Simpson's rule on the specific force, the
attitude at the interval's midpoint) and the error covariance's prediction
``P <- Phi P Phi^T + Qd`` with the clones' cross-covariances ``Phi P_xc``. The filter
runs it for every sample, forward and again in every delay-compensation replay (more
than half of the calls on quickstart); as numpy it was some thirty calls on 3x3 to
20x20 arrays per sample, their overhead the cost. Compiled by numba, the same operations
in the same order (``slam/filter.py`` keeps the state, the caching of ``Qd`` and the
re-orthonormalisation of the attitude).
"""

from __future__ import annotations

import numba
import numpy as np

from slam.lie import skew_compiled, so3_exp_compiled


@numba.njit(cache=True, nogil=True)
def strapdown_step(R0, p, v, f0, f1, w0, w1, ba, bw, g, dt, Phi, phi_p_scale, phi_v_scale, k0, nk,
                   P, base, dim, Qd, gyro_scale_q):
    """One IMU interval ``dt`` from the samples ``(f0, w0)`` to ``(f1, w1)``: returns the
    attitude ``R1``, position and velocity at its end; ``P`` (the filter's covariance
    buffer, its first ``dim`` rows and columns in use, the clones from ``base`` on) is
    propagated in place, ``Phi`` (base x base, identity outside the blocks written here)
    is a work buffer. The error state's layout is slam/filter.py's:
    ``[dp, dv, dtheta, db_a, db_w]`` (the core, ``Qd``'s size), then consider parameters,
    of which ``nk`` from column ``k0`` are the accelerometer's z-axis misalignment (the z
    axis senses ``k . f_xy``, entering like the bias's z component);
    ``gyro_scale_q``: the variance rate per squared turn rate added to the attitude
    (unmodelled gyro scale and misalignment; 0: none)."""
    E = so3_exp_compiled((0.5 * dt) * (0.5 * (w0 + w1) - bw))
    Rh = R0 @ E
    R1 = Rh @ E
    fh_local = Rh @ (0.5 * (f0 + f1) - ba)
    a0 = R0 @ (f0 - ba) + g
    ah = fh_local + g
    a1 = R1 @ (f1 - ba) + g
    p1 = p + dt * v + (dt * dt / 6.0) * (a0 + 2.0 * ah)
    v1 = v + (dt / 6.0) * (a0 + 4.0 * ah + a1)

    # error transition (linearised at the interval midpoint): the 6x9 block of Phi
    # from [dtheta, db_a, db_w] to [dp, dv] is W = [A, R dt, A R dt] scaled per column
    A = skew_compiled(fh_local * dt)  # [R f]x dt
    Rdt = Rh * dt
    ARdt = A @ Rdt
    for i in range(3):
        Phi[i, 3 + i] = dt
        for j in range(3):
            for block, Wij in ((0, A[i, j]), (3, Rdt[i, j]), (6, ARdt[i, j])):
                Phi[i, 6 + block + j] = Wij * (dt * phi_p_scale[block + j])
                Phi[3 + i, 6 + block + j] = Wij * phi_v_scale[block + j]
            Phi[6 + i, 12 + j] = -Rdt[i, j]
    for c in range(nk):
        f_c = 0.5 * (f0[c] + f1[c]) - ba[c]
        for i in range(6):
            Phi[i, k0 + c] = Phi[i, 11] * f_c
    P[:base, :base] = Phi @ np.ascontiguousarray(P[:base, :base]) @ Phi.T
    core = Qd.shape[0]
    P[:core, :core] += Qd
    if gyro_scale_q > 0.0:
        rate = 0.5 * (w0 + w1) - bw
        q = gyro_scale_q * (rate[0] * rate[0] + rate[1] * rate[1] + rate[2] * rate[2]) * dt
        for i in range(6, 9):
            P[i, i] += q
    if dim > base:
        X = Phi @ np.ascontiguousarray(P[:base, base:dim])
        P[:base, base:dim] = X
        P[base:dim, :base] = X.T
    return R1, p1, v1
