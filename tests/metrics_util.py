"""Helpers for tests that compare whole ``metrics.json`` dicts."""


def without_timings(value):
    """``value`` less everything that measures wall time (``runtime``, ``*wall*``, ``*_ms``): what must be the same
    in two runs of one scenario and seed, threaded or inline."""
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k != "runtime" and "wall" not in k and not k.endswith("_ms")}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value
