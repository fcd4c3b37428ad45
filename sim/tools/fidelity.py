"""The thesis's claims (ch. 8) against the committed experiments: the table of docs/fidelity.md.

    python -m sim.tools.fidelity                      # reads results/experiments/<name>/runs.parquet
    python -m sim.tools.fidelity --experiments DIR

Each claim names the experiment (a batch of ``scenarios/experiments/``, run into
``results/experiments/<name>/`` by ``make experiments``) and how its figure is computed
from the batch's tidy table (``runs.parquet``, committed with the report; see
``sim.batch.report``). The unit of every statistic is the seed: a run's robots share its
terrain and noise, so per-robot values are averaged within a seed first. Figures:

- a relative change (``variant`` against ``baseline``, paired by seed, as the batch
  reports): mean(variant - baseline) / mean(baseline), with the Student's t 95 % interval
  of the mean paired difference over the baseline's mean, and the two-sided Wilcoxon
  signed-rank p-value;
- a mean over seeds with its t interval (bandwidth, error per distance).

Verdict on a relative change, against the sign of the thesis's figure: ``reproduced``
when the interval lies entirely on the thesis's side of zero, ``same direction, not
significant`` when only the mean does, ``not reproduced`` otherwise; on an upper bound
(error per distance): ``reproduced`` when the interval's upper end is below it; on
bandwidth: ``reproduced`` when the submaps need less than 1/100 of the simulated camera's
raw stereo (the thesis's reduction is 1/670; its point is orders of magnitude, which the
simulated camera's smaller images bound from below); on a slow link: ``reproduced`` when
the interval of the submaps' 95th-percentile delivery latency lies below the mean time
between two of a robot's submaps (the link keeps up; no backlog builds).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from comms.load import LRU_GUPPY_PRO_F125B
from sim.batch.provenance import REPO
from sim.batch.report import mean_ci, paired_change

EXPERIMENTS = REPO / "results" / "experiments"


@dataclass(frozen=True)
class Figure:
    """One claim's measured figure: ``text`` for the table, ``verdict``, ``n`` seeds."""

    text: str
    verdict: str
    n: int


@dataclass(frozen=True)
class Claim:
    title: str
    section: str
    thesis: str
    experiment: str
    figure: Callable[[pd.DataFrame], Figure]


def _completed(table: pd.DataFrame) -> pd.DataFrame:
    return table[(table["status"] == "completed") & table["robot"].notna()]


def per_seed(table: pd.DataFrame, variant: str, value: Callable[[pd.DataFrame], pd.Series]) -> pd.Series:
    """``value`` of each row (run and robot) of ``variant``'s completed runs, averaged over each seed's robots."""
    rows = _completed(table)
    rows = rows[rows["variant"] == variant]
    return pd.Series(value(rows).to_numpy(float), index=rows["seed"].to_numpy()).groupby(level=0).mean()


def robots_per_run(table: pd.DataFrame) -> pd.Series:
    """For each completed row, how many robots its run has (to share a run's totals among them)."""
    return _completed(table).groupby("run")["robot"].transform("count")


def column(name: str) -> Callable[[pd.DataFrame], pd.Series]:
    return lambda rows: pd.to_numeric(rows[name], errors="coerce")


def relative_change(
    table: pd.DataFrame, variant: str, baseline: str, value: Callable[[pd.DataFrame], pd.Series], sign: int, neutral: str = "control"
) -> Figure:
    """``variant`` against ``baseline`` paired by seed; ``sign`` the thesis's (-1: lower is
    claimed; 0: no claim, the verdict is ``neutral``)."""
    a, b = per_seed(table, variant, value), per_seed(table, baseline, value)
    pairs = pd.concat([b.rename("base"), a.rename("variant")], axis=1).dropna()
    n = len(pairs)
    if n < 2:
        return Figure(f"{n} paired seed(s)", "not enough runs", n)
    _, b_mean, v_mean, rel, low, high, p = paired_change(pairs["base"].to_numpy(), pairs["variant"].to_numpy())
    if not math.isfinite(rel):
        return Figure(f"{v_mean:.3g} against {b_mean:.3g}", "undefined (baseline mean 0)", n)
    if sign == 0:
        verdict = neutral
    elif sign * low > 0 and sign * high > 0:
        verdict = "reproduced"
    elif sign * rel > 0:
        verdict = "same direction, not significant"
    else:
        verdict = "not reproduced"
    text = f"{100 * rel:+.1f} % [{100 * low:+.1f}, {100 * high:+.1f}] ({v_mean:.3g} against {b_mean:.3g}; p = {p:.2g})"
    return Figure(text, verdict, n)


def mean_over_seeds(values: pd.Series) -> tuple[float, float, float, int]:
    v = values.dropna().to_numpy(float)
    low, high = mean_ci(v)
    return float(np.mean(v)) if len(v) else math.nan, low, high, len(v)


def error_per_distance(table: pd.DataFrame, variant: str, bound_percent: float) -> Figure:
    """Mean online SLAM error (``slam.ate_m.mean``) over the distance driven, in percent."""
    mean, low, high, n = mean_over_seeds(per_seed(table, variant, lambda r: 100 * column("slam.ate_m.mean")(r) / column("slam.distance_m")(r)))
    if n < 2:
        return Figure(f"{n} seed(s)", "not enough runs", n)
    distance, *_ = mean_over_seeds(per_seed(table, variant, column("slam.distance_m")))
    verdict = "reproduced" if high < bound_percent else "not reproduced"
    return Figure(f"{mean:.2f} % [{low:.2f}, {high:.2f}] of {distance:.0f} m", verdict, n)


def bandwidth(table: pd.DataFrame, variant: str) -> Figure:
    """Submap bytes per second and robot against the raw stereo streams, at the simulated
    camera and at the LRU's (comms.load.LRU_GUPPY_PRO_F125B)."""
    robots = robots_per_run(table)

    def per_robot(name: str) -> Callable[[pd.DataFrame], pd.Series]:
        return lambda rows: column(name)(rows) / robots.loc[rows.index]

    submap, s_low, s_high, n = mean_over_seeds(per_seed(table, variant, per_robot("comms.by_kind.submap.offered_Bps")))
    raw, *_ = mean_over_seeds(per_seed(table, variant, per_robot("comms.raw_equivalent_Bps")))
    if n < 2:
        return Figure(f"{n} seed(s)", "not enough runs", n)
    thesis_raw = LRU_GUPPY_PRO_F125B.bytes_per_s
    text = (
        f"{submap / 1e3:.1f} kB/s [{s_low / 1e3:.1f}, {s_high / 1e3:.1f}] per robot: 1/{raw / submap:.0f} of the simulated camera's "
        f"{raw / 1e3:.0f} kB/s, 1/{thesis_raw / submap:.0f} of the LRU camera's {thesis_raw / 1e6:.1f} MB/s"
    )
    return Figure(text, "reproduced" if submap < raw / 100 else "not reproduced", n)


def link_keeps_up(table: pd.DataFrame, variant: str) -> Figure:
    """The submaps' 95th-percentile delivery latency against the mean time between two of
    a robot's submaps (``comms.duration_s`` over the submaps each robot offered)."""
    robots = robots_per_run(table)

    def interval(rows: pd.DataFrame) -> pd.Series:
        return column("comms.duration_s")(rows) * robots.loc[rows.index] / column("comms.by_kind.submap.offered_msgs")(rows)

    latency, low, high, n = mean_over_seeds(per_seed(table, variant, column("comms.by_kind.submap.latency_s.p95")))
    between, *_ = mean_over_seeds(per_seed(table, variant, interval))
    if n < 2:
        return Figure(f"{n} seed(s)", "not enough runs", n)
    text = f"submap latency p95 {latency:.1f} s [{low:.1f}, {high:.1f}] against {between:.0f} s between a robot's submaps"
    return Figure(text, "reproduced" if high < between else "not reproduced", n)


CLAIMS = [
    Claim(
        "local-reference topology beats sequential odometry (mean 3D error, online)",
        "8.2.2, Table 8.6",
        "-15 % (mean of three experiments)",
        "graph_topology",
        lambda t: relative_change(t, "local_reference", "sequential", column("slam.ate_m.mean"), -1),
    ),
    Claim(
        "4D matching finds more matches than 6D",
        "8.1.2, Fig. 8.8",
        "+40 %",
        "matching_4d_6d",
        lambda t: relative_change(t, "match_4d", "match_6d", column("loop_closures.team.matches"), +1),
    ),
    Claim(
        "4D+6D matching finds more matches than 6D",
        "8.1.2, Fig. 8.8",
        "more (between 6D and 4D)",
        "matching_4d_6d",
        lambda t: relative_change(t, "match_4d_6d", "match_6d", column("loop_closures.team.matches"), +1),
    ),
    Claim(
        "learned marker model (LUT + online) beats constant (SLAM ATE RMSE)",
        "8.1.3, Table 8.3",
        "-71 % (0.14 against 0.48 m)",
        "marker_uncertainty",
        lambda t: relative_change(t, "lut_online", "constant", column("slam.ate_m.rmse"), -1),
    ),
    Claim(
        "learned marker model (LUT + online) beats quadratic (SLAM ATE RMSE)",
        "8.1.3, Table 8.3",
        "-18 % (0.14 against 0.17 m)",
        "marker_uncertainty",
        lambda t: relative_change(t, "lut_online", "quadratic", column("slam.ate_m.rmse"), -1),
    ),
    Claim(
        "multi-robot beats single-robot SLAM (mean 3D error, online)",
        "8.3.1, Table 8.7",
        "-32 % (8.3.2, Table 8.9: -79 %)",
        "multi_vs_single",
        lambda t: _team_against_alone(t, "slam.ate_m.mean"),
    ),
    Claim(
        "control for the row above: the filter alone (no collaboration in it), team against alone",
        "",
        "0 (the filter does not use the team)",
        "multi_vs_single",
        lambda t: _team_against_alone(t, "filter.ate_m.mean", sign=0),
    ),
    Claim(
        "submaps cut bandwidth against raw stereo",
        "8.4",
        "58 KB/s for two rovers (700 KB submaps at 0.04 Hz each) against 38.75 MB/s of raw stereo",
        "multi_vs_single",
        lambda t: bandwidth(t, "team"),
    ),
    Claim(
        "submaps keep up with a low-bandwidth link (64 kbit/s per direction, GPRS class)",
        "8.4",
        "58 KB/s 'allows a transmission over low-bandwidth connections like [...] GSM'",
        "bandwidth",
        lambda t: link_keeps_up(t, "link_64k"),
    ),
    Claim(
        "what the 64 kbit/s link costs: mean 3D error (online) against the 20 Mbit/s WiFi",
        "8.4",
        "no figure (implied: little)",
        "bandwidth",
        lambda t: relative_change(t, "link_64k", "wifi_20M", column("slam.ate_m.mean"), 0, neutral="measured, no claim"),
    ),
    Claim(
        "SLAM error below 0.5 % of the distance (mean 3D error / distance)",
        "8.3.2, 8.5",
        "< 0.5 % (0.19 % in 8.3.2)",
        "multi_vs_single",
        lambda t: error_per_distance(t, "team", 0.5),
    ),
]


def _team_against_alone(table: pd.DataFrame, metric: str, sign: int = -1) -> Figure:
    """Each rover's ``metric`` in the team against alone (``<robot>_alone`` variants),
    averaged over the rovers per seed."""
    alone = {v.removesuffix("_alone") for v in table["variant"].unique() if v.endswith("_alone")}
    rows = _completed(table)
    team = rows[(rows["variant"] == "team") & rows["robot"].isin(alone)]
    single = rows[rows["variant"].str.endswith("_alone") & (rows["robot"] + "_alone" == rows["variant"])]
    both = pd.concat([team, single.assign(variant="alone")])
    # a seed counts when every rover has both runs
    complete = both.groupby("seed")["run"].nunique() == 1 + len(alone)
    both = both[both["seed"].isin(complete[complete].index)]
    return relative_change(both, "team", "alone", column(metric), sign)


def table_rows(experiments: Path) -> list[str]:
    """The Markdown rows of docs/fidelity.md's table, one per claim."""
    rows = ["| claim | thesis | experiment | ours: mean [95 % CI] | seeds | verdict |", "|---|---|---|---|---|---|"]
    for claim in CLAIMS:
        path = experiments / claim.experiment / "runs.parquet"
        if path.is_file():
            figure = claim.figure(pd.read_parquet(path))
            ours, n, verdict = figure.text, str(figure.n), figure.verdict
        else:
            ours, n, verdict = "not run yet", "0", "-"
        where = f" ({claim.section})" if claim.section else ""
        rows.append(f"| {claim.title}{where} | {claim.thesis} | `{claim.experiment}` | {ours} | {n} | {verdict} |")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--experiments", type=Path, default=EXPERIMENTS, help="folder of the experiment batches")
    args = parser.parse_args(argv)
    print("\n".join(table_rows(args.experiments)))


if __name__ == "__main__":
    main()
