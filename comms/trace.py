"""A link trace: measured (or made-up) latency, bandwidth and loss over time, from a CSV file.

The file has the header ``t_s,latency_s,bandwidth_bps,loss`` (these four columns in any
order, no others) and one row per change. A row holds from its ``t_s`` until the next
row's; the last row holds to the end of the run (a trace does not loop). ``t_s`` starts
at 0 and strictly increases; every value is a finite number; ``latency_s`` in
[0, 3600], ``bandwidth_bps`` in [1, 1e12] (the bounds of the link keys of the same
names) and ``0 <= loss < 1``. Blank lines are skipped.

A link that follows a trace takes the row in effect when a fragment starts to serialize
for that whole fragment: its serialization time (``bandwidth_bps``), its propagation
delay (``latency_s``, plus the link's jitter) and its loss probability (``loss``).

In a scenario, ``trace:`` names the file; a relative path is taken from the scenario
file's folder (the ``base_dir`` of the validation context, else the current
directory). The field holds the parsed :class:`LinkTrace` and dumps as its absolute path,
so a dumped scenario loads again from anywhere.
"""

from __future__ import annotations

import bisect
import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pydantic import PlainSerializer, PlainValidator, ValidationInfo, WithJsonSchema

COLUMNS = ("t_s", "latency_s", "bandwidth_bps", "loss")
MAX_ROWS = 100_000  # a row costs about 130 bytes in memory
MAX_BYTES = 16_000_000  # checked before reading: room for MAX_ROWS rows of long numbers
_BOUNDS = {
    "latency_s": (0.0, 3600.0, "in [0, 3600] s, as the link's latency_s"),
    "bandwidth_bps": (1.0, 1e12, "in [1, 1e12] bit/s, as the link's bandwidth_bps"),
}


@dataclass(frozen=True)
class LinkTrace:
    """A parsed trace: ``path`` (absolute) and one tuple per column, row by row."""

    path: str
    t_s: tuple[float, ...]
    latency_s: tuple[float, ...]
    bandwidth_bps: tuple[float, ...]
    loss: tuple[float, ...]

    def row(self, t: float) -> int:
        """Index of the row in effect at simulated time ``t >= 0``."""
        return bisect.bisect_right(self.t_s, t) - 1

    def max_latency_s(self) -> float:
        return max(self.latency_s)

    def min_bandwidth_bps(self) -> float:
        return min(self.bandwidth_bps)


def load_trace(path: str | Path, base_dir: str | Path | None = None) -> LinkTrace:
    """Read and check a trace file; ``ValueError`` naming the file, line and column otherwise."""
    given = Path(path).expanduser()
    source = (given if given.is_absolute() else Path(base_dir or Path.cwd()) / given).resolve()
    if not source.is_file():
        where = "" if given.is_absolute() else f" (a relative path is taken from {Path(base_dir or Path.cwd()).resolve()})"
        raise ValueError(f"no trace file {source}{where}")
    size = source.stat().st_size
    if size > MAX_BYTES:
        raise ValueError(f"trace {source}: {size} bytes, at most {MAX_BYTES}")
    try:
        lines = source.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"trace {source}: cannot read it: {exc}") from None

    def fail(line: int, problem: str) -> ValueError:
        return ValueError(f"trace {source}, line {line}: {problem}")

    rows = [(n, r) for n, r in enumerate(csv.reader(lines), start=1) if any(cell.strip() for cell in r)]
    if not rows:
        raise ValueError(f"trace {source}: empty file; the first line must be the header {','.join(COLUMNS)}")
    header_line, header = rows[0]
    names = [cell.strip() for cell in header]
    unknown = [n for n in names if n not in COLUMNS]
    missing = [c for c in COLUMNS if c not in names]
    if unknown or missing or len(names) != len(COLUMNS):
        problems = [f"unknown column(s) {', '.join(map(repr, unknown))}" if unknown else "", f"missing {', '.join(missing)}" if missing else ""]
        problem = "; ".join(p for p in problems if p) or f"repeated columns in {names}"
        raise fail(header_line, f"header {','.join(names)}: {problem}; expected exactly the columns {','.join(COLUMNS)}")
    if len(rows) - 1 > MAX_ROWS:
        raise ValueError(f"trace {source}: {len(rows) - 1} rows, at most {MAX_ROWS} (memory and load time): thin it out")
    order = [names.index(c) for c in COLUMNS]
    columns: list[list[float]] = [[] for _ in COLUMNS]
    for n, cells in rows[1:]:
        if len(cells) != len(COLUMNS):
            raise fail(n, f"{len(cells)} values, expected {len(COLUMNS)} ({','.join(names)})")
        values = {}
        for name, i in zip(COLUMNS, order, strict=True):
            text = cells[i].strip()
            try:
                value = float(text)
            except ValueError:
                raise fail(n, f"{name} {text!r} is not a number") from None
            if not math.isfinite(value):
                raise fail(n, f"{name} is {text}, must be finite")
            values[name] = value
        t, loss = values["t_s"], values["loss"]
        if not columns[0] and t != 0.0:
            raise fail(n, f"t_s {t:g}: the first row must start at t_s 0")
        if columns[0] and not t > columns[0][-1]:
            raise fail(n, f"t_s {t:g} is not after the previous row's {columns[0][-1]:g}: t_s must strictly increase")
        for name, (low, high, allowed) in _BOUNDS.items():
            if not low <= values[name] <= high:
                raise fail(n, f"{name} {values[name]:g} out of range: {allowed}")
        if not 0.0 <= loss < 1.0:
            raise fail(n, f"loss {loss:g} out of range: 0 <= loss < 1 (a link that is down for a while is an outage, comms.outages)")
        for column, name in zip(columns, COLUMNS, strict=True):
            column.append(values[name])
    if not columns[0]:
        raise ValueError(f"trace {source}: a header and no rows; it needs at least one row, starting at t_s 0")
    return LinkTrace(str(source), *(tuple(c) for c in columns))


def _validate(value: Any, info: ValidationInfo) -> LinkTrace:
    if isinstance(value, LinkTrace):
        return value
    if not isinstance(value, str | Path) or not str(value).strip():
        raise ValueError("expected the path of a CSV trace file (t_s,latency_s,bandwidth_bps,loss)")
    context = info.context if isinstance(info.context, dict) else {}
    return load_trace(value, context.get("base_dir"))


#: The type of a ``trace:`` key: a path in YAML and in the JSON schema, a :class:`LinkTrace`
#: once validated, its absolute path when dumped.
TraceFile = Annotated[
    LinkTrace,
    PlainValidator(_validate),
    PlainSerializer(lambda trace: trace.path, return_type=str),
    WithJsonSchema({"type": "string"}),
]
