"""The four Gaussian runs (``ekf``, ``ukf``, ``sqrt_ekf``, ``sqrt_ukf`` ``filter_scan``) check their
arrays in one place (``gaussian.check_run_inputs``) and so accept and refuse the same inputs
with the same messages; nearest-neighbour and joint-compatibility association never match on a
non-finite input (under ``jit``, where they have no status to say so).

Expected results are written by hand (messages, flags, which rows are kept) or come from the same
call with the well-formed argument.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.filters import ekf, ekf_slam as es, sqrt_ekf, sqrt_ukf, ukf

F = np.array([[1.0, 0.1], [0.0, 1.0]])


def f(x, u):
    return jnp.asarray(F, x.dtype) @ x


def h(x):
    return x[:1]


T = 6
ZS = np.random.default_rng(0).normal(size=(T, 1))
Q2 = 0.01 * np.eye(2)
R1 = 0.1 * np.eye(1)
RUNS = {"ekf": ekf.filter_scan, "ukf": ukf.filter_scan, "sqrt_ekf": sqrt_ekf.filter_scan,
        "sqrt_ukf": sqrt_ukf.filter_scan}


def _run(name, x0=None, P0=None, zs=None, masks=None, Q=None, R=None, **kw):
    x0 = np.zeros(2) if x0 is None else x0
    P0 = np.eye(2) if P0 is None else P0
    zs = ZS if zs is None else zs
    Q = Q2 if Q is None else Q
    R = R1 if R is None else R
    return RUNS[name](f, h, x0, P0, None, zs, masks, Q, R, **kw)


# --- 1. one check of a run's arrays --------------------------------------------------------------

@pytest.mark.parametrize("name", list(RUNS))
@pytest.mark.parametrize("arg, value, message", [
    ("x0", np.array(["a", "b"]), r"^x0: expected numbers"),
    ("x0", np.array([None, 1.0], dtype=object), r"^x0: expected numbers"),
    ("zs", np.array([["a"]] * T), r"^zs: expected numbers"),
    ("P0", np.array([["1", "0"], ["0", "1"]]), r"^P0: expected numbers"),
    ("P0", np.eye(2) + 0j, r"^P0: expected a real array"),
], ids=["x0-str", "x0-None", "zs-str", "P0-str", "P0-complex"])
def test_a_run_refuses_arrays_that_are_not_real_numbers(name, arg, value, message):
    # before: a str x0 / zs ended in a bare TypeError or ValueError (sqrt_ekf read None as NaN:
    # "contains NaN"), and ekf.filter_scan parsed a str P0 as numbers and ran a complex P0 with
    # only a ComplexWarning (the other three refused those two)
    with pytest.raises(InputError, match=message):
        _run(name, **{arg: value})


@pytest.mark.parametrize("name", list(RUNS))
def test_the_same_shape_defect_gets_the_same_message_in_every_run(name):
    # before: three wordings of a per-step Q of the wrong count, two of a per-step R's and of masks'
    with pytest.raises(InputError, match=r"^Q: one matrix per step needs 6 of them \(zs has 6 steps\), "
                                         r"got shape \(5, 2, 2\)$"):
        _run(name, Q=np.stack([Q2] * (T - 1)))
    with pytest.raises(InputError, match=r"^R: expected shape \(1, 1\) or \(6, 1, 1\), got \(7, 1, 1\)$"):
        _run(name, R=np.stack([R1] * (T + 1)), masks=np.ones((T, 1), bool))
    with pytest.raises(InputError, match=r"^masks: expected shape \(6, 1\) like zs, got \(6,\)$"):
        _run(name, masks=np.ones(T, bool))


@pytest.mark.parametrize("name", list(RUNS))
def test_every_run_takes_a_scalar_r_for_one_measurement_and_refuses_a_non_finite_x0(name):
    # the two rules the square-root EKF's own checks had apart from the shared ones: the same
    a = _run(name, R=0.1)
    b = _run(name, R=R1)
    np.testing.assert_array_equal(np.asarray(a.means), np.asarray(b.means))
    c = jax.jit(lambda R: _run(name, R=R))(jnp.asarray(0.1))
    np.testing.assert_allclose(np.asarray(c.means), np.asarray(b.means), rtol=1e-12, atol=1e-14)
    for bad in (np.nan, np.inf):
        with pytest.raises(InputError, match=r"^x0: contains NaN or Inf$"):
            _run(name, x0=np.array([bad, 0.0]))
    with pytest.raises(InputError, match=r"^R: not positive definite"):
        _run(name, R=-0.1)


def test_sqrt_ekf_checks_q_only_when_no_square_root_is_given():
    C = np.sqrt(0.01) * np.eye(2)
    a = sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, None, R1, Q_chol=C)
    b = sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1)
    np.testing.assert_allclose(np.asarray(a.means), np.asarray(b.means), rtol=1e-12, atol=1e-14)
    with pytest.raises(InputError, match=r"^Q: a process-noise covariance \(or Q_chol=\) is required$"):
        sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, None, R1)
    with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\) or \(6, 2, 2\), got \(3, 3\)$"):
        sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, np.eye(3), R1)
    with pytest.raises(InputError, match=r"^Q_chol: expected numbers"):
        sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, None, R1,
                             Q_chol=np.array([["1", "0"], ["0", "1"]]))


# --- 2. association on non-finite input ----------------------------------------------------------

def _motion(s, u, p):
    return jnp.stack([s[0] + 0.1 * u[0] * jnp.cos(s[2]), s[1] + 0.1 * u[0] * jnp.sin(s[2]), s[2] + 0.1 * u[1]])


def _observe(s, lm, p):
    d = lm - s[:2]
    return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0]) - s[2]])


def _inverse(s, z, p):
    return s[:2] + z[0] * jnp.stack([jnp.cos(s[2] + z[1]), jnp.sin(s[2] + z[1])])


M = es.SlamModel(3, 2, 2, _motion, _observe, _inverse)
R = np.diag([0.05**2, 0.01**2])
LMS = np.array([[2.0, 1.0], [1.0, -2.0]])
Z = np.stack([np.linalg.norm(LMS, axis=1), np.arctan2(LMS[:, 1], LMS[:, 0])], 1)  # exact sightings
THR = jnp.full((2,), 13.8)  # χ²(2·m) at 0.999 for m = 1 (and above the clean NIS, 0, for m = 2)


def _state():
    st = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    return es.preload(st, M, jnp.asarray(LMS))


_nn = jax.jit(lambda st, z, R: es.associate_nn(st, M, z, jnp.ones(2, bool), R))
_jc = jax.jit(lambda st, z, R, thr: es.joint_compatibility(st, M, z, jnp.arange(2, dtype=jnp.int32),
                                                           jnp.ones(2, bool), R, None, thr))


CASES = [f"{what}-{v}" for v in ("nan", "inf") for what in ("z", "R", "P-robot", "x-lm0")]


def _bad_input(case):
    """(state, z, R) with one NaN/Inf: row 0's z or R, the robot's variance (every row reads
    it) or landmark 0's mean (the rows' d² against slot 0; the joint test of row 0)."""
    what, v = case.rsplit("-", 1)
    v = float(v)
    st = _state()
    z, r = Z.copy(), np.stack([R, R])
    if what == "z":
        z[0, 0] = v
    elif what == "R":
        r[0, 1, 1] = v
    elif what == "P-robot":
        P = np.asarray(st.P).copy()
        P[0, 0] = v
        st = st._replace(P=jnp.asarray(P))
    else:
        x = np.asarray(st.x).copy()
        x[3] = v
        st = st._replace(x=jnp.asarray(x))
    return st, z, r


def test_clean_scan_is_matched_by_both():
    st = _state()
    _, matched, new, d2 = _nn(st, Z, np.stack([R, R]))
    assert np.asarray(matched).tolist() == [True, True] and not np.any(np.asarray(new))
    kept, dropped, nis = _jc(st, Z, np.stack([R, R]), THR)
    assert np.asarray(kept).tolist() == [True, True] and not np.any(np.asarray(dropped))


def test_nearest_neighbour_does_not_match_a_row_with_an_infinite_variance():
    # row 0 is 0.3 rad off in bearing (d² ≈ 69: not matched, a new landmark); with an infinite
    # bearing variance in its R the old table divided the bearing away, d² 0, and matched it
    st = _state()
    z = Z.copy()
    z[0, 1] += 0.3
    _, matched, new, _ = _nn(st, z, np.stack([R, R]))
    assert np.asarray(matched).tolist() == [False, True] and np.asarray(new).tolist() == [True, False]
    r = np.stack([R, R])
    r[0, 1, 1] = np.inf
    slots, matched, new, d2 = _nn(st, z, r)
    assert np.asarray(matched).tolist() == [False, True]
    assert np.asarray(new).tolist() == [False, False]
    assert np.isnan(float(d2[0])) and float(d2[1]) < 1e-9
    d2_table, _ = jax.jit(lambda st, z, R: es.marginal_d2(st, M, z, jnp.ones(2, bool), R))(st, z, r)
    assert np.all(np.isnan(np.asarray(d2_table)[0, :2]))  # the mapped slots of the bad row
    assert np.all(np.isinf(np.asarray(d2_table)[:, 2:]))  # free slots stay +inf


@pytest.mark.parametrize("case", CASES)
def test_a_non_finite_input_never_produces_a_match(case):
    st, z, r = _bad_input(case)
    _, matched, new, d2 = _nn(st, z, r)
    kept, dropped, nis = _jc(st, z, r, THR)
    # nearest neighbour: a row whose d² table met the bad value (every row for a state value)
    nn_bad = [0] if case.split("-")[0] in ("z", "R") else [0, 1]
    for k in nn_bad:
        assert not bool(matched[k]) and not bool(new[k]), case
        assert not np.isfinite(float(d2[k])), case
    # joint compatibility: the matched rows whose own innovation or S block holds it
    jc_bad = [0, 1] if "robot" in case else [0]
    for k in jc_bad:
        assert not bool(kept[k]) and bool(dropped[k]), case  # before: kept, with a NaN joint NIS
    if jc_bad == [0]:
        assert bool(kept[1]) and not bool(dropped[1])  # the good row is still jointly compatible
        assert float(nis) == pytest.approx(0.0, abs=1e-12)  # its exact sighting alone
    else:
        assert float(nis) == 0.0  # nothing left to test


def test_joint_compatibility_drops_rows_on_a_nan_cross_covariance_and_a_nan_threshold():
    # each row's own block is finite, the landmarks' cross-covariance is NaN: the joint NIS is
    # NaN, which `nis > thr` read as compatible (both kept)
    st = _state()
    P = np.asarray(st.P).copy()
    P[3, 5] = P[5, 3] = np.nan
    kept, dropped, _ = _jc(st._replace(P=jnp.asarray(P)), Z, np.stack([R, R]), THR)
    assert int(np.sum(np.asarray(kept))) == 1 and int(np.sum(np.asarray(dropped))) == 1
    # a traced NaN threshold: no row passes a test it cannot make (before: all kept)
    kept, dropped, _ = _jc(st, Z, np.stack([R, R]), jnp.full((2,), jnp.nan))
    assert np.asarray(kept).tolist() == [False, False] and np.asarray(dropped).tolist() == [True, True]
