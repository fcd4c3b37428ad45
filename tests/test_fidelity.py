"""The claims table of docs/fidelity.md (sim/tools/fidelity.py) on hand-made batch tables."""

import pandas as pd
import pytest

from comms.load import LRU_GUPPY_PRO_F125B
from sim.tools import fidelity


def rows(variant: str, seed: int, values: dict[str, dict[str, float]], run_level: dict[str, float] | None = None) -> list[dict]:
    """A completed run's rows, one per robot: ``values[robot][metric]``, run-level metrics repeated."""
    run = f"{variant}/seed{seed}"
    return [{"run": run, "variant": variant, "seed": seed, "status": "completed", "robot": r, **(run_level or {}), **m} for r, m in values.items()]


def test_team_against_alone_pairs_each_rover_with_its_own_single_run_per_seed():
    data = []
    for seed in range(6):
        team = {"a": 1.0 + 0.1 * seed, "b": 2.0}
        alone = {"a": 2.0 + 0.1 * seed, "b": 2.0 + 0.01 * (seed + 1)}  # a gains 1.0, b little
        data += rows("team", seed, {r: {"slam.ate_m.mean": v} for r, v in team.items()})
        data += rows("a_alone", seed, {"a": {"slam.ate_m.mean": alone["a"]}})
        data += rows("b_alone", seed, {"b": {"slam.ate_m.mean": alone["b"]}})
    data += rows("team", 6, {"a": {"slam.ate_m.mean": 9.0}, "b": {"slam.ate_m.mean": 9.0}})  # no single runs: left out
    figure = fidelity._team_against_alone(pd.DataFrame(data), "slam.ate_m.mean")
    team_mean = sum((1.0 + 0.1 * s + 2.0) / 2 for s in range(6)) / 6
    alone_mean = sum((2.0 + 0.1 * s + 2.0 + 0.01 * (s + 1)) / 2 for s in range(6)) / 6
    assert figure.n == 6 and figure.verdict == "reproduced"  # every seed lower in the team
    assert f"{100 * (team_mean - alone_mean) / alone_mean:+.1f} %" in figure.text
    assert fidelity._team_against_alone(pd.DataFrame(data), "slam.ate_m.mean", sign=0).verdict == "control"


@pytest.mark.parametrize(
    ("deltas", "verdict"),
    [
        ([-0.2, -0.3, -0.25, -0.1, -0.2], "reproduced"),
        ([-0.5, 0.3, -0.4, 0.2, -0.3], "same direction, not significant"),
        ([0.2, 0.3, 0.1, 0.2, 0.3], "not reproduced"),
    ],
)
def test_relative_change_verdict_follows_the_interval(deltas, verdict):
    data = []
    for seed, d in enumerate(deltas):
        data += rows("base", seed, {"r": {"m": 1.0}})
        data += rows("new", seed, {"r": {"m": 1.0 + d}})
    figure = fidelity.relative_change(pd.DataFrame(data), "new", "base", fidelity.column("m"), -1)
    assert figure.verdict == verdict and figure.n == 5
    assert figure.text.startswith(f"{100 * sum(deltas) / len(deltas):+.1f} %")


def test_error_per_distance_and_bandwidth_per_robot():
    data = []
    for seed in range(4):
        per_robot = {r: {"slam.ate_m.mean": 0.2 + 0.01 * seed, "slam.distance_m": 100.0} for r in ("a", "b")}
        data += rows("team", seed, per_robot, {"comms.by_kind.submap.offered_Bps": 14_000.0, "comms.raw_equivalent_Bps": 1_536_000.0})
    table = pd.DataFrame(data)
    error = fidelity.error_per_distance(table, "team", 0.5)
    assert error.n == 4 and error.verdict == "reproduced" and error.text.startswith("0.21 %") and "of 100 m" in error.text
    assert fidelity.error_per_distance(table, "team", 0.2).verdict == "not reproduced"
    band = fidelity.bandwidth(table, "team")  # two robots share the run's totals
    assert band.text.startswith("7.0 kB/s") and "1/110 of the simulated camera's 768 kB/s" in band.text
    assert f"1/{LRU_GUPPY_PRO_F125B.bytes_per_s / 7000:.0f} of the LRU camera's 35.6 MB/s" in band.text


@pytest.mark.parametrize(("p95", "verdict"), [(20.0, "reproduced"), (40.0, "not reproduced")])
def test_link_keeps_up_compares_submap_latency_with_the_time_between_a_robots_submaps(p95, verdict):
    data = []
    for seed in range(4):
        run = {"comms.duration_s": 300.0, "comms.by_kind.submap.offered_msgs": 20.0, "comms.by_kind.submap.latency_s.p95": p95 + seed * 0.1}
        data += rows("slow", seed, {"a": {}, "b": {}}, run)  # two robots, 10 submaps each: one per 30 s
    figure = fidelity.link_keeps_up(pd.DataFrame(data), "slow")
    assert figure.n == 4 and figure.verdict == verdict
    assert figure.text.startswith(f"submap latency p95 {p95 + 0.15:.1f} s") and figure.text.endswith("against 30 s between a robot's submaps")


def test_claims_without_results_say_so(tmp_path):
    lines = fidelity.table_rows(tmp_path)
    assert len(lines) == 2 + len(fidelity.CLAIMS)
    assert all("not run yet" in line for line in lines[2:])
