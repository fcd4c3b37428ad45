"""Rover guidance: heading/speed law towards a waypoint and all-wheel-steering kinematics.

The LRU steers and drives each wheel individually (thesis 7.1). A body twist
(forward speed ``v``, yaw rate ``w``) is turned into one steering angle and one wheel
speed per wheel so that every wheel rolls along the velocity of its contact point
(instantaneous centre of rotation on the body's y axis, "double Ackermann"; ``v = 0``
gives a point turn). Steering angles are kept within +-90 deg by reversing the wheel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from slam.lie import wrap_angle


@dataclass(frozen=True)
class DriveGains:
    heading_gain: float = 1.5  # yaw rate per rad of heading error (1/s)
    max_yaw_rate: float = 0.6  # rad/s
    turn_in_place_rad: float = math.radians(60)  # forward speed falls to 0 at this heading error
    approach_gain: float = 0.8  # speed per metre of remaining distance near the goal (1/s)
    min_approach_speed: float = 0.08  # m/s


def drive_command(
    xy, yaw: float, goal, speed: float, gains: DriveGains = DriveGains()
) -> tuple[float, float]:
    """Forward speed and yaw rate that turn towards ``goal`` and drive there."""
    dx, dy = float(goal[0]) - float(xy[0]), float(goal[1]) - float(xy[1])
    dist = math.hypot(dx, dy)
    err = wrap_angle(math.atan2(dy, dx) - yaw)
    w = max(-gains.max_yaw_rate, min(gains.max_yaw_rate, gains.heading_gain * err))
    v = speed * max(0.0, 1.0 - abs(err) / gains.turn_in_place_rad)
    v = min(v, max(gains.min_approach_speed, gains.approach_gain * dist))
    return v, w


def wheel_commands(
    v: float,
    w: float,
    wheel_xy: Sequence[tuple[float, float]],
    radius: float,
    previous_steer: Sequence[float],
    max_steer: float = math.pi / 2,
) -> tuple[list[float], list[float]]:
    """Steering angles (rad) and wheel angular speeds (rad/s) for a body twist.

    ``wheel_xy`` are the steering axes in the body frame. A wheel whose commanded
    contact speed is ~0 keeps its previous steering angle. (Plain Python: for four
    wheels it is several times faster than numpy.)
    """
    steers, speeds = [], []
    for (x, y), prev in zip(wheel_xy, previous_steer, strict=True):
        ux, uy = v - w * y, w * x
        speed = math.hypot(ux, uy)
        if speed < 1e-4:
            steers.append(float(prev))
            speeds.append(0.0)
            continue
        steer = math.atan2(uy, ux)
        if abs(steer) > max_steer:
            steer -= math.copysign(math.pi, steer)
            speed = -speed
        steers.append(steer)
        speeds.append(speed / radius)
    return steers, speeds
