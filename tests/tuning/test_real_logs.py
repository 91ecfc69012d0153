"""Noise learned from real logs (issue 16): ``jaxslam tune mrclam`` and ``dataset --params``.

Oracles: central finite differences of the whole-log innovation NLL (the gradient goes
through the jitted, block-checkpointed scan); the unblocked scan (blocks must change no
number); the error messages the issue names.  Accuracy figures of the fit come from the full
logs (docs/datasets.md, protocol there); the excerpts in tests/data check the plumbing.
"""

import json
import pathlib
import shlex

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from central_differences import assert_gradient_matches

from jaxslam.data import presets
from jaxslam.errors import InputError
from jaxslam.systems import planar_ekf_slam as pe
from jaxslam.tuning.targets import mrclam as RL

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def excerpt():
    logs, raw = RL.mrclam_logs(DATA, [1], np.float64)
    return logs


def _item(logs):
    return jax.tree.map(lambda a: jnp.asarray(a[0]), logs)


def test_nll_gradient_matches_central_differences(excerpt):
    item = _item(excerpt)
    base = presets.mrclam_params(1, dtype=jnp.float64, preset="hand")
    theta0 = RL.planar_theta0(base)
    cfg = RL.mrclam_train_config()._replace(block=64)  # several blocks on the excerpt

    def loss(th):
        return RL.planar_nll(RL.planar_physical(th, base), cfg, item)

    assert_gradient_matches(jax.jit(loss), jax.jit(jax.grad(loss))(theta0), theta0)


def test_checkpoint_blocks_change_no_number(excerpt):
    it = _item(excerpt)
    prm = presets.mrclam_params(dtype=jnp.float64)
    a = pe.run(pe.Log(it.dt, it.u, it.z, it.ids, it.mask, it.pose0), presets.mrclam_config(), prm)
    b = pe.run(pe.Log(it.dt, it.u, it.z, it.ids, it.mask, it.pose0), presets.mrclam_config()._replace(block=50), prm)
    # the blocked scan is another XLA program (other fusion, other rounding): equal up to
    # rounding, measured at <= 2.2e-15 relative; a wrong block boundary would differ by far more
    np.testing.assert_allclose(np.asarray(a.pose), np.asarray(b.pose), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.nll), np.asarray(b.nll), rtol=1e-12, atol=1e-12)


def test_fit_window_longer_than_the_log_is_a_clear_error():
    with pytest.raises(InputError, match=r"--window: robot 1's log covers .* shorter than the 900 s"):
        RL.mrclam_logs(DATA, [1], np.float64, t_max=900.0)
    # the excerpt's odometry starts 0.5 s into its ground truth: a shorter window holds no step
    # (it used to surface as merge_events' "reversed window" of t_start and t_end)
    with pytest.raises(InputError, match=r"--window: robot 1's odometry starts 0.5 s .* above 0.5"):
        RL.mrclam_logs(DATA, [1], np.float64, t_max=0.4)


def test_mrclam_target_rejects_overlapping_and_bad_robots(monkeypatch):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)  # data=None would fall back to it
    with pytest.raises(InputError, match="--test-robots"):
        RL.mrclam_noise(data=DATA, robots=(1, 2), test_robots=(2,))
    with pytest.raises(InputError, match=r"MRCLAM robot 7 is not in .*\(found: 1, 2\)"):
        RL.mrclam_noise(data=DATA, robots=(7,), test_robots=())
    with pytest.raises(InputError, match="--data"):
        RL.mrclam_noise(data=None)


def test_tune_mrclam_writes_a_params_file_that_dataset_reads(tmp_path, run_cli):
    js, po = tmp_path / "tune.json", tmp_path / "noise.json"
    rc, out, err = run_cli(["tune", "mrclam", "--data", str(DATA), "--robots", "1", "--test-robots", "2",
                            "--window", "10", "--steps", "2", "--json", str(js), "--params-out", str(po)])
    assert rc == 0, err
    rep = json.loads(js.read_text())
    assert rep["scenario"] == "mrclam" and rep["config"]["test_robots"] == [2]
    assert rep["config"]["t_max_s"] == 10.0
    assert len(rep["history"]) == 3 and all(np.isfinite(h["loss"]) for h in rep["history"])
    assert set(rep["after"]["metrics"]) >= {"ate_m", "nll"}
    p = json.loads(po.read_text())
    assert p["dataset"] == "mrclam" and {"M_c", "R", "Q_floor", "range_model"} <= set(p["noise"])
    # the printed command names the file written and the folder given: run as printed
    line = next(ln for ln in out.splitlines() if ln.startswith("run the tuned parameters: "))
    printed = shlex.split(line.split(": ", 1)[1])
    assert printed[0] == "jaxslam" and printed[printed.index("--params") + 1] == str(po)
    assert printed[printed.index("--data") + 1] == str(DATA)
    for argv in (printed[1:], ["dataset", "mrclam", "--data", str(DATA), "--robot", "2", "--params", str(js)]):
        rc, out, err = run_cli([*argv, "--json", str(tmp_path / "ds.json")])  # the params file, the whole report
        assert rc == 0, err
        ds = json.loads((tmp_path / "ds.json").read_text())
        assert ds["config"]["noise"] == "--params file"
        # the tune table's "after" ATE is the dataset command's (scored at the ground-truth samples)
        assert ds["metrics"]["ate_m"] == pytest.approx(rep["after"]["metrics"]["ate_m"]["per_run"][0], rel=1e-9)
    R = np.asarray(p["noise"]["R"])
    assert np.all(np.linalg.eigvalsh(R) > 0)


@pytest.mark.parametrize("doc, match", [
    ({"dataset": "victoria-park", "noise": {}}, "key 'dataset' is 'victoria-park'"),
    ({"dataset": "mrclam", "noise": {"R_typo": [1.0, 1.0]}}, r"unknown key\(s\) \['R_typo'\]"),
    ({"dataset": "mrclam", "noise": {}, "sigma": 1}, r"unknown key\(s\) \['sigma'\]"),
    ({"noise": {}}, r"missing key\(s\) \['dataset'\]"),
    ({"dataset": "mrclam", "noise": {"R": [0.1, -1.0]}}, "--params: noise.R"),
])
def test_dataset_params_errors_name_the_key(tmp_path, run_cli, doc, match):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(doc))
    rc, out, err = run_cli(["dataset", "mrclam", "--data", str(DATA), "--params", str(f)])
    assert rc == 2
    assert len(err.strip().splitlines()) == 1
    import re

    assert re.search(match, err), err


def test_params_do_not_apply_to_other_datasets_or_fastslam(tmp_path, run_cli):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"dataset": "mrclam", "noise": {}}))
    rc, _, err = run_cli(["dataset", "plaza", "--data", str(DATA), "--params", str(f)])
    assert rc == 2 and "--params" in err
    rc, _, err = run_cli(["dataset", "mrclam", "--data", str(DATA), "--filter", "fastslam", "--params", str(f)])
    assert rc == 2 and "fastslam" in err


def test_a_diverged_run_warns_in_one_line_and_says_so_in_the_json(tmp_path, run_cli):
    # R far below the camera's real noise: most sightings of mapped landmarks become outliers
    f = tmp_path / "tiny_r.json"
    f.write_text(json.dumps({"dataset": "mrclam", "noise": {"R": [1e-8, 1e-8]}}))
    js = tmp_path / "ds.json"
    rc, out, err = run_cli(["dataset", "mrclam", "--data", str(DATA), "--robot", "1", "--params", str(f),
                            "--json", str(js), "--quiet"])
    assert rc == 0
    lines = [ln for ln in err.strip().splitlines() if "DIVERGED" in ln]
    assert len(lines) == 1 and "warning" in lines[0]
    doc = json.loads(js.read_text())
    assert "diverged" in doc["counts"]["status_flags"]
    assert doc["metrics"]["outlier_fraction_mapped"] > 0.10
    assert any(n.startswith("DIVERGED") for n in doc["notes"])
    # and the default noise on the same excerpt is not flagged
    rc, out, err = run_cli(["dataset", "mrclam", "--data", str(DATA), "--robot", "1", "--json", str(js),
                            "--quiet"])
    assert rc == 0 and "DIVERGED" not in err
    assert "diverged" not in json.loads(js.read_text())["counts"]["status_flags"]


def test_odometry_delay_is_the_argmin_of_the_training_nll():
    base = presets.mrclam_params(1, dtype=jnp.float64, preset="hand")
    grid = (0.0, 0.1, 0.25)
    best, table = RL.select_odometry_delay(DATA, [1], base, RL.mrclam_train_config(), t_max=10.0, grid=grid)
    assert set(table) == set(grid) and best == min(table, key=table.get)
    # each entry is the NLL of the log built with that delay (value oracle: the scan itself)
    logs, _ = RL.mrclam_logs(DATA, [1], np.float64, 10.0, odometry_delay=0.1)
    it = _item(logs)
    res = pe.run(pe.Log(it.dt, it.u, it.z, it.ids, it.mask, it.pose0), presets.mrclam_config(), base)
    np.testing.assert_allclose(table[0.1], float(np.sum(res.nll) / np.sum(res.nll_dof)), rtol=1e-9)


@pytest.mark.parametrize("log, match", [
    ({"odometry_delay": "x"}, r"log.odometry_delay: expected a number in \[0, 2\]"),
    ({"odometry_delay": 5.0}, r"log.odometry_delay: expected a number in \[0, 2\]"),
    ({"delay": 0.1}, r"log: unknown key\(s\) \['delay'\]"),
])
def test_params_log_options_errors_name_the_key(tmp_path, run_cli, log, match):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"dataset": "mrclam", "noise": {}, "log": log}))
    rc, out, err = run_cli(["dataset", "mrclam", "--data", str(DATA), "--params", str(f)])
    assert rc == 2 and len(err.strip().splitlines()) == 1 and re_search(match, err), err


def re_search(pattern, text):
    import re

    return re.search(pattern, text) is not None
