"""Reliable delivery: acks, retransmission, exactly once."""

import pytest
from comms_util import collect, make_net

LINK = {"latency_s": 0.05, "bandwidth_bps": 2e6, "mtu_bytes": 500}


def test_reliable_delivery_recovers_from_loss_exactly_once():
    env, net = make_net(
        seed=4,
        defaults={**LINK, "loss": {"model": "bernoulli", "rate": 0.2}},
        kinds={"submap": {"delivery": "reliable", "max_retries": 50}},
    )
    got = collect(env, net, "b")
    sent = [net.send("a", "b", "submap", bytes([i % 256]) * (1000 + 37 * i)) for i in range(100)]
    env.run(until=200)
    ids = [d.message.id for d in got]
    assert sorted(ids) == [m.id for m in sent]  # every one, once
    assert all(d.message.payload == m.payload for d, m in zip(sorted(got, key=lambda d: d.message.id), sent))
    stats = net.accounting.links[("a", "b")]
    assert stats.fragments_lost > 0 and stats.retransmitted_bytes > 0
    assert net.accounting.links[("b", "a")].ack_bytes > 0  # acks are real bytes on the reverse link
    row = net.to_table()[0]
    assert row["delivered_msgs"] == 100 and row["dropped_msgs"] == 0 and row["pending_msgs"] == 0


def test_lost_acks_cause_retransmissions_but_no_duplicate_delivery():
    env, net = make_net(
        seed=5,
        defaults=LINK,
        links={"b->a": {"loss": {"model": "bernoulli", "rate": 0.5}}},
        kinds={"loop_closure": {"delivery": "reliable", "max_retries": 50}},
    )
    got = collect(env, net, "b")
    for _ in range(200):
        net.send("a", "b", "loop_closure", bytes(300))
    env.run(until=100)
    assert len(got) == 200 and len({d.message.id for d in got}) == 200
    assert net.accounting.links[("a", "b")].duplicates > 0  # resent after a lost ack, suppressed


def test_lossless_reliable_message_takes_one_round():
    env, net = make_net(defaults=LINK, kinds={"submap": {"delivery": "reliable"}})
    got = collect(env, net, "b")
    net.send("a", "b", "submap", bytes(10_000))
    env.run(until=10)
    assert got[0].latency == pytest.approx(8 * 10_000 / 2e6 + 0.05, rel=1e-12)
    assert net.accounting.links[("a", "b")].retransmission_rounds == 0


def test_reliable_gives_up_after_max_retries_and_says_why():
    env, net = make_net(
        seed=6,
        defaults={**LINK, "loss": {"model": "bernoulli", "rate": 0.95}},
        kinds={"submap": {"delivery": "reliable", "max_retries": 2}},
    )
    msg = net.send("a", "b", "submap", bytes(20_000))
    env.run(until=30)
    assert net.accounting.fate(msg.id) == "retries_exhausted"
    assert net.accounting.links[("a", "b")].give_ups == 1


def test_without_an_ack_path_the_sender_gives_up_but_the_message_arrived():
    # thesis 9.2: a one-way channel has no acknowledgements; what arrives still counts
    env, net = make_net(
        defaults=LINK,
        links={"b->a": {"enabled": False}},
        kinds={"submap": {"delivery": "reliable", "max_retries": 1}},
    )
    got = collect(env, net, "b")
    msg = net.send("a", "b", "submap", bytes(5000))
    env.run(until=10)
    assert len(got) == 1 and net.accounting.fate(msg.id) == "delivered"
    stats = net.accounting.links[("a", "b")]
    assert stats.give_ups == 1 and stats.acks_lost >= 2 and stats.duplicates == 1


def test_an_ack_cut_by_an_outage_leads_to_a_resend_after_reconnect_still_once():
    # the data arrives at 0.108 s, but b->a is down from 0.105 s: no ack gets back
    env, net = make_net(
        defaults={"latency_s": 0.1, "bandwidth_bps": 1e6, "mtu_bytes": 1000},
        outages=[{"start_s": 0.105, "end_s": 2.0, "links": ["a<->b"]}],
        kinds={"loop_closure": {"delivery": "reliable"}},
    )
    got = collect(env, net, "b")
    net.send("a", "b", "loop_closure", bytes(1000))
    env.run(until=1.0)
    assert len(got) == 1 and got[0].received_at == pytest.approx(0.108)
    assert len(net.held("a")) == 1  # the sender cannot know: it waits to resend
    env.run(until=5.0)
    assert len(got) == 1 and net.held("a") == []
    assert net.accounting.links[("a", "b")].duplicates == 1
    assert net._nodes["a"].buffered["loop_closure"] == 0  # acknowledged at last
