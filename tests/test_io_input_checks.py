"""Bad input to the host-side modules (paramfile, io, files, plotting) raises InputError naming
the argument (or the file's key) before anything is drawn or written."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxslam import files, io  # noqa: E402
from jaxslam import paramfile as pf  # noqa: E402
from jaxslam.errors import InputError  # noqa: E402

_SCHEMA = {"noise": {"q": 0.1, "Q": [[0.1, 0.0], [0.0, 0.1]]}}


@pytest.mark.parametrize("given, msg", [
    ({"q": "0.5"}, r"^--params: noise\.q: expected numbers"),
    ({"Q": [["0.1", "0"], ["0", "0.1"]]}, r"^--params: noise\.Q: expected numbers"),
    ({"Q": ["0.1", "0.2"]}, r"^--params: noise\.Q: expected numbers"),
])
def test_paramfile_refuses_numbers_given_as_strings(given, msg):
    with pytest.raises(InputError, match=msg):
        pf.check({"noise": given}, _SCHEMA, target="t")


def test_paramfile_accepts_numbers():
    assert pf.check({"noise": {"q": 0.5, "Q": [1.0, 2.0]}}, _SCHEMA, target="t") == {
        "noise": {"q": 0.5, "Q": [1.0, 2.0]}}


@pytest.mark.parametrize("call, msg", [
    (lambda: io.summarize_metrics({"a": ["x"]}), r"^metrics\['a'\]: expected numbers"),
    (lambda: io.summarize_metrics([1, 2]), r"^metrics: expected a mapping"),
    (lambda: io.format_table({"a": {"mean": 1.0}}), r"^summary\['a'\]: missing median, p95, max"),
    (lambda: io.write_json(None, {"a": 1}), r"^path: expected a file path"),
    (lambda: files.prepare_file("--out", None), r"^--out: expected a file or folder path"),
    (lambda: files.prepare_dir("--dir", 5), r"^--dir: expected a file or folder path"),
])
def test_io_and_files_refuse_bad_input(call, msg):
    with pytest.raises(InputError, match=msg):
        call()


def test_writers_refuse_a_folder_as_the_file(tmp_path):
    with pytest.raises(InputError, match=r"^path: .* is a folder"):
        files.atomic_write(tmp_path, lambda f: f.write("x"))
    with pytest.raises(InputError, match=r"^path: .* is a folder"):
        io.write_json(tmp_path, {"a": 1})
    with pytest.raises(InputError, match=r"^mode: expected 'w' or 'wb'"):
        files.atomic_write(tmp_path / "a.txt", lambda f: f.write("x"), mode="a")
    assert io.summarize_metrics({"a": [1.0, None]})["a"]["per_run"][0] == 1.0  # None: NaN, as before


def test_plotting_refuses_bad_input(tmp_path):
    from jaxslam.plotting import flight, slam3d, uwb
    from jaxslam.plotting import tuning as pt

    report = {"before": {"metrics": {"a": {"mean": 1.0}}}, "after": {"metrics": {"a": {"mean": 2.0}}}}
    blocker = tmp_path / "file"
    blocker.write_text("x")
    cases = [
        (lambda: uwb.ellipse_points(np.zeros(2), -np.eye(2)), r"^cov: not positive semi-definite"),
        (lambda: uwb.ellipse_points(np.zeros(2), np.eye(3)), r"^cov: expected shape \(2, 2\)"),
        (lambda: flight.save(flight.plt().figure(), blocker, "x"), r"^directory: .* is a file, not a folder"),
        (lambda: flight.trajectory_3d(np.zeros(3), np.zeros(3)), r"^truth_pos: expected shape \(T, 3\+\)"),
        (lambda: flight.trajectory_3d(np.zeros((5, 2)), np.zeros((5, 3))), r"^truth_pos: expected shape"),
        (lambda: flight.states_over_time(np.arange(5.0), np.zeros((5, 3)), np.zeros((5, 4))),
         r"^truth: expected shape \(T, 9\+\)"),
        (lambda: flight.inputs_over_time(np.arange(5.0), np.zeros((5, 2))), r"^u: expected shape \(T, 4\+\)"),
        (lambda: pt.before_after(report, metrics=["zzz"]), r"^metrics: unknown statistic\(s\) \['zzz'\]"),
        (lambda: pt.before_after(report, max_panels=0), r"^max_panels: expected an int >= 1"),
        (lambda: pt.choose_panels(report, max_panels=-1), r"^max_panels: expected an int >= 1"),
        (lambda: pt.plot_all({}, tmp_path), r"^report: missing key\(s\)"),
        (lambda: pt.loss_curves([{"loss": 1.0}]), r"^history: record 0 is not a step record"),
        (lambda: slam3d.magnification([1.0], 10.0, fraction=np.inf), r"^fraction: expected a positive finite"),
    ]
    try:
        for call, msg in cases:
            with pytest.raises(InputError, match=msg):
                call()
    finally:
        flight.plt().close("all")
    assert uwb.ellipse_points(np.zeros(2), np.eye(2), n=8).shape == (8, 2)
    assert pt.choose_panels(report, max_panels=1)[0][0]["key"] == "a"


def test_write_json_refuses_a_nul_byte_in_the_path(tmp_path):
    """Review of 2026-12-07: Python's own ValueError ("embedded null byte") escaped."""
    from jaxslam.errors import InputError

    with pytest.raises(InputError, match=r"^path: cannot write JSON to .*embedded null byte"):
        io.write_json(str(tmp_path / "a\0b.json"), {"x": 1})
