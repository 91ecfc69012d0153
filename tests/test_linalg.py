"""jaxslam.linalg.take / put and their block forms take_blocks / put_blocks: NumPy oracles for
values, plain-indexing and finite-difference oracles for derivatives, and the property they
exist for (no scatter in a derivative)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxslam.errors import InputError
from jaxslam.linalg import put, put_blocks, small_matmul, take, take_blocks


def _prims(jaxpr):
    """Names of every primitive in a (closed) jaxpr, sub-jaxprs included."""
    out = []

    def walk(j):
        for e in j.eqns:
            out.append(e.primitive.name)
            for p in e.params.values():
                for q in p if isinstance(p, (list, tuple)) else [p]:
                    if hasattr(q, "jaxpr") and hasattr(q.jaxpr, "eqns"):
                        walk(q.jaxpr)
                    elif hasattr(q, "eqns"):
                        walk(q)

    walk(jaxpr.jaxpr)
    return out


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_take_equals_numpy(dtype, axis):
    rng = np.random.default_rng(axis)
    a = rng.normal(size=(5, 6, 7)).astype(dtype)
    idx = rng.integers(0, a.shape[axis], size=(3, 2)).astype(np.int32)
    got = np.asarray(jax.jit(take, static_argnums=2)(jnp.asarray(a), jnp.asarray(idx), axis))
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, np.take(a, idx, axis=axis))


@pytest.mark.parametrize("axis", [0, 1])
def test_put_equals_numpy_and_drops_out_of_range(axis):
    rng = np.random.default_rng(1 + axis)
    a = rng.normal(size=(6, 5))
    idx = np.array([4, 0, 99], np.int32)  # 99: out of range, dropped
    vals = rng.normal(size=(3, 5) if axis == 0 else (6, 3))
    want = a.copy()
    for j, i in enumerate(idx):
        if i < a.shape[axis]:
            if axis == 0:
                want[i] = vals[j]
            else:
                want[:, i] = vals[:, j]
    got = np.asarray(put(jnp.asarray(a), jnp.asarray(idx), jnp.asarray(vals), axis))
    np.testing.assert_array_equal(got, want)


def test_take_put_derivatives_equal_plain_indexing_and_fd():
    rng = np.random.default_rng(7)
    a = jnp.asarray(rng.normal(size=(7, 7)))
    v = jnp.asarray(rng.normal(size=(7, 3)))
    idx = jnp.asarray([5, 1, 3], jnp.int32)
    w = jnp.asarray(rng.normal(size=(7, 7)))

    def f(a, v):  # both helpers, nonlinear around them
        cols = take(a, idx, 1)  # (7, 3)
        b = put(a, idx, jnp.sin(cols) * v, 1)
        return jnp.sum(w * b * b) + jnp.sum(take(b, jnp.asarray([[2, 6]]), 0) ** 3)

    def f_plain(a, v):
        cols = a[:, idx]
        b = a.at[:, idx].set(jnp.sin(cols) * v)
        return jnp.sum(w * b * b) + jnp.sum(b[jnp.asarray([[2, 6]])] ** 3)

    f, f_plain = jax.jit(f), jax.jit(f_plain)  # jitted: programs, not one per operation
    np.testing.assert_allclose(f(a, v), f_plain(a, v), rtol=1e-14)
    for g, gp in zip(jax.jit(jax.grad(f, (0, 1)))(a, v), jax.jit(jax.grad(f_plain, (0, 1)))(a, v)):
        np.testing.assert_allclose(g, gp, rtol=1e-12, atol=1e-12)
    check_grads(f, (a, v), order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_derivatives_hold_no_scatter():
    """The point of the helpers: the linearised and the transposed programs gather and scatter
    nothing (XLA's CPU backend runs every scatter as a loop over its indices)."""
    rng = np.random.default_rng(3)
    a = jnp.asarray(rng.normal(size=(9, 9)))
    v = jnp.asarray(rng.normal(size=(9, 2)))
    idx = jnp.asarray([2, 7], jnp.int32)

    def f(a, v):
        return put(a, idx, take(a, idx, 1) * v, 1)

    _, f_lin = jax.linearize(f, a, v)
    lin = _prims(jax.make_jaxpr(f_lin)(a, v))
    f_t = jax.linear_transpose(f_lin, a, v)
    tr = _prims(jax.make_jaxpr(f_t)(a))
    for prims in (lin, tr):
        assert not [p for p in prims if "scatter" in p or p == "gather"], prims
    # ... whereas plain indexing transposes into a scatter-add
    _, p_lin = jax.linearize(lambda a: a[:, idx], a)
    assert any("scatter" in p for p in _prims(jax.make_jaxpr(jax.linear_transpose(p_lin, a))(a[:, idx])))


def test_check_scalar_accepts_and_names_the_argument():
    import numpy as np
    import pytest

    from jaxslam.errors import InputError
    from jaxslam.linalg import check_scalar

    assert check_scalar(3, "p.x") == 3.0 and isinstance(check_scalar(np.float32(2.5), "p.x"), float)
    assert check_scalar(float("inf"), "p.gate", finite=False) == float("inf")
    assert check_scalar(0.0, "p.t", lower=0) == 0.0
    for value, kw, needle in [
        (float("nan"), {"finite": False}, "p.v: expected a number"),
        ([1.0, 2.0], {}, "p.v: expected a finite scalar"),
        (float("inf"), {}, "p.v: expected a finite scalar"),
        (0.0, {"lower": 0, "strict": True}, "p.v: expected a positive finite scalar"),
        (-1e-9, {"lower": 0}, "p.v: expected a non-negative finite scalar"),
        ("abc", {}, "p.v: expected a finite scalar"),
        ("1.5", {}, "p.v: expected a finite scalar"),
        (0.5, {"lower": 1.0}, "p.v: expected a finite scalar >= 1"),
    ]:
        with pytest.raises(InputError, match=needle):
            check_scalar(value, "p.v", **kw)


def test_check_numbers_refuses_strings_and_check_psd_names_them():
    from jaxslam.linalg import check_numbers, check_psd

    np.testing.assert_array_equal(check_numbers([1, 2.5], "p.v"), [1.0, 2.5])
    for value in ("abc", "1.5", ["1", "2"], None, [1.0, None], [[1.0], [1.0, 2.0]], {"a": 1}):
        with pytest.raises(InputError, match="^p.v: expected numbers"):
            check_numbers(value, "p.v")
    with pytest.raises(InputError, match="^params.R: expected numbers"):
        check_psd([["1", "0"], ["0", "1"]], "params.R")


# ---------------------------------------------------------------------------
# Closed-form small inverses and Cholesky factors (NumPy oracles)
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("d", [1, 2, 3])
def test_small_inverse_determinant_and_cholesky_equal_numpy(dtype, d):
    from jaxslam.linalg import cholesky_small, det_small, inv_small

    rng = np.random.default_rng(d)
    A = rng.normal(size=(7, d, d))
    S = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(d)  # SPD batch
    tol = 1e-10 if dtype == np.float64 else 2e-3
    inv, det = jax.jit(inv_small)(jnp.asarray(S, dtype))
    np.testing.assert_allclose(np.asarray(inv), np.linalg.inv(S), rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(det), np.linalg.det(S), rtol=tol)
    np.testing.assert_allclose(np.asarray(jax.jit(det_small)(jnp.asarray(A, dtype))),
                               np.linalg.det(A), rtol=tol, atol=tol)
    L = np.asarray(jax.jit(cholesky_small)(jnp.asarray(S, dtype)))
    np.testing.assert_allclose(L, np.linalg.cholesky(S), rtol=tol, atol=tol)
    assert L.dtype == dtype
    # one matrix (no batch axis), as called inside vmap
    inv1, _ = inv_small(jnp.asarray(S[0], dtype))
    np.testing.assert_allclose(np.asarray(inv1), np.linalg.inv(S[0]), rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(cholesky_small(jnp.asarray(S[0], dtype))),
                               np.linalg.cholesky(S[0]), rtol=tol, atol=tol)


def test_small_cholesky_of_an_indefinite_matrix_is_nan_and_singular_inverse_flags_det():
    from jaxslam.linalg import cholesky_small, inv_small

    assert np.isnan(np.asarray(cholesky_small(jnp.asarray(-np.eye(3))))).any()
    inv, det = inv_small(jnp.ones((3, 3)))
    assert float(det) == 0.0 and np.all(np.isfinite(np.asarray(inv)))
    with pytest.raises(ValueError, match="d <= 4"):
        cholesky_small(jnp.eye(5))


def test_small_cholesky_of_4x4_equals_numpy():
    from jaxslam.linalg import cholesky_small

    A = np.random.default_rng(4).normal(size=(5, 4, 4))
    S = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
    np.testing.assert_allclose(np.asarray(cholesky_small(jnp.asarray(S))), np.linalg.cholesky(S),
                               rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("shapes", [((9, 9), (9, 9)), ((9, 6), (6, 9)), ((3, 1), (1, 4)), ((20, 9), (9, 20))])
def test_small_matmul_equals_numpy_product_and_its_derivative(shapes, dtype):
    """small_matmul against NumPy's A @ B (broadcast-sum below the limit, ``@`` above), and its
    JVP against the product rule."""
    rng = np.random.default_rng(sum(shapes[0]) + sum(shapes[1]))
    A, B = rng.normal(size=shapes[0]), rng.normal(size=shapes[1])
    out = np.asarray(small_matmul(jnp.asarray(A, dtype), jnp.asarray(B, dtype)))
    assert out.dtype == dtype
    tol = 1e-13 if dtype == np.float64 else 1e-5
    np.testing.assert_allclose(out, A @ B, atol=tol * max(1.0, np.abs(A @ B).max()))
    dA, dB = rng.normal(size=A.shape), rng.normal(size=B.shape)
    _, t = jax.jvp(small_matmul, (jnp.asarray(A), jnp.asarray(B)), (jnp.asarray(dA), jnp.asarray(dB)))
    np.testing.assert_allclose(np.asarray(t), dA @ B + A @ dB, atol=1e-12)


# --- block forms: blocks of `size` from `offset` (a filter's landmark blocks after the robot) ---

def _np_blocks(a, blocks, size, offset, axis):
    """NumPy oracle of take_blocks: the blocks stacked on a new axis at ``axis``."""
    nb = (a.shape[axis] - offset) // size
    b = np.clip(blocks, 0, nb - 1)
    idx = offset + size * b[:, None] + np.arange(size)[None, :]
    return np.take(a, idx, axis=axis)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_take_blocks_equals_numpy(dtype, axis):
    rng = np.random.default_rng(10 + axis)
    a = rng.normal(size=(11, 8, 5)).astype(dtype)
    size, offset = {0: (3, 2), 1: (2, 0), 2: (2, 1)}[axis]
    blocks = np.array([2, 0, 7, -1], np.int32)  # 7 and -1 out of range: clipped, as take clips
    got = np.asarray(jax.jit(take_blocks, static_argnums=(2, 3, 4))(jnp.asarray(a), jnp.asarray(blocks),
                                                                     size, offset, axis))
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, _np_blocks(a, blocks, size, offset, axis))


@pytest.mark.parametrize("axis", [0, 1])
def test_put_blocks_equals_numpy_and_drops_out_of_range(axis):
    rng = np.random.default_rng(20 + axis)
    a = rng.normal(size=(11, 11))
    size, offset = 3, 2  # blocks 0..2 at rows 2-4, 5-7, 8-10
    blocks = np.array([2, 3, 0, -1], np.int32)  # 3 and -1 out of range: dropped
    vals = rng.normal(size=(4, 3, 11) if axis == 0 else (11, 4, 3))
    want = a.copy()
    for j, b in enumerate(blocks):
        if 0 <= b < 3:
            sl = slice(offset + size * b, offset + size * (b + 1))
            if axis == 0:
                want[sl] = vals[j]
            else:
                want[:, sl] = vals[:, j]
    got = np.asarray(put_blocks(jnp.asarray(a), jnp.asarray(blocks), jnp.asarray(vals), size, offset, axis))
    np.testing.assert_array_equal(got, want)


def test_block_forms_reject_a_ragged_layout_naming_the_argument():
    with pytest.raises(InputError, match="take_blocks: offset 0 and size 3"):
        take_blocks(jnp.zeros((10, 4)), jnp.asarray([0]), 3, 0, 0)
    with pytest.raises(InputError, match="put_blocks: offset 2 and size 3"):
        put_blocks(jnp.zeros((4, 10)), jnp.asarray([0]), jnp.zeros((4, 1, 3)), 3, 2, 1)
    with pytest.raises(InputError, match="take_blocks: size must be >= 1, got 0"):
        take_blocks(jnp.zeros((10, 4)), jnp.asarray([0]), 0, 0, 0)
    with pytest.raises(InputError, match="offset -1"):
        take_blocks(jnp.zeros((10, 4)), jnp.asarray([0]), 1, -1, 0)


@pytest.mark.parametrize("axis", [0, 1])
def test_block_form_derivatives_equal_plain_indexing(axis):
    """Values and gradients equal plain indexing at the blocks' element indices (the one-hot
    products over blocks are exact), and the derivatives pass finite differences, both modes,
    second order."""
    rng = np.random.default_rng(30 + axis)
    a = jnp.asarray(rng.normal(size=(11, 11)))
    size, offset = 3, 2
    blocks = jnp.asarray([2, 0], jnp.int32)
    wblocks = jnp.asarray([1, 5], jnp.int32)  # 5: dropped
    v = jnp.asarray(rng.normal(size=(2, 3, 11) if axis == 0 else (11, 2, 3)))
    w = jnp.asarray(rng.normal(size=(11, 11)))
    idx = offset + size * blocks[:, None] + jnp.arange(size)
    widx = jnp.where((wblocks < 3)[:, None], offset + size * wblocks[:, None] + jnp.arange(size), 11).reshape(-1)
    flat = (lambda t: t.reshape(t.shape[:axis] + (-1,) + t.shape[axis + 2:]))

    def f(a, v):
        got = take_blocks(a, blocks, size, offset, axis)
        b = put_blocks(a, wblocks, jnp.sin(got) * v, size, offset, axis)
        return jnp.sum(w * b * b)

    def f_plain(a, v):
        got = jnp.take(a, idx, axis=axis)
        where = (slice(None),) * axis + (widx,)
        b = a.at[where].set(flat(jnp.sin(got) * v), mode="drop")
        return jnp.sum(w * b * b)

    f, f_plain = jax.jit(f), jax.jit(f_plain)
    np.testing.assert_allclose(f(a, v), f_plain(a, v), rtol=1e-14)
    for g, gp in zip(jax.jit(jax.grad(f, (0, 1)))(a, v), jax.jit(jax.grad(f_plain, (0, 1)))(a, v)):
        np.testing.assert_allclose(g, gp, rtol=1e-12, atol=1e-12)
    check_grads(f, (a, v), order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_block_form_derivatives_hold_no_scatter():
    a = jnp.asarray(np.random.default_rng(4).normal(size=(8, 8)))
    blocks = jnp.asarray([2, 0], jnp.int32)

    def f(a):
        return put_blocks(a, blocks, take_blocks(a, blocks, 2, 2, 1) * 2.0, 2, 2, 1)

    _, f_lin = jax.linearize(f, a)
    for prims in (_prims(jax.make_jaxpr(f_lin)(a)), _prims(jax.make_jaxpr(jax.linear_transpose(f_lin, a))(a))):
        assert not [p for p in prims if "scatter" in p or p == "gather"], prims


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pow2_factors_are_the_power_of_two_below_m_and_its_normal_reciprocal_factors(dtype):
    """Oracle: NumPy's frexp (m = f·2^k, f in [0.5, 1), so the power of two at or below m is
    2^(k−1)); 1s for 0, subnormal, Inf and NaN magnitudes."""
    from jaxslam.linalg import pow2_factors

    fi = np.finfo(dtype)
    rng = np.random.default_rng(5)
    exps = rng.uniform(np.log2(fi.tiny), np.log2(fi.max), 400)
    m = np.concatenate([np.exp2(exps), [fi.tiny, fi.max, 1.0, 0.75, 2.0, 3.0]]).astype(dtype)
    d1, d2, up = (np.asarray(a) for a in jax.jit(pow2_factors)(jnp.asarray(m)))
    _, k = np.frexp(m)
    np.testing.assert_array_equal(up, np.ldexp(np.ones_like(m), k - 1))
    for d in (d1, d2):
        assert np.all(np.abs(d) >= fi.tiny) and np.all(np.isfinite(d)), "a factor is not a normal number"
    np.testing.assert_array_equal(d1.astype(np.float64) * d2.astype(np.float64), np.ldexp(1.0, 1 - k))
    assert np.all((m * d1 * d2 >= 1) & (m * d1 * d2 < 2))
    odd = np.array([0.0, fi.smallest_subnormal, np.inf, np.nan], dtype)
    for a in jax.jit(pow2_factors)(jnp.asarray(odd)):
        np.testing.assert_array_equal(np.asarray(a), np.ones(4, dtype))
    g = jax.grad(lambda x: jnp.sum(x * pow2_factors(x)[0]))(jnp.asarray([3.0, 5e-3], dtype))
    np.testing.assert_array_equal(np.asarray(g), np.asarray(pow2_factors(jnp.asarray([3.0, 5e-3], dtype))[0]))


def test_complex_is_refused_by_the_shared_number_checks_themselves():
    """check_numbers (behind check_scalar) and float_array refuse complex input themselves (it
    was refused only where a caller added check_real: check_numbers dropped the imaginary
    part with a ComplexWarning, so a complex σ passed range_bearing3d's spec check)."""
    from jaxslam.linalg import check_numbers, float_array
    from jaxslam.sensors import range_bearing3d as rb

    with pytest.raises(InputError, match=r"^x: expected a real array, got dtype complex128"):
        check_numbers(np.array([1 + 2j]), "x")
    with pytest.raises(InputError, match=r"^x: expected a real array, got dtype complex64"):
        float_array(jnp.zeros(2, jnp.complex64), "x")
    with pytest.raises(InputError, match=r"sigma_az"):
        rb.check_range_bearing_spec(rb.RangeBearingSpec(np.complex128(0.1 + 1j), 0.1, 0.1))
