"""An explicit --odometry-delay on a window without updating sightings, and ten study scripts on
the scripts' one parser (jaxslam.cli.common.ScriptParser with the CLI's types).

Oracles, by hand from the files and the design:

* ``tests/data/mrclam6`` robot 1 (as tests/tuning/test_data_targets_s35.py): the first sightings
  are 1.108 s into the ground truth (landmarks 41, 18 and 54, each its first), the next after
  1.2 s; so the first 1.0 s hold no sighting and the first 1.2 s only first ones, at any delay
  that leaves the odometry inside the window;
* the scripts' command lines are those of their docstrings and of docs/datasets.md; a usage
  error is one line ``NAME.py: error: ...`` and exit code 2, before any data is read.  Nothing
  here runs a study.
"""

from __future__ import annotations

import pathlib

import pytest
from script_modules import load_script, one_error_line as _error_line

from jaxslam.errors import InputError

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"


# --- 1. tune mrclam --odometry-delay S on a window in which no sighting updates the filter ----------

@pytest.mark.parametrize("t_max", [1.0, 1.2])  # no sighting; only first sightings (they place landmarks)
@pytest.mark.parametrize("delay", [0.0, 0.2])
def test_an_explicit_delay_on_a_window_without_updating_sightings_is_an_error(t_max, delay):
    # the target was built and the fit ran on the constant loss 0 (gradient 0: nothing learned)
    from jaxslam.tuning.targets import mrclam as RL

    with pytest.raises(InputError, match=rf"^--window: no sighting in the first {t_max:g} s of robot\(s\) 1 with "
                                         rf"the odometry delay {delay:g} s updates the filter \(none, or only each "
                                         r"landmark's first\), .*give a longer --window$"):
        RL.mrclam_noise(data=str(DATA), robots=[1], test_robots=[], t_max=t_max, odometry_delay=delay)


def test_an_explicit_delay_on_a_window_with_updating_sightings_builds_the_target():
    from jaxslam.tuning.targets import mrclam as RL

    tg = RL.mrclam_noise(data=str(DATA), robots=[1], test_robots=[], t_max=3.0, odometry_delay=0.2)
    assert tg.config["odometry_delay_s"] == 0.2 and tg.config["odometry_delay_nll"] is None


def test_tune_mrclam_with_an_explicit_delay_says_so_in_one_line_before_the_fit(run_cli, monkeypatch):
    from jaxslam.tuning import optimize

    def no_fit(*a, **k):
        raise AssertionError("the fit was reached")

    monkeypatch.setattr(optimize, "fit", no_fit)
    rc, out, err = run_cli(["tune", "mrclam", "--data", str(DATA), "--robots", "1", "--test-robots", "none",
                            "--window", "1", "--odometry-delay", "0", "--quiet"])
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith("jaxslam tune: error: --window: no sighting in the first 1 s of robot(s) 1 with the "
                               "odometry delay 0 s updates the filter "), err


# --- 2. the study scripts' arguments --------------------------------------------------------------------


_mods = {}


def mod(script):
    if script not in _mods:
        _mods[script] = load_script(script, "s35b")
    return _mods[script]


@pytest.fixture
def data_env(monkeypatch):
    monkeypatch.setenv("JAXSLAM_DATA_DIR", str(DATA))


D = str(DATA)


def test_association_compare_documented_lines(data_env):
    parse = mod("study_association_compare").parse
    for argv, which, preset in ((["mrclam", "fitted"], "mrclam", "fitted"), (["mrclam", "hand"], "mrclam", "hand"),
                                (["vp"], "vp", None), (["vp", "-"], "vp", "-")):
        a = parse(argv)
        assert (a.which, a.preset, a.data) == (which, preset, D)
    a = parse(["mrclam", "hand", "/tmp"])
    assert a.data == "/tmp"
    assert parse(["vp", "-", "/tmp"]).data == "/tmp"


@pytest.mark.parametrize("argv, part", [
    ([], "the following arguments are required: which"),
    (["kitti", "hand"], "argument which: invalid choice: 'kitti'"),
    (["mrclam"], "preset: mrclam needs one of fitted, hand, got None"),  # was an IndexError
    (["mrclam", "fited"], "preset: mrclam needs one of fitted, hand, got 'fited'"),
    (["vp", "hand"], "preset: vp has one preset, give '-' (or nothing), got 'hand'"),  # was ignored
    (["mrclam", "hand", ""], "argument DATA_DIR: '' is not a path"),
    (["mrclam", "hand", "/nonexistent/s35b"], "DATA_DIR: '/nonexistent/s35b' is not a folder"),
    (["vp", "-", "x", "y"], "unrecognized arguments: y"),
])
def test_association_compare_usage_errors(data_env, capsys, argv, part):
    line = _error_line(lambda: mod("study_association_compare").main(argv), capsys)
    assert line.startswith("study_association_compare.py: error: ") and part in line, line


def test_association_compare_without_data_dir_or_environment(monkeypatch, capsys):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)  # was a KeyError traceback
    line = _error_line(lambda: mod("study_association_compare").main(["vp"]), capsys)
    assert line.startswith("study_association_compare.py: error: DATA_DIR: the dataset folder is required"), line


def test_fusion_emitters(capsys):
    p = mod("study_fastslam_fusion_emitters").parser
    assert p().parse_args([]).N == 2000 and p().parse_args(["500"]).N == 500
    for argv, part in ((["0"], "argument N: must be >= 1, got 0"), (["many"], "argument N: invalid int value"),
                       (["1", "2"], "unrecognized arguments: 2")):
        line = _error_line(lambda: mod("study_fastslam_fusion_emitters").main(argv), capsys)
        assert line.startswith("study_fastslam_fusion_emitters.py: error: ") and part in line, line


def test_fusion_emitters_leaves_the_process_environment_alone_on_import(monkeypatch):
    # it set XLA_FLAGS at import (and before parsing): now in main, after the arguments
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    import os

    load_script("study_fastslam_fusion_emitters", "s35b")
    assert "XLA_FLAGS" not in os.environ


@pytest.mark.parametrize("study", ["robust", "optimal", "hidden", "pruning"])
def test_mrclam_fastslam_documented_lines(study):
    p = mod("study_mrclam_fastslam").parser
    assert vars(p().parse_args([study])) == {"study": study, "data": "../shared/data"}
    assert vars(p().parse_args([study, D])) == {"study": study, "data": D}


@pytest.mark.parametrize("argv, part", [
    ([], "the following arguments are required: study"),  # was exit 1 with a usage line
    (["robst"], "argument study: invalid choice: 'robst'"),
    (["robust", ""], "argument DATA_DIR: '' is not a path"),
    (["robust", "/nonexistent/s35b"], "DATA_DIR: '/nonexistent/s35b' holds no mrclam6/ folder"),
])
def test_mrclam_fastslam_usage_errors(capsys, argv, part):
    line = _error_line(lambda: mod("study_mrclam_fastslam").main(argv), capsys)
    assert line.startswith("study_mrclam_fastslam.py: error: ") and part in line, line


def test_mrclam_hidden_gates(capsys, monkeypatch):
    p = mod("study_mrclam_hidden_gates").parser
    assert p().parse_args([]).data is None and p().parse_args([D]).data == D
    for argv, part in (([D, "x"], "unrecognized arguments: x"), ([""], "argument DATA_DIR: '' is not a path")):
        line = _error_line(lambda: mod("study_mrclam_hidden_gates").main(argv), capsys)
        assert line.startswith("study_mrclam_hidden_gates.py: error: ") and part in line, line
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)  # was a KeyError traceback
    line = _error_line(lambda: mod("study_mrclam_hidden_gates").main([]), capsys)
    assert line.startswith("study_mrclam_hidden_gates.py: error: DATA_DIR: the dataset folder is required"), line


def test_range_only_documented_lines():
    p = mod("study_range_only").parser
    assert vars(p().parse_args([])) == {"what": "all", "f32": False, "data": None}
    assert vars(p().parse_args(["util"])) == {"what": "util", "f32": False, "data": None}
    assert vars(p().parse_args(["plaza", "--f32", "--data", D])) == {"what": "plaza", "f32": True, "data": D}
    # the options first: 'what' was sys.argv[1], so '--data DIR util' and '--f32 util' ran nothing
    assert vars(p().parse_args(["--data", D, "util"])) == {"what": "util", "f32": False, "data": D}
    assert vars(p().parse_args(["--f32", "all"])) == {"what": "all", "f32": True, "data": None}


@pytest.mark.parametrize("argv, part", [
    (["utill"], "argument what: invalid choice: 'utill'"),  # ran nothing, exit 0
    (["util", "--data"], "argument --data: expected one argument"),  # was an IndexError at import
    (["util", "--f64"], "unrecognized arguments: --f64"),  # was ignored
    (["util", "--data", ""], "argument --data: '' is not a path"),
])
def test_range_only_usage_errors(capsys, argv, part):
    line = _error_line(lambda: mod("study_range_only").main(argv), capsys)
    assert line.startswith("study_range_only.py: error: ") and part in line, line


def test_range_only_without_data_or_environment(monkeypatch, capsys):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)  # was a KeyError traceback at import
    line = _error_line(lambda: mod("study_range_only").main(["util"]), capsys)
    assert line.startswith("study_range_only.py: error: --data: the dataset folder is required"), line


def test_util_anchor_bias_documented_lines():
    p = mod("study_util_anchor_bias").parser
    assert vars(p().parse_args(["0.1", "5", "none"])) == {"sig_ab": 0.1, "nu": 5.0, "gate": None, "sigma_r": 0.2,
                                                          "data": None}
    assert vars(p().parse_args(["0", "none", "3.84", "0.3", D])) == {"sig_ab": 0.0, "nu": None, "gate": 3.84,
                                                                     "sigma_r": 0.3, "data": D}


@pytest.mark.parametrize("argv, part", [
    (["0.1", "5"], "the following arguments are required: GATE|none"),  # an IndexError
    (["-0.1", "5", "none"], "argument SIGMA_AB: must be a number >= 0, got -0.1"),
    (["0.1", "five", "none"], "argument NU|none: invalid float value: 'five'"),  # a ValueError traceback
    (["0.1", "nan", "none"], "argument NU|none: must be a positive number, got nan"),
    (["0.1", "5", "0"], "argument GATE|none: must be a positive number, got 0"),
    (["0.1", "5", "none", "0"], "argument SIGMA_R: must be a positive number, got 0"),
    (["0.1", "5", "none", "0.2", "/nonexistent/s35b"], "DATA_DIR: '/nonexistent/s35b' is not a folder"),
])
def test_util_anchor_bias_usage_errors(data_env, capsys, argv, part):
    line = _error_line(lambda: mod("study_util_anchor_bias").main(argv), capsys)
    assert line.startswith("study_util_anchor_bias.py: error: ") and part in line, line


def test_util_anisotropic_documented_lines(monkeypatch):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)
    p = mod("study_util_anisotropic").parser
    assert vars(p().parse_args([])) == {"data": "../shared/data", "json": None}
    assert vars(p().parse_args([D])) == {"data": D, "json": None}
    # '--json PATH' (the docstring's form) took PATH as the data folder and wrote no JSON: only
    # '--json=PATH' was read
    assert vars(p().parse_args(["--json", "out.json"])) == {"data": "../shared/data", "json": "out.json"}
    assert vars(p().parse_args([D, "--json", "out.json"])) == {"data": D, "json": "out.json"}
    assert vars(p().parse_args([D, "--json=out.json"])) == {"data": D, "json": "out.json"}
    monkeypatch.setenv("JAXSLAM_DATA_DIR", "/some/where")
    assert p().parse_args([]).data == "/some/where"


def test_util_anisotropic_usage_errors_and_no_patch_on_import(capsys, tmp_path):
    from jaxslam.systems import util_range as ur

    before = ur.cv_process_noise
    m = mod("study_util_anisotropic")
    assert ur.cv_process_noise is before  # importing the file replaced the library's process noise
    for argv, part in ((["--json"], "argument --json: expected one argument"),
                       ([D, "x"], "unrecognized arguments: x"),
                       ([D, "--json", str(tmp_path)], "--json: ")):  # a folder: before the fits
        line = _error_line(lambda: m.main(argv), capsys)
        assert line.startswith("study_util_anisotropic.py: error: ") and part in line, line
    assert ur.cv_process_noise is before


def test_util_imu_vertical_documented_lines():
    parse = mod("study_util_imu_vertical").parse
    given, v = parse([])
    assert given == {} and v == {"imu": 1, "qh": 0.139, "qz": 0.01, "qg": 1e-4, "qba": 1e-4, "qb": 3.4e-5,
                                 "sab": 0.0, "sr": 0.0592, "nu": 5.0, "ds": 5}
    given, v = parse(["imu=0"])
    assert given == {"imu": "0"} and v["imu"] == 0
    given, v = parse(["imu=1", "qz=0.001"])
    assert given == {"imu": "1", "qz": "0.001"} and (v["imu"], v["qz"]) == (1, 0.001)
    given, v = parse(["sab=0.2", "ds=1", "nu=3"])
    assert (v["sab"], v["ds"], v["nu"]) == (0.2, 1, 3.0)


@pytest.mark.parametrize("argv, part", [
    (["qZ=0.1"], "unknown key 'qZ' in 'qZ=0.1'"),  # was ignored: the default run, labelled {'qZ': '0.1'}
    (["qz"], "expected key=value, got 'qz'"),  # a ValueError traceback
    (["qz=0.1=2"], "qz: invalid float value: '0.1=2'"),  # a ValueError traceback
    (["imu=2"], "imu: expected 0 or 1, got '2'"),  # scaled the vertical acceleration by 2
    (["ds=0"], "ds: must be >= 1, got 0"),  # a ZeroDivisionError
    (["sr=-1"], "sr: must be a positive number, got -1"),
    (["qz=1", "qz=2"], "key=value: qz given more than once"),  # the last won
    (["--qz=1"], "unrecognized arguments: --qz=1"),
])
def test_util_imu_vertical_usage_errors(capsys, argv, part):
    line = _error_line(lambda: mod("study_util_imu_vertical").main(argv), capsys)
    assert line.startswith("study_util_imu_vertical.py: error: ") and part in line, line


def test_victoria_park_ekf(capsys, monkeypatch):
    m = mod("study_victoria_park_ekf")  # (it read the data at import: a KeyError without the variable)
    assert m.D is None and vars(m.parser().parse_args([])) == {}
    line = _error_line(lambda: m.main(["x"]), capsys)  # was ignored
    assert line == "study_victoria_park_ekf.py: error: unrecognized arguments: x", line
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)
    line = _error_line(lambda: m.main([]), capsys)
    assert line.startswith("study_victoria_park_ekf.py: error: $JAXSLAM_DATA_DIR: the dataset folder is "), line


def test_victoria_park_fastslam_documented_lines():
    p = mod("study_victoria_park_fastslam").parser
    assert vars(p().parse_args([])) == {"data": "../shared/data", "study": "proposal"}
    assert vars(p().parse_args([D])) == {"data": D, "study": "proposal"}
    assert vars(p().parse_args([D, "pruning"])) == {"data": D, "study": "pruning"}


@pytest.mark.parametrize("argv, part", [
    ([D, "prunning"], "argument study: invalid choice: 'prunning'"),  # a KeyError traceback
    (["", "pruning"], "argument DATA_DIR: '' is not a path"),
    (["/nonexistent/s35b"], "DATA_DIR: '/nonexistent/s35b' holds no victoria_park/ folder"),
    ([D, "pruning", "x"], "unrecognized arguments: x"),
])
def test_victoria_park_fastslam_usage_errors(capsys, argv, part):
    line = _error_line(lambda: mod("study_victoria_park_fastslam").main(argv), capsys)
    assert line.startswith("study_victoria_park_fastslam.py: error: ") and part in line, line


@pytest.mark.parametrize("script", ["study_association_compare", "study_fastslam_fusion_emitters",
                                    "study_mrclam_fastslam", "study_mrclam_hidden_gates", "study_range_only",
                                    "study_util_anchor_bias", "study_util_anisotropic", "study_util_imu_vertical",
                                    "study_victoria_park_ekf", "study_victoria_park_fastslam"])
def test_every_script_has_help_and_names_itself(capsys, script):
    with pytest.raises(SystemExit) as e:
        mod(script).main(["--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: {script}.py")


_ORDER_PROBE = """
import runpy, sys
from jaxslam import runtime
def spy(*a, **k):
    print("numpy loaded" if "numpy" in sys.modules else "numpy not loaded")
    raise SystemExit(0)
runtime.configure_process = spy
runpy.run_path(sys.argv[1], run_name="probe")
"""


@pytest.mark.parametrize("script", ["study_mrclam_fastslam", "study_range_only", "study_victoria_park_fastslam",
                                    "study_victoria_park_ekf", "study_association_compare",
                                    "study_mrclam_hidden_gates", "study_util_anisotropic",
                                    "study_covariance_forms", "study_plaza_smoothing",
                                    "study_util_anchor_bias"])  # (s36: it never called it)
def test_configure_process_runs_before_numpy_loads(script):
    # OpenBLAS reads its thread count when NumPy loads (jaxslam/runtime.py): the scripts' parser
    # imports (jaxslam.cli.common, errors, catalogue load NumPy) came before configure_process
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _ORDER_PROBE, str(ROOT / "scripts" / f"{script}.py")],
                       capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "numpy not loaded", (r.stdout, r.stderr[-2000:])
