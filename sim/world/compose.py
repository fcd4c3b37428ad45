"""World composition: terrain + robots in one MJCF (dm_control PyMJCF), compiled once.

Physics settings: Earth gravity for every terrain preset (the robots, their
controllers and IMU models are those of the thesis's Earth analogue tests; the
presets change the ground, not the planet), the ``implicitfast`` integrator (stable
with the stiff velocity-controlled wheels at 1 ms steps), elliptic friction cones.

MuJoCo's ``visual.map.znear``/``zfar`` are fractions of ``statistic.extent``; we set
the extent explicitly to the terrain size and derive them from the robots' camera
``znear_m``/``zfar_m`` so that cameras see the ground a few centimetres away. The
offscreen buffer is made large enough for the largest camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
from dm_control import mjcf

from sim.robots.base import Robot
from sim.scenario import Scenario
from sim.world.terrain import Terrain, add_terrain

GRAVITY = (0.0, 0.0, -9.81)


class WorldError(RuntimeError):
    """The composed world does not compile; the message carries MuJoCo's reason."""


@dataclass
class World:
    root: mjcf.RootElement
    model: mujoco.MjModel
    data: mujoco.MjData
    robots: list[Robot]
    terrain: Terrain
    _control_tick: int = field(default=0, repr=False)

    def robot(self, name: str) -> Robot:
        for r in self.robots:
            if r.name == name:
                return r
        raise KeyError(f"no robot named {name!r}; robots: {[r.name for r in self.robots]}")

    def advance(self, duration_s: float, control_rate_hz: float = 200.0) -> None:
        """Run controllers at ``control_rate_hz`` and physics for ``duration_s``.

        A convenience for tests and tools; the runner drives the same calls from SimPy.
        """
        dt = self.model.opt.timestep
        substeps = max(1, round(1.0 / (control_rate_hz * dt)))
        n_ticks = round(duration_s / (substeps * dt))
        for _ in range(n_ticks):
            for robot in self.robots:
                robot.control(self.data.time, self.terrain)
            mujoco.mj_step(self.model, self.data, nstep=substeps)


def build_world(scenario: Scenario, terrain: Terrain, robots: Sequence[Robot]) -> World:
    """Compose, compile and bind: terrain, then each robot at its start pose."""
    root = mjcf.RootElement(model="marsyard")
    root.option.timestep = scenario.physics.timestep_s
    root.option.gravity = list(GRAVITY)
    root.option.integrator = "implicitfast"
    root.option.cone = "elliptic"
    add_terrain(root, terrain, scenario.realism.light)
    for robot in robots:
        robot.attach(root, terrain)
    configure_visual(root, terrain, robots)
    try:
        model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    except ValueError as exc:
        raise WorldError(f"world of scenario {scenario.name!r} does not compile: {exc}") from exc
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for robot in robots:
        robot.bind(model, data)
    mujoco.mj_forward(model, data)
    return World(root=root, model=model, data=data, robots=list(robots), terrain=terrain)


def configure_visual(root: mjcf.RootElement, terrain: Terrain, robots: Sequence[Robot]) -> None:
    """Extent, near/far planes and offscreen buffer size for the robots' cameras."""
    extent = float(terrain.size_m)
    cams = [r.cfg.camera for r in robots]
    znear = min((c.znear_m for c in cams), default=0.05)
    zfar = max((c.zfar_m for c in cams), default=60.0)
    root.statistic.extent = extent
    root.visual.map.znear = znear / extent
    root.visual.map.zfar = zfar / extent
    glob = getattr(root.visual, "global")
    glob.offwidth = max([640, *(c.width for c in cams)])
    glob.offheight = max([480, *(c.height for c in cams)])
