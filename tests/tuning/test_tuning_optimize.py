"""The optimisation loop: convergence, NaN stop with last good parameters, skipped gradients."""

import jax.numpy as jnp
import numpy as np
import pytest

import jax
from jaxslam.errors import InputError
from jaxslam.tuning import optimize as O


def _quad(theta, item):
    return jnp.sum((theta["a"] - item) ** 2)


def test_converges_to_batch_mean_and_records_history():
    items = jnp.asarray([[1.0, -2.0], [3.0, 0.0], [2.0, 1.0]])
    seen = []
    res = O.fit(_quad, {"a": jnp.zeros(2)}, items, steps=150, lr=0.2, test=items[:1], eval_every=50,
                callback=seen.append, describe=lambda th: {"a": [float(v) for v in th["a"]]})
    np.testing.assert_allclose(np.asarray(res.theta["a"]), [2.0, -1.0 / 3.0], atol=2e-3)
    assert res.stopped is None and res.n_skipped == 0
    assert len(res.history) == 151 and len(seen) == 151
    assert [h["step"] for h in res.history if "test_loss" in h] == [0, 50, 100, 150]
    assert res.history[-1]["loss"] < res.history[0]["loss"]
    assert "params" in res.history[0] and res.history[0]["params"]["a"] == [0.0, 0.0]
    assert res.compile_s > 0 and res.memory["peak_rss_mb"] > 0
    # Test loss at the end is the loss of the returned parameters on the held-out item.
    np.testing.assert_allclose(res.history[-1]["test_loss"], float(_quad(res.theta, items[0])), rtol=1e-12)


def test_nan_loss_stops_with_last_good_parameters():
    def loss(theta, item):  # finite below 1.5, NaN above (e.g. a diverged filter)
        t = theta["a"][0]
        return jnp.where(t < 1.5, (t - 3.0) ** 2, jnp.nan) + 0.0 * item

    res = O.fit(loss, {"a": jnp.zeros(1)}, jnp.zeros(2), steps=200, lr=0.3)
    assert res.stopped is not None and "non-finite" in res.stopped and "last" in res.stopped
    good = float(res.theta["a"][0])
    assert np.isfinite(float(loss(res.theta, 0.0))) and 0.0 < good < 1.5
    last = res.history[-1]
    assert not np.isfinite(last["loss"]) and last["step"] < 200
    # The kept parameters are those of the previous record, whose loss was finite.
    np.testing.assert_allclose(res.history[-2]["loss"], (good - 3.0) ** 2, rtol=1e-12)


def test_non_finite_gradient_is_skipped_never_applied():
    def loss(theta, item):  # finite value, NaN gradient at a = 0 (d|a|^½/da)
        return jnp.sqrt(jnp.abs(theta["a"][0])) + 0.0 * item

    res = O.fit(loss, {"a": jnp.zeros(1)}, jnp.zeros(3), steps=20, lr=0.1, max_skips=3)
    assert res.n_skipped == 3 and float(res.theta["a"][0]) == 0.0
    assert all(h["skipped"] for h in res.history) and len(res.history) == 3
    assert "never applied" in res.stopped


def _diverging(theta, item):
    """Item 9 is a diverged run: NaN loss at every θ; item 7 explodes once a > 0.5 (1e6 × its
    loss); the others are plain quadratics."""
    q = _quad(theta, item)
    q = jnp.where((item[0] == 7.0) & (theta["a"][0] > 0.5), 1e6 * (1.0 + q), q)
    return jnp.where(item[0] == 9.0, jnp.nan, q)


@pytest.mark.parametrize("sequential", [False, True])
def test_a_diverged_run_is_left_out_and_counted_never_averaged(sequential):
    """One NaN run in the batch: every step goes on with the other runs (same iterates as a fit
    on those runs alone, the oracle), the run is named in each record and counted."""
    good = jnp.asarray([[1.0, -2.0], [3.0, 0.0]])
    items = jnp.concatenate([good, jnp.asarray([[9.0, 9.0]])])
    ref = O.fit(_quad, {"a": jnp.zeros(2)}, good, steps=30, lr=0.2, sequential=sequential)
    res = O.fit(_diverging, {"a": jnp.zeros(2)}, items, steps=30, lr=0.2, sequential=sequential)
    assert res.stopped is None and res.n_skipped == 0
    assert res.n_dropped == 31 and all(h["dropped_runs"] == [2] for h in res.history)
    np.testing.assert_allclose(np.asarray(res.theta["a"]), np.asarray(ref.theta["a"]), rtol=1e-12)
    np.testing.assert_allclose([h["loss"] for h in res.history], [h["loss"] for h in ref.history], rtol=1e-12)
    # Without the other runs nothing is left: the NaN mean stops the fit at once.
    alone = O.fit(_diverging, {"a": jnp.zeros(2)}, items[2:], steps=5, lr=0.2, sequential=sequential)
    assert alone.stopped is not None and "non-finite" in alone.stopped and alone.n_dropped == 0


def test_an_exploding_run_is_left_out_only_with_explode_ratio():
    items = jnp.asarray([[1.0, -2.0], [3.0, 0.0], [7.0, 0.0]])
    res = O.fit(_diverging, {"a": jnp.zeros(2)}, items, steps=40, lr=0.2, explode_ratio=1e3)
    dropped = [h["step"] for h in res.history if h.get("dropped_runs")]
    assert dropped and all(h["dropped_runs"] == [2] for h in res.history if h.get("dropped_runs"))
    assert res.n_dropped == len(dropped) and res.history[0].get("dropped_runs") is None  # a = 0: not exploding
    for h in res.history:  # the recorded loss never contains the exploding run
        assert h["loss"] < 1e3
    plain = O.fit(_diverging, {"a": jnp.zeros(2)}, items, steps=40, lr=0.2)
    assert plain.n_dropped == 0 and max(h["loss"] for h in plain.history) > 1e5


def test_minibatches_need_a_key_and_converge():
    items = jnp.arange(8.0)[:, None] * jnp.ones((1, 2))
    with pytest.raises(InputError, match="key"):
        O.fit(_quad, {"a": jnp.zeros(2)}, items, steps=2, batch_size=4)
    res = O.fit(_quad, {"a": jnp.zeros(2)}, items, steps=200, lr=0.2, batch_size=4, key=jax.random.PRNGKey(0))
    np.testing.assert_allclose(np.asarray(res.theta["a"]), [3.5, 3.5], atol=0.6)


@pytest.mark.parametrize("kw, needle", [
    (dict(lr=-1.0), "--lr"), (dict(steps=0), "--steps"), (dict(batch_size=9), "batch_size"),
    (dict(eval_every=-1), "eval_every"), (dict(clip=0.0), "clip"), (dict(explode_ratio=1.0), "explode_ratio"),
    (dict(explode_ratio=float("nan")), "explode_ratio"),
])
def test_bad_arguments(kw, needle):
    args = dict(steps=2, lr=0.1)
    args.update(kw)
    with pytest.raises(InputError, match=needle):
        O.fit(_quad, {"a": jnp.zeros(2)}, jnp.zeros((3, 2)), **args)


def test_schedule_warms_up_and_decays():
    tx, sched = O.make_optimizer(0.5, 100)
    assert float(sched(0)) == pytest.approx(0.05)
    assert float(sched(5)) == pytest.approx(0.5)
    assert float(sched(100)) == pytest.approx(0.025)
    _, const = O.make_optimizer(0.5, 100, schedule="constant")
    assert float(const(77)) == 0.5


def test_log_objective_descends_log_of_mean_and_records_plain_loss():
    """d log f = df / f: with a positive loss the two objectives share the minimiser."""
    items = jnp.asarray([[1.0, -2.0], [3.0, 0.0]])
    res = O.fit(lambda th, it: 0.5 + _quad(th, it), {"a": jnp.zeros(2)}, items, steps=150, lr=0.2,
                log_objective=True)
    np.testing.assert_allclose(np.asarray(res.theta["a"]), [2.0, -1.0], atol=2e-3)
    # The history holds the mean loss itself (not its log): at θ = 0 it is 0.5 + (1+4+9+0)/2.
    assert res.history[0]["loss"] == pytest.approx(7.5)
    with pytest.raises(InputError, match="b2"):
        O.make_optimizer(0.1, 10, b2=1.0)


def test_fit_names_bad_parameters_and_batches_before_compiling():
    items = jnp.asarray([[1.0, -2.0], [3.0, 0.0]])
    cases = [
        (dict(theta0={"a": jnp.zeros(2, jnp.int32)}), r"^theta0: parameters must be floating-point"),
        (dict(theta0={"a": jnp.array([0.0, jnp.nan])}), r"^theta0: contains NaN or Inf"),
        (dict(theta0={}), r"^theta0: no parameters"),
        (dict(train=jnp.zeros((0, 2))), r"^train: every array needs the same leading axis of runs \(≥ 1\)"),
        (dict(train=(items, jnp.zeros((3, 2)))), r"^train: every array needs the same leading axis"),
        (dict(max_skips=-1), r"^max_skips: must be an int >= 0"),
        (dict(warmup=-2), r"^warmup: must be an int >= 0"),
    ]
    for change, msg in cases:
        a = dict(theta0={"a": jnp.zeros(2)}, train=items, max_skips=3, warmup=None)
        a.update(change)
        loss = _quad if not isinstance(a["train"], tuple) else (lambda th, it: _quad(th, it[0]))
        with pytest.raises(InputError, match=msg):
            O.fit(loss, a["theta0"], a["train"], steps=2, max_skips=a["max_skips"], warmup=a["warmup"])
