"""Spin images about the gravity axis: yaw-invariant 3D descriptors for submap matching.

A spin image (Johnson and Hebert 1999) describes a point's neighbourhood by a 2D
histogram over two cylindrical coordinates about an axis through it: the distance from
the axis (alpha) and the height along it (beta). Johnson and Hebert take the point's
normal as the axis. Submaps here are gravity-aligned (thesis 6.1.2: their origins have
zero roll and pitch, and the 4D alignment of eq. 6.5-6.7 keeps them so), so the axis is
the vertical itself: the descriptor is invariant to yaw, the only rotation the 4D
matcher estimates, and needs neither a normal nor a local reference frame, both of
which stereo noise turns from one view to the next (docs/matching.md, "Voting without
reference frames"). It stands in for the thesis's CSHOT (6.1.2), which no maintained
Python library offers; neither does one offer spin images (PCL's spin about the normal and
lack a maintained Python binding), so they are written here, as a numba kernel.

Each neighbour within ``radius`` adds a unit weight, bilinearly interpolated between
the bin centres (points beyond the outer centres go to the edge bins; heights are
clipped to ``[-height, height]``). Counts are square-rooted, which damps the stereo
clouds' uneven density, and each image is scaled to unit L2 norm.
"""

from __future__ import annotations

import itertools
import math

import numba
import numpy as np
from scipy.spatial import cKDTree


@numba.njit(cache=True, nogil=True)
def _images(cloud, centers, starts, flat, radius, bins, height, out):
    for k in range(len(centers)):
        nb = flat[starts[k] : starts[k + 1]]
        if len(nb) < 5:
            continue
        h = np.zeros((bins, bins))
        for i in nb:
            dx, dy, dz = cloud[i, 0] - centers[k, 0], cloud[i, 1] - centers[k, 1], cloud[i, 2] - centers[k, 2]
            al = math.sqrt(dx * dx + dy * dy) / radius * bins - 0.5
            be = (min(max(dz, -height), height) + height) / (2 * height) * bins - 0.5
            a0, b0 = math.floor(al), math.floor(be)
            fa, fb = al - a0, be - b0
            for da in range(2):
                ia = min(max(a0 + da, 0), bins - 1)
                wa = fa if da else 1 - fa
                for db in range(2):
                    ib = min(max(b0 + db, 0), bins - 1)
                    h[ia, ib] += wa * (fb if db else 1 - fb)
        h = np.sqrt(h)
        norm = math.sqrt((h * h).sum())
        if norm > 0:
            out[k] = h.ravel() / norm


def vertical_spin_images(cloud: np.ndarray, tree: cKDTree, centers: np.ndarray, radius: float, bins: int, height: float) -> np.ndarray:
    """(n, bins^2) unit spin images about the vertical through each of ``centers`` over
    the points of ``cloud`` (indexed by ``tree``) within ``radius``: ``bins`` distances
    from the axis in [0, radius] by ``bins`` heights in [-height, height]. A center with
    fewer than 5 neighbours gets a zero row."""
    nbs = tree.query_ball_point(np.asarray(centers, dtype=float), radius)
    starts = np.zeros(len(centers) + 1, np.int64)
    starts[1:] = np.cumsum([len(n) for n in nbs])
    flat = np.fromiter(itertools.chain.from_iterable(nbs), np.int64, count=int(starts[-1]))
    out = np.zeros((len(centers), bins * bins))
    cloud, centers = np.ascontiguousarray(cloud, dtype=float), np.ascontiguousarray(centers, dtype=float)
    _images(cloud, centers, starts, flat, float(radius), int(bins), float(height), out)
    return out
