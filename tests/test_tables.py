"""jaxmpm.tables: the one CSV format (header lines, column names, rows), written and read back."""

import numpy as np
import pytest

from jaxmpm import io, tables


def test_layout_is_header_then_names_then_rows(tmp_path):
    path = tables.write_profile_csv(tmp_path / "p.csv", [0.0, 0.5], np.array([1.0, 0.0], np.float32),
                                    {"experiment": "e", "time_s": 0.5, "scene": {"L": 0.2, "n": np.arange(2)},
                                     "status": np.int32(0)})
    assert path == tmp_path / "p.csv"
    assert path.read_text() == ("# experiment: e\n# time_s: 0.5\n# scene: {\"L\": 0.2, \"n\": [0, 1]}\n# status: 0\n"
                                "x_m,h_m\n0.000000e+00,1.000000e+00\n5.000000e-01,0.000000e+00\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv"]  # no temporary file left behind
    assert io.write_profile_csv is tables.write_profile_csv and io.PROFILE_COLUMNS == ("x_m", "h_m")


def test_values_read_back_as_written(tmp_path):
    meta = {"note": "true", "digits": "12", "spaced": " padded ", "lines": "a\nb\rc", "plain": "caf\u00e9, ok",
            "empty": "", "nested": {"a": [1, 2.5, None]}, "flag": False, "nan_text": "NaN"}
    path = tables.write_table(tmp_path / "t.csv", {"a": [1.0, 2.0], "b_over_c": [3.0, 4.0]}, meta, fmt=".10g")
    table = tables.read_table(path)
    assert table.header == meta and table.header_line == {key: n for n, key in enumerate(meta, start=1)}
    assert table.rows == [(len(meta) + 1, ["a", "b_over_c"]), (len(meta) + 2, ["1", "3"]), (len(meta) + 3, ["2", "4"])]
    assert "# plain: caf\u00e9, ok\n" in path.read_text(encoding="utf-8")  # plain strings stay plain


def test_reader_takes_continuations_spreadsheet_delimiters_and_a_bom(tmp_path):
    path = tmp_path / "s.csv"
    path.write_bytes("\ufeff# source: a long\r\n#   citation\r\n# free comment\r\nx;h\r\n\"1,5\";2\r\n".encode())
    table = tables.read_table(path)
    assert table.header == {"source": "a long citation"} and table.header_line == {"source": 1}
    assert table.rows == [(4, ["x", "h"]), (5, ["1.5", "2"])] and table.file == str(path)


@pytest.mark.parametrize("meta, columns, message", [
    ({"a:b": 1}, {"x": [0.0]}, r"meta keys must be non-empty strings without ':' or newlines, got 'a:b'"),
    ({" a": 1}, {"x": [0.0]}, "meta keys"),
    ({}, {"x,y": [0.0]}, r"columns must be named by non-empty strings without ','"),
    ({}, {}, "columns must be named"),
    ({}, {"x": [0.0, 1.0], "h": [0.0]}, r"x and h must be 1-D of equal length, got \(2,\) and \(1,\)"),
    ({"o": object()}, {"x": [0.0]}, "object is not JSON serialisable"),
])
def test_writer_refuses_what_would_not_read_back(tmp_path, meta, columns, message):
    with pytest.raises((ValueError, TypeError), match=message):
        tables.write_table(tmp_path / "t.csv", columns, meta)
    assert list(tmp_path.iterdir()) == []


def test_writer_and_reader_name_the_path(tmp_path):
    with pytest.raises(ValueError, match=r"directory '.*nope' does not exist"):
        tables.write_table(tmp_path / "nope" / "t.csv", {"x": [0.0]}, {})
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match=r"directory '.*afile' is a file, not a directory"):
        tables.write_table(tmp_path / "afile" / "t.csv", {"x": [0.0]}, {})
    with pytest.raises(ValueError, match=r"missing\.csv: no such file"):
        tables.read_table(tmp_path / "missing.csv")
    (tmp_path / "twice.csv").write_text("# a: 1\n# a: 2\nx\n1\n")
    with pytest.raises(ValueError, match=r"twice\.csv: line 2: header key 'a' repeats line 1"):
        tables.read_table(tmp_path / "twice.csv")
