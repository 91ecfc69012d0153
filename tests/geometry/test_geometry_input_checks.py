"""Bad input to jaxslam.geometry raises InputError naming the function's argument; integer
inputs of the angle functions are promoted to float."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.geometry import euler as eu
from jaxslam.geometry import quaternion as qu


@pytest.mark.parametrize("call, msg", [
    (lambda: qu.qnormalize(jnp.ones(3)), r"^qnormalize: q expected shape \(\.\.\., 4\)"),
    (lambda: qu.qcanonical(jnp.ones(3)), r"^qcanonical: q expected shape \(\.\.\., 4\)"),
    (lambda: eu.rotate_jacobian(jnp.ones(3), jnp.ones(2)), r"^rotate_jacobian: v expected shape \(3,\)"),
    (lambda: eu.rotate_jacobian(jnp.ones(2), jnp.ones(3)), r"^rotate_jacobian: euler expected shape \(3,\)"),
    (lambda: eu.rotate_jacobian(jnp.ones(3), jnp.ones(3), C=jnp.eye(2)), r"^rotate_jacobian: C expected shape"),
    (lambda: eu.unrotate_jacobian(jnp.ones(3), jnp.ones(4)), r"^unrotate_jacobian: d expected shape \(3,\)"),
])
def test_geometry_refuses_bad_shapes(call, msg):
    with pytest.raises(InputError, match=msg):
        call()


def test_jacobians_accept_lists():
    e, v = [0.1, 0.2, 0.3], [1.0, 2.0, 3.0]
    np.testing.assert_allclose(np.asarray(eu.rotate_jacobian(e, v)),
                               np.asarray(eu.rotate_jacobian(jnp.asarray(e), jnp.asarray(v))))
    np.testing.assert_allclose(np.asarray(eu.unrotate_jacobian(e, v)),
                               np.asarray(eu.unrotate_jacobian(jnp.asarray(e), jnp.asarray(v))))


def test_integer_inputs_are_promoted():
    np.testing.assert_allclose(np.asarray(qu.qexp(jnp.array([1, 0, 0]))),
                               np.asarray(qu.qexp(jnp.array([1.0, 0.0, 0.0]))))
    np.testing.assert_allclose(np.asarray(eu.euler_from_dcm(jnp.eye(3, dtype=int))), np.zeros(3), atol=0)
    np.testing.assert_allclose(np.asarray(qu.quat_from_dcm(jnp.eye(3, dtype=int))), [1.0, 0, 0, 0])
    np.testing.assert_allclose(np.asarray(qu.qlog(jnp.array([1, 0, 0, 0]))), np.zeros(3))
