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

import numpy as np
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
    # the GPS error is split where the held-out NLL is (--window 10), not at the runner's 500 s
    for k in ("ate_t_lt_10s_m", "ate_t_ge_10s_m"):
        assert np.isfinite(rep["after"]["metrics"][k]["mean"]), k
    assert not any("500s" in k for k in rep["after"]["metrics"])
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


def test_split_ate_by_hand():
    from jaxslam.data.runners import split_ate

    ev = {"t": np.array([1.0, 2.0, 3.0, 4.0]), "ref_xy": np.zeros((4, 2)),
          "est_xy": np.array([[3.0, 4.0], [0.0, 1.0], [0.0, 2.0], [6.0, 8.0]])}
    # before 2.5 s: errors 5 and 1 -> sqrt(13); from 2.5 s: 2 and 10 -> sqrt(52)
    assert split_ate(ev, 2.5, "2.5") == pytest.approx({"ate_t_lt_2.5s_m": np.sqrt(13.0),
                                                        "ate_t_ge_2.5s_m": np.sqrt(52.0)}, rel=1e-15)
    assert split_ate(ev, 0.5, "0.5") == pytest.approx({"ate_t_ge_0.5s_m": np.sqrt(130.0 / 4)}, rel=1e-15)
