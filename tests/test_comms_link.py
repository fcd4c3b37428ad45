"""Timing of one link against the formulas: serialization + propagation, the cap,
priorities between fragments, jitter without reordering."""

import numpy as np
import pytest
from comms_util import collect, make_net, send_at

from comms import CommsError

BW = 1e6  # bit/s
LAT = 0.25


def lone(size, mtu=1000, **defaults):
    env, net = make_net(defaults={"latency_s": LAT, "bandwidth_bps": BW, "mtu_bytes": mtu, **defaults})
    got = collect(env, net, "b")
    net.send("a", "b", "blob", bytes(size))
    env.run(until=100)
    return net, got


@pytest.mark.parametrize("size", [0, 1, 999, 1000, 1001, 65_536, 700_000])
def test_lone_message_latency_is_serialization_plus_propagation(size):
    net, got = lone(size)
    assert len(got) == 1 and got[0].message.size == size
    assert got[0].latency == pytest.approx(8 * size / BW + LAT, rel=1e-12, abs=1e-12)
    stats = net.accounting.links[("a", "b")]
    assert stats.fragments_sent == max(1, -(-size // 1000))
    assert stats.wire_bytes == size


def test_payload_size_is_the_length_of_the_bytes():
    _, net = make_net()
    msg = net.send("a", "b", "blob", bytearray(b"abc"))
    assert msg.size == 3 and msg.payload == b"abc"
    for bad in ("text", 12, np.zeros(3)):
        with pytest.raises(CommsError, match="bytes"):
            net.send("a", "b", "blob", bad)
    with pytest.raises(CommsError, match="unknown node 'c'"):
        net.send("a", "c", "blob", b"x")
    with pytest.raises(CommsError, match="priority"):
        net.send("a", "b", "blob", b"x", priority=99)


def test_saturated_link_delivers_at_its_cap():
    env, net = make_net(defaults={"latency_s": LAT, "bandwidth_bps": BW, "mtu_bytes": 1400})
    got = collect(env, net, "b")
    n, size = 300, 12_345
    for _ in range(n):
        net.send("a", "b", "blob", bytes(size))
    env.run(until=60)
    assert len(got) == n
    times = np.array([d.received_at for d in got])
    measured = 8 * size * (n - 1) / (times[-1] - times[0])
    assert measured == pytest.approx(BW, rel=0.01)
    assert [d.message.id for d in got] == sorted(d.message.id for d in got)  # FIFO


def test_pose_overtakes_a_queued_submap():
    # thesis 8.4: submaps of about 700 KB; a pose must not wait the ~5.6 s behind it
    env, net = make_net(defaults={"latency_s": LAT, "bandwidth_bps": BW, "mtu_bytes": 1400})
    got = collect(env, net, "b")
    net.send("a", "b", "submap", bytes(700_000))
    send_at(env, 1.0, lambda: net.send("a", "b", "pose", bytes(200)))
    env.run(until=20)
    assert [d.message.kind for d in got] == ["pose", "submap"]
    pose, submap = got
    # at most one submap fragment in serialization ahead of it
    assert pose.latency <= 8 * (1400 + 200) / BW + LAT + 1e-12
    assert submap.latency == pytest.approx(8 * 700_200 / BW + LAT, rel=1e-12)


def test_same_priority_is_first_come_first_served():
    env, net = make_net(defaults={"latency_s": LAT, "bandwidth_bps": BW})
    got = collect(env, net, "b")
    net.send("a", "b", "submap", bytes(50_000))
    net.send("a", "b", "submap", bytes(10))
    net.send("a", "b", "blob", bytes(10), priority=0)
    env.run(until=10)
    assert [d.message.size for d in got] == [10, 50_000, 10]


def test_jitter_stays_within_bounds_and_never_reorders():
    env, net = make_net(defaults={"latency_s": LAT, "jitter_s": 0.1, "bandwidth_bps": 1e9})
    got = collect(env, net, "b")
    for i in range(200):
        send_at(env, i * 0.01, lambda: net.send("a", "b", "blob", bytes(100)))
    env.run(until=10)
    lat = np.array([d.latency for d in got])
    assert len(got) == 200
    assert lat.min() >= LAT and lat.max() <= LAT + 0.1 + 0.01 + 1e-9
    assert lat.std() > 0.01  # jitter really varies
    ids = [d.message.id for d in got]
    assert ids == sorted(ids)
