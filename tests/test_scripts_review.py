"""Review of the example and the reproduction scripts: argument handling, outputs that are
not lost, and the notebook executor.  Everything here is cheap (no reproduction is run:
usage errors stop before any compute, tables are rebuilt from hand-written JSONs)."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _load(rel, name):
    spec = importlib.util.spec_from_file_location(name, ROOT / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _code_cell(src, outputs=None, count=None):
    return {"cell_type": "code", "metadata": {}, "outputs": outputs or [], "execution_count": count,
            "source": src}


def _nb(*cells):
    return {"nbformat": 4, "nbformat_minor": 4, "metadata": {}, "cells": list(cells)}


def _one_error_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --- scripts/run_notebook.py ----------------------------------------------------------------


def test_notebook_magic_inside_a_block_keeps_its_indentation(tmp_path):
    rn = _load("scripts/run_notebook.py", "rn_review")
    src = tmp_path / "a.ipynb"
    src.write_text(json.dumps(_nb(_code_cell("y = 0\nif True:\n    %time\n    y = 41\ny + 1"))))
    nb, err = rn.execute(src, tmp_path / "o.ipynb")
    assert err is None, err
    # the block ran: 41 + 1, as Jupyter (which runs the magic) would show
    assert nb["cells"][0]["outputs"][-1]["data"]["text/plain"] == ["42"]


def test_notebook_trailing_semicolon_hides_the_value_as_in_jupyter(tmp_path):
    rn = _load("scripts/run_notebook.py", "rn_review")
    src = tmp_path / "a.ipynb"
    src.write_text(json.dumps(_nb(_code_cell("x = 3\nx;  # hidden"), _code_cell("x + 1"),
                                  _code_cell("s = 'a;'\ns"))))
    nb, err = rn.execute(src, None)
    assert err is None
    assert nb["cells"][0]["outputs"] == []
    assert nb["cells"][1]["outputs"][0]["data"]["text/plain"] == ["4"]
    assert nb["cells"][2]["outputs"][0]["data"]["text/plain"] == ["'a;'"]


def test_notebook_stale_outputs_after_a_failing_cell_are_cleared(tmp_path):
    rn = _load("scripts/run_notebook.py", "rn_review")
    stale = [{"output_type": "stream", "name": "stdout", "text": ["from an earlier run\n"]}]
    src = tmp_path / "a.ipynb"
    src.write_text(json.dumps(_nb(_code_cell("1 / 0"), _code_cell("print('x')", stale, 7))))
    nb, err = rn.execute(src, src)  # --inplace
    assert err["cell"] == 0
    on_disk = json.loads(src.read_text())
    for cells in (nb["cells"], on_disk["cells"]):
        assert cells[1]["outputs"] == [] and cells[1]["execution_count"] is None


def test_notebook_inplace_write_that_cannot_be_utf8_keeps_a_valid_notebook(tmp_path):
    rn = _load("scripts/run_notebook.py", "rn_review")
    src = tmp_path / "a.ipynb"
    src.write_text(json.dumps(_nb(_code_cell("print('a\\ud800b')"))))
    nb, err = rn.execute(src, src)  # --inplace: the notebook must not be truncated
    assert err is None
    back = json.loads(src.read_text(encoding="utf-8"))
    assert back["cells"][0]["outputs"][0]["text"] == ["a\ud800b\n"]
    assert [p.name for p in tmp_path.iterdir()] == ["a.ipynb"]  # no temporary file left


@pytest.mark.parametrize("content, args, needle", [
    (None, [], "cannot read the notebook"),
    ("{not json", [], ":1: not a JSON notebook"),
    (json.dumps({"nbformat": 3, "cells": []}), [], "only nbformat 4"),
    (json.dumps(_nb()), ["--inplace", "--out", "x.ipynb"], "--inplace and --out"),
    (json.dumps(_nb()), ["--cwd", "no_such_folder"], "--cwd"),
    (json.dumps(_nb(_code_cell("print('ran')"))), ["--out", "no_such_folder/x.ipynb"], "--out"),
])
def test_notebook_cli_usage_errors_exit_2_with_one_line(tmp_path, content, args, needle):
    src = tmp_path / "nb.ipynb"
    if content is not None:
        src.write_text(content)
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "run_notebook.py"), str(src), *args],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert needle in _one_error_line(proc.stderr)
    assert not (tmp_path / "nb.executed.ipynb").exists() and "ran" not in proc.stdout


# --- scripts/reproduce_paper00x.py: usage errors before any compute -------------------------


def _script(num):
    # the scripts call runtime.configure_process() on import (compilation cache, XLA flags):
    # not in this test process, whose settings belong to conftest
    from unittest import mock

    from jaxslam import runtime

    with mock.patch.object(runtime, "configure_process", lambda *a, **k: {}):
        return _load(f"scripts/reproduce_paper{num}.py", f"reproduce_paper{num}_review")


def _main_exit(num, argv, capsys):
    with pytest.raises(SystemExit) as e:
        rc = _script(num).main(argv)
        raise SystemExit(rc)
    return e.value.code, capsys.readouterr().err


def test_paper004_unknown_part_is_a_usage_error_and_keeps_table(tmp_path, capsys):
    (tmp_path / "table.md").write_text("old table\n")
    code, err = _main_exit("004", ["--parts", "atitude", "--out", str(tmp_path)], capsys)
    assert code == 2 and "--parts" in _one_error_line(err)
    assert (tmp_path / "table.md").read_text() == "old table\n"


def test_paper003_empty_scenario_list_is_a_usage_error_and_keeps_table(tmp_path, capsys):
    (tmp_path / "table.md").write_text("old table\n")
    code, err = _main_exit("003", ["--scenarios", ",", "--out", str(tmp_path)], capsys)
    assert code == 2 and "--scenarios" in _one_error_line(err)
    assert (tmp_path / "table.md").read_text() == "old table\n"


@pytest.mark.parametrize("argv, needle", [
    (["--biases", "abc"], "--biases"),
    (["--biases", "0.005,nan"], "--biases"),
    (["--runs", "0"], "--runs"),
    (["--chunk", "0"], "--chunk"),
    (["--particles", "-3"], "--particles"),
    (["--duration", "0"], "--duration"),
])
def test_paper001_bad_options_exit_2_before_any_run(tmp_path, capsys, argv, needle):
    code, err = _main_exit("001", [*argv, "--table-only", "--out", str(tmp_path)], capsys)
    assert code == 2 and needle in _one_error_line(err)


def _fake_001_report(dtype, pos):
    metrics = {k: {"mean": pos, "median": pos, "p95": pos, "max": pos, "per_run": [pos, pos]}
               for k in _script("001").SHOW}
    return {"runs": 2, "dtype": dtype, "config": {"particles": 10, "duration": 1.0}, "metrics": metrics}


def test_paper001_float32_results_have_their_own_files(tmp_path, capsys):
    # float64 results (the shipped layout) and float32 ones side by side: --float32 must
    # tabulate the float32 files, into their own table, and leave table.md alone
    (tmp_path / "table.md").write_text("float64 table\n")
    for name in ("kinematics", "dynamics"):
        (tmp_path / f"bias0.005_{name}.json").write_text(json.dumps(_fake_001_report("float64", 1.25)))
        (tmp_path / f"bias0.005_{name}_f32.json").write_text(json.dumps(_fake_001_report("float32", 3.5)))
    rc = _script("001").main(["--table-only", "--float32", "--biases", "0.005", "--configs",
                              "kinematics,dynamics", "--out", str(tmp_path)])
    assert rc == 0
    table = (tmp_path / "table_f32.md").read_text()
    assert "float32" in table and "| 0.005 | dynamics | 3.5 (3.5)" in table and "1.25" not in table
    assert (tmp_path / "table.md").read_text() == "float64 table\n"


def test_paper001_table_only_refuses_rows_of_different_settings(tmp_path, capsys):
    # the table's header gives one number of runs for every row: rows of 2 and of 5 runs
    (tmp_path / "bias0.005_kinematics.json").write_text(json.dumps(_fake_001_report("float64", 1.0)))
    other = _fake_001_report("float64", 2.0)
    other["runs"] = 5
    (tmp_path / "bias0.005_dynamics.json").write_text(json.dumps(other))
    code, err = _main_exit("001", ["--table-only", "--biases", "0.005", "--configs", "kinematics,dynamics",
                                   "--out", str(tmp_path)], capsys)
    assert code == 2 and "bias0.005_dynamics.json" in _one_error_line(err)
    assert not (tmp_path / "table.md").exists()


# --- scripts/reproduce_paper004.py: one part rebuilt keeps the other in table.md --------------


def _fake_004_jsons(out, runs=3, att_runs=2, seed=0):
    p4 = _script("004")
    m = {"mean": 0.5, "median": 0.5, "p95": 0.75, "max": 1.0}
    for g, t, p in p4.ATT_CASES:
        (out / f"attitude-smc_{g}_{t}_{p}.json").write_text(json.dumps(
            {"runs": att_runs, "seed": seed, "metrics": {k: m for k in p4.ATT_SHOW}}))
    (out / "lineslam-room.json").write_text(json.dumps({
        "runs": runs, "seed": seed, "metrics": {k: m for k in p4.LS_SHOW},
        "consistency": {"anees": 3.0, "anees_bounds": [2.5, 3.5], "nis_mean": 1.0, "nis_bounds": [0.9, 1.1],
                        "anees_steps_inside": 0.9},
        "flags": {}, "timing": {}}))


def test_paper004_one_part_keeps_the_other_part_in_the_table(tmp_path):
    _fake_004_jsons(tmp_path)
    # what docs/papers.md says to run for the attitude part (here from the stored JSONs)
    rc = _script("004").main(["--parts", "attitude", "--table-only", "--runs", "3", "--att-runs", "2",
                              "--out", str(tmp_path)])
    assert rc == 0
    table = (tmp_path / "table.md").read_text()
    assert "| thesis | direct | constant | 0.5 / 0.75" in table
    assert "lineslam-room: 3 runs" in table and "| pos_rmse_m | 0.5 | 0.5 | 0.75 | 1 |" in table


def test_paper004_part_not_run_with_other_runs_is_left_out(tmp_path):
    _fake_004_jsons(tmp_path, runs=5)  # lineslam JSON of 5 runs, the table asks for 3
    rc = _script("004").main(["--parts", "attitude", "--table-only", "--runs", "3", "--att-runs", "2",
                              "--out", str(tmp_path)])
    assert rc == 0
    table = (tmp_path / "table.md").read_text()
    assert "| thesis | direct | constant |" in table and "lineslam-room" not in table


# --- examples/bearing_only_slam.py ------------------------------------------------------------


def test_bearing_only_unusable_plot_path_fails_before_the_run(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "bearing_only_slam.py"), "--quick",
                           "--plot", str(blocker / "run.png")], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = _one_error_line(proc.stderr)
    assert "--plot" in line and "is a file" in line
    assert "robot RMSE" not in proc.stdout  # nothing was computed
