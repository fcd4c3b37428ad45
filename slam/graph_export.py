"""A robot's multi-robot graph (thesis 4.2) as files other tools read: g2o, its key map and GTSAM's own serialisation.

Pure module: numpy, gtsam and :mod:`slam.graph`; it writes the paths it is given and nothing else. What it writes is
the graph as it stands: the factors in the estimate (:meth:`MultiRobotGraph.batch_graph`) and the current iSAM2
estimate, in the owner's map frame (its first submap origin).

g2o (:func:`write_g2o`), in the 3D format GTSAM's ``readG2o(path, is3D=True)`` and g2o read:

- ``VERTEX_SE3:QUAT id x y z qx qy qz qw``: every variable in the estimate (submap origins ``s``, robot poses ``x``,
  landmarks ``l``; all are poses) at its estimate;
- ``EDGE_SE3:QUAT id1 id2 x y z qx qy qz qw`` and the upper triangle, row by row, of the 6x6 information matrix: every
  binary factor (w, v, u, d, o, c), ``id2 = id1 (+) z``. g2o orders the tangent space [translation, rotation], GTSAM
  (and the graph's covariances) [rotation, translation]: the information is permuted, not scaled. Its rotation block
  is on the rotation vector, Pose3's local coordinates, as GTSAM's ``writeG2o`` and ``readG2o`` take it (g2o's own
  ``EdgeSE3`` measures a rotation error by the quaternion's vector part, half the angle when small);
- the measured factors' robust kernel (Cauchy, eq. 4.10) is left out, their Gaussian base written: the format has no
  kernel (GTSAM's ``writeG2o`` refuses a robust noise model);
- the graph's one prior, the anchor of the map frame on ``s[owner,0]`` (always vertex 0), as g2o's ``FIX 0``. GTSAM's
  ``readG2o`` has no prior record and skips that line: a reader that optimises with GTSAM adds a prior on vertex 0
  (at its vertex pose) to fix the gauge as the graph does;
- numbers as Python's ``repr`` writes them (the shortest text that reads back to the same float; GTSAM's own writer
  keeps 6 digits).

Vertex ids are consecutive from 0, because gtsam keys (Symbols: a character per kind of variable and a count) are
large and sparse, and g2o readers index arrays by id: submap origins first, the owner's before the peers' (by name),
each robot's by index, then robot poses by robot and time, then landmarks by id. :func:`write_keys` writes the map
from ids to keys and variables as CSV (:class:`Vertex`).

GTSAM's serialisation (:func:`write_gtsam`): ``NonlinearFactorGraph.serialize()`` of the factors in the estimate, with
their gtsam keys and noise models as they are (robust ones included), and ``Values.serialize()`` of the estimate:
boost text archives, read back with ``gtsam.NonlinearFactorGraph().deserialize(text)`` and
``gtsam.Values().deserialize(text)`` by the same GTSAM version.
"""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import gtsam
import numpy as np

from slam.graph import MultiRobotGraph

#: g2o's tangent order [translation, rotation], as indices into GTSAM's [rotation, translation].
G2O_FROM_GTSAM = np.array([3, 4, 5, 0, 1, 2])
_KIND_ORDER = {"s": 0, "x": 1, "l": 2}


class GraphExportException(Exception):
    """A factor the g2o format cannot hold (neither a pose prior nor a factor between two poses)."""


@dataclass(frozen=True)
class Vertex:
    """One variable of the graph as a g2o vertex: a row of the key map (:func:`write_keys`)."""

    id: int  # g2o vertex id, consecutive from 0
    key: int  # the gtsam key (a Symbol)
    symbol: str  # the key as gtsam prints it, e.g. ``s12``
    variable: str  # :meth:`MultiRobotGraph.describe`, e.g. ``s[lru1,3]``
    kind: str  # ``s`` submap origin, ``x`` robot pose, ``l`` landmark
    robot: str  # ``""`` for a landmark
    index: int | float  # submap index, time (simulated seconds) or landmark id


def vertices(graph: MultiRobotGraph) -> list[Vertex]:
    """The graph's variables in vertex id order (module docstring)."""
    owner = graph.owner

    def order(item: tuple[int, tuple]) -> tuple:
        kind, robot, index = item[1]
        return _KIND_ORDER[kind], robot != owner, robot, index

    ordered = sorted(graph.variables().items(), key=order)
    return [Vertex(i, key, gtsam.DefaultKeyFormatter(key), graph.describe(key), *node) for i, (key, node) in enumerate(ordered)]


def write_g2o(graph: MultiRobotGraph, path: Path) -> list[Vertex]:
    """The graph as a g2o file at ``path`` (module docstring); returns its vertices."""
    verts = vertices(graph)
    ids = {v.key: v.id for v in verts}
    values = graph.estimate_values()
    vertex_lines = [f"VERTEX_SE3:QUAT {v.id} {_pose_text(values.atPose3(v.key))}" for v in verts]
    fixed, edges = [], []
    factors = graph.batch_graph()
    for i in range(factors.size()):
        factor = factors.at(i)
        if isinstance(factor, gtsam.PriorFactorPose3):
            fixed.append(f"FIX {ids[factor.keys()[0]]}")
        elif isinstance(factor, gtsam.BetweenFactorPose3):
            a, b = (ids[k] for k in factor.keys())
            info = gaussian(factor.noiseModel()).information()[np.ix_(G2O_FROM_GTSAM, G2O_FROM_GTSAM)]
            upper = " ".join(_number(v) for v in info[np.triu_indices(6)])
            edges.append(f"EDGE_SE3:QUAT {a} {b} {_pose_text(factor.measured())} {upper}")
        else:
            raise GraphExportException(f"factor {i} is a {type(factor).__name__}: g2o holds pose priors and factors between two poses only")
    path.write_text("\n".join(vertex_lines + fixed + edges) + "\n")
    return verts


def write_keys(verts: list[Vertex], path: Path) -> None:
    """The key map as CSV: ``id,key,symbol,variable,kind,robot,index`` (:class:`Vertex`)."""
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[field.name for field in fields(Vertex)])
        writer.writeheader()
        writer.writerows(asdict(v) for v in verts)


def write_gtsam(graph: MultiRobotGraph, factors_path: Path, values_path: Path) -> None:
    """GTSAM's serialisation of the factors in the estimate and of the estimate (module docstring)."""
    factors_path.write_text(graph.batch_graph().serialize())
    values_path.write_text(graph.estimate_values().serialize())


def gaussian(noise: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """A noise model's Gaussian base: a robust model's, unwrapped; any other as it is."""
    return noise.noise() if isinstance(noise, gtsam.noiseModel.Robust) else noise


def _pose_text(pose: gtsam.Pose3) -> str:
    """``x y z qx qy qz qw``."""
    q = pose.rotation().toQuaternion()
    return " ".join(_number(v) for v in (*pose.translation(), q.x(), q.y(), q.z(), q.w()))


def _number(v: float) -> str:
    return repr(float(v))
