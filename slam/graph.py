"""One robot's multi-robot SLAM graph (thesis 4.2.2 front-end, 4.2.3 back-end).

Pure module: numpy, gtsam and ``slam.lie``. Each robot owns a :class:`MultiRobotGraph` and estimates the whole team in its
own map frame, the origin of its first submap ``s[owner,0]`` (unary prior at identity, the only prior).

Variables (named :meth:`MultiRobotGraph.describe`; gtsam keys ``symbol(kind, n)``, ``n`` counted per kind
in order of first use): submap origins ``s[r,i]``, robot poses ``x[r,t]`` (sampled sparsely: only once a detection or
landmark observation refers to them) and landmarks ``l[k]``. Factors, all binary except the prior:

- ``w`` frame switch ``s[r,i] -> s[r,i+1]`` and ``v`` filter pose ``s[r,j] -> x[r,t]`` (local reference
  topology, Fig. 4.2b); the online pose is ``s_j (+) v_t`` (eq. 4.6);
- ``d`` robot detection ``x[a,t] -> x[b,t]`` (eq. 4.7), ``o`` landmark observation ``x[r,t] -> l[k]`` and
  ``c`` submap match ``s[a,i] -> s[b,j]``, the measured factors, robust by ``GraphParams.robust``
  (:class:`RobustKernel`, below);
- ``u`` sequential odometry (Fig. 4.2a, eq. 4.8, 4.9), only in :attr:`Topology.SEQUENTIAL`, for comparison:
  per robot and frame ``k`` the nodes ``s_k``, the frame's robot poses in the graph and ``s_{k+1}`` are
  ordered by time and chained with ``u = P_a^-1 P_b``, covariance ``Σ_b - Σ_a`` with eigenvalues clipped
  to ``min_sequential_var``. A late pose between two chained nodes replaces their ``u`` (removed from
  iSAM2 by its factor index); the local reference topology never removes anything.

Poses are 4x4 arrays; every covariance is 6x6 ``[rotation, translation]``, right perturbation
(``T_true = T Exp(xi)``, GTSAM's ``Pose3``), as ``filter.pose_covariance``.

Inputs may arrive in any order and late. :meth:`MultiRobotGraph.update` moves into iSAM2 (Kaess et al. 2012)
every pending factor whose variables are in the estimate or can be initialised breadth-first from it
through pending factors (in content order: type, node names, measurement, never arrival order); the rest
stays pending, so a chain that nothing connects to the anchored component never reaches iSAM2 (Cholesky
would find it indeterminant) and joins with its whole backlog once something does.

A factor is also kept pending until every variable it touches is tied into the topology of Fig. 4.2b:
a submap origin ``s[r,i]`` once robot ``r``'s frame switches ``w`` from ``s[r,0]`` up to ``s[r,i]`` are all
registered (its chain of submap origins has no gap), a robot pose ``x[r,t]`` once its filter pose ``v`` is
registered and its frame is tied, a landmark always. So a detection whose answering pose is lost or still
on its way, or a pose in a frame whose switch arrives late, waits instead of leaving a variable held from
one side only. (A submap origin whose only factor was a confident ``v``, sampled just after its frame
switch, hanging on a robot pose that one loose landmark observation held, made iSAM2 fail: iSAM2 puts
the new variables last, here both in the root clique, and GTSAM's pivot check rejected the origin's
pivot, the loose anchor's information, as below 2^-24 of its diagonal, the confident ``v``'s.) The
factors that end up in the estimate are the same as without the rule; only a detection whose answer
comes later, or a factor in a frame whose switch comes later, enters with it instead of before it.

:meth:`MultiRobotGraph.update` never raises on a failure of iSAM2 (which may still fail the same way when a
robot joins through one loose detection while its filter pose is confident): it rebuilds iSAM2 from the
batch graph (one elimination of everything, rooted at the prior) seeded with the current estimate; if that
fails too, it drops the newest measurement (``d``, ``o``, ``c``) among the new factors that touches the
variable gtsam named (else any new factor touching it, else the newest new factor) for good and tries
again; with no new factor left, it re-seeds from batch Levenberg-Marquardt, then uses QR; if all that
fails the previous estimate stays and the next update starts with a rebuild. Each recovery is recorded in
:attr:`MultiRobotGraph.recoveries` (:class:`GraphRecovery`), each dropped factor in
:meth:`MultiRobotGraph.dropped_factors`.

Robust options for the measured factors (thesis 4.2.3: "overconfident, erroneous loop closure constraints
can corrupt the entire graph optimization result"), :class:`RobustKernel`:

- ``cauchy`` (default, the thesis's choice): the Cauchy M-estimator (eq. 4.10, IRLS weights eq. 4.11) on the
  Mahalanobis distance, ``GraphParams.cauchy_c`` (``math.inf``: plain Gaussian). It bounds an outlier's pull
  but never removes it, and its weights change only when iSAM2 relinearises;
- ``none``: plain Gaussian (eq. 4.5);
- ``gnc``: Graduated Non-Convexity (Yang et al. 2020, GTSAM's ``GncOptimizer`` with Levenberg-Marquardt) as
  an outlier classifier beside iSAM2. GNC is a batch method, so it does not replace iSAM2: whenever new
  measured factors can enter, one GNC run over the batch graph (the factors in iSAM2, the new ones and the
  ones rejected so far; the prior, w, v and u factors as known inliers, ``setKnownInliers``; seeded with
  the current estimate) judges every measured factor, and only those it calls inliers stay in or enter
  iSAM2, with plain Gaussian noise; the others are removed from iSAM2 by their factor index (as the
  sequential topology removes ``u``) and kept aside, re-admitted when a later run calls them inliers. The
  loss is truncated least squares (TLS): its weights converge to exactly 0 or 1, a classification without
  a threshold of its own, and its solution is what iSAM2 then computes (the inliers with Gaussian noise, the
  outliers left out); Geman-McClure's weights never reach 0. A measured factor is an inlier when its
  squared Mahalanobis distance is below the ``GraphParams.gnc_inlier_probability`` quantile of a 6-dof
  chi-square (0.99: 16.8, a distance of 4.1, next to the Cauchy kernel's 3.5). An outlier whose removal
  would cut a variable off the anchored component is kept (a bridge: GNC satisfies it exactly anyway).
  Each run is a :class:`GncRun` in :attr:`MultiRobotGraph.gnc_runs`; a run that fails leaves the
  classification as it was (the new factors enter) and records the error.

Back-end notes. iSAM2 factorises with Cholesky; the sequential topology uses QR, because the eq. 4.9 floor
(information up to 1e10) made Cholesky report an indeterminant system on chains whose filter covariance
does not grow. iSAM2 relinearises a variable only once its update exceeds ``relinearize_threshold``, and the
Cauchy weights (eq. 4.11) change only on relinearisation: with the default 0.01 the estimate stays about
1-3 mm from the batch optimum (:meth:`MultiRobotGraph.batch_optimize`); with 1e-6 and ~20 extra iterations
it agrees within 1e-5. Cost (2-core machine, 3 robots, ~400 factors and ~310 variables, one detection per
update): about 2 ms per update in the local reference topology (1.2 ms ``ISAM2.update``, 0.3 ms estimate),
5 ms in the sequential one; a marginal covariance 1-2 ms; batch Levenberg-Marquardt 50-80 ms.

The bookkeeping of an update grows with what changed, not with the graph: the factors the inputs define are kept
input by input (rebuilt from all inputs only after a recovery dropped one, and in the sequential topology, where
a late pose can change any ``u`` of its frame), the ones not yet in iSAM2 apart from them, and the estimate is read
per variable (``ISAM2.calculateEstimatePose3``) unless the whole of it is asked for (:meth:`MultiRobotGraph.estimate`
and the like). ``python -m slam.bench`` measures it (docs/slam.md, its table).
"""

from __future__ import annotations

import math
import re
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property

import gtsam
import numpy as np

from slam.lie import adjoint, se3_inv

Node = tuple[str, str, int | float]  # (kind "s" | "x" | "l", robot ("" for landmarks), index | time | landmark id)


class GraphException(Exception):
    """Bad input to the multi-robot graph (shapes, non-finite or indefinite covariances, self-detections)."""


class _StaleIsam(RuntimeError):
    """iSAM2 was left failed by an earlier update's recovery: rebuild it before anything else."""


class Topology(StrEnum):
    LOCAL_REFERENCE = "local_reference"  # Fig. 4.2b: w and v factors
    SEQUENTIAL = "sequential"  # Fig. 4.2a: u factors (eq. 4.8, 4.9)


class RobustKernel(StrEnum):
    """How the measured factors (d, c, o) are made robust (module docstring; thesis 4.2.3)."""

    CAUCHY = "cauchy"  # eq. 4.10, weights eq. 4.11
    GNC = "gnc"  # Graduated Non-Convexity (TLS) as the outlier classifier, Gaussian in iSAM2
    NONE = "none"  # plain Gaussian (eq. 4.5)


class FactorType(StrEnum):
    PRIOR = "prior"
    FRAME_SWITCH = "w"
    FILTER_POSE = "v"
    ODOMETRY = "u"
    DETECTION = "d"
    MATCH = "c"
    LANDMARK = "o"


@dataclass(frozen=True)
class GraphParams:
    """``robust`` (:class:`RobustKernel`) applies to d, c and o factors: ``cauchy_c`` (eq. 4.10, Mahalanobis
    units; ``math.inf`` for no kernel) with ``cauchy``, ``gnc_inlier_probability`` (chi-square quantile of an
    inlier's squared Mahalanobis distance, in (0, 1)) with ``gnc``."""

    topology: Topology = Topology.LOCAL_REFERENCE
    robust: RobustKernel = RobustKernel.CAUCHY
    cauchy_c: float = 3.5
    gnc_inlier_probability: float = 0.99
    prior_sigma_rad: float = 1e-4
    prior_sigma_m: float = 1e-4
    min_sequential_var: float = 1e-10
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1

    def __post_init__(self):
        if not isinstance(self.topology, Topology):
            raise GraphException(f"GraphParams.topology must be one of {[t.value for t in Topology]}, got {self.topology!r}")
        if not isinstance(self.robust, RobustKernel):
            raise GraphException(f"GraphParams.robust must be one of {[k.value for k in RobustKernel]}, got {self.robust!r}")
        if not 0.0 < self.gnc_inlier_probability < 1.0:
            raise GraphException(f"GraphParams.gnc_inlier_probability must be in (0, 1), got {self.gnc_inlier_probability!r}")
        for name in ("cauchy_c", "prior_sigma_rad", "prior_sigma_m", "min_sequential_var"):
            if not getattr(self, name) > 0.0:
                raise GraphException(f"GraphParams.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.relinearize_threshold >= 0.0:
            raise GraphException(f"GraphParams.relinearize_threshold must be >= 0, got {self.relinearize_threshold!r}")
        if not (isinstance(self.relinearize_skip, int) and self.relinearize_skip >= 1):
            raise GraphException(f"GraphParams.relinearize_skip must be an int >= 1, got {self.relinearize_skip!r}")


@dataclass(frozen=True)
class UpdateStats:
    wall_s: float
    factors_added: int
    variables_added: int
    factors_removed: int
    recovered: bool = False  # iSAM2 failed and was rebuilt (see :class:`GraphRecovery`)


@dataclass(frozen=True)
class GraphRecovery:
    """One iSAM2 failure :meth:`MultiRobotGraph.update` recovered from (module docstring)."""

    t: float | None  # the caller's time of the update (simulated seconds), if it gave one
    update: int  # the number of the update that failed (0: the first that reached iSAM2)
    error: str  # gtsam's message, its first line
    variable: str | None  # the variable gtsam named, e.g. ``x[lru2,52.2]``
    action: str  # RECOVERY_ACTIONS: what finally worked
    dropped: tuple[str, ...]  # the factors left out for good (:meth:`MultiRobotGraph.dropped_factors`)


@dataclass(frozen=True)
class GncRun:
    """One GNC classification of the measured factors (``robust: gnc``, module docstring)."""

    t: float | None  # the caller's time of the update (simulated seconds), if it gave one
    update: int  # the number of the update it preceded (as :attr:`GraphRecovery.update`)
    factors: int  # factors in the batch graph GNC solved
    measured: int  # measured factors (d, c, o) it judged
    rejected: tuple[str, ...]  # the measured factors it left out (``type: node -> node``)
    newly_rejected: int  # of those, the ones that were in iSAM2 or new
    readmitted: int  # measured factors rejected before that it called inliers
    bridges: int  # outliers kept because leaving them out would cut a variable off
    wall_s: float
    error: str | None = None  # gtsam's message when GNC failed (the classification was left as it was)


RECOVERY_ACTIONS = ("rebuilt", "rebuilt from levenberg_marquardt", "rebuilt with qr", "failed: previous estimate kept")


@dataclass(frozen=True, eq=False)
class _Factor:
    type: FactorType
    nodes: tuple[Node, ...]
    z: np.ndarray  # 4x4 measurement (the prior's mean)
    cov: np.ndarray  # 6x6

    @cached_property
    def signature(self) -> tuple:
        """``(type, node names, measurement rounded to 1e-6)``: what :meth:`MultiRobotGraph.signatures` lists."""
        return (self.type.value, tuple(_name(n) for n in self.nodes), tuple(round(float(v), 6) + 0.0 for v in self.z[:3].ravel()))


@dataclass(frozen=True, eq=False)
class _Registered:
    """A frame switch (``frame`` = index_from) or a filter pose (``frame`` = its frame index) as given."""

    t: float
    frame: int
    T: np.ndarray
    cov: np.ndarray

    def same(self, other: _Registered) -> bool:
        return self.t == other.t and self.frame == other.frame and np.array_equal(self.T, other.T) and np.array_equal(self.cov, other.cov)


_ROBUST = frozenset({FactorType.DETECTION, FactorType.MATCH, FactorType.LANDMARK})
# what gtsam's C++ exceptions become in Python (IndeterminateSystemException: RuntimeError; std::domain_error,
# std::invalid_argument: ValueError)
_GTSAM_ERRORS = (RuntimeError, ValueError)
# extra iSAM2 iterations after GNC took factors out of it: one Gauss-Newton step from a linearisation point
# the outliers had pulled does not reach the new optimum (test_gnc_readmits_... in tests/test_graph.py, two
# 0.5 m / 10 deg outliers removed: 0.68 mm from batch Levenberg-Marquardt without, 0.01 mm with 1 or 3)
_SETTLE_ITERATIONS = 2


def _describe(f: _Factor) -> str:
    """``type: node -> node``, e.g. ``o: x[lru2,52.2] -> l[0]``."""
    return f"{f.type.value}: " + " -> ".join(_name(n) for n in f.nodes)


def _name(node: Node) -> str:
    kind, robot, index = node
    return f"l[{index}]" if kind == "l" else f"{kind}[{robot},{index!r}]"


def _robot(robot, what: str) -> str:
    if not (isinstance(robot, str) and robot):
        raise GraphException(f"{what} must be a non-empty string, got {robot!r}")
    return robot


def _index(i, what: str) -> int:
    if isinstance(i, bool) or not isinstance(i, int | np.integer) or i < 0:
        raise GraphException(f"{what} must be an int >= 0, got {i!r}")
    return int(i)


def _landmark(landmark) -> int:
    if isinstance(landmark, bool) or not isinstance(landmark, int | np.integer):
        raise GraphException(f"landmark must be an int id, got {landmark!r}")
    return int(landmark)


def _time(t, what: str) -> float:
    try:
        t = float(t)
    except (TypeError, ValueError):
        raise GraphException(f"{what} must be a finite float, got {t!r}") from None
    if not math.isfinite(t):
        raise GraphException(f"{what} must be a finite float, got {t!r}")
    return t


def _pose(T, what: str) -> np.ndarray:
    try:
        T = np.array(T, dtype=float)
    except (TypeError, ValueError):
        raise GraphException(f"{what} must be a 4x4 rigid transform, got {T!r}") from None
    if T.shape != (4, 4):
        raise GraphException(f"{what} must be a 4x4 rigid transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GraphException(f"{what} must be finite, got {T.tolist()}")
    R = T[:3, :3]
    if not (np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]) and np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0.0):
        raise GraphException(f"{what} must be a rigid transform (rotation block orthonormal, det +1, last row 0 0 0 1), got {T.tolist()}")
    return T


def _covariance(cov, what: str) -> np.ndarray:
    try:
        C = np.array(cov, dtype=float)
    except (TypeError, ValueError):
        raise GraphException(f"{what} must be a 6x6 covariance, got {cov!r}") from None
    if C.shape != (6, 6):
        raise GraphException(f"{what} must be a 6x6 covariance [rotation, translation], got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise GraphException(f"{what} must be finite")
    C = 0.5 * (C + C.T)
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise GraphException(f"{what} must be positive definite, eigenvalues {np.linalg.eigvalsh(C)}") from None
    return C


class MultiRobotGraph:
    """The owner's pose graph of the whole team in the owner's map frame (see the module docstring)."""

    def __init__(self, owner: str, params: GraphParams = GraphParams()):
        self.owner = _robot(owner, "owner")
        self.params = params
        self._factorization = "QR" if params.topology is Topology.SEQUENTIAL else "CHOLESKY"
        self._isam = self._new_isam()
        self._values: gtsam.Values | None = gtsam.Values()  # the estimate if computed (:attr:`_estimate`), else None
        self._initial = gtsam.Values()  # every variable's value when it entered iSAM2
        self._keys: dict[Node, int] = {}
        self._nodes: dict[int, Node] = {}  # keys are allocated only for variables entering iSAM2
        self._counters: Counter[str] = Counter()  # keys allocated per kind
        self._known: set[Node] = set()  # nodes in the estimate
        self._robots: set[str] = set()  # robots with a submap origin or a pose in the estimate
        self._latest: dict[str, int] = {}  # per robot, its latest submap origin in the estimate
        self._switches: dict[tuple[str, int], _Registered] = {}
        self._poses: dict[tuple[str, float], _Registered] = {}
        self._measured: list[_Factor] = []  # d, o and c in order of arrival
        self._in_isam: dict[tuple, tuple[int, _Factor]] = {}  # factor id -> (iSAM2 factor index, factor)
        self._derived: dict[tuple, _Factor] = {}  # prior, w, v and u factors built so far, by id (inputs never change)
        # what the inputs define, kept up to date input by input (:meth:`_wanted_factors`); None: rebuild from the inputs
        self._wanted: dict[tuple, _Factor] | None = None
        self._waiting: dict[tuple, _Factor] = {}  # the wanted factors not in iSAM2 (whether tied or connected or not)
        self._referenced: set[Node] = set()  # robot poses the measured factors (not dropped) refer to
        self._ends: dict[str, int] | None = {}  # :meth:`_spine_ends`, kept up to date; None: recompute
        self._audit = False  # the wanted factors were rebuilt: a factor in iSAM2 may have left them
        sigmas = [params.prior_sigma_rad] * 3 + [params.prior_sigma_m] * 3
        self._prior = _Factor(FactorType.PRIOR, (("s", self.owner, 0),), np.eye(4), np.diag(np.square(sigmas)))
        self._dropped: dict[tuple, _Factor] = {}  # factors left out for good by a recovery, by id
        self._stale: str | None = None  # a recovery that failed: the next update rebuilds iSAM2
        self._rejected: dict[tuple, _Factor] = {}  # measured factors the last GNC run called outliers, by id
        self.update_times: list[float] = []
        self.recoveries: list[GraphRecovery] = []
        self.gnc_runs: list[GncRun] = []

    # ------------------------------------------------------------------ inputs

    def add_frame_switch(self, robot: str, index_from: int, t: float, T_from_to: np.ndarray, cov: np.ndarray) -> None:
        """Frame switch ``w`` of ``robot`` from submap ``index_from`` to ``index_from + 1`` at time ``t``."""
        robot, index_from = _robot(robot, "robot"), _index(index_from, "index_from")
        what = f"frame switch {robot} {index_from}->{index_from + 1}"
        entry = _Registered(_time(t, f"{what}: t"), index_from, _pose(T_from_to, f"{what}: T_from_to"), _covariance(cov, f"{what}: cov"))
        self._register(self._switches, (robot, index_from), entry, what)
        if self._ends is not None:
            self._advance_end(robot)
        self._want(("w", robot, index_from), lambda: self._switch_factor(robot, index_from))

    def add_robot_pose(self, robot: str, t: float, frame_index: int, T_frame_body: np.ndarray, cov: np.ndarray) -> None:
        """The filter's pose ``v`` of ``robot`` at ``t`` in its frame ``frame_index``; it enters the graph once a
        detection or landmark observation refers to ``x[robot,t]``."""
        robot, t = _robot(robot, "robot"), _time(t, "t")
        what = f"robot pose of {robot} at t={t!r}"
        entry = _Registered(
            t, _index(frame_index, f"{what}: frame_index"), _pose(T_frame_body, f"{what}: T_frame_body"), _covariance(cov, f"{what}: cov")
        )
        self._register(self._poses, (robot, t), entry, what)
        node = ("x", robot, t)
        if node in self._referenced:
            self._want(("v", robot, t), lambda: self._pose_factor(node))

    def add_detection(self, robot_a: str, robot_b: str, t: float, T_a_b: np.ndarray, cov: np.ndarray) -> None:
        """Detection ``d`` of ``robot_b`` by ``robot_a`` at ``t`` (eq. 4.7): ``x[b,t] = x[a,t] (+) T_a_b``."""
        robot_a, robot_b, t = _robot(robot_a, "robot_a"), _robot(robot_b, "robot_b"), _time(t, "t")
        if robot_a == robot_b:
            raise GraphException(f"a detection needs two different robots, got {robot_a!r} detecting itself at t={t!r}")
        what = f"detection {robot_a}->{robot_b} at t={t!r}"
        self._measure(FactorType.DETECTION, (("x", robot_a, t), ("x", robot_b, t)), T_a_b, cov, what)

    def add_landmark_observation(self, robot: str, t: float, landmark: int, T_body_landmark: np.ndarray, cov: np.ndarray) -> None:
        """Landmark observation ``o``: ``l[landmark] = x[robot,t] (+) T_body_landmark``."""
        robot, t = _robot(robot, "robot"), _time(t, "t")
        landmark = _landmark(landmark)
        what = f"observation of landmark {landmark} by {robot} at t={t!r}"
        self._measure(FactorType.LANDMARK, (("x", robot, t), ("l", "", landmark)), T_body_landmark, cov, what)

    def add_match(self, robot_a: str, submap_a: int, robot_b: str, submap_b: int, T_a_b: np.ndarray, cov: np.ndarray) -> None:
        """Submap match ``c``: ``s[b,submap_b] = s[a,submap_a] (+) T_a_b`` (intra- or inter-robot)."""
        nodes = (("s", _robot(robot_a, "robot_a"), _index(submap_a, "submap_a")), ("s", _robot(robot_b, "robot_b"), _index(submap_b, "submap_b")))
        if nodes[0] == nodes[1]:
            raise GraphException(f"a match needs two different submaps, got {_name(nodes[0])} with itself")
        self._measure(FactorType.MATCH, nodes, T_a_b, cov, f"match {_name(nodes[0])}->{_name(nodes[1])}")

    # ------------------------------------------------------------------ optimisation

    def update(self, extra_iterations: int = 0, t: float | None = None) -> UpdateStats:
        """Move every pending factor that is tied into the topology and connects to the anchored component into
        iSAM2 and run ``ISAM2.update`` (plus ``extra_iterations`` further ones). Nothing to do and no extra
        iterations: iSAM2 is not called. Never raises on a failure of iSAM2: it recovers (module docstring) and
        records a :class:`GraphRecovery` stamped with ``t``, the caller's time. With ``robust: gnc`` and new
        measured factors, a GNC classification comes first (module docstring; its time is part of the update's)."""
        start = time.perf_counter()
        if isinstance(extra_iterations, bool) or not isinstance(extra_iterations, int) or extra_iterations < 0:
            raise GraphException(f"extra_iterations must be an int >= 0, got {extra_iterations!r}")
        t = None if t is None else _time(t, "t")
        removed, addable, initial = self._plan()
        if self.params.robust is RobustKernel.GNC and any(f.type in _ROBUST for _, f in addable):
            if self._classify(t):  # outliers leave iSAM2: let it settle without them
                extra_iterations = max(extra_iterations, _SETTLE_ITERATIONS)
            removed, addable, initial = self._plan()
        if not (addable or removed or extra_iterations or self._stale):
            return UpdateStats(time.perf_counter() - start, 0, 0, 0)
        known = len(self._known)
        try:
            if self._stale:
                raise _StaleIsam(self._stale)
            self._commit(addable, initial, removed, extra_iterations)
            recovered = False
        except _GTSAM_ERRORS as exc:  # gtsam's IndeterminateSystemException (and any other failure inside iSAM2)
            self._recover(exc, t, extra_iterations)
            recovered = True
            addable = [(fid, f) for fid, f in addable if fid in self._in_isam]
        wall = time.perf_counter() - start
        self.update_times.append(wall)
        return UpdateStats(wall, len(addable), len(self._known) - known, len(removed), recovered)

    def to_batch_values(self) -> gtsam.Values:
        """The initial value of every variable in the estimate (as it entered iSAM2)."""
        return gtsam.Values(self._initial)

    def batch_graph(self) -> gtsam.NonlinearFactorGraph:
        """Exactly the factors in the estimate, as one graph."""
        graph = gtsam.NonlinearFactorGraph()
        for _, f in sorted(self._in_isam.values(), key=lambda item: item[0]):
            graph.add(self._gtsam_factor(f))
        return graph

    def batch_optimize(self) -> dict[int, np.ndarray]:
        """Levenberg-Marquardt over :meth:`batch_graph` from :meth:`to_batch_values`: key -> 4x4 pose."""
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-12)
        params.setMaxIterations(200)
        values = gtsam.LevenbergMarquardtOptimizer(self.batch_graph(), self.to_batch_values(), params).optimize()
        return {key: values.atPose3(key).matrix() for key in sorted(self._nodes)}

    # ------------------------------------------------------------------ outputs (owner's map frame)

    def estimate(self) -> dict[int, np.ndarray]:
        """The current iSAM2 estimate, key -> 4x4 pose (keys as :meth:`batch_optimize`)."""
        return {key: self._estimate.atPose3(key).matrix() for key in sorted(self._nodes)}

    def estimate_values(self) -> gtsam.Values:
        """The current iSAM2 estimate as ``gtsam.Values`` (a copy), for GTSAM's own tools and files."""
        return gtsam.Values(self._estimate)

    def submap_origin(self, robot: str, index: int) -> np.ndarray | None:
        return self._value(("s", _robot(robot, "robot"), _index(index, "index")))

    def online_pose(self, robot: str, frame_index: int, T_frame_body: np.ndarray) -> np.ndarray | None:
        """Eq. 4.6: ``s_j (+) v_t`` with ``s_j = s[robot,frame_index]`` from the graph and ``v_t`` from the filter."""
        s = self.submap_origin(robot, frame_index)
        return None if s is None else s @ _pose(T_frame_body, "T_frame_body")

    def robot_pose(self, robot: str, t: float) -> np.ndarray | None:
        return self._value(("x", _robot(robot, "robot"), _time(t, "t")))

    def landmark(self, landmark: int) -> np.ndarray | None:
        return self._value(("l", "", _landmark(landmark)))

    def marginal_covariance(self, robot: str, index: int) -> np.ndarray | None:
        """6x6 ``[rotation, translation]`` marginal covariance of ``s[robot,index]`` from iSAM2."""
        node = ("s", _robot(robot, "robot"), _index(index, "index"))
        return self._isam.marginalCovariance(self._keys[node]) if node in self._known else None

    def relative_covariances(self, pairs: list[tuple[tuple[str, int], tuple[str, int]]]) -> dict[tuple, np.ndarray]:
        """6x6 covariances of ``s_a^-1 s_b`` for each pair ``((robot_a, index_a), (robot_b,
        index_b))`` of submap origins in the estimate (thesis 6.1.1: the relative uncertainty
        the thesis approximated by ``sqrt|Σ_a - Σ_b|``). One batch ``gtsam.Marginals`` of the
        current estimate gives each pair's joint 12x12 covariance; with right perturbations,
        ``s_a^-1 s_b`` is perturbed by ``ξ_b - Ad(T_ab^-1) ξ_a``. Pairs with an origin not in
        the estimate are left out."""
        nodes = {}
        for pair in pairs:
            keys = [("s", _robot(r, "robot"), _index(i, "index")) for r, i in pair]
            if all(n in self._known for n in keys):
                nodes[pair] = keys
        if not nodes:
            return {}
        marginals = gtsam.Marginals(self.batch_graph(), self._estimate)
        out = {}
        for pair, (na, nb) in nodes.items():
            ka, kb = self._keys[na], self._keys[nb]
            joint = marginals.jointMarginalCovariance(gtsam.KeyVector([ka, kb])).fullMatrix()
            T_ab = se3_inv(self._estimate.atPose3(ka).matrix()) @ self._estimate.atPose3(kb).matrix()
            J = np.hstack([-adjoint(se3_inv(T_ab)), np.eye(6)])
            out[pair] = J @ joint @ J.T
        return out

    def connected_robots(self) -> list[str]:
        return sorted(self._robots)

    def latest_submap(self, robot: str) -> int | None:
        return self._latest.get(robot)

    def factor_counts(self) -> dict[str, int]:
        counts = Counter(f.type for _, f in self._in_isam.values())
        return {t.value: counts[t] for t in FactorType}

    def pending_count(self) -> int:
        """Factors the inputs define that are not in the estimate (not yet connected or tied; not the dropped, nor
        those GNC rejected: :meth:`rejected_factors`)."""
        self._wanted_factors()
        return sum(fid not in self._rejected for fid in self._waiting)

    def dropped_factors(self) -> list[str]:
        """Every factor a recovery left out for good (:class:`GraphRecovery`), as ``type: node -> node``."""
        return [_describe(f) for f in self._dropped.values()]

    def rejected_factors(self) -> list[str]:
        """The measured factors GNC calls outliers now (``robust: gnc``; none otherwise), as ``type: node -> node``."""
        return [_describe(f) for f in self._rejected.values()]

    def node_count(self) -> int:
        return len(self._known)

    def variables(self) -> dict[int, Node]:
        """Every variable in the estimate, gtsam key -> ``(kind, robot, index)``: kind ``s``, ``x`` or ``l``, robot ``""``
        for a landmark, index the submap index, the time or the landmark id (keys as :meth:`estimate`)."""
        return {key: self._nodes[key] for key in sorted(self._nodes)}

    def signatures(self) -> list[tuple]:
        """``(type, node names, measurement rounded to 1e-6)`` of every factor in the estimate, sorted: the same
        for two graphs that got the same inputs in any order."""
        return sorted(f.signature for _, f in self._in_isam.values())

    def edges(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """``(type, xyz of end 1, xyz of end 2)`` of every binary factor in the estimate, for drawing."""
        out = []
        for _, f in sorted(self._in_isam.values(), key=lambda item: item[0]):
            if len(f.nodes) == 2:
                a, b = (self._value(n)[:3, 3] for n in f.nodes)
                out.append((f.type.value, a, b))
        return out

    def describe(self, key: int) -> str:
        """The name of a gtsam key, e.g. ``s[lru1,3]``, ``x[lru1,12.5]``, ``l[7]``."""
        if key not in self._nodes:
            raise GraphException(f"key {key} is not a variable of this graph")
        return _name(self._nodes[key])

    # ------------------------------------------------------------------ internals

    @staticmethod
    def _register(table: dict, key: tuple, entry: _Registered, what: str) -> None:
        old = table.get(key)
        if old is not None and not old.same(entry):
            raise GraphException(f"{what} was already registered with different values")
        table[key] = entry

    def _measure(self, kind: FactorType, nodes: tuple[Node, Node], T, cov, what: str) -> None:
        f = _Factor(kind, nodes, _pose(T, f"{what}: transform"), _covariance(cov, f"{what}: cov"))
        self._measured.append(f)
        for node in nodes:
            if node[0] == "x" and node not in self._referenced:
                self._referenced.add(node)
                if (node[1], node[2]) in self._poses:
                    self._want(("v", node[1], node[2]), lambda node=node: self._pose_factor(node))
        self._want((kind.value, len(self._measured) - 1), lambda: f)

    def _want(self, fid: tuple, build: Callable[[], _Factor]) -> None:
        """A new input defines factor ``fid`` (built by ``build``): add it to the wanted factors in the local
        reference topology; in the sequential one a new input can change any ``u`` of its frame, so the wanted
        factors are rebuilt from the inputs (:meth:`_wanted_factors`)."""
        if self._wanted is None or fid in self._wanted or fid in self._dropped:
            return
        if self.params.topology is Topology.SEQUENTIAL:
            self._wanted = None
            return
        f = self._wanted[fid] = self._derived.get(fid) or build()
        if f.type not in _ROBUST:
            self._derived[fid] = f
        if fid not in self._in_isam:
            self._waiting[fid] = f

    def _switch_factor(self, robot: str, i: int) -> _Factor:
        w = self._switches[(robot, i)]
        return _Factor(FactorType.FRAME_SWITCH, (("s", robot, i), ("s", robot, i + 1)), w.T, w.cov)

    def _pose_factor(self, node: Node) -> _Factor:
        v = self._poses[(node[1], node[2])]
        return _Factor(FactorType.FILTER_POSE, (("s", node[1], v.frame), node), v.T, v.cov)

    def _key(self, node: Node) -> int:
        key = self._keys.get(node)
        if key is None:
            key = gtsam.symbol(node[0], self._counters[node[0]])
            self._counters[node[0]] += 1
            self._keys[node] = key
            self._nodes[key] = node
        return key

    @property
    def _estimate(self) -> gtsam.Values:
        """The whole estimate, computed from iSAM2 on first use after an update (an update only marks it stale)."""
        if self._values is None:
            self._values = self._isam.calculateEstimate()
        return self._values

    def _value(self, node: Node) -> np.ndarray | None:
        """One variable's estimate: from the whole estimate if computed, else from iSAM2 alone."""
        if node not in self._known:
            return None
        key = self._keys[node]
        return (self._values.atPose3(key) if self._values is not None else self._isam.calculateEstimatePose3(key)).matrix()

    def _enter(self, nodes) -> None:
        """``nodes`` are in the estimate now."""
        self._known.update(nodes)
        for kind, robot, index in nodes:
            if kind != "l":
                self._robots.add(robot)
            if kind == "s" and index > self._latest.get(robot, -1):
                self._latest[robot] = index

    def _spine_ends(self) -> dict[str, int]:
        """Per robot, the last submap index its registered frame switches (none dropped) tie to ``s[r,0]``."""
        if self._ends is None:
            self._ends = {}
            for robot, _ in self._switches:
                if robot not in self._ends:
                    self._advance_end(robot)
        return self._ends

    def _advance_end(self, robot: str) -> None:
        end = self._ends.get(robot, 0)
        while (robot, end) in self._switches and ("w", robot, end) not in self._dropped:
            end += 1
        self._ends[robot] = end

    def _tied(self, node: Node, ends: dict[str, int]) -> bool:
        """Whether ``node`` is tied into the topology of Fig. 4.2b (module docstring): ``s[r,i]`` with no gap in
        the w chain from ``s[r,0]``, ``x[r,t]`` with its registered v in such a frame, any landmark."""
        kind, robot, index = node
        if kind == "l":
            return True
        if kind == "x":
            pose = self._poses.get((robot, index))
            if pose is None or ("v", robot, index) in self._dropped:
                return False
            index = pose.frame
        return index <= ends.get(robot, 0)

    def _plan(self, include_rejected: bool = False) -> tuple[list[tuple], list[tuple[tuple, _Factor]], dict[Node, np.ndarray]]:
        """``(removed, addable, initial)``: ids of factors in iSAM2 no longer desired; pending factors, tied into
        the topology, whose variables are in the estimate or initialised (content order); new variables' values.
        ``include_rejected``: the measured factors GNC rejected count as desired (what a GNC run judges)."""
        wanted = self._wanted_factors()
        excluded = {} if include_rejected else self._rejected
        if self._audit:
            removed = [fid for fid in self._in_isam if fid not in wanted or fid in excluded]
        else:  # iSAM2 holds only wanted factors: what leaves it is what GNC rejected
            removed = sorted((fid for fid in excluded if fid in self._in_isam), key=lambda fid: self._in_isam[fid][0])
        ends = self._spine_ends()
        pending = sorted(
            ((fid, f) for fid, f in self._waiting.items() if fid not in excluded and all(self._tied(n, ends) for n in f.nodes)),
            key=lambda item: item[1].signature,
        )
        initial = self._initialise([f for _, f in pending])
        addable = [(fid, f) for fid, f in pending if all(n in self._known or n in initial for n in f.nodes)]
        return removed, addable, initial

    def _new_isam(self) -> gtsam.ISAM2:
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self.params.relinearize_threshold)
        isam_params.relinearizeSkip = self.params.relinearize_skip
        isam_params.setFactorization(self._factorization)
        return gtsam.ISAM2(isam_params)

    def _commit(self, addable: list[tuple[tuple, _Factor]], initial: dict[Node, np.ndarray], removed: list[tuple], extra_iterations: int) -> None:
        """One incremental ``ISAM2.update``; the bookkeeping changes only once iSAM2 succeeded."""
        graph = gtsam.NonlinearFactorGraph()
        for _, f in addable:
            graph.add(self._gtsam_factor(f))
        values = gtsam.Values()
        for node, T in initial.items():
            values.insert(self._key(node), gtsam.Pose3(T))
        result = self._isam.update(graph, values, [self._in_isam[fid][0] for fid in removed])
        for _ in range(extra_iterations):
            self._isam.update()
        self._settle(removed, addable, result.getNewFactorsIndices())
        self._initial.insert(values)
        self._enter(initial)

    def _settle(self, removed: list[tuple], addable: list[tuple[tuple, _Factor]], indices) -> None:
        """Bookkeeping after iSAM2 took ``addable`` (at factor ``indices``) and left ``removed``."""
        for fid in removed:
            _, f = self._in_isam.pop(fid)
            if fid in self._wanted:
                self._waiting[fid] = f
        for (fid, f), index in zip(addable, indices):
            self._in_isam[fid] = (index, f)
            self._waiting.pop(fid, None)
        self._values, self._audit = None, False

    def _rebuild(self, seed: gtsam.Values, extra_iterations: int) -> None:
        """A fresh iSAM2 over the factors in the estimate and the addable pending ones, in one update (one
        elimination in a fresh order, rooted at the prior's ``s[owner,0]``), the known variables seeded from
        ``seed``; replaces the old on success. Rooted at the prior, a variable that hangs on a loosely held one
        by a single confident factor is eliminated in a clique of its own below it, never in one clique with it
        (the failure the topology rules of the module docstring avoid, in a new robot joining through one loose
        detection or landmark observation while its filter pose is confident)."""
        removed, addable, initial = self._plan()
        kept = [(fid, f) for fid, (_, f) in sorted(self._in_isam.items(), key=lambda item: item[1][0]) if fid not in removed]
        isam, graph, values = self._new_isam(), gtsam.NonlinearFactorGraph(), gtsam.Values()
        for _, f in kept + addable:
            graph.add(self._gtsam_factor(f))
        for node in self._known:
            values.insert(self._keys[node], seed.atPose3(self._keys[node]))
        new_values = gtsam.Values()
        for node, T in initial.items():
            new_values.insert(self._key(node), gtsam.Pose3(T))
        values.insert(new_values)
        rooted = gtsam.KeyGroupMap()  # the owner's first origin (the prior) last: the root of the Bayes tree
        rooted.insert2(self._key(self._prior.nodes[0]), 1)
        result = isam.update(graph, values, [], rooted)
        for _ in range(extra_iterations):
            isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], rooted)
        self._isam = isam
        self._settle(removed, [], [])  # what left goes back to waiting
        self._in_isam = {}  # the fresh iSAM2 holds the kept and the added factors, at new indices
        self._settle([], kept + addable, result.getNewFactorsIndices())
        self._initial.insert(new_values)
        self._enter(initial)

    def _recover(self, exc: Exception, t: float | None, extra_iterations: int) -> None:
        """After iSAM2 failed (module docstring): rebuild, dropping offending new factors, then re-seeding from
        batch Levenberg-Marquardt, then with QR; record what worked as a :class:`GraphRecovery`."""
        error = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        named = self._named_node(exc)
        dropped: list[str] = []
        # the estimate before the failed update: iSAM2's own is unusable now; its linearisation point is within
        # the relinearisation threshold of it
        if self._values is None:
            self._values = gtsam.Values(self._isam.getLinearizationPoint())
        seed, fallbacks, action = self._values, ["levenberg_marquardt", "qr"], RECOVERY_ACTIONS[0]
        while True:
            try:
                self._rebuild(seed, extra_iterations)
                self._stale = None
                break
            except _GTSAM_ERRORS as again:
                victim = self._offender(again)
                if victim is not None:
                    self._dropped[victim] = self._wanted_factors()[victim]
                    self._wanted = self._ends = None  # rebuilt without it
                    dropped.append(_describe(self._dropped[victim]))
                    continue
                if not fallbacks:
                    action, self._stale = RECOVERY_ACTIONS[3], error
                    break
                fallback = fallbacks.pop(0)
                if fallback == "levenberg_marquardt":
                    seed, action = self._levenberg_marquardt(), RECOVERY_ACTIONS[1]
                else:
                    self._factorization, action = "QR", RECOVERY_ACTIONS[2]
        for node in [n for n in self._keys if n not in self._known]:  # keys of variables that never entered
            del self._nodes[self._keys.pop(node)]
        self.recoveries.append(GraphRecovery(t, len(self.update_times), error, named and _name(named), action, tuple(dropped)))

    def _named_node(self, exc: Exception) -> Node | None:
        """The variable a gtsam exception names (``... near variable\n<key> (Symbol: x1)``), if it is ours."""
        match = re.search(r"variable\s+(\d+)", str(exc))
        return self._nodes.get(int(match.group(1))) if match else None

    def _offender(self, exc: Exception) -> tuple | None:
        """The id of the new factor to drop after a failed rebuild: the newest measurement among the addable
        factors that touches the variable gtsam named, else any addable factor touching it, else the newest
        addable measurement, else the last addable factor; None when only the prior or nothing is new."""
        _, addable, _ = self._plan()
        candidates = [(fid, f) for fid, f in addable if f.type is not FactorType.PRIOR]
        named = self._named_node(exc)
        touching = [(fid, f) for fid, f in candidates if named in f.nodes]
        for group in (touching, candidates):
            measured = sorted(((fid, f) for fid, f in group if f.type in _ROBUST), key=lambda item: item[0][1])
            if measured:
                return measured[-1][0]
            if group:
                return group[-1][0]
        return None

    def _classify(self, t: float | None) -> bool:
        """One GNC run (``robust: gnc``, module docstring) over the factors in iSAM2, the addable new ones and the
        rejected ones, seeded with the estimate (new variables initialised as :meth:`_plan` does); every measured
        factor it judges is an inlier or rejected from then on. Records a :class:`GncRun`; never raises on a
        failure of GNC (the classification stays). True when a factor in iSAM2 is now rejected."""
        start = time.perf_counter()
        removed, addable, initial = self._plan(include_rejected=True)
        in_isam = sorted(self._in_isam.items(), key=lambda item: item[1][0])
        factors = [(fid, f) for fid, (_, f) in in_isam if fid not in removed] + addable
        temporary = {node: gtsam.symbol("g", i) for i, node in enumerate(initial)}  # no keys of their own yet

        def key(node: Node) -> int:
            return self._keys[node] if node in self._known else temporary[node]

        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for _, f in factors:
            graph.add(self._gtsam_factor(f, key))
        for node in self._known:
            values.insert(self._keys[node], self._estimate.atPose3(self._keys[node]))
        for node, T in initial.items():
            values.insert(temporary[node], gtsam.Pose3(T))
        measured = [i for i, (_, f) in enumerate(factors) if f.type in _ROBUST]
        params = gtsam.GncLMParams()
        params.setLossType(gtsam.GncLossType.TLS)
        params.setKnownInliers([i for i, (_, f) in enumerate(factors) if f.type not in _ROBUST])
        try:
            gnc = gtsam.GncLMOptimizer(graph, values, params)
            gnc.setInlierCostThresholdsAtProbability(self.params.gnc_inlier_probability)
            result = gnc.optimize()
            weights = np.asarray(gnc.getWeights()).ravel()
            thresholds = np.asarray(gnc.getInlierCostThresholds()).ravel()
            # GNC stops as soon as the weights are binary, weights computed at the estimate before its last
            # solve: a factor it left out that the final estimate satisfies within the threshold is an inlier
            consistent = {i for i in measured if graph.at(i).error(result) <= thresholds[i]}
        except Exception as exc:  # gtsam's (and any other) failure of the classifier: the graph goes on without it
            error = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
            run = GncRun(t, len(self.update_times), len(factors), len(measured), (), 0, 0, 0, time.perf_counter() - start, error)
            self.gnc_runs.append(run)
            return False
        # an outlier whose removal would cut a variable off the rest stays (a bridge): union-find over the inliers
        parent: dict[Node, Node] = {}

        def find(n: Node) -> Node:
            parent.setdefault(n, n)
            while parent[n] != n:
                parent[n] = parent[parent[n]]
                n = parent[n]
            return n

        outliers = {i for i in measured if weights[i] < 0.5 and i not in consistent}
        for i, (_, f) in enumerate(factors):
            roots = [find(n) for n in f.nodes]
            if i not in outliers:
                for r in roots[1:]:
                    parent[r] = roots[0]
        bridges = 0
        for i in sorted(outliers, key=lambda i: (-weights[i], factors[i][1].signature)):
            a, b = (find(n) for n in factors[i][1].nodes)
            if a != b:
                parent[b] = a
                outliers.discard(i)
                bridges += 1
        judged = {factors[i][0] for i in measured}
        rejected = {factors[i][0]: factors[i][1] for i in sorted(outliers)}
        readmitted = sum(fid in self._rejected and fid not in rejected for fid in judged)
        newly = sum(fid not in self._rejected for fid in rejected)
        self._rejected = {fid: f for fid, f in self._rejected.items() if fid not in judged} | rejected
        described = tuple(_describe(f) for f in rejected.values())
        run = GncRun(t, len(self.update_times), len(factors), len(measured), described, newly, readmitted, bridges, time.perf_counter() - start)
        self.gnc_runs.append(run)
        return any(fid in self._in_isam for fid in rejected)

    def _levenberg_marquardt(self) -> gtsam.Values:
        """Batch Levenberg-Marquardt over the factors in the estimate from their initial values; the current
        estimate where it fails."""
        try:
            graph = self.batch_graph()
            values = gtsam.LevenbergMarquardtOptimizer(graph, self.to_batch_values(), gtsam.LevenbergMarquardtParams()).optimize()
            return values if all(values.exists(self._keys[n]) for n in self._known) else self._estimate
        except _GTSAM_ERRORS:
            return self._estimate

    def _wanted_factors(self) -> dict[tuple, _Factor]:
        """Every factor the inputs so far define, by a stable id (in iSAM2 or pending), the measured factors GNC
        rejected included (their robot poses stay, with their filter poses); dropped factors excluded. Kept up to
        date input by input (:meth:`_want`); rebuilt from the inputs after a drop and, in the sequential
        topology, after any input."""
        if self._wanted is not None:
            return self._wanted
        wanted: dict[tuple, _Factor] = {("prior",): self._prior}
        measured = {fid: f for seq, f in enumerate(self._measured) if (fid := (f.type.value, seq)) not in self._dropped}
        self._referenced = {n for f in measured.values() for n in f.nodes if n[0] == "x"}
        referenced = sorted(n for n in self._referenced if (n[1], n[2]) in self._poses)
        if self.params.topology is Topology.LOCAL_REFERENCE:
            for robot, i in self._switches:
                fid = ("w", robot, i)
                wanted[fid] = self._derived.get(fid) or self._switch_factor(robot, i)
            for node in referenced:
                fid = ("v", node[1], node[2])
                wanted[fid] = self._derived.get(fid) or self._pose_factor(node)
        else:
            self._sequential(wanted, referenced)
        self._derived.update(wanted)
        wanted.update(measured)
        for fid in self._dropped:
            wanted.pop(fid, None)
        self._wanted = wanted
        self._waiting = {fid: f for fid, f in wanted.items() if fid not in self._in_isam}
        self._audit = True
        return wanted

    def _sequential(self, desired: dict[tuple, _Factor], referenced: list[Node]) -> None:
        """u factors (eq. 4.8, 4.9) along each robot's frame: s_k, its poses in the graph, s_{k+1}, by time."""
        chains: dict[tuple[str, int], list[tuple[tuple[float, int], Node, _Registered]]] = {}
        for (robot, i), w in self._switches.items():
            chains.setdefault((robot, i), []).append(((w.t, 1), ("s", robot, i + 1), w))
        for node in referenced:
            v = self._poses[(node[1], node[2])]
            chains.setdefault((node[1], v.frame), []).append(((v.t, 0), node, v))
        for (robot, k), chain in chains.items():
            prev, P_prev, cov_prev = ("s", robot, k), np.eye(4), np.zeros((6, 6))
            for _, node, entry in sorted(chain, key=lambda item: item[0]):
                fid = ("u", prev, node)
                if fid in self._derived:
                    desired[fid] = self._derived[fid]
                else:
                    lam, V = np.linalg.eigh(entry.cov - cov_prev)
                    cov = (V * np.maximum(lam, self.params.min_sequential_var)) @ V.T
                    desired[fid] = _Factor(FactorType.ODOMETRY, (prev, node), se3_inv(P_prev) @ entry.T, 0.5 * (cov + cov.T))
                prev, P_prev, cov_prev = node, entry.T, entry.cov

    def _initialise(self, pending: list[_Factor]) -> dict[Node, np.ndarray]:
        """Initial values of the new variables reachable from the estimate (or the prior) through pending factors,
        breadth-first in the given order: ``T_b = T_a z`` along a factor, ``T_a = T_b z^-1`` against it."""
        initial: dict[Node, np.ndarray] = {}
        adjacent: dict[Node, list[_Factor]] = {}
        for f in pending:
            if len(f.nodes) == 1 and f.nodes[0] not in self._known:
                initial[f.nodes[0]] = f.z
            for n in f.nodes:
                adjacent.setdefault(n, []).append(f)
        queue = deque(n for n in adjacent if n in self._known or n in initial)
        while queue:
            node = queue.popleft()
            T = initial[node] if node in initial else self._value(node)
            for f in adjacent[node]:
                if len(f.nodes) == 1:
                    continue
                a, b = f.nodes
                other = b if node == a else a
                if other not in self._known and other not in initial:
                    initial[other] = T @ f.z if node == a else T @ se3_inv(f.z)
                    queue.append(other)
        return initial

    def _gtsam_factor(self, f: _Factor, key: Callable[[Node], int] | None = None) -> gtsam.NonlinearFactor:
        """The gtsam factor of ``f``: Gaussian, the measured ones with the Cauchy kernel under ``robust: cauchy``;
        ``key``: node -> gtsam key (default: the graph's own, allocated on first use)."""
        noise = gtsam.noiseModel.Gaussian.Covariance(f.cov)
        if f.type in _ROBUST and self.params.robust is RobustKernel.CAUCHY and math.isfinite(self.params.cauchy_c):
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(self.params.cauchy_c), noise)
        keys = [(key or self._key)(n) for n in f.nodes]
        if f.type is FactorType.PRIOR:
            return gtsam.PriorFactorPose3(keys[0], gtsam.Pose3(f.z), noise)
        return gtsam.BetweenFactorPose3(keys[0], keys[1], gtsam.Pose3(f.z), noise)
