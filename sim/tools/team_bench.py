"""Cost as the team grows: real-time factor, memory and network load for teams of N LRU
rovers on the same terrain, and which part of the run grows fastest with N::

    python -m sim.tools.team_bench --sizes 1 2 4 8 --duration 30 --out results/bench/team

The largest team is a generated scenario (written beside the results as ``team_<N>.yaml``):
a 30 m lunar patch with the lander at its centre, the rovers spaced on a 10 m circle
around it, each driving 4 m towards the lander, 2 m along the circle and back out, with
the full estimation stack and the default network; the smaller teams keep its first
rovers (batch variants, ``team_batch.yaml``: one run at a time, each in its own
process). Writes ``team.json`` and ``team.md`` beside the batch's runs.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
from pathlib import Path

from sim.batch.execute import execute, plan
from sim.batch.spec import load_batch

RADIUS_M = 10.0
IN_M, ALONG_M = 4.0, 2.0


def team_scenario(n: int, duration_s: float, seed: int) -> dict:
    """N LRUs on a circle around the lander, each on its own short loop (module docstring)."""
    def at(a: float, r: float, s: float) -> list[float]:
        """The point ``r`` from the centre along bearing ``a`` and ``s`` along the circle."""
        return [round(r * math.cos(a) - s * math.sin(a), 3), round(r * math.sin(a) + s * math.cos(a), 3)]

    robots = []
    for k in range(n):
        a = 2 * math.pi * k / n + 0.3
        robots.append(
            {
                "name": f"lru{k + 1}",
                "preset": "lru",
                "start": {"xy": at(a, RADIUS_M, 0.0), "yaw_deg": round(math.degrees(a + math.pi), 3)},
                "route": {"speed_mps": 0.3, "waypoints": [at(a, RADIUS_M - IN_M, 0.0), at(a, RADIUS_M - IN_M, ALONG_M), at(a, RADIUS_M, ALONG_M)]},
            }
        )
    return {
        "name": f"team_{n}",
        "description": f"{n} LRU rovers around a lander (sim/tools/team_bench.py)",
        "seed": seed,
        "duration_s": duration_s,
        "terrain": {
            "preset": "moon",
            "size_m": 30,
            "roughness_m": 0.04,
            "craters": {"count": 4, "radius_m": [1.5, 3.5]},
            "rocks": {"count": 18, "diameter_m": [0.15, 0.7]},
            "lander": {"xy": [0, 0], "yaw_deg": 0, "tag_id": 0},
        },
        "robots": robots,
        "output": {"recording": False, "topdown_png": False},
    }


def run_teams(sizes: list[int], duration_s: float, seed: int, out: Path) -> list[dict]:
    """The teams as one batch (``sim.batch``: each run in a fresh process, one at a time, so
    memory and timings are its own): the largest team's scenario, each smaller team keeping
    its first rovers. Each team's size, speed, memory and network load."""
    out.mkdir(parents=True, exist_ok=True)
    scenario = out / f"team_{sizes[-1]}.yaml"
    scenario.write_text(json.dumps(team_scenario(sizes[-1], duration_s, seed), indent=2) + "\n")  # JSON is YAML
    batch_file = out / "team_batch.yaml"
    variants = [{"label": f"team_{n}", "robots": [f"lru{k + 1}" for k in range(n)]} for n in sizes]
    batch_file.write_text(json.dumps({"name": "team_bench", "scenario": scenario.name, "seeds": [seed], "variants": variants}, indent=2) + "\n")
    index, todo = plan(load_batch(batch_file), out)
    execute(index, todo, workers=1, on_start=lambda spec: print(f"{spec.variant}: running {duration_s:.0f} s ...", flush=True))
    rows = []
    for n, spec in zip(sizes, todo):
        path = out / spec.folder / "metrics.json"
        if not path.is_file():
            raise RuntimeError(f"team of {n} failed: {index.runs[spec.id]}")
        rows.append(team_row(n, json.loads(path.read_text())))
    return rows


def team_row(n: int, m: dict) -> dict:
    """A team run's size, speed, memory and network load from its ``metrics.json``."""
    rt, totals = m["runtime"], m["comms"]["totals"]
    sim_s = rt["sim_s"]
    per_sim_s = {f"loop: {k}": v / sim_s for k, v in rt["parts_s"].items() if k != "setup"}
    per_sim_s.update({f"worker: {k}": v / sim_s for k, v in rt.get("image_thread_s", {}).items()})
    return {
        "robots": n,
        "sim_s": sim_s,
        "wall_s": rt["wall_s"],
        "setup_s": rt["parts_s"].get("setup", 0.0),
        "real_time_factor": rt["real_time_factor"],
        "peak_rss_mb": rt["memory"]["peak_rss_mb"],
        "network_offered_Bps": totals["offered_Bps"],
        "network_by_kind_Bps": {k: v["offered_Bps"] for k, v in m["comms"]["by_kind"].items()},
        "wall_s_per_sim_s": per_sim_s,
    }


def growth(rows: list[dict]) -> dict[str, float]:
    """Exponent e of each part's wall time per simulated second ~ N^e between the smallest and the
    largest team (1: linear in the team's size)."""
    a, b = rows[0], rows[-1]
    if b["robots"] == a["robots"]:
        return {}
    scale = math.log(b["robots"] / a["robots"])
    out = {}
    for part, v in b["wall_s_per_sim_s"].items():
        v0 = a["wall_s_per_sim_s"].get(part, 0.0)
        if v0 > 0 and v > 0:
            out[part] = math.log(v / v0) / scale
    return out


def write_report(rows: list[dict], out: Path) -> str:
    exps = growth(rows)
    meta = {"machine": platform.platform(), "python": platform.python_version()}
    (out / "team.json").write_text(json.dumps({"meta": meta, "teams": rows, "growth_exponent": exps}, indent=2))
    parts = sorted({p for r in rows for p in r["wall_s_per_sim_s"]}, key=lambda p: -rows[-1]["wall_s_per_sim_s"].get(p, 0.0))
    lines = [
        "# Cost as the team grows (sim/tools/team_bench.py)",
        "",
        f"Machine: {meta['machine']}. N LRU rovers, {rows[0]['sim_s']:.0f} s simulated each.",
        "",
        "| robots | real-time factor | wall s (setup s) | peak memory MB | network offered kB/s |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        wall = f"{r['wall_s']:.0f} ({r['setup_s']:.1f})"
        lines.append(f"| {r['robots']} | {r['real_time_factor']:.2f} | {wall} | {r['peak_rss_mb']:.0f} | {r['network_offered_Bps'] / 1e3:.1f} |")
    lines += [
        "",
        "Wall seconds per simulated second, per part (the run loop's parts; the image pipeline's worker beside it),",
        "and the exponent e of part ~ N^e between the smallest and the largest team:",
        "",
        "| part | " + " | ".join(f"N={r['robots']}" for r in rows) + " | e |",
        "|---|" + "---|" * (len(rows) + 1),
    ]
    for p in parts:
        cells = " | ".join(f"{r['wall_s_per_sim_s'].get(p, 0.0):.3f}" for r in rows)
        e = f"{exps[p]:.2f}" if p in exps else "-"
        lines.append(f"| {p} | {cells} | {e} |")
    if exps:
        big = [p for p in parts if rows[-1]["wall_s_per_sim_s"].get(p, 0.0) >= 0.05 * rows[-1]["wall_s_per_sim_s"][parts[0]]]
        fastest = max((p for p in big if p in exps), key=exps.get, default=None)
        if fastest is not None:
            lines += ["", f"Fastest-growing part (of those above 5 % of the largest): {fastest}, e = {exps[fastest]:.2f}."]
    text = "\n".join(lines) + "\n"
    (out / "team.md").write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4, 8], help="team sizes, ascending")
    parser.add_argument("--duration", type=float, default=30.0, help="simulated seconds per team")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("results/bench/team"))
    args = parser.parse_args()
    sizes = sorted(set(args.sizes))
    if not sizes or sizes[0] < 1:
        parser.error(f"--sizes must be positive team sizes, got {args.sizes}")
    if not args.duration > 0:
        parser.error(f"--duration must be positive, got {args.duration}")
    rows = run_teams(sizes, args.duration, args.seed, args.out)
    for row in rows:
        print(f"team of {row['robots']}: real-time factor {row['real_time_factor']:.2f}, peak {row['peak_rss_mb']:.0f} MB, "
              f"network {row['network_offered_Bps'] / 1e3:.1f} kB/s", flush=True)
    print(write_report(rows, args.out))


if __name__ == "__main__":
    main()
