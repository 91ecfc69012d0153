"""The closed-loop target (``ekfslam3d-* --target loop``): the gradient through simulation,
sensors, EKF-SLAM and the DF-LQR on the estimate against central finite differences; float32;
the CLI end to end (a tuned file flies with ``jaxslam run``) and its usage errors."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli
from jaxslam.tuning.targets import get


# 1 s flights (10 LiDAR frames), every term of the objective switched on (weights off their
# defaults, so the CLI test below sees each flag arrive), both blocks tuned.  The same settings as
# the CLI test's argv and the notebook's reduced size, so the suite compiles these programs once
# (the persistent cache serves the later tests).
SHORT = dict(train_runs=1, test_runs=1, train_duration=1.0, eval_duration=1.0, tune="both", w_mse=1.0,
             w_nees=0.5, tilt_max_deg=2.0, w_u=0.2, w_tilt=5.0)


@pytest.fixture(scope="module")
def short_target():
    return get("ekfslam3d-unknown", "loop", "cost", **SHORT)


@pytest.fixture(scope="module")
def short_grad(short_target):
    """The per-axis target's jitted gradient, one program for the tests below (tracing it again
    costs ~4 s, compiling it ~10 s)."""
    return jax.jit(jax.grad(short_target.loss_fn))


def test_gradient_matches_central_differences(short_target, short_grad):
    tg = short_target
    key = tg.train[0]
    f = jax.jit(tg.loss_fn)
    g = short_grad(tg.theta0, key)
    J0 = float(f(tg.theta0, key))
    assert np.isfinite(J0) and J0 > 0
    h = 1e-5
    worst = 0.0
    g = {name: np.asarray(v) for name, v in g.items()}
    for name, v in tg.theta0.items():
        v = np.asarray(v)
        for i in range(v.shape[0]):
            # the steps in NumPy (eager .at[].add compiled a program per shape)
            tp, tm = dict(tg.theta0), dict(tg.theta0)
            tp[name], tm[name] = v.copy(), v.copy()
            tp[name][i] += h
            tm[name][i] -= h
            fd = (float(f(tp, key)) - float(f(tm, key))) / (2 * h)
            worst = max(worst, abs(float(g[name][i]) - fd) / max(abs(fd), 1e-6 * J0))
    assert set(tg.theta0) == {"Q", "R", "Qimu"}
    assert worst <= 1e-4, worst


def test_per_sensor_noise_is_the_per_axis_noise_tied(short_target, short_grad):
    """``structure="imu_iso"``: one accelerometer and one gyro density, each repeated on its three
    axes.  Its loss equals the per-axis target's at the tied point, and its gradient is the sum of
    the per-axis gradient over each sensor's axes (the chain rule through the tie; the per-axis
    gradient is checked against finite differences above)."""
    iso = get("ekfslam3d-unknown", "loop", "cost", structure="imu_iso", **SHORT)
    assert set(iso.theta0) == {"Q", "R", "Qimu_sensor"} and iso.config["structure"] == "imu_iso"
    tied = dict(iso.theta0)
    tied["Qimu"] = np.repeat(np.asarray(tied.pop("Qimu_sensor")), 3)
    np.testing.assert_allclose(np.asarray(tied["Qimu"]), np.asarray(short_target.theta0["Qimu"]), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(iso.physical(iso.theta0)[1].Qimu),
                               np.asarray(short_target.physical(tied)[1].Qimu), rtol=1e-15)
    key = iso.train[0]
    g_iso = jax.jit(jax.grad(iso.loss_fn))(iso.theta0, key)
    g_axis = short_grad(tied, key)
    np.testing.assert_allclose(np.asarray(g_iso["Qimu_sensor"]),
                               np.asarray(g_axis["Qimu"]).reshape(2, 3).sum(axis=1), rtol=1e-9, atol=1e-14)
    for name in ("Q", "R"):
        np.testing.assert_allclose(np.asarray(g_iso[name]), np.asarray(g_axis[name]), rtol=1e-9, atol=1e-14)


def test_tilt_term_is_active_and_weights_enter(short_target):
    # With tilt_max 2 deg the figure-8 start exceeds it, so the soft constraint contributes.
    from jaxslam.tuning.targets import loop

    tg = short_target
    terms = {}
    ctrl, noise = tg.physical(tg.theta0)
    ev = tg.evaluate({"x": (ctrl, noise)})["x"]["metrics"]
    terms = {k: float(np.mean(ev[k])) for k in ("objective", "closed_loop_cost", "tilt_penalty",
                                                 "est_pos_ms_m2", "nees_term")}
    assert terms["tilt_penalty"] > 0
    w = tg.config["weights"]
    want = (terms["closed_loop_cost"] + w["w_tilt"] * terms["tilt_penalty"] + w["w_mse"] * terms["est_pos_ms_m2"]
            + w["w_nees"] * terms["nees_term"])
    assert terms["objective"] == pytest.approx(want, rel=1e-12)
    assert loop.TUNE == ("lqr", "noise", "both")


def test_float32_loss_and_gradient_finite_and_close_to_float64(short_target):
    tg32 = get("ekfslam3d-unknown", "loop", "cost", **SHORT, dtype=jnp.float32)
    key = tg32.train[0]
    v32, g32 = jax.jit(jax.value_and_grad(tg32.loss_fn))(tg32.theta0, key)
    assert v32.dtype == jnp.float32
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g32))
    # The closed-loop cost (tracking + effort) agrees with float64 (measured 1.1e-3 relative: the
    # controller acts on a float32 estimate, so the flights part by its rounding).  The NEES term
    # does not: the 3D filter's covariance itself differs in float32 (jaxslam run ekfslam3d-unknown
    # --duration 5: ANEES 10.5 in float32 against 8.3 in float64), so it is only checked finite.
    m32 = tg32.evaluate({"x": tg32.physical(tg32.theta0)})["x"]["metrics"]
    m64 = short_target.evaluate({"x": short_target.physical(short_target.theta0)})["x"]["metrics"]
    assert float(np.mean(m32["closed_loop_cost"])) == pytest.approx(float(np.mean(m64["closed_loop_cost"])), rel=5e-3)
    assert all(np.all(np.isfinite(np.asarray(m32[k]))) for k in ("objective", "nees_term", "est_pos_ms_m2"))
    assert np.isfinite(float(v32))


def test_cli_loop_end_to_end_and_tuned_file_flies(tmp_path, capsys):
    j, p = tmp_path / "t.json", tmp_path / "p.json"
    rc = cli.main(["tune", "ekfslam3d-unknown", "--target", "loop", "--tune", "both", "--w-nees", "0.5",
                   "--w-mse", "1", "--w-u", "0.2", "--w-tilt", "5", "--tilt-max", "2", "--steps", "2", "--lr", "0.2",
                   "--train-runs", "1", "--test-runs", "1", "--duration", "1", "--eval-duration", "1", "--quiet",
                   "--json", str(j), "--params-out", str(p)])
    err = capsys.readouterr().err
    assert rc == 0, err
    rep = json.loads(j.read_text())
    assert rep["target"] == "loop" and rep["config"]["tune"] == "both" and rep["config"]["mode"] == "unknown"
    w = rep["config"]["weights"]
    assert (w["w_u"], w["w_tilt"], w["tilt_max_deg"], w["w_nees"], w["w_mse"]) == (0.2, 5.0, 2.0, 0.5, 1.0)
    assert set(rep["references"]) == {"q_imu_table2", "after_weights_q_imu"}
    # the result's weights with the --q imu filter: the controller of the result, the noise of the start
    aw = rep["references"]["after_weights_q_imu"]["params"]
    assert aw["controller"] == rep["params_after"]["controller"]
    assert aw["noise"] == rep["references"]["q_imu_table2"]["params"]["noise"] != rep["params_after"]["noise"]
    for label in ("before", "after"):
        m = rep[label]["metrics"]
        assert {"objective", "closed_loop_cost", "max_tilt_deg", "pos_rmse_m", "diverged_flights"} <= set(m)
    # the start is Table 2 with the --q imu filter: the reference row flies the same flights
    np.testing.assert_allclose(rep["before"]["metrics"]["objective"]["per_run"],
                               rep["references"]["q_imu_table2"]["metrics"]["objective"]["per_run"], rtol=1e-12)
    params = json.loads(p.read_text())
    assert set(params) >= {"controller", "noise"}
    out = tmp_path / "run.json"
    rc = cli.main(["run", "ekfslam3d-unknown", "--runs", "1", "--duration", "2", "--quiet", "--params", str(p),
                   "--json", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert np.isfinite(json.loads(out.read_text())["metrics"]["pos_rmse_m"]["median"])


@pytest.mark.parametrize("argv, needle", [
    (["tune", "track-figure8", "--target", "lqr", "--tune", "both"], "--tune"),
    (["tune", "ekfslam3d-unknown", "--target", "noise", "--w-nees", "1"], "--w-nees"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--w-mse", "-1"], "--w-mse"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--tune", "gains"], "--tune"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--loss", "nll"], "--loss"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--compare", "/no/such/file.json"], "--compare"),
    (["tune", "track-figure8", "--target", "lqr", "--tilt-max", "5"], "--tilt-max"),
    (["tune", "ekfslam3d-unknown", "--target", "noise", "--w-tilt", "1"], "--w-tilt"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--w-u", "-1"], "--w-u"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--tilt-max", "95"], "--tilt-max"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--structure", "qc"], "--structure"),
    (["tune", "ekfslam3d-unknown", "--target", "loop", "--structure", "imu_iso"], "--structure"),
    (["tune", "track-figure8", "--target", "lqr", "--structure", "imu"], "--structure"),
])
def test_cli_loop_usage_errors_exit_2_naming_the_flag(argv, needle, capsys):
    assert cli.main(argv) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], lines


def test_compare_file_without_controller_is_refused(tmp_path, capsys):
    f = tmp_path / "noise_only.json"
    f.write_text(json.dumps({"noise": {"R": [1.0, 1.0, 1.0]}}))
    assert cli.main(["tune", "ekfslam3d-unknown", "--target", "loop", "--compare", str(f)]) == 2
    assert "controller" in capsys.readouterr().err


def test_closed_loop_notebook_runs_at_reduced_size(tmp_path, monkeypatch):
    # notebooks/tuning_closed_loop.ipynb, executed in this process at a reduced size (default suite)
    import importlib.util
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[2]
    spec = importlib.util.spec_from_file_location("run_notebook", root / "scripts" / "run_notebook.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.setenv("JAXSLAM_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("JAXSLAM_NOTEBOOK_OUT", str(tmp_path))
    nb, err = mod.execute(root / "notebooks" / "tuning_closed_loop.ipynb", tmp_path / "executed.ipynb")
    assert err is None, err
    text = "".join("".join(o.get("text", [])) for c in nb["cells"] for o in c.get("outputs", []))
    for needle in ("central difference", "training objective", "objective", "q_imu_table2", "max_tilt_deg",
                   "jaxslam run ekfslam3d-unknown"):
        assert needle in text, needle
    assert sum("image/png" in o.get("data", {}) for c in nb["cells"] for o in c.get("outputs", [])) == 1
    params = json.loads((tmp_path / "tuned_closed_loop.json").read_text())
    assert set(params) == {"controller", "noise"} and len(params["controller"]["Q"]) == 7


def test_tilt_angle_is_arccos_form_with_finite_gradient_at_level_flight():
    from jaxslam.tuning.targets.loop import tilt_angle

    # jitted, as the loss uses it: one program per shape (eager, every operation compiled its own)
    tilt = jax.jit(tilt_angle)
    phi = np.array([0.0, 0.2, -0.7])
    theta = np.array([0.0, -0.3, 0.4])
    np.testing.assert_allclose(np.asarray(tilt(phi, theta)), np.arccos(np.cos(phi) * np.cos(theta)),
                               rtol=1e-7, atol=1e-12)
    # a pure roll tilts by |φ|, also where arccos(cos φ) has rounded to 0
    assert float(tilt(-1e-9, 0.0)) == pytest.approx(1e-9, rel=1e-9)
    g = jax.jit(jax.grad(lambda p, t: jnp.sum(tilt_angle(p, t)), argnums=(0, 1)))(np.zeros(3), np.zeros(3))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
    # away from level flight: the derivative of arccos(cos φ cos θ) by central differences
    fd = (float(tilt(0.2 + 1e-6, -0.3)) - float(tilt(0.2 - 1e-6, -0.3))) / 2e-6
    assert float(jax.jit(jax.grad(tilt_angle))(0.2, -0.3)) == pytest.approx(fd, rel=1e-6)
