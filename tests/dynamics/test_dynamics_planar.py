"""Planar motion models (``jaxslam.dynamics.planar``): the review of 2026-12-07's findings, each
against a closed form."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.dynamics import integrators, planar
from jaxslam.errors import InputError


@pytest.mark.parametrize("w", [1.01e-4, 3e-4, 1e-3, 1e-2, 0.05, 0.0999, 0.3])
def test_unicycle_turn_rate_gradient_in_float32(w):
    """x' of a unicycle from the origin at unit speed over 1 s is sin(w)/w; its derivative in w is
    (w cos w − sin w)/w².  Above the old Taylor cut-off (1e-4) float32 autodiff of sin(w)/w cancelled:
    23× off at w = 1.01e-4."""
    grad = jax.grad(lambda t: planar.unicycle(jnp.zeros(3, jnp.float32), jnp.stack([jnp.float32(1), t]), 1.0)[0])
    want = (w * np.cos(w) - np.sin(w)) / w**2
    assert float(grad(jnp.float32(w))) == pytest.approx(want, rel=1e-4)
    x = planar.unicycle(jnp.zeros(3, jnp.float32), jnp.array([1.0, w], jnp.float32), 1.0)
    np.testing.assert_allclose(np.asarray(x[:2], np.float64), [np.sin(w) / w, (1 - np.cos(w)) / w], rtol=1e-6)
    assert float(x[2]) == pytest.approx(w, abs=1e-6)  # (wrap_angle: absolute precision ~eps·π)


def test_unicycle_float64_branch_unchanged():
    """float64 keeps its 1e-4 switch: the value and the derivative against the closed forms."""
    for w in (5e-5, 2e-4, 0.3):
        x = planar.unicycle(jnp.zeros(3), jnp.array([1.0, w]), 1.0)
        # (1 − cos w)/w as 2 sin²(w/2)/w: the direct NumPy form cancels at w = 5e-5 (1e-7 relative)
        np.testing.assert_allclose(np.asarray(x[:2]), [np.sin(w) / w, 2 * np.sin(w / 2) ** 2 / w], rtol=1e-14)
        assert float(x[2]) == pytest.approx(w, abs=1e-15)


@pytest.mark.parametrize("fn", [planar.unicycle, planar.ackermann])
def test_planar_steps_refuse_wrong_shapes(fn):
    """An index past the end was clamped: a (2,) pose read y as its heading, a (1,) input v as ω."""
    with pytest.raises(InputError, match=r"^s: .* shape \(3,\), got \(2,\)"):
        fn(jnp.array([1.0, 2.0]), jnp.array([1.0, 0.1]), 0.1)
    with pytest.raises(InputError, match=r"^u: .* shape \(2,\), got \(1,\)"):
        fn(jnp.zeros(3), jnp.array([1.0]), 0.1)
    with pytest.raises(InputError, match=r"^s: .* got \(4,\)"):
        fn(jnp.zeros(4), jnp.array([1.0, 0.1]), 0.1)
    jax.vmap(lambda s: fn(s, jnp.array([1.0, 0.1]), 0.1))(jnp.zeros((5, 3)))  # per pose under vmap


def test_rollout_names_its_own_argument():
    with pytest.raises(InputError, match=r"^us: expected shape \(T, m\)"):
        integrators.rollout(lambda x, u: -x + u, jnp.zeros(2), jnp.zeros(4), 0.1)

