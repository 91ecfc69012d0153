"""The scripts' argument handling in one place (jaxslam.cli.common.ScriptParser and the CLI's
argparse types): every script answers a usage error the same way (one line ``NAME.py: error:
...``, exit code 2, before any compute or output), and refuses the values the CLI refuses.
Each case below behaved differently in one of the per-script copies this replaced.  Nothing
here runs a reproduction: the CLI, the subprocess and the parts are replaced by fakes that fail
the test if reached."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import pytest
from script_modules import guarded_loader, load_script

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"

SCRIPTS = ["gen_api", "reproduce_datasets", "reproduce_paper000", "reproduce_paper001", "reproduce_paper003",
           "reproduce_paper004", "reproduce_plaza_smoothing", "reproduce_tuning", "run_notebook"]


def _one_error_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def guarded(monkeypatch):
    """Loads a script with everything that computes replaced by :func:`_no_compute`."""
    return guarded_loader(monkeypatch, ("render", "smooth_log", "execute", "_execute", "part_oracle", "part_gradcheck",
                                        "part_ekf", "part_lqr", "part_loop", "part_nll_flat", "part_uwb"), "s35")


def _usage_line(mod, argv, capsys):
    with pytest.raises(SystemExit) as e:
        raise SystemExit(mod.main(argv))
    assert e.value.code == 2
    return _one_error_line(capsys.readouterr().err)


REQUIRED = {"reproduce_datasets": ["--data", str(DATA)], "reproduce_plaza_smoothing": ["--data", str(DATA)],
            "run_notebook": ["nb.ipynb"]}


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_answers_an_unknown_option_with_one_line_naming_itself(guarded, capsys, script):
    # reproduce_paper000/003/004 and run_notebook printed argparse's usage block above the error
    line = _usage_line(guarded(script), [*REQUIRED.get(script, []), "--no-such-option"], capsys)
    assert line.startswith(f"{script}.py: error: ") and "--no-such-option" in line


@pytest.mark.parametrize("script, argv, needle", [
    ("reproduce_paper000", ["--runs", "abc"], "--runs"),
    ("reproduce_paper003", ["--runs", "1.5"], "--runs"),
    ("reproduce_paper004", ["--att-runs", "x"], "--att-runs"),
    ("run_notebook", [], "notebook"),  # the notebook not given
])
def test_a_malformed_value_is_one_line_in_every_script(guarded, capsys, script, argv, needle):
    line = _usage_line(guarded(script), argv, capsys)
    assert line.startswith(f"{script}.py: error: ") and needle in line


@pytest.mark.parametrize("script, argv", [
    # a count below 1, a duration not above 0: reproduce_paper001/004 refused them, 000 and 003
    # passed them on to `jaxslam run` (after making --out), which refused them there
    ("reproduce_paper000", ["--runs", "0"]),
    ("reproduce_paper000", ["--chunk", "0"]),
    ("reproduce_paper000", ["--duration", "0"]),
    ("reproduce_paper000", ["--duration", "nan"]),
    ("reproduce_paper003", ["--runs", "0"]),
    # a seed outside [0, 2**63), refused by the CLI: reproduce_paper001 and reproduce_tuning
    # took -1 (the CLI refused it from 000, 003 and 004, after --out was made)
    ("reproduce_paper000", ["--seed", "-1"]),
    ("reproduce_paper001", ["--seed", "-1", "--table-only"]),
    ("reproduce_paper001", ["--seed", str(2**63), "--table-only"]),
    ("reproduce_paper003", ["--seed", "-1"]),
    ("reproduce_paper004", ["--seed", "-1"]),
    ("reproduce_tuning", ["--seed", "-1", "--parts", "oracle", "--cache-dir", ""]),
    # the tuning parts use S + 1 (held-out runs, `jaxslam tune` refuses S = 2**63 - 1) up to S + 7
    # (the gradient check's logs): the largest seed failed with a traceback after earlier parts ran
    ("reproduce_tuning", ["--seed", str(2**63 - 1), "--parts", "oracle", "--cache-dir", ""]),
    ("reproduce_tuning", ["--seed", str(2**63 - 7), "--parts", "gradcheck", "--cache-dir", ""]),
])
def test_values_the_cli_refuses_are_refused_by_every_script_before_any_output(guarded, tmp_path, capsys,
                                                                              script, argv):
    out = tmp_path / "out"
    line = _usage_line(guarded(script), [*argv, "--out", str(out)], capsys)
    assert line.startswith(f"{script}.py: error: argument ") and argv[0] in line
    assert not out.exists()


def test_paper003_unknown_scenario_is_refused_before_the_known_ones_run(guarded, tmp_path, capsys):
    # 'circle,sqare' ran every circle case, then stopped at uwb-sqare (reproduce_paper004 and
    # reproduce_datasets check --parts / --only before any run)
    out = tmp_path / "out"
    line = _usage_line(guarded("reproduce_paper003"), ["--scenarios", "circle,sqare", "--out", str(out)], capsys)
    assert "--scenarios" in line and "'circle,sqare'" in line
    assert not out.exists()


@pytest.mark.parametrize("script, argv, flag", [
    # '' was the current folder: the results (and table.md) were written there, or read from it
    ("reproduce_datasets", ["--data", str(DATA), "--out", ""], "--out"),
    ("reproduce_datasets", ["--data", ""], "--data"),
    ("reproduce_datasets", ["--data", str(DATA), "--plots", ""], "--plots"),
    ("reproduce_paper000", ["--out", ""], "--out"),
    ("reproduce_paper003", ["--out", ""], "--out"),
    ("reproduce_paper004", ["--out", ""], "--out"),
    ("reproduce_tuning", ["--parts", "oracle", "--cache-dir", "", "--out", ""], "--out"),
])
def test_an_empty_path_is_refused_as_the_cli_refuses_it(guarded, tmp_path, monkeypatch, capsys, script, argv,
                                                        flag):
    monkeypatch.chdir(tmp_path)
    line = _usage_line(guarded(script), argv, capsys)
    assert f"argument {flag}: '' is not a path" in line
    assert list(tmp_path.iterdir()) == []


# --- scripts/run_notebook.py --------------------------------------------------------------------

def _notebook(path, src="open('ran.txt', 'w').close()"):
    path.write_text(json.dumps({"nbformat": 4, "nbformat_minor": 4, "metadata": {}, "cells": [
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None, "source": src}]}))
    return path


def _run_notebook(tmp_path, *args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "run_notebook.py"), *args],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)


@pytest.mark.parametrize("args, needle", [
    (["--out", ""], "argument --out: '' is not a path"),  # was: the default NAME.executed.ipynb
    (["--inplace", "--out", ""], "argument --out: '' is not a path"),  # was: --inplace, the --out ignored
    (["--cwd", ""], "argument --cwd: '' is not a path"),  # was: the notebook's folder
    (["--out", "afolder"], "--out: 'afolder' is a folder"),  # was: the cells ran, then a traceback
])
def test_notebook_unusable_output_or_empty_path_exits_2_before_any_cell(tmp_path, args, needle):
    src = _notebook(tmp_path / "nb.ipynb")
    (tmp_path / "afolder").mkdir()
    (tmp_path / "afile").write_text("")
    proc = _run_notebook(tmp_path, str(src), *args)
    assert proc.returncode == 2, proc.stderr
    line = _one_error_line(proc.stderr)
    assert line.startswith("run_notebook.py: error: ") and needle in line
    assert not (tmp_path / "ran.txt").exists()  # no cell ran
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "afolder", "nb.ipynb"]


def test_notebook_is_read_once_and_written_atomically(tmp_path, monkeypatch, capsys):
    rn = load_script("run_notebook", "s35")
    src = _notebook(tmp_path / "nb.ipynb", "print('hello')")
    reads = []
    loads = rn.json.loads
    monkeypatch.setattr(rn.json, "loads", lambda text, *a, **k: reads.append(text) or loads(text, *a, **k))
    # (matplotlib reads its font cache with json.loads too: only the notebook's text is counted)
    from jaxslam import files

    writes = []
    atomic_write = files.atomic_write
    monkeypatch.setattr(files, "atomic_write", lambda path, *a, **k: writes.append(path) or atomic_write(path, *a, **k))
    assert rn.main([str(src), "--out", str(tmp_path / "o.ipynb")]) == 0
    assert reads.count(src.read_text()) == 1  # main validated the notebook and execute() read it a second time
    assert writes == [tmp_path / "o.ipynb"]
    out = json.loads((tmp_path / "o.ipynb").read_text())
    assert out["cells"][0]["outputs"][0]["text"] == ["hello\n"]


@pytest.mark.parametrize("script, argv, needle", [
    # reproduce_paper001 said these with exit code 2 and its name; 003 and 004 exited 1 with a bare
    # "--table-only: ..." line (SystemExit(message))
    ("reproduce_paper003", ["--table-only", "--scenarios", "circle"], "--table-only: "),
    ("reproduce_paper004", ["--table-only", "--parts", "lineslam"], "--table-only: "),
    ("reproduce_paper003", ["--table-only", "--scenarios", "circle", "--runs", "3"], "holds 2 runs with seed 0"),
    ("reproduce_paper004", ["--table-only", "--parts", "lineslam", "--runs", "3"], "holds 2 runs with seed 0"),
])
def test_table_only_without_matching_results_is_a_usage_error_as_in_paper001(guarded, tmp_path, capsys, script,
                                                                              argv, needle):
    if "holds" in needle:  # every result JSON present, of 2 runs
        names = ([f"uwb-circle_{m}_{mo}_{n}_{f}.json" for m, mo, n, f in guarded(script).CASES]
                 if script == "reproduce_paper003" else ["lineslam-room.json"])
        for name in names:
            (tmp_path / name).write_text(json.dumps({"runs": 2, "seed": 0}))
    line = _usage_line(guarded(script), [*argv, "--out", str(tmp_path)], capsys)
    assert line.startswith(f"{script}.py: error: ") and needle in line
    assert not (tmp_path / "table.md").exists()


def test_tuning_script_takes_the_largest_seed_its_parts_can_use():
    # S + 7 must stay a PRNG seed (< 2**63): 2**63 - 8 is the largest S, and it is taken as is
    seed = load_script("reproduce_tuning", "s35")._seed
    assert seed(str(2**63 - 8)) == 2**63 - 8 and seed("0") == 0
