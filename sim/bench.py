"""``make bench``: real-time factor of a scenario and where the wall time goes.

Runs the scenario once per variant (the default camera settings, and variants that
show what faster settings buy) and writes ``bench.json`` and ``bench.md`` into the
output folder. Real-time factor = simulated seconds / wall seconds (1.0 = real time).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

from sim import results
from sim.runner import Run
from sim.scenario import load_scenario

VARIANTS: dict[str, list[str]] = {
    "default": [],
    "no_depth_truth": ["robots.*.camera.depth_ground_truth_every=0"],
    "half_rate": ["robots.*.camera.rate_hz=2.5"],
}


def bench(scenario_path: Path, out: Path, variants: list[str], duration: float | None) -> list[dict]:
    rows = []
    for name in variants:
        overrides = ["output.recording=false", "output.topdown_png=false"] + VARIANTS[name]
        if duration is not None:
            overrides.append(f"duration_s={duration}")
        scenario = load_scenario(scenario_path, overrides)
        t0 = time.perf_counter()
        run = Run(scenario)
        run.execute()
        metrics = results.write(run, out / name)
        runtime = metrics["runtime"]
        rows.append(
            {
                "variant": name,
                "overrides": VARIANTS[name],
                "sim_s": runtime["sim_s"],
                "wall_s": time.perf_counter() - t0,
                "real_time_factor": runtime["real_time_factor"],
                "parts_s": runtime["parts_s"],
            }
        )
        print(f"{name}: real-time factor {runtime['real_time_factor']:.2f} ({runtime['sim_s']:.0f} s sim in {runtime['wall_s']:.0f} s)")
    return rows


def write_report(rows: list[dict], scenario: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = {"scenario": str(scenario), "machine": platform.platform(), "python": platform.python_version()}
    (out / "bench.json").write_text(json.dumps({"meta": meta, "runs": rows}, indent=2))
    parts = sorted({p for r in rows for p in r["parts_s"]})
    lines = [
        f"# Benchmark: {scenario}",
        "",
        f"Machine: {meta['machine']}. Real-time factor = simulated s / wall s.",
        "",
        "| variant | overrides | sim s | wall s | RTF | " + " | ".join(f"{p} s" for p in parts) + " |",
        "|---|---|---|---|---|" + "---|" * len(parts),
    ]
    for r in rows:
        cells = " | ".join(f"{r['parts_s'].get(p, 0.0):.1f}" for p in parts)
        lines.append(
            f"| {r['variant']} | {' '.join(r['overrides']) or '-'} | {r['sim_s']:.0f} | {r['wall_s']:.1f} | {r['real_time_factor']:.2f} | {cells} |"
        )
    (out / "bench.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", type=Path)
    parser.add_argument("--out", type=Path, default=Path("results/bench"))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--duration", type=float, default=None, help="override duration_s")
    args = parser.parse_args()
    rows = bench(args.scenario, args.out, args.variants, args.duration)
    write_report(rows, args.scenario, args.out)


if __name__ == "__main__":
    main()
