"""Paper 003's UWB noise as a tuning target (registered when the UWB system is installed)."""

import jax
import jax.flatten_util
import numpy as np

from jaxslam.tuning import targets as T


def test_uwb_targets_are_registered():
    avail = T.available()
    for sc in ("circle", "square", "rough"):
        assert avail[(f"uwb-{sc}", "noise")] == ("mse", "nees")


# ~20 s (compiles the UWB filter's gradient)
def test_uwb_mse_gradient_and_descent():
    tg = T.get("uwb-circle", "noise", "mse", train_runs=2, test_runs=1)
    item = jax.tree.map(lambda a: a[0], tg.train)
    vg = jax.jit(jax.value_and_grad(tg.loss_fn))
    v, g = vg(tg.theta0, item)
    flat, unravel = jax.flatten_util.ravel_pytree(tg.theta0)
    gf = np.asarray(jax.flatten_util.ravel_pytree(g)[0])
    d = np.random.default_rng(0).normal(size=flat.shape[0])
    d /= np.linalg.norm(d)
    h = 1e-5
    fd = (float(vg(unravel(flat + h * d), item)[0]) - float(vg(unravel(flat - h * d), item)[0])) / (2 * h)
    assert abs(fd - gf @ d) <= 1e-4 * abs(gf @ d)
    # A small step against the gradient lowers the loss (the same compiled function).
    theta1 = unravel(flat - 0.1 * gf / np.linalg.norm(gf))
    assert float(vg(theta1, item)[0]) < float(v)
    # The saved form is the scenario's own --params form.
    from jaxslam.sim.scenarios import uwb

    fp, _ = uwb._filter_params({"model": "squared", "filter": "paper", "dt": 1.0}, np.float64,
                               tg.to_params(tg.physical(theta1)))
    np.testing.assert_allclose(np.asarray(fp.Q), np.asarray(tg.physical(theta1).Q), rtol=1e-12)
