"""Paper 000 eq. 2-3 model: values and Jacobians against the NumPy oracle."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dyn_oracles_np as orc
from jaxslam.dynamics import PAPER000, QuadParams, as_arrays, linearize
from jaxslam.dynamics import euler_ned as en
from jaxslam.errors import InputError

M, J, G = 1.56, (0.1147, 0.0576, 0.1712), 9.81  # Table 1 of paper 000, typed here

# Tests call jitted wrappers: eager op-by-op dispatch is slower than one compile.
f_j = jax.jit(en.f)
lin_j = jax.jit(linearize, static_argnums=0)


def random_state(rng):
    x = rng.normal(size=12)
    x[6:9] = rng.uniform([-1.2, -1.3, -3.0], [1.2, 1.3, 3.0])
    return x


def random_input(rng):
    return np.r_[rng.uniform(5.0, 25.0), rng.normal(scale=0.5, size=3)]


def test_slices():
    x = np.arange(12.0)
    assert x[en.POS].tolist() == [0, 1, 2]
    assert x[en.VEL].tolist() == [3, 4, 5]
    assert x[en.ATT].tolist() == [6, 7, 8]
    assert x[en.RATE].tolist() == [9, 10, 11]


def test_f_matches_oracle():
    rng = np.random.default_rng(0)
    for _ in range(10):
        x, u = random_state(rng), random_input(rng)
        np.testing.assert_allclose(f_j(x, u, PAPER000), orc.f000(x, u, M, J, G), rtol=1e-12, atol=1e-12)


def test_hand_jacobians_match_linearize():
    rng = np.random.default_rng(1)
    for _ in range(10):
        x, u = random_state(rng), random_input(rng)
        A, B = lin_j(en.f, x, u, PAPER000)
        A0, B0 = orc.jac000(x, u, M, J, G)
        np.testing.assert_allclose(A, A0, rtol=0, atol=1e-9)
        np.testing.assert_allclose(B, B0, rtol=0, atol=1e-9)
        # The hand Jacobian itself is checked once against central differences
        # of the oracle so that a shared derivation slip cannot pass silently.
    h = 1e-6
    Afd = np.stack(
        [(orc.f000(x + h * e, u, M, J, G) - orc.f000(x - h * e, u, M, J, G)) / (2 * h) for e in np.eye(12)],
        axis=1,
    )
    np.testing.assert_allclose(A0, Afd, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_hover_is_equilibrium(dtype):
    rng = np.random.default_rng(2)
    run = jax.jit(lambda pos, yaw: (lambda x, u: (x, u, en.f(x, u, PAPER000)))(
        en.hover_state(pos, yaw, dtype=dtype), en.hover_input(PAPER000, dtype=dtype)))
    for _ in range(5):
        pos, yaw = rng.normal(size=3) * 10, rng.uniform(-np.pi, np.pi)
        x, u, xd = run(pos, yaw)
        assert x.dtype == dtype and u.dtype == dtype and xd.dtype == dtype
        np.testing.assert_allclose(np.asarray(x, float)[[0, 1, 2, 8]], [*pos, yaw], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(u), [M * G, 0, 0, 0], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(xd), 0.0, atol=1e-5 if dtype == np.float32 else 1e-13)


def test_hover_input_default_dtype_from_array_params():
    p = as_arrays(PAPER000, jnp.float32)
    assert en.hover_input(p).dtype == jnp.float32


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_follows_state(dtype):
    rng = np.random.default_rng(3)
    x, u = random_state(rng).astype(dtype), random_input(rng)  # u float64 on purpose
    xd = f_j(x, u, PAPER000)
    assert xd.dtype == dtype
    tol = 1e-4 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(xd, orc.f000(x.astype(float), u, M, J, G), rtol=tol, atol=tol)
    A, B = lin_j(en.f, x, u.astype(dtype), as_arrays(PAPER000, dtype))
    assert A.dtype == dtype and B.dtype == dtype


def test_vmap_and_param_gradient():
    rng = np.random.default_rng(4)
    xs = np.stack([random_state(rng) for _ in range(6)])
    us = np.stack([random_input(rng) for _ in range(6)])
    out = jax.jit(jax.vmap(en.f, in_axes=(0, 0, None)))(xs, us, PAPER000)
    ref = np.stack([orc.f000(x, u, M, J, G) for x, u in zip(xs, us)])
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
    # d v̇_z / d m = f_T / m² in a level attitude (closed form).
    x = np.zeros(12)
    u = np.array([20.0, 0, 0, 0])
    gm = jax.jit(jax.grad(lambda m: en.f(x, u, QuadParams(m, J, G))[5]))(1.56)
    np.testing.assert_allclose(gm, 20.0 / 1.56**2, rtol=1e-12)


def test_bad_inputs_raise():
    with pytest.raises(InputError, match="^x:"):
        en.check_state(np.zeros(11))
    with pytest.raises(InputError, match="^x0:"):
        en.check_state(np.zeros((2, 12)), name="x0")
    with pytest.raises(InputError, match="^x:"):
        en.check_state(np.full(12, np.nan))
    with pytest.raises(InputError, match="^u:"):
        en.check_input(np.zeros(3))
    with pytest.raises(InputError, match="^u:"):
        en.check_input(np.array(["a"] * 4))
    assert en.check_state(np.zeros(12)).shape == (12,)
    assert en.check_input(np.zeros(4)).shape == (4,)


def test_f_checks_shapes_and_promotes_an_integer_state():
    """A (13,) state used to be sliced silently and a (3,) input gave a deep index error; an
    integer state truncated the thrust to an integer.  Shapes are static: checked under jit too."""
    with pytest.raises(InputError, match=r"^x: expected shape \(12\)"):
        en.f(np.zeros(13), np.zeros(4), PAPER000)
    with pytest.raises(InputError, match=r"^u: expected shape \(4\)"):
        jax.jit(lambda x, u: en.f(x, u, PAPER000))(jnp.zeros(12), jnp.zeros(3))
    u = np.array([1.5, 0.0, 0.0, 0.0])
    xdot = en.f(np.zeros(12, dtype=int), u, PAPER000)
    assert jnp.issubdtype(xdot.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(xdot), np.asarray(en.f(np.zeros(12), u, PAPER000)), rtol=1e-6)
