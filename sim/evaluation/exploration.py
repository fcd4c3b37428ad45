"""How much of the target region the team explored, against the truth (thesis 9.3).

A region cell counts as explored once a point of an exploring robot's own submaps lies
in it, every submap placed on its true origin (the robot's true pose at the start of
its local frame, :func:`sim.evaluation.trajectory.frame_origins_truth`): the area the
robots' cameras truly mapped, whatever their localisation error (which
``robots.<name>.map.quality`` and ``slam`` report). A submap counts from its end time
(the active one at the run's end), so coverage over time steps when submaps finish.
The robots' own belief (the coverage their explorers computed on their maps, in the
mission frame as they believed it) is reported beside it.

``metrics.json`` ``exploration``: ``coverage`` (the team's, 0-1), ``explored_m2``,
``region_m2``, ``coverage_over_time`` ([t, coverage] pairs), ``distance_m`` (the explorers'
true path lengths together) and per robot its own ``coverage`` (and over time), its
``believed_coverage`` (at its explorer's last answer, ``believed_t``), goals chosen,
reached, failed and withdrawn (given up for a peer's), revisit goals (active loop
closing) with the information each was expected to bring, how often its head turned to a
peer (active mutual observation), and why and when it stopped exploring.
``exploration.png`` draws coverage over time and the explored cells by robot with the
true paths and goals.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sim.evaluation import trajectory
from sim.evaluation.inputs import ExplorerInput, TeamTruth
from slam.lie import apply_planar
from slam.navigation.exploration import RegionGrid


def _placed_cells(robot: ExplorerInput, grid: RegionGrid, truth: trajectory.Trajectory) -> list[tuple[float, np.ndarray]]:
    """(end time, explored grid) of each of the robot's submaps on its true origin."""
    origins = trajectory.frame_origins_truth(robot.start_t, robot.switch_times, truth)
    out = []
    for submap in robot.submaps:
        T = origins.get(submap.frame_index)
        if T is None or len(submap.points) == 0:
            continue
        out.append((submap.t_end, grid.mark(apply_planar(T, submap.points))))
    return out


def exploration_section(region, cell_m: float, robots: dict[str, ExplorerInput], truth: TeamTruth) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``exploration`` metrics and what :func:`plot_exploration` draws."""
    grid = RegionGrid(region, cell_m)
    cell_area = cell_m**2
    events, first_by = [], np.full(grid.shape, -1)
    section: dict[str, Any] = {"region_m2": float(grid.inside.sum() * cell_area), "cell_m": cell_m, "robots": {}}
    names = sorted(robots)
    for k, name in enumerate(names):
        robot, path = robots[name], truth.of(name)
        cells = _placed_cells(robot, grid, path)
        own = np.zeros(grid.shape, bool)
        own_series = []
        for t, mark in sorted(cells, key=lambda c: c[0]):
            own |= mark
            events.append((t, k, mark))
            own_series.append([round(float(t), 3), grid.coverage(own)])
        goals = robot.waypoints[robot.scripted :]
        last = robot.goals[-1] if robot.goals else None
        section["robots"][name] = {
            "coverage": grid.coverage(own),
            "coverage_over_time": own_series,
            "believed_coverage": None if last is None else last[1].coverage,
            "believed_t": None if last is None else round(last[0], 3),
            "goals": len(goals),
            "goals_reached": sum(w.status == "reached" for w in goals),
            "goals_failed": sum(w.status == "failed" and w.reason != "withdrawn" for w in goals),
            "goals_withdrawn": sum(w.reason == "withdrawn" for w in goals),  # given up for a peer's (sim/run/onboard.py)
            "revisits": sum(g.reason == "revisit" for _, g in robot.goals),  # active loop closing
            "revisit_information_nats": [round(g.information, 3) for _, g in robot.goals if g.reason == "revisit"],
            "observations": len(robot.observations),  # times its head turned to a peer (active mutual observation)
            "finished": None if last is None or not last[1].finished else last[1].reason,
            "finished_t": None if last is None or not last[1].finished else round(last[0], 3),
        }
    team = np.zeros(grid.shape, bool)
    series = []
    for t, k, mark in sorted(events, key=lambda e: e[0]):
        first_by[mark & ~team] = k
        team |= mark
        series.append([round(float(t), 3), grid.coverage(team)])
    section.update(
        coverage=grid.coverage(team),
        explored_m2=float((team & grid.inside).sum() * cell_area),
        coverage_over_time=series,
        distance_m=float(sum(trajectory.path_length(truth.of(n)) for n in names)),
    )
    believed = {name: [(t, g.coverage) for t, g in robots[name].goals] for name in names}
    plot = {"grid": grid, "first_by": first_by, "names": names, "series": series, "believed": believed, "robots": robots}
    return section, plot


def plot_exploration(plot: dict[str, Any], truth: TeamTruth, path: Path) -> None:
    """Coverage over time (the team's against the truth, each robot's belief dashed) and the
    explored region cells coloured by the robot that mapped them first, with true paths and goals."""
    grid, names = plot["grid"], plot["names"]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1, 1.3]})
    colors = plt.get_cmap("tab10")
    if plot["series"]:
        t, c = np.array(plot["series"]).T
        ax_t.step(t, c, where="post", color="k", label="team (truth)")
    for k, name in enumerate(names):
        if plot["believed"][name]:
            tb, cb = np.array(plot["believed"][name]).T
            ax_t.plot(tb, cb, "--", color=colors(k), label=f"{name} (its belief)")
    ax_t.set(xlabel="t (s)", ylabel="coverage of the target region", ylim=(0, 1), title="explored fraction of the region")
    ax_t.grid(alpha=0.3)
    ax_t.legend(loc="upper left")
    image = np.full((*grid.shape, 4), 1.0)
    image[grid.inside] = (0.85, 0.85, 0.85, 1.0)
    for k in range(len(names)):
        rgba = np.array(colors(k))
        rgba[3] = 0.45
        image[plot["first_by"] == k] = rgba
    extent = (grid.lo[0], grid.lo[0] + grid.shape[0] * grid.cell_m, grid.lo[1], grid.lo[1] + grid.shape[1] * grid.cell_m)
    ax_m.imshow(image.transpose(1, 0, 2), origin="lower", extent=extent, interpolation="nearest")
    poly = np.vstack([grid.polygon, grid.polygon[:1]])
    ax_m.plot(poly[:, 0], poly[:, 1], "r-", lw=1.5, label="target region")
    for k, name in enumerate(names):
        p = truth.of(name).T[:, :2, 3]
        if len(p):
            ax_m.plot(p[:, 0], p[:, 1], "-", color=colors(k), lw=1.2, label=f"{name} (true path)")
        robot = plot["robots"][name]
        for w in robot.waypoints[robot.scripted :]:
            marker = {"reached": "o", "failed": "x"}.get(w.status, "s")
            ax_m.plot(*w.xy, marker, color=colors(k), ms=6, mfc="none")
    ax_m.set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title="explored cells by robot; goals: o reached, x failed, s pending")
    ax_m.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
