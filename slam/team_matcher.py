"""One robot's submap matcher in the team (thesis 6.1, fig. 6.1): the pairing side
prepares every submap the robot holds, its own and its peers', and queues the candidate
pairs it owns (:func:`pair_owner`) from its graph's latest estimate; the matching side
takes the best of them. The agent turns successes into loop closure messages (``c``
factors, 4.2.2).

The thesis runs the two sides as threads of a low-priority process; here they are the
lane's background jobs ``pairing`` and ``matching`` (see ``sim.run.onboard``). Its
matchers on several robots tell each other which pairs they take up (3.3), so each pair
is tried once; announcements cannot stop two robots that start on a pair before hearing
of each other, so here every pair has one owner, fixed by the pair itself
(docs/matching.md, "In the team").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.graph import MultiRobotGraph
from slam.matcher import Candidate, Keypoints, MatcherParams, MatchResult, PairQueue, Prior, SubmapKey, match_pair
from slam.submap import Submap


def pair_owner(a: SubmapKey, b: SubmapKey) -> str:
    """The one robot that matches submaps ``a`` and ``b``: a robot its own pairs; of two
    robots' submaps, either robot by the parity of the submap indices, so that each
    holds its own submap of the pair and owns half of their pairs."""
    (ra, ia), (rb, ib) = sorted((a, b))
    return ra if ra == rb or (ia + ib) % 2 == 0 else rb


@dataclass(frozen=True)
class MatchRecord:
    """One attempt of this robot: when it finished, the pair's local frames, the graph's
    prior and the result (for evaluation against ground truth)."""

    t: float
    frame_a: int
    frame_b: int
    prior: Prior
    result: MatchResult


@dataclass(frozen=True)
class PendingMatch:
    """A started attempt (:meth:`TeamMatcher.start`): everything :func:`match_pair` needs.
    :meth:`run` touches no state but the two submaps' cached features and geometry."""

    cand: Candidate
    prior: Prior
    a: Keypoints
    b: Keypoints
    params: MatcherParams

    def run(self) -> MatchResult:
        return match_pair(self.a, self.b, self.params, self.prior)


class TeamMatcher:
    """Pairing and matching state of robot ``robot`` (see the module docstring)."""

    def __init__(self, params: MatcherParams, robot: str):
        self.params = params
        self.robot = robot
        self.queue = PairQueue(params)
        self.frames: dict[SubmapKey, int] = {}
        self.records: list[MatchRecord] = []
        self._pending: list[Submap] = []
        self._origins: dict[SubmapKey, np.ndarray] = {}
        self._unplaced: set[SubmapKey] = set()  # prepared, but without an origin in the graph at the last pairing
        self.stale = False  # the graph changed since the last pairing in a way that matters to it
        self.not_queued: dict[str, int] = {}  # the last pairing's open pairs of this robot it did not queue, by reason

    def add_submap(self, submap: Submap) -> None:
        """A finished submap (own or a peer's) to prepare in the next pairing job."""
        self._pending.append(submap)

    @property
    def waiting(self) -> int:
        """Submaps received and not yet prepared by a pairing job."""
        return len(self._pending)

    def graph_updated(self, graph: MultiRobotGraph) -> None:
        """After an optimisation: pair again if a submap the last pairing could not place has an origin now
        (its frame switch, or the link to its robot, came after that pairing)."""
        if any(graph.submap_origin(robot, self.frames[(robot, i)]) is not None for robot, i in self._unplaced):
            self.stale = True

    @property
    def pairing_due(self) -> bool:
        return bool(self._pending) or self.stale

    @property
    def has_work(self) -> bool:
        return self.pairing_due or len(self.queue) > 0

    def pair(self, graph: MultiRobotGraph) -> int:
        """Pairing (6.1.1): prepare the new submaps, then rebuild the queue of the pairs this
        robot owns from the graph. Eq. 6.1 needs each pair's relative sigmas; ``sigma_a +
        sigma_b`` bounds them from above, so only pairs that overlap with that widening get
        the joint marginals. Returns the number of queued pairs."""
        for submap in self._pending:
            self.queue.add(submap)
            self.frames[submap.key] = submap.frame_index
        self._pending = []
        self.stale = False
        origins, sigmas, self._unplaced = {}, {}, set()
        for key in self.queue.prepared:
            robot, frame = key[0], self.frames[key]
            S = graph.submap_origin(robot, frame)
            if S is None:
                self._unplaced.add(key)
                continue
            cov = graph.marginal_covariance(robot, frame)
            if cov is not None:
                origins[key] = S
                sigmas[key] = np.sqrt(np.maximum(np.diag(S[:3, :3] @ cov[3:, 3:] @ S[:3, :3].T), 0.0))
        self._origins = origins
        wide = {}
        for a, b in self.queue.open_pairs():
            if a in origins and b in origins and pair_owner(a, b) == self.robot:
                bound = np.eye(6)
                bound[3:, 3:] = np.diag(np.square(sigmas[a] + sigmas[b]))
                bound[3:, 3:] = origins[b][:3, :3].T @ bound[3:, 3:] @ origins[b][:3, :3]  # into b's frame
                wide[(a, b)] = bound
        self.queue.refresh(origins, wide)
        not_queued = dict(self.queue.rejected)
        survivors = [c.pair for c in self.queue.candidates()]
        pairs = [((a[0], self.frames[a]), (b[0], self.frames[b])) for a, b in survivors]
        exact = graph.relative_covariances(pairs)
        self.queue.refresh(origins, {pair: exact[g] for pair, g in zip(survivors, pairs) if g in exact})
        for reason, n in self.queue.rejected.items():
            not_queued[reason] = not_queued.get(reason, 0) + n
        self.not_queued = not_queued
        return len(self.queue)

    def next_candidate(self) -> Candidate | None:
        return self.queue.pop()

    def attempt(self, cand: Candidate, t: float) -> MatchRecord:
        """Matching (6.1.2) of one queued pair against the prior from the last pairing:
        :meth:`start`, :meth:`PendingMatch.run` and :meth:`finish` in one go."""
        pending = self.start(cand)
        return self.finish(pending, pending.run(), t)

    def start(self, cand: Candidate) -> PendingMatch:
        """An attempt's first part: the pair is taken, its prior fixed from the last pairing.
        The :class:`PendingMatch` may then run anywhere (``sim/run/onboard.py`` runs it beside
        the run loop) while the matcher takes new submaps; the next pairing or attempt
        waits for :meth:`finish`."""
        a, b = cand.pair
        self.queue.mark_attempted(cand.pair)
        S_a, S_b = self._origins[a], self._origins[b]
        prior = Prior(np.linalg.inv(S_a) @ S_b, cand.sigma_xyz, cand.sigma_yaw)
        return PendingMatch(cand, prior, self.queue.prepared[a], self.queue.prepared[b], self.params)

    def finish(self, pending: PendingMatch, result: MatchResult, t: float) -> MatchRecord:
        """An attempt's last part: the matched pair's geometry is held, the record kept."""
        a, b = pending.cand.pair
        self.queue.hold_geometry(pending.cand.pair)
        record = MatchRecord(t, self.frames[a], self.frames[b], pending.prior, result)
        self.records.append(record)
        return record
