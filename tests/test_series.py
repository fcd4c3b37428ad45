"""The run's compact logs (sim/run/series.py) and memory trace (sim/run/memory.py)."""

import numpy as np
import pytest

from sim.run.memory import MemoryTrace
from sim.run.series import BINS_PER_DECADE, LogHistogram, Rows


def test_rows_grow_past_their_capacity_and_read_like_the_stacked_list():
    rows, plain = Rows(capacity=2), []
    rng = np.random.default_rng(3)
    for _ in range(37):
        row = rng.normal(size=(4, 4))
        rows.append(row)
        plain.append(row)
    assert len(rows) == 37 and bool(rows)
    np.testing.assert_array_equal(np.asarray(rows), np.stack(plain))
    np.testing.assert_array_equal(rows[-1], plain[-1])
    assert not Rows() and np.asarray(Rows()).size == 0
    times = Rows()
    for t in (0, 0.005, 0.01):  # SimPy's clock starts at the int 0: the rows stay floats
        times.append(t)
    np.testing.assert_array_equal(np.asarray(times), [0.0, 0.005, 0.01])


@pytest.mark.parametrize("sigma", [0.3, 1.0, 2.5])
def test_histogram_quantiles_are_within_a_bin_of_the_exact_ones(sigma):
    rng = np.random.default_rng(7)
    values = rng.lognormal(-3.0, sigma, 50_000)
    hist = LogHistogram(1e-5, 100.0)
    for chunk in np.array_split(values, 13):  # as image after image
        hist.add(chunk)
    ratio = 10 ** (1 / BINS_PER_DECADE)
    for q in (0.05, 0.5, 0.95):
        exact = np.quantile(values, q)
        assert exact / ratio <= hist.quantile(q) <= exact * ratio, q
    assert hist.n == values.size
    merged = LogHistogram.merged([hist, hist])
    assert merged.n == 2 * values.size and merged.quantile(0.5) == pytest.approx(hist.quantile(0.5))
    assert LogHistogram(1e-5, 1.0).quantile(0.5) is None


def test_memory_trace_samples_on_its_period_and_fits_the_late_growth():
    trace = MemoryTrace(every_s=10.0)
    for t in np.arange(0.0, 100.0, 0.5):
        trace.poll(float(t))
    assert [t for t, _ in trace.samples] == list(np.arange(0.0, 100.0, 10.0))
    trace.samples = [(t, 500.0 + 0.1 * t) for t in range(0, 400, 10)]  # 0.1 MB per simulated second
    report = trace.metrics()
    assert report["growth_mb_per_h"] == pytest.approx(360.0) and report["peak_rss_mb"] == pytest.approx(539.0)
