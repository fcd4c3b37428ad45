"""One robot's submap matcher in the team (thesis 6.1, fig. 6.1): the pairing side
prepares every submap the robot holds, its own and its peers', and queues candidate
pairs from its graph's latest estimate; the matching side takes the best pair, which
the robot announces to the team (a match attempt) before matching it. The agent turns
successes into loop closure messages (``c`` factors, 4.2.2).

The thesis runs the two sides as threads of a low-priority process; here they are the
lane's background jobs ``pairing`` and ``matching`` (see ``sim.run.onboard``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.graph import MultiRobotGraph
from slam.matcher import Candidate, MatcherParams, MatchResult, PairQueue, Prior, SubmapKey, match_pair
from slam.submap import Submap


@dataclass(frozen=True)
class MatchRecord:
    """One attempt of this robot: when it finished, the pair's local frames, the graph's
    prior and the result (for evaluation against ground truth)."""

    t: float
    frame_a: int
    frame_b: int
    prior: Prior
    result: MatchResult


class TeamMatcher:
    """Pairing and matching state of one robot (see the module docstring)."""

    def __init__(self, params: MatcherParams):
        self.params = params
        self.queue = PairQueue(params)
        self.frames: dict[SubmapKey, int] = {}
        self.records: list[MatchRecord] = []
        self._pending: list[Submap] = []
        self._origins: dict[SubmapKey, np.ndarray] = {}
        self.stale = False  # a loop closure changed the graph since the last pairing

    def add_submap(self, submap: Submap) -> None:
        """A finished submap (own or a peer's) to prepare in the next pairing job."""
        self._pending.append(submap)

    def mark_attempted(self, a: SubmapKey, b: SubmapKey) -> None:
        self.queue.mark_attempted((a, b) if a <= b else (b, a))

    @property
    def pairing_due(self) -> bool:
        return bool(self._pending) or self.stale

    @property
    def has_work(self) -> bool:
        return self.pairing_due or len(self.queue) > 0

    def pair(self, graph: MultiRobotGraph) -> int:
        """Pairing (6.1.1): prepare the new submaps, then rebuild the queue from the graph.
        Eq. 6.1 needs each pair's relative sigmas; ``sigma_a + sigma_b`` bounds them from
        above, so only pairs that overlap with that widening get the joint marginals.
        Returns the number of queued pairs."""
        for submap in self._pending:
            self.queue.add(submap)
            self.frames[submap.key] = submap.frame_index
        self._pending = []
        self.stale = False
        origins, sigmas = {}, {}
        for key in self.queue.prepared:
            robot, frame = key[0], self.frames[key]
            S = graph.submap_origin(robot, frame)
            cov = graph.marginal_covariance(robot, frame) if S is not None else None
            if cov is not None:
                origins[key] = S
                sigmas[key] = np.sqrt(np.maximum(np.diag(S[:3, :3] @ cov[3:, 3:] @ S[:3, :3].T), 0.0))
        self._origins = origins
        wide = {}
        for a, b in self.queue.open_pairs():
            if a in origins and b in origins:
                bound = np.eye(6)
                bound[3:, 3:] = np.diag(np.square(sigmas[a] + sigmas[b]))
                bound[3:, 3:] = origins[b][:3, :3].T @ bound[3:, 3:] @ origins[b][:3, :3]  # into b's frame
                wide[(a, b)] = bound
        self.queue.refresh(origins, wide)
        survivors = [c.pair for c in self.queue.candidates()]
        pairs = [((a[0], self.frames[a]), (b[0], self.frames[b])) for a, b in survivors]
        exact = graph.relative_covariances(pairs)
        self.queue.refresh(origins, {pair: exact[g] for pair, g in zip(survivors, pairs) if g in exact})
        return len(self.queue)

    def next_candidate(self) -> Candidate | None:
        return self.queue.pop()

    def attempt(self, cand: Candidate, t: float) -> MatchRecord:
        """Matching (6.1.2) of one queued pair against the prior from the last pairing."""
        a, b = cand.pair
        self.queue.mark_attempted(cand.pair)
        S_a, S_b = self._origins[a], self._origins[b]
        prior = Prior(np.linalg.inv(S_a) @ S_b, cand.sigma_xyz)
        result = match_pair(self.queue.prepared[a], self.queue.prepared[b], self.params, prior)
        record = MatchRecord(t, self.frames[a], self.frames[b], prior, result)
        self.records.append(record)
        return record
