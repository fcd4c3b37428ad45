"""The network: named nodes, one link per direction, inboxes, on a SimPy environment.

``send`` hands a message of real bytes to its source node. A node holds what it has to
send in a per-kind bounded buffer: on a link's queue when the route's next hop is up,
otherwise parked (store and forward) or dropped, as the kind's policy says (thesis
2.1.2: robots must not rely on links). Each hop carries the whole message in
fragments; the next node reassembles it and either delivers it to its inbox (the
destination) or forwards it (a relay). Reliable kinds are acknowledged per hop with
selective acks and retransmitted after a timeout; every node remembers which messages
it has had, so nothing is delivered twice. All randomness comes from the generator
passed in; the same seed gives the same event log.

Typical use (the simulator does this once per run)::

    net = Network(env, scenario.comms, ["lru1", "lru2", "lander"], rng,
                  positions=lambda: {...}, line_of_sight=lambda a, b: ...)
    net.send("lru1", "lru2", "submap", payload_bytes)
    delivery = yield net.inbox("lru2").get()        # or net.on_receive("lru2", fn)
    net.to_table(); net.to_metrics(); net.timeseries()
"""

from __future__ import annotations

import bisect
import itertools
import operator
import zlib
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import simpy

from comms.accounting import Accounting, DropReason, LinkEvent
from comms.availability import Availability, LineOfSight, Positions
from comms.config import (
    CommsConfig,
    KindPolicy,
    OutagePolicy,
    WhenFull,
    auto_ack_timeout,
    resolve_links,
)
from comms.config import Delivery as DeliveryMode
from comms.errors import CommsError
from comms.link import Link, Transfer, TransferState
from comms.loss import UniformStream, make_loss
from comms.message import (
    ACK_KIND,
    Delivery,
    Envelope,
    Message,
    as_payload,
    decode_ack,
    encode_ack,
    fragment_sizes,
)
from comms.routing import Router

# An ack for a message of n fragments: 13 header bytes + ceil(n / 8) bitmap bytes. The
# timeout estimate uses a typical one; the ack's real size is measured when sent.
_TYPICAL_ACK_BYTES = 64


class _Node:
    __slots__ = ("buffered", "handler", "held", "held_bytes", "inbox", "name", "seen")

    def __init__(self, env: simpy.Environment, name: str):
        self.name = name
        self.inbox = simpy.Store(env)
        self.handler: Callable[[Delivery], Any] | None = None
        self.held: list[tuple[int, Envelope]] = []  # parked messages, by arrival order
        self.held_bytes = 0
        self.buffered: dict[str, int] = defaultdict(int)  # kind -> messages this node holds to send
        self.seen: set[int] = set()  # message ids this node has received


class Network:
    """See the module docstring. ``nodes``: the simulator's node names (robots, lander);
    the configuration's ground station is added if missing. ``rng``: one draw from it
    seeds every random stream of the network (per link, per outage generator).
    ``positions``: node name -> position (m, any fixed frame), polled; nodes it leaves
    out have no range or sight limits. ``line_of_sight(a, b)``: True if nothing blocks
    the straight line between the two nodes' antennas. ``keep_log``: keep the full
    event log in ``accounting.log`` (``accounting.digest()`` is always kept)."""

    def __init__(
        self,
        env: simpy.Environment,
        config: CommsConfig,
        nodes: Sequence[str],
        rng: np.random.Generator,
        positions: Positions | None = None,
        line_of_sight: LineOfSight | None = None,
        keep_log: bool = False,
    ):
        names = list(nodes) + [n for n in config.extra_nodes() if n not in nodes]
        if len(names) < 1:
            raise CommsError("a network needs at least one node")
        config.check_nodes(names)
        self.env = env
        self.config = config
        self.nodes: tuple[str, ...] = tuple(names)
        self._nodes = {n: _Node(env, n) for n in names}
        self._policies: dict[str, KindPolicy] = {}
        self._ids = itertools.count(1)
        self._ack_ids = itertools.count(-1, -1)
        self._seq = itertools.count()
        self._subscribers: list[Callable[[LinkEvent], Any]] = []

        params = resolve_links(config, names)
        self.accounting = Accounting(names, list(params), start=env.now, keep_log=keep_log)
        seed = int(rng.integers(0, 2**63 - 1))
        self.links: dict[tuple[str, str], Link] = {}
        for (a, b), cfg in params.items():
            key = f"{a}->{b}"
            self.links[(a, b)] = Link(
                env,
                a,
                b,
                cfg,
                make_loss(cfg.loss, self._stream(seed, "loss", key), cfg.trace),
                UniformStream(self._stream(seed, "jitter", key)),
                self,
                self.accounting.links[(a, b)],
            )
        self._ack_timeout = {
            k: link.cfg.ack_timeout_s
            or auto_ack_timeout(link.cfg, (self.links.get((k[1], k[0])) or link).cfg, _TYPICAL_ACK_BYTES)
            for k, link in self.links.items()
        }
        cost = {k: l.cfg.worst_latency_s() + 8.0 * l.cfg.mtu_bytes / l.cfg.worst_bandwidth_bps() for k, l in self.links.items()}
        self.router = Router(names, config.relays, cost, lambda a, b: self.links[(a, b)].up)
        self.availability = Availability(
            env, config, names, self.links, self._links_changed, seed, positions, line_of_sight
        )
        env.process(self._sampler())

    @staticmethod
    def _stream(seed: int, *path: str) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32("/".join(path).encode())]))

    # ------------------------------------------------------------------ public API

    def send(self, src: str, dst: str, kind: str, payload: bytes, priority: int | None = None) -> Message:
        """Hand a message to ``src`` for ``dst``; returns it (its ``id`` identifies it in
        the accounting). ``priority`` overrides the kind's (0 is most urgent)."""
        self._node(src)
        self._node(dst)
        if src == dst:
            raise CommsError(f"send: source and destination are both {src!r}")
        if not kind or kind == ACK_KIND:
            raise CommsError(f"send: kind must be a non-empty name other than {ACK_KIND!r}, got {kind!r}")
        policy = self.policy(kind)
        if priority is None:
            priority = policy.priority
        else:
            given = priority
            try:
                priority = operator.index(priority)
            except TypeError:
                priority = -1
            if not 0 <= priority <= 15:
                raise CommsError(f"send: priority must be an int in 0..15 (0 most urgent), got {given!r}")
        msg = Message(next(self._ids), src, dst, kind, priority, as_payload(payload), self.env.now)
        self.accounting.offered(msg)
        self._accept(self._nodes[src], Envelope(msg, [src]))
        return msg

    def broadcast(
        self, src: str, kind: str, payload: bytes, priority: int | None = None, to: Iterable[str] | None = None
    ) -> list[Message]:
        """One message to every other node (or to those in ``to``): unicast copies, each
        carried and accounted on its own."""
        targets = [n for n in (self.nodes if to is None else to) if n != src]
        data = as_payload(payload)
        return [self.send(src, dst, kind, data, priority) for dst in targets]

    def inbox(self, node: str) -> simpy.Store:
        """The node's inbox: a ``simpy.Store`` of :class:`comms.message.Delivery`."""
        return self._node(node).inbox

    def on_receive(self, node: str, handler: Callable[[Delivery], Any] | None) -> None:
        """Call ``handler(delivery)`` at each delivery to ``node`` instead of filling its
        inbox (None: back to the inbox)."""
        self._node(node).handler = handler

    def subscribe(self, callback: Callable[[LinkEvent], Any]) -> None:
        """Call ``callback(event)`` whenever a link goes up or down."""
        self._subscribers.append(callback)

    def policy(self, kind: str) -> KindPolicy:
        policy = self._policies.get(kind)
        if policy is None:
            policy = self._policies[kind] = self.config.kind_policy(kind)
        return policy

    def link(self, src: str, dst: str) -> Link:
        try:
            return self.links[(src, dst)]
        except KeyError:
            raise CommsError(f"no link {src}->{dst}; nodes: {list(self.nodes)}") from None

    def radio_fault(self, node: str, start_s: float, end_s: float | None = None) -> None:
        """``node``'s radio fails from ``start_s`` until ``end_s`` (None: for good): no link to or from it is up,
        and messages to it are held or dropped as in an outage."""
        self.availability.node_fault(node, start_s, end_s)

    def is_up(self, src: str, dst: str) -> bool:
        return self.link(src, dst).up

    def route(self, src: str, dst: str) -> tuple[str, ...] | None:
        """The path a message from ``src`` to ``dst`` would take now, or None."""
        self._node(src)
        self._node(dst)
        return self.router.path(src, dst)

    def held(self, node: str) -> list[Message]:
        """Messages parked at ``node`` waiting for a route, oldest first."""
        return [env.message for _, env in self._node(node).held]

    def to_table(self) -> list[dict[str, Any]]:
        return self.accounting.to_table()

    def link_table(self) -> list[dict[str, Any]]:
        return self.accounting.link_table(self.env.now)

    def to_metrics(self) -> dict[str, Any]:
        return self.accounting.to_metrics(self.env.now)

    def timeseries(self) -> dict[str, Any]:
        return self.accounting.timeseries()

    def _node(self, name: str) -> _Node:
        try:
            return self._nodes[name]
        except KeyError:
            raise CommsError(f"unknown node {name!r}; nodes: {list(self.nodes)}") from None

    # ------------------------------------------------------------------ node buffers

    def _accept(self, node: _Node, envelope: Envelope) -> None:
        """A message enters ``node``'s send buffer (from ``send`` or to be relayed)."""
        msg = envelope.message
        policy = self.policy(msg.kind)
        full = node.buffered[msg.kind] >= policy.max_queued
        if full and not (policy.when_full == WhenFull.DROP_OLDEST and self._drop_oldest(node, msg.kind)):
            self._drop(msg, DropReason.QUEUE_FULL)
            return
        node.buffered[msg.kind] += 1
        self._dispatch(node, envelope, next(self._seq))

    def _dispatch(self, node: _Node, envelope: Envelope, seq: int) -> None:
        msg = envelope.message
        hop = self.router.next_hop(node.name, msg.dst)
        if hop is not None:
            policy = self.policy(msg.kind)
            link = self.links[(node.name, hop)]
            transfer = Transfer(
                envelope,
                link,
                seq,
                fragment_sizes(msg.size, link.cfg.mtu_bytes),
                reliable=policy.delivery == DeliveryMode.RELIABLE,
                max_retries=policy.max_retries,
            )
            link.stats.transfers += 1
            link.stats.transfer_bytes += msg.size
            link.enqueue(transfer)
        elif self.policy(msg.kind).outage == OutagePolicy.DROP:
            self._release(node, msg)
            self._drop(msg, DropReason.NO_ROUTE)
        else:
            bisect.insort(node.held, (seq, envelope), key=lambda item: item[0])
            self._set_held(node, msg.size)

    def _set_held(self, node: _Node, delta: int) -> None:
        node.held_bytes += delta
        self.accounting.held(node.name, self.env.now, node.held_bytes)

    def _release(self, node: _Node, msg: Message) -> None:
        node.buffered[msg.kind] -= 1

    def _drop_oldest(self, node: _Node, kind: str) -> bool:
        """Drop the oldest not yet started message of ``kind`` at ``node``."""
        best: tuple[int, Envelope, Transfer | None] | None = None
        for seq, env in node.held:
            if env.message.kind == kind:
                best = (seq, env, None)
                break
        for (a, _), link in self.links.items():
            if a != node.name:
                continue
            for t in link.queued():
                fresh = not t.started and not link.sending(t)
                candidate = fresh and t.ack_for is None and t.envelope.message.kind == kind
                if candidate and (best is None or t.seq < best[0]):
                    best = (t.seq, t.envelope, t)
        if best is None:
            return False
        seq, env, transfer = best
        if transfer is None:
            node.held.remove((seq, env))
            self._set_held(node, -env.message.size)
        else:
            transfer.link.remove(transfer)
            transfer.state = TransferState.ABANDONED
        self._release(node, env.message)
        self._drop(env.message, DropReason.QUEUE_FULL)
        return True

    def _drop(self, msg: Message, reason: DropReason, link: Link | None = None) -> None:
        self.accounting.dropped(msg, reason, self.env.now, None if link is None else (link.src, link.dst))

    # ------------------------------------------------------------------ link callbacks

    def _fragment_lost(self, t: Transfer, index: int) -> None:
        if t.ack_for is not None:
            t.link.stats.acks_lost += 1
        elif not t.reliable and not t.failed:
            t.failed = True
            self._drop(t.envelope.message, DropReason.LOSS, t.link)

    def _round_sent(self, t: Transfer) -> None:
        if t.ack_for is not None:
            t.state = TransferState.DONE
            return
        if not t.reliable:
            t.state = TransferState.DONE
            self._release(self._nodes[t.link.src], t.envelope.message)
            return
        t.state = TransferState.AWAIT_ACK
        round_ = t.round
        timer = self.env.timeout(self._ack_timeout[(t.link.src, t.link.dst)])
        timer.callbacks.append(lambda _e: self._ack_timeout_fired(t, round_))

    def _fragment_arrived(self, t: Transfer, index: int, round_: int, last_of_round: bool) -> None:
        if t.state == TransferState.ABANDONED:
            return  # the sender pulled it off this hop; a partial message is discarded
        if t.completed:
            if last_of_round:
                t.link.stats.duplicates += 1  # a round resent after its ack was lost
        elif not t.received[index]:
            t.received[index] = 1
            t.received_count += 1
        complete_now = not t.completed and t.received_count == len(t.sizes)
        if complete_now:
            t.completed = True
            if t.ack_for is not None:
                self._ack_arrived(t)
                return
            self._hop_complete(t)
        if t.reliable and (last_of_round or complete_now):
            self._send_ack(t, round_)

    def _hop_complete(self, t: Transfer) -> None:
        link, envelope = t.link, t.envelope
        msg = envelope.message
        link.stats.completed_msgs += 1
        link.stats.completed_bytes += msg.size
        node = self._nodes[link.dst]
        if msg.id in node.seen:
            link.stats.duplicates += 1
            return
        node.seen.add(msg.id)
        path = (*envelope.path, node.name)
        if node.name == msg.dst:
            delivery = Delivery(msg, self.env.now, path)
            self.accounting.delivered(msg, self.env.now, path)
            if node.handler is not None:
                node.handler(delivery)
            else:
                node.inbox.put(delivery)
        else:
            self._accept(node, Envelope(msg, list(path)))

    # ------------------------------------------------------------------ reliable delivery

    def _send_ack(self, t: Transfer, round_: int) -> None:
        reverse = self.links.get((t.link.dst, t.link.src))
        if reverse is None or not reverse.up:
            t.link.stats.acks_lost += 1
            return
        payload = encode_ack(t.envelope.message.id, round_, t.completed, t.received)
        ack = Message(next(self._ack_ids), reverse.src, reverse.dst, ACK_KIND, -1, payload, self.env.now)
        reverse.enqueue(
            Transfer(Envelope(ack, [reverse.src]), reverse, -1, fragment_sizes(len(payload), reverse.cfg.mtu_bytes), ack_for=t)
        )

    def _ack_arrived(self, ack: Transfer) -> None:
        target = ack.ack_for
        _, round_, complete, received = decode_ack(ack.envelope.message.payload, len(target.sizes))
        if target.state not in (TransferState.QUEUED, TransferState.AWAIT_ACK):
            return
        if complete:
            if target.state == TransferState.QUEUED:
                target.link.remove(target)
            target.state = TransferState.DONE
            self._release(self._nodes[target.link.src], target.envelope.message)
            return
        if round_ != target.round or target.state != TransferState.AWAIT_ACK:
            return  # an ack of an older round
        for i in np.flatnonzero(received):
            target.confirmed[i] = 1
        self._retransmit(target)

    def _ack_timeout_fired(self, t: Transfer, round_: int) -> None:
        if t.state == TransferState.AWAIT_ACK and t.round == round_:
            self._retransmit(t)

    def _retransmit(self, t: Transfer) -> None:
        link = t.link
        if not link.up:
            # the sender sees its link down: back to the node, to wait or take another route
            t.state = TransferState.ABANDONED
            self._dispatch(self._nodes[link.src], t.envelope, t.seq)
            return
        if t.retries >= t.max_retries:
            t.state = TransferState.ABANDONED
            link.stats.give_ups += 1
            self._release(self._nodes[link.src], t.envelope.message)
            if not t.completed:
                self._drop(t.envelope.message, DropReason.RETRIES_EXHAUSTED, link)
            return
        t.retries += 1
        t.round += 1
        t.pending = [i for i in range(len(t.sizes)) if not t.confirmed[i]]
        t.cursor = 0
        link.stats.retransmission_rounds += 1
        link.enqueue(t, front=True)

    # ------------------------------------------------------------------ availability

    def _links_changed(self, changed: list[Link]) -> None:
        now = self.env.now
        for link in changed:
            if link.up:
                continue
            node = self._nodes[link.src]
            for t in link.drain():
                if t.ack_for is not None:
                    t.state = TransferState.ABANDONED
                    link.stats.acks_lost += 1
                    continue
                t.state = TransferState.ABANDONED
                msg = t.envelope.message
                if t.failed:  # already dropped for loss
                    self._release(node, msg)
                elif self.policy(msg.kind).outage == OutagePolicy.DROP:
                    self._release(node, msg)
                    self._drop(msg, DropReason.LINK_DOWN, link)
                else:
                    bisect.insort(node.held, (t.seq, t.envelope), key=lambda item: item[0])
                    self._set_held(node, msg.size)
        self.router.invalidate()
        for node in self._nodes.values():
            if node.held:
                parked, node.held = node.held, []
                self._set_held(node, -node.held_bytes)
                for seq, envelope in parked:
                    self._dispatch(node, envelope, seq)
        for link in changed:
            event = LinkEvent(now, link.src, link.dst, link.up, link.reasons())
            self.accounting.link_changed(event)
            for callback in self._subscribers:
                callback(event)
            link.kick()

    def _sampler(self):
        interval = self.config.stats_interval_s
        while True:
            yield self.env.timeout(interval)
            self.accounting.sample(
                self.env.now,
                {k: l.up for k, l in self.links.items()},
                {k: l.queued_bytes for k, l in self.links.items()},
            )
