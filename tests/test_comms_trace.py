"""Link traces (comms/trace.py): delivery times and loss follow the row in effect at each
fragment's send time, traces are checked when the configuration is loaded, and a scenario
can name the shipped example."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from comms_util import collect, make_net, send_at
from pydantic import ValidationError

from comms import CommsConfig, LinkConfig, resolve_links
from comms.config import auto_ack_timeout
from comms.trace import LinkTrace, load_trace
from sim.batch.spec import check, load_batch, scenario_dict
from sim.scenario import ScenarioError, dump_scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "assets" / "link_traces" / "example_degrading.csv"
QUICKSTART = ROOT / "scenarios" / "quickstart.yaml"
HEADER = "t_s,latency_s,bandwidth_bps,loss"


def write(tmp_path: Path, text: str, name: str = "trace.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def within_binomial(k: int, n: int, p: float, sigmas: float = 4.0) -> bool:
    return abs(k / n - p) <= sigmas * math.sqrt(p * (1 - p) / n)


def expected_arrival(trace: LinkTrace, start: float, sizes: list[int], last_arrival: float = 0.0) -> tuple[float, float]:
    """What the link does: each fragment takes the row in effect when it starts to
    serialize; arrivals never overtake. Returns (arrival of the last fragment, end of serialization)."""
    t = start
    for size in sizes:
        row = trace.row(t)
        t = t + 8.0 * size / trace.bandwidth_bps[row]
        last_arrival = max(t + trace.latency_s[row], last_arrival)
    return last_arrival, t


def test_delivery_time_follows_latency_and_bandwidth_of_each_segment(tmp_path):
    path = write(tmp_path, f"{HEADER}\n0,0.1,1e6,0\n10,0.5,2e5,0\n20,0.02,4e6,0\n")
    env, net = make_net(defaults={"trace": str(path), "latency_s": 9.0, "bandwidth_bps": 1.0, "mtu_bytes": 1000})
    got = collect(env, net, "b")
    trace = net.link("a", "b").cfg.trace
    # one message inside each segment, one whose fragments straddle 10 s, one whose later
    # fragments (at 20 s: 20 ms) would overtake earlier ones (0.5 s) if a link reordered
    plan = [(1.0, 5_000), (12.0, 3_000), (25.0, 20_000), (9.98, 4_000), (19.99, 2_000)]
    for t, size in plan:
        send_at(env, t, lambda size=size: net.send("a", "b", "blob", bytes(size)))
    env.run(until=60)
    assert len(got) == len(plan)
    by_size = {d.message.size: d for d in got}
    for t, size in plan:
        sizes = [1000] * (size // 1000)
        arrival, _ = expected_arrival(trace, t, sizes)
        assert by_size[size].received_at == pytest.approx(arrival, rel=1e-12, abs=1e-12), (t, size)
    # the straddling messages really changed rows mid-message
    assert trace.row(9.98) == 0 and trace.row(9.98 + 8 * 3000 / 1e6) == 1
    assert expected_arrival(trace, 19.99, [1000])[0] > expected_arrival(trace, 19.99, [1000] * 2)[1] + trace.latency_s[2]


def test_observed_loss_in_each_segment_matches_the_trace(tmp_path):
    rates = [0.0, 0.2, 0.05]
    path = write(tmp_path, f"{HEADER}\n0,0.01,1e9,{rates[0]}\n10,0.01,1e9,{rates[1]}\n20,0.01,1e9,{rates[2]}\n")

    def run(seed: int) -> dict[int, list[bool]]:
        env, net = make_net(
            seed=seed,
            defaults={"trace": str(path), "loss": {"model": "bernoulli", "rate": 0.5}},
            kinds={"blob": {"delivery": "best_effort", "max_queued": 1_000_000}},
        )
        sent: dict[int, list] = {0: [], 1: [], 2: []}
        for segment, t in enumerate((1.0, 11.0, 21.0)):
            send_at(env, t, lambda seg=segment: sent[seg].extend(net.send("a", "b", "blob", bytes(100)) for _ in range(5000)))
        env.run(until=40)
        return {seg: [net.accounting.fate(m.id) == "loss" for m in msgs] for seg, msgs in sent.items()}

    lost = run(seed=7)
    for segment, rate in enumerate(rates):
        k, n = sum(lost[segment]), len(lost[segment])
        if rate == 0.0:
            assert k == 0
        else:
            assert within_binomial(k, n, rate), (segment, k / n, rate)
    assert run(seed=7) == lost  # deterministic: the link's own loss stream
    assert run(seed=8) != lost


def test_jitter_and_outages_still_apply(tmp_path):
    path = write(tmp_path, f"{HEADER}\n0,0.1,1e6,0\n")
    env, net = make_net(defaults={"trace": str(path), "jitter_s": 0.05}, outages=[{"start_s": 0, "end_s": 5}])
    got = collect(env, net, "b")
    net.send("a", "b", "blob", bytes(100))
    env.run(until=10)
    assert len(got) == 1
    assert 5.0 + 8 * 100 / 1e6 + 0.1 <= got[0].received_at <= 5.0 + 8 * 100 / 1e6 + 0.15


def test_overrides_set_and_clear_a_trace_and_timeouts_plan_with_its_worst_row(tmp_path):
    path = write(tmp_path, f"{HEADER}\n0,0.1,1e6,0\n5,0.7,5e4,0.1\n")
    cfg = CommsConfig.model_validate({"preset": None, "defaults": {"trace": str(path)}, "links": {"b->a": {"trace": None}}})
    links = resolve_links(cfg, ["a", "b"])
    assert links[("a", "b")].trace is cfg.defaults.trace  # parsed once, shared
    assert links[("b", "a")].trace is None
    forward, reverse = links[("a", "b")], links[("b", "a")]
    assert forward.worst_latency_s() == 0.7 and forward.worst_bandwidth_bps() == 5e4
    plain = LinkConfig(latency_s=0.7, bandwidth_bps=5e4)
    assert auto_ack_timeout(forward, reverse, 64) == auto_ack_timeout(plain, reverse, 64)


def test_a_trace_dumps_as_its_absolute_path_and_the_schema_says_string(tmp_path, monkeypatch):
    write(tmp_path, f"{HEADER}\n0,0.1,1e6,0\n")
    monkeypatch.chdir(tmp_path)
    cfg = LinkConfig.model_validate({"trace": "trace.csv"})
    assert cfg.model_dump()["trace"] == str(tmp_path.resolve() / "trace.csv")
    assert cfg.model_dump(mode="json")["trace"] == str(tmp_path.resolve() / "trace.csv")
    assert LinkConfig.model_validate(cfg.model_dump()) == cfg
    schema = LinkConfig.model_json_schema()["properties"]["trace"]
    assert {"type": "string"} in schema["anyOf"] and {"type": "null"} in schema["anyOf"]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("t_s,latency,bandwidth_bps,loss\n0,0.1,1e6,0\n", "unknown column(s) 'latency'; missing latency_s"),
        (f"{HEADER},rssi_dbm\n0,0.1,1e6,0,-60\n", "unknown column(s) 'rssi_dbm'"),
        ("", "empty file"),
        (f"{HEADER}\n", "no rows"),
        (f"{HEADER}\n1,0.1,1e6,0\n", "line 2: t_s 1: the first row must start at t_s 0"),
        (f"{HEADER}\n0,0.1,1e6,0\n5,0.1,1e6,0\n5,0.2,1e6,0\n", "line 4: t_s 5 is not after the previous row's 5"),
        (f"{HEADER}\n0,0.1,1e6,0\n5,0.1,1e6,0\n3,0.2,1e6,0\n", "line 4: t_s 3 is not after"),
        (f"{HEADER}\n0,-0.1,1e6,0\n", "line 2: latency_s -0.1 out of range"),
        (f"{HEADER}\n0,0.1,0,0\n", "line 2: bandwidth_bps 0 out of range"),
        (f"{HEADER}\n0,0.1,1e6,1.0\n", "line 2: loss 1 out of range: 0 <= loss < 1"),
        (f"{HEADER}\n0,0.1,1e6,-0.1\n", "line 2: loss -0.1 out of range"),
        (f"{HEADER}\n0,nan,1e6,0\n", "line 2: latency_s is nan, must be finite"),
        (f"{HEADER}\n0,0.1,fast,0\n", "line 2: bandwidth_bps 'fast' is not a number"),
        (f"{HEADER}\n0,0.1,1e6\n", "line 2: 3 values, expected 4"),
    ],
)
def test_bad_traces_are_scenario_errors_naming_the_key(tmp_path, text, problem):
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(QUICKSTART, [f"comms.defaults.trace={path}"])
    (line,) = info.value.problems
    assert line.startswith("comms.defaults.trace: got '") and f": trace {path}" in line, line  # the value itself is shortened
    assert problem in line, line
    with pytest.raises(ValidationError, match="defaults.trace"):
        CommsConfig.model_validate({"defaults": {"trace": str(path)}})


def test_a_missing_trace_names_the_key_and_where_it_looked(tmp_path):
    with pytest.raises(ScenarioError) as info:
        load_scenario(QUICKSTART, ["comms.links={'lru1->lru2': {trace: no_such.csv}}"])
    (line,) = info.value.problems
    assert line.startswith("comms.links.lru1->lru2.trace: got 'no_such.csv': no trace file ")
    assert str(QUICKSTART.parent / "no_such.csv") in line and f"taken from {QUICKSTART.parent}" in line


def test_relative_paths_are_taken_from_the_scenario_folder(tmp_path, monkeypatch):
    (tmp_path / "traces").mkdir()
    write(tmp_path / "traces", f"{HEADER}\n0,0.1,1e6,0\n", "link.csv")
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(QUICKSTART.read_text())
    monkeypatch.chdir(ROOT)
    loaded = load_scenario(scenario, ["comms.defaults.trace=traces/link.csv"])
    assert loaded.comms.defaults.trace.path == str((tmp_path / "traces" / "link.csv").resolve())


def test_the_example_trace_loads_in_a_scenario():
    scenario = load_scenario(QUICKSTART, ["comms.defaults.trace=../assets/link_traces/example_degrading.csv"])
    trace = scenario.comms.defaults.trace
    assert trace == load_trace(EXAMPLE)
    assert trace.t_s[0] == 0 and np.all(np.diff(trace.t_s) > 0)
    assert max(trace.loss) < 1 and trace.bandwidth_bps[0] > trace.min_bandwidth_bps()
    again = load_scenario(yaml.safe_load(dump_scenario(scenario)))
    assert again.comms.defaults.trace == trace


def test_a_batch_takes_relative_trace_paths_from_its_base_scenario_folder(tmp_path, monkeypatch):
    (tmp_path / "scenarios").mkdir()
    write(tmp_path / "scenarios", f"{HEADER}\n0,0.1,1e6,0\n", "link.csv")
    (tmp_path / "scenarios" / "base.yaml").write_text(QUICKSTART.read_text())
    batch_file = tmp_path / "batch.yaml"
    batch_file.write_text("name: traced\nscenario: scenarios/base.yaml\nseeds: 1\nset: {comms.defaults.trace: link.csv}\n")
    monkeypatch.chdir(ROOT)
    batch = load_batch(batch_file)
    assert check(batch) == []
    (spec,) = batch.specs()
    scenario = load_scenario(scenario_dict(spec.raw, spec.robots), spec.overrides, spec.base_dir)
    assert scenario.comms.defaults.trace.path == str((tmp_path / "scenarios" / "link.csv").resolve())
