"""Central finite differences as the oracle of a gradient: each component of θ (a dict of 1-D
arrays, or one 1-D array) moved by ±h, the loss evaluated twice, compared with the autodiff
gradient to a relative tolerance (with a floor for components near zero)."""

import jax.numpy as jnp


def assert_gradient_matches(loss, grad, theta, h=1e-5, rtol=1e-4, floor=1e-2):
    """``grad`` (same structure as ``theta``) against central differences of ``loss(theta)``:
    |ad − fd| ≤ rtol · max(|fd|, floor) for every component."""
    items = theta.items() if isinstance(theta, dict) else [(None, theta)]
    for name, v in items:
        for i in range(v.shape[0]):
            e = jnp.zeros_like(v).at[i].set(h)

            def moved(d):
                return {**theta, name: v + d} if name is not None else v + d

            fd = (float(loss(moved(e))) - float(loss(moved(-e)))) / (2 * h)
            ad = float((grad[name] if name is not None else grad)[i])
            assert abs(ad - fd) <= rtol * max(abs(fd), floor), (name, i, ad, fd)


def assert_target_gradient(target, theta=None, **kw):
    """:func:`assert_gradient_matches` for a tuning target's loss on its first training item, at
    ``theta`` (default: the target's starting point).  Returns the loss there."""
    import jax

    item = jax.tree.map(lambda a: a[0], target.train)
    theta = target.theta0 if theta is None else theta
    f = jax.jit(lambda th: target.loss_fn(th, item))
    assert_gradient_matches(f, jax.jit(jax.grad(lambda th: target.loss_fn(th, item)))(theta), theta, **kw)
    return float(f(theta))
