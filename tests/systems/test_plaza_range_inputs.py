"""Plaza range-only SLAM: malformed input named early, and the public ``step`` with ``PARAMS``.

Review of 2026-12-07: ``plaza_events`` cast fractional / NaN node ids onto other ids and reshaped a
transposed ``dr`` or a two-column ``td_range`` into wrong pairs; ``log_from_events`` truncated
beacon ids; ``run`` took a fractional / zero / text ``config.capacity`` and a ``min_points`` no
buffer can reach; ``step`` failed with the module's own ``PARAMS``.  The expected messages and
values are written by hand.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.systems import plaza_range as pr

T_DR = np.arange(1, 31) * 0.2
U = np.c_[np.full(30, 0.2), np.arange(30) * 0.001]
T_R = T_DR[::3]
NODE = np.array([10, 11, 12] * 4)[:10]
RR = 5.0 + np.arange(10)
BEACONS = np.array([[5.0, 0.0], [0.0, 5.0], [-5.0, 0.0]])
BIDS = np.array([10, 11, 12])


def test_plaza_events_keeps_well_formed_pairs():
    # (M, 1) ranges and float whole-number node ids are accepted; the ranges come back as given
    ev = pr.plaza_events(T_DR, U, T_R, NODE.astype(float), RR[:, None])
    m = np.asarray(ev.mask)
    np.testing.assert_array_equal(np.asarray(ev.z)[..., 0][m], RR)
    np.testing.assert_array_equal(np.asarray(ev.ids)[m], NODE)
    u = np.asarray(ev.u)
    np.testing.assert_allclose(u[np.any(u != 0, axis=1)][1:4], U[1:4], rtol=0, atol=0)


@pytest.mark.parametrize("change, msg", [
    (dict(td_node=NODE + 0.7), r"^td_node: expected whole-number"),  # cast to 10, 11, 12 before
    (dict(td_node=np.where(np.arange(10) == 0, np.nan, NODE)), r"^td_node: expected whole-number"),
    (dict(dr=U.T.copy()), r"^dr: expected shape \(30, 2\)"),  # reshaped into wrong pairs before
    (dict(dr=np.c_[T_DR, U]), r"^dr: expected shape \(30, 2\)"),  # named inputs/input_t before
    (dict(td_range=np.c_[RR, RR + 100]), r"^td_range: expected shape \(10,\)"),  # interleaved before
    (dict(td_range=RR[:9]), r"^td_range: expected shape \(10,\)"),
    (dict(td_node=NODE[:9]), r"^td_node: expected shape \(10,\)"),  # bare IndexError before
])
def test_plaza_events_names_malformed_input(change, msg):
    a = dict(dr_t=T_DR, dr=U, td_t=T_R, td_node=NODE, td_range=RR)
    a.update(change)
    with pytest.raises(InputError, match=msg):
        pr.plaza_events(**a)


@pytest.mark.parametrize("bids", [np.array([10.0, 11.0, 12.9]), np.array([10.0, 11.0, np.nan])])
def test_log_from_events_refuses_fractional_beacon_ids(bids):
    ev = pr.plaza_events(T_DR, U, T_R, NODE, RR)
    assert np.asarray(pr.log_from_events(ev, np.zeros(3), BIDS.astype(float)).beacon_ids).tolist() == [10, 11, 12]
    with pytest.raises(InputError, match=r"^beacon_ids: expected whole-number"):  # 12.9 -> 12 before
        pr.log_from_events(ev, np.zeros(3), bids)


def _log(beacons=None):
    rr = np.linalg.norm(BEACONS[np.arange(10) % 3], axis=1)
    ev = pr.plaza_events(T_DR, np.tile([0.2, 0.01], (30, 1)), T_R, NODE, rr)
    return pr.log_from_events(ev, np.zeros(3), BIDS, beacons=beacons, dtype=jnp.float64)


@pytest.mark.parametrize("cap", [3.7, 0, "5", True, -1])
def test_plaza_run_names_a_capacity_that_is_not_a_count(cap):
    with pytest.raises(InputError, match=r"^config\.capacity: expected an int \(beacon slots\) >= 1"):
        pr.run(_log(), pr.Config(capacity=cap), pr.PARAMS)


def test_plaza_run_names_min_points_above_the_window_and_keeps_the_rest():
    with pytest.raises(InputError, match=r"^params\.min_points: 6 exceeds config\.window = 5"):
        pr.run(_log(), pr.Config(window=5), pr.PARAMS._replace(min_points=6, min_spread=0.0))
    with pytest.raises(InputError, match=r"^params\.min_points: 20\.0 exceeds config\.window = 5"):
        pr.run(_log(), pr.Config(window=5, delayed=True), pr.PARAMS)
    with pytest.raises(InputError, match=r"^config\.capacity: 2 < number of beacons 3"):  # unchanged
        pr.run(_log(), pr.Config(capacity=2), pr.PARAMS)
    # surveyed beacons (no delayed initialisation): min_points unused, accepted; slots as given
    r = pr.run(_log(BEACONS), pr.Config(window=5, capacity=np.int64(4)), pr.PARAMS)
    assert r.active.shape == (4,) and int(r.n_registered) == 3


def _event(z1):
    return pr.Event(dt=jnp.asarray(0.1), u=jnp.asarray([0.1, 0.0]), z=jnp.asarray([[10.0], [z1]]),
                    ids=jnp.asarray([0, 1], jnp.int32), mask=jnp.asarray([True, True]))


def test_plaza_step_runs_with_the_module_params():
    """``step`` with ``PARAMS`` (outlier_gate None) failed: "expected numbers, got None".  Robot at
    (0.1, 0) after the increment, surveyed beacons at (10, 0) and (0, 10), bias 0 ± 5 m: the
    ranges 10 and 10.05 are within 0.1 m of the predicted 9.9 and 10.0005 (no outlier); a
    range of 40 is 30 m off, d² ≥ 30² / (σ_r² + σ_b² + p0²) = 900 / 26.45 ≈ 34 > 6.63 (one)."""
    log = pr.Log(t=np.zeros(1), dt=np.full(1, 0.1), u=np.array([[0.1, 0.0]]), z=np.array([[[10.0], [14.0]]]),
                 ids=np.array([[0, 1]]), mask=np.ones((1, 2), bool), pose0=np.zeros(3),
                 beacon_ids=np.array([0, 1, 2]), beacons=np.array([[10.0, 0.0], [0.0, 10.0], [-10.0, 0.0]]))
    cfg = pr.Config(delayed=False)
    st = pr.init(log, cfg, pr.PARAMS)
    st2, out = pr.step(st, _event(10.05), cfg, pr.PARAMS)
    assert int(out.monitored) == 2 and int(out.outliers) == 0
    np.testing.assert_allclose(np.asarray(st2.slam.x[:2]), [0.1, 0.0], atol=0.05)
    _, out = pr.step(st, _event(40.0), cfg, pr.PARAMS)
    assert int(out.monitored) == 2 and int(out.outliers) == 1
