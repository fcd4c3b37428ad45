"""Monte-Carlo batches: the batch file, validation before running, the process pool and
Ray executors, resuming, and the statistics of the report."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from sim.batch import report
from sim.batch.execute import Outcome, execute, plan, read_index
from sim.batch.spec import BatchError, check, load_batch, override

runner = CliRunner()

TINY = {
    "name": "tiny",
    "duration_s": 2,
    "terrain": {"size_m": 20, "rocks": {"count": 6}, "craters": {"count": 2}},
    "robots": [
        {"name": "rover", "preset": "lru", "start": {"xy": [-3, 0]}, "route": {"waypoints": [[2, 0]]}},
        {"name": "copter", "preset": "ardea", "start": {"xy": [-3, -3]}, "route": {"waypoints": [[2, -3]]}},
    ],
    "output": {"recording": False, "topdown_png": False},
    "slam": {"enabled": False},
}
SLOW_FAST = [
    {"label": "slow", "set": {"robots.*.route.speed_mps": 0.2}},
    {"label": "fast", "set": {"robots.*.route.speed_mps": 0.5}},
]
# valid for the schema, but the run cannot be set up: the random rock placement finds no room for 2000 large rocks
BROKEN = {"label": "broken", "set": {"terrain.rocks.count": 2000, "terrain.rocks.diameter_m": [2.5, 3.0]}}


def write_batch(folder: Path, **fields) -> Path:
    (folder / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    path = folder / "batch.yaml"
    path.write_text(yaml.safe_dump({"name": "tinybatch", "scenario": "tiny.yaml", **fields}, sort_keys=False))
    return path


def invoke(*args):
    """Run the CLI; ``text`` is its output with rich's line wrapping undone."""
    from sim.cli import app

    result = runner.invoke(app, [str(a) for a in args])
    result.text = " ".join(result.output.split())
    return result


def metrics(folder: Path) -> dict:
    return json.loads((folder / "metrics.json").read_text())


# --------------------------------------------------------------------------- statistics on hand-made tables


def table(rows: list[tuple]) -> pd.DataFrame:
    frame = pd.DataFrame(rows, columns=["variant", "seed", "robot", "status", "m"])
    frame["run"] = frame["variant"] + "/seed" + frame["seed"].astype(str)
    frame["error"] = None
    return frame


def test_summary_statistics_on_a_hand_made_table():
    rows = [("a", 0, "r", "completed", 1.0), ("a", 1, "r", "completed", 2.0), ("a", 2, "r", "completed", 6.0)]
    rows += [("a", 3, "r", "failed", 100.0), ("b", 0, "r", "completed", 4.0)]
    summary = report.summarize(table(rows), ["m"]).set_index("variant")
    a = summary.loc["a"]
    assert a["n"] == 3 and a["mean"] == pytest.approx(3.0) and a["median"] == pytest.approx(2.0)  # the failed run is left out
    assert a["std"] == pytest.approx(math.sqrt(7.0))  # ((1-3)^2 + (2-3)^2 + (6-3)^2) / (3-1)
    half = 4.302652729911275 * math.sqrt(7.0) / math.sqrt(3)  # t(0.975, 2 dof) * s / sqrt(n)
    assert (a["ci95_low"], a["ci95_high"]) == pytest.approx((3.0 - half, 3.0 + half))
    b = summary.loc["b"]
    assert b["n"] == 1 and b["mean"] == 4.0 and math.isnan(b["std"]) and math.isnan(b["ci95_low"])


def test_paired_comparison_on_a_hand_made_table():
    base = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    diff = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    rows = [("base", s, "r", "completed", v) for s, v in enumerate(base)]
    rows += [("other", s, "r", "completed", v + d) for s, (v, d) in enumerate(zip(base, diff))]
    rows += [("other", 6, "r", "completed", 50.0), ("other", 0, "extra_robot", "completed", 1.0)]  # no partner: left out
    comparisons = report.compare(table(rows), [("other", "base")], ["m"])
    assert len(comparisons) == 1
    c = comparisons.iloc[0]
    assert c["robot"] == "r" and c["n_pairs"] == 6
    assert c["baseline_mean"] == pytest.approx(3.5) and c["variant_mean"] == pytest.approx(3.85)
    assert c["relative_change"] == pytest.approx(0.35 / 3.5)
    half = 2.570581835636314 * math.sqrt(0.035) / math.sqrt(6)  # t(0.975, 5 dof) * s_d / sqrt(n); s_d^2 = 0.175 / 5
    assert (c["relative_ci95_low"], c["relative_ci95_high"]) == pytest.approx(((0.35 - half) / 3.5, (0.35 + half) / 3.5))
    assert c["wilcoxon_p"] == pytest.approx(2 / 2**6)  # exact two-sided: all six differences positive, no ties
    (back,) = report.compare(table(rows), [("base", "other")], ["m"]).itertuples()  # the pair the other way round
    assert (back.robot, back.n_pairs, back.relative_change) == ("r", 6, pytest.approx(-0.35 / 3.85))


def test_sweep_curves_and_plot_on_a_hand_made_table(tmp_path):
    """One numeric sweep key: per label, robot and swept value the mean and CI over seeds; the runs' labels are
    their variant names without the sweep part; no curves for two sweep keys or a non-numeric one."""
    values = {("a", 0.0): [1.0, 3.0], ("a", 0.5): [2.0, 4.0, 6.0], ("b,c", 0.0): [5.0]}
    rows, runs = [], []
    for (label, x), vs in values.items():
        for seed, v in enumerate(vs):
            rows.append((f"{label},k={x}", seed, "r", "completed", v))
            runs.append({"variant": f"{label},k={x}", "params": {"k": x}})
    rows.append(("a,k=0.5", 9, "r", "failed", 100.0))
    index = {"config": {"sweep": {"k": [0.0, 0.5]}, "variants": [{"label": "a"}, {"label": "b,c"}]}, "runs": runs}
    curves = report.sweep_curves(table(rows), "m", index).set_index(["label", "x"])
    assert list(curves.index) == [("a", 0.0), ("a", 0.5), ("b,c", 0.0)]
    assert curves.loc[("a", 0.5), "n"] == 3 and curves.loc[("a", 0.5), "mean"] == pytest.approx(4.0)  # the failed run left out
    half = 4.302652729911275 * 2.0 / math.sqrt(3)  # t(0.975, 2 dof) * s / sqrt(n)
    assert (curves.loc[("a", 0.5), "ci95_low"], curves.loc[("a", 0.5), "ci95_high"]) == pytest.approx((4.0 - half, 4.0 + half))
    assert curves.loc[("b,c", 0.0), "n"] == 1 and math.isnan(curves.loc[("b,c", 0.0), "ci95_low"])
    assert report.sweep_plot(curves.reset_index(), "m", "k", tmp_path / "sweep.png") and (tmp_path / "sweep.png").stat().st_size > 0
    for sweep in ({"k": [0.0, 0.5], "j": [1, 2]}, {"k": ["low", "high"]}):
        assert report.sweep_curves(table(rows), "m", {**index, "config": {**index["config"], "sweep": sweep}}).empty


# --------------------------------------------------------------------------- the batch file


def test_variants_times_sweep_and_override_round_trip(tmp_path):
    path = write_batch(
        tmp_path,
        seeds=2,
        set={"output.recording": False},
        variants=[{"label": "a", "set": {"comms.preset": "spacebotcamp"}}, {"label": "b", "robots": ["rover"]}],
        sweep={"terrain.rocks.count": [3, 9], "physics.timestep_s": [1e-3]},
    )
    batch = load_batch(path)
    assert [v.name for v in batch.variants] == [
        "a,terrain.rocks.count=3,physics.timestep_s=0.001",
        "a,terrain.rocks.count=9,physics.timestep_s=0.001",
        "b,terrain.rocks.count=3,physics.timestep_s=0.001",
        "b,terrain.rocks.count=9,physics.timestep_s=0.001",
    ]
    assert batch.baseline == batch.variants[0].name
    assert batch.comparisons == [(v.name, batch.baseline) for v in batch.variants[1:]]
    pairs = [["b,terrain.rocks.count=3,physics.timestep_s=0.001", "a,terrain.rocks.count=3,physics.timestep_s=0.001"]]
    assert load_batch(write_batch(tmp_path, seeds=1, variants=[{"label": "a"}, {"label": "b"}], comparisons=[["b", "a"]])).comparisons == [("b", "a")]
    assert load_batch(
        write_batch(
            tmp_path,
            seeds=2,
            variants=[{"label": "a"}, {"label": "b"}],
            sweep={"terrain.rocks.count": [3], "physics.timestep_s": [1e-3]},
            comparisons=pairs,
        )
    ).comparisons == [tuple(pairs[0])]
    specs = batch.specs()
    assert len(specs) == 8 and [s.seed for s in specs[:4]] == [0] * 4  # seed-major
    first = specs[0]
    assert first.overrides == ["output.recording=false", "comms.preset=spacebotcamp", "terrain.rocks.count=3", "physics.timestep_s=0.001", "seed=0"]
    assert specs[2].robots == ["rover"]
    assert not check(batch)
    values = [1e20, "local_reference", [1, 2], True, None, 0.1]
    assert [yaml.safe_load(override("k", v).split("=", 1)[1]) for v in values] == values


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"seeds": 1, "varaints": []}, "varaints: unknown key; allowed keys here: name, description, scenario, seeds"),
        ({"seeds": 1, "set": {"seed": 3}}, "'seed' is set by the batch's seeds"),
        ({"seeds": [1, 1]}, "seeds must be distinct"),
        ({"seeds": 1, "variants": [{"label": "x"}, {"label": "x"}]}, "variant labels must be unique"),
        ({"seeds": 1, "variants": [{"label": "x"}], "baseline": "y"}, "baseline: got 'y': not a variant"),
        ({"seeds": 1, "variants": [{"label": "x", "set": {"a.b": 1}}], "sweep": {"a.b": [1, 2]}}, "keys ['a.b'] are swept too"),
        ({"seeds": 1, "variants": [{"label": "x"}, {"label": "z"}], "comparisons": [["x", "y"]]}, "comparisons: ['y'] not variants"),
        ({"seeds": 1, "variants": [{"label": "x"}], "comparisons": [["x", "x"]]}, "compare a variant with itself"),
        ({"seeds": 1, "timeout_s": True}, "timeout_s: got True"),  # the batch file's numbers are strict, as the scenario's
        ({"seeds": 1, "timeout_s": float("nan")}, "timeout_s: got nan"),
    ],
)
def test_batch_file_errors_name_the_key(tmp_path, fields, expected):
    with pytest.raises(BatchError) as err:
        load_batch(write_batch(tmp_path, **fields))
    assert any(expected in line for line in err.value.problems), err.value.problems


def test_check_names_every_invalid_variant_and_runs_nothing(tmp_path):
    variants = [
        SLOW_FAST[0],
        {"label": "five_d", "set": {"slam.matching.mode": "5d"}},  # a mode that does not exist
        {"label": "nobody", "robots": ["rover", "ghost"]},
        {"label": "moon_laser", "set": {"comms.preset": "moon_laser"}},
    ]
    path = write_batch(tmp_path, seeds=[1], variants=variants)
    result = invoke("batch", path, "--out", tmp_path / "out")
    assert result.exit_code == 2, result.output
    text = result.text
    assert "variant five_d: invalid scenario" in text and "slam.matching.mode" in text and "'4d'" in text
    assert "variant nobody: invalid scenario" in text and "no robot named 'ghost'" in text
    assert "variant moon_laser: invalid scenario" in text and "moon_laser" in text and "spacebotcamp" in text
    assert "variant slow" not in text and "3 of 4 variants invalid; nothing was run" in text
    assert not (tmp_path / "out").exists()
    ok = invoke("batch", write_batch(tmp_path, seeds=[1, 2], variants=SLOW_FAST), "--check")
    assert ok.exit_code == 0 and "2 variants x 2 seeds = 4 runs" in ok.text


# --------------------------------------------------------------------------- running batches


def test_pool_batch_records_a_failing_run_summarises_and_resumes_without_rerunning(tmp_path, monkeypatch):
    path = write_batch(tmp_path, seeds=[1, 2], variants=[*SLOW_FAST, BROKEN], metrics=["distance_m", "camera_frames"])
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["/venv/bin/marsyard", "batch", str(path), "--out", str(out), "--workers", "2"])
    result = invoke("batch", path, "--out", out, "--workers", 2)
    assert result.exit_code == 1, result.output  # not every run completed
    runs = {r["id"]: r for r in read_index(out)["runs"]}
    assert len(runs) == 6
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True).stdout.strip()
    (invocation,) = read_index(out)["invocations"]
    assert invocation["command"] == f"marsyard batch {path} --out {out} --workers 2" and invocation["git_commit"] == head
    assert {r["git_commit"] for r in runs.values()} == {head}
    for variant in ("slow", "fast"):
        for seed in (1, 2):
            run = runs[f"{variant}/seed{seed}"]
            assert run["status"] == "completed", run
            assert metrics(out / run["folder"])["seed"] == seed
    for seed in (1, 2):
        run = runs[f"broken/seed{seed}"]
        assert run["status"] == "failed" and "placed only" in run["error"] and "of 2000 rocks" in run["error"]
        assert (out / run["folder"] / "error.txt").is_file()

    tidy = pd.read_parquet(out / "runs.parquet")
    assert len(tidy) == 4 * 2 + 2  # a row per completed run and robot, one per failed run
    assert set(tidy[tidy["variant"] == "broken"]["robot"].isna()) == {True}
    assert sorted(tidy["set.robots.*.route.speed_mps"].dropna().unique()) == [0.2, 0.5]
    summary = pd.read_csv(out / "summary.csv")
    for variant in ("slow", "fast"):
        row = summary[(summary["variant"] == variant) & (summary["robot"] == "rover") & (summary["metric"] == "distance_m")].iloc[0]
        values = [metrics(out / runs[f"{variant}/seed{s}"]["folder"])["robots"]["rover"]["distance_m"] for s in (1, 2)]
        assert row["n"] == 2 and row["mean"] == pytest.approx(sum(values) / 2)
    run_level = summary[summary["metric"] == "runtime.sim_s"]  # one value per run, not per robot
    assert set(run_level["robot"]) == {"(run)"} and set(run_level["n"]) == {2}
    fast_vs_slow = pd.read_csv(out / "comparisons.csv").query("robot == 'rover' and metric == 'distance_m'").iloc[0]
    assert fast_vs_slow["variant"] == "fast" and fast_vs_slow["relative_change"] > 0.5  # 0.5 against 0.2 m/s
    report = (out / "report.md").read_text()
    assert "(plots/distance_m.png)" in report and (out / "plots" / "distance_m.png").stat().st_size > 0
    assert "broken/seed1" in report and "Wilcoxon" in report
    assert f"| `marsyard batch {path} --out {out} --workers 2` | `{head[:10]}`" in report and f"`{head[:10]}`" in report
    (out / "report.md").unlink()
    assert invoke("report", out, "--metric", "camera_frames").exit_code == 0
    report = (out / "report.md").read_text()
    assert "### `camera_frames`" in report and "### `distance_m`" not in report

    before = {r["id"]: (r["started"], r["finished"]) for r in read_index(out)["runs"]}
    mtimes = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/metrics.json")}
    again = invoke("batch", path, "--out", out, "--resume")
    assert "6 runs, 0 to do" in again.text, again.output
    assert {r["id"]: (r["started"], r["finished"]) for r in read_index(out)["runs"]} == before
    assert {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/metrics.json")} == mtimes
    assert len(read_index(out)["invocations"]) == 2  # the resumed part is recorded too

    retry = invoke("batch", path, "--out", out, "--retry-failed")
    assert "6 runs, 2 to do" in retry.text, retry.output
    after = {r["id"]: (r["started"], r["finished"]) for r in read_index(out)["runs"]}
    assert [i for i in after if after[i] != before[i]] == ["broken/seed1", "broken/seed2"]


def test_resume_runs_again_a_completed_run_whose_metrics_are_gone(tmp_path):
    """A fresh clone holds the index and the committed metrics.json files only: a completed
    run without its metrics must run again rather than be reported empty."""
    batch = load_batch(write_batch(tmp_path, seeds=[1, 2]))
    out = tmp_path / "out"
    index, todo = plan(batch, out)
    for spec in todo:
        index.start(spec)
        index.finish(spec, Outcome("completed", wall_s=1.0))
    kept, lost = todo
    (out / kept.folder).mkdir(parents=True)
    (out / kept.folder / "metrics.json").write_text("{}")
    _, again = plan(batch, out, resume=True)
    assert [s.id for s in again] == [lost.id]


def test_a_run_past_the_timeout_is_killed_and_recorded(tmp_path):
    batch = load_batch(write_batch(tmp_path, seeds=[1], timeout_s=0.5))
    index, todo = plan(batch, tmp_path / "out")
    execute(index, todo, workers=1)
    (run,) = read_index(tmp_path / "out")["runs"]
    assert run["status"] == "timeout" and "timeout_s=0.5" in run["error"]


def test_ray_gives_the_same_metrics_as_the_process_pool(tmp_path):
    path = write_batch(tmp_path, seeds=[4], variants=SLOW_FAST)
    assert invoke("batch", path, "--out", tmp_path / "pool", "--workers", 2).exit_code == 0
    result = invoke("batch", path, "--ray", "--workers", 2, "--out", tmp_path / "ray")
    assert result.exit_code == 0, result.output
    assert "local Ray" in result.text
    for run in read_index(tmp_path / "ray")["runs"]:
        assert run["status"] == "completed"
        pool = report.flatten(metrics(tmp_path / "pool" / run["folder"]))
        ray = report.flatten(metrics(tmp_path / "ray" / run["folder"]))
        timing = [k for k in pool if k.startswith("runtime.") or "wall" in k]
        assert {k: v for k, v in pool.items() if k not in timing} == {k: v for k, v in ray.items() if k not in timing}
        assert (tmp_path / "ray" / run["folder"] / "trajectories" / "rover.gt.tum").is_file()


def _descendants(pid: int) -> set[int]:
    """The processes below ``pid`` (from /proc)."""
    parents = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree from /proc")
def test_sigterm_ends_the_workers_and_puts_running_runs_back_to_pending(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    path = write_batch(tmp_path, seeds=[1, 2])
    out = tmp_path / "out"
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump({**TINY, "duration_s": 600}))  # far longer than the test waits
    cli = subprocess.Popen([sys.executable, "-m", "sim.cli", "batch", str(path), "--out", str(out), "--workers", "2"])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        index = out / "index.json"
        if index.is_file() and [r["status"] for r in read_index(out)["runs"]] == ["running", "running"]:
            break
        time.sleep(0.2)
    else:
        cli.kill()
        pytest.fail("the runs never started")
    time.sleep(2.0)  # the workers are simulating
    workers = _descendants(cli.pid)
    assert workers
    cli.send_signal(signal.SIGTERM)
    assert cli.wait(timeout=60) == 130
    assert [r["status"] for r in read_index(out)["runs"]] == ["pending", "pending"]
    deadline = time.monotonic() + 15.0  # the workers end on their own; on a loaded machine that can take seconds
    while time.monotonic() < deadline and any(_alive(pid) for pid in workers):
        time.sleep(0.2)
    alive = {pid for pid in workers if _alive(pid)}
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[1] / "scenarios" / "experiments").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_experiment_file_is_a_valid_batch(path):
    batch = load_batch(path)
    assert not check(batch), check(batch)
