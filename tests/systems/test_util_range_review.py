"""util_range review fixes: the SLAM start-up state predicted across the gap to the first event,
util_events' id / time checks and K, a non-finite ToF height flagged, startup compiled once and
its inputs checked, Config checked.  Oracles: hand-computed constant-velocity predictions, NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import compilation, errors
from jaxslam.errors import InputError
from jaxslam.systems import util_range as ur

A4 = np.array([[0.0, 0.0, 0.2], [4.0, 0.0, 1.5], [0.0, 4.0, 2.5], [4.0, 4.0, 0.5]])


def _startup(N=2, t0=1.0, p0=(1.0, 2.0, 0.5), v0=(0.3, -0.2, 0.1)):
    return ur.Startup(anchors=jnp.asarray(A4[:N]), bias=jnp.asarray(0.0), cov=0.01 * jnp.eye(3 * N + 1),
                      n_used=jnp.asarray(10), n_rejected=jnp.asarray(0), rms=jnp.asarray(0.1),
                      p0=jnp.asarray(p0), v0=jnp.asarray(v0), t0=jnp.asarray(t0))


def _walk(M=200, seed=3, n_anchors=4):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 20, M)
    P = np.stack([1.5 + np.cos(t), 1.5 + np.sin(1.3 * t), 1.0 + 0.5 * np.sin(0.7 * t)], 1)
    aid = rng.integers(0, n_anchors, M)
    z = np.linalg.norm(P - A4[aid], axis=1) - 0.25 + 0.05 * rng.standard_normal(M)
    return t, aid, z, P


# --- 1: SLAM start-up state predicted from t0 to the first event ---------------------------

def test_slam_first_event_is_the_prediction_across_the_gap():
    # first row's id 99 is no anchor (never used): the state after event 0 is the prediction alone
    ev = ur.util_events([3.0, 3.1], [99, 0], [1.0, 1.0])
    log = ur.log_from_events(ev, np.arange(2), startup=_startup(), dtype=jnp.float64)
    q = 0.5
    res = ur.run(log, ur.Config(), ur.Params(q_acc=q, gate=None))
    gap = 3.0 - 1.0
    # hand CV prediction: p + v Δt; var 0.02² + 0.1² Δt² + q_a Δt³/3 per axis
    np.testing.assert_allclose(np.asarray(res.pos[0]), [1.0 + 0.3 * gap, 2.0 - 0.2 * gap, 0.5 + 0.1 * gap],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.pos_var[0]), np.full(3, 0.02**2 + 0.1**2 * gap**2 + q * gap**3 / 3),
                               rtol=1e-12)
    assert int(res.used[0]) == 0 and int(res.n_unmapped) == 1


def test_slam_log_before_startup_window_end_is_refused():
    ev = ur.util_events([0.5, 0.6], [0, 1], [1.0, 1.0])
    with pytest.raises(InputError, match=r"^log\.startup\.t0: "):
        ur.run(ur.log_from_events(ev, np.arange(2), startup=_startup(t0=1.0), dtype=jnp.float64))


# --- 2, 3, 5, 9: util_events ------------------------------------------------------------------

def test_util_events_reserved_height_id_refused_without_tof():
    with pytest.raises(InputError, match="reserved for height rows"):
        ur.util_events([0.0, 0.1, 0.2], [0, ur.HEIGHT_ID, 1], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("ids", [[0.0, 1.5, 2.0], np.array([0, 2**32 - 1, 1], np.int64), [0.0, np.nan, 1.0],
                                 ["a", "b", "c"]])
def test_util_events_anchor_ids_checked_before_the_cast(ids):
    with pytest.raises(InputError, match=r"^anchor_id: "):
        ur.util_events([0.0, 0.1, 0.2], ids, [1.0, 2.0, 3.0])


def test_util_events_a_second_range_at_one_time_is_dropped_and_counted_without_tof():
    # K = 1 without ToF rows (the fault table's duplicate_line: the copy dropped, counted)
    ev = ur.util_events([0.0, 0.1, 0.1, 0.2], [0, 1, 2, 0], [1.0, 2.0, 3.0, 4.0])
    assert ev.z.shape == (3, 1, 1) and ev.stats["dropped_overflow"] == 1
    assert int(np.sum(ev.mask)) == 3
    np.testing.assert_array_equal(ev.z[:, 0, 0], [1.0, 2.0, 4.0])


@pytest.mark.parametrize("t", [[0.0, 0.2, 0.1], [0.0, np.nan, 0.2]])
def test_util_events_bad_times_name_t(t):
    with pytest.raises(InputError, match=r"^t: "):
        ur.util_events(t, [0, 1, 0], [1.0, 2.0, 3.0])


# --- 4: a non-finite ToF height is flagged -------------------------------------------------------

def test_nonfinite_tof_height_sets_masked_input():
    p = np.array([1.0, 1.5, 0.5])
    A = np.array([[0.0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 3.0]])
    t = np.arange(40) * 0.05
    aid = np.arange(40) % 4
    r = np.linalg.norm(p - A[aid], axis=1)
    h = p[2] - ur.TAG_Z - 0.014
    runs = {}
    for name, tof in (("ok", [h, h]), ("nan", [np.nan, h]), ("inf", [h, np.inf])):
        ev = ur.util_events(t, aid, r, tof_t=[0.51, 0.77], tof=tof)
        runs[name] = ur.run(ur.log_from_events(ev, np.arange(4), anchors=A, dtype=jnp.float64), ur.Config(n_fix=8))
    assert not int(runs["ok"].status) & errors.MASKED_INPUT and int(runs["ok"].n_height_used) == 2
    for name in ("nan", "inf"):
        res = runs[name]
        assert int(res.status) & errors.MASKED_INPUT, name
        assert int(res.n_height_used) == 1 and int(res.n_height_gated) == 0, name
        assert np.all(np.isfinite(np.asarray(res.pos))), name


# --- 6: startup called eagerly compiles once --------------------------------------------------

def test_startup_second_eager_call_compiles_nothing_and_equals_jit():
    t, aid, z, P = _walk()
    ur.startup(t, aid, z, P, np.arange(4), 10.0)
    z2 = z + 0.01
    with compilation.account() as acc:
        su = ur.startup(t, aid, z2, P, np.arange(4), 12.0)
        jax.block_until_ready(su)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    ref = jax.jit(ur.startup, static_argnames="iters")(t, aid, z2, P, np.arange(4), 12.0)
    for a, b in zip(su, ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)


# --- 7: start-up inputs ------------------------------------------------------------------------

def test_startup_inputs_checked():
    t, aid, z, P = _walk()
    ids = np.arange(4)
    with pytest.raises(InputError, match=r"^t_window: "):
        ur.startup(t, aid, z, P, ids, np.nan)
    with pytest.raises(InputError, match=r"^t_window: .*empty"):
        ur.startup(t, aid, z, P, ids, -1.0)
    with pytest.raises(InputError, match=r"^tag_pos: "):
        ur.startup(t, aid, z, P[:10], ids, 15.0)
    with pytest.raises(InputError, match=r"^sigma_r: "):
        ur.startup(t, aid, z, P, ids, 15.0, sigma_r=-0.1)
    t3, aid3, z3, P3 = _walk(n_anchors=3)  # anchor 3 never ranged
    with pytest.raises(InputError, match=r"^anchor_ids: anchor 3 "):
        ur.startup(t3, aid3, z3, P3, ids, 15.0)


def test_run_refuses_a_startup_of_other_anchors():
    t, aid, z, P = _walk()
    su3 = ur.startup(t, aid, z, P, np.arange(3), 10.0)
    ev = ur.util_events(t, aid, z, t_start=10.0 + 1e-9)
    with pytest.raises(InputError, match=r"^log\.startup\.anchors: "):
        ur.run(ur.log_from_events(ev, np.arange(4), startup=su3))


# --- 8: Config -----------------------------------------------------------------------------------

@pytest.mark.parametrize("cfg, name", [(dict(capacity=5.7), "capacity"), (dict(capacity=True), "capacity"),
                                       (dict(height="no"), "height"), (dict(smooth="no"), "smooth")])
def test_config_checked(cfg, name):
    t = np.arange(20) * 0.05
    aid = np.arange(20) % 4
    r = np.linalg.norm(np.array([1.0, 1.5, 0.5]) - A4[aid], axis=1)
    log = ur.log_from_events(ur.util_events(t, aid, r), np.arange(4), anchors=A4, dtype=jnp.float64)
    with pytest.raises(InputError, match=rf"^config\.{name}: "):
        ur.run(log, ur.Config(n_fix=8, **cfg))
