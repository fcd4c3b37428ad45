"""The matching benchmark's descriptor quality (sim/tools/match_bench.py) against pairs whose true transform and
true partners are known by construction."""

import numpy as np

from sim.tools.match_bench import descriptor_quality
from slam.lie import rot_z, se3
from slam.matcher import Keypoints, MatcherParams


def _keypoints(name: str, points: np.ndarray, descriptors: np.ndarray) -> Keypoints:
    empty = np.zeros((0, 3))
    return Keypoints((name, 0), 0, points, empty, empty.astype(np.float32), np.zeros(0, bool), descriptors=descriptors)


def _pair(rng: np.random.Generator, n: int = 60):
    points = rng.uniform(-4.0, 4.0, (n, 3)) * [1, 1, 0.1]
    desc = rng.random((n, 16))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    T_a_b = se3(rot_z(0.7), [1.5, -0.5, 0.05])
    in_b = (points - T_a_b[:3, 3]) @ T_a_b[:3, :3]  # the same places in b's frame
    return points, in_b, desc, T_a_b


def test_identical_descriptors_find_every_partner_and_every_correspondence_is_right():
    points, in_b, desc, T_a_b = _pair(np.random.default_rng(3))
    q = descriptor_quality(_keypoints("a", points, desc), _keypoints("b", in_b, desc), T_a_b, MatcherParams())
    assert q["partners"] == q["partners_found"] == len(points)
    assert q["right_unbounded"] >= q["right_kept"] >= len(points)  # each place with itself, and neighbours within CORRECT_M
    assert q["kept"] > q["right_kept"]  # the 2nd and 3rd nearest descriptors are other places


def test_unrelated_descriptors_find_few_partners_and_the_threshold_drops_them():
    rng = np.random.default_rng(4)
    points, in_b, desc, T_a_b = _pair(rng)
    q = descriptor_quality(_keypoints("a", points, desc), _keypoints("b", in_b, rng.permutation(desc)), T_a_b, MatcherParams())
    assert q["partners_found"] < 0.2 * q["partners"]
    other = rng.random(desc.shape)
    other /= np.linalg.norm(other, axis=1, keepdims=True)
    tight = descriptor_quality(_keypoints("a", points, desc), _keypoints("b", in_b, other), T_a_b, MatcherParams(max_descriptor_distance=0.01))
    assert tight["kept"] == tight["right_kept"] == 0 < tight["right_unbounded"]


def test_a_pair_without_enough_partners_does_not_count():
    points, in_b, desc, T_a_b = _pair(np.random.default_rng(5))
    assert descriptor_quality(_keypoints("a", points, desc), _keypoints("b", in_b + [30.0, 0, 0], desc), T_a_b, MatcherParams()) is None
