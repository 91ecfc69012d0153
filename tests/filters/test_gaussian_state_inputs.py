"""A belief passed to a Gaussian filter's step that is not a (mean, cov) pair of arrays: an
InputError naming ``state``, where None gave a bare TypeError ("cannot unpack") and the
(Gaussian, info) pair an update returns gave NumPy's "inhomogeneous shape" ValueError; lists
are read as arrays (jnp.result_type of a list raised a bare TypeError)."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.filters import ekf, sqrt_ekf, sqrt_ukf, ukf
from jaxslam.filters.gaussian import Gaussian


def _f(x, u):
    return jnp.array([x[0] + 0.1 * x[1], x[1]])


def _h(x):
    return x[:1]


G = Gaussian(jnp.array([0.5, 0.1]), jnp.array([[1.0, 0.2], [0.2, 2.0]]))


@pytest.mark.parametrize("step", ["ekf.predict", "ekf.update", "ukf.predict", "sqrt_ekf.predict", "sqrt_ukf.predict"])
def test_a_state_that_is_not_a_mean_cov_pair_is_named(step):
    call = {"ekf.predict": lambda s: ekf.predict(s, _f, None, jnp.eye(2)),
            "ekf.update": lambda s: ekf.update(s, jnp.array([0.3]), _h, jnp.eye(1)),
            "ukf.predict": lambda s: ukf.predict(s, _f, None, jnp.eye(2)),
            "sqrt_ekf.predict": lambda s: sqrt_ekf.predict(s, _f, None, jnp.eye(2)),
            "sqrt_ukf.predict": lambda s: sqrt_ukf.predict(s, _f, None, jnp.eye(2))}[step]
    second = "chol" if step.startswith("sqrt") else "cov"
    moments = (G.mean, jnp.linalg.cholesky(G.cov)) if second == "chol" else G
    with pytest.raises(InputError, match=rf"^state: expected a Gaussian \(mean, {second}\), got NoneType"):
        call(None)
    with pytest.raises(InputError, match=rf"^state: expected a Gaussian \(mean, {second}\), got ArrayImpl"):
        call(jnp.zeros(2))
    pair = ekf.update(G, jnp.array([0.3]), _h, jnp.eye(1))  # (Gaussian, UpdateInfo)
    with pytest.raises(InputError, match=r"^state: .*whose mean is a Gaussian .*pass its first item"):
        call(pair)
    with pytest.raises(InputError, match=r"^state\.mean: expected an array of numbers"):
        call(([0.5, [0.1]], moments[1]))
    # lists are the arrays they hold
    want, got = call(moments), call(tuple(np.asarray(m).tolist() for m in moments))
    want, got = (r if hasattr(r, "_fields") and r._fields[0] == "mean" else r[0] for r in (want, got))
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_list_pair_is_a_state_and_a_gate_covers_the_components_the_mask_lets_through():
    post = ekf.predict([G.mean, G.cov], _f, None, jnp.eye(2))
    np.testing.assert_array_equal(np.asarray(post.cov), np.asarray(ekf.predict(G, _f, None, jnp.eye(2)).cov))
    # chi2_gate(p, 2) on a 3-component measurement whose mask keeps 2: the gate's own size
    s3 = Gaussian(jnp.zeros(3), jnp.eye(3))
    keep2 = jnp.array([True, True, False])
    got = ekf.update(s3, jnp.ones(3), lambda x: x, jnp.eye(3), mask=keep2, gate=ekf.chi2_gate(0.99, 2))
    want = ekf.update(s3, jnp.ones(3), lambda x: x, jnp.eye(3), mask=keep2, gate=ekf.chi2_gate(0.99, 3))
    np.testing.assert_array_equal(np.asarray(got[0].mean), np.asarray(want[0].mean))
    assert int(got[1].status) == 0
    with pytest.raises(InputError, match=r"^gate: built for at most 2 valid components .*the mask lets 3 through"):
        ekf.update(s3, jnp.ones(3), lambda x: x, jnp.eye(3), mask=jnp.ones(3, bool), gate=ekf.chi2_gate(0.99, 2))
