"""Bad or unusual inputs to jaxslam.dynamics and jaxslam.control: integer promotion, shape, dtype
and value checks (InputError naming the argument), NaN-free derivatives, and flags under jit."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control import attitude_pd, dflqr, flatness, lqr, smc
from jaxslam.control import trajectories as tr
from jaxslam.dynamics import euler_ned, integrators, planar, rotor
from jaxslam.dynamics import params as P
from jaxslam.dynamics import quaternion_quad as qq
from jaxslam.errors import InputError

PP = dflqr.paper000_params()
K = dflqr.gain(PP)
J004 = np.asarray(smc.PAPER004_APPB.inertia)


# ---------------------------------------------------------------- 1. integer inputs promote

def test_integer_inputs_are_promoted_not_truncated():
    np.testing.assert_allclose(rotor.mixer(jnp.array([500, 500, 500, 500]), P.PAPER001),
                               rotor.mixer(jnp.array([500.0] * 4), P.PAPER001))
    np.testing.assert_allclose(rotor.rotor_speeds_from_input(jnp.array([15, 0, 0, 0]), P.PAPER001),
                               rotor.rotor_speeds_from_input(jnp.array([15.0, 0, 0, 0]), P.PAPER001))
    u = jnp.array([20.0, 0, 0, 0])
    xi = integrators.rk4_step(euler_ned.f, jnp.zeros(12, int), u, 0.01, P.PAPER000)
    xf = integrators.rk4_step(euler_ned.f, jnp.zeros(12), u, 0.01, P.PAPER000)
    assert jnp.issubdtype(xi.dtype, jnp.floating) and xi[5] != 0
    np.testing.assert_array_equal(xi, xf)
    xs = integrators.rollout(euler_ned.f, jnp.zeros(12, int), jnp.tile(u, (3, 1)), 0.01, P.PAPER000)
    np.testing.assert_array_equal(xs, integrators.rollout(euler_ned.f, jnp.zeros(12), jnp.tile(u, (3, 1)),
                                                          0.01, P.PAPER000))
    ui, _ = dflqr.control([0] * 12, 3.0, tr.Helix(), K, PP)
    uf, _ = dflqr.control(np.zeros(12), 3.0, tr.Helix(), K, PP)
    np.testing.assert_array_equal(ui, uf)
    g = attitude_pd.PDGains()
    ti = attitude_pd.pd_torque([0, 0, 1], [1, 0, 0], [0, 0, 0], [0, 0, 0], g)
    np.testing.assert_allclose(ti, attitude_pd.pd_torque([0.0, 0, 1], [1.0, 0, 0], [0.0] * 3, [0.0] * 3, g))
    assert jnp.issubdtype(ti.dtype, jnp.floating)
    assert float(smc.law(jnp.array([1, 0, 0, 0, 0, 0]), smc.PROTOTYPE)[0]) != 0
    e = smc.state_error(jnp.array([1, 0, 0, 0]), jnp.zeros(3), smc.QD_CH34)
    assert np.all(np.isfinite(e)) and abs(float(e[2]) + np.pi / 6) < 1e-12
    f_T = flatness.inverse_map(jnp.array([0, 0, -10, 1]), 0.3, 1.56)[0]
    np.testing.assert_allclose(f_T, 15.6)


# ---------------------------------------------------------------- 2. Theorem 3.1 needs Hurwitz

def test_theorem31_refuses_destabilising_K1_and_flags_it_under_jit():
    K1 = -np.asarray(smc.THESIS_SIM.K1)
    K2 = np.asarray(smc.THESIS_SIM.K2)
    with pytest.raises(InputError, match="^K1: .*Hurwitz"):
        smc.theorem31(K1, K2, 0.1, 0.1)
    with pytest.raises(InputError, match="^gains.K1: .*Hurwitz"):
        smc.perturbation_bounds(smc.SMCGains(K1, K2))
    holds = jax.jit(lambda k: smc.theorem31(k, jnp.asarray(K2), 0.1, 0.1).holds)
    assert not bool(holds(jnp.asarray(K1)))
    assert bool(holds(jnp.asarray(smc.THESIS_SIM.K1)))


# ---------------------------------------------------------------- 3. zero-amplitude figure-8

def test_figure8_zero_amplitude_has_finite_derivatives():
    Y = tr.flat_derivatives(tr.Figure8(a_x=0.0, a_y=0.0), 3.0, 4)
    assert np.all(np.isfinite(Y))
    Y = tr.flat_derivatives(tr.Figure8(a_x=0.0, a_y=0.0, heading_along_path=1.0), 3.0, 2)
    assert np.all(np.isfinite(Y))


# ---------------------------------------------------------------- 4. wrong lengths

@pytest.mark.parametrize("call, name", [
    (lambda: rotor.mixer(jnp.array([400.0, 500, 600]), P.PAPER001), "rotor_speeds"),
    (lambda: rotor.rotor_speeds_from_input(jnp.zeros(3), P.PAPER001), "u"),
    (lambda: rotor.f(jnp.zeros(13), jnp.zeros(4), P.PAPER001), "x"),
    (lambda: rotor.f_input(jnp.zeros(12), jnp.zeros(5), P.PAPER001), "u"),
    (lambda: rotor.state_to_ned(jnp.zeros(13)), "x"),
    (lambda: dflqr.control(jnp.zeros(13), 1.0, tr.Figure8(), K, PP), "x_est"),
    (lambda: dflqr.control(jnp.zeros(12), 1.0, tr.Figure8(), K.T, PP), "K"),
    (lambda: qq.to_euler_ned(jnp.zeros(12)), "x"),
    (lambda: qq.from_euler_ned(jnp.zeros(11)), "x"),
    (lambda: flatness.inverse_map(jnp.array([0.0, 0, -9.8]), 0.0, 1.5), "u"),
    (lambda: attitude_pd.pd_torque(jnp.zeros(2), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3),
                                   attitude_pd.PDGains()), "euler"),
    (lambda: smc.law(jnp.zeros(7), smc.PROTOTYPE), "x"),
    (lambda: euler_ned.hover_state((1.0, 2.0)), "position"),
])
def test_wrong_lengths_name_the_argument(call, name):
    with pytest.raises(InputError, match=rf"^{name}: expected shape"):
        call()


def test_shape_checks_are_static_under_jit():
    with pytest.raises(InputError, match="^rotor_speeds: "):
        jax.jit(lambda w: rotor.mixer(w, P.PAPER001))(jnp.zeros(3))


# ---------------------------------------------------------------- 5, 6, 11. CARE inputs

def test_care_refuses_non_finite_complex_and_bool():
    A, B, _ = flatness.linear_model()
    Q, R = np.asarray(PP.Q), np.asarray(PP.R)
    with pytest.raises(InputError, match="^A: contains NaN or Inf"):
        lqr.care(A.at[0, 3].set(jnp.nan), B, Q, R)
    with pytest.raises(InputError, match="^B: contains NaN or Inf"):
        lqr.lqr_gain(A, B.at[3, 0].set(jnp.inf), Q, R)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning before the error
        with pytest.raises(InputError, match="^A: expected a real array"):
            lqr.care(A + 1j * A, B, Q, R)
    with pytest.raises(InputError, match="^Q: expected numbers, got dtype bool"):
        lqr.care(A, B, jnp.eye(7, dtype=bool), R)


def test_care_with_zero_Q_is_not_ok():
    A, B, _ = flatness.linear_model()
    _, ok = lqr.care(A, B, jnp.zeros((7, 7)), np.asarray(PP.R), return_status=True)
    assert not bool(ok)
    _, ok = lqr.care(A, B, np.asarray(PP.Q), np.asarray(PP.R), return_status=True)
    assert bool(ok)
    _, ok = jax.jit(lambda q: lqr.care(A, B, q, jnp.asarray(PP.R), return_status=True))(jnp.zeros((7, 7)))
    assert not bool(ok)


def test_complex_and_bool_are_refused():
    with pytest.raises(InputError, match="^x: expected a real array"):
        euler_ned.f(jnp.zeros(12) + 1j, jnp.zeros(4), P.PAPER000)
    with pytest.raises(InputError, match="^u: expected a real array"):
        euler_ned.f(jnp.zeros(12), jnp.zeros(4) + 1j, P.PAPER000)
    with pytest.raises(InputError, match="^params.mass: "):
        P.validate_params(P.PAPER000._replace(mass=True))
    with pytest.raises(InputError, match="^params.g: "):
        P.validate_params(P.PAPER000._replace(g=9.81 + 0j))


# ---------------------------------------------------------------- 7. SMC eager validation

def _cl(**kw):
    args = dict(xa0=smc.initial_state(), q_d=jnp.asarray(smc.QD_CH34), gains=smc.THESIS_SIM,
                inertia=J004, dt=1e-3, steps=5, key=jax.random.PRNGKey(0), bounds=(0.1, 0.1))
    args.update(kw)
    opts = {k: args.pop(k) for k in ("eps", "tau_max") if k in args}
    return smc.closed_loop(*args.values(), perturbation_name="none", **opts)


@pytest.mark.parametrize("kw, name", [
    ({"eps": 0.0}, "eps"), ({"dt": -1e-3}, "dt"), ({"inertia": -J004}, "inertia"),
    ({"tau_max": -1.0}, "tau_max"),
])
def test_closed_loop_validates_eagerly(kw, name):
    with pytest.raises(InputError, match=f"^{name}: "):
        _cl(**kw)


def test_closed_loop_still_jits_and_vmaps():
    r = _cl()
    f = jax.jit(lambda dt: smc.closed_loop(smc.initial_state(), jnp.asarray(smc.QD_CH34), smc.THESIS_SIM,
                                           J004, dt, 5, jax.random.PRNGKey(0), (0.1, 0.1),
                                           perturbation_name="none").norms)
    np.testing.assert_allclose(f(1e-3), r.norms, rtol=1e-14)
    v = jax.vmap(lambda dt: smc.closed_loop(smc.initial_state(), jnp.asarray(smc.QD_CH34), smc.THESIS_SIM,
                                            J004, dt, 5, jax.random.PRNGKey(0), (0.1, 0.1),
                                            perturbation_name="none").norms)(jnp.array([1e-3, 1e-3]))
    np.testing.assert_allclose(v[1], r.norms, rtol=1e-14)


def test_smc_law_torque_control_check_values():
    with pytest.raises(InputError, match="^eps: "):
        smc.law(jnp.ones(6), smc.PROTOTYPE, eps=0.0)
    with pytest.raises(InputError, match="^tau_max: "):
        smc.torque(jnp.ones(3), jnp.ones(3), J004, tau_max=-1.0)
    with pytest.raises(InputError, match="^inertia: "):
        smc.torque(jnp.ones(3), jnp.ones(3), -J004)
    with pytest.raises(InputError, match="^q: .*nonzero"):
        smc.control(jnp.zeros(4), jnp.zeros(3), jnp.asarray(smc.QD_CH34), smc.THESIS_SIM, J004)


# ---------------------------------------------------------------- 8. gradients at zero error

def test_perturbation_and_closed_loop_gradients_finite_at_zero_error():
    b = (0.5, 1.0)
    for pert in (smc.perturbation_constant, smc.perturbation_sinusoidal, smc.perturbation_random):
        g = jax.jacfwd(lambda x: pert(jax.random.PRNGKey(0), 0.3, x, b))(jnp.zeros(6))
        assert np.all(np.isfinite(g)), pert.__name__
    xa0 = smc.initial_state()

    def norms(w):  # the two norm columns (‖θ_e‖, ‖ω − ω_d‖; ω − ω_d = 0 at the start)
        return _cl(xa0=jnp.concatenate([xa0[:4], w])).norms[:, :2]

    # forward mode: the max|τ| column's derivative is NaN under the test suite's XLA
    # optimisation level 0 (not with the default level), and reverse mode would mix it in
    assert np.all(np.isfinite(jax.jacfwd(norms)(jnp.zeros(3))))


# ---------------------------------------------------------------- 9. unicycle small turns

def test_unicycle_small_turn_float32_and_float64():
    s32 = jnp.zeros(3, jnp.float32)
    for w in (2e-3, 1e-2):  # ω·dt = 2e-4, 1e-3
        u = jnp.array([1.0, w], jnp.float32)
        y = float(planar.unicycle(s32, u, jnp.float32(0.1))[1])
        th = w * 0.1
        truth = 0.1 * 2 * np.sin(th / 2) ** 2 / th
        assert abs(y - truth) <= 1e-5 * truth
        dy = jax.jacfwd(lambda u_: planar.unicycle(s32, u_, jnp.float32(0.1))[1])(u)[1]
        np.testing.assert_allclose(float(dy), 0.1 * 0.1 * 0.5, rtol=1e-3)
    # float64: the same values up to rounding away from the Taylor branch
    w = jnp.asarray(np.linspace(0.05, 3.0, 50))
    s, c = planar._sinc_terms(w)
    np.testing.assert_allclose(c, (1 - np.cos(np.asarray(w))) / np.asarray(w), rtol=1e-12)


# ---------------------------------------------------------------- 10. planar dt and names

def test_planar_checks():
    with pytest.raises(InputError, match="^dt: "):
        planar.step_input_cov(jnp.eye(2), -1.0)
    with pytest.raises(InputError, match="^dt: "):
        planar.input_noise_cov(planar.unicycle, jnp.zeros(3), jnp.ones(2), -0.1, jnp.eye(2))
    with pytest.raises(InputError, match="^input_mode: "):
        planar.step_input_cov(jnp.eye(2), 0.1, "rates")
    with pytest.raises(InputError, match="^name: .*motion"):
        planar.motion_model("bicycle")
    np.testing.assert_array_equal(planar.step_input_cov(jnp.eye(2), 0.0), jnp.eye(2) / 1e-9)


# ---------------------------------------------------------------- 12-14. the rest

@pytest.mark.parametrize("call, name", [
    (lambda: qq.hover_state(q=(0.0, 0.0, 0.0, 0.0)), "q"),
    (lambda: euler_ned.hover_state((1.0, 2.0, np.nan)), "position"),
    (lambda: euler_ned.hover_state(yaw="a"), "yaw"),
    (lambda: attitude_pd.gains_from_bandwidth((0.1, 0.1, 0.1), -10.0, 0.8), "omega_n"),
    (lambda: attitude_pd.gains_from_bandwidth((0.1, 0.1, 0.1), 10.0, -0.8), "zeta"),
    (lambda: dflqr.validate(PP._replace(min_accel=-1.0)), "params.min_accel"),
    (lambda: dflqr.validate(PP._replace(min_accel=np.nan)), "params.min_accel"),
    (lambda: integrators.rk4_step(euler_ned.f, jnp.zeros(12), jnp.zeros(4), "0.1", P.PAPER000), "dt"),
    (lambda: dflqr.control(jnp.zeros(12), "1.0", tr.Figure8(), K, PP), "t"),
    (lambda: integrators.rk4_linearized(lambda y, c: y, jnp.zeros(3), 0.1, skip=1.5), "skip"),
])
def test_lower_priority_checks(call, name):
    with pytest.raises(InputError, match=f"^{name}: "):
        call()


def test_lyapunov_accepts_lists():
    X = lqr.lyapunov([[-1.0, 0.0], [0.0, -2.0]], [[1.0, 0.0], [0.0, 1.0]])
    np.testing.assert_allclose(X, np.diag([0.5, 0.25]))


def test_review_mends_theorem31_with_p_given_sign_switching_and_scalar_dt():
    # theorem31 checked Hurwitz only when it solved P itself: a given P kept holds True
    K1_bad = -np.asarray(smc.THESIS_SIM.K1)
    with pytest.raises(InputError, match="^K1: A − B K1 is not Hurwitz"):
        smc.theorem31(K1_bad, smc.THESIS_SIM.K2, 0.1, 0.1, P=np.asarray(smc.lqr_gains().P1))
    assert not bool(jax.jit(lambda k: smc.theorem31(k, smc.THESIS_SIM.K2, 0.1, 0.1).holds)(K1_bad))
    # eps is the tanh's width: with sign switching it is unused, so 0 is no error
    assert np.all(np.isfinite(np.asarray(smc.law(jnp.ones(6), smc.PROTOTYPE, eps=0.0, switching="sign"))))
    # a zero bandwidth is zero gains (only a negative one is refused)
    assert np.all(np.asarray(attitude_pd.gains_from_bandwidth((0.1, 0.1, 0.1), 0.0, 0.8).kp) == 0)
    # dt: one real number (a NumPy string array and a bool were taken)
    for bad in (np.array("0.1"), True, np.array([0.1, 0.2])):
        with pytest.raises(InputError, match="^dt: "):
            integrators.rk4_step(lambda y, c, p: -y, jnp.ones(2), None, bad, None)


def test_is_hurwitz_against_eigenvalues():
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = rng.normal(size=(4, 4))
        want = bool(np.max(np.linalg.eigvals(A).real) < 0)
        assert bool(lqr.is_hurwitz(A)) == want
        assert bool(lqr.is_hurwitz(A - 5.0 * np.eye(4))) == bool(np.max(np.linalg.eigvals(A).real) < 5.0)
