"""When links are up: schedules, windows, random outages, range and line of sight.

A link is up while nothing blocks it. Blocking reasons:

- ``disabled``: ``enabled: false`` for the link, or for the whole section;
- ``outage``: a scheduled (``outages``) or random (``random_outages``) outage of the
  link, of one of its nodes, or of the whole network (thesis 9.2: total outages);
- ``window``: outside the link's ``windows`` (e.g. the SpaceBotCamp uplink, blocked
  except in short checkpoints);
- ``range``: the nodes are farther apart than ``range_m``;
- ``line_of_sight``: the caller's line-of-sight test fails (a ray against the terrain);
- ``fault``: a node's radio failed (:meth:`Availability.node_fault`, the simulator's injected faults).

Range and line of sight come from callbacks the simulator supplies (positions of the
nodes; a ray test between two nodes), evaluated at construction and then every
``poll_interval_s``. A node missing from the positions (a ground station) is never
out of range or sight. Every batch of changes reaches ``on_change`` at once, so a
node outage reroutes once, not once per link.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping
from itertools import combinations

import numpy as np
import simpy

from comms.config import CommsConfig, RandomOutageConfig, outage_links
from comms.errors import CommsError
from comms.link import Link

Positions = Callable[[], Mapping[str, np.ndarray]]
LineOfSight = Callable[[str, str], bool]


class Availability:
    def __init__(
        self,
        env: simpy.Environment,
        config: CommsConfig,
        nodes: list[str],
        links: dict[tuple[str, str], Link],
        on_change: Callable[[list[Link]], None],
        seed: int,
        positions: Positions | None = None,
        line_of_sight: LineOfSight | None = None,
    ):
        self.env, self.config, self.nodes, self.links = env, config, nodes, links
        self._on_change = on_change
        self._seed = seed
        self._positions, self._los = positions, line_of_sight
        self.polls = 0
        self.los_queries = 0

        changed: set[Link] = set()
        for link in links.values():
            if not (config.enabled and link.cfg.enabled) and link.block("disabled", 1):
                changed.add(link)

        # windows: one process per distinct window list
        groups: dict[tuple[tuple[float, float], ...], list[Link]] = {}
        for link in links.values():
            if link.cfg.windows is not None:
                groups.setdefault(tuple(tuple(w) for w in link.cfg.windows), []).append(link)
        for windows, members in groups.items():
            changed |= self._apply_windows(windows, members)
            env.process(self._window_process(windows, members))

        for spec in config.outages:
            members = [links[k] for k in outage_links(spec, nodes)]
            if spec.start_s <= env.now < spec.end_s:  # already on: block before anything is sent
                changed |= {link for link in members if link.block("outage", 1)}
            env.process(self._outage_process(spec.start_s, spec.end_s, members))
        for i, spec in enumerate(config.random_outages):
            members = [links[k] for k in outage_links(spec, nodes)]
            rng = np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(f"random_outage/{i}".encode())]))
            env.process(self._random_outage_process(spec, members, rng))

        # range and line of sight
        self._pairs = [
            (a, b)
            for a, b in combinations(nodes, 2)
            if self._needs_geometry(links[(a, b)]) or self._needs_geometry(links[(b, a)])
        ]
        if self._pairs:
            needs_range = any(links[p].cfg.range_m is not None for a, b in self._pairs for p in ((a, b), (b, a)))
            needs_los = any(links[p].cfg.line_of_sight for a, b in self._pairs for p in ((a, b), (b, a)))
            if positions is None:
                what = "range_m" if needs_range else "line_of_sight"
                raise CommsError(
                    f"links use {what} (e.g. {self._pairs[0][0]}<->{self._pairs[0][1]}), "
                    "so the network needs a positions callback"
                )
            if needs_los and line_of_sight is None:
                raise CommsError("links require line_of_sight, so the network needs a line_of_sight callback")
            changed |= self.poll()
            env.process(self._poll_process())
        if changed:
            on_change(sorted(changed, key=lambda link: link.name))

    @staticmethod
    def _needs_geometry(link: Link) -> bool:
        return link.cfg.range_m is not None or link.cfg.line_of_sight

    # ------------------------------------------------------------------ windows and outages

    def _apply_windows(self, windows, members: list[Link]) -> set[Link]:
        now = self.env.now
        inside = any(start <= now < end for start, end in windows)
        return {link for link in members if link.set_block("window", not inside)}

    def _window_process(self, windows, members: list[Link]):
        edges = sorted({t for w in windows for t in w})
        for t in edges:
            if t <= self.env.now:
                continue
            yield self.env.timeout(t - self.env.now)
            self._emit(self._apply_windows(windows, members))

    def _outage_process(self, start: float, end: float, members: list[Link]):
        if end <= self.env.now:
            return
        if start > self.env.now:
            yield self.env.timeout(start - self.env.now)
            self._emit({link for link in members if link.block("outage", 1)})
        yield self.env.timeout(end - self.env.now)
        self._emit({link for link in members if link.block("outage", -1)})

    def node_fault(self, node: str, start: float, end: float | None) -> None:
        """Every link to and from ``node`` is down (reason ``fault``: its radio failed) from ``start`` until
        ``end`` (None: for good)."""
        if node not in self.nodes:
            raise CommsError(f"no node named {node!r}; nodes: {list(self.nodes)}")
        members = [link for (a, b), link in self.links.items() if node in (a, b)]
        self.env.process(self._fault_process(start, end, members))

    def _fault_process(self, start: float, end: float | None, members: list[Link]):
        if start > self.env.now:
            yield self.env.timeout(start - self.env.now)
        self._emit({link for link in members if link.block("fault", 1)})
        if end is not None:
            yield self.env.timeout(max(0.0, end - self.env.now))
            self._emit({link for link in members if link.block("fault", -1)})

    def _random_outage_process(self, spec: RandomOutageConfig, members: list[Link], rng: np.random.Generator):
        if spec.start_s > self.env.now:
            yield self.env.timeout(spec.start_s - self.env.now)
        while True:
            yield self.env.timeout(float(rng.exponential(spec.mean_up_s)))
            self._emit({link for link in members if link.block("outage", 1)})
            yield self.env.timeout(float(rng.exponential(spec.mean_down_s)))
            self._emit({link for link in members if link.block("outage", -1)})

    # ------------------------------------------------------------------ geometry

    def poll(self) -> set[Link]:
        """Evaluate range and line of sight now; the links whose state flipped."""
        self.polls += 1
        positions = self._positions()
        changed: set[Link] = set()
        for a, b in self._pairs:
            ab, ba = self.links[(a, b)], self.links[(b, a)]
            pa, pb = positions.get(a), positions.get(b)
            if pa is None or pb is None:
                in_ab = in_ba = True
                sight = True
            else:
                distance = float(np.linalg.norm(np.asarray(pa, dtype=float) - np.asarray(pb, dtype=float)))
                in_ab = ab.cfg.range_m is None or distance <= ab.cfg.range_m
                in_ba = ba.cfg.range_m is None or distance <= ba.cfg.range_m
                sight = True
                if (ab.cfg.line_of_sight and in_ab) or (ba.cfg.line_of_sight and in_ba):
                    self.los_queries += 1
                    sight = bool(self._los(a, b))
            for link, in_range in ((ab, in_ab), (ba, in_ba)):
                if link.set_block("range", not in_range):
                    changed.add(link)
                blocked = link.cfg.line_of_sight and in_range and not sight
                if link.set_block("line_of_sight", blocked):
                    changed.add(link)
        return changed

    def _poll_process(self):
        interval = self.config.poll_interval_s
        while True:
            yield self.env.timeout(interval)
            self._emit(self.poll())

    def _emit(self, changed: set[Link]) -> None:
        if changed:
            self._on_change(sorted(changed, key=lambda link: link.name))
