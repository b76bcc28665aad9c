"""The project's one CSV format: header lines, a row of column names, rows of numbers.

A deposit profile as ``python -m jaxmpm run ... --profile-csv`` writes it::

    # experiment: cohesive-collapse (synthetic, jaxmpm 0.1.0)
    # time_s: 0.5
    # units: m
    # source: python -m jaxmpm run cohesive-collapse --set beta=0.25 ...
    # parameters: {"beta": 0.25, ...}
    x_m,h_m
    -6.955788e-03,3.189269e-04
    ...

Every table of the project has this shape; only the column names differ: a deposit profile
``x_m,h_m`` (``PROFILE_COLUMNS``), a front history ``t_s,xf_m`` (``FRONT_COLUMNS``), a scaling
law ``a,dL_over_L0[,Hf_over_L0]``, the Bagnold table ``slope_deg,z_m,v_m_per_s``.

Header: a comment line ``# key: value`` sets ``key``; the value is JSON-decoded where it parses
as JSON and kept as a string otherwise. A comment line indented by two or more blanks after the
``#``, right below a key line, continues that key's value (joined with a blank), so a long
citation may span lines. A comment line without ``key:`` is a free comment. A key may appear once.

``write_table`` writes that layout (UTF-8, under a temporary name moved onto the path once
complete), encoding each value so that ``read_table`` decodes it back: a string that would read
back as something else (``"12"``, ``"true"``, `` padded ``, a line break) is written as a JSON
string. ``read_table`` returns the header and the rows as cells of text with their line numbers;
what the columns mean (units, checks, WebPlotDigitizer exports) is the caller's:
``calibration.data`` builds its profiles, front histories and scaling laws on it. The reader also
takes what a spreadsheet saves: ``;``, tab or blanks as delimiter (``;`` and tab rows may use a
decimal comma), cells in double quotes, Windows line endings and a UTF-8 byte-order mark.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
import uuid
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["FRONT_COLUMNS", "PROFILE_COLUMNS", "Table", "read_columns", "read_table", "write_profile_csv",
           "write_table"]

#: Columns of a deposit profile h(x), both in metres.
PROFILE_COLUMNS = ("x_m", "h_m")
#: Columns of a front history x_front(t): seconds and metres.
FRONT_COLUMNS = ("t_s", "xf_m")
#: A header comment indented by this much after "#" continues the value of the key line above it.
_CONTINUATION = "  "
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")


# ---- writing -------------------------------------------------------------------------------------
def _json_default(obj):
    if hasattr(obj, "__array__"):  # numpy and JAX arrays and scalars
        return np.asarray(obj).tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _breaks_line(text: str) -> bool:
    return "".join(text.splitlines()) != text


def _decode(value: str):
    try:
        return json.loads(value)
    except ValueError:
        return value


def _header_line(key, value) -> str:
    """``# key: value`` such that ``read_table`` decodes ``value`` back."""
    if not isinstance(key, str) or not key.strip() or ":" in key or _breaks_line(key) or key != key.strip():
        raise ValueError(f"meta keys must be non-empty strings without ':' or newlines, got {key!r}")
    if not isinstance(value, str):
        text = json.dumps(value, default=_json_default)
    elif _decode(value) != value or _breaks_line(value) or value != value.strip():
        text = json.dumps(value)
    else:
        text = value
    return f"# {key}: {text}"


def write_table(path: str | os.PathLike, columns: Mapping[str, Any], meta: Mapping[str, Any],
                fmt: str = ".6e") -> pathlib.Path:
    """Write ``columns`` (name -> 1-D array, all of one length) under the header ``meta`` (key ->
    value: a string, or anything JSON holds, numpy and JAX arrays included), each number printed
    with the format spec ``fmt``. The file appears at ``path`` only once complete (atomic)."""
    path = pathlib.Path(path)
    lines = [_header_line(key, value) for key, value in meta.items()]
    names = list(columns)
    if not names or any(not isinstance(n, str) or not n or "," in n or _breaks_line(n) or n != n.strip()
                        for n in names):
        raise ValueError(f"columns must be named by non-empty strings without ',' or newlines, got {names}")
    values = [np.asarray(columns[n], float) for n in names]
    if any(v.ndim != 1 or v.shape != values[0].shape for v in values):
        shapes = " and ".join(str(v.shape) for v in values)
        raise ValueError(f"{' and '.join(names)} must be 1-D of equal length, got {shapes}")
    if not path.parent.is_dir():
        what = "is a file, not a directory" if path.parent.exists() else "does not exist"
        raise ValueError(f"path: directory {str(path.parent)!r} {what}")
    lines.append(",".join(names))
    lines += [",".join(format(v, fmt) for v in row) for row in zip(*values)]
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_profile_csv(path: str | os.PathLike, x, h, meta: Mapping[str, Any]) -> pathlib.Path:
    """Write a deposit profile h(x) (metres, columns ``x_m,h_m``) under the header ``meta``, atomically."""
    return write_table(path, dict(zip(PROFILE_COLUMNS, (x, h))), meta)


# ---- reading -------------------------------------------------------------------------------------
@dataclasses.dataclass
class Table:
    """A file of this format as read: its header and its rows of cells.

    ``header`` maps each key to its decoded value and ``header_line`` to its 1-based line number;
    ``rows`` holds ``(line number, cells)`` for every line that is neither blank nor a comment,
    the row of column names included (the first row, where the file has one), each cell stripped
    of blanks and enclosing double quotes. ``file`` is the path as the error messages name it.
    """

    file: str
    header: dict[str, Any]
    header_line: dict[str, int]
    rows: list[tuple[int, list[str]]]


def _split(line: str, delimiter: str | None) -> list[str]:
    cells = line.split(delimiter) if delimiter else line.split()
    out = []
    for cell in cells:
        cell = cell.strip()
        if len(cell) >= 2 and cell[0] == cell[-1] == '"':
            cell = cell[1:-1].strip()
        if delimiter in (";", "\t") and _DECIMAL_COMMA.match(cell):
            cell = cell.replace(",", ".")
        out.append(cell)
    return out


def read_table(path: str | os.PathLike) -> Table:
    """Read a file of this format (module docstring) into a ``Table``. The delimiter is the first
    of ``;``, tab and ``,`` that the first row holds (blanks when it holds none). Raises
    ``ValueError`` naming the file when it does not exist, is not UTF-8 text, or repeats a key."""
    path = pathlib.Path(path)
    file = str(path)
    if not path.is_file():
        raise ValueError(f"{file}: no such file")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"{file}: not a UTF-8 text file ({err})") from None
    raw: dict[str, str] = {}
    header_line: dict[str, int] = {}
    content: list[tuple[int, str]] = []
    last_key = None  # the key a continuation line would continue
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped:
            last_key = None
            continue
        if stripped.startswith("#"):
            body = stripped[1:]
            if last_key is not None and body.startswith(_CONTINUATION) and body.strip():
                raw[last_key] += " " + body.strip()  # an indented line continues the key above
                continue
            key, sep, value = body.partition(":")
            key = key.strip()
            if not sep or not key:
                last_key = None
                continue  # a free comment
            if key in raw:
                raise ValueError(f"{file}: line {number}: header key {key!r} repeats line {header_line[key]}")
            raw[key] = value.strip()
            header_line[key] = number
            last_key = key
            continue
        last_key = None
        content.append((number, stripped))
    header = {key: _decode(value) for key, value in raw.items()}
    delimiter = None
    if content:
        first = content[0][1]
        delimiter = next((d for d in (";", "\t", ",") if d in first), None)
    rows = [(number, _split(line, delimiter)) for number, line in content]
    return Table(file, header, header_line, rows)


# ---- numeric columns -----------------------------------------------------------------------------
def is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def trim_cells(cells: list[str]) -> list[str]:
    """Drop trailing empty cells (a trailing delimiter)."""
    cells = list(cells)
    while cells and cells[-1] == "":
        cells.pop()
    return cells


def numeric_rows(parsed: Table, rows, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Rows of cells as a float array (n, len(names)) and their line numbers; checks each cell
    (count, number, finite) and names the file, line and column of the first bad one."""
    values = np.empty((len(rows), len(names)))
    lines = np.empty(len(rows), dtype=int)
    for i, (number, cells) in enumerate(rows):
        if len(cells) != len(names):
            raise ValueError(f"{parsed.file}: line {number}: expected {len(names)} columns "
                             f"({','.join(names)}), got {len(cells)}")
        for j, cell in enumerate(cells):
            try:
                value = float(cell)
            except ValueError:
                raise ValueError(f"{parsed.file}: line {number}: column {j + 1} ({names[j]}) is not a number: "
                                 f"{cell!r}") from None
            if not np.isfinite(value):
                raise ValueError(f"{parsed.file}: line {number}: column {j + 1} ({names[j]}) is not finite: "
                                 f"{cell!r}")
            values[i, j] = value
        lines[i] = number
    return values, lines


def read_columns(path: str | os.PathLike,
                 required: tuple[str, ...] = ()) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A file of this format with a row of column names: ``(header, columns)``, the header
    decoded and each column a float64 array (every cell checked). ``required`` names columns
    the file must have."""
    parsed = read_table(path)
    number, first = parsed.rows[0] if parsed.rows else (0, [])
    names = tuple(trim_cells(first))
    if not names or any(is_number(c) for c in names) or len(set(names)) != len(names):
        raise ValueError(f"{parsed.file}: line {number}: expected a row of distinct column names, got {list(names)}")
    missing = [c for c in required if c not in names]
    if missing:
        raise ValueError(f"{parsed.file}: line {number}: missing column(s) {missing}; the file has {list(names)}")
    values, _ = numeric_rows(parsed, [(n, trim_cells(c)) for n, c in parsed.rows[1:]], names)
    return dict(parsed.header), {name: values[:, j].copy() for j, name in enumerate(names)}
