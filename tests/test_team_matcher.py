"""Submap matching in the team (thesis 6.1, docs/matching.md "In the team"): every pair has one owner,
so two robots holding the same submaps never try the same pair, and each tries about half of them."""

from __future__ import annotations

import itertools
import math

import numpy as np

from slam.graph import MultiRobotGraph
from slam.lie import rot_z, se3
from slam.matcher import MatcherParams
from slam.team_matcher import TeamMatcher, pair_owner

ROBOTS = ("lru1", "lru2")
FRAMES = 5  # submaps 0..4 of each robot


class _Keypoints:
    """What pairing reads of a prepared submap: its key and its selected keypoints."""

    def __init__(self, key, selected_xyz):
        self.key = key
        self.selected_xyz = np.asarray(selected_xyz, float)


def _graph(owner: str) -> MultiRobotGraph:
    """Both robots' chains of submap origins, 0.2 m apart with 5 cm and 1 deg per step,
    linked at their first submaps: every origin is uncertain relative to every other."""
    graph = MultiRobotGraph(owner)
    cov = np.diag([1e-6, 1e-6, math.radians(1) ** 2] + [0.05**2] * 3)
    for robot in ROBOTS:
        for k in range(FRAMES - 1):
            graph.add_frame_switch(robot, k, float(k), se3(rot_z(0.0), [0.2, 0.0, 0.0]), cov)
    graph.add_match("lru1", 0, "lru2", 0, np.eye(4), np.diag([1e-4] * 3 + [1e-4] * 3))
    graph.update()
    return graph


def _matcher(robot: str) -> TeamMatcher:
    """A matcher of ``robot`` holding all ten submaps, each a 3 x 3 m box of keypoints, so every
    pair overlaps (and eq. 6.3's stereo error is below every relative sigma)."""
    matcher = TeamMatcher(MatcherParams(stereo_error_m=1e-3), robot)
    for key in itertools.product(ROBOTS, range(FRAMES)):
        matcher.queue.prepared[key] = _Keypoints(key, [[0, 0, 0], [3, 3, 0.5]])
        matcher.frames[key] = key[1]
    return matcher


def _drain_queue(matcher: TeamMatcher) -> list:
    pairs = []
    while (cand := matcher.next_candidate()) is not None:
        matcher.queue.mark_attempted(cand.pair)
        pairs.append(cand.pair)
    return pairs


def test_two_robots_holding_the_same_submaps_never_try_the_same_pair():
    tried = {}
    for robot in ROBOTS:
        matcher = _matcher(robot)
        matcher.pair(_graph(robot))
        tried[robot] = _drain_queue(matcher)
    lru1, lru2 = set(tried["lru1"]), set(tried["lru2"])
    assert not lru1 & lru2
    keys = sorted(itertools.product(ROBOTS, range(FRAMES)))
    consecutive = {(a, b) for a, b in itertools.combinations(keys, 2) if a[0] == b[0] and b[1] - a[1] == 1}
    assert lru1 | lru2 == set(itertools.combinations(keys, 2)) - consecutive  # no pair is left to nobody
    # each its own robot's pairs (6 of 10 not consecutive) and half of the 25 between them
    assert sum(a[0] == b[0] for a, b in lru1) == 6 and sum(a[0] == b[0] for a, b in lru2) == 6
    assert {len(lru1), len(lru2)} == {6 + 12, 6 + 13}


def test_the_owner_is_one_of_the_pair_whatever_the_order():
    for a, b in itertools.combinations(itertools.product(("ardea", "lru1", "lru2"), range(4)), 2):
        assert pair_owner(a, b) == pair_owner(b, a) in (a[0], b[0])
        if a[0] == b[0]:
            assert pair_owner(a, b) == a[0]


def test_a_submap_placed_after_pairing_makes_pairing_due_again():
    """Pairing that ran before the graph held a submap's origin pairs it once the graph has it."""
    graph = _graph("lru1")
    matcher = _matcher("lru1")
    matcher.queue.prepared[("lru1", FRAMES)] = _Keypoints(("lru1", FRAMES), [[0, 0, 0], [3, 3, 0.5]])
    matcher.frames[("lru1", FRAMES)] = FRAMES
    matcher.pair(graph)
    assert not matcher.pairing_due and all(("lru1", FRAMES) not in c.pair for c in matcher.queue.candidates())
    graph.update()
    matcher.graph_updated(graph)
    assert not matcher.pairing_due  # nothing new in the graph
    graph.add_frame_switch("lru1", FRAMES - 1, float(FRAMES), se3(rot_z(0.0), [0.2, 0.0, 0.0]), np.diag([1e-6, 1e-6, 3e-4] + [0.05**2] * 3))
    graph.update()
    matcher.graph_updated(graph)
    assert matcher.pairing_due
    matcher.pair(graph)
    assert any(("lru1", FRAMES) in c.pair for c in matcher.queue.candidates())
