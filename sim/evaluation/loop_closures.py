"""Loop closures against ground truth (thesis 8.1.2, 8.1.3): every submap match a robot
computed and every detection it made, compared with the true transform; counts per
outcome, wrong matches (off by more than ``WRONG_MATCH_M`` or ``WRONG_MATCH_DEG``);
calibration of the predicted uncertainty (the share of errors within 1, 2
and 3 predicted sigmas). Goes into ``metrics.json`` under ``loop_closures``; reads a
:class:`sim.evaluation.inputs.ClosureInput` per robot.

A submap origin's truth is the robot's true pose when the filter switched into that
local frame (frame 0: the filter's start), gravity-aligned as the origins are (4.1.2).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from sim.evaluation import trajectory
from sim.evaluation.inputs import ClosureInput, TeamTruth
from sim.evaluation.online_slam import detection_truth
from sim.evaluation.statistics import StatisticsType, statistics
from slam.lie import rotation_angle, so3_log, yaw_of

SIGMA_LEVELS = (1, 2, 3)
WRONG_MATCH_M = 0.3  # an accepted match off by more than this ...
WRONG_MATCH_DEG = 3.0  # ... or by more than this (rotation) is wrong
ERROR_STATISTICS = (StatisticsType.MEDIAN, StatisticsType.P90, StatisticsType.MAX)


def calibration(normalised: np.ndarray) -> dict[str, float]:
    """Share of |error| / sigma at most 1, 2, 3 (a Gaussian: 68 / 95 / 99.7 % per component)."""
    a = np.abs(np.asarray(normalised, float))
    return {f"within_{k}_sigma": float(np.mean(a <= k)) for k in SIGMA_LEVELS} if a.size else {}


def match_metrics(closures: ClosureInput, origins: dict[str, dict[int, np.ndarray]]) -> dict[str, Any] | None:
    """This robot's own match attempts against the true relative transforms."""
    matcher = closures.matcher
    if matcher is None:
        return None
    records = matcher.records
    reasons = Counter(r.result.reason for r in records if not r.result.success)
    out: dict[str, Any] = {
        "mode": matcher.params.mode.value,
        "submaps_prepared": len(matcher.queue.prepared),
        "submaps_unsuitable": dict(Counter(matcher.queue.unsuitable.values())),
        "attempts": len(records),
        "matches": sum(r.result.success for r in records),
        "rejected": dict(reasons),
        "pairs_untried": len(matcher.queue),  # queued by the last pairing, never matched: the run ended first
        "pairs_not_queued": dict(matcher.not_queued),  # the last pairing's open pairs it owns and did not queue, by reason (eq. 6.1-6.3)
        "submaps_waiting": matcher.waiting,  # received, never prepared
        "wrong_matches": 0,  # accepted, but off by more than WRONG_MATCH_M or WRONG_MATCH_DEG
        "matches_from_prior": 0,  # accepted from the ICP started at the graph's prediction (MatcherParams.icp_from_prior)
    }
    trans, yaw, rot, prior_trans, norm, rows = [], [], [], [], [], []
    stages: dict[str, list[float]] = {}
    for rec in records:
        for stage, s in rec.result.timings.items():
            stages.setdefault(stage, []).append(s)
        res = rec.result
        (ra, _), (rb, _) = res.a, res.b
        Oa, Ob = origins.get(ra, {}).get(rec.frame_a), origins.get(rb, {}).get(rec.frame_b)
        if not res.success or Oa is None or Ob is None:
            continue
        true = np.linalg.solve(Oa, Ob)
        D = np.linalg.solve(true, res.T_a_b)  # T_true^-1 T: the right-perturbation error
        e_t, e_yaw = float(np.linalg.norm(D[:3, 3])), abs(yaw_of(D[:3, :3]))
        trans.append(e_t)
        yaw.append(math.degrees(e_yaw))
        rot.append(float(np.degrees(rotation_angle(D[:3, :3]))))
        out["wrong_matches"] += e_t > WRONG_MATCH_M or rot[-1] > WRONG_MATCH_DEG
        out["matches_from_prior"] += res.start == "prior"
        prior_trans.append(float(np.linalg.norm(rec.prior.T_a_b[:3, 3] - true[:3, 3])))
        sigma = np.sqrt(np.diag(res.cov))
        norm += list(D[:3, 3] / sigma[3:]) + [yaw_of(D[:3, :3]) / sigma[2]]
        rows.append(
            {
                "t": rec.t,
                "a": f"{ra}:{res.a[1]}",
                "b": f"{rb}:{res.b[1]}",
                "error_m": e_t,
                "yaw_error_deg": math.degrees(e_yaw),
                "icp_start": res.start,
            }
        )
    if trans:
        out["translation_error_m"] = statistics(trans, ERROR_STATISTICS)
        out["yaw_error_deg"] = statistics(yaw, ERROR_STATISTICS)
        out["rotation_error_deg"] = statistics(rot, ERROR_STATISTICS)
        out["graph_prior_error_m"] = statistics(prior_trans, ERROR_STATISTICS)  # how far the graph was before the match
        out["calibration"] = calibration(np.asarray(norm))
        out["matches_list"] = rows
    timing = (StatisticsType.MEAN, StatisticsType.MAX)
    out["stage_wall_s"] = {k: {**statistics(v, timing), "n": len(v)} for k, v in sorted(stages.items())}
    return out


def pairs_attempted_twice(closures: dict[str, ClosureInput]) -> int:
    """Submap pairs that more than one attempt (of any robots) went to: work done twice."""
    pairs = Counter(tuple(sorted((r.result.a, r.result.b))) for c in closures.values() if c.matcher is not None for r in c.matcher.records)
    return sum(n > 1 for n in pairs.values())


def detection_calibration(name: str, closures: ClosureInput, truth: TeamTruth) -> dict[str, Any]:
    """Each detection's error in its own covariance's frame (right perturbation of the
    target pose in the detector's body), per component over the predicted sigmas."""
    norm, count = [], 0
    for d in closures.detections:
        true = detection_truth(name, d, truth)
        if true is None:
            continue
        D = np.linalg.solve(d.T_detector_target, true)  # T^-1 T_true = Exp(xi)
        w = so3_log(D[:3, :3])
        xi = np.concatenate([w, D[:3, 3]])
        norm += list(xi / np.sqrt(np.diag(d.cov)))
        count += 1
    return {"count": count, "calibration": calibration(np.asarray(norm))}


def loop_closure_section(closures: dict[str, ClosureInput], truth: TeamTruth) -> dict[str, Any] | None:
    """``metrics.json`` ``loop_closures``: per robot with the graph its matches and
    detections, and team totals."""
    closures = {n: c for n, c in closures.items() if n in truth.robots}
    if not closures:
        return None
    origins = {n: trajectory.frame_origins_truth(c.start_t, c.switch_times, truth.robots[n]) for n, c in closures.items()}
    robots = {}
    for name, c in closures.items():
        robots[name] = {"matches": match_metrics(c, origins), "detections": detection_calibration(name, c, truth)}
    team = {
        "attempts": sum((m["matches"] or {}).get("attempts", 0) for m in robots.values()),
        "matches": sum((m["matches"] or {}).get("matches", 0) for m in robots.values()),
        "wrong_matches": sum((m["matches"] or {}).get("wrong_matches", 0) for m in robots.values()),
        "pairs_untried": sum((m["matches"] or {}).get("pairs_untried", 0) for m in robots.values()),
        "pairs_attempted_twice": pairs_attempted_twice(closures),
        "detections": sum(m["detections"]["count"] for m in robots.values()),
    }
    return {"team": team, "robots": robots}
