"""Routes over the links that are up, through relay nodes only.

A message goes straight to its destination when that link is up; otherwise over the
cheapest chain of up links whose inner nodes are relays (the lander or the
hexacopter, thesis 7.2). Cost of a hop: its latency plus one MTU's serialization
time; ties go to fewer hops, then to node names, so routes are deterministic. Routes
are recomputed lazily after any link changes state.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable


class Router:
    def __init__(
        self,
        nodes: Iterable[str],
        relays: Iterable[str],
        cost: dict[tuple[str, str], float],
        is_up: Callable[[str, str], bool],
    ):
        self.nodes = sorted(nodes)
        self.relays = set(relays)
        self._cost = cost
        self._is_up = is_up
        self._neighbours = {n: sorted(b for (a, b) in cost if a == n) for n in self.nodes}
        self._trees: dict[str, dict[str, tuple[str, ...]]] = {}

    def invalidate(self) -> None:
        self._trees.clear()

    def _tree(self, src: str) -> dict[str, tuple[str, ...]]:
        tree = self._trees.get(src)
        if tree is not None:
            return tree
        tree = {}
        heap: list[tuple[float, int, str, tuple[str, ...]]] = [(0.0, 0, src, (src,))]
        while heap:
            cost, hops, node, path = heapq.heappop(heap)
            if node in tree:
                continue
            tree[node] = path
            if node != src and node not in self.relays:
                continue  # only relays forward
            for nxt in self._neighbours[node]:
                if nxt not in tree and self._is_up(node, nxt):
                    heapq.heappush(heap, (cost + self._cost[(node, nxt)], hops + 1, nxt, (*path, nxt)))
        self._trees[src] = tree
        return tree

    def path(self, src: str, dst: str) -> tuple[str, ...] | None:
        """The nodes from ``src`` to ``dst`` (both included), or None if unreachable."""
        return self._tree(src).get(dst)

    def next_hop(self, src: str, dst: str) -> str | None:
        path = self._tree(src).get(dst)
        return None if path is None or len(path) < 2 else path[1]
