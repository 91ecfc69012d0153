"""The paper-000 EKF-SLAM scenarios end to end (short flights; the 100-run figures come from
scripts/reproduce_paper000.py and are reported in the README)."""

import json

import numpy as np
from jaxslam import cli


def test_cli_reports_capacity_overflow_with_hidden_ids(tmp_path, capsys):
    out = tmp_path / "run.json"
    argv = ["run", "ekfslam3d-unknown", "--runs", "2", "--duration", "6", "--capacity", "8", "--association", "nn"]
    rc = cli.main(argv + ["--threads", "2", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["config"]["threads"] == 2
    # the two flights ran at once on two threads; one thread gives the same runs, bit for bit
    one = tmp_path / "one.json"
    assert cli.main(argv + ["--threads", "1", "--quiet", "--json", str(one)]) == 0
    seq = json.loads(one.read_text())
    assert seq["config"]["threads"] == 1
    assert seq["metrics"] == res["metrics"] and seq["consistency"] == res["consistency"]
    assert res["flags"]["capacity_overflow"] > 0
    assert "capacity_overflow" in capsys.readouterr().out
    assert res["metrics"]["landmarks_mapped"]["max"] == 8
    assert all(np.isfinite(v) for v in res["metrics"]["pos_rmse_m"]["per_run"])
    assert res["metrics"]["pos_rmse_m"]["max"] < 0.5
    # a 6 s flight has nothing in the settled window (t > 10 s): no figure (null), not 0.0
    for k in ("pos_rmse_settled_m", "vel_rmse_settled_mps", "att_rmse_settled_deg", "track_pos_rmse_settled_m"):
        assert res["metrics"][k]["per_run"] == [None, None], (k, res["metrics"][k])
    # STYLE.md's four keys, plus what each covers (docs/cli.md, "consistency")
    assert set(res["consistency"]) == {"anees", "anees_bounds", "nis_mean", "nis_bounds", "anees_steps_inside",
                                       "anees_block", "anees_dim", "nis_block", "nis_dim"}
    assert res["consistency"]["anees_steps_inside"] == res["consistency_detail"]["anees_fraction_in_bounds"]
    assert res["consistency"]["anees_dim"] == 9 and "robot block" in res["consistency"]["anees_block"]
