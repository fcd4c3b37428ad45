"""The local estimator's verdict on its own estimate (thesis 4.1: the filter must say when
its visual odometry has been lost): ``ok``, ``degraded`` with a reason, or ``lost``.
Used by :class:`slam.local_estimator.LocalEstimator`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class HealthException(ValueError):
    """Health parameters out of range."""


class HealthState(StrEnum):
    """The estimator's own verdict on its estimate (members equal their strings)."""

    OK = "ok"
    DEGRADED = "degraded"
    LOST = "lost"


@dataclass(frozen=True)
class Health:
    """``state`` since time ``since`` (when the state was entered), with a ``reason``:
    ``"vo lost"`` (VO failures, or no VO results at all), ``"vo rejected"`` (VO deltas
    rejected), ``"no vo"`` (an estimator without VO), ``"uncertain"`` (the covariance bound
    alone), ``"imu stuck"`` (its samples bridged by a motion model); empty when ok.
    ``detail``: the last VO failure or rejection reason, which bound was exceeded, or the
    stuck IMU channels."""

    state: HealthState
    reason: str = ""
    since: float = 0.0
    detail: str = ""


@dataclass(frozen=True)
class HealthParams:
    """When :class:`LocalEstimator` calls its estimate degraded or lost.

    - ``vo_timeout_s``: degraded when no VO delta has been applied (capture time) for
      longer than this while the robot is not resting with zero-velocity updates: 15
      frames at the simulator's 5 Hz camera, 12x the 250 ms VO latency of thesis 4.1.1.
    - ``lost_after_s``: lost after this long degraded. With the IMU alone, the position
      error grows with ``t^2``: 30 s make about 1 m from a 0.2 mg accelerometer bias (the
      ADIS16407's in-run stability, sim/world/sensors.py) and 4 m from a 1 mrad tilt error.
    - ``max_position_std_m``: lost when the largest position std in the current local
      frame exceeds this: five times the upper submap threshold of thesis 5.1.3 (0.2 m);
      reached only without frame switches, which reset it (thesis 4.1.2).
    - ``max_velocity_std_mps``: lost when the largest velocity std exceeds this (not reset
      by frame switches): the routes' default speed (sim/scenario.py), beyond which the
      estimate cannot tell driving from standing. None disables either bound.
    """

    vo_timeout_s: float = 3.0
    lost_after_s: float = 30.0
    max_position_std_m: float | None = 1.0
    max_velocity_std_mps: float | None = 0.3

    def __post_init__(self):
        bad = [f"{k}={getattr(self, k)!r}" for k in ("vo_timeout_s", "lost_after_s") if not getattr(self, k) > 0]
        bad += [f"{k}={getattr(self, k)!r}" for k in ("max_position_std_m", "max_velocity_std_mps")
                if getattr(self, k) is not None and not getattr(self, k) > 0]
        if bad:
            raise HealthException(f"HealthParams must be positive: {', '.join(bad)}")
