"""How fast the network model itself runs: messages per second of wall time.

Ten nodes (nine robots and a relaying lander) on the ``lab_wifi`` preset; each robot
broadcasts a pose (150 B) at 10 Hz, sends a loop closure (400 B) every 2 s and
broadcasts a submap (700 KB, thesis 8.4) every 25 s (0.04 Hz); payloads are random
bytes from a seeded generator. Run ``python -m comms.bench [--sim-seconds S]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import simpy

from comms.config import CommsConfig
from comms.network import Network


def run(sim_seconds: float = 30.0, robots: int = 9, seed: int = 0) -> dict:
    env = simpy.Environment()
    names = [f"robot{i}" for i in range(robots)]
    config = CommsConfig(preset="lab_wifi", relays=["lander"])
    net = Network(env, config, [*names, "lander"], np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    submap = rng.bytes(700_000)
    received = [0]

    def count(_delivery) -> None:
        received[0] += 1

    for n in net.nodes:
        net.on_receive(n, count)

    def robot(i: int, name: str):
        yield env.timeout(0.01 * i)  # robots not in lockstep
        k = 0
        while True:
            k += 1
            net.broadcast(name, "pose", rng.bytes(150), to=names)
            if k % 20 == 0:
                net.send(name, names[(i + 1) % robots], "loop_closure", rng.bytes(400))
            if k % 250 == i * 250 // robots:
                net.broadcast(name, "submap", submap, to=names)
            yield env.timeout(0.1)

    for i, name in enumerate(names):
        env.process(robot(i, name))
    start = time.perf_counter()
    env.run(until=sim_seconds)
    wall = time.perf_counter() - start
    totals = net.to_metrics()["totals"]
    fragments = sum(s.fragments_sent for s in net.accounting.links.values())
    return {
        "nodes": len(net.nodes),
        "sim_seconds": sim_seconds,
        "wall_seconds": wall,
        "messages_offered": totals["offered_msgs"],
        "messages_delivered": received[0],
        "fragments_sent": fragments,
        "messages_per_wall_s": totals["offered_msgs"] / wall,
        "fragments_per_wall_s": fragments / wall,
        "sim_over_wall": sim_seconds / wall,
        "delivered_MBps_simulated": totals["delivered_bytes"] / sim_seconds / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-seconds", type=float, default=30.0)
    parser.add_argument("--robots", type=int, default=9)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="also write the result as JSON to this file")
    args = parser.parse_args()
    text = json.dumps(run(args.sim_seconds, args.robots, args.seed), indent=2)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
