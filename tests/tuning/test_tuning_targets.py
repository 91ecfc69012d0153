"""Targets: the log filter is the package's filter; NLL terms match the engine; registry; params files."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.sensors import imu as imu_mod
from jaxslam.systems import ekf_slam_3d as sys3d
from jaxslam.tuning import targets as T
from jaxslam.tuning.targets import ekfslam3d as T3
from jaxslam.tuning.targets import figure8 as T8


@pytest.fixture(scope="module")
def logs():
    return T3.make_slam_logs(5, 1, 1.0)


def test_logs_layout_and_first_imu_sample(logs):
    F, L = 10, 40
    assert logs.imu.shape == (1, F * 10 + 1, 6) and logs.y.shape == (1, F, L, 3)
    assert logs.visible.shape == (1, F, L) and logs.truth.shape == (1, F * 10 + 1, 12)
    # Sample 0 is the noise-free reading at the initial hover: specific force −g along body z.
    np.testing.assert_allclose(np.asarray(logs.imu[0, 0]), [0, 0, -9.81, 0, 0, 0], atol=1e-12)
    # The initial estimate is within 6σ of the truth under the --q imu P0.
    e0 = np.asarray(logs.s0[0] - logs.truth[0, 0, :9])
    assert np.all(np.abs(e0) <= 6 * np.sqrt(np.asarray(sys3d.IMU_P0))) and np.any(e0 != 0)


def test_log_run_equals_the_estimator_stepped_by_hand_and_nll_terms(logs):
    """systems.ekf_slam_3d.run (the one open-loop log filter) = the closed-loop estimator's
    propagate/correct called step by step from Python (an independent driver of the same
    functions): same means to 1e-12, and the frames' NLL terms are the updates' own."""
    log = jax.tree.map(lambda a: np.asarray(a)[0], logs)  # run 0 (host slices: no eager dispatch)
    noise = sys3d.imu_noise(imu_mod.PAPER000_IMU)
    cfg = sys3d.Config(capacity=40)
    res = sys3d.run(log, cfg, noise)

    est = sys3d.make_estimator(cfg, noise)
    prop, corr = jax.jit(est.propagate), jax.jit(est.correct)
    from jaxslam.filters import ekf_slam as es

    e = sys3d.State(es.init(jnp.asarray(log.s0), noise.P0, cfg.capacity, 3), jnp.zeros((), jnp.int32),
                    jnp.zeros((), jnp.int32))
    means, nis, dof = [], [], []
    F = log.visible.shape[0]
    for f in range(F):
        for j in range(10):
            k = f * 10 + j
            e = prop(e, jnp.asarray(log.imu[k]), jnp.asarray(log.imu[k + 1]))
            means.append(np.asarray(e.slam.x[:9]))
        e, out = corr(e, jnp.asarray(log.y[f]), jnp.asarray(log.ids), jnp.asarray(log.visible[f]),
                      jnp.asarray(log.truth[(f + 1) * 10]))
        nis.append(float(out.nis))
        dof.append(int(out.dof))
    np.testing.assert_allclose(np.asarray(res.means), np.asarray(means), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.frames.nis), nis, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(res.frames.dof), dof)
    used = np.asarray(res.frames.dof) > 0
    assert used.sum() >= 5
    assert np.all(np.isfinite(np.asarray(res.frames.nees))) and np.all(np.asarray(res.frames.logdet)[used] < 0)
    # without the truth the NEES is not computed (NaN); the estimates are the same (another XLA
    # program: equal to rounding)
    res0 = sys3d.run(log._replace(truth=None), cfg, noise)
    assert np.all(np.isnan(np.asarray(res0.frames.nees)))
    np.testing.assert_allclose(np.asarray(res0.means), np.asarray(res.means), rtol=0, atol=1e-12)


def test_registry_and_errors():
    avail = T.available()
    assert avail[("ekfslam3d-unknown", "noise")] == ("nll", "mse", "nees")
    assert avail[("track-figure8", "lqr")] == ("cost",)
    with pytest.raises(InputError, match="ekfslam3d-unknown --target noise"):
        T.get("no-such-scenario", "noise", "nll")
    with pytest.raises(InputError, match="--loss"):
        T.get("track-figure8", "lqr", "nll")


def test_lqr_target_params_round_trip_through_the_scenario_parser():
    from jaxslam.control import dflqr
    from jaxslam.sim.scenarios.tracking import controller_from_dict

    tg = T8.figure8_lqr(train_runs=1, test_runs=1, train_duration=1.0)
    theta = jax.tree.map(lambda a: a + 0.3, tg.theta0)
    ctrl = tg.physical(theta)
    back = controller_from_dict(tg.to_params(ctrl)["controller"], dflqr.paper000_params())
    np.testing.assert_allclose(np.asarray(back.Q), np.asarray(ctrl.Q), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.R), np.asarray(ctrl.R), rtol=1e-12)
    np.testing.assert_allclose(np.diag(np.asarray(tg.physical(tg.theta0).Q)), [0.01] * 6 + [0.04], rtol=1e-12)
    # Training starts differ from the nominal hover at the origin (random offsets), held-out ones too.
    assert float(jnp.linalg.norm(tg.train["x0"][0, :3])) > 0
    assert not np.allclose(np.asarray(tg.train["x0"]), np.asarray(tg.test["x0"]))


def test_ekfslam3d_structures_start_from_table7_and_map_to_noise_params():
    """--structure qc tunes Q_c (Q_imu = 0); --structure imu tunes Q_imu (Q_c = 0); both start at Table 7."""
    kw = dict(train_runs=1, test_runs=1, train_duration=1.0, eval_duration=1.0)
    qc = T.get("ekfslam3d-unknown", "noise", "mse", **kw)
    imu = T.get("ekfslam3d-unknown", "noise", "mse", structure="imu", **kw)
    n0 = qc.physical(qc.theta0)
    np.testing.assert_allclose(np.diag(np.asarray(n0.Qc)), sys3d.TABLE7_Q, rtol=1e-12)
    assert not np.any(np.asarray(n0.Qimu))
    n1 = imu.physical(jax.tree.map(lambda a: a + 1.0, imu.theta0))  # θ moved: e·Table 7
    np.testing.assert_allclose(np.diag(np.asarray(n1.Qimu)), np.e * np.asarray(sys3d.TABLE7_Q[3:]), rtol=1e-12)
    assert not np.any(np.asarray(n1.Qc))
    assert imu.config["structure"] == "imu" and set(imu.specs) == {"Qimu"}
    # The saved --params form carries both matrices, so the scenario's parser rebuilds the filter.
    from jaxslam.sim.scenarios import ekfslam3d

    back = ekfslam3d._noise("paper", "unknown", np.float64, imu.to_params(n1))
    np.testing.assert_allclose(np.asarray(back.Qimu), np.asarray(n1.Qimu), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.Qc), 0.0)
    iso = T.get("ekfslam3d-unknown", "noise", "mse", structure="imu_iso", **kw)
    n2 = iso.physical(iso.theta0)  # one density per sensor, the means of Table 7's entries
    np.testing.assert_allclose(np.diag(np.asarray(n2.Qimu)), [0.01] * 3 + [0.14] * 3, rtol=1e-12)
    assert iso.describe(iso.theta0)["Qimu_sensor"] == pytest.approx([0.01, 0.14], rel=1e-12)
    with pytest.raises(InputError, match="--structure"):
        T.get("ekfslam3d-unknown", "noise", "mse", structure="bogus", **kw)
    with pytest.raises(InputError, match="--cov diag"):
        T.get("ekfslam3d-unknown", "noise", "mse", structure="imu_iso", cov="chol", **kw)
