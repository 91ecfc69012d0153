"""Input checks of the generic EKF-SLAM engine and its helpers: add_landmark's slot
and covariances, a float32 run with a float64 control, NaN rows under NN association, masks that
are not bool (or 0/1), and eager value checks of update_robot / associate_known / associate_nn."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import association, consistency, delayed_init, ekf_slam as es, fastslam as fs
from jaxslam.filters import trilateration as tri


def _motion(s, u, p):
    return jnp.stack([s[0] + 0.1 * u[0] * jnp.cos(s[2]), s[1] + 0.1 * u[0] * jnp.sin(s[2]), s[2] + 0.1 * u[1]])


def _observe(s, l, p):
    d = l - s[:2]
    return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0]) - s[2]])


def _inverse(s, z, p):
    return s[:2] + z[0] * jnp.stack([jnp.cos(s[2] + z[1]), jnp.sin(s[2] + z[1])])


M = es.SlamModel(3, 2, 2, _motion, _observe, _inverse)
Q = np.diag([0.01, 0.01, 0.001])
R = np.diag([0.05**2, 0.01**2])
R_BAD = np.array([[0.05, 0.1], [0.1, 0.05]])  # symmetric, indefinite


def _state(dtype=jnp.float64):
    st = es.init(jnp.zeros(3, dtype), 1e-3 * jnp.eye(3, dtype=dtype), 4, 2)
    return es.preload(st, M, jnp.array([[2.0, 1.0], [1.0, -2.0]], dtype))


# --- B: add_landmark ---------------------------------------------------------------------------

@pytest.mark.parametrize("slot", [9, 4, -1])
def test_add_landmark_concrete_slot_out_of_map_is_input_error(slot):
    st = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    with pytest.raises(InputError, match=r"^slot: "):
        es.add_landmark(st, M, slot, jnp.array([5.0, 6.0]), 0.1 * jnp.eye(2), jnp.zeros((2, 11)), 7)


def test_add_landmark_traced_slot_out_of_map_writes_nothing_and_flags():
    st = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    add = jax.jit(lambda st, k: es.add_landmark(st, M, k, jnp.array([5.0, 6.0]), 0.1 * jnp.eye(2),
                                                jnp.zeros((2, 11)), 7))
    for k in (9, -1):
        o = add(st, jnp.int32(k))
        np.testing.assert_array_equal(o.x, st.x)
        np.testing.assert_array_equal(o.P, st.P)
        np.testing.assert_array_equal(o.active, st.active)
        np.testing.assert_array_equal(o.ids, st.ids)
        assert int(o.status) & errors.MASKED_INPUT
    o = add(st, jnp.int32(2))  # in the map: written, no flag
    assert bool(o.active[2]) and int(o.ids[2]) == 7 and int(o.status) == 0
    np.testing.assert_allclose(o.x[3 + 4:3 + 6], [5.0, 6.0])
    # not asked for (ok False): nothing written, no flag even outside the map
    o = jax.jit(lambda st, k: es.add_landmark(st, M, k, jnp.zeros(2), jnp.eye(2), jnp.zeros((2, 11)), 1,
                                              ok=False))(st, jnp.int32(9))
    assert int(o.status) == 0


def test_add_landmark_checks_cov_shapes_and_psd():
    st = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    with pytest.raises(InputError, match=r"^cov_lx: "):
        es.add_landmark(st, M, 2, jnp.zeros(2), 0.1 * jnp.eye(2), jnp.zeros((2, 3)), 9)
    with pytest.raises(InputError, match=r"^cov_ll: "):
        es.add_landmark(st, M, 2, jnp.zeros(2), -0.1 * jnp.eye(2), jnp.zeros((2, 11)), 9)


# --- C: float32 state, float64 control ---------------------------------------------------------

def test_predict_and_run_cast_a_float64_control_to_a_float32_state():
    st = es.init(jnp.zeros(3, jnp.float32), 1e-3 * jnp.eye(3, dtype=jnp.float32), 4, 2)
    u64 = np.array([1.0, 0.2])
    assert es.predict(st, M, u64, Q.astype(np.float32)).x.dtype == jnp.float32
    log = es.SlamLog(u=np.tile(u64, (3, 1)), z=np.ones((3, 1, 2), np.float32), ids=np.zeros((3, 1), np.int32),
                     mask=np.ones((3, 1), bool))
    out = es.run(M, st, log, Q.astype(np.float32), R.astype(np.float32))
    assert out.robot.dtype == jnp.float32 and np.all(np.isfinite(out.robot))


# --- E: NaN rows under NN association ----------------------------------------------------------

def test_run_nn_flags_a_nan_measurement_row():
    z = np.array([[[2.0, 0.3], [1.5, -1.0]]] * 3)
    z[1, 0, 0] = np.nan
    log = es.SlamLog(u=np.tile([1.0, 0.2], (3, 1)), z=z, mask=np.ones((3, 2), bool))
    st0 = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    o = jax.jit(lambda lg: es.run(M, st0, lg, Q, R, association="nn"))(log)
    assert int(o.final.status) & errors.MASKED_INPUT
    z[1, 0, 0] = 2.0  # all finite: no flag
    o = jax.jit(lambda lg: es.run(M, st0, lg, Q, R, association="nn"))(log._replace(z=z))
    assert not int(o.final.status) & errors.MASKED_INPUT



def test_run_known_flags_a_nan_row_of_a_landmark_not_yet_mapped():
    # Known ids: the NaN row of a mapped landmark reaches update, which flags it; the NaN row of
    # a landmark not yet mapped registers nothing and used to vanish without a flag.
    z = np.array([[[2.0, 0.3], [1.5, -1.0]]] * 3)
    z[0, 1, 0] = np.nan  # id 1's first sighting, before it is mapped
    ids = np.tile([0, 1], (3, 1))
    log = es.SlamLog(u=np.tile([1.0, 0.2], (3, 1)), z=z, mask=np.ones((3, 2), bool), ids=ids)
    st0 = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    run = jax.jit(lambda lg: es.run(M, st0, lg, Q, R))
    o = run(log)
    assert int(o.final.status) & errors.MASKED_INPUT
    assert int(jnp.sum(o.final.active)) == 2  # id 1 registered from its next, finite row
    z[0, 1, 0] = 1.5
    assert not int(run(log._replace(z=z)).final.status) & errors.MASKED_INPUT

# --- F: masks that are not bool or 0/1 ---------------------------------------------------------

def _mask_calls(bad):
    st = _state()
    z = np.array([[2.2, 0.45], [2.2, -1.1]])
    m2 = np.ones(2, bool)
    K4 = lambda m: np.concatenate([np.asarray(m), np.ones(2, np.asarray(m).dtype)])  # noqa: E731
    fmodel = fs.LandmarkModel(2, 2, lambda pose, l, p: l - pose[:2], lambda pose, z, p: pose[:2] + z)
    p = fs.init(jnp.zeros(3), 4, 4, 2)
    mon = consistency.init(jnp.float64)
    mp = consistency.MonitorParams(jnp.float64(0.1), jnp.float64(2.0), jnp.float64(4.0), jnp.float64(9.21))
    pts = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0]])
    rng = np.linalg.norm(pts - np.array([1.0, 2.0]), axis=1)
    T = 3
    log = es.SlamLog(u=np.tile([1.0, 0.2], (T, 1)), z=np.tile(z, (T, 1, 1)), ids=np.array([[0, 1]] * T, np.int32),
                     mask=np.tile(bad, (T, 1)))
    return {
        "update": ("mask", lambda: es.update(st, M, z, np.array([0, 1]), bad, R)),
        "register": ("mask", lambda: es.register(st, M, z, np.array([5, 6]), bad, R)),
        "update_robot": ("mask", lambda: es.update_robot(st, M, lambda s, p: s[:2], z[0], bad, R)),
        "associate_known": ("mask", lambda: es.associate_known(st, np.array([0, 1]), bad)),
        "associate_nn": ("mask", lambda: es.associate_nn(st, M, z, bad, R)),
        "run": ("log.mask", lambda: es.run(M, st, log, Q, R)),
        "fastslam.observe_update": ("mask", lambda: fs.observe_update(p, fmodel, z, np.array([0, 1]), bad, R)),
        "jcbb": ("mask", lambda: association.jcbb(st, M, z, bad, R, gate=9.21, thresholds=np.array([9.21, 13.3]))),
        "trilaterate": ("mask", lambda: tri.trilaterate(pts, rng, mask=K4(bad))),
        "from_buffer": ("valid", lambda: delayed_init.from_buffer(pts, 0.01, rng, K4(bad), 0.01)),
        "consistency.observe": ("valid", lambda: consistency.observe(mon, st, M, np.array([1.0, 2.0]), bad, mp)),
        "ok": ("", lambda: m2),
    }


@pytest.mark.parametrize("bad", [np.array([2, 0]), np.array([0.5, 1.0])], ids=["int2", "float"])
@pytest.mark.parametrize("fn", ["update", "register", "update_robot", "associate_known", "associate_nn", "run",
                                "fastslam.observe_update", "jcbb", "trilaterate", "from_buffer",
                                "consistency.observe"])
def test_masks_must_be_bool_or_0_1(fn, bad):
    name, call = _mask_calls(bad)[fn]
    with pytest.raises(InputError, match=rf"^{name}: expected a bool mask"):
        call()


@pytest.mark.parametrize("fn", ["update", "associate_known", "trilaterate", "from_buffer", "consistency.observe"])
def test_masks_of_0_1_integers_still_pass(fn):
    _mask_calls(np.array([1, 0]))[fn][1]()


# --- I: eager value checks ---------------------------------------------------------------------

def test_update_robot_and_associate_nn_refuse_an_indefinite_R():
    st = _state()
    z = np.array([[2.2, 0.45], [2.2, -1.1]])
    with pytest.raises(InputError, match=r"^R(\[0\])?: not positive semi-definite"):
        es.update_robot(st, M, lambda s, p: s[:2], z[0], np.ones(2, bool), R_BAD)
    with pytest.raises(InputError, match=r"^R(\[0\])?: not positive semi-definite"):
        es.associate_nn(st, M, z, np.ones(2, bool), R_BAD)
    # a masked-out component's R is not read
    es.update_robot(st, M, lambda s, p: s[:2], z[0], np.array([True, False]),
                    np.array([[0.1, 0.0], [0.0, np.nan]]))


def test_associate_known_and_nn_shapes_are_input_errors():
    st = _state()
    with pytest.raises(InputError, match=r"^(lm_ids|mask): "):
        es.associate_known(st, np.array([0, 1, 2]), np.ones(2, bool))
    with pytest.raises(InputError, match=r"^z: "):
        es.associate_nn(st, M, np.array([2.2, 0.45]), np.ones(2, bool), R)


# --- leftovers of the 2026-12-06 filters probe ---------------------------------------------------

def test_complex_measurements_are_refused_by_the_engine():
    # run and update cast a complex z to real with only a ComplexWarning
    st = _state()
    log = es.SlamLog(u=np.tile([1.0, 0.2], (3, 1)), z=np.ones((3, 1, 2)) + 1j, ids=np.zeros((3, 1), np.int32),
                     mask=np.ones((3, 1), bool))
    with pytest.raises(InputError, match=r"^log\.z: expected a real array"):
        es.run(M, st, log, Q, R)
    with pytest.raises(InputError, match=r"^z: expected a real array"):
        es.update(st, M, np.ones((1, 2)) + 1j, np.array([0]), np.array([True]), R)


def test_predict_names_the_motion_when_its_output_has_the_wrong_shape():
    # a (2, 2) control broadcast by the model into a (2, 3) "robot state": an XLA error before
    m = es.SlamModel(3, 2, 2, lambda s, u, p: s + u[:, :1], _observe, _inverse)
    with pytest.raises(InputError, match=r"^model\.motion: returned shape \(2, 3\)"):
        es.predict(_state(), m, np.ones((2, 2)), Q)


def test_trilateration_drops_a_non_finite_point_like_a_bad_range():
    # a NaN or Inf point made the fit DEGENERATE (ok False) with four good rows left, and
    # from_buffer returned a NaN covariance
    pts = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0], [2.0, 5.0]])
    target = np.array([1.0, 2.0])
    r = np.sqrt(np.sum((pts - target) ** 2, axis=1))  # exact ranges: the fit is the target
    tri_j = jax.jit(tri.trilaterate)
    buf = jax.jit(lambda p, rr: delayed_init.from_buffer(p, 0.01, rr, jnp.ones(5, bool), 0.01))
    for bad in (np.nan, np.inf):
        p_bad = pts.copy()
        p_bad[1, 0] = bad
        fit = tri_j(p_bad, r)
        assert bool(fit.ok) and int(fit.n_used) == 4
        assert int(fit.status) == errors.MASKED_INPUT
        np.testing.assert_allclose(fit.position, target, atol=1e-9)
        fit_b, P_ll = buf(p_bad, r)
        assert bool(fit_b.ok) and np.all(np.isfinite(np.asarray(P_ll)))
        assert np.isfinite(float(fit_b.spread)) and np.isfinite(float(fit_b.residual_max))
    # the same point masked out by the caller: no flag
    assert int(tri_j(pts, r, np.array([True, False, True, True, True])).status) == 0


@pytest.mark.parametrize("bad", [np.nan, -1.0, 0.0, None, "9"])
def test_nearest_neighbour_thresholds_known_now_must_be_positive(bad):
    """A NaN or negative gate / new-landmark threshold matched nothing and registered nothing,
    without an error or a flag (a review reproduced it, eagerly and in ``run``)."""
    st = _state()
    z = np.array([[2.2, 0.45], [2.2, -1.1]])
    m2 = np.ones(2, bool)
    with pytest.raises(InputError, match=r"^gate: expected a scalar > 0"):
        es.associate_nn(st, M, z, m2, R, gate=bad)
    with pytest.raises(InputError, match=r"^new_threshold: expected a scalar > 0"):
        es.associate_nn(st, M, z, m2, R, new_threshold=bad)
    log = es.SlamLog(u=np.tile([1.0, 0.2], (2, 1)), z=np.tile(z, (2, 1, 1)), mask=np.ones((2, 2), bool))
    for kw in ("nn_gate", "nn_new"):
        with pytest.raises(InputError, match=rf"^{kw}: expected a scalar > 0"):
            es.run(M, st, log, Q, R, association="nn", **{kw: bad})
    es.run(M, st, log._replace(ids=np.zeros((2, 2), np.int32)), Q, R, association="known", nn_gate=bad)  # unused


def test_nearest_neighbour_thresholds_inf_and_traced_still_pass():
    st = _state()
    z = np.array([[2.2, 0.45], [2.2, -1.1]])
    m2 = np.ones(2, bool)
    a = es.associate_nn(st, M, z, m2, R, gate=9.21, new_threshold=np.inf)
    assert not np.asarray(a[2]).any()  # nothing is beyond an infinite threshold: nothing new
    b = jax.jit(lambda g: es.associate_nn(st, M, z, m2, R, gate=g))(9.21)
    for x, y in zip(a[:2], b[:2]):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
