"""Render cost of the sun's shadows (docs/realism.md, "Shadows"): the first robot's first
stereo pair of a scenario, rendered ``--frames`` times at its start pose without and with
``realism.light.shadows``, with ground-truth depth as a run reads it. Prints milliseconds
per pair and their ratio as JSON::

    python -m sim.tools.render_bench scenarios/etna_two_rovers.yaml --set realism.light.sun_elevation_deg=15
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from sim.run.runner import Run
from sim.scenario import load_scenario

WARM_UP_FRAMES = 5


def pair_ms(scenario: Path, overrides: list[str], frames: int) -> float:
    """Milliseconds per rendered stereo pair (with depth) of the first robot's first rig."""
    run = Run(load_scenario(scenario, ["output.recording=false", *overrides]))
    try:
        renderer = next(iter(run.robots.values())).renderers[0]
        for _ in range(WARM_UP_FRAMES):
            renderer.render(run.world.data, with_depth=True)
        t0 = time.perf_counter()
        for _ in range(frames):
            renderer.render(run.world.data, with_depth=True)
        return (time.perf_counter() - t0) / frames * 1e3
    finally:
        run.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", type=Path)
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="dotted.key=value, repeatable")
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    plain = pair_ms(args.scenario, [*args.overrides, "realism.light.shadows=false"], args.frames)
    shadows = pair_ms(args.scenario, [*args.overrides, "realism.light.shadows=true"], args.frames)
    print(json.dumps({"no_shadows_ms_per_pair": round(plain, 1), "shadows_ms_per_pair": round(shadows, 1), "ratio": round(shadows / plain, 2)}))


if __name__ == "__main__":
    main()
