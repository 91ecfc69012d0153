"""Guards of the two tuning notebooks' statements (review of 2026-12-07).

Oracles: the stored result files the notebooks cite (docs/results/tuning/*.json), the targets'
own declared settings, and Jupyter's semantics of a trailing ``;`` (it hides a cell's value,
it does not skip the statement).  Parse-only and fast: no notebook is executed here.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import pathlib
import shlex


ROOT = pathlib.Path(__file__).resolve().parents[1]
NB_DIR = ROOT / "notebooks"
RESULTS = ROOT / "docs" / "results" / "tuning"


def _cells(name):
    return json.loads((NB_DIR / name).read_text(encoding="utf-8"))["cells"]


def _src(cell):
    return "".join(cell["source"])


def _full_size_dict(code: str, var: str) -> dict:
    """The literal ``var = dict(...)`` of the ``else:`` branch of ``if SMALL:`` in ``code``."""
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "SMALL":
            for st in node.orelse:
                if isinstance(st, ast.Assign) and st.targets[0].id == var:
                    return {kw.arg: ast.literal_eval(kw.value) for kw in st.value.keywords}
    raise AssertionError(f"no full-size {var} = dict(...) under `if SMALL:`")


def test_closed_loop_notebook_full_size_is_the_loop_both_json_setting():
    """The notebook says its full size is docs/results/tuning/loop_both.json's setting; that run
    tuned one density per sensor (--structure imu_iso), and the notebook's target and its
    command line used to leave it out (the per-axis run, loop_both_per_axis.json)."""
    cells = _cells("tuning_closed_loop.ipynb")
    code = next(_src(c) for c in cells if c["cell_type"] == "code" and "SMALL =" in _src(c))
    target = _full_size_dict(code, "target")
    fit = _full_size_dict(code, "cfg")
    argv = shlex.split(json.loads((RESULTS / "loop_both.json").read_text())["command"])
    flags = {argv[i]: argv[i + 1] for i in range(3, len(argv) - 1, 2)}
    assert argv[:3] == ["jaxslam", "tune", "ekfslam3d-unknown"] and flags["--tune"] == "both"
    expect = {"structure": flags["--structure"], "w_nees": float(flags["--w-nees"]), "w_mse": float(flags["--w-mse"]),
              "train_runs": int(flags["--train-runs"]), "test_runs": int(flags["--test-runs"]),
              "train_duration": float(flags["--duration"])}
    assert {k: target.get(k) for k in expect} == expect
    assert fit == {"steps": int(flags["--steps"]), "lr": float(flags["--lr"])}
    # the command line quoted in the first markdown cell carries every flag of the stored run but
    # --compare (an extra evaluation row) and --seed (its default)
    md = _src(cells[0])
    quoted = next(line for line in md.split("`") if line.startswith("jaxslam tune"))
    q = shlex.split(quoted)
    assert {q[i]: q[i + 1] for i in range(3, len(q) - 1, 2)} == {
        k: v for k, v in flags.items() if k not in ("--compare", "--seed")}


def test_ekfslam3d_notebook_fits_as_the_cli_does():
    """The CLI fits a target with ``sequential=tg.sequential`` (the noise target's logs one after
    another); the notebook, which says the CLI runs the same steps, used to vmap them."""
    code = "\n".join(_src(c) for c in _cells("tuning_ekfslam3d.ipynb") if c["cell_type"] == "code")
    fit_calls = [n for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Call)
                 and isinstance(n.func, ast.Attribute) and n.func.attr == "fit"]
    assert fit_calls and all(any(kw.arg == "sequential" for kw in c.keywords) for c in fit_calls)
    cli = (ROOT / "jaxslam" / "cli" / "tune.py").read_text()
    assert "sequential=tg.sequential" in cli


def test_executor_runs_a_last_expression_that_ends_with_semicolon(tmp_path):
    # fec193e popped the expression to show its value and then never evaluated it behind a ';'
    # (notebooks/tuning_ekfslam3d.ipynb lost its parameter-trajectory figure)
    spec = importlib.util.spec_from_file_location("run_notebook", ROOT / "scripts" / "run_notebook.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    nb = {"nbformat": 4, "nbformat_minor": 4, "metadata": {}, "cells": [
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None,
         "source": ["x = []\n", "x.append(1);"]},
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None, "source": ["print(x)"]},
    ]}
    src = tmp_path / "t.ipynb"
    src.write_text(json.dumps(nb))
    out, err = mod.execute(src, tmp_path / "o.ipynb")
    assert err is None
    assert out["cells"][0]["outputs"] == []  # Jupyter: the value is hidden ...
    assert out["cells"][1]["outputs"][0]["text"] == ["[1]\n"]  # ... but the call ran
