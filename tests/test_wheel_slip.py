"""slam.local_estimator: wheel odometry whose error is slip (thesis 4.1.1).

A rover cruises at 0.3 m/s with IMU and wheel odometry only (50 Hz, no VO). The wheels'
relative speed error is a first-order Gauss-Markov process of 3 % std and 5 s
correlation time, as sim/world/sensors.py's ``WheelOdometryModel`` varies slip with the
soil. Taken as white noise (``slip_std=0``) the 50 samples a second average it away and
the filter is overconfident (mean NEES of the forward velocity 3-16 per seed, 1 dof);
with the slip term of ``on_wheel_odometry`` it is on the safe side (0.16-0.41: the
equivalent white noise is the error's power at low frequencies, more than it has at
the filter's time scale).
"""

from __future__ import annotations

import math

import numpy as np

from sim.world.sensors import IMU_PRESETS
from tests.test_local_estimator_rest import RATE, cruise, estimator, feed, noisy_imu

SLIP_STD, SLIP_TAU = 0.03, 5.0


def velocity_nees(slip_std: float, seed: int) -> list[float]:
    """NEES of the forward velocity (1 dof), once a second over the last 30 s of the cruise."""
    spec = IMU_PRESETS["adis16407"]
    tr = cruise(40.0, t_acc=2.0, ramp=2.0)
    imu = noisy_imu(tr, spec, np.random.default_rng(seed))
    rng = np.random.default_rng(100 + seed)
    est = estimator(spec)
    a = math.exp(-4 / RATE / SLIP_TAU)  # the error's step over one wheel sample
    slip = [SLIP_STD * rng.standard_normal()]
    out = []

    def each(k, e):
        if k % 4 == 0 and e.initialised:
            slip[0] = a * slip[0] + math.sqrt(1 - a * a) * SLIP_STD * rng.standard_normal()
            e.on_wheel_odometry(tr.t[k], np.array([tr.v[k, 0] * (1 + slip[0]), 0.0, 0.0]), 0.01, 0.01, slip_std=slip_std,
                                slip_correlation_s=SLIP_TAU)
        if tr.t[k] >= 10.0 and k % round(RATE) == 0:
            err = e.filter.velocity()[0] - tr.v[k, 0]
            out.append(err**2 / e.filter.covariance()[3, 3])

    feed(est, tr, imu, each)
    return out


def test_slip_is_in_the_wheel_odometry_covariance():
    modelled = np.concatenate([velocity_nees(SLIP_STD, s) for s in range(4)])
    white = np.concatenate([velocity_nees(0.0, s) for s in range(4)])
    assert 0.1 < modelled.mean() < 1.0, modelled.mean()  # 1 dof: conservative, not blind
    assert white.mean() > 3.0, white.mean()  # overconfident
