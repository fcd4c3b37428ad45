"""A batch's results as tables, statistics, box plots and a Markdown report.

Files written into the batch folder by :func:`write_report`::

    runs.csv, runs.parquet   the tidy table: one row per run and robot
    summary.csv              per variant, robot and metric: n, mean, median, std, 95 % CI
    comparisons.csv          each variant against the baseline (or the batch's ``comparisons``
                             pairs) over the same seeds
    plots/<metric>.png       box plots of the report's metrics per variant (one panel per robot)
    plots/sweep_<metric>.png with one numeric sweep key: each metric against it, one line per
                             variant label (mean and 95 % CI over seeds, seeds as dots)
    report.md                the report linking them

Tidy table columns: ``run``, ``variant``, ``seed``, ``status``, ``error``,
``set.<key>`` (every key a variant sets or sweeps), ``robot``; then every scalar of the
run's ``metrics.json`` flattened with dotted names: the robot's own section without its
``robots.<name>.`` prefix (``filter.ate_m.rmse``) and the run-level sections with
theirs (``runtime.wall_s``, ``comms.totals.offered_bytes``, repeated on each robot's row;
statistics and plots count them once per run, as robot ``(run)``). A run without
metrics (crashed, timed out, set-up failure) keeps one row with ``robot`` empty.

Statistics (over seeds, completed runs only): the 95 % CI of a mean is Student's t
interval. A comparison pairs a variant's runs with the baseline's by seed: relative
change = mean(variant - baseline) / mean(baseline), its CI the t interval of the mean
paired difference divided by the baseline's mean; the test is the two-sided Wilcoxon
signed-rank test (:func:`scipy.stats.wilcoxon`) of the paired values.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from scipy import stats

from sim.batch.execute import read_index
from sim.batch.provenance import REPO

RUN_COLUMNS = ["run", "variant", "seed", "status", "error"]
#: Keys of metrics.json that the index columns already hold.
INDEX_KEYS = ("scenario", "seed", "status", "error", "robots")
SUMMARY_COLUMNS = ["variant", "robot", "metric", "n", "mean", "median", "std", "ci95_low", "ci95_high"]
COMPARISON_COLUMNS = [
    "variant", "baseline", "robot", "metric", "n_pairs", "baseline_mean", "variant_mean",
    "relative_change", "relative_ci95_low", "relative_ci95_high", "wilcoxon_p",
]  # fmt: skip


def flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    """Scalars of nested dicts under dotted keys; lists are left out (not scalars)."""
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
        return out
    if isinstance(node, list):
        return {}
    return {prefix: node}


def tidy_table(batch_dir: Path) -> pd.DataFrame:
    """One row per run and robot (see the module docstring)."""
    index = read_index(batch_dir)
    params = index.get("params", [])
    rows, run_level = [], set()
    for run in index["runs"]:
        base = {"run": run["id"], "variant": run["variant"], "seed": run["seed"], "status": run["status"], "error": run["error"]}
        base.update({f"set.{k}": _cell(run["params"].get(k)) for k in params})
        path = Path(batch_dir) / run["folder"] / "metrics.json"
        if run["status"] not in ("completed", "failed") or not path.is_file():
            rows.append({**base, "robot": None})
            continue
        metrics = json.loads(path.read_text())
        shared = flatten({k: v for k, v in metrics.items() if k not in INDEX_KEYS})
        run_level.update(shared)
        robots = metrics.get("robots") or {}
        rows += [{**base, "robot": name, **shared, **flatten(section)} for name, section in robots.items()] or [{**base, "robot": None, **shared}]
    columns = RUN_COLUMNS + [f"set.{k}" for k in params] + ["robot"]
    table = pd.DataFrame(rows)
    table = table[columns + [c for c in table.columns if c not in columns]]
    table.attrs["run_level"] = sorted(run_level)
    return table


def _cell(value: Any) -> Any:
    return json.dumps(value) if isinstance(value, (list, dict)) else value


def metric_columns(table: pd.DataFrame) -> list[str]:
    """Numeric metric columns (not the seed, not swept values)."""
    skip = set(RUN_COLUMNS) | {"robot"}
    return [
        c for c in table.columns
        if c not in skip and not c.startswith("set.") and pd.api.types.is_numeric_dtype(table[c]) and not pd.api.types.is_bool_dtype(table[c])
    ]  # fmt: skip


def mean_ci(values: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Student's t interval of the mean; NaN for fewer than two values."""
    n = len(values)
    if n < 2:
        return math.nan, math.nan
    half = stats.t.ppf(0.5 + level / 2, n - 1) * np.std(values, ddof=1) / math.sqrt(n)
    mean = float(np.mean(values))
    return mean - half, mean + half


def metric_rows(table: pd.DataFrame, metric: str) -> pd.DataFrame:
    """Completed runs' rows with a value of ``metric``: ``variant``, ``seed``, ``robot``,
    ``value``. A run-level metric (``table.attrs["run_level"]``, e.g. ``comms.*``)
    gives one row per run, its robot ``(run)``."""
    if metric not in table:
        return pd.DataFrame(columns=["variant", "seed", "robot", "value"])
    rows = table[table["status"] == "completed"][["run", "variant", "seed", "robot", metric]].rename(columns={metric: "value"})
    rows["value"] = pd.to_numeric(rows["value"], errors="coerce")
    if metric in table.attrs.get("run_level", ()):
        rows = rows.drop_duplicates("run").assign(robot="(run)")
    return rows.dropna(subset=["value"]).drop(columns="run")


def summarize(table: pd.DataFrame, metrics: list[str] | None = None) -> pd.DataFrame:
    """Per variant, robot and metric over the completed runs' seeds: n, mean, median, std (n-1), 95 % CI."""
    out = []
    for metric in metrics if metrics is not None else metric_columns(table):
        for (variant, robot), group in metric_rows(table, metric).groupby(["variant", "robot"], sort=False):
            values = group["value"].to_numpy(dtype=float)
            low, high = mean_ci(values)
            std = float(np.std(values, ddof=1)) if len(values) > 1 else math.nan
            out.append([variant, robot, metric, len(values), float(np.mean(values)), float(np.median(values)), std, low, high])
    return pd.DataFrame(out, columns=SUMMARY_COLUMNS)


def compare(table: pd.DataFrame, pairs: list[tuple[str, str]], metrics: list[str]) -> pd.DataFrame:
    """Each ``(variant, baseline)`` pair, per robot the two share and metric, paired by seed."""
    out = []
    for metric in metrics:
        rows = metric_rows(table, metric)
        for variant, baseline in pairs:
            base = rows[rows["variant"] == baseline]
            for robot, group in rows[rows["variant"] == variant].groupby("robot", sort=False):
                paired = group.merge(base[base["robot"] == robot], on="seed", suffixes=("", "_base"))
                if not paired.empty:
                    values = paired["value_base"].to_numpy(float), paired["value"].to_numpy(float)
                    out.append([variant, baseline, robot, metric, *paired_change(*values)])
    return pd.DataFrame(out, columns=COMPARISON_COLUMNS)


def paired_change(base: np.ndarray, variant: np.ndarray) -> list[float]:
    """n, both means, relative change with its 95 % CI, and the Wilcoxon signed-rank p-value."""
    n = len(base)
    diff = variant - base
    b_mean = float(np.mean(base))
    low, high = mean_ci(diff)
    scale = b_mean if b_mean != 0 else math.nan
    if not np.any(diff):
        p = 1.0
    else:
        p = float(stats.wilcoxon(variant, base, alternative="two-sided").pvalue)
    return [n, b_mean, float(np.mean(variant)), float(np.mean(diff)) / scale, low / scale, high / scale, p]


# --------------------------------------------------------------------------- plots and report


def box_plot(table: pd.DataFrame, metric: str, variants: list[str], path: Path) -> bool:
    """Box plots of ``metric`` per variant, one panel per robot, seeds as dots; False if no values."""
    rows = metric_rows(table, metric)
    robots = list(rows["robot"].unique())
    if not robots:
        return False
    fig, axes = plt.subplots(1, len(robots), figsize=(max(4.0, 0.9 * len(variants) * len(robots) + 2), 4.2), dpi=110, squeeze=False)
    for ax, robot in zip(axes[0], robots):
        mine = rows[rows["robot"] == robot]
        present = [v for v in variants if v in set(mine["variant"])]
        data = [mine[mine["variant"] == v]["value"].to_numpy(float) for v in present]
        ax.boxplot(data, showmeans=True)
        ax.set_xticks(range(1, len(present) + 1), present, rotation=30, ha="right", fontsize=8)
        for i, values in enumerate(data, start=1):
            ax.plot(np.full(len(values), i) + np.linspace(-0.08, 0.08, len(values)), values, "k.", alpha=0.5)
        ax.set_title(str(robot), fontsize=9)
        ax.grid(alpha=0.3)
    _save(fig, axes, metric, path)
    return True


def sweep_curves(table: pd.DataFrame, metric: str, index: dict) -> pd.DataFrame:
    """``metric`` against the batch's sweep when it has exactly one key with numeric values: per variant label
    (``all`` without labelled variants), robot and swept value the completed runs' n, mean and 95 % CI, and
    the values themselves; empty otherwise. A variant's label is its name without the sweep part
    (:func:`sim.batch.spec.expand` appends ``,key=value``)."""
    columns = ["label", "robot", "x", "n", "mean", "ci95_low", "ci95_high", "values"]
    sweep = index["config"].get("sweep") or {}
    if len(sweep) != 1:
        return pd.DataFrame(columns=columns)
    ((key, values),) = sweep.items()
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return pd.DataFrame(columns=columns)
    x_of = {run["variant"]: float(run["params"][key]) for run in index["runs"]}
    labelled = bool(index["config"].get("variants"))
    rows = metric_rows(table, metric)
    rows = rows.assign(label=[v.rsplit(",", 1)[0] if labelled else "all" for v in rows["variant"]], x=rows["variant"].map(x_of))
    out = []
    for (label, robot, x), group in rows.groupby(["label", "robot", "x"], sort=False):
        v = group["value"].to_numpy(float)
        out.append([label, robot, x, len(v), float(np.mean(v)), *mean_ci(v), v])
    return pd.DataFrame(out, columns=columns).sort_values(["robot", "label", "x"], kind="stable", ignore_index=True)


def sweep_plot(curves: pd.DataFrame, metric: str, key: str, path: Path) -> bool:
    """:func:`sweep_curves` drawn: one panel per robot, a line per label with its CI as error bars, seeds as
    dots; False when there is nothing to draw."""
    if curves.empty:
        return False
    robots = list(dict.fromkeys(curves["robot"]))
    fig, axes = plt.subplots(1, len(robots), figsize=(4.2 * len(robots) + 1, 4.2), dpi=110, squeeze=False)
    span = float(np.ptp(curves["x"])) or 1.0
    for ax, robot in zip(axes[0], robots):
        for i, (label, line) in enumerate(curves[curves["robot"] == robot].groupby("label", sort=False)):
            shift = (i - 1) * 0.012 * span  # labels side by side at each value
            err = np.abs(np.vstack([line["mean"] - line["ci95_low"], line["ci95_high"] - line["mean"]]).astype(float))
            bars = ax.errorbar(line["x"] + shift, line["mean"], yerr=np.nan_to_num(err), marker="o", capsize=3, label=label)
            for x, values in zip(line["x"], line["values"]):
                ax.plot(np.full(len(values), x + shift), values, ".", color=bars[0].get_color(), alpha=0.4)
        ax.set_title(str(robot), fontsize=9)
        ax.set_xlabel(key)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    _save(fig, axes, metric, path)
    return True


def _save(fig, axes, metric: str, path: Path) -> None:
    """Label the first panel with ``metric`` and write the figure to ``path``."""
    axes[0][0].set_ylabel(metric)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def write_report(batch_dir: Path, metrics: list[str] | None = None) -> Path:
    """Write the tables, plots and ``report.md`` of a batch folder; return the report's path."""
    batch_dir = Path(batch_dir)
    index = read_index(batch_dir)
    metrics = metrics or index["config"]["metrics"]
    variants, baseline = index["variants"], index["baseline"]
    table = tidy_table(batch_dir)
    table.to_csv(batch_dir / "runs.csv", index=False)
    _parquet_safe(table).to_parquet(batch_dir / "runs.parquet", index=False)
    summary = summarize(table)
    summary.to_csv(batch_dir / "summary.csv", index=False)
    pairs = [tuple(p) for p in index.get("comparisons") or [[v, baseline] for v in variants if v != baseline]]
    comparisons = compare(table, pairs, metrics)
    comparisons.to_csv(batch_dir / "comparisons.csv", index=False)

    runs = index["runs"]
    counts = {s: sum(r["status"] == s for r in runs) for s in ("completed", "failed", "crashed", "timeout", "pending", "running")}
    lines = [
        f"# Batch {index['batch']}",
        "",
        *([index["description"], ""] if index.get("description") else []),
        f"Base scenario `{_shown(index['scenario'])}`, batch file `{_shown(index['batch_file'])}`; seeds {index['config']['seeds']}; "
        f"{len(variants)} variants, {len(runs)} runs: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n) + ".",
        "",
        "Tables: [runs.csv](runs.csv) / [runs.parquet](runs.parquet) (one row per run and robot), "
        "[summary.csv](summary.csv) (every numeric metric), [comparisons.csv](comparisons.csv).",
        "",
        *provenance_lines(index),
        "## Variants",
        "",
        "| variant | completed | not completed |",
        "|---|---|---|",
    ]
    for v in variants:
        done = sum(r["status"] == "completed" for r in runs if r["variant"] == v)
        total = sum(r["variant"] == v for r in runs)
        lines.append(f"| {v}{' (baseline)' if v == baseline else ''} | {done} | {total - done} |")
    failures = [r for r in runs if r["status"] != "completed"]
    if failures:
        lines += ["", "## Runs that did not complete", "", "| run | status | error |", "|---|---|---|"]
        lines += [f"| [{r['id']}]({r['folder']}) | {r['status']} | {(r['error'] or '').replace('|', '/')} |" for r in failures]
    lines += [
        "",
        "## Metrics",
        "",
        "Over the seeds of completed runs: mean, median, std, and Student's t 95 % CI of the mean.",
    ]
    for metric in metrics:
        rows = summary[summary["metric"] == metric]
        lines += ["", f"### `{metric}`", ""]
        if rows.empty:
            lines.append("No numeric value in any completed run's metrics.")
            continue
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", metric)
        swept = next(iter(index["config"].get("sweep") or {}), "")
        if sweep_plot(sweep_curves(table, metric, index), metric, swept, batch_dir / f"plots/sweep_{name}.png"):
            lines += [f"![{metric} against the sweep](plots/sweep_{name}.png)", ""]
        if box_plot(table, metric, variants, batch_dir / f"plots/{name}.png"):
            lines += [f"![{metric}](plots/{name}.png)", ""]
        lines += ["| variant | robot | n | mean | median | std | 95 % CI |", "|---|---|---|---|---|---|---|"]
        for r in rows.itertuples():
            ci = f"[{_fmt(r.ci95_low)}, {_fmt(r.ci95_high)}]"
            lines.append(f"| {r.variant} | {_fmt(r.robot)} | {r.n} | {_fmt(r.mean)} | {_fmt(r.median)} | {_fmt(r.std)} | {ci} |")
    lines += [
        "",
        "## Paired comparisons",
        "",
        "Runs paired by seed. Relative change = mean(variant - baseline) / mean(baseline); its CI: Student's t 95 % interval",
        "of the mean paired difference over the baseline's mean. p: two-sided Wilcoxon signed-rank test (scipy.stats.wilcoxon;",
        "with fewer than 6 pairs it cannot fall below 0.05).",
        "",
    ]
    if comparisons.empty:
        lines.append("No variant has completed runs paired with its baseline's.")
    else:
        lines += [
            "| variant | baseline | robot | metric | pairs | baseline mean | variant mean | relative change | 95 % CI | Wilcoxon p |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in comparisons.itertuples():
            lines.append(
                f"| {r.variant} | {r.baseline} | {_fmt(r.robot)} | `{r.metric}` | {r.n_pairs} | {_fmt(r.baseline_mean)} | {_fmt(r.variant_mean)} "
                f"| {_pct(r.relative_change)} | [{_pct(r.relative_ci95_low)}, {_pct(r.relative_ci95_high)}] | {_fmt(r.wilcoxon_p, 3)} |"
            )
    path = batch_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def provenance_lines(index: dict) -> list[str]:
    """The report's "Provenance" section: every command that ran part of the batch, with
    its code's commit, and how many of the completed runs each commit computed."""
    invocations = index.get("invocations") or []
    if not invocations:
        return ["## Provenance", "", "Not recorded (the batch was run before its index kept commits and commands).", ""]
    lines = ["## Provenance", "", "| started | command | commit |", "|---|---|---|"]
    for inv in invocations:
        lines.append(f"| {inv['started']} | `{inv['command']}` | {_commit(inv.get('git_commit'), inv.get('git_dirty'))} |")
    done = [r for r in index["runs"] if r["status"] == "completed"]
    per_commit: dict[str, int] = {}
    for r in done:
        key = _commit(r.get("git_commit"), r.get("git_dirty"))
        per_commit[key] = per_commit.get(key, 0) + 1
    lines += ["", "Completed runs by commit: " + (", ".join(f"{k}: {n}" for k, n in per_commit.items()) or "none") + ".", ""]
    return lines


def _commit(commit: str | None, dirty: bool | None) -> str:
    if commit is None:
        return "unknown"
    return f"`{commit[:10]}`" + (" with uncommitted changes" if dirty else "")


def _shown(path: str) -> str:
    """A path inside the repository relative to its root (reports are committed), others as they are."""
    try:
        return str(Path(path).resolve().relative_to(REPO))
    except ValueError:
        return path


def _pct(value: float) -> str:
    return "-" if value is None or math.isnan(value) else f"{100 * value:+.1f} %"


def _parquet_safe(table: pd.DataFrame) -> pd.DataFrame:
    """Object columns that mix strings with other values become strings (Parquet needs one type per column)."""
    out = table.copy()
    for column in out.columns[out.dtypes.map(pd.api.types.is_object_dtype)]:
        values = out[column].dropna()
        if values.map(type).nunique() > 1:
            out[column] = out[column].map(lambda x: None if x is None or (isinstance(x, float) and math.isnan(x)) else str(x))
    return out
