"""``make bench``: batch throughput, runs per hour with 1 and 2 workers, process pool against Ray.

A small batch (``--runs`` seeds of a short quickstart, full estimation stack, no
recording) runs once per executor and worker count, each into a fresh folder. Runs per
hour = runs / wall time of the whole batch (Ray's start-up included); scaling efficiency
= runs per hour with n workers / (n x runs per hour with one worker of the same
executor). Writes a JSON file (default ``results/bench/batch.json``).
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import yaml

from sim.batch.execute import execute, plan
from sim.batch.spec import load_batch

REPO = Path(__file__).resolve().parents[2]
#: The project's throughput target (README, "Measured"): runs per hour of the 8 s quickstart with two workers.
TARGET_RUNS_PER_HOUR = 400
TARGET_WORKERS = 2


def bench_one(batch_file: Path, out: Path, workers: int, use_ray: bool) -> dict:
    batch = load_batch(batch_file)
    index, todo = plan(batch, out)
    t0 = time.perf_counter()
    execute(index, todo, workers=workers, use_ray=use_ray)
    wall = time.perf_counter() - t0
    runs = list(index.runs.values())
    completed = sum(r["status"] == "completed" for r in runs)
    return {
        "executor": "ray" if use_ray else "pool",
        "workers": workers,
        "runs": len(runs),
        "completed": completed,
        "wall_s": wall,
        "runs_per_hour": 3600 * completed / wall,
        "run_wall_mean_s": sum(r["wall_s"] or 0 for r in runs) / len(runs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/bench/batch.json"))
    parser.add_argument("--scenario", type=Path, default=REPO / "scenarios" / "quickstart.yaml")
    parser.add_argument("--runs", type=int, default=4, help="seeds in the batch")
    parser.add_argument("--duration", type=float, default=8.0, help="simulated seconds per run")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--executors", nargs="+", default=["pool", "ray"], choices=["pool", "ray"])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="marsyard-batch-bench-") as tmp:
        batch_file = Path(tmp) / "bench.yaml"
        batch = {
            "name": "batch_bench",
            "scenario": str(args.scenario.resolve()),
            "seeds": args.runs,
            "set": {"duration_s": args.duration, "output.recording": False, "output.topdown_png": False},
        }
        batch_file.write_text(yaml.safe_dump(batch))
        rows = []
        for executor in args.executors:
            for workers in args.workers:
                row = bench_one(batch_file, Path(tmp) / f"{executor}-{workers}", workers, executor == "ray")
                one = next((r for r in rows if r["executor"] == executor and r["workers"] == 1), None)
                row["scaling_efficiency"] = row["runs_per_hour"] / (workers * one["runs_per_hour"]) if one else None
                rows.append(row)
                eff = f", scaling efficiency {row['scaling_efficiency']:.2f}" if row["scaling_efficiency"] is not None else ""
                target = ""
                if workers == TARGET_WORKERS:
                    met = "met" if row["runs_per_hour"] >= TARGET_RUNS_PER_HOUR else "not met"
                    target = f" (target >= {TARGET_RUNS_PER_HOUR} runs/h: {met})"
                done = f"{row['completed']}/{row['runs']} runs in {row['wall_s']:.1f} s"
                print(f"{executor} x{workers}: {done} = {row['runs_per_hour']:.0f} runs/h{eff}{target}")
    meta = {
        "machine": platform.platform(),
        "python": platform.python_version(),
        "scenario": str(args.scenario),
        "duration_s": args.duration,
        "runs": args.runs,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
