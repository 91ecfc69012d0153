"""Review fixes of jaxslam.sim.scenarios.{tracking, attitude, ekfslam3d}: expected values by hand
or NumPy, never from the code under test."""

from types import SimpleNamespace as NS

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.sim.scenarios import attitude, ekfslam3d, tracking


def _flight(T=6):
    t = np.arange(T) * 1.0
    return t, np.zeros((T, 12)), np.zeros((T, 4))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_tracking_settle_time_counts_a_nan_error_as_outside(dtype):
    t, truth, ref = _flight()
    truth[0, 0] = 1.0  # outside at t = 0, inside at 1..4
    truth[5, 0] = np.nan  # diverged at the end: it never settled -> the duration, 5 s
    m = tracking.tracking_metrics(jnp.asarray(t, dtype), jnp.asarray(truth, dtype), jnp.asarray(ref, dtype))
    assert float(m["settle_time_s"]) == 5.0
    truth[5, 0] = 0.0
    truth[2, 1] = np.nan  # NaN at t = 2, inside after it: settles at 3 s (not 1 s)
    m = tracking.tracking_metrics(jnp.asarray(t, dtype), jnp.asarray(truth, dtype), jnp.asarray(ref, dtype))
    assert float(m["settle_time_s"]) == 3.0


def test_tracking_metrics_finite_flight_matches_numpy():
    rng = np.random.default_rng(1)
    t = np.arange(21) * 1.0
    truth = rng.normal(size=(21, 12)) * 0.01  # position errors well inside 0.1 m
    ref = rng.normal(size=(21, 4)) * 0.01
    truth[:, 6:9] = rng.normal(size=(21, 3)) * 0.3
    truth[:4, 0] += 1.0  # outside up to t = 3 -> settles at 4 s
    m = tracking.tracking_metrics(jnp.asarray(t), jnp.asarray(truth), jnp.asarray(ref))
    e = truth[:, :3] - ref[:, :3]
    assert np.isclose(float(m["track_pos_rmse_m"]), np.sqrt(np.mean(np.sum(e * e, 1))))
    assert np.isclose(float(m["track_pos_rmse_settled_m"]), np.sqrt(np.mean(np.sum(e[11:] ** 2, 1))))
    tilt = np.degrees(np.max(np.arccos(np.cos(truth[:, 6]) * np.cos(truth[:, 7]))))
    assert np.isclose(float(m["max_tilt_deg"]), tilt)
    assert float(m["settle_time_s"]) == 4.0


def test_tracking_metrics_refuses_mismatched_shapes():
    t, truth, ref = _flight()
    with pytest.raises(InputError, match="^ref: "):  # a (1, 4) reference was broadcast silently
        tracking.tracking_metrics(jnp.asarray(t), jnp.asarray(truth), jnp.asarray(ref[:1]))
    with pytest.raises(InputError, match="^truth: "):
        tracking.tracking_metrics(jnp.asarray(t), jnp.asarray(truth[:, :3]), jnp.asarray(ref))
    with pytest.raises(InputError, match="^t: "):
        tracking.tracking_metrics(jnp.zeros(0), jnp.zeros((0, 12)), jnp.zeros((0, 4)))


@pytest.mark.parametrize("value", [True, np.bool_(True)])
def test_paper000_figure8_refuses_a_bool_altitude_or_ramp(value):
    with pytest.raises(InputError, match="^altitude: "):
        tracking.paper000_figure8(value)
    with pytest.raises(InputError, match="^ramp: "):
        tracking.paper000_figure8(3.0, value)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_attitude_settle_time_counts_a_nan_error_as_above(dtype):
    z = np.zeros(4)
    e = np.array([0.1, 0.0, 0.0, np.nan])  # NaN at the last step: never settled
    m = attitude.metrics(jnp.asarray(np.stack([e, z, z], 1), dtype), 0.5)
    assert np.isnan(float(m["settle_time_s"]))
    e = np.array([np.nan, 0.0, 0.0, 0.0])  # NaN at step 0 (t = 0), then 0: settles at t = 0.5
    m = attitude.metrics(jnp.asarray(np.stack([e, z, z], 1), dtype), 0.5)
    assert float(m["settle_time_s"]) == 0.5
    assert m["settle_time_s"].dtype == jnp.dtype(dtype)


def test_attitude_metrics_refuses_bad_norms_and_dt():
    for bad in (np.zeros((4, 2)), np.zeros((0, 3)), np.zeros(3)):
        with pytest.raises(InputError, match="^norms: "):
            attitude.metrics(jnp.asarray(bad), 0.1)
    for dt in (0.0, -1.0, float("nan"), True):
        with pytest.raises(InputError, match="^dt: "):
            attitude.metrics(jnp.zeros((4, 3)), dt)


def _fake_flight(active, L_hat, ids, T=30, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T + 1) * 1.0
    truth = rng.normal(size=(T + 1, 12)) * 0.1
    mean = truth[1:, :9] + rng.normal(size=(T, 9)) * 0.05
    slam = NS(active=jnp.asarray(active), x=jnp.asarray(np.concatenate([np.zeros(9), L_hat.ravel()])),
              ids=jnp.asarray(ids), overflow=jnp.int32(0), status=jnp.int32(0))
    return NS(t=jnp.asarray(t), truth=jnp.asarray(truth), ref=jnp.zeros((T + 1, 4)),
              est_steps=NS(mean=jnp.asarray(mean)),
              est_final=NS(slam=slam, dropped=jnp.int32(0), masked=jnp.int32(0)),
              est_frames=NS(nees=jnp.zeros(3), nis=jnp.zeros(3), dof=jnp.zeros(3)))


def test_ekfslam3d_landmark_axis_rmse_is_nan_with_nothing_mapped():
    lms = jnp.asarray(np.random.default_rng(2).normal(size=(5, 3)) * 5)
    cfg = NS(mode="unknown", association="nn")
    m = ekfslam3d.evaluate(_fake_flight(np.zeros(4, bool), np.zeros((4, 3)), -np.ones(4, int)), lms, cfg)["metrics"]
    assert float(m["landmarks_mapped"]) == 0.0
    assert np.isnan(float(m["landmark_rmse_m"]))
    assert np.isnan(float(m["landmark_rmse_axis_m"]))  # was 0.0: a perfect map of nothing


@pytest.mark.parametrize("association", ["nn", "known"])
def test_ekfslam3d_landmark_rmse_ignores_a_non_finite_inactive_slot(association):
    rng = np.random.default_rng(3)
    lms = rng.normal(size=(5, 3)) * 5
    active = np.array([1, 1, 0, 1], bool)
    L_hat = lms[[2, 0, 1, 4]] + rng.normal(size=(4, 3)) * 0.1
    L_hat[2] = np.nan  # a stale, inactive slot
    m = ekfslam3d.evaluate(_fake_flight(active, L_hat, np.array([2, 0, -1, 4])), jnp.asarray(lms),
                           NS(mode="unknown", association=association))["metrics"]
    d = L_hat[active] - lms[[2, 0, 4]]
    assert np.isclose(float(m["landmark_rmse_m"]), np.sqrt(np.mean(np.sum(d * d, 1))))
    assert np.isclose(float(m["landmark_rmse_axis_m"]), np.mean(np.sqrt(np.mean(d * d, 0))))
    assert float(m["landmarks_mapped"]) == 3.0
