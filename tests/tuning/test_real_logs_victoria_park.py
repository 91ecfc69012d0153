"""Victoria Park's noise learned from the log's start (issue 16, item 1): ``jaxslam tune
victoria-park`` and ``jaxslam dataset victoria-park --params``.

Oracle: central finite differences of the fit window's innovation NLL through the jitted,
block-checkpointed scan with nearest-neighbour association (on the excerpt in tests/data);
the error messages.  The fit on the whole log and its held-out figures are in
docs/datasets.md (protocol there).
"""

import json
import pathlib
import re

import pytest
from central_differences import assert_target_gradient

from jaxslam.errors import InputError
from jaxslam.tuning.targets import victoria_park as VT

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


def test_nll_gradient_matches_central_differences():
    tg = VT.victoria_park_noise(data=DATA, t_max=10.0)
    assert assert_target_gradient(tg) < 0 and tg.config["fit_capacity"] >= 32


def test_window_outside_the_log_is_a_clear_error():
    with pytest.raises(InputError, match=r"--window: the fit window must end inside the log \(0 - 20 s\)"):
        VT.victoria_park_noise(data=DATA, t_max=500.0)


def test_tune_victoria_park_writes_a_params_file_that_dataset_reads(tmp_path, run_cli):
    js, po = tmp_path / "tune.json", tmp_path / "noise.json"
    rc, out, err = run_cli(["tune", "victoria-park", "--data", str(DATA), "--window", "10", "--steps", "1",
                            "--json", str(js), "--params-out", str(po)])
    assert rc == 0, err
    rep = json.loads(js.read_text())
    assert rep["scenario"] == "victoria-park" and rep["config"]["fit_window_s"][1] == pytest.approx(10.852)
    assert set(rep["after"]["metrics"]) >= {"ate_m", "nll", "refused_in_fit_window"}
    p = json.loads(po.read_text())
    assert p["dataset"] == "victoria-park" and set(p["noise"]) == {"M_c", "R"}
    ds = tmp_path / "ds.json"
    rc, out, err = run_cli(["dataset", "victoria-park", "--data", str(DATA), "--params", str(po), "--json", str(ds)])
    assert rc == 0, err
    assert json.loads(ds.read_text())["config"]["noise"] == "--params file"
    f = tmp_path / "bad.json"
    f.write_text(json.dumps({"dataset": "victoria-park", "noise": {"Rr": [1.0, 1.0]}}))
    rc, out, err = run_cli(["dataset", "victoria-park", "--data", str(DATA), "--params", str(f)])
    assert rc == 2 and re.search(r"unknown key\(s\) \['Rr'\]", err), err
    rc, out, err = run_cli(["dataset", "victoria-park", "--data", str(DATA), "--filter", "fastslam", "--params",
                            str(po)])
    assert rc == 2 and "fastslam" in err
