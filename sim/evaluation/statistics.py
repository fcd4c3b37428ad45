"""Summary statistics of an error series: one vocabulary for every section of ``metrics.json``.

After evo's ``evo.core.metrics``: a statistic is a member of :class:`StatisticsType`, whose
value is its key in ``metrics.json``, and :func:`statistics` computes a chosen set of them
in the order given (each section keeps its own set: ``trajectory.ERROR_STATISTICS``,
``online_slam.BELIEF_STATISTICS``, ``loop_closures.ERROR_STATISTICS``). ``rmse`` is
computed as evo computes it, so the trajectory errors equal evo's own statistics.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from enum import StrEnum

import numpy as np


class StatisticsType(StrEnum):
    RMSE = "rmse"
    MEAN = "mean"
    MEDIAN = "median"
    MIN = "min"
    P90 = "p90"  # 90th percentile (numpy's linear interpolation)
    MAX = "max"
    FINAL = "final"  # the last value of a series in time order


def get_statistic(values: np.ndarray, statistic: StatisticsType) -> float:
    """One statistic of a non-empty series."""
    match statistic:
        case StatisticsType.RMSE:
            return math.sqrt(np.mean(np.power(values, 2)))  # as evo.core.metrics.PE.get_statistic
        case StatisticsType.MEAN:
            return float(np.mean(values))
        case StatisticsType.MEDIAN:
            return float(np.median(values))
        case StatisticsType.MIN:
            return float(np.min(values))
        case StatisticsType.P90:
            return float(np.percentile(values, 90))
        case StatisticsType.MAX:
            return float(np.max(values))
        case StatisticsType.FINAL:
            return float(values[-1])
    raise ValueError(f"unsupported statistic {statistic!r}")


def statistics(values, types: Iterable[StatisticsType]) -> dict[str, float]:
    """``{statistic: value}`` of ``values`` for each of ``types``, in that order; empty
    when there are no values."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return {}
    return {str(s): get_statistic(values, s) for s in types}
