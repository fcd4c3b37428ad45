"""Submap matching benchmark (thesis 8.1, 8.1.2): time per stage and the share of
correct matches, for the matching modes (4D, 6D, 4D+6D) and keypoint selections, on
submaps built from rendered stereo along crossing paths through a scene of
:mod:`sim.tools.rocky_scene` (rocky, or rough ground with few rocks), each pair
against its true transform.

    python -m sim.tools.match_bench [--paths N] [--scene rocky rough] [--mode 4d 6d 4d+6d]
        [--keypoints obstacles geometry both] [--voting hough3d yaw_sweep]
        [--descriptor-resolution 0 0.05] [--descriptor fpfh spin]
        [--max-descriptor-distance 0.2 0.25] [--out results/match_bench.json]

Thesis (8.1): keypoints and features 0.39 s per map, feature matching 3.07 s per pair,
Hough voting 0.02 s, ICP 2.38 s. Stage names here: ``keypoints`` (suitability and
keypoints, per submap), ``features`` (normals, descriptors, reference frames, per suitable
submap, computed on first use), and per pair ``correspondences``, ``hough``, ``ransac``
(hypotheses and their checks) and ``icp`` (pairs that reach it).

The descriptors' quality, over the pairs that overlap under the truth: the share of
keypoints with a true partner (within ``PARTNER_M``) that find it among their
``nearest`` most similar descriptors (6.1.2, before the distance threshold), the right
correspondences (within ``CORRECT_M`` under the truth) the threshold keeps and drops,
and the share of all correspondences that are right.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import time
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sim.tools.rocky_scene import SCENES, RockyScene
from slam.lie import yaw_of
from slam.matcher import Descriptor, Keypoints, KeypointSelection, MatcherParams, MatchMode, Voting, correspondences, match_pair, prepare
from slam.submap import Submap

# Straight drives through the 20 m rocky scene: (start, end) xy in metres.
PATHS = [
    ((-3.0, -0.4), (2.0, -0.4)),
    ((-2.0, 1.2), (2.5, -0.8)),
    ((2.0, -2.5), (-2.5, -1.0)),
    ((0.0, -3.5), (0.5, 1.5)),
    ((-1.0, 2.5), (3.5, 1.5)),
    ((3.0, 1.0), (-1.5, 0.0)),
    ((5.0, -8.0), (8.0, -3.0)),
    ((-8.0, 4.0), (-3.0, 5.0)),
]
CORRECT_M, CORRECT_DEG = 0.3, 3.0  # a match this close to the truth counts as correct
PARTNER_M = 0.2  # a keypoint of the other submap this close under the truth is a keypoint's true partner
MIN_PARTNERS = 20  # pairs with fewer keypoints that have a partner do not count as overlapping


def build(paths: int, scene: str = "rocky") -> list[tuple[Submap, np.ndarray]]:
    """Submaps of the first ``paths`` drives through ``scene`` with their true origins."""
    rendered = RockyScene(scene=scene)
    try:
        return [rendered.submap("bench", i, *PATHS[i]) for i in range(paths)]
    finally:
        rendered.close()


def descriptor_quality(a: Keypoints, b: Keypoints, T_a_b: np.ndarray, params: MatcherParams) -> dict[str, int] | None:
    """Counts for the module docstring's descriptor quality on one pair with features (None: the pair does not
    overlap): keypoints of ``a`` with a true partner in ``b`` and those of them that find it among their ``nearest``
    descriptors; right correspondences with and without ``max_descriptor_distance``; correspondences kept."""
    pb = b.points @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    gap, partner = cKDTree(pb).query(a.points)
    has = gap < PARTNER_M
    if has.sum() < MIN_PARTNERS:
        return None
    k = min(params.nearest, len(b.points))
    _, idx = cKDTree(b.descriptors).query(a.descriptors[has], k=k)
    found = (idx.reshape(int(has.sum()), k) == partner[has][:, None]).any(axis=1)

    def right(corr: np.ndarray) -> int:
        return int((np.linalg.norm(a.points[corr[:, 0]] - pb[corr[:, 1]], axis=1) < CORRECT_M).sum())

    kept = correspondences(a, b, params)
    unbounded = correspondences(a, b, dataclasses.replace(params, max_descriptor_distance=1.0))
    return {"partners": int(has.sum()), "partners_found": int(found.sum()), "right_kept": right(kept),
            "right_unbounded": right(unbounded), "kept": len(kept)}


def evaluate(built: list[tuple[Submap, np.ndarray]], params: MatcherParams) -> dict:
    """Every pair of ``built`` matched without a prior, against its true transform."""
    t0 = time.perf_counter()
    kps = [prepare(s, params) for s, _ in built]
    keypoint_s = (time.perf_counter() - t0) / len(built)
    stages: dict[str, list[float]] = {"keypoints": [keypoint_s]}
    correct = wrong = rejected = 0
    errors = []
    quality: Counter = Counter()
    for i in range(len(built)):
        for j in range(i + 1, len(built)):
            if isinstance(kps[i], str) or isinstance(kps[j], str):
                continue
            res = match_pair(kps[i], kps[j], params)
            counts = descriptor_quality(kps[i], kps[j], np.linalg.solve(built[i][1], built[j][1]), params)
            quality.update({"overlapping_pairs": 1, **counts} if counts else {})
            for k, v in res.timings.items():
                stages.setdefault(k, []).append(v)
            if not res.success:
                rejected += 1
                continue
            D = np.linalg.solve(np.linalg.solve(built[i][1], built[j][1]), res.T_a_b)
            e_t, e_yaw = float(np.linalg.norm(D[:3, 3])), math.degrees(abs(yaw_of(D[:3, :3])))
            ok = e_t < CORRECT_M and e_yaw < CORRECT_DEG
            correct += ok
            wrong += not ok
            errors.append((e_t, e_yaw))
    suitable = [k for k in kps if not isinstance(k, str)]
    stages["features"] = [sum(stages.get("features", [0.0])) / max(len(suitable), 1)]  # once per submap, on first use
    e = np.asarray(errors).reshape(-1, 2)
    return {
        "submaps": len(built),
        "suitable": len(suitable),
        "unsuitable": dict(Counter(k for k in kps if isinstance(k, str))),
        "keypoints_median": float(np.median([len(k.points) for k in suitable])) if suitable else 0.0,
        "pairs_tried": correct + wrong + rejected,
        "correct": correct,
        "wrong": wrong,
        "rejected": rejected,
        "translation_error_m_median": float(np.median(e[:, 0])) if len(e) else None,
        "yaw_error_deg_median": float(np.median(e[:, 1])) if len(e) else None,
        "descriptors": {
            "overlapping_pairs": quality["overlapping_pairs"],
            "partner_among_nearest": quality["partners_found"] / quality["partners"] if quality["partners"] else None,
            "right_correspondences": quality["right_kept"],
            "right_dropped_by_distance": quality["right_unbounded"] - quality["right_kept"],
            "right_share": quality["right_kept"] / quality["kept"] if quality["kept"] else None,
        },
        "stage_s": {k: {"mean": float(np.mean(v)), "max": float(np.max(v))} for k, v in stages.items()},
    }


def run(
    paths: int,
    scenes: list[str],
    modes: list[str],
    keypoints: list[str],
    votings: list[str] | None = None,
    descriptor_resolutions: list[float] | None = None,
    descriptors: list[str] | None = None,
    max_descriptor_distances: list[float] | None = None,
) -> dict:
    """Every combination, keyed ``"scene keypoints mode"`` and, where more than the default
    is asked for, the voting, the descriptor, the descriptors' cloud resolution and their
    distance threshold."""
    votings = votings or [MatcherParams.voting.value]
    resolutions = descriptor_resolutions or [MatcherParams.descriptor_resolution_m]
    kinds = descriptors or [MatcherParams.descriptor.value]
    thresholds = max_descriptor_distances or [MatcherParams.max_descriptor_distance]
    out = {}
    for scene in scenes:
        built = build(paths, scene)
        for kp, mode, voting, kind, res, threshold in itertools.product(keypoints, modes, votings, kinds, resolutions, thresholds):
            name = f"{scene} {kp} {mode}"
            if len(votings) > 1 or voting != MatcherParams.voting.value:
                name += f" {voting}"
            if len(kinds) > 1 or kind != MatcherParams.descriptor.value:
                name += f" {kind}"
            if len(resolutions) > 1 or res != MatcherParams.descriptor_resolution_m:
                name += f" descriptors@{res:g}m"
            if len(thresholds) > 1 or threshold != MatcherParams.max_descriptor_distance:
                name += f" distance<={threshold:g}"
            params = MatcherParams(
                mode=mode, keypoints=kp, voting=voting, descriptor=kind, descriptor_resolution_m=res, max_descriptor_distance=threshold
            )
            out[name] = evaluate(built, params)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paths", type=int, default=len(PATHS), help=f"submaps to build (at most {len(PATHS)})")
    ap.add_argument("--scene", nargs="+", choices=sorted(SCENES), default=["rocky"], help="terrains of sim.tools.rocky_scene")
    ap.add_argument("--mode", nargs="+", choices=[m.value for m in MatchMode], default=[m.value for m in MatchMode])
    ap.add_argument("--keypoints", nargs="+", choices=[k.value for k in KeypointSelection], default=[KeypointSelection.OBSTACLES.value])
    ap.add_argument("--voting", nargs="+", choices=[v.value for v in Voting], default=None)
    ap.add_argument(
        "--descriptor-resolution", nargs="+", type=float, default=None, metavar="M",
        help="slam.matching.descriptor_resolution_m values (0: FPFH on the full cloud)",
    )
    ap.add_argument("--descriptor", nargs="+", choices=[d.value for d in Descriptor], default=None)
    ap.add_argument(
        "--max-descriptor-distance", nargs="+", type=float, default=None, metavar="D",
        help="slam.matching.max_descriptor_distance values, in (0, 1]",
    )
    ap.add_argument("--out", type=Path, default=Path("results/match_bench.json"))
    args = ap.parse_args(argv)
    if not 2 <= args.paths <= len(PATHS):
        ap.error(f"--paths must be between 2 and {len(PATHS)}")
    if args.descriptor_resolution and min(args.descriptor_resolution) < 0:
        ap.error("--descriptor-resolution must be >= 0")
    if args.max_descriptor_distance and not all(0 < d <= 1 for d in args.max_descriptor_distance):
        ap.error("--max-descriptor-distance must be in (0, 1]")
    result = run(
        args.paths, args.scene, args.mode, args.keypoints, args.voting, args.descriptor_resolution, args.descriptor, args.max_descriptor_distance
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    for name, r in result.items():
        stages = ", ".join(f"{k} {v['mean']:.3f} s" for k, v in r["stage_s"].items())
        print(
            f"{name}: {r['suitable']}/{r['submaps']} submaps suitable {r['unsuitable']}, {r['keypoints_median']:.0f} keypoints; "
            f"{r['pairs_tried']} pairs: {r['correct']} correct, "
            f"{r['wrong']} wrong, {r['rejected']} rejected; median error {r['translation_error_m_median']} m, "
            f"{r['yaw_error_deg_median']} deg; per stage: {stages}"
        )
        d = r["descriptors"]
        if d["overlapping_pairs"]:
            print(
                f"  descriptors on {d['overlapping_pairs']} overlapping pairs: true partner among the nearest {d['partner_among_nearest']:.1%}; "
                f"{d['right_correspondences']} right correspondences ({d['right_share']:.1%} of those kept), "
                f"{d['right_dropped_by_distance']} right ones dropped by the distance threshold"
            )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
