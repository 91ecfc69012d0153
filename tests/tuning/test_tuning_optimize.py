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


def test_minibatches_need_a_key_and_converge():
    items = jnp.arange(8.0)[:, None] * jnp.ones((1, 2))
    with pytest.raises(InputError, match="key"):
        O.fit(_quad, {"a": jnp.zeros(2)}, items, steps=2, batch_size=4)
    res = O.fit(_quad, {"a": jnp.zeros(2)}, items, steps=200, lr=0.2, batch_size=4, key=jax.random.PRNGKey(0))
    np.testing.assert_allclose(np.asarray(res.theta["a"]), [3.5, 3.5], atol=0.6)


@pytest.mark.parametrize("kw, needle", [
    (dict(lr=-1.0), "--lr"), (dict(steps=0), "--steps"), (dict(batch_size=9), "batch_size"),
    (dict(eval_every=-1), "eval_every"), (dict(clip=0.0), "clip"),
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
