"""Clustering of keypoint correspondences into transformation hypotheses (thesis 6.1.2):
each correspondence votes for a transformation, and the peaks of the vote grid are the
clusters that RANSAC then turns into hypotheses.

- :func:`hough3d`, the thesis's Hough3D voting (Tombari and Di Stefano 2010, as PCL's
  ``Hough3DGrouping``): every keypoint has a local reference frame (SHOT's); each
  correspondence carries the vector from the model keypoint to the model's reference
  point (the centroid of its keypoints) through the two frames into the scene and votes
  for a position there. Its votes are only as good as the frames are repeatable between
  the two clouds.
- :func:`yaw_sweep`, ours: the thesis's own argument for its 4D RANSAC and ICP ("the early
  incorporation of prior knowledge to reduce the dimensionality ... directs the optimizer
  towards the correct solution", 6.1.2) applied to the voting. Both submaps are
  gravity-aligned, so a transformation is ``t`` and a yaw; for every yaw on a grid of
  ``yaw_step`` each correspondence ``(p, q)`` votes for ``t = p - R_z(yaw) q``. The right
  correspondences agree at the right yaw wherever they lie, and no local reference frame
  enters. docs/matching.md ("Voting without reference frames") measures both.

Both take the peaks of the 3x3x3 neighbourhood sums of the grid (``bin_m`` cells, at least
``min_votes``), largest first, and give each peak the correspondences in its
neighbourhood not yet taken by a larger one. Only numpy.
"""

from __future__ import annotations

import numpy as np

# the yaw sweep evaluates neighbourhood sums around its fullest cells only (not tuned): a true
# cluster spreads over at most two cells per axis (noise and half a yaw step over the lever)
_SWEEP_CANDIDATES = 4000
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])


def hough3d(
    scene_points: np.ndarray,
    scene_frames: np.ndarray,
    model_points: np.ndarray,
    model_frames: np.ndarray,
    corr: np.ndarray,
    bin_m: float,
    min_votes: int,
    max_clusters: int,
) -> list[np.ndarray]:
    """Hough3D clusters: lists of indices into ``corr`` (columns: scene and model
    keypoint); ``*_frames`` are (n, 3, 3) local reference frames, rows x, y, z."""
    if len(corr) < min_votes:
        return []
    ref = model_points.mean(axis=0)
    local = np.einsum("nij,nj->ni", model_frames[corr[:, 1]], ref - model_points[corr[:, 1]])
    votes = scene_points[corr[:, 0]] + np.einsum("nji,nj->ni", scene_frames[corr[:, 0]], local)
    return _peaks(np.floor(votes / bin_m).astype(np.int64)[None], min_votes, max_clusters, None)


def yaw_sweep(
    scene_points: np.ndarray,
    model_points: np.ndarray,
    corr: np.ndarray,
    bin_m: float,
    yaw_step: float,
    min_votes: int,
    max_clusters: int,
    yaw_window: tuple[float, float] | None = None,
    t_window: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Clusters of the 4D vote (yaw on a grid of ``yaw_step`` rad, translation in
    ``bin_m`` cells): lists of indices into ``corr``. The yaws cover the full turn, or
    ``yaw_window`` = (centre, half width): the only yaws the plausibility checks would
    accept, so that clusters at others do not take the places of ``max_clusters``.
    ``t_window`` = (centre (3,), half widths (3,)) likewise keeps only the votes for
    translations inside that box. One direction suffices: the vote space of ``b`` into
    ``a`` is that of ``a`` into ``b``."""
    if len(corr) < min_votes:
        return []
    p, q = scene_points[corr[:, 0]], model_points[corr[:, 1]]
    if yaw_window is None or yaw_window[1] >= np.pi:
        yaws = np.arange(0.0, 2 * np.pi, yaw_step)
    else:
        half = int(np.ceil(yaw_window[1] / yaw_step))
        yaws = yaw_window[0] + yaw_step * np.arange(-half, half + 1)
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    t = np.empty((len(yaws), len(corr), 3))
    t[..., 0] = p[:, 0] - (c * q[:, 0] - s * q[:, 1])
    t[..., 1] = p[:, 1] - (s * q[:, 0] + c * q[:, 1])
    t[..., 2] = p[:, 2] - q[:, 2]
    valid = None if t_window is None else np.all(np.abs(t - t_window[0]) <= t_window[1], axis=-1)
    return _peaks(np.floor(t / bin_m).astype(np.int64), min_votes, max_clusters, _SWEEP_CANDIDATES, valid)


def _peaks(cells: np.ndarray, min_votes: int, max_clusters: int, candidates: int | None, valid: np.ndarray | None = None) -> list[np.ndarray]:
    """Greedy clusters from (layers, n, 3) vote cells (a layer per yaw; one for Hough3D):
    neighbourhood sums at every occupied cell, or at the ``candidates`` fullest ones;
    only the votes where ``valid`` (layers, n) is true, all without it."""
    if valid is None:  # every vote: a view, no gather
        voted, vl = cells.reshape(-1, 3), np.repeat(np.arange(len(cells)), cells.shape[1])
    else:
        vl, vi = np.nonzero(valid)
        voted = cells[vl, vi]
    if len(vl) < min_votes:
        return []
    lo = voted.min(axis=0) - 1
    width = int((voted.max(axis=0) - lo).max()) + 2

    def key(layer, c):
        return ((layer * width + (c[..., 0] - lo[0])) * width + (c[..., 1] - lo[1])) * width + (c[..., 2] - lo[2])

    uniq, first, counts = np.unique(key(vl, voted), return_index=True, return_counts=True)
    at = np.arange(len(uniq))
    if candidates is not None and len(uniq) > candidates:
        at = np.sort(np.argpartition(-counts, candidates - 1)[:candidates])
    at_layer = vl[first[at]]
    centre = voted[first[at]]
    support = np.zeros(len(at), np.int64)
    for off in _OFFSETS:
        k = key(at_layer, centre + off)
        pos = np.minimum(np.searchsorted(uniq, k), len(uniq) - 1)
        support += np.where(uniq[pos] == k, counts[pos], 0)
    clusters: list[np.ndarray] = []
    taken = np.zeros(cells.shape[1], bool)
    for u in np.argsort(-support, kind="stable"):
        if support[u] < min_votes:
            break
        near = np.all(np.abs(cells[at_layer[u]] - centre[u]) <= 1, axis=1) & ~taken
        if valid is not None:
            near &= valid[at_layer[u]]
        if near.sum() >= min_votes:
            clusters.append(np.flatnonzero(near))
            taken |= near
            if len(clusters) == max_clusters:
                break
    return clusters
