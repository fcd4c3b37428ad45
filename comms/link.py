"""One direction of a link: a priority queue of transfers, a transmitter, a channel.

The transmitter sends one fragment at a time: it takes ``8 * size / bandwidth`` of
simulated time (serialization), then the fragment propagates for ``latency`` plus a
uniform extra delay in ``[0, jitter]``. Between two fragments the transmitter picks
the most urgent transfer again, so a small pose message preempts a 700 KB submap at
the next fragment boundary (thesis 8.4 sizes). Within a priority, first come first
served. Arrivals never overtake each other (a link is a pipe, not a mesh). Loss is
drawn per fragment. A link that follows a trace (:mod:`comms.trace`) looks up the row in
effect when a fragment starts to serialize (bisect on the time) and takes that row's
bandwidth, latency and loss for the fragment. Driven by SimPy callbacks, not processes,
to keep events cheap.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import IntEnum
from typing import TYPE_CHECKING, Protocol

import simpy

from comms.config import LinkConfig
from comms.loss import Loss, UniformStream
from comms.message import Envelope

if TYPE_CHECKING:
    from comms.accounting import LinkStats

ACK_PRIORITY = -1  # acknowledgements go before every message kind
_LEVELS = 17  # priorities -1 .. 15


class TransferState(IntEnum):
    QUEUED = 0  # waiting in, or being sent from, the link's queue
    AWAIT_ACK = 1  # reliable: round sent, waiting for the acknowledgement
    DONE = 2  # the sender is finished with it
    ABANDONED = 3  # pulled off this link (outage, reroute, give-up, dropped)


@dataclass(slots=True, eq=False)
class Transfer:
    """One message crossing one link (one hop). Holds the sender's progress and the
    receiver's reassembly of this hop."""

    envelope: Envelope
    link: Link
    seq: int  # order of arrival at the sending node (keeps store-and-forward in order)
    sizes: list[int]  # fragment sizes in bytes
    reliable: bool = False
    max_retries: int = 0
    ack_for: Transfer | None = None  # set on acknowledgements: the transfer they answer
    pending: list[int] = field(default_factory=list)  # fragment indices of this round
    cursor: int = 0
    round: int = 0
    retries: int = 0
    state: TransferState = TransferState.QUEUED
    token: int = 0  # queue entries carry it; an old token marks a stale entry
    failed: bool = False  # best effort: a fragment was lost, the message with it
    confirmed: bytearray | None = None  # reliable: fragments the receiver acknowledged
    received: bytearray | None = None  # receiver: fragments arrived
    received_count: int = 0
    completed: bool = False  # receiver: all fragments arrived

    def __post_init__(self) -> None:
        n = len(self.sizes)
        self.pending = list(range(n))
        self.received = bytearray(n)
        if self.reliable:
            self.confirmed = bytearray(n)

    @property
    def priority(self) -> int:
        return ACK_PRIORITY if self.ack_for is not None else self.envelope.message.priority

    @property
    def started(self) -> bool:
        return self.cursor > 0 or self.round > 0

    def remaining_bytes(self) -> int:
        sizes = self.sizes
        return sum(sizes[i] for i in self.pending[self.cursor :])


class LinkHost(Protocol):
    """What a link reports to its network."""

    def _fragment_lost(self, transfer: Transfer, index: int) -> None: ...
    def _fragment_arrived(self, transfer: Transfer, index: int, round_: int, last_of_round: bool) -> None: ...
    def _round_sent(self, transfer: Transfer) -> None: ...


class Link:
    """The direction ``src -> dst``. ``up`` is maintained by
    :class:`comms.availability.Availability` through :meth:`block`."""

    def __init__(
        self,
        env: simpy.Environment,
        src: str,
        dst: str,
        cfg: LinkConfig,
        loss: Loss,
        jitter: UniformStream,
        host: LinkHost,
        stats: LinkStats,
    ):
        self.env, self.src, self.dst, self.cfg = env, src, dst, cfg
        self.name = f"{src}->{dst}"
        self._loss, self._jitter, self._host, self.stats = loss, jitter, host, stats
        self._bits_per_s = float(cfg.bandwidth_bps)
        self._trace = cfg.trace
        self._queues: list[deque[tuple[int, Transfer]]] = [deque() for _ in range(_LEVELS)]
        self._busy = False
        self._current: tuple[Transfer, int, int, int, float, float] | None = None  # ..., epoch, send time, latency
        self._last_arrival = 0.0
        self.epoch = 0  # +1 each time the link goes down: aborts a fragment in serialization
        self.blocks: dict[str, int] = {}  # reason -> count; up when all are zero
        self.up = True
        self.queued_bytes = 0

    # ------------------------------------------------------------------ state

    def reasons(self) -> tuple[str, ...]:
        return tuple(sorted(r for r, n in self.blocks.items() if n > 0))

    def block(self, reason: str, delta: int) -> bool:
        """Add ``delta`` to a blocking reason; True if ``up`` flipped."""
        self.blocks[reason] = max(0, self.blocks.get(reason, 0) + delta)
        up = not any(n > 0 for n in self.blocks.values())
        if up == self.up:
            return False
        self.up = up
        if not up:
            self.epoch += 1
        self.stats.state(self.env.now, up)
        return True

    def set_block(self, reason: str, blocked: bool) -> bool:
        current = self.blocks.get(reason, 0) > 0
        if current == blocked:
            return False
        return self.block(reason, 1 if blocked else -1)

    # ------------------------------------------------------------------ queue

    def enqueue(self, transfer: Transfer, front: bool = False) -> None:
        transfer.token += 1
        transfer.state = TransferState.QUEUED
        queue = self._queues[transfer.priority + 1]
        entry = (transfer.token, transfer)
        if front:
            queue.appendleft(entry)
        else:
            queue.append(entry)
        self._add_bytes(transfer.remaining_bytes())
        self.kick()

    def remove(self, transfer: Transfer) -> None:
        """Take a queued transfer off the queue (it keeps its stale entry, skipped later)."""
        if transfer.state == TransferState.QUEUED:
            transfer.token += 1
            self._add_bytes(-transfer.remaining_bytes())

    def sending(self, transfer: Transfer) -> bool:
        """True while one of the transfer's fragments is being serialized."""
        return self._current is not None and self._current[0] is transfer

    def queued(self) -> Iterator[Transfer]:
        """The transfers waiting in (or being sent from) the queue."""
        for queue in self._queues:
            for token, t in queue:
                if token == t.token and t.state == TransferState.QUEUED:
                    yield t

    def drain(self) -> list[Transfer]:
        """Take every queued transfer off, in the order they came to the node."""
        out = sorted(self.queued(), key=lambda t: t.seq)
        for t in out:
            t.token += 1
        for queue in self._queues:
            queue.clear()
        self._add_bytes(-self.queued_bytes)
        return out

    def _add_bytes(self, delta: int) -> None:
        if delta:
            self.queued_bytes += delta
            self.stats.queue(self.env.now, self.queued_bytes)

    def _head(self) -> Transfer | None:
        for queue in self._queues:
            while queue:
                token, t = queue[0]
                if token == t.token and t.state == TransferState.QUEUED:
                    return t
                queue.popleft()
        return None

    # ------------------------------------------------------------------ transmitter

    def kick(self) -> None:
        """Start the next fragment if the link is up and idle."""
        if self._busy or not self.up:
            return
        t = self._head()
        if t is None:
            return
        index = t.pending[t.cursor]
        now = self.env.now
        if self._trace is None:
            bits_per_s, latency = self._bits_per_s, self.cfg.latency_s
        else:
            row = self._trace.row(now)
            bits_per_s, latency = self._trace.bandwidth_bps[row], self._trace.latency_s[row]
        self._busy = True
        self._current = (t, index, t.token, self.epoch, now, latency)
        event = self.env.timeout(8.0 * t.sizes[index] / bits_per_s)
        event.callbacks.append(self._serialized)

    def _serialized(self, _event: simpy.Event) -> None:
        self._busy = False
        t, index, token, epoch, sent, latency = self._current
        self._current = None
        if epoch != self.epoch or token != t.token or t.state != TransferState.QUEUED:
            # the link went down meanwhile, or the transfer left the queue: aborted
            self.kick()
            return
        size = t.sizes[index]
        now = self.env.now
        self._add_bytes(-size)
        self.stats.fragment_sent(size, ack=t.ack_for is not None, retransmission=t.round > 0)
        t.cursor += 1
        last = t.cursor == len(t.pending)
        if last:
            t.token += 1  # leaves the queue; its entry goes stale
        if self._loss.lost(sent):
            self.stats.fragment_lost(size)
            self._host._fragment_lost(t, index)
        else:
            arrival = now + latency
            if self.cfg.jitter_s > 0.0:
                arrival += self.cfg.jitter_s * self._jitter.next()
            arrival = max(arrival, self._last_arrival)
            self._last_arrival = arrival
            event = self.env.timeout(arrival - now, value=(t, index, t.round, last))
            event.callbacks.append(self._arrived)
        if last:
            self._host._round_sent(t)
        self.kick()

    def _arrived(self, event: simpy.Event) -> None:
        t, index, round_, last = event.value
        self.stats.fragment_arrived(t.sizes[index])
        self._host._fragment_arrived(t, index, round_, last)
