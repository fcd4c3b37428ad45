"""The scenario reference, generated from the schema (:class:`sim.scenario.Scenario` and the
``comms`` section's :class:`comms.CommsConfig`): ``docs/scenario.md``, every key in tables
per section, and ``assets/scenario.schema.json``, the JSON Schema that editors read through
the ``# yaml-language-server: $schema=...`` first line of the scenario files::

    python -m sim.tools.scenario_reference           # write both files
    python -m sim.tools.scenario_reference --check   # exit 1 if the committed files differ

A key's text is its field's ``description``: change it there and regenerate.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim.scenario import FAULT_SHORT_KEYS, Scenario

ROOT = Path(__file__).resolve().parents[2]
MARKDOWN = Path("docs/scenario.md")
JSON_SCHEMA = Path("assets/scenario.schema.json")
COMMAND = "python -m sim.tools.scenario_reference"
#: The dialect of pydantic's schema (``prefixItems`` for tuples), stated for the editors.
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

INTRO = f"""\
# Scenario reference

<!-- Generated from the schema by `{COMMAND}`: do not edit. -->

Every key of a scenario YAML file, section by section, in the order of the schema.
This file is generated from the schema (`sim/scenario.py`, and `comms/config.py` for
the `comms` section): to change a text, change the field's `description` there and run
`{COMMAND}`; with `--check` it exits 1 while this file or the JSON
schema is out of date. `marsyard validate FILE` checks a scenario, `--show` prints it
with every default filled in.

The same schema is in [`assets/scenario.schema.json`](../assets/scenario.schema.json)
(JSON Schema): an editor with the YAML language server (e.g. VS Code's YAML extension)
completes and checks the keys of a file whose first line is
`# yaml-language-server: $schema=../assets/scenario.schema.json` (the path relative to
the file), as in `scenarios/*.yaml`.

Columns: **key** is the dotted path, as `--set key=value` takes it; `*` stands for
every item of a list (or one item, by index or by `name`), `<key>` for a key of a map.
**default** is what a key left out means, written as YAML (`required`: it has none;
`see below`: a section with its own table). Unknown keys, `NaN`, infinities and
numbers of the wrong type are errors. Two keys fill in more than their defaults:
`comms.preset` merges its channel under the `comms` section ([comms.md](comms.md)),
and `realism.profile` sets every `realism` key left out or `null` ([realism.md](realism.md)).
"""


# --------------------------------------------------------------------------- JSON schema


def schema() -> dict[str, Any]:
    """The scenario's JSON Schema (validation mode), with its dialect."""
    return {"$schema": SCHEMA_DIALECT, **Scenario.model_json_schema(mode="validation")}


def editor_schema() -> dict[str, Any]:
    """:func:`schema` that also takes the short forms the scenario's ``mode="before"``
    validators accept and pydantic's schema cannot know: a waypoint as ``[x, y]`` or
    ``[x, y, altitude_m]`` (``RouteConfig._short_form``), and a fault's ``kind``,
    ``at_s`` and ``robot`` (``Scenario._fault_short_forms``). Without them an editor would
    flag the waypoints of every shipped scenario."""
    out = schema()
    defs = out["$defs"]
    waypoints = defs["RouteConfig"]["properties"]["waypoints"]
    altitude = next(m for m in defs["WaypointConfig"]["properties"]["altitude_m"]["anyOf"] if m.get("type") == "number")
    short = {
        "description": "short form: [x, y] or [x, y, altitude_m]",
        "type": "array",
        "prefixItems": [{"type": "number"}, {"type": "number"}, altitude],
        "minItems": 2,
        "maxItems": 3,
    }
    waypoints["items"] = {"anyOf": [waypoints["items"], short]}
    faults = out["properties"]["faults"]["items"]
    tag = faults["discriminator"]["propertyName"]
    for member in faults["oneOf"]:
        entry = defs[member["$ref"].rsplit("/", 1)[-1]]
        props = entry["properties"]
        for short_key, key in FAULT_SHORT_KEYS.items():
            props[short_key] = {k: v for k, v in props[key].items() if k not in ("default", "title")}
            props[short_key]["description"] = f"short form of `{key}`"
        props["robot"] = {"type": "string", "description": "short form of `robots: [robot]`"}
        entry["required"] = [k for k in entry["required"] if k != tag]
        entry["anyOf"] = [{"required": [tag]}, {"required": [k for k, v in FAULT_SHORT_KEYS.items() if v == tag]}]
    return out


def render_json_schema() -> str:
    return json.dumps(editor_schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


# --------------------------------------------------------------------------- markdown


@dataclass
class _Table:
    """One heading (markdown ``level``), the text under it and its rows (none: a heading
    only, over the tables of a typed list's members)."""

    level: int
    heading: str
    text: str
    rows: list[tuple[str, str, str, str, str]] = field(default_factory=list)


class _Walker:
    """Walks the JSON schema depth first, in the order of the schema's fields."""

    def __init__(self, root: dict[str, Any]):
        self.defs: dict[str, Any] = root.get("$defs", {})
        self.tables: list[_Table] = []
        self.seen: dict[str, str] = {}  # definition name -> path of its table

    def ref(self, node: dict[str, Any]) -> tuple[str | None, dict[str, Any]]:
        if "$ref" in node:
            name = node["$ref"].rsplit("/", 1)[-1]
            return name, self.defs[name]
        return None, node

    def section(self, node: dict[str, Any]) -> tuple[str | None, dict[str, Any]] | None:
        """The section (object with properties) ``node`` holds, through a ref or ``X | null``."""
        for member in node.get("anyOf", [node]):
            name, target = self.ref(member)
            if target.get("type") == "object" and "properties" in target:
                return name, target
        return None

    def type_of(self, node: dict[str, Any], plural: bool = False) -> str:
        if "anyOf" in node:
            return " or ".join(self.type_of(m, plural) for m in node["anyOf"])
        if "oneOf" in node:
            return "typed entries" if plural else "typed entry"
        _, target = self.ref(node)
        kind = target.get("type")
        if kind == "object" and "properties" in target:
            return "sections" if plural else "section"
        if kind == "object":
            return f"map of {self.type_of(target.get('additionalProperties', {}), plural=True)}"
        if kind == "array" and "prefixItems" in target:
            return "[" + ", ".join(self.type_of(m) for m in target["prefixItems"]) + "]"
        if kind == "array":
            return f"list of {self.type_of(target.get('items', {}), plural=True)}"
        return {"number": "float", "integer": "int", "boolean": "bool", "string": "string", "null": "null"}.get(kind, "any")

    def bounds(self, node: dict[str, Any]) -> list[str]:
        if "anyOf" in node:
            return [b for m in node["anyOf"] for b in self.bounds(m)]
        _, target = self.ref(node)
        out = []
        if "enum" in target:
            out.append(", ".join(f"`{_yaml(v)}`" for v in target["enum"]))
        if "const" in target:
            out.append(f"`{_yaml(target['const'])}`")
        for key, sign in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<")):
            if key in target:
                out.append(f"{sign} {_number(target[key])}")
        if "pattern" in target:
            out.append(f"pattern `{target['pattern']}`")
        if target.get("type") == "array" and "prefixItems" in target:
            parts = [", ".join(self.bounds(m)) for m in target["prefixItems"]]
            if len(set(parts)) == 1 and parts[0]:
                out.append(f"each {parts[0]}")
            elif any(parts):
                out.append("[" + "; ".join(p or "any" for p in parts) + "]")
        elif target.get("type") == "array":
            if "minItems" in target:
                out.append(f"at least {target['minItems']} item{'s' if target['minItems'] != 1 else ''}")
            items = target.get("items", {})
            inner = [] if "oneOf" in items or self.section(items) else self.bounds(items)
            if inner:
                out.append("each " + ", ".join(inner))
        return out

    def walk(self, path: str, text: str, node: dict[str, Any], heading: str | None = None, level: int = 2) -> None:
        """A table for the section ``node`` at ``path``, then the tables of its sub-sections
        (top-level sections at heading level 2, all deeper ones at 3)."""
        table = _Table(level, heading or f"`{path}`", text)
        self.tables.append(table)
        sub_level = 2 if not path else 3
        later: list[tuple[str, str, dict[str, Any] | None, str | None]] = []  # path, text, section, heading
        required = set(node.get("required", []))
        for key, prop in node["properties"].items():
            key_path = row_path = f"{path}.{key}" if path else key
            description = prop.get("description", "")
            sub = self.section(prop)
            _, target = self.ref(prop)
            items = target.get("items", {}) if target.get("type") == "array" else {}
            values = target.get("additionalProperties", {}) if target.get("type") == "object" else {}
            if "oneOf" in items:  # a typed list: a table per member, headed by its tag and docstring
                later.append((key_path, description + _short_forms(key_path), None, None))
                tag_key = items["discriminator"]["propertyName"]
                for member in items["oneOf"]:
                    _, entry = self.ref(member)
                    tag = entry["properties"][tag_key]["const"]
                    later.append((f"{key_path}.*", _docstring(entry.get("description", "")), entry, f"`{key_path}.*` with `{tag_key}: {tag}`"))
            elif sub is None and self.section(items) is not None:
                sub, key_path = self.section(items), f"{key_path}.*"
            elif sub is None and self.section(values) is not None:
                sub, key_path = self.section(values), f"{key_path}.<key>"
            if sub is not None:
                name, section = sub
                if name in self.seen:
                    description += f" (keys as in `{self.seen[name]}`)"
                else:
                    if name is not None:
                        self.seen[name] = key_path
                    later.append((key_path, description, section, None))
            if "default" not in prop or key in required:
                default = "required"
            elif isinstance(prop["default"], dict) and prop["default"] and sub is not None:
                default = "see below"
            else:
                default = f"`{_yaml(prop['default'])}`"
            bounds = "" if sub is not None else ", ".join(self.bounds(prop))
            table.rows.append((f"`{row_path}`", self.type_of(prop), default, bounds, _cell(description)))
        for sub_path, sub_text, section, sub_heading in later:
            if section is None:
                self.tables.append(_Table(sub_level, f"`{sub_path}`", sub_text))
            else:
                self.walk(sub_path, sub_text, section, sub_heading, 3 if sub_heading else sub_level)


def _short_forms(path: str) -> str:
    """What the scenario's validator accepts besides the keys of a typed list (``faults``)."""
    if path != "faults":
        return ""
    forms = [f"`{short}` for `{key}`" for short, key in FAULT_SHORT_KEYS.items()]
    return "; short forms: " + ", ".join([*forms, "`robot: NAME` for `robots: [NAME]`"])


def _docstring(text: str) -> str:
    """A model docstring as one markdown paragraph."""
    text = " ".join(text.split())
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


_PLAIN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_YAML_WORDS = {"null", "true", "false", "yes", "no", "on", "off", "y", "n", "~"}


def _yaml(value: Any) -> str:
    """``value`` as a user writes it in a scenario (flow style)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return value if _PLAIN.match(value) and value.lower() not in _YAML_WORDS else json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_yaml(k)}: {_yaml(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no YAML form for {value!r}")


def _cell(text: str) -> str:
    """Text for a table cell: ``|``, ``*`` and ``<`` escaped outside code spans."""
    parts = text.split("`")
    for i in range(0, len(parts), 2):
        parts[i] = parts[i].replace("|", "\\|").replace("*", "\\*").replace("<", "&lt;")
    return "`".join(parts)


def render_markdown() -> str:
    root = schema()
    walker = _Walker(root)
    walker.walk("", "", root, heading="Top level")
    blocks = [INTRO.rstrip("\n")]
    for table in walker.tables:
        blocks.append(f"{'#' * table.level} {table.heading}")
        blocks.append(_cell(table.text))
        if table.rows:
            rows = ["| key | type | default | bounds | description |", "|---|---|---|---|---|"]
            rows += ["| " + " | ".join(row) + " |" for row in table.rows]
            blocks.append("\n".join(rows))
    return "\n\n".join(block for block in blocks if block) + "\n"


# --------------------------------------------------------------------------- files


def outputs() -> dict[Path, str]:
    """What the generator writes, by path relative to the repository root."""
    return {MARKDOWN: render_markdown(), JSON_SCHEMA: render_json_schema()}


def stale(root: Path = ROOT) -> list[Path]:
    """The generated files under ``root`` that differ from what the generator writes now."""
    return [path for path, text in outputs().items() if not (root / path).is_file() or (root / path).read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the committed files differ from what would be written")
    args = parser.parse_args(argv)
    if args.check:
        paths = stale()
        for path in paths:
            print(f"{path} is out of date: run `{COMMAND}`", file=sys.stderr)
        return 1 if paths else 0
    for path, text in outputs().items():
        (ROOT / path).parent.mkdir(parents=True, exist_ok=True)
        (ROOT / path).write_text(text, encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
