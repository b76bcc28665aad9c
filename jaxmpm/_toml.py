"""The text of an experiment file (``jaxmpm.experiment``): values with units and provenance read
from parsed TOML, the line a key stands on for the error messages, and values written back.

A number is a bare number in its SI unit, a string with its unit ("60 mm") or a table
``{value, unit, source, note, expression}``; ``Units`` names the units a key accepts. Every error
is an ``ExperimentError`` made by ``Where.error``: ``FILE:LINE: [section] key: what``.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
import types
from collections.abc import Mapping
from typing import Any, NamedTuple

from .params import LENGTH_UNITS, PURE_UNITS

__all__ = ["ANGLE", "LENGTH", "PURE", "SPEED", "TIME", "ExperimentError", "Table", "Units", "Where", "inline_table",
           "key_name", "number", "plain", "provenance", "read_section", "relative", "toml_entry", "toml_value"]


class ExperimentError(ValueError):
    """An experiment file that cannot be used: the message names the file, the line and the key."""


class Units(NamedTuple):
    """The unit names a number may be given in (name -> factor to SI) and the name of its SI
    unit, which a bare number is in; ``parameter``: a parameter's name the value may be instead
    (kept as that string: the value is the parameter's, e.g. a wall friction of "mu_w")."""

    table: Mapping[str, float]
    si: str
    parameter: str | None = None


LENGTH = Units(LENGTH_UNITS, "m")
TIME = Units(types.MappingProxyType({"s": 1.0, "ms": 1e-3}), "s")
SPEED = Units(types.MappingProxyType({"m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3}), "m/s")
ANGLE = Units(types.MappingProxyType({"deg": 1.0, "rad": 180.0 / math.pi}), "deg")
PURE = Units(PURE_UNITS, "-")


class Table(NamedTuple):
    """An inline table of numbers, ``key = { entry = number, ... }``: each entry's units (an
    entry may itself be a number with its unit or a ``{value, unit, source, note}`` table)."""

    entries: Mapping[str, Units]


@dataclasses.dataclass(frozen=True)
class Where:
    """A file's path and text, to name the line of a key in an error."""

    path: pathlib.Path | None
    text: str | None

    def error(self, section: str | None, key: str | None, what: str, index: int | None = None) -> ExperimentError:
        """``PATH:LINE: [section] key: what`` (the ``index``-th ``[[section]]`` when given)."""
        label = str(self.path) if self.path is not None else "<experiment>"
        line = _line_of(self.text, section, key, index) if self.text is not None else None
        place = f"{label}:{line}" if line else label
        name = key_name(section, key, index)
        return ExperimentError(f"{place}: {name}: {what}" if name else f"{place}: {what}")


def key_name(section, key, index=None) -> str:
    """``[section] key``, ``[[section]] #n key`` or the key alone."""
    if section is None:
        return key or ""
    head = f"[[{section}]] #{index + 1}" if index is not None else f"[{section}]"
    return f"{head} {key}" if key else head


_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")


def _line_of(text: str, section: str | None, key: str | None, index: int | None = None) -> int | None:
    """The 1-based line of ``key`` in ``[section]`` (the ``index``-th ``[[section]]``), or of the
    section's header when the key is not written there (a missing key); None if not found."""
    current, seen, header_line = None, -1, None
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.split("#", 1)[0]
        head = _HEADER.match(stripped)
        if head:
            current = head.group(1)
            if current == section:
                seen += 1
                if index is None or seen == index:
                    header_line = number
            continue
        match = _KEY.match(stripped)
        if match and match.group(1) == key and current == section and (index is None or seen == index):
            return number
    return header_line


def _split_unit(text: str) -> tuple[float, str] | None:
    match = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\s\d].*?)?\s*", text)
    if not match:
        return None
    return float(match.group(1)), (match.group(2) or "")


def provenance(value, where: Where, section, key, index=None) -> tuple[Any, dict, str | None]:
    """(the value, its provenance entries, its unit entry) of a plain value or of a
    ``{value, unit, source, note, expression}`` table."""
    meta: dict[str, str] = {}
    if not isinstance(value, dict):
        return value, meta, None
    unknown = sorted(set(value) - {"value", "unit", "source", "note", "expression"})
    if unknown:
        raise where.error(section, key, f"unknown entries {unknown}; a value table holds value, unit, source, "
                                        "note, expression", index)
    if "value" not in value:
        raise where.error(section, key, "a value table needs 'value'", index)
    for entry in ("source", "note", "expression"):
        if entry in value:
            if not isinstance(value[entry], str):
                raise where.error(section, key, f"'{entry}' must be text", index)
            meta[entry] = value[entry]
    unit = value.get("unit")
    if unit is not None and not isinstance(unit, str):
        raise where.error(section, key, f"'unit' must be text, got {unit!r}", index)
    return value["value"], meta, unit


def number(value, units: Units, where: Where, section, key, index=None) -> tuple[float, dict]:
    """(the value in SI units, its provenance entries) of a number, a "value unit" string or a
    ``{value, unit, source, note}`` table."""
    value, meta, unit = provenance(value, where, section, key, index)
    if units.parameter is not None and value == units.parameter:
        if unit is not None:
            raise where.error(section, key, f"the parameter {value!r} takes no unit, got unit = {unit!r}", index)
        return value, meta
    if isinstance(value, str):
        split = _split_unit(value)
        if split is None:
            named = f" or the parameter {units.parameter!r}" if units.parameter else ""
            raise where.error(section, key, f"expected a number or 'number unit'{named}, got {value!r}", index)
        if unit is not None and split[1]:
            raise where.error(section, key, f"the unit is given twice ({split[1]!r} and unit = {unit!r})", index)
        value, unit = split[0], (split[1] or unit)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise where.error(section, key, f"expected a number, got {value!r}", index)
    unit = "" if unit is None else unit.strip()
    if unit == "":  # a bare number is in SI units
        unit = units.si
    if unit not in units.table:
        accepted = ", ".join(repr(u) for u in units.table if u)
        raise where.error(section, key, f"unit {unit!r} is not one of {accepted}" if accepted
                          else f"takes no unit (a pure number), got {unit!r}", index)
    value = float(value) * units.table[unit]
    if not math.isfinite(value):
        raise where.error(section, key, f"must be finite, got {value}", index)
    if unit != units.si:
        meta["unit"] = unit
    return value, meta
class _Entry(NamedTuple):
    """A ``Where`` whose errors name the entry of an inline table: ``[section] key: entry: what``."""

    where: Where
    entry: str

    def error(self, section, key, what, index=None) -> ExperimentError:
        return self.where.error(section, key, f"{self.entry}: {what}", index)


def inline_table(value, kind: Table, where: Where, section, key, index=None) -> tuple[dict, dict]:
    """(entry -> value in SI units, entry -> provenance) of an inline table of numbers."""
    if not isinstance(value, dict):
        raise where.error(section, key, f"expected a table {{ {', '.join(e + ' = ...' for e in kind.entries)} }}, "
                                        f"got {value!r}", index)
    values, meta = {}, {}
    for entry, item in value.items():
        if entry not in kind.entries:
            raise where.error(section, key, f"unknown entry {entry!r}; {key} takes {', '.join(kind.entries)}", index)
        values[entry], meta[entry] = number(item, kind.entries[entry], _Entry(where, entry), section, key, index)
    return values, {k: v for k, v in meta.items() if v}


def plain(value, kind: str, where: Where, section, key, index=None):
    """A value of ``kind``: "str", "path", "int", "bool", "strings" (a list of names, or a
    comma-separated string) or "numbers" (a table of key = number)."""
    if kind == "str":
        if not isinstance(value, str):
            raise where.error(section, key, f"expected text, got {value!r}", index)
        return value
    if kind == "path":
        if not isinstance(value, str) or not value.strip():
            raise where.error(section, key, f"expected a file name, got {value!r}", index)
        return value
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.error(section, key, f"expected an integer, got {value!r}", index)
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise where.error(section, key, f"expected true or false, got {value!r}", index)
        return value
    if kind == "strings":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",")]
        if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
            raise where.error(section, key, f"expected a list of names, got {value!r}", index)
        return tuple(value)
    if kind == "numbers":
        if not isinstance(value, dict):
            raise where.error(section, key, f"expected a table of key = number, got {value!r}", index)
        out = {}
        for k, v in value.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise where.error(section, f"{key}.{k}", f"expected a finite number, got {v!r}", index)
            out[k] = float(v)
        return out
    raise AssertionError(kind)


def read_section(raw: dict, name: str, schema: Mapping[str, Any], where: Where, index=None,
                 takes: str | None = None) -> tuple[dict, dict]:
    """(values, provenance) of the section ``name``, every key in ``schema`` (key -> ``Units``
    or a ``plain`` kind) and of its kind; ``raw`` is the parsed file, or the table itself for
    the ``index``-th ``[[name]]``. ``takes``: what an unknown key's error lists (default: the
    schema's keys)."""
    table = raw if index is not None else raw.get(name, {})
    if not isinstance(table, dict):
        raise where.error(None, name, "must be a table ([" + name + "])")
    values, sources = {}, {}
    for key, value in table.items():
        if key not in schema:
            raise where.error(name, key, f"unknown key; [{name}] takes {takes or ', '.join(schema)}", index)
        kind = schema[key]
        if isinstance(kind, Units):
            values[key], meta = number(value, kind, where, name, key, index)
        elif isinstance(kind, Table):
            values[key], meta = inline_table(value, kind, where, name, key, index)
        elif kind == "numbers":
            values[key], meta = plain(value, kind, where, name, key, index), None
        else:
            value, meta, unit = provenance(value, where, name, key, index)
            if unit is not None:
                raise where.error(name, key, f"takes no unit, got unit = {unit!r}", index)
            values[key] = plain(value, kind, where, name, key, index)
        if meta:
            sources[f"{name}.{key}"] = meta
    return values, sources


# -- writing --------------------------------------------------------------------------------------------

def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {value!r} as TOML")


def _with_meta(value, meta: Mapping[str, str] | None):
    """``value``, or a ``{value, source, ...}`` table where it has a provenance (its value in SI
    units: the unit it was written in is kept as a note, not applied)."""
    if not meta:
        return value
    entries = {"value": value, **{k: v for k, v in meta.items() if k != "unit"}}
    if "unit" in meta:
        entries["note"] = (entries.get("note", "") + f" (given in {meta['unit']})").strip()
    return entries


def toml_entry(key: str, value, meta: Mapping[str, Any] | None) -> str:
    """``key = value``, as a ``{value, source, ...}`` table where the value has a provenance (its
    value in SI units: the unit it was written in is kept as a note, not applied). An inline
    table of numbers (a dict ``value``) takes its entries' provenance, entry -> meta."""
    if isinstance(value, dict):
        return f"{key} = {toml_value({k: _with_meta(v, (meta or {}).get(k)) for k, v in value.items()})}"
    return f"{key} = {toml_value(_with_meta(value, meta))}"


def relative(file: pathlib.Path, base: pathlib.Path | None) -> str:
    """``file`` relative to the folder of the experiment file ``base`` where it lies inside it,
    else as an absolute path."""
    if base is not None:
        try:
            return str(file.relative_to(base.parent))
        except ValueError:
            pass
    return str(file.resolve())
