"""One robot's on-board collaborative SLAM (thesis 3.3, 4.2, 5.2.1, 6.2.1).

The agent composes the local estimator (filter and VO, thesis 4.1), the local mapping
(ch. 5), marker detection (6.2.1) and the robot's own multi-robot graph (4.2). Its
caller (the simulator's lane jobs, or a log player) hands it sensor data and peer
messages in the order the robot's computer would process them; every method that
produces something for the team returns :class:`Outgoing` messages of real bytes
(:mod:`slam.messages`) for the caller's network. What it exchanges (thesis 3.3):

- its pose estimates, periodically and in answer to a detection of itself;
- each frame switch ``w`` and, once finished, each submap, once to every robot;
- its robot detections ``d`` and landmark observations ``o``, with its own pose at the
  detection time from its :class:`~slam.pose_buffer.PoseBuffer`;
- when it explores, each new exploration goal (thesis 9.3), which its peers keep away from.

Every robot applies every message, its own included, to its own graph, so all robots
that received the same messages hold the same factors (delayed or reordered messages
change nothing: the local-reference topology never replaces a factor). A robot cut off
keeps estimating with what it has and catches up when messages arrive; a message seen
before (same origin and sequence number) is ignored.

A caller that tests robustness (thesis 4.2.3: erroneous loop closures) hands the agent a
:class:`MeasurementFaults`: it may replace a detection's transform before the robot uses and
sends it, or turn a match attempt into a wrong loop closure; the robot's records keep the
wrong values, marked (``DetectionRecord.injected``, match reason ``injected``).
"""

from __future__ import annotations

import itertools
import math
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Protocol

import numpy as np

from slam.filter import switch_pose3_covariance
from slam.graph import GraphParams, MultiRobotGraph, UpdateStats
from slam.local_estimator import FrameSwitch, LocalEstimator
from slam.local_mapper import LocalMapper
from slam.marker_uncertainty import DEFAULT_DP_PX, MAX_ROTATION_SIGMA_RAD, MarkerErrorTable, detection_sigmas
from slam.markers import MarkerDetection, MarkerDetector, UncertaintyModel, detection_covariance, relative_pose
from slam.matcher import Candidate, MatcherParams, SubmapKey
from slam.messages import (
    DetectionMessage,
    Envelope,
    FrameSwitchMessage,
    GoalMessage,
    LoopClosureMessage,
    MessageException,
    PoseEstimate,
    SubmapMessage,
    decode,
    encode,
)
from slam.pose_buffer import PoseBuffer
from slam.submap import Submap
from slam.team_matcher import MatchRecord, TeamMatcher

#: Network message kinds (comms policies) of each exchanged type.
KIND_POSE = "pose"
KIND_DETECTION = "detection"
KIND_FRAME_SWITCH = "frame_switch"
KIND_SUBMAP = "submap"
KIND_LOOP_CLOSURE = "loop_closure"
KIND_GOAL = "goal"
MESSAGE_KINDS = (KIND_POSE, KIND_DETECTION, KIND_FRAME_SWITCH, KIND_SUBMAP, KIND_LOOP_CLOSURE, KIND_GOAL)


@dataclass(frozen=True)
class TeamMarker:
    """A marker the team knows (calibrated, thesis 4.2.2): on a robot (``T_body_marker``)
    or defining a landmark (the landmark frame is the marker frame); ``up``: the target
    frame's axis that points up when it stands level (body z on robots)."""

    tag_id: int
    size_m: float
    robot: str | None = None
    landmark: int | None = None
    T_body_marker: np.ndarray = field(default_factory=lambda: np.eye(4))  # the target frame's marker
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # the target's up axis, in its frame

    def __post_init__(self):
        if (self.robot is None) == (self.landmark is None):
            raise ValueError(f"marker {self.tag_id}: give exactly one of robot and landmark")


def upright_solution(
    candidates: tuple[np.ndarray | None, ...], marker: TeamMarker, T_body_cam: np.ndarray, T_frame_body: np.ndarray, max_tilt_rad: float
) -> np.ndarray | None:
    """The planar pose ambiguity (thesis 6.2.1) resolved by gravity: of PnP's solutions
    ``T_cam_marker``, the one whose target stands closest to upright in the detecting
    robot's gravity-aligned local frame (its pose ``T_frame_body``), if tilted at most
    ``max_tilt_rad``. Robots drive upright and landmarks stand still, so a mirrored
    solution shows as a tilted target."""
    up = T_frame_body[:3, :3].T[:, 2]  # gravity's up in the detecting robot's body frame
    best, best_tilt = None, math.inf
    for T_cam_marker in candidates:
        if T_cam_marker is None:
            continue
        R_body_target = (T_body_cam @ T_cam_marker @ np.linalg.inv(marker.T_body_marker))[:3, :3]
        tilt = math.acos(float(np.clip(up @ (R_body_target @ marker.up), -1.0, 1.0)))
        if tilt < best_tilt:
            best, best_tilt = T_cam_marker, tilt
    return best if best_tilt <= max_tilt_rad else None


class MeasurementFaults(Protocol):
    """Wrong measurements injected by the agent's caller (a simulator's fault model; thesis 4.2.3 on erroneous
    loop closures). Each method returns None to leave the measurement as it is."""

    def detection(self, t: float, target: str, T_detector_target: np.ndarray) -> np.ndarray | None:
        """A wrong ``T_detector_target`` for this robot's detection of ``target`` (a robot, or
        ``landmark:<id>``) captured at ``t``, used and sent instead of the measured one (its covariance stays)."""

    def match(self, t: float, a: SubmapKey, b: SubmapKey, predicted_T_a_b: np.ndarray, matched: bool) -> tuple[np.ndarray, np.ndarray] | None:
        """A wrong loop closure ``(T_a_b, 6x6 covariance)`` for this robot's match attempt of submaps ``a`` and
        ``b`` finished at ``t``, whatever the matcher found (``matched``); ``predicted_T_a_b``: the graph's
        estimate of the pair from the last pairing."""


@dataclass(frozen=True)
class AgentParams:
    graph: GraphParams = field(default_factory=GraphParams)
    uncertainty: UncertaintyModel = UncertaintyModel.QUADRATIC  # eq. 8.1 / 8.2, or 6.2.3's lut / online / lut_online
    marker_tables: dict[tuple[str, float], MarkerErrorTable] = field(default_factory=dict)  # (camera, marker size) -> table
    corner_error_px: float = DEFAULT_DP_PX  # eq. 6.9's corner perturbation
    detection_interval_s: float = 2.0  # at most one detection of a target per interval
    max_detection_distance_m: float = 6.0
    max_ambiguity: float = 0.7  # PnP: best / second-best reprojection error at most this (1: ambiguous)
    max_target_tilt_rad: float = math.radians(30.0)  # a detected target tilted more is a mirrored PnP solution
    pose_period_s: float = 1.0  # periodic pose broadcast
    buffer_period_s: float = 0.05
    buffer_horizon_s: float = 900.0
    covariance_period_s: float = 10.0  # marginals of the latest submap origins (for the matcher)
    join_iterations: int = 5  # extra iSAM2 iterations when a robot joins the graph
    matching: MatcherParams | None = None  # submap matching (thesis 6.1); None: off


@dataclass(frozen=True)
class Outgoing:
    """A message for the network: ``to`` None means every other robot."""

    kind: str
    payload: bytes
    to: str | None = None


@dataclass
class DetectionRecord:
    """One of this robot's own detections, for evaluation against ground truth."""

    t: float
    tag_id: int
    target: str  # robot name or "landmark:<id>"
    T_detector_target: np.ndarray
    cov: np.ndarray
    distance_m: float
    ambiguity: float
    injected: bool = False  # replaced by a wrong one (:class:`MeasurementFaults`)


@dataclass
class AgentStats:
    received: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    duplicates: int = 0
    undecodable: int = 0
    detections_seen: int = 0  # markers of the team found in images
    detections_used: int = 0
    detections_rejected: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    unanswerable: int = 0  # detections of this robot at a time its buffer no longer (or not yet) holds
    marginal_failures: int = 0  # marginal covariances gtsam could not compute (the previous one kept)
    graph_updates: list[UpdateStats] = field(default_factory=list)
    covariance_s: list[float] = field(default_factory=list)


def _chained(S: np.ndarray, chain: dict[int, np.ndarray], start: int, end: int) -> np.ndarray | None:
    """``S`` composed with the frame switches ``chain[i]`` (local frame ``i`` -> ``i + 1``) for
    ``start <= i < end``; None if one of them has not arrived."""
    for i in range(start, end):
        if i not in chain:
            return None
        S = S @ chain[i]
    return S


class Agent:
    """See the module docstring. ``team``: every robot's name (this one included)."""

    def __init__(
        self,
        name: str,
        team: list[str],
        markers: list[TeamMarker],
        estimator: LocalEstimator,
        mapper: LocalMapper | None = None,
        params: AgentParams = AgentParams(),
        faults: MeasurementFaults | None = None,
    ):
        if name not in team:
            raise ValueError(f"agent {name!r} is not in its team {team}")
        self.name = name
        self.peers = [r for r in team if r != name]
        self.markers = {m.tag_id: m for m in markers}
        self.estimator = estimator
        self.mapper = mapper
        self.params = params
        self.faults = faults
        self.graph = MultiRobotGraph(name, params.graph)
        self.buffer = PoseBuffer(name, params.buffer_period_s, params.buffer_horizon_s)
        self.stats = AgentStats()
        self.detections: list[DetectionRecord] = []
        self.peer_submaps: dict[tuple[str, int], Submap] = {}
        self.peer_pose: dict[str, PoseEstimate] = {}  # latest periodic estimate of each peer
        self.peer_goals: dict[str, GoalMessage] = {}  # latest exploration goal of each peer
        self.peer_switches: dict[str, dict[int, np.ndarray]] = defaultdict(dict)  # robot -> index_from -> T (own too)
        self.marginals: dict[tuple[str, int], np.ndarray] = {}
        self.dirty = False  # factors arrived since the last optimisation
        self._seq = itertools.count(1)
        self._seen: set[tuple[str, int]] = set()
        self._registered: set[tuple[str, float]] = set()  # robot poses handed to the graph
        self._last_detection: dict[str, float] = {}
        self._switches_done = 0
        self._next_pose_t: float | None = None
        self._last_covariance_t = -math.inf
        self._detectors: dict[str, MarkerDetector] = {}
        self.matcher = TeamMatcher(params.matching, name) if params.matching is not None else None
        self.graph.update()  # the prior on this robot's first submap origin: its map frame

    # ------------------------------------------------------------------ own sensors

    def on_imu(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> list[Outgoing]:
        """A strapdown step; buffers the estimate and broadcasts it periodically."""
        est = self.estimator
        est.on_imu(t, accel, gyro)
        out = self._sync_switches()
        if not est.initialised:
            return out
        f = est.filter
        if self.buffer.due(t):
            self.buffer.add(t, f.frame_index, f.pose(), f.pose_covariance())
        if self._next_pose_t is None or t >= self._next_pose_t - 1e-9:
            self._next_pose_t = t + self.params.pose_period_s
            pose = PoseEstimate(self.name, t, f.frame_index, f.pose(), f.pose_covariance())
            out.append(self._outgoing(KIND_POSE, pose))
        return out

    def new_submap(self, t: float) -> list[Outgoing]:
        """Thesis 5.1.3: the mapping starts a new submap, and with it the filter a new frame."""
        switch = self.estimator.frame_switch()
        finished = self.mapper.start_submap(t, switch.frame_index) if self.mapper is not None else None
        out = self._sync_switches()
        if finished is not None and self.matcher is not None:
            self.matcher.add_submap(finished)
        if finished is not None:
            out.append(self._outgoing(KIND_SUBMAP, SubmapMessage(self.name, finished.index, finished.to_bytes())))
        return out

    def _sync_switches(self) -> list[Outgoing]:
        """Frame switches the estimator made since the last call (submap partitions, or
        distance when mapping is off) become w factors and messages."""
        out = []
        switches = self.estimator.switches
        while self._switches_done < len(switches):
            out.append(self._outgoing(KIND_FRAME_SWITCH, self._switch_message(switches[self._switches_done])))
            self._switches_done += 1
        return out

    def _switch_message(self, switch: FrameSwitch) -> FrameSwitchMessage:
        rp_var = float(np.max(np.diag(self.estimator.filter.roll_pitch_covariance())))
        cov = switch_pose3_covariance(switch.T_old_new, switch.cov_xyz_yaw, roll_pitch_var=max(rp_var, 1e-10))
        return FrameSwitchMessage(self.name, switch.frame_index - 1, switch.t, switch.T_old_new, cov)

    def find_markers(self, camera: str, K: np.ndarray, image: np.ndarray) -> list[MarkerDetection]:
        """Marker detection (thesis 6.2.1), first step: the team's markers in one rectified
        image of ``camera`` (intrinsics ``K``); :meth:`detections_from` makes detections of
        them. Reads none of the agent's state: it may run on another thread than the
        agent's other methods, one call per camera at a time."""
        detector = self._detectors.get(camera)
        if detector is None:
            detector = self._detectors[camera] = MarkerDetector(K, {m.tag_id: m.size_m for m in self.markers.values() if m.robot != self.name})
        return detector.detect(image)

    def _latest_pose(self) -> PoseEstimate | None:
        """The filter's current estimate (beyond the pose buffer's last entry), None before it starts."""
        est = self.estimator
        if est is None or not est.initialised:
            return None
        f = est.filter
        return PoseEstimate(self.name, f.t, f.frame_index, f.pose(), f.pose_covariance())

    def detections_from(self, t: float, found: list[MarkerDetection], camera: str, T_body_cam: np.ndarray) -> list[Outgoing]:
        """The detections to use of the markers ``found`` in an image of ``camera`` captured
        at ``t`` (:meth:`find_markers`): at most one per target and ``detection_interval_s``,
        the nearest marker of it, with the own pose at ``t`` and the uncertainty model's covariance."""
        detector = self._detectors.get(camera)  # made by find_markers, which found ``found``
        self.stats.detections_seen += len(found)
        best: dict[str, tuple] = {}
        for det in found:
            marker = self.markers[det.tag_id]
            target = marker.robot if marker.robot is not None else f"landmark:{marker.landmark}"
            if det.distance_m > self.params.max_detection_distance_m:
                self.stats.detections_rejected["too far"] += 1
            elif det.ambiguity > self.params.max_ambiguity:
                self.stats.detections_rejected["ambiguous"] += 1
            elif target not in best or det.distance_m < best[target][0].distance_m:
                best[target] = (det, marker)
        out = []
        for target, (det, marker) in sorted(best.items()):
            if t - self._last_detection.get(target, -math.inf) < self.params.detection_interval_s:
                continue
            own = self.buffer.at(t, self._latest_pose())
            if own is None:
                self.stats.detections_rejected["no own pose"] += 1
                continue
            T_cam_marker = upright_solution(
                (det.T_cam_marker, det.T_cam_marker_alt), marker, T_body_cam, own.T_frame_body, self.params.max_target_tilt_rad
            )
            if T_cam_marker is None:
                self.stats.detections_rejected["not upright"] += 1
                continue
            cov_marker = self._marker_covariance(camera, det, marker.size_m, detector)
            if cov_marker is None:
                self.stats.detections_rejected["uncertain"] += 1
                continue
            T, cov = relative_pose(T_body_cam, T_cam_marker, marker.T_body_marker, cov_marker)
            wrong = self.faults.detection(t, target, T) if self.faults is not None else None
            if wrong is not None:
                T = wrong
            msg = DetectionMessage(own, T, cov, marker.robot, marker.landmark, det.tag_id, det.distance_m)
            self._last_detection[target] = t
            self.stats.detections_used += 1
            self.detections.append(DetectionRecord(t, det.tag_id, target, T, cov, det.distance_m, det.ambiguity, wrong is not None))
            out.append(self._outgoing(KIND_DETECTION, msg))
        return out

    def _marker_covariance(self, camera: str, det: MarkerDetection, size_m: float, detector: MarkerDetector) -> np.ndarray | None:
        """6x6 covariance of ``T_cam_marker`` by the configured model (eq. 8.1, 8.2 or 6.2.3);
        None when a learned model puts a rotational sigma above 75 deg (thesis 8.1.3)."""
        model = self.params.uncertainty
        if model in (UncertaintyModel.CONSTANT, UncertaintyModel.QUADRATIC):
            return detection_covariance(model, det.distance_m)
        table = self.params.marker_tables.get((camera, size_m))
        sigma = detection_sigmas(model, det, table=table, detector=detector, dp_px=self.params.corner_error_px)
        if sigma[:3].max() > MAX_ROTATION_SIGMA_RAD:
            return None
        return np.diag(sigma**2)

    # ------------------------------------------------------------------ the team

    def _outgoing(self, kind: str, body) -> Outgoing:
        """Encode a message of this robot, apply it here first, and address it to the team."""
        payload = encode(self.name, next(self._seq), body)
        answers = self.receive(payload)
        if answers:  # only a detection of this robot by itself would be answered
            raise RuntimeError(f"{self.name}: own message produced answers")
        return Outgoing(kind, payload)

    def receive(self, payload: bytes) -> list[Outgoing]:
        """A message from the network (or from this robot itself); returns the answers."""
        try:
            env = decode(payload)
        except MessageException:
            self.stats.undecodable += 1
            return []
        if env.key in self._seen:
            self.stats.duplicates += 1
            return []
        self._seen.add(env.key)
        self.stats.received[type(env.body).__name__] += env.origin != self.name
        return self._apply(env)

    def _apply(self, env: Envelope) -> list[Outgoing]:
        """Hand the message's body to its handler (:attr:`_HANDLERS`, by body type); returns the answers."""
        return self._HANDLERS[type(env.body)](self, env.body)

    def _on_pose(self, body: PoseEstimate) -> list[Outgoing]:
        """An answer to a detection becomes a filter pose v; a periodic estimate updates the belief."""
        if body.answer:
            self._register(body)
        elif body.robot != self.name:
            latest = self.peer_pose.get(body.robot)
            if latest is None or body.t > latest.t:
                self.peer_pose[body.robot] = body
        return []

    def _on_frame_switch(self, body: FrameSwitchMessage) -> list[Outgoing]:
        self.graph.add_frame_switch(body.robot, body.index_from, body.t, body.T_from_to, body.cov)
        self.peer_switches[body.robot][body.index_from] = body.T_from_to
        self.dirty = True
        return []

    def _on_submap(self, body: SubmapMessage) -> list[Outgoing]:
        if body.robot != self.name:
            submap = Submap.from_bytes(body.data)
            self.peer_submaps[(body.robot, body.index)] = submap
            if self.matcher is not None:
                self.matcher.add_submap(submap)
        return []

    def _on_loop_closure(self, body: LoopClosureMessage) -> list[Outgoing]:
        """A submap match c (one per pair: only the pair's owner matches it, :func:`slam.team_matcher.pair_owner`)."""
        if self.matcher is not None:
            self.matcher.stale = True
        self.graph.add_match(body.robot_a, body.frame_a, body.robot_b, body.frame_b, body.T_a_b, body.cov)
        self.dirty = True
        return []

    def announce_goal(self, t: float, xy, finished: bool = False) -> list[Outgoing]:
        """This robot's new exploration goal (or the end of its exploration) for the team (thesis 9.3)."""
        return [self._outgoing(KIND_GOAL, GoalMessage(self.name, t, (float(xy[0]), float(xy[1])), finished))]

    def _on_goal(self, body: GoalMessage) -> list[Outgoing]:
        latest = self.peer_goals.get(body.robot)
        if body.robot != self.name and (latest is None or body.t >= latest.t):
            self.peer_goals[body.robot] = body
        return []

    def current_peer_goals(self) -> list[np.ndarray]:
        """The peers' exploration goals they still pursue (mission frame)."""
        return [np.array(g.xy) for g in self.peer_goals.values() if not g.finished]

    def _on_detection(self, body: DetectionMessage) -> list[Outgoing]:
        """A detection d or landmark observation o with the detector's pose; a detection of this robot
        is answered with its own pose at that time from its buffer (thesis 4.2.2)."""
        pose = body.detector_pose
        self._register(pose)
        if body.landmark is not None:
            self.graph.add_landmark_observation(pose.robot, pose.t, body.landmark, body.T_detector_target, body.cov)
        else:
            self.graph.add_detection(pose.robot, body.target_robot, pose.t, body.T_detector_target, body.cov)
        self.dirty = True
        if body.target_robot != self.name or (self.name, pose.t) in self._registered:
            return []
        mine = self.buffer.at(pose.t, self._latest_pose())
        if mine is None:
            self.stats.unanswerable += 1
            return []
        return [self._outgoing(KIND_DETECTION, PoseEstimate(self.name, pose.t, mine.frame_index, mine.T_frame_body, mine.cov, answer=True))]

    #: Message body type -> handler.
    _HANDLERS: ClassVar[dict[type, Callable[[Agent, Any], list[Outgoing]]]] = {
        PoseEstimate: _on_pose,
        FrameSwitchMessage: _on_frame_switch,
        SubmapMessage: _on_submap,
        LoopClosureMessage: _on_loop_closure,
        DetectionMessage: _on_detection,
        GoalMessage: _on_goal,
    }

    def _register(self, pose: PoseEstimate) -> None:
        key = (pose.robot, pose.t)
        if key not in self._registered:
            self._registered.add(key)
            self.graph.add_robot_pose(pose.robot, pose.t, pose.frame_index, pose.T_frame_body, pose.cov)
            self.dirty = True

    # ------------------------------------------------------------------ optimisation

    def optimize(self, now: float) -> UpdateStats:
        """One iSAM2 step with what arrived; every ``covariance_period_s`` also the marginal
        covariances of each connected robot's latest submap origin. Never raises on a
        numerical failure: the graph recovers from iSAM2's (``graph.recoveries``, stamped
        with ``now``); a marginal that cannot be computed keeps its previous value and is
        counted in ``stats.marginal_failures``."""
        connected = len(self.graph.connected_robots())
        stats = self.graph.update(t=now)
        if len(self.graph.connected_robots()) > connected:  # a robot joined with its backlog: converge
            stats = self.graph.update(extra_iterations=self.params.join_iterations, t=now)
        self.stats.graph_updates.append(stats)
        self.dirty = False
        if self.matcher is not None:
            self.matcher.graph_updated(self.graph)
        if now - self._last_covariance_t >= self.params.covariance_period_s:
            self._last_covariance_t = now
            t0 = time.perf_counter()
            for robot in self.graph.connected_robots():
                index = self.graph.latest_submap(robot)
                if index is None:
                    continue
                try:
                    self.marginals[(robot, index)] = self.graph.marginal_covariance(robot, index)
                except (RuntimeError, ValueError):  # gtsam: the Bayes tree cannot give this marginal
                    self.stats.marginal_failures += 1
            self.stats.covariance_s.append(time.perf_counter() - t0)
        return stats

    # ------------------------------------------------------------------ submap matching

    def pair_submaps(self) -> int:
        """Pairing (thesis 6.1.1) with the graph's latest estimate: the number of queued pairs."""
        return self.matcher.pair(self.graph) if self.matcher is not None else 0

    def attempt_match(self, cand: Candidate, t: float) -> tuple[list[Outgoing], MatchRecord]:
        """Match a queued pair (6.1.2): a loop closure for the team (and this robot's graph) on success."""
        return self.match_done(self.matcher.attempt(cand, t))

    def match_done(self, record: MatchRecord) -> tuple[list[Outgoing], MatchRecord]:
        """A finished attempt (:meth:`TeamMatcher.attempt`, or its parts): the scenario's wrong
        match if one is due, and a loop closure for the team on success."""
        t = record.t
        if self.faults is not None:
            res = record.result
            wrong = self.faults.match(t, res.a, res.b, record.prior.T_a_b, res.success)
            if wrong is not None:  # the attempt's record shows the wrong closure (reason "injected")
                T_a_b, cov = wrong
                record = replace(record, result=replace(res, T_a_b=T_a_b, cov=cov, reason="injected"))
                self.matcher.records[-1] = record
        res = record.result
        if not res.success:
            return [], record
        (ra, ia), (rb, ib) = res.a, res.b
        msg = LoopClosureMessage(ra, ia, record.frame_a, rb, ib, record.frame_b, res.T_a_b, res.cov)
        return [self._outgoing(KIND_LOOP_CLOSURE, msg)], record

    # ------------------------------------------------------------------ beliefs

    def _origin(self, robot: str, frame_index: int, chain: dict[int, np.ndarray]) -> np.ndarray | None:
        """Origin of ``robot``'s local frame in this robot's map: the latest optimised submap
        origin at or before it, with the frame switches since (eq. 4.6)."""
        latest = self.graph.latest_submap(robot)
        if latest is None:
            return None
        k = min(latest, frame_index)
        S = self.graph.submap_origin(robot, k)
        while S is None and k > 0:
            k -= 1
            S = self.graph.submap_origin(robot, k)
        return None if S is None else _chained(S, chain, k, frame_index)

    def pose_in_map(self, robot: str, frame_index: int, T_frame_body: np.ndarray) -> np.ndarray | None:
        """Eq. 4.6 with the graph as it is now: ``robot``'s pose ``T_frame_body`` in its local
        frame ``frame_index`` placed in this robot's map on that frame's origin (the latest
        optimised submap origin at or before it, with the frame switches since); None until
        the graph holds ``robot``. A robot's whole logged filter trajectory through this after
        the run is its trajectory by the final graph."""
        S = self._origin(robot, frame_index, self.peer_switches[robot])
        return None if S is None else S @ T_frame_body

    def online_pose(self) -> np.ndarray | None:
        """This robot's pose in its map (eq. 4.6): submap origin ``s_j`` from the graph
        composed with the filter's current estimate ``v_t``."""
        est = self.estimator
        if not est.initialised:
            return None
        f = est.filter
        return self.pose_in_map(self.name, f.frame_index, f.pose())

    def belief(self, robot: str) -> tuple[float, np.ndarray] | None:
        """Where this robot believes ``robot`` was at the time of its latest pose estimate
        (returned with it), in this robot's map: that estimate on the peer's optimised
        submap origin; None until the graph connects them."""
        pose = self.peer_pose.get(robot)
        if pose is None:
            return None
        B = self.pose_in_map(robot, pose.frame_index, pose.T_frame_body)
        return None if B is None else (pose.t, B)

    def peer_odometry_pose(self, robot: str) -> tuple[float, np.ndarray] | None:
        """``robot``'s latest periodic pose estimate in its first local frame (its odometry
        frame: where its map frame sits until its graph moves it), its frame switches
        chained, with the estimate's time; None without an estimate or with a switch of the
        chain missing. Needs no graph connection (slam/navigation/observation.py)."""
        pose = self.peer_pose.get(robot)
        if pose is None:
            return None
        T = _chained(np.eye(4), self.peer_switches[robot], 0, pose.frame_index)
        return None if T is None else (pose.t, T @ pose.T_frame_body)

    def last_detection_t(self, robot: str) -> float:
        """When this robot last detected ``robot``'s markers (-inf: never)."""
        return self._last_detection.get(robot, -math.inf)

    def placed_submaps(self) -> list[tuple[Submap, np.ndarray]]:
        """Every finished submap this robot holds, its own and its peers', with its origin
        in this robot's map from the graph (thesis 5.2.2); peers' submaps only once the
        graph connects them."""
        out = []
        own = [(s, self.name) for s in self.mapper.submaps] if self.mapper is not None else []
        for submap, robot in own + [(s, r) for (r, _), s in sorted(self.peer_submaps.items())]:
            S = self._origin(robot, submap.frame_index, self.peer_switches[robot])
            if S is not None:
                out.append((submap, S))
        return out

    def revisit_places(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Places to return to for a loop closure (slam/navigation/exploration.py, active loop
        closing): the origin ``S`` (in this robot's map) of each submap the matcher prepared
        as suitable (thesis 6.1.1), own and peers', with the 3x3 covariance (map axes) of its
        position relative to this robot's latest submap origin, from the graph's joint
        marginals (:meth:`MultiRobotGraph.relative_covariances`). Empty without a matcher."""
        latest = self.graph.latest_submap(self.name)
        if self.matcher is None or latest is None:
            return []
        me = (self.name, latest)
        pairs = {}
        for key in sorted(self.matcher.queue.prepared):
            node = (key[0], self.matcher.frames[key])
            S = None if node == me else self.graph.submap_origin(*node)
            if S is not None:
                pairs[(me, node)] = S
        try:
            covs = self.graph.relative_covariances(list(pairs))
        except (RuntimeError, ValueError):  # gtsam: no marginals of this estimate
            self.stats.marginal_failures += 1
            return []
        out = []
        for pair, S in pairs.items():
            if pair in covs:
                R = S[:3, :3]
                out.append((S, R @ covs[pair][3:, 3:] @ R.T))
        return out

    def active_submap(self) -> tuple[Submap, np.ndarray] | None:
        """This robot's submap under construction with its origin, if it has images."""
        if self.mapper is None or not self.mapper.builder.images:
            return None
        active = self.mapper.builder.current()
        S = self._origin(self.name, active.frame_index, self.peer_switches[self.name])
        return None if S is None else (active, S)
