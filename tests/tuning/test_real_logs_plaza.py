"""The Plaza range-only SLAM's noise learned from its logs (issue 16, item 1): ``jaxslam tune
plaza`` and ``jaxslam dataset plaza --params``.

Oracles: central finite differences of the innovation NLL through the whole jitted SLAM scan,
the delayed beacon initialisation included (the excerpt's thresholds lowered so that its four
beacons initialise); the error messages.  The fits on the full logs and their held-out figures
are in docs/datasets.md (protocol there).
"""

import json
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from central_differences import assert_gradient_matches

from jaxslam.errors import InputError
from jaxslam.systems import plaza_range as pr
from jaxslam.tuning.targets import plaza as PT

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


def test_nll_gradient_through_the_delayed_initialisation_matches_central_differences():
    (log, _, _), = PT.plaza_logs(DATA, [2])
    base = pr.PARAMS._replace(min_points=8.0, min_spread=0.3, gate=None, nu=PT.NU)
    th0 = jnp.log(jnp.asarray([getattr(base, f) for f in PT.NOISE_FIELDS]))

    def loss(th):
        r = pr.run(log, pr.Config(), base._replace(**{f: jnp.exp(th[i]) for i, f in enumerate(PT.NOISE_FIELDS)}))
        return jnp.sum(r.nll) / jnp.maximum(jnp.sum(r.nll_dof), 1.0), r.n_registered

    (v, n_reg), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(th0)
    assert int(n_reg) == 4  # every beacon initialised inside the excerpt: the path is exercised
    assert_gradient_matches(jax.jit(lambda th: loss(th)[0]), g, th0)


def test_plaza_target_refuses_bad_and_overlapping_sequences():
    with pytest.raises(InputError, match="sequences 1 and 2, got \\[3\\]"):
        PT.plaza_noise(data=DATA, robots=(3,), test_robots=())
    with pytest.raises(InputError, match="--test-robots: \\[1\\] also in --robots"):
        PT.plaza_noise(data=DATA, robots=(1,), test_robots=(1,))
    with pytest.raises(InputError, match="--window: Plaza 1's log covers"):
        PT.plaza_logs(DATA, [1], t_max=1e6)


def test_tune_plaza_writes_a_params_file_that_dataset_reads(tmp_path, run_cli):
    js, po = tmp_path / "tune.json", tmp_path / "noise.json"
    rc, out, err = run_cli(["tune", "plaza", "--data", str(DATA), "--robots", "2", "--test-robots", "1", "--steps", "1",
                            "--json", str(js), "--params-out", str(po)])
    assert rc == 0, err
    rep = json.loads(js.read_text())
    assert rep["scenario"] == "plaza" and rep["config"]["robots"] == [2] and rep["config"]["test_robots"] == [1]
    assert set(rep["after"]["metrics"]) >= {"ate_m", "nll", "map_err_m"}
    assert "hand_gaussian_gated" in rep["references"]
    p = json.loads(po.read_text())
    assert p["dataset"] == "plaza" and p["noise"]["nu"] == PT.NU and p["noise"]["gate"] is None
    ds = tmp_path / "ds.json"
    rc, out, err = run_cli(["dataset", "plaza", "--data", str(DATA), "--robot", "1", "--params", str(po),
                            "--json", str(ds)])
    assert rc == 0, err
    doc = json.loads(ds.read_text())
    assert doc["config"]["noise"] == "--params file" and doc["config"]["noise_values"]["nu"] == PT.NU
    # a UTIL file, an unknown key: exit 2 naming it
    for bad, match in (({"dataset": "util-uwb", "noise": {}}, "key 'dataset' is 'util-uwb'"),
                       ({"dataset": "plaza", "noise": {"alpha": 1.0}}, "unknown key\\(s\\) \\['alpha'\\]")):
        f = tmp_path / "bad.json"
        f.write_text(json.dumps(bad))
        rc, out, err = run_cli(["dataset", "plaza", "--data", str(DATA), "--params", str(f)])
        assert rc == 2 and len(err.strip().splitlines()) == 1
        assert re.search(match, err), err


def test_student_t_slam_in_float32_follows_float64():
    """The Student-t Plaza SLAM (the excerpt, thresholds lowered so its beacons initialise) in
    float32 and float64: positions to 1 cm, the NLL per range to 1e-3 nats, the same beacons."""
    out = {}
    for dt in (jnp.float32, jnp.float64):
        (log, _, _), = PT.plaza_logs(DATA, [2], dt)
        r = pr.run(log, pr.Config(), pr.PARAMS._replace(min_points=8.0, min_spread=0.3, gate=None, nu=PT.NU))
        assert r.pos.dtype == dt and int(r.n_registered) == 4
        out[dt] = (np.asarray(r.pos, np.float64), float(jnp.sum(r.nll) / jnp.sum(r.nll_dof)))
    np.testing.assert_allclose(out[jnp.float32][0], out[jnp.float64][0], atol=1e-2)
    assert abs(out[jnp.float32][1] - out[jnp.float64][1]) < 1e-3
