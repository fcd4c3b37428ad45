"""Injected failures: the scenario's ``faults`` section (:class:`sim.scenario.FaultEntry` and its types) at run time.

Each entry is typed (``type:``) and hits some robots (default all) within a time window. Measurement faults
(thesis 4.2.3: "overconfident, erroneous loop closure constraints can corrupt the entire graph optimization
result") replace a share ``rate`` of one robot's loop-closure measurements by wrong ones; the robot's
:class:`slam.agent.Agent` asks its :class:`MeasurementFaultInjector` (the agent's
:class:`slam.agent.MeasurementFaults`) about each:

- ``wrong_detection``: a robot detection or landmark observation (thesis 6.2.1) becomes the measured transform
  turned by ``rotation_deg`` about a uniformly random axis and moved by ``translation_m`` in a uniformly random
  direction (a misread tag, a mirrored PnP solution), before the robot uses or sends it;
- ``wrong_match``: a submap match attempt (thesis 6.1), whatever the matcher found, becomes a loop closure at
  the graph's prediction of the pair (the prior of the attempt) turned by ``rotation_deg`` about the vertical
  and moved by ``translation_m`` in a random horizontal direction (what a gravity-aligned 4D match can be wrong
  by), with the confident covariance ``sigma_m``, ``sigma_deg`` of an accepted match.

Every draw comes from the entry's own stream ``rng("faults", <entry index>, <type>, <robot>)``
(:mod:`sim.seeding`): a fault changes no other random number of the run, so ``rate: 0`` gives the same run
as no ``faults`` section. Every injected measurement is recorded (:class:`FaultEvent`); ``metrics.json``
reports per robot ``faults.injected`` (counts per type) and ``faults.events``, which tell the injected wrong
closures from real ones (the robot's records mark them too: ``DetectionRecord.injected``, match reason
``injected``).

Condition faults (:class:`ConditionFaults`) make part of a robot fail for their window (``dies``: for good);
the run (sim/run/runner.py) asks about them where the failing part works:

- ``dies``: the robot's motors stop (:meth:`sim.robots.base.Robot.fail`; a flying hexacopter falls), its
  sensors stop, its lane halts (:meth:`sim.run.lanes.Lane.halt`) and its radio fails for good; the team keeps
  whatever it received from it;
- ``camera_dark``: the rendered images of the dark rigs are black before image formation (the sensor's noise
  stays, sim/world/imaging.py);
- ``imu_stuck``: the IMU repeats the sample before the window; ``imu_saturation``: each axis clips;
- ``encoder_failure``: one wheel's encoder reads zero speed, which the wheel odometry gets (its encoder check, sim/world/sensors.py, may outvote it);
- ``radio_silent``: every link to and from the robot is down (:meth:`comms.Network.radio_fault`);
- ``compute_slowdown``: its lane's compute times are multiplied by ``factor``.

``metrics.json`` ``robots.<name>.faults.timeline`` lists the condition faults that began before the run
ended, each with its window, and ``died_s`` when the robot died.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from sim.robots import PRESETS
from sim.scenario import FaultEntry, ImuSaturationFault, MeasurementFault, Scenario
from sim.seeding import RandomStreams
from slam.lie import rot_z, se3, so3_exp
from slam.matcher import SubmapKey

if TYPE_CHECKING:
    from sim.robots.base import WheelState
    from sim.run.onboard import OnboardStack

#: Measurement fault types, in the order ``faults.injected`` lists them.
MEASUREMENT_FAULTS = ("wrong_detection", "wrong_match")
#: Condition fault types: a part of the robot fails for a window (``dies``: for good).
CONDITION_FAULTS = ("dies", "camera_dark", "imu_stuck", "imu_saturation", "encoder_failure", "radio_silent", "compute_slowdown")


@dataclass(frozen=True)
class FaultEvent:
    """One injected wrong measurement."""

    t: float  # the measurement's time (a detection's capture, a match attempt's end)
    type: str  # a :data:`MEASUREMENT_FAULTS` type
    entry: int  # its index in the scenario's ``faults``
    what: str  # the detection's target (a robot, ``landmark:<id>``) or the pair ``robot:submap -> robot:submap``


class MeasurementFaultInjector:
    """One robot's measurement faults (module docstring); implements :class:`slam.agent.MeasurementFaults`."""

    def __init__(self, robot: str, entries: list[tuple[int, MeasurementFault]], streams: RandomStreams):
        self.robot = robot
        self._entries = [(i, entry, streams.rng("faults", str(i), entry.type, robot)) for i, entry in entries]
        self.events: list[FaultEvent] = []

    def _fires(self, kind: str, t: float) -> tuple[int, MeasurementFault, np.random.Generator] | None:
        """The first entry of ``kind`` active at ``t`` whose draw hits (one draw per active entry, in order)."""
        for i, entry, rng in self._entries:
            if entry.type == kind and entry.hits(self.robot, t) and rng.random() < entry.rate:
                return i, entry, rng
        return None

    def detection(self, t: float, target: str, T_detector_target: np.ndarray) -> np.ndarray | None:
        fired = self._fires("wrong_detection", t)
        if fired is None:
            return None
        i, entry, rng = fired
        axis, direction = _unit(rng, 3), _unit(rng, 3)
        error = se3(so3_exp(axis * math.radians(entry.rotation_deg)), direction * entry.translation_m)
        self.events.append(FaultEvent(t, entry.type, i, target))
        return T_detector_target @ error

    def match(self, t: float, a: SubmapKey, b: SubmapKey, predicted_T_a_b: np.ndarray, matched: bool) -> tuple[np.ndarray, np.ndarray] | None:
        fired = self._fires("wrong_match", t)
        if fired is None:
            return None
        i, entry, rng = fired
        sign, direction = rng.choice([-1.0, 1.0]), np.append(_unit(rng, 2), 0.0)
        error = se3(rot_z(sign * math.radians(entry.rotation_deg)), direction * entry.translation_m)
        cov = np.diag([math.radians(entry.sigma_deg) ** 2] * 3 + [entry.sigma_m**2] * 3)
        self.events.append(FaultEvent(t, entry.type, i, f"{a[0]}:{a[1]} -> {b[0]}:{b[1]}"))
        return predicted_T_a_b @ error, cov

    def counts(self) -> dict[str, int]:
        return {kind: sum(e.type == kind for e in self.events) for kind in MEASUREMENT_FAULTS}


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=n)
    return v / np.linalg.norm(v)


def measurement_faults(scenario: Scenario, robot: str, streams: RandomStreams) -> MeasurementFaultInjector | None:
    """The robot's measurement faults, None when no entry can hit it."""
    entries = [(i, f) for i, f in enumerate(scenario.faults) if f.type in MEASUREMENT_FAULTS and (f.robots is None or robot in f.robots)]
    return MeasurementFaultInjector(robot, entries, streams) if entries else None


class ConditionFaults:
    """One robot's condition faults (module docstring): which one is active when, and what the run made of them."""

    def __init__(self, robot: str, entries: list[tuple[int, FaultEntry]]):
        self.robot = robot
        self.entries = entries
        self.died_s: float | None = None
        self._last_imu: tuple[np.ndarray, np.ndarray] | None = None

    def active(self, kind: str, t: float) -> FaultEntry | None:
        """The first entry of ``kind`` active at ``t``."""
        return next((e for _, e in self.entries if e.type == kind and e.hits(self.robot, t)), None)

    def dark(self, rig: str, t: float) -> bool:
        """Whether the stereo rig ``rig`` is dark at ``t``."""
        return any(e.type == "camera_dark" and e.hits(self.robot, t) and (e.rigs is None or rig in e.rigs) for _, e in self.entries)

    def imu(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The IMU sample as the failing IMU gives it."""
        if self.active("imu_stuck", t) is not None and self._last_imu is not None:
            return self._last_imu
        saturation = self.active("imu_saturation", t)
        if isinstance(saturation, ImuSaturationFault):
            limit = math.radians(saturation.gyro_limit_dps)
            accel = np.clip(accel, -saturation.accel_limit_mps2, saturation.accel_limit_mps2)
            gyro = np.clip(gyro, -limit, limit)
        self._last_imu = (accel, gyro)
        return accel, gyro

    def wheels(self, t: float, names: tuple[str, ...], states: list[WheelState]) -> list[WheelState]:
        """The wheel states as the encoders read them: a failed encoder reads zero speed."""
        failed = {e.wheel for _, e in self.entries if e.type == "encoder_failure" and e.hits(self.robot, t)}
        if not failed:
            return states
        return [replace(w, angular_speed=0.0) if name in failed else w for name, w in zip(names, states)]

    def timeline(self, end_s: float) -> list[dict[str, Any]]:
        """The condition faults that began by ``end_s``: type, entry index and window (``end_s`` None: to the end)."""
        return [
            {"type": e.type, "entry": i, "start_s": e.start_s, "end_s": e.end_s if e.end_s is not None and e.end_s < end_s else None}
            for i, e in self.entries
            if e.start_s <= end_s
        ]


def condition_faults(scenario: Scenario, robot: str) -> ConditionFaults | None:
    """The robot's condition faults, None when no entry can hit it (an ``encoder_failure`` hits only robots with
    that wheel: the scenario checks that it hits some)."""
    preset = PRESETS[scenario.robot(robot).preset]
    entries = [
        (i, f)
        for i, f in enumerate(scenario.faults)
        if f.type in CONDITION_FAULTS and (f.robots is None or robot in f.robots) and (f.type != "encoder_failure" or f.wheel in preset.wheel_names)
    ]
    return ConditionFaults(robot, entries) if entries else None


def fault_metrics(onboard: OnboardStack | None, conditions: ConditionFaults | None = None, end_s: float = math.inf) -> dict[str, Any]:
    """``metrics.json`` ``robots.<name>.faults``: injected wrong measurements per type and each of them; the
    condition faults' timeline up to ``end_s`` and when the robot died (None: it did not)."""
    injector = onboard.faults if onboard is not None else None
    out: dict[str, Any] = {"injected": dict.fromkeys(MEASUREMENT_FAULTS, 0), "events": []}
    if injector is not None:
        out = {"injected": injector.counts(), "events": [asdict(e) for e in injector.events]}
    out["timeline"] = conditions.timeline(end_s) if conditions is not None else []
    out["died_s"] = conditions.died_s if conditions is not None else None
    return out
