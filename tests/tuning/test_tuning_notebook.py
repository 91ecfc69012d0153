"""The tuning notebook executes (reduced size) and its saved parameters load in the scenario.

Runs ``scripts/run_notebook.py``'s executor in this process (shares the JAX compilation
cache of the test session) with ``JAXSLAM_NOTEBOOK_SMALL=1``.  The execution takes about
1.5 min on a cold 2-core machine, so it is marked ``slow`` (run it with ``-m slow``); the
default suite checks that every code cell compiles and uses only the public API the tuning
tests exercise.
"""

import importlib.util
import json
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
NB = ROOT / "notebooks" / "tuning_ekfslam3d.ipynb"


def _executor():
    spec = importlib.util.spec_from_file_location("run_notebook", ROOT / "scripts" / "run_notebook.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_executor_captures_stdout_values_figures_and_errors(tmp_path):
    nb = {"nbformat": 4, "nbformat_minor": 4, "metadata": {}, "cells": [
        {"cell_type": "markdown", "metadata": {}, "source": ["# t"]},
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None,
         "source": ["x = 20\n", "print('hi', x)\n", "x + 1"]},
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None,
         "source": ["import matplotlib.pyplot as plt\n", "plt.plot([1, 2]); plt.show()"]},
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None,
         "source": ["%matplotlib inline\n", "1 / 0"]},
        {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None, "source": ["print('never')"]},
    ]}
    src = tmp_path / "t.ipynb"
    src.write_text(json.dumps(nb))
    out, err = _executor().execute(src, tmp_path / "o.ipynb")
    cells = json.loads((tmp_path / "o.ipynb").read_text())["cells"]
    assert cells[1]["outputs"][0]["text"] == ["hi 20\n"]
    assert cells[1]["outputs"][1]["data"]["text/plain"] == ["21"]
    assert any("image/png" in o.get("data", {}) for o in cells[2]["outputs"])
    assert cells[3]["outputs"][-1]["ename"] == "ZeroDivisionError"
    assert err == {"cell": 3, "ename": "ZeroDivisionError", "evalue": "division by zero"}
    assert cells[4]["outputs"] == [] and cells[4]["execution_count"] is None


def test_tuning_notebook_cells_compile():
    nb = json.loads(NB.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert len(code) >= 5
    for i, c in enumerate(code):
        src = "".join(c["source"])
        src = "\n".join("" if ln.lstrip().startswith(("%", "!")) else ln for ln in src.splitlines())
        compile(src, f"{NB.name} cell {i}", "exec")
    text = "".join("".join(c["source"]) for c in code)
    assert "jaxslam.tuning" in text or "from jaxslam import tuning" in text


@pytest.mark.slow
def test_tuning_notebook_runs_at_reduced_size(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXSLAM_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("JAXSLAM_NOTEBOOK_OUT", str(tmp_path))
    nb, err = _executor().execute(NB, tmp_path / "executed.ipynb")
    assert err is None, err
    text = "".join("".join(o.get("text", [])) for c in nb["cells"] for o in c.get("outputs", []))
    for needle in ("NLL at Table 7 Q", "tuned Q_c diagonal", "pos_rmse_m", "q_imu", "jaxslam run ekfslam3d-unknown"):
        assert needle in text, needle
    n_png = sum("image/png" in o.get("data", {}) for c in nb["cells"] for o in c.get("outputs", []))
    assert n_png == 2
    # The saved file is a valid --params file for the scenario (the scenario's own parser).
    from jaxslam.sim.scenarios import ekfslam3d

    params = json.loads((tmp_path / "tuned_ekfslam3d.json").read_text())
    noise = ekfslam3d._noise("imu", "unknown", np.float64, params)
    np.testing.assert_allclose(np.asarray(noise.Qc), np.asarray(params["noise"]["Qc"]), rtol=1e-12)
