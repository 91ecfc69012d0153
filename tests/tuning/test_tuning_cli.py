"""``jaxslam tune`` end to end on the cheap linear-Gaussian target; usage errors exit 2."""

import json

import jax
import numpy as np
import pytest

from jaxslam import cli
from jaxslam.cli import tune as tcli


def test_tune_end_to_end_writes_json_params_and_plots(tmp_path, capsys):
    j, p, d = tmp_path / "t.json", tmp_path / "p.json", tmp_path / "plots"
    rc = cli.main(["tune", "linear-gaussian", "--loss", "nll", "--steps", "4", "--train-runs", "1",
                   "--test-runs", "1", "--eval-every", "2", "--json", str(j), "--params-out", str(p),
                   "--plots", str(d)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "held-out evaluation" in out.out and "after" in out.out and "tuned parameters" in out.out
    assert "step    0" in out.err  # progress lines on a non-terminal stream
    rep = json.loads(j.read_text())
    for key in ("scenario", "target", "loss", "before", "after", "params_before", "params_after", "history"):
        assert key in rep
    assert rep["scenario"] == "linear-gaussian" and rep["loss"] == "nll"
    assert len(rep["history"]) == 5 and rep["history"][-1]["step"] == 4
    assert [h["step"] for h in rep["history"] if "test_loss" in h] == [0, 2, 4]
    assert set(rep["before"]["metrics"]["nll"]) >= {"mean", "median", "p95", "max", "per_run"}
    # The tune JSON doubles as a --params file: the tuned parameters sit at its top level.
    assert rep["noise"] == rep["params_after"]["noise"] == json.loads(p.read_text())["noise"]
    assert rep["history"][-1]["loss"] < rep["history"][0]["loss"]
    pngs = sorted(x.name for x in d.iterdir())
    assert len(pngs) == 3 and all(n.endswith(".png") for n in pngs)


def test_a_diverged_training_run_is_named_counted_and_left_out(tmp_path, capsys, monkeypatch):
    """A target whose first training run is NaN at every step: the tune goes on with the other
    runs, says so at every step and at the end, and the JSON counts and names the run."""
    import jax.numpy as jnp

    from jaxslam.tuning import targets

    targets._load()  # the built-in targets registered (available() answers from DECLARED)
    base, losses = targets._FACTORIES[("linear-gaussian", "noise")]

    def poisoned(**kw):
        tg = base(**kw)
        n_tr, n_te = (jax.tree.leaves(b)[0].shape[0] for b in (tg.train, tg.test))

        def loss_fn(theta, item):
            i, log = item
            return jnp.where(i == 0, jnp.nan, tg.loss_fn(theta, log))

        return tg._replace(loss_fn=loss_fn, train=(jnp.arange(n_tr), tg.train),
                           test=(jnp.full(n_te, -1), tg.test))

    monkeypatch.setitem(targets._FACTORIES, ("lg-poisoned", "noise"), (poisoned, losses))
    j = tmp_path / "t.json"
    rc = cli.main(["tune", "lg-poisoned", "--loss", "nll", "--steps", "3", "--train-runs", "3",
                   "--test-runs", "1", "--json", str(j)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    rep = json.loads(j.read_text())
    assert rep["n_dropped_runs"] == 4 and rep["n_skipped"] == 0 and rep["stopped"] is None
    assert [h["dropped_runs"] for h in rep["history"]] == [[0]] * 4
    assert rep["history"][-1]["loss"] < rep["history"][0]["loss"]  # the other two runs still train
    assert out.err.count("training run(s) 0 non-finite or exploding") == 4
    assert "warning: 4 training run(s)" in out.err


@pytest.mark.parametrize("argv, needle", [
    (["tune", "no-such"], "no-such"),
    (["tune", "track-figure8", "--target", "noise"], "--target"),
    (["tune", "track-figure8", "--loss", "nll"], "--loss"),
    # without --target a scenario with a noise target tunes the noise (not the loop target)
    (["tune", "ekfslam3d-unknown", "--loss", "cost"], "ekfslam3d-unknown --target noise supports"),
    (["tune", "uwb-circle", "--filter", "ukf"], "--filter"),
    (["tune", "linear-gaussian", "--filter", "pf"], "--filter"),
    (["tune", "linear-gaussian", "--steps", "0"], "--steps"),
    (["tune", "linear-gaussian", "--lr", "-1"], "--lr"),
    (["tune", "linear-gaussian", "--bogus"], "--bogus"),
    # options a target would ignore are refused by name (uwb-* ran its full flight, exit 0)
    (["tune", "uwb-circle", "--duration", "5"], "--duration: uwb-circle --target noise does not use it"),
    (["tune", "uwb-circle", "--eval-duration", "5"], "--eval-duration: uwb-circle --target noise does not"),
    (["tune", "uwb-square", "--no-checkpoint"], "--no-checkpoint: uwb-square --target noise does not"),
    (["tune", "linear-gaussian", "--cov", "chol"], "--cov: linear-gaussian --target noise does not use it"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--cov", "chol"], "--cov: ekfslam3d-unknown --target loop"),
    (["tune", "track-figure8", "--cov", "chol"], "--cov: track-figure8 --target lqr does not use it"),
])
def test_usage_errors_exit_2_one_line(capsys, argv, needle):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_sigma_point_filters_tune_like_the_kf_on_the_linear_oracle(tmp_path, capsys):
    """``--filter ukf|cubature``: on the linear-Gaussian oracle both sigma-point filters are the
    Kalman filter, so NLL tuning through them (gradient through the sigma points) follows the
    EKF's iterates to rounding; the CLI records the filter."""
    from jaxslam.tuning import optimize, targets

    res = {}
    for f in ("ekf", "ukf", "cubature"):
        tg = targets.get("linear-gaussian", "noise", "nll", train_runs=2, test_runs=1, T=300, filter=f)
        res[f] = optimize.fit(tg.loss_fn, tg.theta0, tg.train, 15, 0.3)
    for f in ("ukf", "cubature"):
        for k in res["ekf"].theta:
            np.testing.assert_allclose(np.asarray(res[f].theta[k]), np.asarray(res["ekf"].theta[k]),
                                       rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose([h["loss"] for h in res[f].history], [h["loss"] for h in res["ekf"].history],
                                   rtol=1e-10)
    assert res["ukf"].history[-1]["loss"] < res["ukf"].history[0]["loss"]
    j = tmp_path / "u.json"
    assert cli.main(["tune", "linear-gaussian", "--filter", "ukf", "--steps", "2", "--train-runs", "1",
                     "--test-runs", "1", "--json", str(j), "--quiet"]) == 0, capsys.readouterr().err
    assert json.loads(j.read_text())["config"]["filter"] == "ukf"


def test_default_target_is_noise_where_offered():
    from jaxslam.tuning import targets

    assert targets.default_target("ekfslam3d-unknown") == "noise"
    assert targets.default_target("ekfslam3d-known") == "noise"
    assert targets.default_target("track-figure8") == "lqr"
    assert targets.default_target("no-such") is None


def test_help_lists_targets(capsys):
    assert tcli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "ekfslam3d-unknown --target noise" in out and "track-figure8 --target lqr" in out


def test_tuned_lqr_json_reproduces_its_after_row_with_jaxslam_run(tmp_path, capsys):
    """The tune JSON is a --params file: ``jaxslam run track-figure8 --params`` flies the tuned
    controller and reproduces the held-out 'after' row of the nominal start."""
    j, r = tmp_path / "t.json", tmp_path / "r.json"
    rc = cli.main(["tune", "track-figure8", "--target", "lqr", "--steps", "2", "--train-runs", "1",
                   "--test-runs", "1", "--duration", "1", "--eval-duration", "2", "--eval-every", "0",
                   "--json", str(j), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads(j.read_text())
    assert rep["controller"]["Q"] != rep["params_before"]["controller"]["Q"]  # it moved
    rc = cli.main(["run", "track-figure8", "--duration", "2", "--params", str(j), "--json", str(r), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    run = json.loads(r.read_text())
    for key in ("track_pos_rmse_m", "track_pos_rmse_settled_m"):
        after = rep["after"]["metrics"][f"nominal_{key}"]["mean"]
        got = run["metrics"][key]["mean"]
        if key.endswith("_settled_m"):  # a 2 s flight has no settled window (t > 10 s): null on both sides
            assert got is None and after is None, (key, got, after)
            continue
        assert abs(got - after) <= 1e-9 * max(1.0, abs(after)), key


def test_ekfslam3d_only_flags_are_rejected_elsewhere(capsys):
    assert cli.main(["tune", "linear-gaussian", "--structure", "imu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--structure" in err[0]


def test_float32_tuning_follows_float64(tmp_path, capsys):
    """--float32 runs in float32 end to end; on the same data (cast), float32 and float64 Adam
    trajectories agree."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxslam.tuning import optimize
    from jaxslam.tuning.targets import linear_gaussian as lg

    j = tmp_path / "f32.json"
    assert cli.main(["tune", "linear-gaussian", "--loss", "nll", "--steps", "6", "--train-runs", "1",
                     "--test-runs", "1", "--eval-every", "0", "--json", str(j), "--quiet", "--float32"]) == 0
    rep = json.loads(j.read_text())
    assert rep["config"]["dtype"] == "float32" and rep["history"][-1]["loss"] < rep["history"][0]["loss"]
    # Same data in both precisions: the float64 logs cast to float32.
    tg = lg.linear_gaussian("nll", train_runs=1, test_runs=1, T=2000)
    f32 = lambda t: jax.tree.map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, t)  # noqa: E731
    r64 = optimize.fit(tg.loss_fn, tg.theta0, tg.train, 20, 0.3)
    r32 = optimize.fit(tg.loss_fn, f32(tg.theta0), f32(tg.train), 20, 0.3)
    assert all(a.dtype == jnp.float32 for a in jax.tree.leaves(r32.theta))
    for k in ("Q", "R"):
        np.testing.assert_allclose(np.asarray(r32.theta[k]), np.asarray(r64.theta[k]), rtol=0, atol=2e-3)


def test_declared_targets_are_what_the_modules_register():
    """``targets.DECLARED`` (read by ``jaxslam tune`` before JAX is imported) against the
    registrations of the target modules themselves."""
    from jaxslam.tuning import targets

    targets._load()
    registered = {k: v[1] for k, v in targets._FACTORIES.items()}
    assert {k: registered[k] for k in targets.DECLARED} == targets.DECLARED
    assert set(registered) == set(targets.DECLARED)  # no built-in target left undeclared
    assert targets.available() == dict(sorted(registered.items()))


def test_default_target_is_noise_else_the_first_registered(monkeypatch):
    from jaxslam.tuning import targets

    assert targets.default_target("track-figure8") == "lqr" and targets.default_target("mrclam") == "noise"
    assert targets.default_target("ekfslam3d-unknown") == "noise" and targets.default_target("nope") is None
    monkeypatch.setitem(targets._FACTORIES, ("myscen", "zeta"), (None, ("cost",)))
    monkeypatch.setitem(targets._FACTORIES, ("myscen", "alpha"), (None, ("cost",)))
    assert targets.default_target("myscen") == "zeta"  # registration order, not the sorted one
