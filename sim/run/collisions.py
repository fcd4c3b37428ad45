"""Collisions of the robots with what they should have avoided, from MuJoCo's contacts.

A collision is a contact between a robot's geometry other than what touches the ground
by design (each preset's ``ground_contact_geoms``: the rover's wheels, the hexacopter's
skids) and a rock or the lander, or any contact between two robots (a collision of
both). The ground does not count, and nor do wheels on rocks: driving over a small rock
is what wheels are for, and the body only reaches a rock taller than the ground
clearance (a rock too tall to climb stops a rover by its tilt guard, which ends as a
stuck waypoint, sim/robots/lru.py). One collision is a run of contacts with the same
thing, sampled at the ground-truth rate; contacts again after ``GAP_S`` without any are
a new one.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import mujoco
import numpy as np

from sim.robots.base import Robot

GAP_S = 1.0


@dataclass(frozen=True)
class Collision:
    t: float  # first contact
    robot: str
    other: str  # "rock_<i>", "lander" or a robot's name


class CollisionMonitor:
    """Sample the contacts (:meth:`sample`) and keep the collisions (:attr:`events`)."""

    def __init__(self, model: mujoco.MjModel, robots: Iterable[Robot]):
        robots = list(robots)
        n = model.ngeom
        self._names: list[str] = [r.name for r in robots]
        self._robot = np.full(n, -1)  # index of the robot the geom belongs to
        self._body = np.full(n, -1)  # the same, for geometry that must not touch obstacles
        self._thing = np.full(n, -1)  # index into self._names of a rock or the lander
        prefixes = [f"{r.name}/" for r in robots]
        exempt = {f"{r.name}/{g}" for r in robots for g in r.ground_contact_geoms}
        for g in range(n):
            name = model.geom(g).name
            body = model.body(model.geom_bodyid[g]).name
            owner = next((k for k, p in enumerate(prefixes) if body.startswith(p) or name.startswith(p)), None)
            if owner is not None:
                self._robot[g] = owner
                if name not in exempt:
                    self._body[g] = owner
                continue
            local = name.rsplit("/", 1)[-1]
            if local.startswith("rock_"):
                self._thing[g] = self._index(local)
            elif local.startswith("lander") or body.rsplit("/", 1)[-1] == "lander":
                self._thing[g] = self._index("lander")
        self._last: dict[tuple[int, int], float] = {}
        self.events: list[Collision] = []

    def _index(self, name: str) -> int:
        if name not in self._names:
            self._names.append(name)
        return self._names.index(name)

    def sample(self, t: float, data: mujoco.MjData) -> None:
        """Look at the contacts of the current physics state: a robot's body on a rock or
        the lander, and any contact between two robots (a collision for both)."""
        n = data.ncon
        if n == 0:
            return
        g1, g2 = data.contact.geom1[:n], data.contact.geom2[:n]
        pairs = set()
        for a, b in ((g1, g2), (g2, g1)):
            robot, other = self._robot[a], self._robot[b]
            hit = (robot >= 0) & (other >= 0) & (robot != other)
            pairs.update(zip(robot[hit].tolist(), other[hit].tolist(), strict=True))
            body, thing = self._body[a], self._thing[b]
            hit = (body >= 0) & (thing >= 0)
            pairs.update(zip(body[hit].tolist(), thing[hit].tolist(), strict=True))
        for key in sorted(pairs):
            last = self._last.get(key)
            if last is None or t - last > GAP_S:
                self.events.append(Collision(t, self._names[key[0]], self._names[key[1]]))
            self._last[key] = t

    def of(self, robot: str) -> list[Collision]:
        return [e for e in self.events if e.robot == robot]
