"""What travels: messages of real bytes, and the records of their arrival.

A message's size is ``len(payload)``, the bytes the sender really serialized (thesis
3.3 lists what robots exchange; 8.4 compares their measured sizes with raw images).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from comms.errors import CommsError

ACK_KIND = "_ack"  # control traffic of reliable delivery; never handed to a node
_ACK_HEADER = struct.Struct("<QIB")  # message id, round, complete flag


@dataclass(frozen=True, slots=True, eq=False)
class Message:
    """One message from ``src`` to ``dst``. ``id`` is unique in its network;
    ``sent_at`` is the simulated time of :meth:`comms.network.Network.send`."""

    id: int
    src: str
    dst: str
    kind: str
    priority: int
    payload: bytes
    sent_at: float

    @property
    def size(self) -> int:
        return len(self.payload)

    def __repr__(self) -> str:
        return (
            f"Message(id={self.id}, {self.src}->{self.dst}, kind={self.kind!r}, "
            f"priority={self.priority}, {self.size} B, sent_at={self.sent_at:.6f})"
        )


@dataclass(frozen=True, slots=True)
class Delivery:
    """A message as its destination receives it (exactly once)."""

    message: Message
    received_at: float
    path: tuple[str, ...]  # nodes it passed, source first, destination last

    @property
    def latency(self) -> float:
        return self.received_at - self.message.sent_at


@dataclass(slots=True, eq=False)
class Envelope:
    """A message on its way, with the nodes it has passed so far."""

    message: Message
    path: list[str] = field(default_factory=list)


def as_payload(data: bytes | bytearray | memoryview) -> bytes:
    """The payload as immutable bytes; anything else is an error (sizes are measured
    from real serialized bytes, never estimated)."""
    if isinstance(data, bytes):
        return data
    if isinstance(data, (bytearray, memoryview)):
        return bytes(data)
    raise CommsError(
        f"payload must be bytes (the serialized message), got {type(data).__name__}; "
        "serialize it first (e.g. numpy's tobytes(), pickle, msgpack)"
    )


def fragment_sizes(size: int, mtu: int) -> list[int]:
    """Sizes of the fragments of a ``size``-byte message at ``mtu`` bytes (an empty
    message is one empty fragment)."""
    if size <= 0:
        return [0]
    full, rest = divmod(size, mtu)
    return [mtu] * full + ([rest] if rest else [])


def encode_ack(message_id: int, round_: int, complete: bool, received: bytearray | None) -> bytes:
    """A selective acknowledgement as real bytes: header, then (if not complete) one
    bit per fragment that has arrived."""
    head = _ACK_HEADER.pack(message_id, round_, 1 if complete else 0)
    if complete or received is None:
        return head
    return head + np.packbits(np.frombuffer(bytes(received), dtype=np.uint8)).tobytes()


def decode_ack(data: bytes, n_fragments: int) -> tuple[int, int, bool, np.ndarray | None]:
    """Inverse of :func:`encode_ack`: ``(message id, round, complete, received mask)``."""
    message_id, round_, complete = _ACK_HEADER.unpack_from(data)
    if complete:
        return message_id, round_, True, None
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8, offset=_ACK_HEADER.size))[:n_fragments]
    return message_id, round_, False, bits.astype(bool)
