"""The scenario's ``comms:`` section: pydantic models, named presets, resolution.

A network is a set of named nodes (the robots, optionally the lander and a ground
station) joined by one link per direction. :class:`CommsConfig` describes it:

- ``preset``: a named channel (:data:`PRESETS`) merged *under* whatever the section
  sets itself, so ``{preset: spacebotcamp, defaults: {bandwidth_bps: 2e6}}`` is the
  SpaceBotCamp channel with less bandwidth.
- ``defaults``: the :class:`LinkConfig` of every link.
- ``links``: overrides keyed ``"a->b"`` (one direction) or ``"a<->b"`` (both), ``*``
  standing for any node; the more names a key spells out the later it applies, and a
  direction beats a pair.
- ``kind_defaults`` / ``kinds``: per message kind, a :class:`KindPolicy` (priority,
  best-effort or reliable delivery, what happens while the destination is unreachable).
- ``outages``, ``random_outages``, ``uplink_windows``: when links are down.
- ``relays``: nodes that forward messages for others (the lander, the hexacopter).

Thesis: robots must not rely on links (2.1.2 fault tolerance, low bandwidth); they
exchange pose estimates, loop closures, match attempts and submaps (3.3); the
SpaceBotCamp channel had a 2 s one-way delay, 100 Mbit/s, an uplink blocked except in
up to three five-minute windows, and outages (7.2, 9.2).
"""

from __future__ import annotations

import copy
import math
import re
from enum import StrEnum
from typing import Annotated, Any, ClassVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)
from pydantic_core import CoreSchema

from comms.errors import CommsError
from comms.trace import TraceFile

NODE_PATTERN = r"^[A-Za-z][A-Za-z0-9_]{0,31}$"
LINK_KEY = re.compile(r"^\s*(\*|[A-Za-z][A-Za-z0-9_]{0,31})\s*(<->|->)\s*(\*|[A-Za-z][A-Za-z0-9_]{0,31})\s*$")

NonNegFloat = Annotated[float, Field(ge=0)]
PositiveFloat = Annotated[float, Field(gt=0)]
Probability = Annotated[float, Field(ge=0, le=1)]
# Plausibility bounds; ``why`` (in the JSON schema) is what an error message adds.
Delay = Annotated[float, Field(ge=0, le=3600, json_schema_extra={"why": "a one-way delay of at most an hour: Earth to Mars is 22 min at most"})]
Bandwidth = Annotated[float, Field(ge=1, le=1e12, json_schema_extra={"why": "1 bit/s (slower is no link) to 1 Tbit/s (beyond any radio)"})]
Period = Annotated[
    float, Field(ge=0.01, json_schema_extra={"why": "at least 10 ms (a control tick is 5 ms), so that the network's processes cannot flood the run"})
]
OutageMean = Annotated[
    float, Field(ge=0.1, json_schema_extra={"why": "at least 0.1 s (shorter cuts are fragment loss, `loss:`), so that outages cannot flood the run"})
]


def strict_numbers(schema: Any) -> None:
    """Make every number and boolean in a pydantic core ``schema`` strict: no ``true`` taken
    as 1, no ``"3"`` as 3, no 2.5 rounded into an integer (floats still take integers)."""
    if isinstance(schema, dict):
        if schema.get("type") in ("float", "int", "bool"):
            schema["strict"] = True
        for value in schema.values():
            strict_numbers(value)
    elif isinstance(schema, list):
        for value in schema:
            strict_numbers(value)


class StrictConfig(BaseModel):
    """Base of every model here and of the scenario schema's (``sim.scenario.StrictModel``): unknown keys,
    NaN, infinities and numbers of the wrong type are errors."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @classmethod
    def __get_pydantic_core_schema__(cls, source: type[BaseModel], handler: GetCoreSchemaHandler) -> CoreSchema:
        schema = handler(source)
        strict_numbers(schema)
        return schema


def _check_window(value: tuple[float, float]) -> tuple[float, float]:
    start, end = value
    if start < 0 or not end > start:
        raise ValueError(f"a window is [start_s, end_s] with 0 <= start_s < end_s, got {list(value)}")
    return value


Window = tuple[NonNegFloat, PositiveFloat]


# --------------------------------------------------------------------------- enums


class LossModel(StrEnum):
    NONE = "none"
    BERNOULLI = "bernoulli"  # independent per fragment
    GILBERT_ELLIOTT = "gilbert_elliott"  # two-state Markov chain per fragment: bursts


class Delivery(StrEnum):
    BEST_EFFORT = "best_effort"  # one try per hop; a lost fragment loses the message
    RELIABLE = "reliable"  # per-hop selective acks, retransmission after a timeout


class OutagePolicy(StrEnum):
    STORE_AND_FORWARD = "store_and_forward"  # wait (bounded) until a route comes back
    DROP = "drop"  # drop what cannot be sent now


class WhenFull(StrEnum):
    DROP_NEWEST = "drop_newest"  # the arriving message is dropped (tail drop)
    DROP_OLDEST = "drop_oldest"  # the oldest waiting message makes room (fresh poses)


class Preset(StrEnum):
    LAB_WIFI = "lab_wifi"
    SPACEBOTCAMP = "spacebotcamp"
    LUNAR_SURFACE_UHF = "lunar_surface_uhf"


# --------------------------------------------------------------------------- links


class LossConfig(StrictConfig):
    """Fragment loss. ``bernoulli``: each fragment lost with ``rate``.
    ``gilbert_elliott``: a good and a bad state, switched per fragment with
    ``p_good_to_bad`` / ``p_bad_to_good``, losing with ``loss_good`` / ``loss_bad``;
    or give the short form ``rate`` (long-run loss) + ``mean_burst_fragments`` (mean
    run of consecutive losses), which sets ``loss_good = 0``, ``loss_bad = 1``,
    ``p_bad_to_good = 1 / mean_burst_fragments`` and
    ``p_good_to_bad = rate * p_bad_to_good / (1 - rate)``."""

    model: LossModel = Field(
        LossModel.NONE, description="none, bernoulli (independent per fragment) or gilbert_elliott (bursts: a good and a bad state)"
    )
    rate: Annotated[float, Field(ge=0, lt=1)] = Field(
        0.0, description="bernoulli: probability that a fragment is lost; gilbert_elliott short form: long-run loss"
    )
    mean_burst_fragments: Annotated[float, Field(ge=1)] | None = Field(
        None, description="gilbert_elliott short form: mean run of consecutive lost fragments"
    )
    p_good_to_bad: Probability | None = Field(
        None, description="gilbert_elliott: per-fragment probability of switching from the good to the bad state"
    )
    p_bad_to_good: Annotated[float, Field(gt=0, le=1)] | None = Field(
        None, description="gilbert_elliott: per-fragment probability of switching back to the good state"
    )
    loss_good: Probability = Field(0.0, description="gilbert_elliott: loss probability in the good state")
    loss_bad: Probability = Field(1.0, description="gilbert_elliott: loss probability in the bad state")

    @model_validator(mode="after")
    def _complete(self) -> LossConfig:
        if self.model != LossModel.GILBERT_ELLIOTT:
            if self.mean_burst_fragments is not None or self.p_good_to_bad is not None or self.p_bad_to_good is not None:
                raise ValueError("mean_burst_fragments, p_good_to_bad and p_bad_to_good are for model gilbert_elliott")
            return self
        explicit = self.p_good_to_bad is not None and self.p_bad_to_good is not None
        short = self.mean_burst_fragments is not None
        if explicit == short or (not explicit and (self.p_good_to_bad is not None or self.p_bad_to_good is not None)):
            raise ValueError(
                "gilbert_elliott needs either p_good_to_bad + p_bad_to_good, "
                "or rate + mean_burst_fragments (not both, not neither)"
            )
        if short and (self.loss_good != 0.0 or self.loss_bad != 1.0):
            raise ValueError("the short form (rate + mean_burst_fragments) assumes loss_good=0, loss_bad=1")
        return self

    def gilbert_elliott(self) -> tuple[float, float, float, float]:
        """``(p_good_to_bad, p_bad_to_good, loss_good, loss_bad)``, from either form."""
        if self.mean_burst_fragments is not None:
            p_bg = 1.0 / self.mean_burst_fragments
            return min(1.0, self.rate * p_bg / (1.0 - self.rate)), p_bg, 0.0, 1.0
        return self.p_good_to_bad, self.p_bad_to_good, self.loss_good, self.loss_bad

    def stationary_loss_rate(self) -> float:
        """The long-run fraction of fragments lost."""
        if self.model == LossModel.NONE:
            return 0.0
        if self.model == LossModel.BERNOULLI:
            return self.rate
        gb, bg, lg, lb = self.gilbert_elliott()
        pi_bad = gb / (gb + bg) if gb + bg > 0 else 0.0
        return (1 - pi_bad) * lg + pi_bad * lb


class LinkConfig(StrictConfig):
    """One direction of a link, fully resolved.

    A message of ``n`` bytes is cut into ``ceil(n / mtu_bytes)`` fragments; each takes
    ``8 * size / bandwidth_bps`` to serialize (one at a time per link, so fragments
    queue) and then ``latency_s`` plus a uniform extra delay in ``[0, jitter_s]`` to
    propagate; a link never reorders (an arrival waits for the one before it). With
    ``trace``, the trace's row in effect when a fragment starts to serialize replaces
    ``latency_s``, ``bandwidth_bps`` and ``loss`` for that fragment (:mod:`comms.trace`)."""

    enabled: bool = Field(True, description="false: the link is down for the whole run")
    latency_s: Delay = Field(0.002, description="one-way propagation delay of each fragment")
    jitter_s: Delay = Field(0.0, description="extra delay per fragment, uniform in [0, jitter_s]")
    bandwidth_bps: Bandwidth = Field(20e6, description="serialization rate (bit/s)")
    mtu_bytes: int = Field(1400, ge=16, le=1_000_000, description="largest fragment: a message of n bytes travels as ceil(n / mtu_bytes) fragments")
    loss: LossConfig = Field(LossConfig(), description="fragment loss")
    range_m: PositiveFloat | None = Field(None, description="up only while the nodes are this close (null: any distance)")
    line_of_sight: bool = Field(False, description="up only while the line-of-sight callback says so")
    windows: list[Window] | None = Field(
        None, description="up only inside these [start_s, end_s) windows (null: always; []: never)"
    )
    ack_timeout_s: PositiveFloat | None = Field(
        None, description="reliable delivery: retransmit after this (null: from both directions' latencies)"
    )
    trace: TraceFile | None = Field(
        None,
        description="CSV file t_s,latency_s,bandwidth_bps,loss (docs/comms.md) whose rows replace latency_s, bandwidth_bps and loss over time; "
        "a relative path is taken from the scenario file's folder (null: no trace)",
    )

    _w = field_validator("windows")(lambda v: None if v is None else [_check_window(w) for w in v])

    def worst_latency_s(self) -> float:
        """``latency_s``, or the trace's largest latency (what timeouts and routes plan with)."""
        return self.latency_s if self.trace is None else self.trace.max_latency_s()

    def worst_bandwidth_bps(self) -> float:
        """``bandwidth_bps``, or the trace's smallest bandwidth (what timeouts and routes plan with)."""
        return self.bandwidth_bps if self.trace is None else self.trace.min_bandwidth_bps()


class _OnlySet(StrictConfig):
    """Overrides: a field applies only if it was given (so ``range_m: null`` can mean
    'no range limit' rather than 'not overridden'); dumps only what was given."""

    #: Fields whose ``null`` is a value (the others' ``None`` only means "not given").
    NULLABLE: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="after")
    def _no_null_values(self) -> _OnlySet:
        bad = sorted(k for k in self.model_fields_set if getattr(self, k) is None and k not in self.NULLABLE)
        if bad:
            raise ValueError(f"{', '.join(bad)}: null is no value here (leave the key out to keep the default)")
        return self

    @model_serializer(mode="wrap")
    def _dump_set_fields(self, handler):
        data = handler(self)
        return {k: v for k, v in data.items() if k in self.model_fields_set}

    def given(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.model_fields_set}


class LinkOverride(_OnlySet):
    """Any subset of :class:`LinkConfig`'s fields for the links a key names."""

    NULLABLE: ClassVar[frozenset[str]] = frozenset({"range_m", "windows", "ack_timeout_s", "trace"})

    enabled: bool | None = Field(None, description="overrides defaults.enabled")
    latency_s: Delay | None = Field(None, description="overrides defaults.latency_s")
    jitter_s: Delay | None = Field(None, description="overrides defaults.jitter_s")
    bandwidth_bps: Bandwidth | None = Field(None, description="overrides defaults.bandwidth_bps")
    mtu_bytes: int | None = Field(None, ge=16, le=1_000_000, description="overrides defaults.mtu_bytes")
    loss: LossConfig | None = Field(None, description="replaces defaults.loss as a whole")
    range_m: PositiveFloat | None = Field(None, description="overrides defaults.range_m (null: no range limit)")
    line_of_sight: bool | None = Field(None, description="overrides defaults.line_of_sight")
    windows: list[Window] | None = Field(None, description="overrides defaults.windows (null: always up; []: never)")
    ack_timeout_s: PositiveFloat | None = Field(None, description="overrides defaults.ack_timeout_s (null: from both directions' latencies)")
    trace: TraceFile | None = Field(None, description="overrides defaults.trace (null: no trace, the link's own latency, bandwidth and loss)")

    _w = field_validator("windows")(lambda v: None if v is None else [_check_window(w) for w in v])


# --------------------------------------------------------------------------- kinds


class KindPolicy(StrictConfig):
    """How messages of one kind travel. ``priority``: 0 is served first; a link sends
    one fragment at a time and always picks the most urgent waiting one, so a pose is
    not stuck behind a 700 KB submap (thesis 8.4). ``max_queued``: messages of this
    kind one node may hold for sending (waiting for a route, queued on a link, or
    awaiting an ack)."""

    priority: int = Field(5, ge=0, le=15, description="0 is served first: a link always sends the most urgent waiting fragment")
    delivery: Delivery = Field(Delivery.BEST_EFFORT, description="best_effort: one try per hop; reliable: per-hop acks and retransmission")
    max_retries: int = Field(10, ge=0, le=1000, description="reliable: retransmission rounds per hop")
    outage: OutagePolicy = Field(OutagePolicy.STORE_AND_FORWARD, description="while no route is up: store_and_forward (held at the node) or drop")
    max_queued: int = Field(
        1000, ge=1, le=1_000_000, description="messages of this kind one node may hold for sending (waiting, queued on a link or awaiting an ack)"
    )
    when_full: WhenFull = Field(
        WhenFull.DROP_NEWEST, description="at max_queued: drop_newest drops the arriving message, drop_oldest the oldest waiting one"
    )


class KindOverride(_OnlySet):
    priority: int | None = Field(None, ge=0, le=15, description="overrides kind_defaults.priority")
    delivery: Delivery | None = Field(None, description="overrides kind_defaults.delivery")
    max_retries: int | None = Field(None, ge=0, le=1000, description="overrides kind_defaults.max_retries")
    outage: OutagePolicy | None = Field(None, description="overrides kind_defaults.outage")
    max_queued: int | None = Field(None, ge=1, le=1_000_000, description="overrides kind_defaults.max_queued")
    when_full: WhenFull | None = Field(None, description="overrides kind_defaults.when_full")


# --------------------------------------------------------------------------- availability


class OutageConfig(StrictConfig):
    """All named links down in ``[start_s, end_s)``. ``nodes``: every link to or from
    these nodes; ``links``: keys like ``links:`` uses; both empty: the whole network."""

    start_s: NonNegFloat = Field(..., description="the links go down at this simulated time")
    end_s: PositiveFloat = Field(..., description="the links come back up at this simulated time")
    nodes: list[Annotated[str, Field(pattern=NODE_PATTERN)]] = Field([], description="every link to or from these nodes")
    links: list[str] = Field([], description="link keys as comms.links uses them; nodes and links both empty: the whole network")

    @model_validator(mode="after")
    def _order(self) -> OutageConfig:
        if not self.end_s > self.start_s:
            raise ValueError(f"end_s ({self.end_s:g}) must be after start_s ({self.start_s:g})")
        for key in self.links:
            parse_link_key(key)
        return self


class RandomOutageConfig(StrictConfig):
    """Outages at random: up for an exponential time with mean ``mean_up_s``, then all
    named links (same scoping as :class:`OutageConfig`) down together for an
    exponential time with mean ``mean_down_s``, from ``start_s`` on. Seeded."""

    mean_up_s: OutageMean = Field(..., description="mean of the exponential time up between outages")
    mean_down_s: OutageMean = Field(..., description="mean of the exponential length of an outage")
    start_s: NonNegFloat = Field(0.0, description="the first up period starts at this simulated time")
    nodes: list[Annotated[str, Field(pattern=NODE_PATTERN)]] = Field([], description="every link to or from these nodes")
    links: list[str] = Field([], description="link keys as comms.links uses them; nodes and links both empty: the whole network")

    @field_validator("links")
    @classmethod
    def _keys(cls, value: list[str]) -> list[str]:
        for key in value:
            parse_link_key(key)
        return value


# --------------------------------------------------------------------------- presets

# Kinds of thesis 3.3. The lead's slam messages use these names; any other kind gets
# ``kind_defaults``. Poses are small and frequent: most urgent, and a stale one is
# worth less than a fresh one. Loop closures and match attempts are small and must
# not be lost (a pair is attempted once); so must frame switches (a lost one breaks a
# robot's chain of submap origins in every other robot's graph). Submaps (about 700 KB, thesis 8.4) are big.
BASE_KINDS: dict[str, dict[str, Any]] = {
    "pose": {"priority": 0, "delivery": "best_effort", "max_queued": 20, "when_full": "drop_oldest"},
    "detection": {"priority": 1, "delivery": "reliable"},
    "frame_switch": {"priority": 1, "delivery": "reliable"},
    "loop_closure": {"priority": 1, "delivery": "reliable"},
    "submap": {"priority": 3, "delivery": "reliable", "max_queued": 200},
    # exploration goals (thesis 9.3): small, rare, and a robot keeps away from the goals it heard of
    "goal": {"priority": 1, "delivery": "reliable"},
}

PRESETS: dict[Preset, dict[str, Any]] = {
    # An indoor 802.11n network as in the thesis's lab experiments: chosen values
    # (the thesis gives no figures), a few ms, tens of Mbit/s, rare loss.
    Preset.LAB_WIFI: {
        "defaults": {
            "latency_s": 0.002,
            "jitter_s": 0.002,
            "bandwidth_bps": 20e6,
            "mtu_bytes": 1400,
            "loss": {"model": "bernoulli", "rate": 0.001},
        },
    },
    # Thesis 9.2 / 7.2: 4 s round trip (2 s one way), 100 Mbit/s, uplink (ground
    # station -> site) blocked except in up to three five-minute checkpoints, whose
    # times a scenario sets in ``uplink_windows``. Every link passes the channel
    # simulator, as all traffic did at SpaceBotCamp. The thesis reports outages and
    # packet loss but no figures: add them with ``outages``/``random_outages``/``loss``.
    Preset.SPACEBOTCAMP: {
        "defaults": {
            "latency_s": 2.0,
            "jitter_s": 0.0,
            "bandwidth_bps": 100e6,
            "mtu_bytes": 1400,
            "loss": {"model": "none"},
        },
        "ground_station": "ground",
        "uplink_windows": [],
    },
    # A surface-to-surface UHF proximity radio: chosen values (not from the thesis):
    # 256 kbit/s, a few ms of MAC delay, 1 % bursty loss, 300 m range, line of sight.
    Preset.LUNAR_SURFACE_UHF: {
        "defaults": {
            "latency_s": 0.005,
            "jitter_s": 0.005,
            "bandwidth_bps": 256e3,
            "mtu_bytes": 1024,
            "loss": {"model": "gilbert_elliott", "rate": 0.01, "mean_burst_fragments": 3},
            "range_m": 300.0,
            "line_of_sight": True,
        },
    },
}


def _deep_merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in top.items():
        if isinstance(value, BaseModel):  # a model given from Python: merge what it set
            value = value.model_dump(exclude_unset=True)
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


# --------------------------------------------------------------------------- root


class CommsConfig(StrictConfig):
    """The scenario's ``comms:`` section (see the module docstring)."""

    enabled: bool = Field(True, description="false: every link is down, robots share nothing")
    preset: Preset | None = Field(
        Preset.LAB_WIFI, description="channel merged under this section: lab_wifi, spacebotcamp (thesis 9.2) or lunar_surface_uhf; null: no preset"
    )
    defaults: LinkConfig = Field(LinkConfig(), description="every link direction before the links overrides (merged over the preset's)")
    links: dict[str, LinkOverride] = Field(
        {}, description="overrides keyed 'a->b' (one direction) or 'a<->b' (both), '*' any node; keys naming more nodes apply later"
    )
    kind_defaults: KindPolicy = Field(KindPolicy(), description="delivery policy of message kinds that kinds does not name")
    kinds: dict[str, KindOverride] = Field(
        {},
        description="per message kind, overrides of kind_defaults (built in: pose, detection, frame_switch, loop_closure, submap, goal)",
    )
    outages: list[OutageConfig] = Field([], description="scheduled outages: named links down in [start_s, end_s)")
    random_outages: list[RandomOutageConfig] = Field([], description="outages at random times (seeded)")
    ground_station: str | None = Field(
        None, pattern=NODE_PATTERN, description="an Earth-side node added to the network; it has no position"
    )
    uplink_windows: list[Window] | None = Field(
        None, description="links from the ground station are up only in these windows (null: always; []: never)"
    )
    relays: list[Annotated[str, Field(pattern=NODE_PATTERN)]] = Field(
        [], description="nodes that forward messages for others over links that are up"
    )
    poll_interval_s: Period = Field(0.5, description="how often range and line of sight are evaluated")
    stats_interval_s: Period = Field(1.0, description="sampling period of the link time series")

    @model_validator(mode="before")
    @classmethod
    def _apply_preset(cls, data: Any) -> Any:
        """Layer: built-in kinds <- preset <- what the section sets."""
        if not isinstance(data, dict):
            return data
        preset = data.get("preset", Preset.LAB_WIFI.value)
        base: dict[str, Any] = {"kinds": BASE_KINDS}
        if preset is not None:
            try:
                base = _deep_merge(base, PRESETS[Preset(preset)])
            except ValueError:
                allowed = ", ".join(p.value for p in Preset)
                raise ValueError(f"preset {preset!r} is not one of: {allowed}") from None
        return _deep_merge(base, data)

    @field_validator("links", "kinds", mode="after")
    @classmethod
    def _keys(cls, value: dict[str, Any], info) -> dict[str, Any]:
        if info.field_name == "links":
            for key in value:
                parse_link_key(key)
        else:
            for key in value:
                if not key or not key.strip():
                    raise ValueError("kind names must not be empty")
        return value

    _uw = field_validator("uplink_windows")(lambda v: None if v is None else [_check_window(w) for w in v])

    # ----------------------------------------------------------------- helpers

    def extra_nodes(self) -> list[str]:
        """Nodes the section adds to the network beside the ones the simulator names
        (the ground station)."""
        return [self.ground_station] if self.ground_station else []

    def kind_policy(self, kind: str) -> KindPolicy:
        """The resolved policy of a message kind (``kind_defaults`` + ``kinds[kind]``)."""
        override = self.kinds.get(kind)
        if override is None:
            return self.kind_defaults
        return KindPolicy.model_validate({**self.kind_defaults.model_dump(), **override.given()})

    def check_nodes(self, nodes: list[str] | tuple[str, ...]) -> None:
        """Raise :class:`CommsError` naming every node this section mentions that the
        network does not have (call it from the scenario validator for early errors)."""
        known = set(nodes)
        problems: list[str] = []
        if len(known) != len(nodes):
            problems.append(f"node names must be unique, got {list(nodes)}")

        def need(name: str, where: str) -> None:
            if name != "*" and name not in known:
                problems.append(f"{where}: unknown node {name!r}; nodes: {sorted(known)}")

        for key in self.links:
            a, b, _ = parse_link_key(key)
            need(a, f"comms.links.{key}")
            need(b, f"comms.links.{key}")
        for i, outage in enumerate([*self.outages, *self.random_outages]):
            where = f"comms.{'outages' if i < len(self.outages) else 'random_outages'}"
            for n in outage.nodes:
                need(n, where)
            for key in outage.links:
                a, b, _ = parse_link_key(key)
                need(a, where)
                need(b, where)
        for n in self.relays:
            need(n, "comms.relays")
        if self.ground_station:
            need(self.ground_station, "comms.ground_station")
        if problems:
            raise CommsError("\n".join(problems))


# --------------------------------------------------------------------------- resolution


def parse_link_key(key: str) -> tuple[str, str, bool]:
    """``"a->b"`` -> ``("a", "b", False)``; ``"a<->b"`` -> ``("a", "b", True)``."""
    m = LINK_KEY.match(key)
    if not m:
        raise CommsError(f"link key {key!r}: expected 'a->b' (one direction) or 'a<->b' (both), '*' for any node")
    a, arrow, b = m.groups()
    return a, b, arrow == "<->"


def link_key_matches(key: str, src: str, dst: str) -> bool:
    a, b, both = parse_link_key(key)

    def fits(x: str, y: str) -> bool:
        return (a == "*" or a == x) and (b == "*" or b == y)

    return fits(src, dst) or (both and fits(dst, src))


def _specificity(key: str) -> tuple[int, int]:
    a, b, both = parse_link_key(key)
    return (int(a != "*") + int(b != "*"), 0 if both else 1)


def resolve_links(config: CommsConfig, nodes: list[str] | tuple[str, ...]) -> dict[tuple[str, str], LinkConfig]:
    """Every ordered pair of distinct nodes -> its :class:`LinkConfig`.

    Layers: ``defaults``; for links leaving the ground station, ``uplink_windows``;
    then the ``links`` overrides that match, least specific first (fewer named nodes,
    a pair before a direction, then in the order given)."""
    config.check_nodes(list(nodes))
    ordered = sorted(enumerate(config.links.items()), key=lambda item: (_specificity(item[1][0]), item[0]))
    base = config.defaults.model_dump()
    base["trace"] = config.defaults.trace  # the parsed trace, not its path: read once
    out: dict[tuple[str, str], LinkConfig] = {}
    for src in nodes:
        for dst in nodes:
            if src == dst:
                continue
            params = dict(base)
            if config.ground_station is not None and src == config.ground_station and config.uplink_windows is not None:
                params["windows"] = [tuple(w) for w in config.uplink_windows]
            for _, (key, override) in ordered:
                if link_key_matches(key, src, dst):
                    given = override.given()
                    if "loss" in given and given["loss"] is not None:
                        given["loss"] = given["loss"].model_dump()
                    params.update(given)
            try:
                out[(src, dst)] = LinkConfig.model_validate(params)
            except ValidationError as exc:  # an override combination that is invalid as a whole
                raise CommsError(f"link {src}->{dst}: {exc}") from None
    return out


def outage_links(spec: OutageConfig | RandomOutageConfig, nodes: list[str] | tuple[str, ...]) -> list[tuple[str, str]]:
    """The ordered pairs an outage takes down."""
    pairs = [(a, b) for a in nodes for b in nodes if a != b]
    if not spec.nodes and not spec.links:
        return pairs
    chosen = set(spec.nodes)
    return [
        (a, b)
        for a, b in pairs
        if a in chosen or b in chosen or any(link_key_matches(k, a, b) for k in spec.links)
    ]


def auto_ack_timeout(forward: LinkConfig, reverse: LinkConfig, ack_bytes: int) -> float:
    """Reliable delivery's retransmission timeout when none is configured: the round
    trip (both latencies plus jitters), one MTU of the reverse link that an ack may
    wait behind, the ack itself, times 1.25, plus 10 ms. A link that follows a trace
    counts with its worst row (largest latency, smallest bandwidth)."""
    rtt = forward.worst_latency_s() + forward.jitter_s + reverse.worst_latency_s() + reverse.jitter_s
    wait = 8.0 * (reverse.mtu_bytes + ack_bytes) / reverse.worst_bandwidth_bps()
    value = 1.25 * (rtt + wait) + 0.01
    return value if math.isfinite(value) else 1.0
