"""Loss against its configuration: rates within binomial bounds, bursts of the
configured mean length, per-fragment loss of fragmented messages."""

import math

import numpy as np
import pytest
from comms_util import make_net

from comms.loss import BernoulliLoss, GilbertElliottLoss

N = 20_000


def within_binomial(k: int, n: int, p: float, sigmas: float = 4.0) -> bool:
    return abs(k / n - p) <= sigmas * math.sqrt(p * (1 - p) / n)


def run_best_effort(loss: dict, size: int, n: int = N, seed: int = 1, mtu: int = 1000):
    env, net = make_net(
        seed=seed,
        defaults={"latency_s": 0.01, "bandwidth_bps": 1e9, "mtu_bytes": mtu, "loss": loss},
        kinds={"blob": {"delivery": "best_effort", "max_queued": 1_000_000}},
    )
    msgs = [net.send("a", "b", "blob", bytes(size)) for _ in range(n)]
    env.run(until=10)
    return net, msgs


def burst_lengths(lost: np.ndarray) -> np.ndarray:
    """Lengths of the runs of consecutive True."""
    padded = np.concatenate([[0], lost.astype(np.int8), [0]])
    edges = np.flatnonzero(np.diff(padded))
    return edges[1::2] - edges[::2]


def test_bernoulli_loss_rate_matches_within_binomial_bound():
    net, msgs = run_best_effort({"model": "bernoulli", "rate": 0.05}, size=100)
    dropped = sum(net.accounting.fate(m.id) == "loss" for m in msgs)
    assert within_binomial(dropped, N, 0.05)
    row = net.to_table()[0]
    assert row["dropped_loss_msgs"] == dropped and row["delivered_msgs"] == N - dropped
    assert row["dropped_loss_bytes"] == 100 * dropped


def test_a_fragmented_message_is_lost_if_any_fragment_is():
    n, k, p = 4000, 8, 0.02
    net, msgs = run_best_effort({"model": "bernoulli", "rate": p}, size=k * 1000, n=n)
    delivered = sum(net.accounting.fate(m.id) == "delivered" for m in msgs)
    assert within_binomial(delivered, n, (1 - p) ** k)
    stats = net.accounting.links[("a", "b")]
    assert within_binomial(stats.fragments_lost, n * k, p)


def test_gilbert_elliott_has_the_configured_rate_and_mean_burst():
    model = GilbertElliottLoss(0.05 * 0.25 / 0.95, 0.25, 0.0, 1.0, np.random.default_rng(3))
    lost = np.array([model.lost(0.0) for _ in range(200_000)])
    assert lost.mean() == pytest.approx(0.05, rel=0.1)
    assert burst_lengths(lost).mean() == pytest.approx(4.0, rel=0.1)
    independent = BernoulliLoss(0.05, np.random.default_rng(3))
    plain = np.array([independent.lost(0.0) for _ in range(200_000)])
    assert burst_lengths(plain).mean() == pytest.approx(1 / 0.95, rel=0.05)


def test_bursty_loss_on_a_link_loses_messages_in_runs():
    net, msgs = run_best_effort({"model": "gilbert_elliott", "rate": 0.05, "mean_burst_fragments": 5}, size=100)
    lost = np.array([net.accounting.fate(m.id) == "loss" for m in msgs])
    assert lost.mean() == pytest.approx(0.05, abs=0.015)
    assert burst_lengths(lost).mean() == pytest.approx(5.0, rel=0.25)
