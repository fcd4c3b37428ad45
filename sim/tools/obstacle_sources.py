"""Where a run's obstacle flags go wrong: the classification of thesis 5.1.1 taken apart.

Runs a scenario and scores every robot's mapped images at their cameras' true poses three
ways (each as ``map.classification_images``, :mod:`sim.evaluation.image_classification`):

- **as run**: the robot's own flags, classified on its believed camera pose (filter
  attitude, calibration and head encoders as the robot knows them);
- **at the true pose**: the same stereo depth classified again on the camera's true pose:
  what the believed attitude costs is the difference to *as run*;
- **on true depth**: the rendered depth classified on the true pose: the criterion itself
  (eq. 5.1-5.4 with the thesis's error margin ``Δd``) against the truth, which applies the
  same steps and steep drops without a margin (``sim.evaluation.map_quality``). Its recall
  is the criterion's without stereo error (noise can lift a marginal cell over the
  threshold, so SGBM's may be higher, at a cost in precision); its misses are split into
  steep-drop-only cells (with the median ratio of drop to ``h_max``) and step cells.

It also counts the false cells *as run* within ``--near-robot`` metres of another robot
(stereo places pixels on a robot's silhouette too near, outside the scores' robot margin,
and their step windows flag the ground around them).

    python -m sim.tools.obstacle_sources scenarios/etna_two_rovers.yaml --seed 3 --set duration_s=330

Needs the true depth of every VO frame, so it sets ``robots.*.camera.depth_ground_truth_every=1``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from sim.evaluation.image_classification import ImageCells, MappedImage, world_xy
from sim.evaluation.map_quality import ObstacleScore, true_step_and_drop
from sim.run.runner import Run
from sim.scenario import ScenarioError, load_scenario
from sim.world.terrain import Terrain
from slam.obstacles import ObstacleParams, classified_pixels, classify_depth

WAYS = ("as_run", "true_pose", "true_depth")


class ObstacleSources:
    """Per robot, the mapped images scored the three ways of the module docstring."""

    def __init__(self, near_robot_m: float = 1.0):
        self.near_robot_m = near_robot_m
        self.cells: dict[str, dict[str, ImageCells]] = {}
        self.near_robot: dict[str, set[tuple[int, int]]] = {}
        self.without_truth: dict[str, int] = {}

    def add(self, image: MappedImage) -> None:
        cal, params = image.calibration, image.params
        if image.robot not in self.cells:
            self.cells[image.robot] = {way: ImageCells(cal, params) for way in WAYS}
            self.near_robot[image.robot] = set()
            self.without_truth[image.robot] = 0
        cells = self.cells[image.robot]
        cells["as_run"].add(image.depth, image.obstacle, image.T_world_cam, image.others, image.true_depth)
        at_true_pose = classify_depth(image.depth, cal, image.T_world_cam, params).pixel_obstacles
        cells["true_pose"].add(image.depth, at_true_pose, image.T_world_cam, image.others, image.true_depth)
        if image.true_depth is None:
            self.without_truth[image.robot] += 1
        else:
            flags = classify_depth(image.true_depth, cal, image.T_world_cam, params).pixel_obstacles
            cells["true_depth"].add(image.true_depth, flags, image.T_world_cam, image.others)
        if image.others:
            flagged = image.obstacle & classified_pixels(image.depth, cal, params)
            xy = world_xy(image.depth, flagged, cal, image.T_world_cam)
            near = np.zeros(len(xy), bool)
            for centre, radius in image.others:
                near |= np.hypot(*(xy - centre).T) < radius + self.near_robot_m
            keys = np.floor(xy[near] / params.resolution_m).astype(np.int64)
            self.near_robot[image.robot].update(map(tuple, keys.tolist()))

    def report(self, terrain: Terrain) -> dict[str, dict]:
        out = {}
        for robot, cells in self.cells.items():
            params = cells["as_run"].params
            scores = {way: cells[way].score(terrain) for way in WAYS}
            entry = {way: _score_dict(scores[way]) for way in WAYS}
            entry["images"] = cells["as_run"].images
            entry["images_without_true_depth"] = self.without_truth[robot]
            fp = np.floor(scores["as_run"].fp_xy / params.resolution_m).astype(np.int64)
            entry["as_run"]["false_cells_near_robot"] = int(sum(tuple(c) in self.near_robot[robot] for c in fp.tolist()))
            entry["true_depth"]["missed"] = _missed(scores["true_depth"].missed_xy, terrain, params)
            out[robot] = entry
        return out


def _score_dict(score: ObstacleScore) -> dict:
    return {
        "precision": score.precision,
        "recall": score.recall,
        "flagged_cells": score.mapped_cells,
        "true_cells_seen": score.true_cells_seen,
        "false_cells": len(score.fp_xy),
        "missed_cells": len(score.missed_xy),
    }


def _missed(xy: np.ndarray, terrain: Terrain, params: ObstacleParams) -> dict:
    """The missed true cells split into step cells (window height difference above ``h_max``,
    with the median difference) and steep-drop-only cells (with the median ratio of drop to
    ``h_max``), from the true surface as ``sim.evaluation.map_quality.true_obstacle_cells``
    samples it (:func:`sim.evaluation.map_quality.true_step_and_drop`)."""
    if len(xy) == 0:
        return {"cells": 0, "steep_drop_only": 0, "drop_ratio_median": None, "step_h_diff_median_m": None}
    keys = np.floor(xy / params.resolution_m).astype(np.int64)
    lo = keys.min(axis=0)
    h_diff, ratio = true_step_and_drop(terrain, lo, tuple(int(v) for v in keys.max(axis=0) - lo + 1), params)
    h_diff, ratio = h_diff[tuple((keys - lo).T)], ratio[tuple((keys - lo).T)]
    step = h_diff > params.step_height_m
    drop_only = ~step & (ratio > 1)
    return {
        "cells": len(keys),
        "steep_drop_only": int(drop_only.sum()),
        "drop_ratio_median": float(np.median(ratio[drop_only])) if drop_only.any() else None,
        "step_h_diff_median_m": float(np.median(h_diff[step])) if step.any() else None,
    }


def _pr(entry: dict) -> str:
    def f(v):
        return "-" if v is None else f"{v:.2f}"

    return f"{f(entry['precision'])} / {f(entry['recall'])} ({entry['flagged_cells']} / {entry['true_cells_seen']})"


def markdown(report: dict[str, dict], near_robot_m: float = 1.0) -> str:
    lines = [
        "| robot | as run: P / R (flagged / true cells) | at the true pose | on true depth (the criterion without stereo error) "
        f"| false cells as run, within {near_robot_m:g} m of a robot "
        "| missed on true depth: steep drops only (median drop / h_max), steps (median h_diff) |",
        "|---|---|---|---|---|---|",
    ]
    for robot, e in report.items():
        m = e["true_depth"]["missed"]
        ratio = "-" if m["drop_ratio_median"] is None else f"{m['drop_ratio_median']:.2f}"
        steps = m["cells"] - m["steep_drop_only"]
        h_diff = "-" if m["step_h_diff_median_m"] is None else f"{m['step_h_diff_median_m']:.2f} m"
        lines.append(
            f"| {robot} | {_pr(e['as_run'])} | {_pr(e['true_pose'])} | {_pr(e['true_depth'])} "
            f"| {e['as_run']['false_cells_near_robot']} of {e['as_run']['false_cells']} "
            f"| {m['steep_drop_only']} of {m['cells']} ({ratio}), {steps} ({h_diff}) |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", type=Path)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--near-robot", type=float, default=1.0, help="metres beyond a robot's body radius (default 1.0)")
    parser.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    args = parser.parse_args(argv)
    if not (args.near_robot >= 0 and math.isfinite(args.near_robot)):
        parser.error(f"--near-robot must be a finite distance >= 0, got {args.near_robot}")
    overrides = [*args.overrides, "output.recording=false", "robots.*.camera.depth_ground_truth_every=1"]
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    try:
        scenario = load_scenario(args.scenario, overrides)
    except ScenarioError as exc:
        print(f"{exc.source}: invalid scenario", *(f"  - {p}" for p in exc.problems), sep="\n", file=sys.stderr)
        return 2
    sources = ObstacleSources(args.near_robot)
    run = Run(scenario, image_observer=sources.add)
    start = time.perf_counter()
    print(f"running {args.scenario} (seed {scenario.seed}, {scenario.duration_s:g} s simulated) ...", file=sys.stderr)
    run.execute()
    print(f"done in {time.perf_counter() - start:.0f} s wall", file=sys.stderr)
    report = sources.report(run.terrain)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        record = {"scenario": str(args.scenario), "seed": scenario.seed, "overrides": args.overrides, "robots": report}
        args.out.write_text(json.dumps(record, indent=2))
    print(markdown(report, args.near_robot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
