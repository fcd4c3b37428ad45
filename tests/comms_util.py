"""Helpers shared by the comms tests."""

from __future__ import annotations

from typing import Any

import numpy as np
import simpy

from comms import CommsConfig, Network


def make_net(
    nodes=("a", "b"),
    seed: int = 0,
    positions=None,
    line_of_sight=None,
    keep_log: bool = False,
    **section: Any,
) -> tuple[simpy.Environment, Network]:
    """A network with no preset: ``section`` is the ``comms:`` section."""
    section.setdefault("preset", None)
    env = simpy.Environment()
    cfg = CommsConfig.model_validate(section)
    net = Network(env, cfg, list(nodes), np.random.default_rng(seed), positions, line_of_sight, keep_log=keep_log)
    return env, net


def collect(env: simpy.Environment, net: Network, node: str) -> list:
    """Deliveries to ``node``, in arrival order, filled while the env runs."""
    got: list = []
    net.on_receive(node, got.append)
    return got


def send_at(env: simpy.Environment, t: float, fn) -> None:
    """Call ``fn()`` at simulated time ``t``."""

    def proc():
        yield env.timeout(t - env.now)
        fn()

    env.process(proc())
