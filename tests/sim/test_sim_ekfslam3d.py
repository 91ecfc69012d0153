"""The paper-000 EKF-SLAM scenarios end to end (short flights; the 100-run figures come from
scripts/reproduce_paper000.py and are reported in the README)."""

import json

import numpy as np
import pytest

from jaxslam import cli
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import registry


def _run(name, runs, dtype, **opts):
    sc = registry.get(name)
    options = {o.name: o.default for o in sc.options}
    options.update(opts)
    return sc.run(runs=runs, seed=1, dtype=np.dtype(dtype), options=options, progress=Progress.null())


def test_cli_reports_capacity_overflow_with_hidden_ids(tmp_path, capsys):
    out = tmp_path / "run.json"
    rc = cli.main(["run", "ekfslam3d-unknown", "--runs", "2", "--duration", "6", "--capacity", "8",
                   "--association", "nn", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["flags"]["capacity_overflow"] > 0
    assert "capacity_overflow" in capsys.readouterr().out
    assert res["metrics"]["landmarks_mapped"]["max"] == 8
    assert all(np.isfinite(v) for v in res["metrics"]["pos_rmse_m"]["per_run"])
    assert res["metrics"]["pos_rmse_m"]["max"] < 0.5
    assert set(res["consistency"]) == {"anees", "anees_bounds", "nis_mean", "nis_bounds"}


def test_float32_matches_float64_within_ten_percent():
    r64 = _run("ekfslam3d-unknown", 2, np.float64, duration=6.0, capacity=32)
    r32 = _run("ekfslam3d-unknown", 2, np.float32, duration=6.0, capacity=32)
    assert r32.flags["non_finite"] == 0
    for k in ("pos_rmse_m", "att_rmse_deg"):
        a, b = np.mean(r64.metrics[k]), np.mean(r32.metrics[k])
        assert np.isfinite(b) and abs(b - a) <= 0.1 * a, (k, a, b)
