"""jaxslam.data.textfile: the numeric table reader and its file:line errors."""

import gzip
import pickle

import numpy as np
import pytest

from jaxslam.data.textfile import (DataFormatError, MissingDataError, TruncatedLineWarning, int_column,
                                   read_table, resolve_dataset_dir)
from jaxslam.errors import InputError


def _write(p, text, gz=False):
    data = text.encode()
    p.write_bytes(gzip.compress(data) if gz else data)
    return p


def test_whitespace_tabs_crlf_trailing_tab_and_comments(tmp_path):
    p = _write(tmp_path / "a.txt", "# header\n# more\n 1.0\t 2.0 \t3e0\t\r\n\n4 5 6\r\n# mid comment\n7\t8\t9\n")
    t = read_table(p, 3, time_cols=0)
    np.testing.assert_array_equal(t.data, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    np.testing.assert_array_equal(t.lines, [3, 5, 7])
    assert t.path == str(p)
    assert t.where(1) == f"{p}:5"


def test_csv_header_checked_and_gzip(tmp_path):
    p = _write(tmp_path / "s.csv.gz", "t,a,b\n0.5,1,2\n0.5,3,4\n", gz=True)
    t = read_table(p, 3, delimiter=",", header_rows=1, header=("t", "a", "b"), time_cols=0)
    np.testing.assert_array_equal(t.data, [[0.5, 1, 2], [0.5, 3, 4]])  # equal times allowed
    np.testing.assert_array_equal(t.lines, [2, 3])
    with pytest.raises(DataFormatError, match=r"s\.csv\.gz:1: expected header 't,b,a'"):
        read_table(p, 3, delimiter=",", header_rows=1, header=("t", "b", "a"))


def test_trailing_comma_is_not_a_column(tmp_path):
    p = _write(tmp_path / "c.csv", "1,2,\n3,4,\n")
    np.testing.assert_array_equal(read_table(p, 2, delimiter=",").data, [[1, 2], [3, 4]])


@pytest.mark.parametrize("text, line, pattern", [
    ("1 2 3\n4 5\n7 8 9\n", 2, "expected 3 columns, got 2$"),
    ("1 2 3\n4 5 6 7\n", 2, "expected 3 columns, got 4"),
    ("1 2 3\n4 x5 6\n", 2, "non-numeric field 'x5' in column 2"),
    ("1 2 3\n4 5 6\n7 8", 3, r"expected 3 columns, got 2 \(truncated line"),
    ("# h\n1 2 3\n4 nan 6\n", 3, "non-finite value nan in column 2"),
    ("1 2 3\n4 5 inf\n", 2, "non-finite value inf in column 3"),
    ("1 2 3\n2 5 6\n1.5 8 9\n", 3, r"time goes backwards in column 1: 1\.5 after 2\.0 \(line 2\)"),
])
def test_errors_name_file_and_line(tmp_path, text, line, pattern):
    p = _write(tmp_path / "bad.dat", text)
    with pytest.raises(DataFormatError, match=pattern) as ei:
        read_table(p, 3, time_cols=0)
    e = ei.value
    assert e.line == line and e.path == str(p)
    assert str(e).startswith(f"{p}:{line}: ")
    assert isinstance(e, InputError) and isinstance(e, ValueError)


@pytest.mark.parametrize("gz", [False, True])
def test_a_last_line_without_line_end_is_read_with_a_warning(tmp_path, gz):
    # "7 8 9.25" cut to "7 8 9.2": still three numbers, so only the missing line end can tell
    p = _write(tmp_path / ("cut.dat.gz" if gz else "cut.dat"), "# t a b\n1 2 3\n4 5 6\n7 8 9.2", gz=gz)
    with pytest.warns(TruncatedLineWarning) as rec:
        t = read_table(p, 3, time_cols=0)
    assert len(rec) == 1 and str(rec[0].message).startswith(f"jaxslam: {p}:4: the last line has no line end")
    np.testing.assert_array_equal(t.data[-1], [7, 8, 9.2])  # read as it stands, nothing dropped
    # a file that ends with its line end, or whose unterminated last line is a comment: no warning
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_table(_write(tmp_path / "ok.dat", "1 2 3\n4 5 6\r\n"), 3)
        read_table(_write(tmp_path / "c.dat", "1 2 3\n4 5 6\n# end"), 3)


def test_non_finite_allowed_where_asked(tmp_path):
    p = _write(tmp_path / "n.dat", "1 nan\n2 3\n")
    assert np.isnan(read_table(p, 2, finite=False).data[0, 1])
    assert np.isnan(read_table(p, 2, finite=[0]).data[0, 1])
    with pytest.raises(DataFormatError, match=":1: non-finite"):
        read_table(p, 2, finite=[1])


def test_second_time_column_checked(tmp_path):
    p = _write(tmp_path / "t.csv", "0,1,0\n1,2,0.5\n2,3,0.4\n")
    read_table(p, 3, delimiter=",", time_cols=0)
    with pytest.raises(DataFormatError, match=r"t\.csv:3: time goes backwards in column 3"):
        read_table(p, 3, delimiter=",", time_cols=(0, 2))


def test_empty_missing_and_corrupt_gzip(tmp_path):
    p = _write(tmp_path / "e.dat", "# only a header\n")
    with pytest.raises(DataFormatError, match="no data rows"):
        read_table(p, 2)
    assert read_table(p, 2, allow_empty=True).data.shape == (0, 2)
    with pytest.raises(MissingDataError, match="nope.dat: file not found") as ei:
        read_table(tmp_path / "nope.dat", 2)
    assert isinstance(ei.value, FileNotFoundError) and isinstance(ei.value, DataFormatError)
    assert ei.value.line is None
    g = tmp_path / "cut.csv.gz"
    g.write_bytes(gzip.compress(b"1,2\n" * 1000)[:40])
    with pytest.raises(DataFormatError, match="corrupt or truncated gzip"):
        read_table(g, 2, delimiter=",")


def test_int_column_and_pickling(tmp_path):
    p = _write(tmp_path / "i.dat", "2.0000000000000000e+000 1\n3 1.5\n")
    t = read_table(p, 2)
    np.testing.assert_array_equal(int_column(t, 0, "id"), [2, 3])
    with pytest.raises(DataFormatError, match=r"i\.dat:2: ok \(column 2\): expected an integer, got 1\.5"):
        int_column(t, 1, "ok")
    with pytest.raises(DataFormatError, match=r"i\.dat:2: id \(column 1\): expected an integer in \[0, 2\]"):
        int_column(t, 0, "id", lo=0, hi=2)
    e = pickle.loads(pickle.dumps(DataFormatError("f.dat", 7, "boom")))
    assert str(e) == "f.dat:7: boom" and e.line == 7


def test_resolve_dataset_dir(tmp_path):
    (tmp_path / "ds").mkdir()
    for f in ("a.dat", "b.dat"):
        (tmp_path / "ds" / f).write_text("1\n")
    assert resolve_dataset_dir(tmp_path, "ds", ["a.dat", "b.dat"], "X") == tmp_path / "ds"
    assert resolve_dataset_dir(tmp_path / "ds", "ds", ["a.dat", "b.dat"], "X") == tmp_path / "ds"
    with pytest.raises(MissingDataError, match=r"c\.dat: X: missing file\(s\) c\.dat"):
        resolve_dataset_dir(tmp_path, "ds", ["a.dat", "c.dat"], "X")
    with pytest.raises(MissingDataError, match="no dataset files found; looked in"):
        resolve_dataset_dir(tmp_path / "nowhere", "ds", ["a.dat"], "X")


def test_large_file_is_fast(tmp_path):
    import time
    rng = np.random.default_rng(0)
    a = np.column_stack([np.arange(70000) * 0.01, rng.normal(size=(70000, 3))])
    p = tmp_path / "big.dat"
    np.savetxt(p, a, fmt="%.6f", delimiter="\t", header="t a b c")
    t0 = time.perf_counter()
    t = read_table(p, 4, time_cols=0)
    dt = time.perf_counter() - t0
    assert t.data.shape == (70000, 4)
    assert dt < 3.0, dt  # ~0.1 s on one core; generous for a loaded CI machine


def test_a_nan_time_does_not_hide_a_step_back(tmp_path):
    """finite=False on the time column keeps a NaN time; the step back across it (1, nan, 0.5)
    must still be refused, as (1, 0.5) is (NaN < 0 is False: it passed)."""
    p = _write(tmp_path / "t.txt", "1.0 2 3\nnan 2 3\n0.5 2 3\n")
    with pytest.raises(DataFormatError, match=r"t\.txt:3: time goes backwards in column 1: 0\.5 after 1\.0 \(line 1\)"):
        read_table(p, 3, time_cols=0, finite=[1, 2])
    tab = read_table(_write(tmp_path / "u.txt", "1.0 2 3\nnan 2 3\n1.5 2 3\n"), 3, time_cols=0, finite=[1, 2])
    assert np.isnan(tab.data[1, 0]) and tab.data[2, 0] == 1.5


def test_byte_order_mark_is_not_data_and_only_ascii_numbers_are_numbers(tmp_path):
    # A spreadsheet's UTF-8 CSV starts with a byte-order mark: it was read as part of the first
    # field ("non-numeric field '\ufeff1'", or a header mismatch).  Python's float() also reads
    # '1_000' and other scripts' digits, which the fallback parser then accepted as numbers.
    p = _write(tmp_path / "bom.csv", "\ufeff1,2\n3,4\n")
    np.testing.assert_array_equal(read_table(p, 2, delimiter=",").data, [[1.0, 2.0], [3.0, 4.0]])
    p = _write(tmp_path / "bomh.csv", "\ufefft,x\n1,2\n")
    np.testing.assert_array_equal(read_table(p, 2, delimiter=",", header_rows=1, header=["t", "x"]).data,
                                  [[1.0, 2.0]])
    for name, field in (("us.txt", "1_000"), ("ar.txt", "\u0661\u0662")):
        p = _write(tmp_path / name, f"5 6\n{field} 2\n")
        with pytest.raises(DataFormatError, match=r":2: non-numeric field .* in column 1"):
            read_table(p, 2)
