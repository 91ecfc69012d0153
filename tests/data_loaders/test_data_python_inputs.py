"""Bad arguments to the ``jaxslam.data`` Python API are refused early with an InputError naming
them (a probe of the API found each case below silently wrong or failing with a bare error).

Uses the committed excerpts (tests/data) and tmp_path copies of them; nothing is compiled.
"""

import shutil
import subprocess
import sys

import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import catalogue, load_mrclam, load_plaza, load_util, load_victoria_park, tag_positions
from jaxslam.data.events import check_times, merge_events
from jaxslam.data.textfile import DataFormatError, int_column, read_table
from jaxslam.errors import InputError


def _merge(**kw):
    """Two inputs, two measurement rows; ``kw`` overrides any argument."""
    args = dict(input_t=[0.0, 1.0], inputs=np.zeros((2, 2)), meas_t=[0.5, 0.5], meas=np.ones((2, 2)))
    args.update(kw)
    return merge_events(**args)


# ------------------------------------------------------------------- catalogue (items 1, 20)
@pytest.mark.parametrize("name, options, match", [
    ("mrclam", {"filter": "EKF"}, r"^mrclam: --filter: expected one of 'ekf', 'fastslam', got 'EKF'"),
    ("mrclam", {"filter": None}, r"^mrclam: --filter: expected one of"),
    ("mrclam", {"ids": "Known"}, r"^mrclam: --ids: expected one of 'known', 'hidden', got 'Known'"),
    ("plaza", {"anchors": "Known"}, r"^plaza: --anchors: expected one of None, 'known', 'unknown'"),
    ("util-uwb", {"anchors": "surveyed"}, r"^util-uwb: --anchors: expected one of"),
    ("mrclam", {"robot": np.array([1, 2])}, r"^mrclam: --robot: expected an int >= 1"),  # ambiguous truth value
    ("mrclam", {"robot": "1"}, r"^mrclam: --robot: expected an int >= 1, got '1'"),
    ("plaza", {"robot": 2.0}, r"^plaza: --robot: expected an int >= 1"),
    ("util-uwb", {"tof": "no"}, r"^util-uwb: --tof: expected True or False"),
    ("bogus", {"robot": 2}, r"^dataset: unknown name 'bogus' \(choose from mrclam, plaza, util-uwb, victoria-park\)"),
    ("mrclam", {1: 2, "x": 1}, r"^dataset: unknown option\(s\) \[1, 'x'\]"),  # sorted() of mixed keys
])
def test_check_options_refuses_values_an_option_does_not_take(name, options, match):
    with pytest.raises(InputError, match=match):
        catalogue.check_options(name, options)


def test_check_options_still_takes_the_valid_values():
    catalogue.check_options("mrclam", {"filter": "fastslam", "ids": "hidden", "robot": np.int64(2), "particles": 8})
    catalogue.check_options("plaza", {"anchors": "known", "robot": 2, "smooth": np.True_})
    catalogue.check_options("util-uwb", {"anchors": None, "tof": True})
    with pytest.raises(InputError, match=r"^victoria-park: --particles do\(es\) not apply"):
        catalogue.check_options("victoria-park", {"particles": np.array([1, 2])})  # no ambiguous-truth error


def test_run_dataset_refuses_a_misspelt_method_before_loading():
    from jaxslam.data.runners import run_dataset

    # each ran another method before: FastSLAM, ids hidden, unknown-beacon SLAM
    for name, opt in (("mrclam", {"filter": "EKF"}), ("mrclam", {"ids": "Known"}),
                      ("plaza", {"anchors": "Known"}), ("util-uwb", {"anchors": "x"})):
        with pytest.raises(InputError, match=rf"^{name}: --{next(iter(opt))}: expected one of"):
            run_dataset(name, EXCERPTS, **opt)


def test_catalogue_lookups_name_a_bad_dataset_root_or_robot():
    for fn in (catalogue.find, catalogue.robots_found):  # KeyError before
        with pytest.raises(InputError, match=r"^dataset: unknown name 'bogus'"):
            fn("bogus", EXCERPTS)
    with pytest.raises(InputError, match=r"^root: expected a folder path"):
        catalogue.find("mrclam", None)
    with pytest.raises(InputError, match=r"^dataset: unknown name 'bogus'"):
        catalogue.check_robot("bogus", EXCERPTS, 1)
    with pytest.raises(InputError, match=r"^--robot: expected an int >= 1, got '1'"):
        catalogue.check_robot("mrclam", EXCERPTS, "1")  # "MRCLAM robot 1 is not in ... (found: 1, 2)" before
    with pytest.raises(InputError, match=r"^--robots: expected a list of robot numbers, got 3"):
        catalogue.check_robots("mrclam", EXCERPTS, 3)  # TypeError before
    with pytest.raises(InputError, match=r"^--robots: expected a list of robot numbers, got '13'"):
        catalogue.check_robots("mrclam", EXCERPTS, "13")  # checked '1' and '3' before
    catalogue.check_robots("mrclam", EXCERPTS, (1, np.int64(2)))
    with pytest.raises(InputError, match=r"MRCLAM robot 3 is not in"):
        catalogue.check_robots("mrclam", EXCERPTS, [1, 3])


def test_catalogue_textfile_and_events_stay_free_of_jax():
    code = ("import sys; import jaxslam.data.catalogue, jaxslam.data.textfile, jaxslam.data.events; "
            "print('jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr


# ------------------------------------------------------------------- merge_events (4, 5, 6, 21)
def test_merge_events_ids_must_fit_int32():
    for ids, what in (([2**32 - 1, 2**32 + 7], "4294967295"),  # wrapped to [-1, 7]
                      (np.array([2.0**33, 1.0]), "8589934592.0"),  # -2147483648
                      (np.array([-(2**31) - 1, 0]), "-2147483649")):
        with pytest.raises(InputError, match=rf"^meas_ids: id {what} at index 0 does not fit int32"):
            _merge(meas_ids=np.asarray(ids))
    for ids in (np.array([True, False]), np.array([1 + 0j, 2]), ["a", "b"], [None, 1]):
        with pytest.raises(InputError, match=r"^meas_ids: expected integer ids \(-1 for none\), got dtype"):
            _merge(meas_ids=ids)
    log = _merge(meas_ids=np.array([2**31 - 1, -1], np.int64))
    assert log.ids.dtype == np.int32 and log.ids[1].tolist() == [2**31 - 1, -1]


def test_merge_events_window_must_be_finite_and_in_order():
    with pytest.raises(InputError, match=r"^t_start, t_end: t_start 1\.5 is after t_end 1\.2"):
        _merge(t_start=1.5, t_end=1.2)  # returned an event at 1.5
    with pytest.raises(InputError, match=r"^t_start: expected a time \[s\] \(None or -inf for an open start\), got inf"):
        _merge(t_start=np.inf)  # gave one event at t = inf
    with pytest.raises(InputError, match=r"^t_end: expected a time \[s\] \(None or \+inf for an open end\), got -inf"):
        _merge(t_end=-np.inf)
    with pytest.raises(InputError, match=r"^t_start, t_end: expected numbers \(or None\), got nan, 0.5"):
        _merge(t_start=float("nan"), t_end=0.5)  # the existing message
    with pytest.raises(InputError, match=r"^t_start: expected real numbers, got dtype <U1"):
        _merge(t_start="a")
    with pytest.raises(InputError, match=r"^t_end: expected one time \[s\] \(or None\), got shape \(2,\)"):
        _merge(t_end=np.array([0.5, 1.0]))
    with pytest.raises(InputError, match=r"^t_start: expected real numbers, got dtype bool"):
        _merge(t_start=True)
    log = _merge(t_start=0.5, t_end=0.5)  # one instant is a window
    assert log.t.tolist() == [0.5] and log.stats["n_meas"] == 2


def test_merge_events_infinite_open_ends_are_none():
    # -inf for t_start and +inf for t_end are open ends, as None (refused by this session's first check)
    ref = _merge(t_start=0.2)
    for kw in (dict(t_start=-np.inf, t_end=np.inf), dict(t_start=-np.inf), dict(t_end=np.inf),
               dict(t_start=-np.inf, t_end=1.0)):
        log = _merge(**kw)
        assert log.t.tolist() == [0.0, 0.5, 1.0] and log.stats["outside_window"] == 0
    log = _merge(t_start=0.2, t_end=np.inf)
    assert log.t.tolist() == ref.t.tolist() == [0.2, 0.5, 1.0]
    assert np.array_equal(log.u, ref.u)


def test_merge_events_checks_only_the_inputs_in_use():
    # a NaN input sample outside the window is never used: it no longer fails the call
    U = np.array([[np.nan, 0.0], [1.0, 2.0], [3.0, 4.0], [np.inf, 0.0]])
    t = [0.0, 1.0, 2.0, 3.0]
    kw = dict(input_t=t, inputs=U, meas_t=[1.5, 2.5], meas=np.ones((2, 2)))
    for mode in ("rate", "increment"):
        log = merge_events(**kw, input_mode=mode, t_start=1.0, t_end=2.5)
        assert np.all(np.isfinite(log.u)) and log.t.tolist() == [1.0, 1.5, 2.0, 2.5]
    # "rate" holds the last sample before t_start into the window: u over (1.0, 1.5] is row 1
    log = merge_events(**kw, t_start=1.2, t_end=2.5)
    assert log.t.tolist() == [1.2, 1.5, 2.0, 2.5] and log.u[1].tolist() == [1.0, 2.0]
    # that held sample must be finite (named by its row in the caller's array); "increment" does not use it
    with pytest.raises(InputError, match=r"^inputs: non-finite value nan at row 0, column 0"):
        merge_events(**kw, t_start=0.5, t_end=2.5)
    log = merge_events(**kw, input_mode="increment", t_start=0.5, t_end=2.5)
    assert np.all(np.isfinite(log.u))
    with pytest.raises(InputError, match=r"^inputs: non-finite value inf at row 3, column 0"):
        merge_events(**kw, t_start=1.0, t_end=3.0)
    with pytest.raises(InputError, match=r"^inputs: non-finite value nan at row 0, column 0"):
        merge_events(**kw)  # no window: every sample is used


@pytest.mark.parametrize("K", [1.5, True, "2", float("nan"), float("inf"), 0, np.float64(2.0)])
def test_merge_events_K_must_be_an_int(K):
    # 1.5 and True were truncated to 1 (a row dropped into dropped_overflow), '2' parsed,
    # nan / inf a bare ValueError / OverflowError
    with pytest.raises(InputError, match=r"^K: expected an int >= 1"):
        _merge(K=K)


def test_merge_events_K_takes_numpy_ints():
    assert _merge(K=np.int64(3)).z.shape == (3, 3, 2)


def test_merge_events_names_bad_inputs_and_times():
    with pytest.raises(InputError, match=r"^u_before: expected 2 value\(s\) \(one per input column\), got shape \(3,\)"):
        _merge(u_before=[1.0, 2.0, 3.0])  # a bare reshape ValueError before
    with pytest.raises(InputError, match=r"^u_before: non-finite value nan at index 1"):
        _merge(u_before=[0.0, np.nan])
    with pytest.raises(InputError, match=r"^u_before: applies to input_mode='rate' only"):
        _merge(u_before=[0.0, 0.0], input_mode="increment")
    with pytest.raises(InputError, match=r"^inputs: non-finite value nan at row 1, column 0"):
        _merge(inputs=np.array([[0.0, 0.0], [np.nan, 0.0]]))  # poisoned every later prediction
    with pytest.raises(InputError, match=r"^inputs: non-finite value inf at row 0, column 1"):
        _merge(inputs=np.array([[0.0, np.inf], [0.0, 0.0]]))
    with pytest.raises(InputError, match=r"^inputs: expected real numbers, got dtype <U3"):
        _merge(inputs=["1.5", "2.5"])  # NumPy parsed the strings
    with pytest.raises(InputError, match=r"^meas: expected real numbers, got dtype complex128"):
        _merge(meas=np.ones((2, 2)) * 1j)
    with pytest.raises(InputError, match=r"^meas: expected real numbers, got a ragged sequence"):
        _merge(meas=[[1.0], [1.0, 2.0]])
    # datetimes were read as epoch seconds (datetime64) or seconds (timedelta64)
    stamps = np.array(["2020-01-01T00:00:00", "2020-01-01T00:00:01"], dtype="datetime64[s]")
    with pytest.raises(InputError, match=r"^input_t: expected real numbers, got dtype datetime64\[s\] \(times are seconds"):
        _merge(input_t=stamps)
    with pytest.raises(InputError, match=r"^meas_t: expected real numbers, got dtype timedelta64\[s\]"):
        _merge(meas_t=np.array([1, 1], dtype="timedelta64[s]"))
    with pytest.raises(InputError, match=r"^meas_t: expected real numbers, got dtype object"):
        _merge(meas_t=[0.5, None])
    with pytest.raises(InputError, match=r"^t: expected real numbers, got dtype datetime64"):
        check_times(stamps, "t")
    with pytest.raises(InputError, match=r"^input_mode: expected 'rate' or 'increment', got \['rate'\]"):
        _merge(input_mode=["rate"])
    # NaN measurements stay allowed (the systems mask them and count them)
    assert _merge(meas=np.array([[np.nan, 1.0], [1.0, 1.0]])).mask.sum() == 2


# ------------------------------------------------------------------- read_table / int_column (8, 9, 23)
def test_read_table_checks_its_arguments(tmp_path):
    p = tmp_path / "t.dat"
    p.write_text("# a b c\n1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match=r"^header_rows: expected an int >= 0, got -1"):
        read_table(p, 3, header_rows=-1)  # the last line was read again as data row "line 0"
    for kw, match in [
        (dict(ncols="3"), r"^ncols: expected an int >= 1, got '3'"),  # "expected 3 columns, got 3"
        (dict(ncols=0), r"^ncols: expected an int >= 1, got 0"),
        (dict(finite=[10]), r"^finite: column index 10 is out of range for 3 column\(s\)"),  # IndexError
        (dict(finite=[-4]), r"^finite: column index -4 is out of range for 3 column\(s\)"),
        (dict(time_cols=10), r"^time_cols: column index 10 is out of range"),  # IndexError
        (dict(time_cols=True), r"^time_cols: expected a column index or a sequence of them, got True"),
        (dict(time_cols=[0, 1.0]), r"^time_cols: expected an int column index, got 1.0"),
        (dict(delimiter="ab"), r"^delimiter: expected None \(whitespace\) or one character, got 'ab'"),
        (dict(comments=""), r"^comments: expected None or a non-empty prefix string"),
        (dict(header=("a", "b", "c")), r"^header: .* give header_rows >= 1"),  # silently unchecked
        (dict(gz="no"), r"^gz: expected True or False \(or None\), got 'no'"),
        (dict(allow_empty=None), r"^allow_empty: expected True or False, got None"),
        (dict(gz=2), r"^gz: expected True or False \(or None\), got 2"),
        (dict(allow_empty=-1), r"^allow_empty: expected True or False, got -1"),
    ]:
        with pytest.raises(InputError, match=match):
            read_table(p, **{"ncols": 3, **kw})
    with pytest.raises(InputError, match=r"^path: expected a file or folder path \(str or os.PathLike\), got None"):
        read_table(None, 3)
    t = read_table(str(p), np.int64(3), header_rows=np.int64(0), time_cols=np.array([0]), finite=np.True_)
    assert t.data.shape == (2, 3) and t.lines.tolist() == [2, 3]
    assert read_table(p, 3, finite=(0, 2)).data.shape == (2, 3)


def test_read_table_takes_negative_column_indices_and_0_1_flags(tmp_path):
    # NumPy indexing took -1 (the last column) before this session's check refused it; gz and
    # allow_empty were read as truth values, so 0 and 1 worked
    p = tmp_path / "t.dat"
    p.write_text("1 2 9\n4 nan 6\n")
    assert read_table(p, 3, finite=[-1, 0]).data.shape == (2, 3)  # column 2 (the NaN) unchecked
    with pytest.raises(DataFormatError, match=r"t\.dat:2: non-finite value nan in column 2$"):
        read_table(p, 3, finite=[-2])
    with pytest.raises(DataFormatError, match=r"t\.dat:2: time goes backwards in column 3: 6\.0 after 9\.0"):
        read_table(p, 3, finite=False, time_cols=-1)
    assert read_table(p, 3, finite=False, time_cols=[-3]).data[1, 0] == 4.0
    assert read_table(p, 3, finite=False, gz=0, allow_empty=1).data.shape == (2, 3)
    e = tmp_path / "e.dat"
    e.write_text("# nothing\n")
    assert read_table(e, 2, allow_empty=np.int64(1)).data.shape == (0, 2)
    with pytest.raises(DataFormatError, match=r"no data rows"):
        read_table(e, 2, allow_empty=0)
    t = read_table(p, 3, finite=False)
    assert int_column(t, -1, "id").tolist() == [9, 6] == int_column(t, 2, "id").tolist()
    with pytest.raises(InputError, match=r"^col: column index -4 is out of range for 3 column\(s\)"):
        int_column(t, -4, "id")


def test_int_column_names_the_int64_range_before_the_bounds(tmp_path):
    # with lo given, 1e30 was "expected an integer >= 0" (it is >= 0: the int64 range is what fails)
    p = tmp_path / "i.dat"
    p.write_text("1 2\n1e30 3\n-1e19 4\n")
    t = read_table(p, 2)
    for kw in (dict(lo=0), dict(hi=10**6), dict(lo=0, hi=10**6)):
        with pytest.raises(DataFormatError, match=r"i\.dat:2: id \(column 1\): expected an integer in the "
                                                  r"int64 range, got 1e\+30"):
            int_column(t, 0, "id", **kw)
    q = tmp_path / "j.dat"
    q.write_text("1 2\n-3 3\n")
    with pytest.raises(DataFormatError, match=r"j\.dat:2: id \(column 1\): expected an integer >= 0, got -3\.0"):
        int_column(read_table(q, 2), 0, "id", lo=0)


def test_int_column_refuses_values_beyond_int64(tmp_path):
    p = tmp_path / "i.dat"
    p.write_text("1 2\n1e30 3\n-1e19 4\n")
    t = read_table(p, 2)
    with pytest.raises(DataFormatError, match=r"i\.dat:2: id \(column 1\): expected an integer in the int64 range, got 1e\+30"):
        int_column(t, 0, "id")  # -9223372036854775808 with a RuntimeWarning before
    with pytest.raises(InputError, match=r"^col: column index 2 is out of range for 2 column\(s\)"):
        int_column(t, 2, "id")
    q = tmp_path / "u.dat"
    q.write_text("5 0\n6 0\n5 1\n")
    with pytest.raises(DataFormatError, match=r"u\.dat:3: id 5 listed twice \(first at .*u\.dat:1\)"):
        int_column(read_table(q, 2), 0, "id", unique=True)
    assert int_column(read_table(q, 2), 1, "flag").tolist() == [0, 0, 1]


def _util_copy(tmp_path, anchor_lines=(), replace=None):
    u = tmp_path / "util_uwb"
    shutil.copytree(EXCERPTS / "util_uwb", u)
    a = u / "anchors_const3.csv"
    text = a.read_text()
    if replace is not None:
        text = text.replace(*replace)
    a.write_text(text + "".join(line + "\n" for line in anchor_lines))
    return u, a


def test_util_ids_beyond_int32_are_refused_at_their_line(tmp_path):
    # anchor 2**31 was cast to int32 -2147483648 (and its ranges' ids with it)
    u, a = _util_copy(tmp_path, replace=("\n7,", "\n2147483648,"))
    with pytest.raises(DataFormatError, match=r"anchors_const3\.csv:9: anchor_id \(column 1\): expected an integer "
                                              r"in \[0, 2147483647\], got 2147483648\.0"):
        load_util(u)


# ------------------------------------------------------------------- duplicated ids (13)
def test_util_anchor_listed_twice_is_refused_at_its_line(tmp_path):
    u, a = _util_copy(tmp_path, anchor_lines=["0,9,9,9,0,0,0,1"])
    n = len(a.read_text().splitlines())
    with pytest.raises(DataFormatError, match=rf"anchors_const3\.csv:{n}: anchor_id 0 listed twice "
                                              r"\(first at .*anchors_const3\.csv:2\)"):
        load_util(u)  # two positions for anchor 0 before


def test_plaza_node_listed_twice_is_refused_at_its_line(tmp_path):
    g = tmp_path / "gtsam"
    shutil.copytree(EXCERPTS / "gtsam", g)
    tl = g / "Plaza1_TL.txt"
    tl.write_text(tl.read_text() + "0 99 99\n")
    n = len(tl.read_text().splitlines())
    with pytest.raises(DataFormatError, match=rf"Plaza1_TL\.txt:{n}: node id 0 listed twice \(first at .*Plaza1_TL\.txt:2\)"):
        load_plaza(tmp_path, 1)
    assert sorted(load_plaza(EXCERPTS, 1).node_id.tolist()) == [0, 1, 5, 6]  # the shipped TL: four distinct nodes


# ------------------------------------------------------------------- tag_positions (14)
def test_tag_positions_refuses_bad_shapes_and_zero_quaternions():
    with pytest.raises(InputError, match=r"^q_xyzw: quaternion \[0\.0, 0\.0, 0\.0, 0\.0\] is zero or not finite"):
        tag_positions([0, 0, 0], [0, 0, 0, 0])  # [nan, nan, nan] before
    with pytest.raises(InputError, match=r"^q_xyzw: quaternion \[0\.0, 0\.0, 0\.0, 0\.0\] at index \(1,\)"):
        tag_positions(np.zeros((2, 3)), [[0, 0, 0, 1], [0, 0, 0, 0]])
    with pytest.raises(InputError, match=r"^p: expected shape \(\.\.\., 3\), got \(2,\)"):
        tag_positions([0, 0], [0, 0, 0, 1])  # bare ValueError
    with pytest.raises(InputError, match=r"^q_xyzw: expected shape \(\.\.\., 4\), got \(3,\)"):
        tag_positions([0, 0, 0], [0, 0, 1])  # bare IndexError
    with pytest.raises(InputError, match=r"^offset: expected shape \(\.\.\., 3\)"):
        tag_positions([0, 0, 0], [0, 0, 0, 1], offset=[1.0, 2.0])
    with pytest.raises(InputError, match=r"^p, q_xyzw, offset: leading shapes \(2,\), \(3,\), \(\) do not broadcast"):
        tag_positions(np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (3, 1)))
    with pytest.raises(InputError, match=r"^p: expected numbers"):
        tag_positions(["a", 0, 0], [0, 0, 0, 1])
    np.testing.assert_allclose(tag_positions([1, 2, 3], [0, 0, 0, 2], offset=[1, 0, 0]), [2, 2, 3])


# ------------------------------------------------------------------- loader arguments (23)
def test_loaders_name_a_path_that_is_not_one():
    for load in (lambda p: load_mrclam(p, 1), load_victoria_park, lambda p: load_plaza(p, 1), load_util):
        with pytest.raises(InputError, match=r"^path: expected a file or folder path \(str or os.PathLike\), got None"):
            load(None)  # TypeError before
    for which in (np.True_, 1.0, np.array([1, 2])):  # np.True_ loaded Plaza 1
        with pytest.raises(InputError, match=r"^which: expected 1 or 2 \(Plaza 1 or Plaza 2\)"):
            load_plaza(EXCERPTS, which)
    assert load_plaza(EXCERPTS, np.int64(2)).which == 2
    for flight in (None, 1, "", "../util_uwb"):
        with pytest.raises(InputError, match=r"^flight: expected a flight folder name"):
            load_util(EXCERPTS, flight)
