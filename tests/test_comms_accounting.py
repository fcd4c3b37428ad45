"""Accounting: invariants under a mixed load, plain-data reports, determinism, and
the raw-equivalent stereo load of thesis 8.4."""

import json

import numpy as np
import pytest
from comms_util import make_net

from comms import StereoStream, raw_stereo_load
from comms.load import LRU_GUPPY_PRO_F125B

NODES = ["lru1", "lru2", "ardea", "lander"]


def busy_network(seed: int, until: float = 60.0, keep_log: bool = False):
    """Four nodes, bursty loss, random and scheduled outages, a relay, all kinds. Returns
    the network, the deliveries per node and every message handed to it (in send order)."""
    env, net = make_net(
        nodes=NODES,
        seed=seed,
        keep_log=keep_log,
        defaults={
            "latency_s": 0.05,
            "jitter_s": 0.02,
            "bandwidth_bps": 2e6,
            "mtu_bytes": 1400,
            "loss": {"model": "gilbert_elliott", "rate": 0.03, "mean_burst_fragments": 3},
        },
        relays=["lander"],
        outages=[{"start_s": 10, "end_s": 20, "links": ["lru1<->lru2"]}, {"start_s": 30, "end_s": 35, "nodes": ["lander"]}],
        random_outages=[{"mean_up_s": 8, "mean_down_s": 2, "links": ["ardea<->*"]}],
        kinds={"submap": {"max_queued": 3}},
    )
    received = {n: [] for n in NODES}
    sent = []
    for n in NODES:
        net.on_receive(n, received[n].append)
    rng = np.random.default_rng(seed)
    robots = NODES[:3]

    def robot(name):
        k = 0
        while True:
            yield env.timeout(0.1)
            k += 1
            sent.extend(net.broadcast(name, "pose", rng.bytes(120), to=robots))
            if k % 20 == 0:
                other = robots[(robots.index(name) + 1) % 3]
                sent.append(net.send(name, other, "loop_closure", rng.bytes(400)))
            if k % 50 == 0:
                sent.extend(net.broadcast(name, "submap", rng.bytes(int(rng.integers(50_000, 200_000))), to=robots))

    for name in robots:
        env.process(robot(name))
    env.run(until=until)
    return net, received, sent


def test_every_message_has_one_fate_and_none_arrives_twice():
    net, received, sent = busy_network(seed=11)
    deliveries = [d for got in received.values() for d in got]
    ids = [d.message.id for d in deliveries]
    assert len(ids) == len(set(ids))
    # the totals against what was handed in and what arrived, message by message
    fates = {m.id: net.accounting.fate(m.id) for m in sent}
    assert len(fates) == len(sent)
    assert {i for i, fate in fates.items() if fate == "delivered"} == set(ids)
    totals = net.to_metrics()["totals"]
    assert totals["offered_msgs"] == len(sent) and totals["offered_bytes"] == sum(m.size for m in sent)
    assert totals["delivered_msgs"] == len(deliveries) and totals["delivered_bytes"] == sum(d.message.size for d in deliveries)
    reasons = totals["dropped_by_reason"]
    for reason, dropped in reasons.items():  # each undelivered message counted once, under the reason of its fate
        lost = [m for m in sent if fates[m.id] == reason]
        assert (dropped["msgs"], dropped["bytes"]) == (len(lost), sum(m.size for m in lost)), reason
    assert totals["pending_msgs"] == sum(fate is None for fate in fates.values())
    assert reasons["loss"]["msgs"] > 0 and reasons["queue_full"]["msgs"] > 0  # poses lost, and pushed out of their bounded queue
    for d in deliveries:
        assert d.received_at >= d.message.sent_at + 0.05 * (len(d.path) - 1)
    by_kind = net.to_metrics()["by_kind"]
    assert by_kind["loop_closure"]["dropped_msgs"] == 0  # reliable
    assert by_kind["pose"]["latency_s"]["p50"] < by_kind["submap"]["latency_s"]["p50"]


def test_benchmark_runs():
    from comms.bench import run

    result = run(sim_seconds=2.0, robots=4)
    assert result["nodes"] == 5 and result["messages_delivered"] > 0 and result["messages_per_wall_s"] > 0


def test_reports_are_plain_json_data():
    net, _, _ = busy_network(seed=12, until=20)
    metrics = net.to_metrics()
    json.dumps(metrics)
    json.dumps(net.to_table())
    json.dumps(net.link_table())
    series = net.timeseries()
    json.dumps(series)
    assert len(series["t"]) == 19 and set(series["links"]) == {f"{a}->{b}" for a in NODES for b in NODES if a != b}
    row = net.to_table()[0]
    assert {"src", "dst", "kind", "offered_bytes", "delivered_bytes", "dropped_loss_bytes", "latency_p95_s"} <= set(row)
    link = metrics["by_link"]["lru1->lru2"]
    assert 0 < link["up_fraction"] < 1 and link["queue_bytes_max"] > 0
    assert link["wire_bytes"] >= link["completed_bytes"]


def test_same_seed_same_event_log_other_seed_other_log():
    a, _, _ = busy_network(seed=21, until=30, keep_log=True)
    b, _, _ = busy_network(seed=21, until=30, keep_log=True)
    c, _, _ = busy_network(seed=22, until=30)
    assert len(a.accounting.log) > 1000
    assert a.accounting.log == b.accounting.log
    assert a.accounting.digest() == b.accounting.digest()
    assert a.to_metrics() == b.to_metrics()
    assert a.accounting.digest() != c.accounting.digest()
    assert c.accounting.log is None  # kept only on request


def test_raw_stereo_load_of_the_lru():
    # thesis 7.1: Guppy PRO F-125B, 1292 x 964 px greyscale -> the "1.25 MB image" of 8.4
    assert LRU_GUPPY_PRO_F125B.image_bytes == 1292 * 964 == 1_245_488
    assert LRU_GUPPY_PRO_F125B.image_bytes / 1e6 == pytest.approx(1.25, abs=0.005)
    # one stereo pair at 14.3 Hz; the thesis's 38.75 MB/s is 2 x 1.25 MB x 15.5 Hz
    # (see comms/load.py: the thesis's three figures disagree with each other)
    assert raw_stereo_load([LRU_GUPPY_PRO_F125B]) == pytest.approx(2 * 1_245_488 * 14.3)
    assert raw_stereo_load([StereoStream(1000, 1250, rate_hz=15.5)]) == pytest.approx(38.75e6)
    # a team: two LRUs and ARDEA (two pairs of 666 x 506 virtual pinholes at 8 Hz)
    team = [LRU_GUPPY_PRO_F125B, LRU_GUPPY_PRO_F125B, StereoStream(666, 506, rate_hz=8.0, pairs=2)]
    assert raw_stereo_load(team) == pytest.approx(2 * 2 * 1_245_488 * 14.3 + 4 * 666 * 506 * 8.0)
    rgb = StereoStream(320, 240, rate_hz=5, channels=3)
    assert rgb.bytes_per_s == 2 * 320 * 240 * 3 * 5
