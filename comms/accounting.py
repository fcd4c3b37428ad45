"""What the network did: per flow (source, destination, kind) and per link.

End to end, each message has exactly one fate: delivered, dropped (with a reason), or
still pending when the run ends; latency is measured in simulated time from
``send`` to the inbox. Per link (one hop, one direction): bytes on the wire (with
retransmissions and acknowledgements), fragments lost, time up, queue occupancy
(time-weighted mean and max) and a sampled time series of state, queue and throughput.
Everything comes out as plain data: :meth:`Accounting.to_table` (rows),
:meth:`Accounting.to_metrics` (a JSON-able dict), :meth:`Accounting.timeseries`.
"""

from __future__ import annotations

import hashlib
from array import array
from collections import defaultdict
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from comms.message import Message


class DropReason(StrEnum):
    LOSS = "loss"  # best effort: a fragment was lost on the channel
    QUEUE_FULL = "queue_full"  # the kind's bounded queue at a node was full
    NO_ROUTE = "no_route"  # policy drop: the destination was unreachable at send/forward
    LINK_DOWN = "link_down"  # policy drop: the link went down while the message waited on it
    RETRIES_EXHAUSTED = "retries_exhausted"  # reliable: no ack after max_retries rounds


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """A link went up or down; ``reasons`` name what blocks it (empty when up)."""

    t: float
    src: str
    dst: str
    up: bool
    reasons: tuple[str, ...]


class TimeWeighted:
    """A piecewise-constant quantity: its time-weighted mean and its max."""

    __slots__ = ("integral", "max", "since", "start", "value")

    def __init__(self, start: float = 0.0, value: float = 0.0):
        self.value, self.since, self.integral, self.max, self.start = value, start, 0.0, value, start

    def set(self, now: float, value: float) -> None:
        self.integral += self.value * (now - self.since)
        self.value, self.since = value, now
        self.max = max(self.max, value)

    def mean(self, until: float) -> float:
        span = until - self.start
        if span <= 0:
            return float(self.value)
        return (self.integral + self.value * (until - self.since)) / span


def _new_drops() -> dict[str, list[int]]:
    return {reason.value: [0, 0] for reason in DropReason}


_REASONS = list(DropReason)
_PENDING, _DELIVERED = 0, 1  # fate codes; a drop is 2 + its index in DropReason


@dataclass
class FlowStats:
    """One (source, destination, kind), end to end."""

    offered_msgs: int = 0
    offered_bytes: int = 0
    delivered_msgs: int = 0
    delivered_bytes: int = 0
    dropped: dict[str, list[int]] = field(default_factory=_new_drops)  # reason -> [msgs, bytes]
    latencies: array = field(default_factory=lambda: array("d"))
    hops: array = field(default_factory=lambda: array("H"))


@dataclass
class LinkStats:
    """One direction of one link (one hop)."""

    src: str
    dst: str
    start: float = 0.0
    transfers: int = 0  # hop transfers started (a message re-sent after an outage counts again)
    transfer_bytes: int = 0
    completed_msgs: int = 0  # hop completions (the next node has the whole message)
    completed_bytes: int = 0
    dropped: dict[str, list[int]] = field(default_factory=_new_drops)
    fragments_sent: int = 0
    fragments_lost: int = 0
    wire_bytes: int = 0  # every byte serialized: data, retransmissions, acks
    retransmitted_bytes: int = 0
    ack_bytes: int = 0
    acks_lost: int = 0  # acks lost on the channel or not sendable (reverse link down)
    retransmission_rounds: int = 0
    give_ups: int = 0
    duplicates: int = 0  # completed again after the next node had it (suppressed)
    arrived_bytes: int = 0  # fragment bytes that reached the far end
    queue_bytes: TimeWeighted = field(default_factory=TimeWeighted)
    up_time: TimeWeighted = field(default_factory=lambda: TimeWeighted(value=1.0))
    _interval_bytes: int = 0

    def __post_init__(self) -> None:
        self.queue_bytes = TimeWeighted(self.start)
        self.up_time = TimeWeighted(self.start, 1.0)

    def state(self, now: float, up: bool) -> None:
        self.up_time.set(now, 1.0 if up else 0.0)

    def queue(self, now: float, queued_bytes: int) -> None:
        self.queue_bytes.set(now, queued_bytes)

    def fragment_sent(self, size: int, ack: bool, retransmission: bool) -> None:
        self.fragments_sent += 1
        self.wire_bytes += size
        if ack:
            self.ack_bytes += size
        elif retransmission:
            self.retransmitted_bytes += size

    def fragment_lost(self, size: int) -> None:
        self.fragments_lost += 1

    def fragment_arrived(self, size: int) -> None:
        self.arrived_bytes += size
        self._interval_bytes += size


class Accounting:
    """``keep_log``: keep every event as a tuple in ``log`` (memory grows with the
    run); the running ``digest()`` of the same events is always kept."""

    def __init__(self, nodes: list[str], links: list[tuple[str, str]], start: float = 0.0, keep_log: bool = False):
        self.start = start
        self.nodes = list(nodes)
        self.flows: dict[tuple[str, str, str], FlowStats] = defaultdict(FlowStats)
        self.links: dict[tuple[str, str], LinkStats] = {k: LinkStats(*k, start=start) for k in links}
        self.held_bytes: dict[str, TimeWeighted] = {n: TimeWeighted(start) for n in nodes}
        self.link_events: list[LinkEvent] = []
        self.log: list[tuple] | None = [] if keep_log else None
        self._hash = hashlib.blake2b(digest_size=16)
        self._fate = bytearray(1)  # message ids count from 1: one fate code per message
        self._drop_link: dict[int, tuple[str, str]] = {}  # dropped on a link: which
        self._sample_t: list[float] = []
        self._samples: dict[tuple[str, str], dict[str, list]] = {
            k: {"up": [], "queue_bytes": [], "throughput_Bps": []} for k in links
        }
        self._last_sample = start

    def _record(self, event: tuple) -> None:
        self._hash.update(repr(event).encode())
        if self.log is not None:
            self.log.append(event)

    def digest(self) -> str:
        """A hash of every event so far (sent, delivered, dropped, link changes):
        same seed, same digest."""
        return self._hash.hexdigest()

    # ------------------------------------------------------------------ recording

    def offered(self, msg: Message) -> None:
        if msg.id != len(self._fate):
            raise AssertionError(f"message ids must count up from 1, got {msg.id} after {len(self._fate) - 1}")
        self._fate.append(_PENDING)
        f = self.flows[(msg.src, msg.dst, msg.kind)]
        f.offered_msgs += 1
        f.offered_bytes += msg.size
        self._record(("sent", msg.sent_at, msg.id, msg.src, msg.dst, msg.kind, msg.size))

    def delivered(self, msg: Message, now: float, path: tuple[str, ...]) -> None:
        fate = self._fate[msg.id]
        if fate == _DELIVERED:
            raise AssertionError(f"message {msg.id} delivered twice")  # never: nodes deduplicate
        if fate != _PENDING:
            self._undo_drop(msg, _REASONS[fate - 2])  # a copy on another path made it after all
        self._fate[msg.id] = _DELIVERED
        f = self.flows[(msg.src, msg.dst, msg.kind)]
        f.delivered_msgs += 1
        f.delivered_bytes += msg.size
        f.latencies.append(now - msg.sent_at)
        f.hops.append(len(path) - 1)
        self._record(("delivered", now, msg.id, path))

    def dropped(self, msg: Message, reason: DropReason, now: float, link: tuple[str, str] | None = None) -> None:
        if self._fate[msg.id] != _PENDING:
            return  # its fate is already decided (delivered, or dropped on another path)
        self._fate[msg.id] = 2 + _REASONS.index(reason)
        d = self.flows[(msg.src, msg.dst, msg.kind)].dropped[reason.value]
        d[0] += 1
        d[1] += msg.size
        if link is not None:
            self._drop_link[msg.id] = link
            ld = self.links[link].dropped[reason.value]
            ld[0] += 1
            ld[1] += msg.size
        self._record(("dropped", now, msg.id, reason.value))

    def _undo_drop(self, msg: Message, reason: DropReason) -> None:
        d = self.flows[(msg.src, msg.dst, msg.kind)].dropped[reason.value]
        d[0] -= 1
        d[1] -= msg.size
        link = self._drop_link.pop(msg.id, None)
        if link is not None:
            ld = self.links[link].dropped[reason.value]
            ld[0] -= 1
            ld[1] -= msg.size

    def link_changed(self, event: LinkEvent) -> None:
        self.link_events.append(event)
        self._record(("link", event.t, event.src, event.dst, event.up, event.reasons))

    def held(self, node: str, now: float, held_bytes: int) -> None:
        self.held_bytes[node].set(now, held_bytes)

    def sample(self, now: float, up: dict[tuple[str, str], bool], queued: dict[tuple[str, str], int]) -> None:
        """One row of the link time series (state, queue, throughput since last sample)."""
        span = now - self._last_sample
        self._sample_t.append(now)
        for key, series in self._samples.items():
            stats = self.links[key]
            series["up"].append(bool(up[key]))
            series["queue_bytes"].append(int(queued[key]))
            series["throughput_Bps"].append(stats._interval_bytes / span if span > 0 else 0.0)
            stats._interval_bytes = 0
        self._last_sample = now

    # ------------------------------------------------------------------ reports

    def fate(self, message_id: int) -> str | None:
        """``"delivered"``, a drop reason, or None while pending (or unknown)."""
        if not 0 < message_id < len(self._fate):
            return None
        code = self._fate[message_id]
        if code == _PENDING:
            return None
        return "delivered" if code == _DELIVERED else _REASONS[code - 2].value

    @staticmethod
    def _latency(values) -> dict[str, float | None]:
        if not len(values):
            return {"p50": None, "p95": None, "max": None, "mean": None}
        a = np.asarray(values)
        return {
            "p50": float(np.percentile(a, 50)),
            "p95": float(np.percentile(a, 95)),
            "max": float(a.max()),
            "mean": float(a.mean()),
        }

    @staticmethod
    def _summary(flows: list[FlowStats], duration: float) -> dict[str, Any]:
        offered_m = sum(f.offered_msgs for f in flows)
        offered_b = sum(f.offered_bytes for f in flows)
        deliv_m = sum(f.delivered_msgs for f in flows)
        deliv_b = sum(f.delivered_bytes for f in flows)
        drops = {r.value: {"msgs": 0, "bytes": 0} for r in DropReason}
        for f in flows:
            for reason, (m, b) in f.dropped.items():
                drops[reason]["msgs"] += m
                drops[reason]["bytes"] += b
        drop_m = sum(d["msgs"] for d in drops.values())
        drop_b = sum(d["bytes"] for d in drops.values())
        lat = np.concatenate([np.frombuffer(f.latencies, dtype=float) for f in flows]) if flows else []
        return {
            "offered_msgs": offered_m,
            "offered_bytes": offered_b,
            "delivered_msgs": deliv_m,
            "delivered_bytes": deliv_b,
            "dropped_msgs": drop_m,
            "dropped_bytes": drop_b,
            "pending_msgs": offered_m - deliv_m - drop_m,
            "pending_bytes": offered_b - deliv_b - drop_b,
            "dropped_by_reason": drops,
            "offered_Bps": offered_b / duration if duration > 0 else None,
            "delivered_Bps": deliv_b / duration if duration > 0 else None,
            "latency_s": Accounting._latency(lat),
        }

    def to_table(self) -> list[dict[str, Any]]:
        """One row per (source, destination, kind), end to end, sorted."""
        rows = []
        for (src, dst, kind), f in sorted(self.flows.items()):
            lat = self._latency(f.latencies)
            row: dict[str, Any] = {
                "src": src,
                "dst": dst,
                "kind": kind,
                "offered_msgs": f.offered_msgs,
                "offered_bytes": f.offered_bytes,
                "delivered_msgs": f.delivered_msgs,
                "delivered_bytes": f.delivered_bytes,
            }
            dropped_m = dropped_b = 0
            for reason, (m, b) in f.dropped.items():
                row[f"dropped_{reason}_msgs"] = m
                row[f"dropped_{reason}_bytes"] = b
                dropped_m += m
                dropped_b += b
            row["dropped_msgs"] = dropped_m
            row["dropped_bytes"] = dropped_b
            row["pending_msgs"] = f.offered_msgs - f.delivered_msgs - dropped_m
            row["latency_p50_s"] = lat["p50"]
            row["latency_p95_s"] = lat["p95"]
            row["latency_max_s"] = lat["max"]
            row["mean_hops"] = float(np.mean(f.hops)) if len(f.hops) else None
            rows.append(row)
        return rows

    def link_table(self, now: float) -> list[dict[str, Any]]:
        """One row per link direction (per hop), sorted."""
        rows = []
        duration = now - self.start
        for (src, dst), s in sorted(self.links.items()):
            row: dict[str, Any] = {
                "link": f"{src}->{dst}",
                "up_fraction": s.up_time.mean(now),
                "transfers": s.transfers,
                "transfer_bytes": s.transfer_bytes,
                "completed_msgs": s.completed_msgs,
                "completed_bytes": s.completed_bytes,
                "wire_bytes": s.wire_bytes,
                "retransmitted_bytes": s.retransmitted_bytes,
                "ack_bytes": s.ack_bytes,
                "fragments_sent": s.fragments_sent,
                "fragments_lost": s.fragments_lost,
                "fragment_loss_rate": s.fragments_lost / s.fragments_sent if s.fragments_sent else None,
                "acks_lost": s.acks_lost,
                "retransmission_rounds": s.retransmission_rounds,
                "give_ups": s.give_ups,
                "duplicates": s.duplicates,
                "throughput_Bps": s.arrived_bytes / duration if duration > 0 else None,
                "queue_bytes_mean": s.queue_bytes.mean(now),
                "queue_bytes_max": s.queue_bytes.max,
            }
            for reason, (m, b) in s.dropped.items():
                row[f"dropped_{reason}_msgs"] = m
                row[f"dropped_{reason}_bytes"] = b
            rows.append(row)
        return rows

    def to_metrics(self, now: float) -> dict[str, Any]:
        """Totals, per kind and per link, as a JSON-able dict (for ``metrics.json``)."""
        duration = now - self.start
        by_kind: dict[str, list[FlowStats]] = defaultdict(list)
        for (_, _, kind), f in self.flows.items():
            by_kind[kind].append(f)
        links = {row.pop("link"): row for row in self.link_table(now)}
        return {
            "duration_s": duration,
            "totals": self._summary(list(self.flows.values()), duration),
            "by_kind": {k: self._summary(v, duration) for k, v in sorted(by_kind.items())},
            "by_link": links,
            "held_bytes": {
                n: {"mean": tw.mean(now), "max": tw.max} for n, tw in sorted(self.held_bytes.items())
            },
            "link_events": len(self.link_events),
        }

    def timeseries(self) -> dict[str, Any]:
        """Sampled link state, queue and throughput: ``{"t": [...], "links": {"a->b":
        {"up": [...], "queue_bytes": [...], "throughput_Bps": [...]}}}`` plus every
        state change as ``events`` (exact times)."""
        return {
            "t": list(self._sample_t),
            "links": {f"{a}->{b}": {k: list(v) for k, v in s.items()} for (a, b), s in sorted(self._samples.items())},
            "events": [
                {"t": e.t, "link": f"{e.src}->{e.dst}", "up": e.up, "reasons": list(e.reasons)} for e in self.link_events
            ],
        }
