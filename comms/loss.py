"""Per-fragment loss: none, independent (Bernoulli), bursty (Gilbert-Elliott) or
following a link trace (independent, with the rate of the trace's row at the send time).

The Gilbert-Elliott channel is a two-state Markov chain stepped once per fragment: in
the good state a fragment is lost with ``loss_good``, in the bad state with
``loss_bad``. With ``loss_good = 0, loss_bad = 1`` the runs of consecutive losses are
geometric with mean ``1 / p_bad_to_good`` and the long-run loss rate is
``p_good_to_bad / (p_good_to_bad + p_bad_to_good)``. Every model draws from its own
``numpy.random.Generator``, so a seed fixes every loss.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from comms.config import LossConfig, LossModel
from comms.trace import LinkTrace

_BLOCK = 1024


class UniformStream:
    """Uniform draws in [0, 1) from a generator, fetched in blocks (one numpy call per
    1024 draws instead of one per fragment). The sequence depends only on the seed."""

    __slots__ = ("_buf", "_i", "_rng")

    def __init__(self, rng: np.random.Generator):
        self._rng = rng
        self._buf = rng.random(_BLOCK)
        self._i = 0

    def next(self) -> float:
        if self._i == _BLOCK:
            self._buf = self._rng.random(_BLOCK)
            self._i = 0
        value = self._buf[self._i]
        self._i += 1
        return float(value)


class Loss(ABC):
    """Decides for each fragment whether it is lost."""

    @abstractmethod
    def lost(self, t: float) -> bool:
        """True if the next fragment, sent at simulated time ``t``, is lost."""


class NoLoss(Loss):
    def lost(self, t: float) -> bool:
        return False


class BernoulliLoss(Loss):
    def __init__(self, rate: float, rng: np.random.Generator):
        self.rate = rate
        self._u = UniformStream(rng)

    def lost(self, t: float) -> bool:
        return self._u.next() < self.rate


class TraceLoss(Loss):
    """Independent loss with the rate of the trace's row in effect at ``t``; one draw
    per fragment, also where the rate is 0, so the draws do not shift with the trace."""

    def __init__(self, trace: LinkTrace, rng: np.random.Generator):
        self.trace = trace
        self._u = UniformStream(rng)

    def lost(self, t: float) -> bool:
        return self._u.next() < self.trace.loss[self.trace.row(t)]


class GilbertElliottLoss(Loss):
    def __init__(
        self,
        p_good_to_bad: float,
        p_bad_to_good: float,
        loss_good: float,
        loss_bad: float,
        rng: np.random.Generator,
        start_bad: bool = False,
    ):
        self.p_gb, self.p_bg = p_good_to_bad, p_bad_to_good
        self.loss_good, self.loss_bad = loss_good, loss_bad
        self.bad = start_bad
        self._u = UniformStream(rng)

    def lost(self, t: float) -> bool:
        u = self._u.next()
        self.bad = (u >= self.p_bg) if self.bad else (u < self.p_gb)
        p = self.loss_bad if self.bad else self.loss_good
        if p <= 0.0:
            return False
        if p >= 1.0:
            return True
        return self._u.next() < p


def make_loss(cfg: LossConfig, rng: np.random.Generator, trace: LinkTrace | None = None) -> Loss:
    """The loss of a link: its trace's if it follows one (``cfg`` is then ignored), else ``cfg``'s."""
    if trace is not None:
        return TraceLoss(trace, rng)
    if cfg.model == LossModel.NONE or cfg.stationary_loss_rate() == 0.0:
        return NoLoss()
    if cfg.model == LossModel.BERNOULLI:
        return BernoulliLoss(cfg.rate, rng)
    return GilbertElliottLoss(*cfg.gilbert_elliott(), rng=rng)
