"""Paper 004 line-feature EKF-SLAM: model against hand/thesis Jacobians, the NumPy twin, bad input.

Oracles: hand-derived Jacobians (tests/oracles/numpy_lineslam.py, independent of the
autodiff ones the engine uses), the thesis' eq. 4.11-4.14 entries where they are
consistent with the real model, and a dense NumPy EKF replaying the recorded
inputs step by step (1e-9).
"""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.systems import line_slam_004 as LS

import numpy_lineslam as twin  # noqa: E402

RNG = np.random.default_rng(4)
S = np.array([1.2, -0.7, 0.4, -0.1, 0.8, 0.05])
L = np.array([2.5, -2.2])
DT = 0.1


# Model values and Jacobians, each in one compiled program (eager, jacfwd compiled every
# primitive it dispatched).
_motion_and_jac = jax.jit(lambda s: (LS.motion(s, None, DT),
                                     jax.jacfwd(lambda s_: LS.motion(s_, None, DT))(s)))
_observe_and_jac = jax.jit(lambda s, l: (LS.observe(s, l),
                                         jax.jacfwd(LS.observe, argnums=(0, 1))(s, l)))


@jax.jit
def _inverse_round_trip(s, l):
    z = LS.observe(s, l)
    return z, LS.inverse(s, z), jax.jacfwd(LS.inverse, argnums=(0, 1))(s, z)


def test_motion_jacobian_hand_and_thesis_eq_4_11():
    m, F = _motion_and_jac(jnp.asarray(S))
    F = np.asarray(F)
    np.testing.assert_allclose(F, twin.motion_jac(S, DT), atol=1e-14)
    c, s = np.cos(S[4]), np.sin(S[4])
    # eq. 4.11: ∂p/∂V = e^{-θ}Δt (a rotation by the yaw), ∂θ/∂ω = Δt, V and ω constant.
    np.testing.assert_allclose(F[0:2, 2:4], DT * np.array([[c, -s], [s, c]]), atol=1e-15)
    assert F[4, 5] == pytest.approx(DT)
    np.testing.assert_allclose(F[2:4, :], np.eye(6)[2:4], atol=0)
    np.testing.assert_allclose(F[5], np.eye(6)[5], atol=0)
    np.testing.assert_allclose(np.asarray(m), twin.motion(S, DT), atol=1e-15)


def test_observation_jacobian_hand_and_thesis_eq_4_13_4_14():
    z, (Hs, Hl) = _observe_and_jac(jnp.asarray(S), jnp.asarray(L))
    Hs_h, Hl_h = twin.observe_jac(S, L)
    np.testing.assert_allclose(np.asarray(Hs), Hs_h, atol=1e-14)
    np.testing.assert_allclose(np.asarray(Hl), Hl_h, atol=1e-14)
    # Thesis entries consistent with the real model: ∂ρ_s/∂p = −[cos θ_F, sin θ_F]
    # (−e^{−k θ_F}, without the ½), ∂ρ_s/∂ρ_F = 1 and ∂θ_s/∂θ_F = 1 (the "1" of eq. 4.13).
    np.testing.assert_allclose(np.asarray(Hs)[0, :2], -np.array([np.cos(L[1]), np.sin(L[1])]), atol=1e-15)
    assert float(Hl[0, 0]) == 1.0 and float(Hl[1, 1]) == 1.0 and float(Hl[1, 0]) == 0.0
    np.testing.assert_allclose(np.asarray(z), twin.observe(S, L), atol=1e-15)


def test_inverse_round_trip_flip_and_jacobians():
    for s, l in ((S, L), (np.array([3.0, 0.5, 0, 0, -2.5, 0]), np.array([1.0, 0.2]))):
        z, back, (Gs, Gz) = _inverse_round_trip(jnp.asarray(s), jnp.asarray(l))
        z, back = np.asarray(z), np.asarray(back)
        assert back[0] >= 0
        np.testing.assert_allclose(back[0], l[0], atol=1e-12)
        assert abs(np.remainder(back[1] - l[1] + np.pi, 2 * np.pi) - np.pi) < 1e-12
        _, Gs_h, Gz_h = twin.inverse(s, z)
        np.testing.assert_allclose(np.asarray(Gs), Gs_h, atol=1e-13)
        np.testing.assert_allclose(np.asarray(Gz), Gz_h, atol=1e-13)
    # The second case puts the robot beyond the line (ρ_s < 0): the map line is still ρ_F ≥ 0.
    assert float(z[0]) < 0


def test_residual_is_smooth_through_the_rho_flip():
    """A robot crossing the infinite extension of a wall: ρ_s changes sign, the scan fit
    reports (|ρ|, θ ± π), and the innovation must stay small (no 2π or sign jump)."""
    from jaxslam.features.lines import hesse_normalize

    @jax.jit  # one program for the four crossings
    def fit_and_residual(s, l):
        zh = LS.observe(s, l)
        zr, zt = hesse_normalize(zh[0] + 0.003, zh[1] - 0.001)
        return zr, LS.line_residual(jnp.stack([zr, zt]), zh)

    l = jnp.array([1.0, 0.3])
    n = np.array([np.cos(0.3), np.sin(0.3)])
    for d in (-0.02, -1e-4, 1e-4, 0.02):
        s = jnp.asarray(np.r_[n * (1.0 - d), 0, 0, 0.2, 0])
        zr, nu = fit_and_residual(s, l)
        assert float(zr) >= 0
        np.testing.assert_allclose(np.asarray(nu), [0.003, -0.001], atol=1e-12)
    # Angle wrapping: θ near ±π.
    nu = np.asarray(jax.jit(LS.line_residual)(jnp.array([2.0, np.pi - 0.01]),
                                              jnp.array([2.0, -np.pi + 0.01])))
    np.testing.assert_allclose(nu, [0.0, -0.02], atol=1e-12)


def test_validate_params_and_log_errors():
    fp = LS.default_params()
    LS.validate_params(fp)
    with pytest.raises(InputError, match="R_odo"):
        LS.validate_params(fp._replace(R_odo=jnp.zeros((2, 2))))
    with pytest.raises(InputError, match="Q"):
        LS.validate_params(fp._replace(Q=-jnp.eye(6)))
    T, n = 3, LS.Config().spec.n_beams
    log = LS.Log(ranges=np.ones((T, n)), valid=np.ones((T, n), bool), tilt=np.zeros((T, 2)),
                 flow=np.zeros((T, 2)), gyro=np.zeros(T), s0=np.zeros(6))
    LS.validate_log(log)
    with pytest.raises(InputError, match="682"):
        LS.validate_log(log._replace(ranges=np.ones((T, 600))))
    with pytest.raises(InputError, match="valid"):
        LS.validate_log(log._replace(valid=np.ones((T, n))))
    with pytest.raises(InputError, match="s0"):
        LS.validate_log(log._replace(s0=np.full(6, np.nan)))


# --------------------------------------------------------------------------- runs
@pytest.fixture(scope="module")
def short_flight():
    """A recorded 6 s flight of the lineslam-room scenario (float64)."""
    from jaxslam.sim.scenarios import lineslam as sc

    setup = sc.make_setup(duration=6.0)
    cfg = LS.Config(record_inputs=True)
    fp = LS.default_params()
    key = jax.random.PRNGKey(3)
    log = jax.jit(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float64))(key)
    res = LS.run(log, cfg, fp, key=jax.random.PRNGKey(5))
    return setup, cfg, fp, log, res


def test_filter_matches_numpy_twin_step_by_step(short_flight):
    setup, cfg, fp, log, res = short_flight
    inp = jax.tree.map(np.asarray, res.steps.inputs)
    assert inp.used.sum() > 50 and inp.reg.sum() >= 4  # the replay exercises updates and registrations
    (m, P, lines, act), (x_end, P_end) = twin.replay(
        np.asarray(log.s0), np.asarray(log.flow), np.asarray(log.gyro), inp, np.asarray(fp.Q),
        np.asarray(fp.R_odo), np.asarray(fp.P0), cfg.dt, cfg.capacity)
    st = res.steps
    np.testing.assert_array_equal(np.asarray(st.active), act)
    np.testing.assert_allclose(np.asarray(st.mean), m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(st.cov), P, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(st.lines), lines, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(res.final.P), P_end, rtol=0, atol=1e-9)


def test_short_flight_tracks_and_maps(short_flight):
    setup, cfg, fp, log, res = short_flight
    st = res.steps
    e = np.asarray(st.mean)[:, :2] - setup.truth[:, :2]
    assert np.all(np.isfinite(np.asarray(st.cov)))
    assert np.sqrt(np.mean(np.sum(e * e, axis=1))) < 0.05
    assert int(np.asarray(st.active)[-1].sum()) >= 4  # walls in view in the first 6 s (5 measured)
    assert not int(res.final.status) & (errors.NON_FINITE | errors.NOT_PSD)


def test_all_invalid_scans_and_no_walls_in_view_dead_reckon_without_nan(short_flight):
    setup, cfg, fp, log, res = short_flight
    blind = log._replace(ranges=np.full(log.ranges.shape, np.nan, log.ranges.dtype),
                         valid=np.zeros(log.valid.shape, bool))
    r2 = LS.run(blind, cfg, fp, key=jax.random.PRNGKey(5))
    assert not np.asarray(r2.steps.active).any()
    assert np.all(np.isfinite(np.asarray(r2.steps.mean))) and np.all(np.isfinite(np.asarray(r2.steps.cov)))
    # Dead reckoning: the covariance grows.
    assert np.trace(np.asarray(r2.steps.cov)[-1, :2, :2]) > np.trace(np.asarray(res.steps.cov)[-1, :2, :2])


def test_nan_tilt_under_jit_masks_its_scan_and_flags_it(short_flight):
    # The host check refuses a NaN tilt eagerly; traced, the scan is masked and flagged (it used
    # to lose the scan's matches with status 0).
    setup, cfg, fp, log, res = short_flight
    tilt = np.array(log.tilt)
    tilt[4, 0] = np.nan
    bad = log._replace(tilt=jnp.asarray(tilt))
    with pytest.raises(InputError, match=r"^log\.tilt: contains NaN or Inf"):
        LS.run(bad, cfg, fp, key=jax.random.PRNGKey(5))
    r2 = jax.jit(lambda lg: LS.run(lg, cfg, fp, key=jax.random.PRNGKey(5)))(bad)
    status = np.asarray(r2.steps.status)
    assert not status[:4].any() and status[4] & errors.MASKED_INPUT
    assert int(r2.final.status) & errors.MASKED_INPUT
    assert int(r2.steps.n_matched[4]) == 0 and int(res.steps.n_matched[4]) > 0
    np.testing.assert_allclose(np.asarray(r2.steps.mean[:4]), np.asarray(res.steps.mean[:4]), rtol=0, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(r2.steps.mean))) and np.all(np.isfinite(np.asarray(r2.steps.cov)))


def test_float32_run_is_finite_and_tracks():
    from jaxslam.sim.scenarios import lineslam as sc

    setup = sc.make_setup(duration=3.0)
    cfg = LS.Config()
    fp = jax.tree.map(lambda a: a.astype(jnp.float32), LS.default_params())
    log = jax.jit(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float32))(jax.random.PRNGKey(3))
    res = LS.run(log, cfg, fp, key=jax.random.PRNGKey(5))
    st = res.steps
    assert st.mean.dtype == jnp.float32 and st.cov.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(st.cov)))
    e = np.asarray(st.mean)[:, :2] - setup.truth[:, :2]
    assert np.sqrt(np.mean(np.sum(e * e, axis=1))) < 0.05
    assert int(np.asarray(st.active)[-1].sum()) >= 3


def test_run_and_step_require_a_key_and_check_the_log():
    T, n = 3, LS.Config().spec.n_beams
    log = LS.Log(ranges=np.ones((T, n)), valid=np.ones((T, n), bool), tilt=np.zeros((T, 2)),
                 flow=np.zeros((T, 2)), gyro=np.zeros(T), s0=np.zeros(6))
    key = jax.random.PRNGKey(0)
    with pytest.raises(InputError, match="key"):
        LS.run(log, key=None)
    with pytest.raises(InputError, match="key"):
        LS.step(None, None, LS.Config(), None, key=None)
    with pytest.raises(InputError, match=r"log\.ranges.*682"):
        LS.run(log._replace(ranges=np.ones((T, 600))), key=key)
    with pytest.raises(InputError, match=r"log\.gyro"):
        LS.run(log._replace(gyro=np.zeros((T, 1))), key=key)
    with pytest.raises(InputError, match=r"log\.s0"):
        LS.run(log._replace(s0=np.full(6, np.nan)), key=key)
    with pytest.raises(InputError, match=r"params\.R_odo"):
        LS.run(log, params=LS.default_params()._replace(R_odo=jnp.zeros((3, 3))), key=key)


# --------------------------------------------------------------------------- review 2026-12-07
def test_run_names_a_key_that_is_not_a_prng_key():
    # each failed with a bare JAX error; step and the other systems name it
    T, n = 3, LS.Config().spec.n_beams
    log = LS.Log(ranges=np.ones((T, n)), valid=np.ones((T, n), bool), tilt=np.zeros((T, 2)),
                 flow=np.zeros((T, 2)), gyro=np.zeros(T), s0=np.zeros(6))
    for key in (0, np.int64(7), jax.random.split(jax.random.PRNGKey(0), 2), "seed"):
        with pytest.raises(InputError, match=r"^key: expected a PRNG key"):
            LS.run(log, key=key)


def _wall_log(T=2):
    """A wall at x = 2 m ahead of a still robot: beams within ±50° return 2 / cos(a) (1.999-3.11 m,
    inside the URG-04LX's [0.02, 4] m), the rest no return."""
    spec = LS.Config().spec
    a = spec.angle_min + spec.angle_step * np.arange(spec.n_beams)
    valid = np.abs(a) < np.deg2rad(50.0)
    r = np.where(valid, 2.0 / np.cos(a), np.nan)
    return LS.Log(ranges=np.tile(r, (T, 1)), valid=np.tile(valid, (T, 1)), tilt=np.zeros((T, 2)),
                  flow=np.zeros((T, 2)), gyro=np.zeros(T), s0=np.zeros(6)), valid


def test_ranges_outside_the_laser_limits_are_masked_and_flagged(short_flight):
    """Negated ranges (the wall mirrored to x = -2 m) and 1e6 m returns, marked valid, were mapped
    as lines with status 0.  Now they are not used: no line, the still robot stays at 0, and
    MASKED_INPUT is set; the well-formed log maps the wall (ρ, θ) = (2, 0) with status 0."""
    # the short flight's length and config: its program serves these runs (compiled once for both)
    _, cfg, _, flight_log, _ = short_flight
    T = flight_log.ranges.shape[0]
    log, valid = _wall_log(T)
    fp, key = LS.default_params(), jax.random.PRNGKey(1)
    good = LS.run(log, cfg, fp, key=key)
    act = np.asarray(good.final.active)
    assert act.sum() == 1 and int(good.final.status) == 0
    np.testing.assert_allclose(np.asarray(good.steps.lines)[-1][act][0], [2.0, 0.0], atol=1e-3)
    big = np.array(log.ranges)
    big[:, valid] = 1e6
    for bad in (log._replace(ranges=-np.asarray(log.ranges)), log._replace(ranges=big)):
        r = LS.run(bad, cfg, fp, key=key)
        assert not np.asarray(r.steps.active).any()
        assert np.all(np.asarray(r.steps.status) & errors.MASKED_INPUT)
        np.testing.assert_array_equal(np.asarray(r.steps.mean), 0.0)
    # one beam out of range marks its scan only; the others are used as before
    one = np.array(log.ranges)
    one[1, np.flatnonzero(valid)[0]] = 5.0
    r = LS.run(log._replace(ranges=one), cfg, fp, key=key)
    # (the status word is sticky: the scans after it carry the flag on)
    st = np.asarray(r.steps.status)
    assert st[:2].tolist() == [0, errors.MASKED_INPUT] and np.all(st[1:] == errors.MASKED_INPUT)
    assert int(np.asarray(r.final.active).sum()) == 1
