"""Follow-ups of the day's reviews: every case below escaped as a bare exception, a traceback or
a usage block before the fix (``--params`` files the JSON parser cannot hold; ``--out`` /
``--plots`` folders that are existing files; the study scripts' plain argparse parsers).

Nothing here runs a reproduction or a study: their compute is replaced by fakes that fail the
test if reached."""

from __future__ import annotations

import argparse
import pathlib
import subprocess
import sys

import pytest
from script_modules import guarded_loader

from jaxslam import paramfile
from jaxslam.errors import InputError

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"


# --- 1. paramfile.load: what the JSON parser itself cannot read ---------------------------------

def _load_error(tmp_path, text, **kw):
    path = tmp_path / "p.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as e:
        paramfile.load(path, **kw)
    msg = str(e.value)
    assert "\n" not in msg and len(msg) < 300, msg
    return msg


@pytest.mark.parametrize("digits", [4301, 5000])
def test_an_integer_of_more_digits_than_python_reads_is_an_input_error_naming_the_option(tmp_path, digits):
    # was a bare ValueError ("Exceeds the limit (4300 digits) for integer string conversion")
    text = '{"noise": {"r": ' + "7" * digits + "}}"
    msg = _load_error(tmp_path, text)
    assert msg.startswith("--params: ") and f"holds an integer of {digits} digits" in msg, msg
    msg = _load_error(tmp_path, '{"controller": {"kp": [-' + "7" * digits + "]}}", name="--compare")
    assert msg.startswith("--compare: ") and f"holds an integer of {digits} digits" in msg, msg


@pytest.mark.parametrize("text", ["[" * 100_000, '{"a": ' * 100_000, "[" * 100_000 + "]" * 100_000])
def test_nesting_too_deep_for_the_parser_is_an_input_error_naming_the_option(tmp_path, text):
    # was a bare RecursionError ("maximum recursion depth exceeded while decoding a JSON array")
    for name in ("--params", "--compare"):
        msg = _load_error(tmp_path, text, name=name)
        assert msg.startswith(f"{name}: ") and "nests arrays or objects too deeply" in msg, msg


def test_the_usual_files_still_load_as_before(tmp_path):
    # the integer hook changes no value: ints stay ints (4300 digits still read), floats floats,
    # a repeated key and invalid JSON keep their messages
    path = tmp_path / "p.json"
    big = "9" * 4300
    path.write_text('{"noise": {"r": [1, -2, 0.5, 1e-3], "n": ' + big + '}, "deep": ' + "[" * 50 + "]" * 50 + "}")
    obj = paramfile.load(path)
    assert obj["noise"]["r"] == [1, -2, 0.5, 1e-3] and type(obj["noise"]["r"][0]) is int
    assert obj["noise"]["n"] == int(big)
    assert _load_error(tmp_path, '{"a": 1, "a": 2}').startswith("--params: ") and "twice" in \
        _load_error(tmp_path, '{"a": 1, "a": 2}')
    assert "is not valid JSON (line 1, column" in _load_error(tmp_path, '{"a": }')


def test_a_4300_digit_integer_keeps_its_too_large_message_naming_the_key(tmp_path):
    # (the OverflowError path of check(): unchanged; the integer is read, then refused by key)
    path = tmp_path / "p.json"
    path.write_text('{"noise": {"r": ' + "9" * 4300 + "}}")
    with pytest.raises(InputError, match=r"^--params: noise\.r: holds a number too large for a float"):
        paramfile.check(paramfile.load(path), {"noise": {"r": 1.0}}, target="t")


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999", "-1e999"])
def test_nan_infinity_and_out_of_range_floats_are_read_and_refused_by_key_as_documented(tmp_path, literal):
    # load's docstring: read as non-finite floats; check() refuses them naming the key
    path = tmp_path / "p.json"
    path.write_text('{"noise": {"r": ' + literal + ', "Q": [1.0, ' + literal + "]}}")
    obj = paramfile.load(path)
    assert obj["noise"]["r"] != obj["noise"]["r"] or abs(obj["noise"]["r"]) == float("inf")
    with pytest.raises(InputError, match=r"^--params: noise\.r: holds a non-finite value"):
        paramfile.check({"noise": {"r": obj["noise"]["r"]}}, {"noise": {"r": 1.0}}, target="t")
    with pytest.raises(InputError, match=r"^--params: noise\.Q: holds a non-finite value"):
        paramfile.check({"noise": {"Q": obj["noise"]["Q"]}}, {"noise": {"Q": [[1.0, 0.0], [0.0, 1.0]]}}, target="t")


def test_the_new_errors_need_no_jax(tmp_path):
    (tmp_path / "deep.json").write_text("[" * 100_000)
    (tmp_path / "long.json").write_text("{\"a\": " + "1" * 5000 + "}")
    code = ("import sys; from jaxslam import paramfile; from jaxslam.errors import InputError\n"
            "for f in sys.argv[1:]:\n"
            "    try: paramfile.load(f)\n"
            "    except InputError as e: print(str(e).split(':')[0])\n"
            "assert 'jax' not in sys.modules, 'jax imported'\n")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "deep.json"), str(tmp_path / "long.json")],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.split() == ["--params", "--params"], r.stdout + r.stderr


def test_jaxslam_run_answers_a_too_deep_params_file_with_one_line_exit_2(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000)
    r = subprocess.run([sys.executable, "-m", "jaxslam", "run", "ekfslam3d-unknown", "--params", str(path)],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "--params: " in lines[0] and "nests arrays or objects too deeply" in lines[0], lines[0]


# --- 2. and 3. scripts: one usage line, exit 2, before any compute --------------------------------


COMPUTE = ("part_oracle", "part_gradcheck", "part_ekf", "part_lqr", "part_loop", "part_nll_flat", "part_uwb",
           "controls", "simulate", "study", "probe", "part_resid", "part_odo", "part_loc", "part_slam", "mrclam",
           "victoria", "prepare", "run_config", "em_fit", "window_offsets")


@pytest.fixture
def guarded(monkeypatch):
    """Loads a script with everything that computes replaced by :func:`_no_compute`."""
    return guarded_loader(monkeypatch, COMPUTE, "followups_s35")


def _usage_line(mod, script, argv, capsys):
    with pytest.raises(SystemExit) as e:
        raise SystemExit(mod.main(argv))
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert e.value.code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{script}.py: error: "), lines[0]
    return lines[0]


FOLDER_OPTIONS = [
    ("reproduce_paper000", [], "--out"),
    ("reproduce_paper001", [], "--out"),
    ("reproduce_paper003", [], "--out"),
    ("reproduce_paper003", ["--out", "{tmp}/out"], "--plots"),
    ("reproduce_paper004", [], "--out"),
    ("reproduce_paper004", ["--out", "{tmp}/out"], "--plots"),
    ("reproduce_datasets", ["--data", str(DATA)], "--out"),
    ("reproduce_datasets", ["--data", str(DATA), "--out", "{tmp}/out"], "--plots"),
    ("reproduce_tuning", ["--quick", "--parts", "lqr"], "--out"),
    ("reproduce_tuning", ["--quick", "--parts", "lqr", "--out", "{tmp}/out"], "--plots"),
    ("reproduce_tuning", ["--quick", "--parts", "lqr", "--out", "{tmp}/out"], "--cache-dir"),
]


@pytest.mark.parametrize("script, argv, flag", FOLDER_OPTIONS)
@pytest.mark.parametrize("under", [False, True])
def test_an_output_folder_that_is_a_file_is_one_usage_line_before_any_run(guarded, tmp_path, capsys, script,
                                                                            argv, flag, under):
    # was a FileExistsError / NotADirectoryError traceback from mkdir (--out, --cache-dir), the
    # CLI's error once per case and a table of failed cases (reproduce_datasets --plots), or the
    # tuning parts' whole compute and then a traceback from the plots (reproduce_tuning --plots)
    blocker = tmp_path / "a_file"
    blocker.write_text("keep")
    path = blocker / "sub" if under else blocker
    mod = guarded(script)
    line = _usage_line(mod, script, [a.format(tmp=tmp_path) for a in argv] + [flag, str(path)], capsys)
    assert line.startswith(f"{script}.py: error: {flag}: '{blocker}' "), line
    assert ("is a file, so" if under else "exists and is not a folder") in line, line
    assert blocker.read_text() == "keep"


# The study scripts that had a plain argparse parser: (script, argv, the option the line names).
STUDY_ERRORS = [
    ("study_covariance_forms", ["--steps", "0"], "--steps"),
    ("study_covariance_forms", ["--steps", "9"], "--steps"),  # no frame
    ("study_covariance_forms", ["--steps", "x"], "--steps"),
    ("study_covariance_forms", ["--seeds", "0,x"], "--seeds"),
    ("study_covariance_forms", ["--seeds", "-1"], "--seeds"),
    ("study_covariance_forms", ["--r-scale", "1,0"], "--r-scale"),
    ("study_covariance_forms", ["--r-scale", "nan"], "--r-scale"),
    ("study_covariance_forms", ["--json", ""], "--json"),
    ("study_covariance_forms", ["--json", "{tmp}"], "--json"),
    ("study_covariance_forms", ["--bogus"], "--bogus"),
    ("study_loop_roughness", ["sideways"], "modes"),
    ("study_loop_roughness", ["--parts", "lin"], "--parts"),
    ("study_loop_roughness", ["--parts", ","], "--parts"),
    ("study_loop_roughness", ["--out", ""], "--out"),
    ("study_loop_roughness", ["--out", "{tmp}"], "--out"),
    ("study_loop_roughness", ["--out", "{tmp}/not.json"], "--out"),
    ("study_mrclam_diagnostics", ["--part", "resids"], "--part"),
    ("study_mrclam_diagnostics", ["--data", ""], "--data"),
    ("study_mrclam_diagnostics", ["--data", "{tmp}"], "--data"),
    ("study_planar_fastslam", ["--particles", "0"], "--particles"),
    ("study_planar_fastslam", ["--seeds", "-1"], "--seeds"),
    ("study_planar_fastslam", ["--robots", "1,7"], "--robots"),
    ("study_planar_fastslam", ["--robots", "1,,2"], "--robots"),
    ("study_planar_fastslam", ["--vp-capacity", "x"], "--vp-capacity"),
    ("study_planar_fastslam", ["--vp-t-end", "inf"], "--vp-t-end"),
    ("study_planar_fastslam", ["--floor", "-1"], "--floor"),
    ("study_planar_fastslam", ["--data", ""], "--data"),
    ("study_plaza_smoothing", ["--robot", "3"], "--robot"),
    ("study_plaza_smoothing", ["--robot", "1", "1"], "--robot"),
    ("study_plaza_smoothing", ["--configs", "nope"], "--configs"),
    ("study_plaza_smoothing", ["--configs", "huber-mad", "--robot", "1"], "--configs"),
    ("study_plaza_smoothing", ["--json", "{tmp}"], "--json"),
    ("study_plaza_smoothing", ["--data", ""], "--data"),
    ("study_util_motion_floor", ["{tmp}"], "data"),
    ("study_util_motion_floor", [""], "data"),
    ("study_util_motion_floor", ["--json", "{tmp}", "{tmp}"], "--json"),
]


@pytest.mark.parametrize("script, argv, flag", STUDY_ERRORS)
def test_study_scripts_answer_bad_arguments_with_one_line_naming_the_option(guarded, tmp_path, capsys, script,
                                                                           argv, flag):
    # were: argparse's usage block above the error, values accepted that started (or crashed) the
    # study (--steps 0, --seeds -1, --particles 0, an unknown --part or --parts that ran nothing),
    # or a traceback (a KeyError for --configs nope, MissingDataError for --data, a folder as --json
    # or --out after the whole study)
    (tmp_path / "not.json").write_text("{ not json")
    mod = guarded(script)
    line = _usage_line(mod, script, [a.format(tmp=tmp_path) for a in argv], capsys)
    assert flag in line, line


@pytest.mark.parametrize("script, argv", [("study_util_motion_floor", ["--json", ""]),
                                          ("study_planar_fastslam", ["--particles", "0"])])
def test_study_scripts_read_their_command_line_when_run(script, argv):
    # main() is given no argv when the script runs: the parser reads sys.argv
    r = subprocess.run([sys.executable, f"scripts/{script}.py", *argv], capture_output=True, text=True,
                       timeout=300, cwd=ROOT)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"{script}.py: error: argument {argv[0]}: "), lines[0]


def test_study_list_options_read_the_same_values_as_before(guarded):
    # the comma lists are now parsed by the parser: the same numbers reach the study
    mod = guarded("study_covariance_forms")
    assert mod._list_of(mod.seed_int)("0, 1") == [0, 1]
    assert mod._list_of(mod.positive_float)("1,1e-4") == [1.0, 1e-4]
    assert guarded("study_planar_fastslam")._robots("1,2") == [1, 2]
    with pytest.raises(argparse.ArgumentTypeError, match="robot numbers 1-5"):
        guarded("study_planar_fastslam")._robots("6")
