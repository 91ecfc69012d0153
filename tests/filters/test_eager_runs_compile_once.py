"""A whole run called eagerly compiles once per model (``jaxslam.compilation.call_compiled``).

Before, every eager call of a run function re-traced and re-compiled its ``lax.scan``
(0.43-0.56 s for a two-state EKF over 200 steps, against 1.5-3 ms for the compiled program).
Checked here for every generic run function:

* a second eager call with new numbers traces and compiles nothing (JAX's own trace and
  compile events, counted by :func:`jaxslam.compilation.account`);
* its result equals the same run under the caller's own ``jit`` (the uncompiled path: inside a
  transformation nothing is cached) — the oracle is the path that existed before;
* a new length, a new dtype, a model that needs concrete arguments (Python branching) and an
  unhashable model all still give the right answer;
* under ``grad`` / ``vmap`` the plain scan runs (no tracer is cached).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import compilation
from jaxslam.filters import ekf, ekf_slam as es, fastslam as fs, gaussian, smoother, sqrt_ekf, sqrt_ukf, ukf


def f(x, u):
    return jnp.stack([x[0] + 0.05 * x[1], x[1] - 0.05 * 9.81 * jnp.sin(x[0])])


def h(x):
    return jnp.sin(x[:1])


def _data(T=60, seed=0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    return (np.asarray([0.3, 0.0], dtype), (0.1 * np.eye(2)).astype(dtype),
            (0.1 * rng.normal(size=(T, 1))).astype(dtype), rng.random((T, 1)) > 0.1)


Q = 1e-4 * np.eye(2)
R = 0.01 * np.eye(1)
FLT = ekf.make_filter(f, h)

RUNS = {  # name -> run(x0, P0, zs, masks, q) returning an array of means
    "gaussian.run": lambda x0, P0, zs, mk, q: gaussian.run(FLT, x0, P0, None, zs, mk, q * Q, R).means,
    "gaussian.run, make_filter inline": lambda x0, P0, zs, mk, q: gaussian.run(
        ekf.make_filter(f, h, gate=9.0), x0, P0, None, zs, mk, q * Q, R).means,
    "gaussian.run, ukf.make_filter inline": lambda x0, P0, zs, mk, q: gaussian.run(
        ukf.make_filter(f, h, points=ukf.cubature()), x0, P0, None, zs, mk, q * Q, R).means,
    "ekf.filter_scan": lambda x0, P0, zs, mk, q: ekf.filter_scan(f, h, x0, P0, None, zs, mk, q * Q, R,
                                                                 gate=9.0).means,
    "ukf.filter_scan": lambda x0, P0, zs, mk, q: ukf.filter_scan(f, h, x0, P0, None, zs, mk, q * Q, R).means,
    "sqrt_ekf.filter_scan": lambda x0, P0, zs, mk, q: sqrt_ekf.filter_scan(f, h, x0, P0, None, zs, mk, q * Q,
                                                                           R).means,
    "sqrt_ukf.filter_scan": lambda x0, P0, zs, mk, q: sqrt_ukf.filter_scan(f, h, x0, P0, None, zs, mk, q * Q,
                                                                           R).means,
    "smoother.rts": lambda x0, P0, zs, mk, q: smoother.rts(
        gaussian.run(FLT, x0, P0, None, zs, mk, q * Q, R, save_smoother=True)).means,
    "smoother.fixed_lag": lambda x0, P0, zs, mk, q: smoother.fixed_lag(FLT, x0, P0, None, zs, mk, q * Q, R,
                                                                       lag=4).means,
    "smoother.iterated": lambda x0, P0, zs, mk, q: smoother.iterated(f, h, x0, P0, None, zs, mk, q * Q, R,
                                                                     num_iter=2).means,
}


def _jitted(run, *a):
    """The same run under the caller's own jit: the plain (uncached) path."""
    return jax.jit(run)(*a)


@pytest.mark.parametrize("name", sorted(RUNS))
def test_second_eager_call_traces_nothing_and_equals_the_run_under_jit(name):
    run = RUNS[name]
    x0, P0, zs, mk = _data()
    run(x0, P0, zs, mk, 1.0)
    x1, P1, zs1, mk1 = _data(seed=1)
    with compilation.account() as acc:
        out = np.asarray(run(x1, P1, zs1, mk1, 3.0))
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    ref = np.asarray(_jitted(run, x1, P1, zs1, mk1, 3.0))
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-14)
    assert not np.allclose(out, np.asarray(run(x0, P0, zs, mk, 1.0)))  # the new numbers did run


@pytest.mark.parametrize("name", ["ekf.filter_scan", "smoother.fixed_lag", "smoother.iterated"])
def test_a_new_length_and_a_new_dtype_with_the_same_model(name):
    run = RUNS[name]
    run(*_data(T=60), 1.0)
    for T, dt, tol in ((37, np.float64, 1e-12), (37, np.float32, 1e-5)):
        a = _data(T=T, seed=2, dtype=dt)
        out = run(*a, 1.0)
        assert out.shape == (T, 2) and out.dtype == dt
        np.testing.assert_allclose(np.asarray(out), np.asarray(_jitted(run, *a, 1.0)), rtol=tol, atol=tol)


def test_array_arguments_of_the_model_are_arguments_of_the_program_not_constants():
    """A filter made again with new arrays among ``*args`` (or a new gate array) reuses the
    program with the new values — never the first call's, which a program that had baked them
    in as constants would return."""
    def fa(x, u, scale):
        return f(x, u) * scale[0]

    def ha(x, scale):
        return jnp.sin(x[:1]) * scale[1]

    x0, P0, zs, mk = _data()
    outs = []
    for sc in ([1.0, 1.0], [0.99, 2.0], [1.01, 0.5]):
        a = np.asarray(sc)
        with compilation.account() as acc:
            out = gaussian.run(ekf.make_filter(fa, ha, a, gate=np.asarray(9.0)), x0, P0, None, zs, mk, Q, R)
        if outs:
            assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
        ref = jax.jit(lambda a: gaussian.run(ekf.make_filter(fa, ha, a, gate=9.0), x0, P0, None, zs, mk, Q, R))(a)
        np.testing.assert_allclose(np.asarray(out.means), np.asarray(ref.means), rtol=1e-12)
        outs.append(np.asarray(out.means))
    assert not np.allclose(outs[0], outs[1]) and not np.allclose(outs[1], outs[2])


def test_a_model_that_branches_in_python_on_an_argument_still_runs():
    """Arrays among ``*args`` are arguments of the compiled program; a model that needs them
    concrete (Python ``if``) makes JAX raise a concretization error, and the run goes back to
    the uncompiled scan, where they are constants (as before)."""
    def hb(x, sign):
        if float(sign[0]) > 0:  # needs a concrete value
            return jnp.sin(x[:1])
        return -jnp.sin(x[:1])

    def fb(x, u, sign):
        return f(x, u)

    x0, P0, zs, mk = _data()
    for s in (1.0, -1.0, -1.0):
        out = ekf.filter_scan(fb, hb, x0, P0, None, zs, mk, Q, R, np.asarray([s]))
        ref = ekf.filter_scan(f, (lambda x: s * jnp.sin(x[:1])), x0, P0, None, zs, mk, Q, R)
        np.testing.assert_allclose(np.asarray(out.means), np.asarray(ref.means), rtol=1e-12)


def test_a_model_that_slices_with_an_argument_still_runs():
    """A model slicing with an extra argument (``x[:n]``) or indexing with a boolean mask needs it
    concrete; compiled, JAX raises an IndexError (not a TypeError), and the run goes back to the
    uncompiled scan as for a Python branch (it raised 'Slice entries must be static integers')."""
    def hn(x, n):
        return jnp.sin(x[:n])[:1]

    def hm(x, keep):
        return jnp.sin(x[keep])[:1]

    x0, P0, zs, mk = _data()
    ref = ekf.filter_scan(f, lambda x: jnp.sin(x[:1]), x0, P0, None, zs, mk, Q, R)
    for _ in range(3):
        for hx, arg in ((hn, 1), (hm, np.asarray([True, False]))):
            out = ekf.filter_scan(lambda x, u, a: f(x, u), hx, x0, P0, None, zs, mk, Q, R, arg)
            np.testing.assert_allclose(np.asarray(out.means), np.asarray(ref.means), rtol=1e-12)


def test_an_argument_jax_cannot_take_runs_uncompiled():
    """A string array among ``*args`` cannot be an argument of a compiled program (JAX raises a
    TypeError): the run goes back to the uncompiled scan, where the model reads it as before."""
    def hs(x, names):
        return jnp.sin(x[:1]) * (2.0 if names[0] == "double" else 1.0)

    x0, P0, zs, mk = _data()
    for names, scale in ((np.asarray(["double"]), 2.0), (np.asarray(["single"]), 1.0)):
        out = ekf.filter_scan(lambda x, u, n: f(x, u), hs, x0, P0, None, zs, mk, Q, R, names)
        ref = ekf.filter_scan(f, lambda x: scale * jnp.sin(x[:1]), x0, P0, None, zs, mk, Q, R)
        np.testing.assert_allclose(np.asarray(out.means), np.asarray(ref.means), rtol=1e-12)


def test_an_unhashable_model_runs_uncompiled():
    class H:  # __eq__ without __hash__: unhashable, so it cannot key a compiled program
        def __eq__(self, other):
            return isinstance(other, H)

        __hash__ = None

        def __call__(self, x):
            return h(x)

    x0, P0, zs, mk = _data()
    out = ekf.filter_scan(f, H(), x0, P0, None, zs, mk, Q, R)
    np.testing.assert_allclose(np.asarray(out.means), np.asarray(RUNS["ekf.filter_scan"](x0, P0, zs, mk, 1.0)),
                               rtol=1e-12)


def test_under_grad_and_vmap_the_plain_scan_runs():
    x0, P0, zs, mk = _data()
    seen = []

    def loss(q):
        seen.append(compilation.at_top_level())
        return jnp.sum(gaussian.run(FLT, x0, P0, None, zs, mk, q * Q, R).log_likelihood)

    g = jax.grad(loss)(1.0)
    eps = 1e-6
    fd = (loss(1.0 + eps) - loss(1.0 - eps)) / (2 * eps)
    assert float(g) == pytest.approx(float(fd), rel=1e-5)
    assert seen == [False, True, True]
    v = jax.vmap(lambda q: RUNS["gaussian.run"](x0, P0, zs, mk, q))(jnp.asarray([1.0, 2.0]))
    np.testing.assert_allclose(np.asarray(v[1]), np.asarray(RUNS["gaussian.run"](x0, P0, zs, mk, 2.0)),
                               rtol=1e-12)


def _slam_case(T=20, K=3, seed=0):
    model = es.SlamModel(robot_dim=2, lm_dim=2, meas_dim=2, motion=_motion, observe=_observe, inverse=_inverse)
    rng = np.random.default_rng(seed)
    log = es.SlamLog(u=rng.normal(size=(T, 2)) * 0.1, z=rng.normal(size=(T, K, 2)),
                     ids=np.tile(np.arange(K), (T, 1)), mask=np.ones((T, K), bool))
    return model, log


def _motion(s, u, p=None):
    return s + u


def _observe(s, lm, p=None):
    return lm - s


def _inverse(s, z, p=None):
    return s + z


def test_ekf_slam_run_second_eager_call_traces_nothing():
    model, log = _slam_case()
    st = es.init(jnp.zeros(2), jnp.eye(2), 4, 2)
    es.run(model, st, log, 0.01 * np.eye(2), 0.1 * np.eye(2), gate=9.21)
    log2 = _slam_case(seed=1)[1]
    with compilation.account() as acc:
        out = es.run(model, st, log2, 0.02 * np.eye(2), 0.3 * np.eye(2), gate=9.21)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    ref = jax.jit(lambda lg: es.run(model, st, lg, 0.02 * np.eye(2), 0.3 * np.eye(2), gate=9.21))(log2)
    np.testing.assert_allclose(np.asarray(out.robot), np.asarray(ref.robot), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.final.P), np.asarray(ref.final.P), rtol=1e-12, atol=1e-15)


def _sample(pose, aux, key, du):
    return pose + du + 0.02 * jax.random.normal(key, pose.shape, pose.dtype), aux


def test_fastslam_run_second_eager_call_traces_nothing():
    model = fs.LandmarkModel(2, 2, lambda pose, lm, p=None: lm - pose[:2], lambda pose, z, p=None: pose[:2] + z)
    T, N, K = 6, 8, 2
    rng = np.random.default_rng(0)
    u = rng.normal(size=(T, 3)) * 0.1
    zs = rng.normal(size=(T, K, 2))
    masks = np.ones((T, K), bool)
    R = 0.01 * np.eye(2)
    p0 = fs.init(np.zeros(3), N, 4, 2)
    kw = dict(angle_mask=[False, False, True], slot_by_id=True, threshold=0.7)
    fs.run(p0, jax.random.PRNGKey(0), _sample, (u,), model, zs, np.arange(K), masks, R, **kw)
    with compilation.account() as acc:
        out = fs.run(p0, jax.random.PRNGKey(1), _sample, (u * 2,), model, zs, np.arange(K), masks, R, **kw)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    ref = jax.jit(lambda k, uu: fs.run(p0, k, _sample, (uu,), model, zs, np.arange(K), masks, R, **kw))(
        jax.random.PRNGKey(1), u * 2)
    np.testing.assert_allclose(np.asarray(out.pose_mean), np.asarray(ref.pose_mean), rtol=1e-12)


# --- one step at a time: a Python loop of eager predict / update calls ------------------------

def _belief(mod, x0, P0):
    if mod in (sqrt_ekf, sqrt_ukf):
        return sqrt_ekf.SqrtGaussian(jnp.asarray(x0), jnp.asarray(np.linalg.cholesky(P0)))
    return ekf.Gaussian(jnp.asarray(x0), jnp.asarray(P0))


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
def test_a_python_loop_of_eager_steps_compiles_once_and_equals_the_scan(mod):
    """The filterpy-style loop: the second pair of eager ``predict`` / ``update`` calls compiles
    (the first runs op by op), every later one runs the kept programs (9-11 ms a step before,
    each op dispatched on its own; 11 ms for the square-root filters), and the loop's means
    equal the whole run under jit (``filter_scan``), float64 and float32."""
    calls = {"f": 0, "h": 0}  # the models run in Python only while a step is traced

    def fc(x, u):
        calls["f"] += 1
        return f(x, u)

    def hc(x):
        calls["h"] += 1
        return h(x)

    for dt, tol in ((np.float64, 1e-10), (np.float32, 2e-5)):
        x0, P0, zs, mk = _data(T=25, dtype=dt)
        st = _belief(mod, x0, P0)
        means = []
        for t in range(len(zs)):
            before = dict(calls)
            with compilation.account() as acc:
                st = mod.predict(st, fc, None, Q.astype(dt))
                st, info = mod.update(st, zs[t], hc, R.astype(dt), mask=mk[t], gate=9.0)
            if t > 1:  # op by op, each step ran f and h again (and traced nothing new)
                assert acc.result.trace_s == 0.0 and acc.result.programs == 0, (t, acc.result)
                assert calls == before, (t, before, calls)
            means.append(np.asarray(st.mean))
        assert st.mean.dtype == dt
        ref = jax.jit(lambda x0, P0, zs, mk: mod.filter_scan(f, h, x0, P0, None, zs, mk, Q.astype(dt),
                                                             R.astype(dt), gate=9.0).means)(x0, P0, zs, mk)
        np.testing.assert_allclose(np.stack(means), np.asarray(ref), rtol=tol, atol=tol)


def test_eager_steps_still_check_the_values_known_at_the_call():
    """The compiled step sees traced values; the checks of the values a caller passed run
    before it, as they always did (a negative Q, a non-PD R, a NaN mean, a mask wider than the
    gate's table; a square-root factor with a negative diagonal)."""
    from jaxslam.errors import InputError

    def fi(x, u):
        return x

    def hi(x):
        return x

    def h2(x):
        return jnp.stack([x[0], x[0]])

    gate = ekf.chi2_gate(0.99, max_dof=1)
    for mod in (ekf, ukf, sqrt_ekf, sqrt_ukf):
        st = _belief(mod, np.asarray([0.1]), np.eye(1))
        Q1 = 1.0 if mod in (ekf, sqrt_ekf) else np.eye(1)  # the sigma-point predicts take (n, n) only
        # good calls first, twice: the programs are compiled and kept, so the bad calls hit them
        for _ in range(2):
            mod.predict(st, fi, None, Q1)
            mod.update(st, 0.1, hi, 1.0)
            mod.update(st, jnp.asarray([0.1, 0.2]), h2, jnp.eye(2), gate=gate, mask=np.asarray([True, False]))
        with pytest.raises(InputError, match=r"^Q: "):
            mod.predict(st, fi, None, -1.0 * np.asarray(Q1))
        with pytest.raises(InputError, match=r"^R: "):
            mod.update(st, 0.1, hi, -1.0)
        with pytest.raises(InputError, match=r"^state.mean: "):
            mod.update(st._replace(mean=jnp.asarray([np.nan])), 0.1, hi, 1.0)
        with pytest.raises(InputError, match=r"^gate: "):
            mod.update(st, jnp.asarray([0.1, 0.2]), h2, jnp.eye(2), gate=gate, mask=np.asarray([True, True]))
        if mod in (sqrt_ekf, sqrt_ukf):  # a factor with a negative diagonal, predict and update
            for call in (lambda s: mod.predict(s, fi, None, Q1), lambda s: mod.update(s, 0.1, hi, 1.0)):
                with pytest.raises(InputError, match=r"^state.chol: .*non-negative diagonal"):
                    call(st._replace(chol=-jnp.eye(1)))


def test_a_model_made_anew_at_every_step_is_not_compiled_in_vain():
    """A lambda written inside the loop is a new model at every call: each is seen once, so the
    step runs op by op as before (no program is traced or compiled for it after the first
    iteration: JAX keeps its per-op programs), where compiling on first sight would trace and
    compile at every step (0.3-0.6 s each)."""
    x0, P0, zs, mk = _data(T=6)
    st = ekf.Gaussian(jnp.asarray(x0), jnp.asarray(P0))
    lm = np.asarray([0.5, -0.2, 0.1, 0.3, 0.0, 0.2])
    for t in range(len(zs)):
        with compilation.account() as acc:
            st = ekf.predict(st, lambda x, u: f(x, u), None, Q)
            st, _ = ekf.update(st, zs[t], lambda x, t=t: jnp.sin(x[:1]) + lm[t], R)
        if t > 0:
            assert acc.result.programs == 0 and acc.result.trace_s < 0.05, (t, acc.result)
    assert bool(jnp.all(jnp.isfinite(st.mean)))


def test_option_values_known_at_the_call_are_still_checked_by_the_compiled_runs():
    """Numbers among a run's options are arguments of its compiled program (a new gate never
    recompiles), so the program sees them traced; the runs check them before, as they did when
    each eager call was traced with the values in hand (a negative or NaN gate, a resampling
    threshold outside [0, 1], a Student-t ν ≤ 0)."""
    from jaxslam.errors import InputError

    model, log = _slam_case(T=5, K=2)
    st = es.init(jnp.zeros(2), jnp.eye(2), 4, 2)
    es.run(model, st, log, 0.01 * np.eye(2), 0.1 * np.eye(2), gate=9.21)  # compiled and kept
    for bad in (-1.0, float("nan")):
        with pytest.raises(InputError, match=r"^gate: "):
            es.run(model, st, log, 0.01 * np.eye(2), 0.1 * np.eye(2), gate=bad)
    fmodel = fs.LandmarkModel(2, 2, lambda pose, lm, p=None: lm - pose[:2], lambda pose, z, p=None: pose[:2] + z)
    u = np.zeros((5, 3))
    p0 = fs.init(np.zeros(3), 8, 4, 2)
    args = (p0, jax.random.PRNGKey(0), _sample, (u,), fmodel, log.z, np.arange(2), log.mask, 0.01 * np.eye(2))
    fs.run(*args, threshold=0.5, gate=9.21, robust=4.0)  # compiled and kept
    for kw, name in ((dict(threshold=1.5), "threshold"), (dict(robust=-1.0), "robust"),
                     (dict(gate=float("nan")), "gate")):
        with pytest.raises(InputError, match=rf"^{name}: "):
            fs.run(*args, **{**dict(threshold=0.5, gate=9.21, robust=4.0), **kw})
    x0, P0, zs, mk = _data()
    sqrt_ekf.filter_scan(f, h, x0, P0, None, zs, mk, Q, R, gate=9.0)
    with pytest.raises(InputError, match=r"^gate: "):
        sqrt_ekf.filter_scan(f, h, x0, P0, None, zs, mk, Q, R, gate=-9.0)


# --- the EKF-SLAM engine's steps called one at a time ------------------------------------------

def _gps(s, p=None):
    return s


def _engine_step(model, st, u, z, ids, mask, R, Qs):
    """One step of a user's loop: predict, known-id association, update, registration of the
    unmapped ids, a position fix, and nearest-neighbour association (its table only)."""
    st = es.predict(st, model, u, Qs)
    slots, mapped = es.associate_known(st, ids, mask)
    st, _ = es.update(st, model, z, slots, mapped, R, gate=9.21)
    st = es.register(st, model, z, ids, mask & ~mapped, R)
    st, _ = es.update_robot(st, model, _gps, st.x[:2] + 0.01, np.ones(2, bool), 0.5 * np.eye(2))
    nn = es.associate_nn(st, model, z, mask, R, gate=9.21, new_threshold=20.0)
    return st, nn


def test_a_python_loop_of_eager_engine_steps_compiles_once_and_equals_the_jitted_steps():
    """The engine's predict / update / register / update_robot / associate_nn called eagerly in
    a Python loop compile on their first call (``after="auto"``: uncompiled, the first step ran
    op by op for seconds) and run the kept programs from the second step on; every step equals
    the same step under the caller's ``jit`` (the traced path), float64 and float32."""
    model, log = _slam_case(T=8, K=3)
    for dt, tol in ((np.float64, 1e-12), (np.float32, 1e-5)):
        Qs, Rm = (0.01 * np.eye(2)).astype(dt), (0.1 * np.eye(2)).astype(dt)
        st = st_ref = es.init(jnp.zeros(2, dt), jnp.eye(2, dtype=dt), 4, 2)
        jstep = jax.jit(lambda st, u, z, ids, mask: _engine_step(model, st, u, z, ids, mask, Rm, Qs))
        for t in range(len(log.u)):
            u, z = log.u[t].astype(dt), log.z[t].astype(dt)
            with compilation.account() as acc:
                st, nn = _engine_step(model, st, u, z, log.ids[t], log.mask[t], Rm, Qs)
            if t > 0:
                assert acc.result.trace_s == 0.0 and acc.result.programs == 0, (t, acc.result)
            st_ref, nn_ref = jstep(st_ref, u, z, log.ids[t], log.mask[t])
            np.testing.assert_allclose(np.asarray(st.x), np.asarray(st_ref.x), rtol=tol, atol=tol)
            np.testing.assert_allclose(np.asarray(st.P), np.asarray(st_ref.P), rtol=tol, atol=tol)
            np.testing.assert_array_equal(np.asarray(nn[1]), np.asarray(nn_ref[1]))
        assert st.x.dtype == dt and int(jnp.sum(st.active)) == 3 and int(st.status) == int(st_ref.status)


def test_eager_engine_steps_still_check_the_values_known_at_the_call():
    """As the Gaussian filters' steps: the values a caller passed are checked before the kept
    program runs (a non-PSD Q or R, a mask that is not bool, a Student-t ν ≤ 0)."""
    from jaxslam.errors import InputError

    model, log = _slam_case(T=2, K=3)
    st = es.init(jnp.zeros(2), jnp.eye(2), 4, 2)
    z, ids, mask, R = log.z[0], log.ids[0], log.mask[0], 0.1 * np.eye(2)
    for _ in range(2):  # compiled and kept
        st2 = es.predict(st, model, log.u[0], 0.01 * np.eye(2))
        st2 = es.register(st2, model, z, ids, mask, R)
        es.update(st2, model, z, np.arange(3), mask, R, robust=4.0)
        es.update_robot(st2, model, _gps, np.zeros(2), np.ones(2, bool), np.eye(2))
        es.associate_nn(st2, model, z, mask, R)
    with pytest.raises(InputError, match=r"^Q: "):
        es.predict(st, model, log.u[0], -0.01 * np.eye(2))
    for call in (lambda R: es.update(st2, model, z, np.arange(3), mask, R, robust=4.0),
                 lambda R: es.register(st2, model, z, ids, mask, R),
                 lambda R: es.associate_nn(st2, model, z, mask, R),
                 lambda R: es.update_robot(st2, model, _gps, np.zeros(2), np.ones(2, bool), R[0])):
        with pytest.raises(InputError, match=r"^R"):
            call(np.broadcast_to(-np.eye(2), (3, 2, 2)))
    with pytest.raises(InputError, match=r"^mask: "):
        es.update(st2, model, z, np.arange(3), np.asarray([0.5, 1.0, 1.0]), R)
    with pytest.raises(InputError, match=r"^robust: "):
        es.update(st2, model, z, np.arange(3), mask, R, robust=-1.0)


def test_auto_compiles_on_first_sight_until_a_site_meets_models_made_anew():
    """``call_compiled(after="auto")``: a key compiles on its first call; once its site has
    compiled two keys in a row that served one call each (a model made anew for every call),
    the site compiles on a key's second call, so a lambda written inside the loop costs two
    compiles, not one per step; a kept program that serves a second call puts the site back to
    compiling on first sight.  Another site is not affected."""
    compilation.clear_programs()
    traced = []

    def make():
        def fn(x):
            traced.append(isinstance(x, jax.core.Tracer))
            return x + 1.0
        return fn

    stable = make()
    for _ in range(3):
        compilation.call_compiled(("test.stable", stable), stable, (jnp.ones(2),), after="auto")
    assert traced == [True]  # compiled on the first call, then served
    assert compilation.kept_programs() == {"test.stable": 1}
    traced.clear()
    for _ in range(5):
        fresh = make()
        compilation.call_compiled(("test.fresh", fresh), fresh, (jnp.ones(2),), after="auto")
    assert traced == [True, True, False, False, False]
    assert compilation.kept_programs() == {"test.stable": 1, "test.fresh": 2}  # the three uncompiled keep none
    traced.clear()
    again = make()
    for _ in range(3):  # a model kept at that site now compiles on its second call
        compilation.call_compiled(("test.fresh", again), again, (jnp.ones(2),), after="auto")
    assert traced == [False, True]
    traced.clear()
    later = make()  # its third call was served by the kept program: the site compiles on first sight again
    for _ in range(2):
        compilation.call_compiled(("test.fresh", later), later, (jnp.ones(2),), after="auto")
    assert traced == [True]
    traced.clear()
    other = make()
    compilation.call_compiled(("test.other", other), other, (jnp.ones(2),), after="auto")
    assert traced == [True]
    compilation.clear_programs()
    assert compilation.kept_programs() == {}


# --- the FastSLAM core's steps called one at a time --------------------------------------------

def _fs_observe(pose, lm, p=None):
    return lm - pose[:2]


def _fs_inverse(pose, z, p=None):
    return pose[:2] + z


_FMODEL = fs.LandmarkModel(2, 2, _fs_observe, _fs_inverse)


def _fs_steps(p, key, u, z, ids, mask, R):
    """A user's loop body: a FastSLAM 1.0 step, then a FastSLAM 2.0 draw and its landmark update."""
    k1, k2 = jax.random.split(key)
    p, info = fs.step(p, k1, _sample, (u,), _FMODEL, z, ids, mask, R, slot_by_id=True, threshold=0.5, gate=9.21)
    cov = jnp.broadcast_to(1e-3 * jnp.eye(3, dtype=p.pose.dtype), p.pose.shape + (3,))
    q, ll, _, _ = fs.propose_optimal(p, _FMODEL, z, ids, mask, R, cov, k2, slot_by_id=True,
                                     angle_mask=[False, False, True])
    q, _ = fs.observe_update(q, _FMODEL, z, ids, mask, R, weights="none", slot_by_id=True)
    return fs.reweight(q, ll), info


def test_a_python_loop_of_eager_fastslam_steps_compiles_once_and_equals_the_jitted_steps():
    """``fastslam.step``, ``propose_optimal`` and ``observe_update`` called eagerly compile on
    their first call and run the kept programs after (uncompiled, each call re-traced and
    re-compiled its scan over the rows: 0.9 s a step for 100 particles); every step equals the
    same step under the caller's ``jit``, float64 and float32."""
    T, N, K = 6, 16, 2
    rng = np.random.default_rng(0)
    us, zs = rng.normal(size=(T, 3)) * 0.1, rng.normal(size=(T, K, 2))
    ids, mask = np.arange(K), np.ones(K, bool)
    jsteps = jax.jit(_fs_steps)
    for dt, tol in ((np.float64, 1e-12), (np.float32, 1e-5)):
        R = (0.01 * np.eye(2)).astype(dt)
        p = p_ref = fs.init(np.zeros(3, dt), N, 4, 2)
        for t in range(T):
            key = jax.random.PRNGKey(t)
            with compilation.account() as acc:
                p, info = _fs_steps(p, key, us[t].astype(dt), zs[t].astype(dt), ids, mask, R)
            if t > 0:
                assert acc.result.trace_s == 0.0 and acc.result.programs == 0, (t, acc.result)
            p_ref, info_ref = jsteps(p_ref, key, us[t].astype(dt), zs[t].astype(dt), ids, mask, R)
            for a, b in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(p_ref)):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)
        assert p.pose.dtype == dt and int(info.n_used) == int(info_ref.n_used)


def test_eager_fastslam_steps_still_check_the_values_known_at_the_call():
    """The values a caller passed are checked before the kept program runs: a non-PD R, a
    threshold outside [0, 1], a Student-t ν ≤ 0, a mask that is not bool, a fractional id."""
    from jaxslam.errors import InputError

    p = fs.init(np.zeros(3), 8, 4, 2)
    z, ids, mask, R = np.zeros((2, 2)), np.arange(2), np.ones(2, bool), 0.01 * np.eye(2)
    cov = jnp.broadcast_to(1e-3 * jnp.eye(3), (8, 3, 3))
    key = jax.random.PRNGKey(0)

    def calls(z=z, ids=ids, mask=mask, R=R, threshold=0.5, robust=4.0):
        yield lambda: fs.step(p, key, _sample, (np.zeros(3),), _FMODEL, z, ids, mask, R, threshold=threshold,
                              robust=robust)
        yield lambda: fs.observe_update(p, _FMODEL, z, ids, mask, R, robust=robust)
        yield lambda: fs.propose_optimal(p, _FMODEL, z, ids, mask, R, cov, key, robust=robust)

    for _ in range(2):  # compiled and kept
        for call in calls():
            call()
    for kw, name in ((dict(R=-R), "R"), (dict(robust=-1.0), "robust"), (dict(ids=np.asarray([0.0, 1.5])), "lm_ids")):
        for call in calls(**kw):
            with pytest.raises(InputError, match=rf"^{name}"):
                call()
    with pytest.raises(InputError, match=r"^threshold: "):
        next(calls(threshold=1.5))()
    for call in list(calls(mask=np.asarray([0.5, 1.0])))[:2]:
        with pytest.raises(InputError, match=r"^mask: "):
            call()


# --- other functions with a loop inside: RANSAC lines, JCBB, resampling -----------------------

def _scan_points(seed):
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, 40)
    wall = np.stack([4.0 * s, 1.0 + 0.01 * rng.normal(size=40)], 1)
    side = np.stack([0.5 + 0.01 * rng.normal(size=40), 1.0 + 3.0 * s], 1)
    return np.concatenate([wall, side]), np.ones(80, bool)


def _jcbb_case():
    model = es.SlamModel(robot_dim=3, lm_dim=2, meas_dim=2, motion=lambda s, u, p=None: s + u,
                         observe=_fs_observe, inverse=_fs_inverse)
    st = es.init(np.zeros(3), 0.01 * np.eye(3), 8, 2)
    st = es.preload(st, model, np.array([[1.0, 0.0], [0.0, 1.0], [2.0, 2.0]]),
                    np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)))
    return model, st


def _lines_calls():
    from jaxslam.features import lines

    cfg = lines.RansacConfig(n_hyp=64, max_lines=3, min_inliers=10)
    return {
        "extract_lines": lambda seed: lines.extract_lines(jax.random.PRNGKey(seed), *_scan_points(seed), cfg),
        "extract_guided": lambda seed: lines.extract_guided(jax.random.PRNGKey(seed), *_scan_points(seed),
                                                            np.array([1.0, 0.5]), np.array([np.pi / 2, 0.0]),
                                                            np.array([True, seed % 2 == 0]), cfg),
    }


def _other_calls():
    from jaxslam.filters import association

    model, st = _jcbb_case()
    p = fs.init(np.zeros(3), 32, 4, 2)
    calls = {
        "association.jcbb": lambda seed: association.jcbb(
            st, model, np.array([[1.0, 0.0], [0.0, 1.0]]) + 0.01 * seed, np.ones(2, bool), 0.01 * np.eye(2),
            gate=9.2, thresholds=np.array([9.2, 13.3])),
        "fastslam.maybe_resample": lambda seed: fs.maybe_resample(
            p._replace(log_w=jnp.asarray(np.random.default_rng(seed).normal(size=32))), jax.random.PRNGKey(seed),
            0.9),
    }
    calls.update({f"lines.{k}": v for k, v in _lines_calls().items()})
    from jaxslam.dynamics import integrators
    from jaxslam.sensors import imu
    from jaxslam.stats import chi2_ppf

    calls["ekf_slam.marginal_d2"] = lambda seed: es.marginal_d2(
        st, model, np.array([[1.0, 0.0], [0.0, 1.0]]) + 0.01 * seed, np.ones(2, bool), 0.01 * np.eye(2))
    calls["stats.chi2_ppf"] = lambda seed: chi2_ppf(np.asarray([0.9, 0.99]), 2.0 + seed)
    from jaxslam.sim.scenarios.tracking import make_setup, paper000_figure8
    from jaxslam.sim.simulate import simulate

    setup = make_setup(paper000_figure8(2.0, 0.0), jnp.float64)
    calls["sim.simulate"] = lambda seed: simulate(setup._replace(x0=setup.x0 + 0.01 * seed), jax.random.PRNGKey(seed),
                                                  1, 3)
    calls["integrators.rollout"] = lambda seed: integrators.rollout(f, np.asarray([0.3, 0.0]),
                                                                    np.full((20, 1), 0.1 * seed), 0.05)
    calls["imu.bias_drift_rollout"] = lambda seed: imu.bias_drift_rollout(
        jax.random.PRNGKey(seed), imu.BiasDriftState(jnp.zeros(6), jnp.full(6, 0.01 * seed)),
        imu.ImuSpec(drift_tau=10.0, drift_density=0.1), 0.01, 30)
    from jaxslam.filters import resampling, trilateration

    calls["ekf_slam.preload"] = lambda seed: es.preload(st, model, np.array([[1.0, 0.0]]) + 0.01 * seed,
                                                        1e-4 * np.eye(2)[None] * (1 + seed), ids=[7])
    anchors = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [5.0, 5.0]])
    calls["trilateration.trilaterate"] = lambda seed: trilateration.trilaterate(
        anchors, np.linalg.norm(anchors - [1.0 + 0.1 * seed, 2.0], axis=1), mask=[True, True, True, seed == 0],
        range_var=0.01)
    xs = np.arange(5.0)
    calls["trilateration.trilaterate_line"] = lambda seed: trilateration.trilaterate_line(
        xs, np.hypot(xs - 1.5 - 0.1 * seed, 2.0), side=-1.0)
    log_w = np.log(np.linspace(0.1, 1.0, 40))
    for scheme in ("systematic", "residual"):
        calls[f"resampling.{scheme}"] = lambda seed, fn=getattr(resampling, scheme): fn(
            jax.random.PRNGKey(seed), log_w + 0.1 * seed)
    calls["resampling.soft"] = lambda seed: resampling.soft(jax.random.PRNGKey(seed), log_w, 0.3 + 0.1 * seed)
    from jaxslam import metrics

    path = np.c_[np.cos(np.linspace(0, 3, 30)), np.sin(np.linspace(0, 3, 30)), np.linspace(0, 1, 30)]
    calls["metrics.ate"] = lambda seed: metrics.ate(path + 0.01 * seed * path[::-1], path)
    calls["metrics.umeyama"] = lambda seed: metrics.umeyama(path + 0.01 * seed, path, with_scale=True)
    calls["metrics.rpe"] = lambda seed: metrics.rpe(path + 0.01 * seed * path[::-1], path, lag=2)
    calls["metrics.rpe_se2"] = lambda seed: metrics.rpe_se2(path + 0.01 * seed * path[::-1], path)
    from jaxslam.control import lqr

    A, B = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]])
    calls["lqr.care"] = lambda seed: lqr.care(A, B, np.diag([1.0 + seed, 2.0]), np.eye(1), return_status=True)
    calls["lqr.lqr_gain"] = lambda seed: lqr.lqr_gain(A, B, np.diag([1.0 + seed, 2.0]), np.eye(1))
    from jaxslam import stats

    calls["stats.quadratic_form"] = lambda seed: stats.nees(path + 0.1 * seed, np.tile(np.eye(3), (30, 1, 1)))
    from jaxslam.filters import delayed_init

    pts = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [5.0, 5.0], [2.0, 7.0], [6.0, 2.0]])
    rng_ = np.linalg.norm(pts - [1.0, 2.0], axis=1) + np.array([0, 0, 0, 0, 0, 3.0])  # one outlier
    calls["delayed_init.robust_trilaterate"] = lambda seed: delayed_init.robust_trilaterate(
        pts, rng_ + 0.01 * seed, np.ones(6, bool), 0.01)
    calls["delayed_init.from_buffer"] = lambda seed: delayed_init.from_buffer(
        pts, 0.001 * (1 + seed), rng_, np.ones(6, bool), 0.01, robust=True)
    return calls


@pytest.mark.parametrize("name", ["lines.extract_lines", "lines.extract_guided", "association.jcbb",
                                  "fastslam.maybe_resample", "stats.chi2_ppf", "integrators.rollout",
                                  "imu.bias_drift_rollout", "ekf_slam.marginal_d2", "sim.simulate",
                                  "ekf_slam.preload", "trilateration.trilaterate", "trilateration.trilaterate_line",
                                  "resampling.systematic", "resampling.residual", "resampling.soft",
                                  "metrics.ate", "metrics.umeyama", "metrics.rpe", "metrics.rpe_se2", "lqr.care",
                                  "lqr.lqr_gain", "stats.quadratic_form", "delayed_init.robust_trilaterate",
                                  "delayed_init.from_buffer"])
def test_other_looping_functions_called_eagerly_compile_once_and_keep_nothing_more(name):
    """RANSAC line extraction (``extract_lines``, ``extract_guided``), JCBB,
    ``fastslam.maybe_resample``, ``chi2_ppf``, the RK4 ``rollout``, the IMU drift rollout and the
    flight simulation hold a ``lax.scan`` / ``while_loop`` / ``fori_loop`` / ``cond``: uncompiled,
    each eager call traced and compiled it again and kept the program (40 ms to 1.9 s a call;
    6-508 memory mappings a call).  ``marginal_d2`` (17-29 ms a call), ``preload``, the
    trilaterations, the resampling schemes, the trajectory metrics, NEES / NIS and the CARE's
    status and gain ran op by op (0.4-7 ms a call, and 0.4-3 s for the first).  A second call with new numbers now traces and compiles nothing, runs a kept program
    (:func:`jaxslam.compilation.kept_programs`: op by op, none is kept), and equals the same call
    under the caller's ``jit``."""
    compilation.clear_programs()
    call = _other_calls()[name]
    call(0)
    with compilation.account() as acc:
        out = call(1)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    site = "lines.extract_lines" if name == "lines.extract_guided" else name
    assert compilation.kept_programs().get(site, 0) >= 1, compilation.kept_programs()
    ref = jax.jit(lambda: call(1))()
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def test_a_loop_over_twenty_kept_programs_compiles_nothing_on_its_second_pass():
    """The kept programs are bounded (least recently used first out), and the bound holds a
    loop that mixes the engine's, FastSLAM's and the filters' steps (~20 keys, one site each):
    with 16 such a loop evicted each program before its next use and compiled at every call."""
    compilation.clear_programs()
    fns = []
    for i in range(20):
        def fn(x, i=i):
            return x * (i + 1.0)
        fns.append(fn)
    for _ in range(2):
        with compilation.account() as acc:
            for i, fn in enumerate(fns):
                # a closure made at each call, as the library's steps make theirs
                compilation.call_compiled((f"test.site{i}",), lambda x, fn=fn: fn(x), (jnp.ones(3),), after="auto")
    assert acc.result.programs == 0 and acc.result.trace_s == 0.0, acc.result
    compilation.clear_programs()


def test_system_models_built_per_call_are_one_object_per_configuration():
    """The planar and UWB systems build their engine model inside ``step`` (``make_model``):
    equal configurations now give the same object, so the engine's steps called eagerly from a
    system's ``step`` find their kept programs (a new closure at every call made every key new:
    two compiles in vain, then op by op)."""
    from jaxslam.systems import planar_ekf_slam as pe, uwb_slam_2d as uw

    a, b = pe.make_model(pe.Config()), pe.make_model(pe.Config())
    assert a is b and hash(("ekf_slam.update", a)) == hash(("ekf_slam.update", b))
    calibrated = pe.make_model(pe.Config(calibrate=True))
    assert calibrated is not a and calibrated.robot_dim == 6
    assert uw.make_model("squared") is uw.make_model("squared") is not uw.make_model("range")


@pytest.mark.parametrize("sequential", [False, True])
def test_eager_update_batch_compiles_at_its_second_call_and_equals_the_jitted_update(sequential):
    """``ekf.update_batch`` called eagerly runs a kept program from its model's second call, as
    ``update`` does (10 ms a call op by op; the sequential form traced its scan at every call,
    which this test catches; the joint form's gain is its speed alone), and equals the same
    update under the caller's ``jit``."""
    st = ekf.Gaussian(jnp.asarray([0.3, 0.0]), 0.1 * jnp.eye(2))
    lm = np.asarray([[0.5], [-0.2], [0.1]])

    def hb(x, l):
        return jnp.sin(x[:1]) + l

    def call(k):
        return ekf.update_batch(st, 0.1 * k + np.zeros((3, 1)), hb, R, lm, masks=np.asarray([True, k % 2 == 0, True]),
                                gate=9.0, sequential=sequential)

    call(0)
    call(1)
    with compilation.account() as acc:
        post, info = call(2)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    ref, ref_info = jax.jit(lambda: call(2))()
    np.testing.assert_allclose(np.asarray(post.mean), np.asarray(ref.mean), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(post.cov), np.asarray(ref.cov), rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(np.asarray(info.status), np.asarray(ref_info.status))


def test_kept_programs_follow_the_dtype_of_each_call():
    """A kept program is keyed by what it closes over and retraced for new argument dtypes, so
    a float32 call after a float64 one returns float32 (``metrics.umeyama`` closed over the
    first call's dtype and returned float64 for float32 points until this test)."""
    from jaxslam import metrics, stats
    from jaxslam.control import lqr
    from jaxslam.filters import resampling, trilateration

    path = np.c_[np.cos(np.linspace(0, 3, 30)), np.sin(np.linspace(0, 3, 30)), np.linspace(0, 1, 30)]
    anchors = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [5.0, 5.0]])
    A, B = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]])
    calls = {
        "umeyama": lambda dt: metrics.umeyama(path.astype(dt) + 0.1, path.astype(dt), with_scale=True)[0],
        "ate": lambda dt: metrics.ate(path.astype(dt) + 0.1, path.astype(dt)),
        "rpe_se2": lambda dt: metrics.rpe_se2(path.astype(dt) + 0.1, path.astype(dt))[0],
        "trilaterate": lambda dt: trilateration.trilaterate(
            anchors.astype(dt), np.linalg.norm(anchors - [1.0, 2.0], axis=1).astype(dt)).position,
        "care": lambda dt: lqr.care(A.astype(dt), B.astype(dt), np.eye(2, dtype=dt), np.eye(1, dtype=dt)),
        "soft": lambda dt: resampling.soft(jax.random.PRNGKey(0), np.log(np.linspace(0.1, 1.0, 8)).astype(dt), 0.5)[1],
        "nees": lambda dt: stats.nees(path.astype(dt), np.eye(3, dtype=dt)),
    }
    for name, call in calls.items():
        for dt in (np.float64, np.float32, np.float64):
            assert call(dt).dtype == dt, (name, dt)


def test_eager_steps_given_lists_still_run_kept_programs():
    """Lists for Q, z, R and the mask are arrays before the compiled step: as lists they reached
    it as lists of tracers, which the shape checks' NumPy calls cannot read; the TypeError made
    ``call_compiled`` run that model uncompiled for good, arrays passed later included."""
    def fi(x, u):
        return x

    def h2(x):
        return x[:2]

    Q2, R2 = [[1e-2, 0.0], [0.0, 1e-2]], [[1.0, 0.0], [0.0, 1.0]]
    for mod in (ekf, ukf, sqrt_ekf, sqrt_ukf):
        compilation.clear_programs()
        st = _belief(mod, np.asarray([0.1, 0.2]), np.eye(2))
        for _ in range(3):
            out = mod.predict(st, fi, None, Q2)
            post, _ = mod.update(out, [0.1, 0.2], h2, R2, mask=[True, False])
        name = mod.__name__.rsplit(".", 1)[-1]
        kept = compilation.kept_programs()
        assert kept.get(f"{name}.predict") == 1 and kept.get(f"{name}.update") == 1, (name, kept)
        ref = jax.jit(lambda s: mod.update(mod.predict(s, fi, None, jnp.asarray(Q2)), jnp.asarray([0.1, 0.2]), h2,
                                           jnp.asarray(R2), mask=jnp.asarray([True, False]))[0])(st)
        np.testing.assert_allclose(np.asarray(post.mean), np.asarray(ref.mean), rtol=1e-12)
    model, _ = _slam_case(T=2, K=1)
    compilation.clear_programs()
    st = es.init(jnp.zeros(2), jnp.eye(2), 4, 2)
    for _ in range(2):
        es.predict(st, model, jnp.zeros(2), [[0.01, 0.0], [0.0, 0.01]])
    assert compilation.kept_programs().get("ekf_slam.predict") == 1


def test_a_scalar_q_is_still_factored_on_the_host_in_float64():
    """A one-noise-input predict takes a scalar ``Q``; as a matrix one, it is factored on the host
    in float64 and then cast (``sqrt_ekf.predict``), so a float32 factor is the float64 root
    rounded once: ``float32(sqrt(q))`` (the oracle), whatever the compiled step does."""
    st = sqrt_ekf.SqrtGaussian(jnp.zeros(1, jnp.float32), jnp.zeros((1, 1), jnp.float32))
    # the last three give another float32 when the root is taken of float32(q) in float32 (what the
    # compiled step alone did with a scalar Q: this test failed on 4ee65c6)
    for q in (0.1, 0.3, 1e-7, 9.486494471372438, 8.277025938204417, 7.535131086748066):
        for _ in range(2):  # the first call and the kept program
            out = sqrt_ekf.predict(st, None, None, q)
            assert out.chol.dtype == jnp.float32
            assert float(out.chol[0, 0]) == float(np.float32(np.sqrt(np.float64(q)))), q


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64])
def test_eager_inits_are_one_program_and_numpy_inputs_compile_nothing(dtype):
    """``ekf_slam.init`` / ``fastslam.init`` called eagerly build their state in one program
    per sizes and dtype (a dozen one-operation programs each before: 345-355 ms and 180 ms for
    a first call in a fresh process); a NumPy array enters through ``device_put`` (JAX 0.10's
    ``jnp.asarray`` of one compiles an identity program per shape).  The oracle is NumPy."""
    from jaxslam.linalg import float_array, to_jax

    want = np.float32 if dtype == np.float32 else np.float64
    m0 = np.array([1, 2, 3]).astype(dtype)
    c0 = (np.eye(3) * 2).astype(dtype)
    cap = {np.float64: 37, np.float32: 38, np.int64: 39}[dtype]  # sizes no other test uses
    with compilation.account() as acc:
        s = es.init(m0, c0, cap, 2)
    assert acc.result.programs == 1, acc.result
    n = 3 + 2 * cap
    x_ref, P_ref = np.zeros(n, want), np.zeros((n, n), want)
    x_ref[:3], P_ref[:3, :3] = m0, c0
    assert s.x.dtype == want and s.P.dtype == want
    np.testing.assert_array_equal(np.asarray(s.x), x_ref)
    np.testing.assert_array_equal(np.asarray(s.P), P_ref)
    np.testing.assert_array_equal(np.asarray(s.ids), -np.ones(cap, np.int32))
    assert not np.asarray(s.active).any() and int(s.status) == 0 and int(s.overflow) == 0

    aux = {"b": np.array([0.5, -0.5]).astype(want)}
    with compilation.account() as acc:
        p = fs.init(m0, cap + 5, cap, 2, aux=aux)
    assert acc.result.programs == 1, acc.result
    assert p.pose.dtype == want and p.lm_mean.shape == (cap + 5, cap, 2)
    np.testing.assert_array_equal(np.asarray(p.pose), np.broadcast_to(m0.astype(want), (cap + 5, 3)))
    np.testing.assert_array_equal(np.asarray(p.aux["b"]), np.broadcast_to(aux["b"], (cap + 5, 2)))
    np.testing.assert_allclose(np.asarray(p.log_w), np.full(cap + 5, -np.log(cap + 5)), rtol=1e-6)

    z = np.arange(cap * 3.0).reshape(cap, 3).astype(dtype)
    with compilation.account() as acc:
        a, b = to_jax(z), float_array(z, "z")
    assert acc.result.programs == 0, acc.result
    ja = jnp.asarray(z)
    assert a.dtype == ja.dtype and not a.weak_type and b.dtype == want
    np.testing.assert_array_equal(np.asarray(a), z)
    np.testing.assert_array_equal(np.asarray(b), z.astype(want))


def test_inits_under_jit_and_vmap_equal_the_eager_ones():
    m0, c0 = np.array([0.1, -0.2, 0.3]), 0.5 * np.eye(3)
    eager = es.init(m0, c0, 5, 2)
    traced = jax.jit(lambda m, c: es.init(m, c, 5, 2))(m0, c0)
    for a, b in zip(eager, traced):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    batch = jax.vmap(lambda m: fs.init(m, 4, 3, 2))(np.stack([m0, 2 * m0]))
    np.testing.assert_array_equal(np.asarray(batch.pose[1]), np.broadcast_to(2 * m0, (4, 3)))
    assert batch.lm_cov.shape == (2, 4, 3, 2, 2)
