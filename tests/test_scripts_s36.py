"""Scripts: options by their whole names only, --help and usage errors before JAX loads, the data
folder's ../shared/data default refused in one line when missing, reproduce_paper001 --table-only
with an --out that is not a folder.  Oracles by hand: argparse with allow_abbrev=False answers
'--hel' with "unrecognized arguments"; JAX must not be in sys.modules after a usage error."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest
from script_modules import JAX_PROBE as _PROBE, load_script, one_error_line as _one_line

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.stem for p in (ROOT / "scripts").glob("*.py") if p.stem not in ("gen_api", "run_notebook"))


DATA = str(ROOT / "tests" / "data")
REQUIRED = {"reproduce_datasets": ["--data", DATA], "reproduce_plaza_smoothing": ["--data", DATA],
            "study_association_compare": ["vp"], "study_mrclam_fastslam": ["robust"],
            "study_util_anchor_bias": ["0.1", "5", "none"]}


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_refuses_an_abbreviated_option(script, capsys):
    # '--hel' was read as --help (exit 0, the usage) by every script
    argv = [*REQUIRED.get(script, []), "--hel"]
    line = _one_line(lambda: load_script(script, "s36").main(argv), capsys)
    assert line == f"{script}.py: error: unrecognized arguments: --hel", line


LAZY = ["study_association_compare", "study_covariance_forms", "study_loop_roughness", "study_mrclam_diagnostics",
        "study_mrclam_fastslam", "study_mrclam_hidden_gates", "study_planar_fastslam", "study_util_anisotropic",
        "study_victoria_park_fastslam"]


def _probe(script, *argv, cwd=ROOT, env=None):
    return subprocess.run([sys.executable, "-c", _PROBE, str(ROOT / "scripts" / f"{script}.py"), *argv],
                          capture_output=True, text=True, timeout=300, cwd=cwd, env=env)


@pytest.mark.parametrize("script", LAZY)
@pytest.mark.parametrize("argv, code", [(["--help"], 0), (["--no-such-option"], 2)])
def test_help_and_usage_errors_exit_before_jax_loads(script, argv, code):
    r = _probe(script, *argv)
    assert r.returncode == code, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1] == "no jax", r.stderr[-2000:]


@pytest.mark.parametrize("script, argv, needle", [
    ("study_mrclam_fastslam", ["robust"], "DATA_DIR: '../shared/data' (the default when DATA_DIR is not given) "
                                          "is not a folder; give DATA_DIR"),
    ("study_victoria_park_fastslam", [], "DATA_DIR: '../shared/data' (the default when DATA_DIR is not given) "
                                         "is not a folder; give DATA_DIR"),
    ("study_util_anisotropic", [], "DATA_DIR: '../shared/data' (the default when neither DATA_DIR nor "
                                   "$JAXSLAM_DATA_DIR is given) is not a folder; give DATA_DIR"),
    ("study_util_motion_floor", [], "data: '../shared/data' (the default when neither data nor $JAXSLAM_DATA_DIR "
                                    "is given) is not a folder"),
    ("study_util_imu_vertical", [], "$JAXSLAM_DATA_DIR: not set, and the default data folder '../shared/data' "
                                    "is not a folder"),
])
def test_a_missing_default_data_folder_is_one_line_naming_the_option(tmp_path, script, argv, needle):
    # were: a MissingDataError traceback (anisotropic, imu_vertical), or a line that did not say
    # the folder was the default one
    cwd = tmp_path / "a" / "b"  # ../shared/data does not exist from here
    cwd.mkdir(parents=True)
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAXSLAM_DATA_DIR"}
    r = _probe(script, *argv, cwd=cwd, env=env)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert lines[0].startswith(f"{script}.py: error: {needle}"), lines[0]


def test_a_missing_default_data_folder_still_works_when_it_exists(tmp_path, capsys):
    # the default is kept: from a folder beside shared/data it is found (here: an empty one, so the
    # next check, the dataset's subfolder, answers)
    (tmp_path / "shared" / "data").mkdir(parents=True)
    (tmp_path / "main").mkdir()
    r = _probe("study_mrclam_fastslam", "robust", cwd=tmp_path / "main")
    assert r.returncode == 2 and "DATA_DIR: '../shared/data' holds no mrclam6/ folder" in r.stderr, r.stderr


@pytest.mark.parametrize("out_kind", ["file", "missing"])
def test_paper001_table_only_out_not_a_folder(tmp_path, capsys, out_kind):
    # said "--table-only: no result JSON in FILE", as if the file were a folder
    out = tmp_path / "x.json"
    if out_kind == "file":
        out.write_text("{}")
    line = _one_line(lambda: load_script("reproduce_paper001", "s36").main(["--table-only", "--out", str(out)]),
                     capsys)
    assert line.startswith(f"reproduce_paper001.py: error: --table-only: --out '{out}' is not a folder"), line
    assert (out.read_text() == "{}") if out_kind == "file" else not out.exists()
