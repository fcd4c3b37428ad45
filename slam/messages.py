"""What robots exchange (thesis 3.3), as versioned bytes for the network.

Every message carries its origin robot and a per-origin sequence number, so a
receiver applies each exactly once whatever the network does. The types:

- :class:`PoseEstimate`: a robot's filter pose ``v`` at time ``t`` in its local frame
  ``frame_index``, with its 6x6 covariance. Broadcast periodically (the team's view of
  where everyone is) and, flagged ``answer``, in reply to a detection of that robot at
  ``t`` (thesis 4.2.2: both robots' filter estimates at the detection time, from each
  robot's buffer, recover the detection's robot poses despite delays).
- :class:`FrameSwitchMessage`: the transformation ``w`` between consecutive submap
  origins (local frames) with its covariance.
- :class:`DetectionMessage`: a robot detection ``d`` (eq. 4.7) or a landmark observation
  ``o``, with the detecting robot's own pose estimate at the detection time.
- :class:`SubmapMessage`: a finished submap (thesis 5.2.1), sent once to each robot.
- :class:`LoopClosureMessage`: a submap match ``c`` (6.1.2) with its covariance.
- :class:`GoalMessage`: a robot's current exploration goal (thesis 9.3), or that it
  finished exploring.

The thesis's robots also announce the pairs their matchers take up (3.3); here each pair
has one owner that matches it (:func:`slam.team_matcher.pair_owner`), so there is
nothing to announce.

Layout (little-endian): magic ``MYSL``, version u8, type u8, origin (u8 length +
UTF-8), sequence u32, then the type's body. Poses are 3x4 float64 (the last row of a
rigid transform is implied), covariances their 21 upper-triangle float64 values.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

_MAGIC = b"MYSL"
_VERSION = 1
_HEAD = struct.Struct("<4sBB")
_U8 = struct.Struct("<B")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_F64 = struct.Struct("<d")
_TRIU = np.triu_indices(6)


class MessageException(ValueError):
    """Bytes that are not a message of this version, or a message that cannot be encoded."""


class MessageType(IntEnum):
    POSE = 1
    FRAME_SWITCH = 2
    DETECTION = 3
    SUBMAP = 4
    LOOP_CLOSURE = 6  # 5 was a match attempt
    GOAL = 7


@dataclass(frozen=True)
class PoseEstimate:
    """Filter pose of ``robot`` at ``t`` in its local frame ``frame_index`` (thesis 4.2.2's v)."""

    robot: str
    t: float
    frame_index: int
    T_frame_body: np.ndarray
    cov: np.ndarray
    answer: bool = False  # reply to a detection of this robot at t


@dataclass(frozen=True)
class FrameSwitchMessage:
    """w: local frame ``index_from`` -> ``index_from + 1`` of ``robot`` at time ``t``."""

    robot: str
    index_from: int
    t: float
    T_from_to: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True)
class DetectionMessage:
    """d (``target_robot`` set, eq. 4.7) or o (``landmark`` set): the pose of the target
    in the detecting robot's body frame at ``detector_pose.t``."""

    detector_pose: PoseEstimate
    T_detector_target: np.ndarray
    cov: np.ndarray
    target_robot: str | None = None
    landmark: int | None = None
    tag_id: int = -1
    distance_m: float = float("nan")

    def __post_init__(self):
        if (self.target_robot is None) == (self.landmark is None):
            raise MessageException("a detection names exactly one target: a robot or a landmark")


@dataclass(frozen=True)
class SubmapMessage:
    """A finished submap of ``robot`` as :meth:`slam.submap.Submap.to_bytes`."""

    robot: str
    index: int
    data: bytes


@dataclass(frozen=True)
class LoopClosureMessage:
    """c: submap ``index_b`` of ``robot_b`` (local frame ``frame_b``) seen from submap
    ``index_a`` of ``robot_a`` (local frame ``frame_a``): ``s_b = s_a (+) T_a_b``."""

    robot_a: str
    index_a: int
    frame_a: int
    robot_b: str
    index_b: int
    frame_b: int
    T_a_b: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True)
class GoalMessage:
    """``robot``'s exploration goal ``xy`` chosen at ``t``, in the mission frame as it
    believes it (thesis 9.3: "each robot communicates each new exploration goal to all other
    robots"); ``finished``: it explores no more (``xy`` is its last position)."""

    robot: str
    t: float
    xy: tuple[float, float]
    finished: bool = False


Body = PoseEstimate | FrameSwitchMessage | DetectionMessage | SubmapMessage | LoopClosureMessage | GoalMessage


@dataclass(frozen=True)
class Envelope:
    """A decoded message: who sent it first, its sequence number there, and the body."""

    origin: str
    seq: int
    body: Body

    @property
    def key(self) -> tuple[str, int]:
        return (self.origin, self.seq)


# --------------------------------------------------------------------------- encoding


class _Writer:
    def __init__(self):
        self.parts: list[bytes] = []

    def u8(self, v: int) -> None:
        self.parts.append(_U8.pack(v))

    def u32(self, v: int) -> None:
        self.parts.append(_U32.pack(v))

    def i32(self, v: int) -> None:
        self.parts.append(_I32.pack(v))

    def f64(self, v: float) -> None:
        self.parts.append(_F64.pack(v))

    def text(self, s: str) -> None:
        raw = s.encode("utf-8")
        if len(raw) > 255:
            raise MessageException(f"name {s!r} is longer than 255 bytes")
        self.u8(len(raw))
        self.parts.append(raw)

    def pose(self, T: np.ndarray) -> None:
        T = np.asarray(T, dtype="<f8")
        if T.shape != (4, 4):
            raise MessageException(f"a pose must be 4x4, got {T.shape}")
        self.parts.append(np.ascontiguousarray(T[:3]).tobytes())

    def cov(self, C: np.ndarray) -> None:
        C = np.asarray(C, dtype="<f8")
        if C.shape != (6, 6):
            raise MessageException(f"a covariance must be 6x6, got {C.shape}")
        self.parts.append(np.ascontiguousarray(C[_TRIU]).tobytes())

    def blob(self, data: bytes) -> None:
        self.u32(len(data))
        self.parts.append(bytes(data))


class _Reader:
    def __init__(self, data: bytes, pos: int):
        self.data = data
        self.pos = pos

    def _take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise MessageException(f"message truncated: needs {self.pos + n} bytes, has {len(self.data)}")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self) -> int:
        return _U8.unpack(self._take(1))[0]

    def u32(self) -> int:
        return _U32.unpack(self._take(4))[0]

    def i32(self) -> int:
        return _I32.unpack(self._take(4))[0]

    def f64(self) -> float:
        return _F64.unpack(self._take(8))[0]

    def text(self) -> str:
        raw = self._take(self.u8())
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise MessageException(f"name is not UTF-8: {exc}") from None

    def pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3] = np.frombuffer(self._take(96), dtype="<f8").reshape(3, 4)
        return T

    def cov(self) -> np.ndarray:
        C = np.zeros((6, 6))
        C[_TRIU] = np.frombuffer(self._take(168), dtype="<f8")
        return C + np.triu(C, 1).T

    def blob(self) -> bytes:
        return self._take(self.u32())


def _write_pose_estimate(w: _Writer, p: PoseEstimate) -> None:
    w.text(p.robot)
    w.f64(p.t)
    w.i32(p.frame_index)
    w.u8(1 if p.answer else 0)
    w.pose(p.T_frame_body)
    w.cov(p.cov)


def _read_pose_estimate(r: _Reader) -> PoseEstimate:
    robot, t, frame, answer = r.text(), r.f64(), r.i32(), bool(r.u8())
    return PoseEstimate(robot, t, frame, r.pose(), r.cov(), answer)


def encode(origin: str, seq: int, body: Body) -> bytes:
    """The message as bytes (what the network carries and accounts)."""
    w = _Writer()
    if isinstance(body, PoseEstimate):
        kind = MessageType.POSE
        _write_pose_estimate(w, body)
    elif isinstance(body, FrameSwitchMessage):
        kind = MessageType.FRAME_SWITCH
        w.text(body.robot)
        w.i32(body.index_from)
        w.f64(body.t)
        w.pose(body.T_from_to)
        w.cov(body.cov)
    elif isinstance(body, DetectionMessage):
        kind = MessageType.DETECTION
        _write_pose_estimate(w, body.detector_pose)
        w.pose(body.T_detector_target)
        w.cov(body.cov)
        w.text(body.target_robot or "")
        w.i32(-1 if body.landmark is None else body.landmark)
        w.i32(body.tag_id)
        w.f64(body.distance_m)
    elif isinstance(body, SubmapMessage):
        kind = MessageType.SUBMAP
        w.text(body.robot)
        w.i32(body.index)
        w.blob(body.data)
    elif isinstance(body, LoopClosureMessage):
        kind = MessageType.LOOP_CLOSURE
        for robot, index, frame in ((body.robot_a, body.index_a, body.frame_a), (body.robot_b, body.index_b, body.frame_b)):
            w.text(robot)
            w.i32(index)
            w.i32(frame)
        w.pose(body.T_a_b)
        w.cov(body.cov)
    elif isinstance(body, GoalMessage):
        kind = MessageType.GOAL
        w.text(body.robot)
        w.f64(body.t)
        w.f64(body.xy[0])
        w.f64(body.xy[1])
        w.u8(int(body.finished))
    else:
        raise MessageException(f"cannot encode {type(body).__name__}")
    head = _Writer()
    head.parts.append(_HEAD.pack(_MAGIC, _VERSION, int(kind)))
    head.text(origin)
    head.u32(seq)
    return b"".join(head.parts + w.parts)


def decode(data: bytes) -> Envelope:
    """Inverse of :func:`encode`; raises :class:`MessageException` on anything else."""
    data = bytes(data)
    if len(data) < _HEAD.size:
        raise MessageException(f"message too short: {len(data)} bytes")
    magic, version, kind = _HEAD.unpack_from(data)
    if magic != _MAGIC:
        raise MessageException(f"not a marsyard SLAM message: magic {magic!r}")
    if version != _VERSION:
        raise MessageException(f"message version {version} is not supported (this reader knows {_VERSION})")
    r = _Reader(data, _HEAD.size)
    origin, seq = r.text(), r.u32()
    if kind == MessageType.POSE:
        body: Body = _read_pose_estimate(r)
    elif kind == MessageType.FRAME_SWITCH:
        body = FrameSwitchMessage(r.text(), r.i32(), r.f64(), r.pose(), r.cov())
    elif kind == MessageType.DETECTION:
        pose, T, C = _read_pose_estimate(r), r.pose(), r.cov()
        target, landmark, tag, dist = r.text(), r.i32(), r.i32(), r.f64()
        body = DetectionMessage(pose, T, C, target or None, None if landmark < 0 else landmark, tag, dist)
    elif kind == MessageType.SUBMAP:
        body = SubmapMessage(r.text(), r.i32(), r.blob())
    elif kind == MessageType.LOOP_CLOSURE:
        a, ia, fa, b, ib, fb = r.text(), r.i32(), r.i32(), r.text(), r.i32(), r.i32()
        body = LoopClosureMessage(a, ia, fa, b, ib, fb, r.pose(), r.cov())
    elif kind == MessageType.GOAL:
        robot, t, x, y, finished = r.text(), r.f64(), r.f64(), r.f64(), r.u8()
        body = GoalMessage(robot, t, (x, y), bool(finished))
    else:
        raise MessageException(f"unknown message type {kind}")
    if r.pos != len(data):
        raise MessageException(f"message has {len(data) - r.pos} trailing bytes")
    return Envelope(origin, seq, body)
