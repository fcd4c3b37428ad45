"""sim.evaluation.loop_closures: accepted matches against the true relative transform of
their submap origins."""

import math

import numpy as np

from sim.evaluation.inputs import ClosureInput
from sim.evaluation.loop_closures import WRONG_MATCH_DEG, WRONG_MATCH_M, match_metrics
from slam.lie import rot_z, se3
from slam.matcher import MatcherParams, MatchResult, Prior
from slam.team_matcher import MatchRecord, TeamMatcher


def test_matches_off_by_more_than_the_thresholds_count_as_wrong():
    """Three accepted matches of a robot's submaps 0 and 1 (origins 4 m apart): one right
    to 2 cm, one 0.5 m off, one 5 deg off (its ICP started at the graph's prediction); one
    rejected attempt."""
    origins = {"lru1": {0: se3(np.eye(3), [0.0, 0.0, 0.0]), 1: se3(rot_z(0.3), [4.0, 0.0, 0.0])}}
    true = np.linalg.solve(origins["lru1"][0], origins["lru1"][1])
    matcher = TeamMatcher(MatcherParams(), "lru1")
    cov = np.diag([1e-4] * 3 + [1e-3] * 3)
    prior = Prior(true, np.full(3, 0.2))
    results = [
        true @ se3(np.eye(3), [0.02, 0.0, 0.0]),
        true @ se3(np.eye(3), [WRONG_MATCH_M + 0.2, 0.0, 0.0]),
        true @ se3(rot_z(math.radians(WRONG_MATCH_DEG + 2)), [0.0, 0.0, 0.0]),
        None,
    ]
    for k, T in enumerate(results):
        result = MatchResult(("lru1", 0), ("lru1", 1), T_a_b=T, cov=None if T is None else cov, reason="" if T is not None else "no hypothesis")
        result.start = "prior" if k == 2 else "hypothesis" if T is not None else ""
        matcher.records.append(MatchRecord(float(k), 0, 1, prior, result))
    out = match_metrics(ClosureInput(start_t=0.0, switch_times={1: 10.0}, matcher=matcher, detections=[]), origins)
    assert out["attempts"] == 4 and out["matches"] == 3 and out["rejected"] == {"no hypothesis": 1}
    assert out["wrong_matches"] == 2
    assert out["matches_from_prior"] == 1 and [m["icp_start"] for m in out["matches_list"]] == ["hypothesis", "hypothesis", "prior"]
    assert out["translation_error_m"]["max"] > WRONG_MATCH_M and abs(out["matches_list"][0]["error_m"] - 0.02) < 1e-9
