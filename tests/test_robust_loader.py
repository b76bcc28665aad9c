"""Property test: the loaders fed random malformed files either return data that
satisfy their invariants or raise a ``ValueError`` that names the file; never another exception,
never silently altered data. Files are built from fragments of what real exports contain
(headers, column names, WebPlotDigitizer layouts, decimal commas, delimiters, blank cells, NaN,
huge numbers, BOMs, CR/CRLF line ends) mixed with junk and random bytes."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.data.loaders import load_front_history, load_profile
from calibration.data.parse import UNITS

HEADERS = ["# time_s: 0.5", "# units: m", "# units: mm", "# experiment: lab", "# synthetic: true",
           "# source: a paper", "# free comment", "#"]
BAD_HEADERS = ["# time_s: nan", "# time_s: \"soon\"", "# time_s: 1e400", "# units: inch", "# synthetic: maybe"]
COLUMNS = [None, None, "x_m,h_m", "x_mm,h_mm", "x,h", "X,Y", "t_s,xf_m", "t_ms,xf_cm"]
BAD_COLUMNS = ["x_m,h_cm", "a,b,c", "Dataset 1,,Dataset 2,", "\"x_m\",\"h_m\"", "x_m h_m", "x;h"]
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64).map(repr),
    st.floats(-1e3, 1e3).map(lambda v: f"{v:.6g}"),
    st.sampled_from(["nan", "NaN", "inf", "-inf", "1e400", "-0", "0x10", "1,5", "1.5.2", "", " ", "\"3\"", "abc",
                     "1e-320", "\u0663"]),
)
MUTATIONS = ("junk row", "bad cell", "swap rows", "repeat row", "negative h", "tiny negative h", "bad header",
             "repeat header", "bad columns", "drop line", "blank line", "extra cell", "truncate", "random bytes",
             "latin-1")


@st.composite
def files(draw) -> bytes:
    """A valid profile or front file (project CSV or WebPlotDigitizer export) with 0-3 mutations."""
    n = draw(st.integers(3, 9))
    x = np.cumsum(draw(st.lists(st.floats(1e-4, 10.0), min_size=n, max_size=n)))
    h = draw(st.lists(st.floats(0.0, 100.0), min_size=n, max_size=n))
    delimiter = draw(st.sampled_from([",", ";", "\t"]))
    lines = draw(st.lists(st.sampled_from(HEADERS), unique=True, max_size=3))
    columns = draw(st.sampled_from(COLUMNS))
    if columns:
        lines.append(columns.replace(",", delimiter))
    first = len(lines)
    lines += [f"{a:.6g}{delimiter}{b:.6g}" for a, b in zip(x, h)]
    tail = b""
    for mutation in draw(st.lists(st.sampled_from(MUTATIONS), max_size=3)):
        k = draw(st.integers(first, len(lines) - 1)) if len(lines) > first else len(lines)
        if mutation == "junk row":
            lines.insert(k, draw(st.sampled_from([",", ";", " "])).join(draw(st.lists(NUMBERS, max_size=4))))
        elif mutation == "bad cell" and k < len(lines):
            cells = lines[k].split(delimiter)
            cells[draw(st.integers(0, len(cells) - 1))] = draw(NUMBERS)
            lines[k] = delimiter.join(cells)
        elif mutation == "swap rows" and len(lines) - first >= 2:
            j = draw(st.integers(first, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
        elif mutation == "repeat row" and k < len(lines):
            lines.insert(k, lines[k])
        elif mutation in ("negative h", "tiny negative h") and k < len(lines):
            cells = lines[k].split(delimiter)
            value = -1e-6 if mutation == "tiny negative h" else -draw(st.floats(1e-3, 50.0))
            lines[k] = delimiter.join(cells[:-1] + [f"{value:.6g}"])
        elif mutation == "bad header":
            lines.insert(0, draw(st.sampled_from(BAD_HEADERS)))
        elif mutation == "repeat header" and lines and lines[0].startswith("# "):
            lines.insert(1, lines[0])
        elif mutation == "bad columns":
            lines.insert(first, draw(st.sampled_from(BAD_COLUMNS)))
        elif mutation == "drop line" and lines:
            del lines[min(k, len(lines) - 1)]
        elif mutation == "blank line":
            lines.insert(k, "")
        elif mutation == "extra cell" and k < len(lines):
            lines[k] += delimiter + draw(NUMBERS)
        elif mutation == "truncate":
            lines = lines[: draw(st.integers(0, len(lines)))]
        elif mutation == "random bytes":
            tail = draw(st.binary(min_size=1, max_size=40))
        elif mutation == "latin-1":
            lines.insert(0, "# experiment: caf\u00e9")
            tail = b"\xe9"
    data = draw(st.sampled_from(["\n", "\r\n", "\r"])).join(lines).encode("utf-8") + tail
    return (b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + data


def check_error(err: ValueError, path) -> None:
    assert str(path) in str(err), f"the message does not name the file: {err}"


@pytest.mark.parametrize("data", [b"x_mm,h_mm\n1,0\n2,0\n3,4.94066e-324",  # the peak underflows in metres
                                  b"x_mm,h_mm\n1e-323,1\n1.5e-323,1\n3,1"])  # two x become one in metres
def test_a_profile_that_vanishes_in_metres_is_refused(tmp_path, data):
    path = tmp_path / "profile.csv"
    path.write_bytes(data)
    with pytest.raises(ValueError) as err:
        load_profile(path)
    check_error(err.value, path)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(data=files(), units=st.sampled_from([None, "m", "mm", "ft"]), sort=st.booleans(), clip=st.booleans())
def test_load_profile_never_fails_silently(tmp_path_factory, data, units, sort, clip):
    path = tmp_path_factory.mktemp("malformed") / "profile.csv"
    path.write_bytes(data)
    try:
        p = load_profile(path, units=units, sort=sort, clip_noise=clip)
    except ValueError as err:
        check_error(err, path)
        return
    # What came back is a valid profile, in metres, from the file's own numbers.
    assert p.n >= 3 and p.x.shape == p.h.shape
    assert np.all(np.isfinite(p.x)) and np.all(np.isfinite(p.h))
    assert np.all(np.diff(p.x) > 0) and np.all(p.h >= 0) and p.h.max() > 0
    assert p.time_s is None or math.isfinite(p.time_s)
    if not clip:
        assert "clipped_noise_lines" not in p.meta
    assert units is None or units in UNITS


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(data=files(), units=st.sampled_from([None, "m", "cm"]), time_units=st.sampled_from([None, "s", "ms"]),
       sort=st.booleans())
def test_load_front_history_never_fails_silently(tmp_path_factory, data, units, time_units, sort):
    path = tmp_path_factory.mktemp("malformed") / "front.csv"
    path.write_bytes(data)
    try:
        f = load_front_history(path, units=units, time_units=time_units, sort=sort)
    except ValueError as err:
        check_error(err, path)
        return
    assert f.n >= 3 and np.all(np.isfinite(f.t)) and np.all(np.isfinite(f.x_front))
    assert np.all(np.diff(f.t) > 0)
