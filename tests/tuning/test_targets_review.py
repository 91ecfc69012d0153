"""Reviewed defects of the tuning targets (linear-Gaussian oracle, window_nll, ekfslam3d noise
and loop, figure-8 LQR): each test fails on the code before its fix.

Oracles are independent of the code under test: a NumPy Kalman filter, hand-computed NLLs,
the constant-velocity model written out, the float64 draws rounded to float32.
"""

import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import compilation
from jaxslam.errors import InputError
from jaxslam.tuning import targets as TG
from jaxslam.tuning.targets import ekfslam3d as T3
from jaxslam.tuning.targets import linear_gaussian as LG

R_TRUE = np.asarray(LG.LG_R_TRUE)
Q_TRUE = np.diag(LG.LG_Q_TRUE)


# ------------------------------------------------------------------ 1. singular Q / R in lg_simulate

def test_lg_simulate_with_zero_q_gives_finite_noise_free_motion():
    key = jax.random.PRNGKey(3)
    d = LG.lg_simulate(key, 30, np.zeros((4, 4)), R_TRUE)
    x, z = np.asarray(d["x"]), np.asarray(d["z"])
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(z))
    np.testing.assert_array_equal(x, 0.0)  # x_0 = 0 and no process noise: x_{k+1} = F x_k = 0
    assert np.std(z) > 0.1  # the measurement noise is still drawn
    # no noise on position: p_{k+1} = p_k + dt v_k exactly, while the velocity is a random walk
    d = LG.lg_simulate(key, 30, np.diag([0.0, 0.0, 0.1, 0.2]), R_TRUE)
    x = np.asarray(d["x"])
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(np.asarray(d["z"])))
    F = np.array([[1, 0, LG.LG_DT, 0], [0, 1, 0, LG.LG_DT], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    np.testing.assert_allclose(x[1:, :2], (x[:-1] @ F.T)[:, :2], rtol=0, atol=1e-12)
    assert np.std(np.diff(x[:, 2:], axis=0)) > 0.05
    # a singular R (PSD, the velocity measured exactly)
    d = LG.lg_simulate(key, 30, Q_TRUE, np.diag([0.05, 0.04, 0.0, 0.0]))
    np.testing.assert_allclose(np.asarray(d["z"])[:, 2:], np.asarray(d["x"])[:, 2:], rtol=0, atol=1e-12)


# ------------------------------------------------------------------ 2. window_nll with weight-0 events

def test_window_nll_ignores_nan_on_weight_zero_events_and_takes_lists():
    def res(nll):
        return types.SimpleNamespace(nll=nll, nll_dof=jnp.array([1.0, 0.0, 1.0]))

    nll = jnp.array([1.0, np.nan, 3.0])
    for w in (np.array([1.0, 0.0, 1.0]), [1, 0, 1], [True, False, True], jnp.array([True, False, True])):
        assert float(TG.window_nll(res(nll), w)) == pytest.approx(2.0)  # (1 + 3) / (1 + 1)
    assert TG.heldout_nll(res(nll), np.array([True, False, True])) == pytest.approx(2.0)
    g = jax.grad(lambda v: TG.window_nll(res(v), np.array([1.0, 0.0, 1.0])))(nll)
    np.testing.assert_allclose(np.asarray(g), [0.5, 0.0, 0.5])
    ok = types.SimpleNamespace(nll=jnp.array([1.0, 2.0, 3.0]), nll_dof=jnp.array([1.0, 1.0, 1.0]))
    assert float(TG.window_nll(ok)) == pytest.approx(2.0)


# ------------------------------------------------------------------ 3. make_slam_logs' P0 and duration

@pytest.mark.parametrize("kw, msg", [
    (dict(P0=np.eye(3)), r"^P0: expected shape \(9, 9\)"),
    (dict(P0=np.full((9, 9), np.nan)), r"^P0: "),
    (dict(P0="x"), r"^P0: expected numbers"),
    (dict(P0=-np.diag([1e-4] * 6 + [3e-4] * 3)), r"^P0: "),
    (dict(duration="1"), r"^duration: expected a number"),
])
def test_make_slam_logs_refuses_bad_p0_and_duration(kw, msg):
    args = dict(seed=0, runs=1, duration=0.1)
    args.update(kw)
    with pytest.raises(InputError, match=msg):
        T3.make_slam_logs(**args)


# ------------------------------------------------------------------ 4, 5, 10, 11. factories' arguments up front

@pytest.mark.parametrize("kw, msg", [
    (dict(eval_duration=-1.0), r"^--eval-duration: must be at least 0.1 s"),
    (dict(eval_duration="x"), r"^--eval-duration: "),
    (dict(eval_chunk="x"), r"^eval_chunk: expected"),
    (dict(eval_chunk=2.5), r"^eval_chunk: expected"),
    (dict(eval_chunk=True), r"^eval_chunk: expected"),
    (dict(eval_chunk=0), r"^eval_chunk: expected"),
    (dict(dtype="float7"), r"^dtype: expected a floating dtype"),
    (dict(train_duration="10"), r"^duration: "),
    (dict(mode="known"), r"^mode: "),
])
def test_ekfslam3d_noise_refuses_bad_arguments_before_simulating(kw, msg):
    with pytest.raises(InputError, match=msg):
        TG.get("ekfslam3d-unknown", "noise", "nll", train_runs=1, test_runs=1, **kw)


@pytest.mark.parametrize("kw, msg", [
    (dict(dtype="float7"), r"^dtype: expected a floating dtype"),
    (dict(tilt_max_deg="12"), r"^--tilt-max: "),
    (dict(train_duration="10"), r"^--duration: must be at least"),
    (dict(eval_duration=None), r"^--eval-duration: must be at least"),
    (dict(seed=1.5), r"^seed: expected an int"),
    (dict(mode="known"), r"^mode: "),
])
def test_loop_refuses_bad_arguments_up_front(kw, msg, monkeypatch):
    from jaxslam.sim import simulate

    def compiles(*a, **k):  # the reference grid's program (14.7 s for a bad seed): nothing is checked after it
        raise AssertionError("the flight's reference was compiled before the arguments were checked")

    monkeypatch.setattr(simulate, "controls", compiles)
    with pytest.raises(InputError, match=msg):
        TG.get("ekfslam3d-unknown", "loop", "cost", train_runs=1, test_runs=1, **kw)


# ------------------------------------------------------------------ 6, 11, 12. figure-8 target

@pytest.mark.parametrize("kw, msg", [
    (dict(w_u=float("nan")), r"^w_u: "), (dict(w_u=-1.0), r"^w_u: "), (dict(w_u="0.1"), r"^w_u: "),
    (dict(start_sigma=float("nan")), r"^start_sigma: "), (dict(start_sigma=-0.5), r"^start_sigma: "),
    (dict(feedforward="no"), r"^feedforward: expected True or False"),
    (dict(checkpoint="no"), r"^checkpoint: expected True or False"),
    (dict(dtype="float7"), r"^dtype: expected a floating dtype"),
])
def test_figure8_refuses_bad_arguments(kw, msg):
    with pytest.raises(InputError, match=msg):
        TG.get("track-figure8", "lqr", "cost", train_runs=1, test_runs=1, **kw)


def test_figure8_float32_starts_are_the_float64_starts_rounded():
    t64 = TG.get("track-figure8", "lqr", "cost", train_runs=2, test_runs=1, train_duration=0.2, eval_duration=0.2)
    t32 = TG.get("track-figure8", "lqr", "cost", train_runs=2, test_runs=1, train_duration=0.2, eval_duration=0.2,
                 dtype=jnp.float32)
    x64, x32 = np.asarray(t64.train["x0"]), np.asarray(t32.train["x0"])
    assert x32.dtype == np.float32
    np.testing.assert_allclose(x32, x64.astype(np.float32), rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------ 7. evaluate compiles once

def _np_kf_metrics(Q, R, z, x):
    """NumPy Kalman filter of the oracle model (x_0 = 0, P0 = I): NLL per scalar, RMSEs."""
    F = np.array([[1, 0, LG.LG_DT, 0], [0, 1, 0, LG.LG_DT], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    m, P = np.zeros(4), np.eye(4)
    nll, means = 0.0, []
    for zk in z:
        m, P = F @ m, F @ P @ F.T + Q
        S = P + R
        nu = zk - m
        nll += 0.5 * (nu @ np.linalg.solve(S, nu) + np.linalg.slogdet(S)[1] + 4 * math.log(2 * math.pi))
        K = P @ np.linalg.inv(S)
        m, P = m + K @ nu, (np.eye(4) - K) @ P
        means.append(m)
    err = np.asarray(means) - x
    return (nll / (4 * len(z)), np.sqrt(np.mean(np.sum(err[:, :2] ** 2, 1))),
            np.sqrt(np.mean(np.sum(err[:, 2:] ** 2, 1))))


def test_lg_evaluate_second_call_compiles_nothing_and_matches_a_numpy_filter():
    tg = LG.linear_gaussian("nll", train_runs=1, test_runs=2, T=40)
    phys = {"before": tg.physical(tg.theta0), "true": tg.references["true"]}
    first = tg.evaluate(phys)
    with compilation.account() as acc:
        second = tg.evaluate(phys)
    assert acc.result.programs == 0 and acc.result.trace_s == 0.0, acc.result
    z, x = np.asarray(tg.test["z"]), np.asarray(tg.test["x"])
    for label, m in phys.items():
        Q, R = np.asarray(m["Q"], float), np.asarray(m["R"], float)
        for i in range(2):
            want = _np_kf_metrics(Q, R, z[i], x[i])
            got = [second[label]["metrics"][k][i] for k in ("nll", "pos_rmse_m", "vel_rmse_mps")]
            np.testing.assert_allclose(got, want, rtol=1e-9)
            np.testing.assert_array_equal(first[label]["metrics"]["nll"], second[label]["metrics"]["nll"])


# ------------------------------------------------------------------ 8, 9. lg_run's P0 and z

def test_lg_run_takes_a_p0_list():
    z = np.asarray(LG.lg_simulate(jax.random.PRNGKey(0), 6, Q_TRUE, R_TRUE)["z"])
    P0 = np.diag([2.0, 3.0, 0.5, 0.25])
    a = LG.lg_run(Q_TRUE, R_TRUE, z, P0=P0.tolist())
    b = LG.lg_run(Q_TRUE, R_TRUE, z, P0=P0)
    for u, v in zip(a, b):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-14)
    # first update by hand: prior P = F P0 Fᵀ + Q, S = P + R
    F = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    S = F @ P0 @ F.T + Q_TRUE + R_TRUE
    np.testing.assert_allclose(float(a[2][0]), np.linalg.slogdet(S)[1], rtol=1e-12)


def test_lg_run_refuses_a_nan_z():
    z = np.asarray(LG.lg_simulate(jax.random.PRNGKey(0), 6, Q_TRUE, R_TRUE)["z"])
    zn = z.copy()
    zn[2, 1] = np.nan
    with pytest.raises(InputError, match=r"^z: contains NaN or Inf"):
        LG.lg_run(Q_TRUE, R_TRUE, jnp.asarray(zn))
