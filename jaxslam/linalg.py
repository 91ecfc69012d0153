"""Numerically careful linear algebra shared by every filter.

Covariance hygiene (STYLE.md): symmetrise after updates, Cholesky-based solves
(never an explicit inverse), the factored Joseph form, and angle wrapping for
residuals.  All functions are pure, jit/vmap-safe and follow their inputs'
dtype.
"""

from __future__ import annotations

import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from .errors import InputError, check_flag, check_int  # (re-exported: JAX-free, in errors)

__all__ = [
    "host_array",
    "to_jax",
    "is_concrete",
    "check_numbers",
    "float_array",
    "list_array",
    "value_and_jacfwd",
    "take",
    "put",
    "take_blocks",
    "put_blocks",
    "symmetrize",
    "wrap_angle",
    "pow2_factors",
    "chol_solve",
    "det_small",
    "inv_small",
    "cholesky_small",
    "small_matmul",
    "safe_norm",
    "check_psd",
    "check_scalar",
    "check_int",
    "check_shape",
    "reworded",
    "check_real",
    "check_flag",
    "check_float_dtype",
    "check_key",
    "check_finite",
]


def value_and_jacfwd(fun, argnums=0):
    """``fun``'s value and forward-mode Jacobian from one trace of ``fun``.

    ``value_and_jacfwd(f, argnums)(*args) -> (f(*args), jacfwd(f, argnums)(*args))``, but
    ``f`` is traced once (its primal comes out of the forward pass as ``has_aux``), where
    calling ``f`` and ``jax.jacfwd(f)`` separately traces, lowers and compiles it twice.
    """

    nums = (argnums,) if isinstance(argnums, int) else tuple(argnums)

    def both(*a):
        y = fun(*a)
        return y, y

    def wrapped(*args):
        def lin(*diff):
            full = list(args)
            for i, v in zip(nums, diff):
                full[i] = v
            jac, val = jax.jacfwd(both, argnums=argnums, has_aux=True)(*full)
            return val, jac

        diff = [args[i] for i in nums]
        if is_concrete(args):
            # No argument is traced: an eager call, where a checkpoint of this per-call closure
            # was traced, lowered and compiled (or read from the persistent cache) anew on
            # every call.  (Under a transformation of a value ``fun`` closes over, with concrete
            # arguments, the remat is skipped too: the same values and derivatives, without
            # the memory saving under reverse mode.)
            return lin(*diff)
        # Rematerialised under reverse mode: the backward pass recomputes the linearisation
        # from its inputs instead of the forward pass storing every intermediate of the
        # forward-mode Jacobian (hundreds of small arrays per call, each a kernel per step of a
        # scan); without autodiff it costs nothing.
        return jax.checkpoint(lin)(*diff)

    return wrapped


# ---------------------------------------------------------------------------
# Indexing with scatter-free derivatives
# ---------------------------------------------------------------------------
#
# XLA's CPU backend has no scatter kernel: it expands every scatter into a while loop with one
# iteration per index (a few small kernels each).  Reverse mode turns each gather into a
# scatter-add and each scatter into a scatter plus a gather, so the gradient of an EKF-SLAM
# frame held ~20 such loops (16-48 iterations each): they dominated both its run time and its
# compile time.  ``take`` and ``put`` keep the gather/scatter for the primal but define their
# derivatives as products with one-hot matrices, which transpose to products again.  A
# derivative then costs O(N·k) per gathered row instead of a loop over k indices; with N the
# size of the indexed axis (the state dimension) this is the cost class of the update itself.


def _one_hot(idx, N, dtype):
    """(k, N) one-hot rows of the flat indices ``idx``; an index outside [0, N) gives a zero row."""
    return (idx.reshape(-1)[:, None] == jnp.arange(N, dtype=idx.dtype)[None, :]).astype(dtype)


def _place(d, axis, nd):
    """Move the leading ``nd`` axes of ``d`` to position ``axis``."""
    return jnp.moveaxis(d, tuple(range(nd)), tuple(range(axis, axis + nd)))


def take(a, idx, axis: int = 0):
    """``jnp.take(a, idx, axis)`` (indices clipped into range) with a scatter-free derivative.

    The result has shape ``a.shape[:axis] + idx.shape + a.shape[axis+1:]``.  Its tangent and
    cotangent are products with the one-hot matrix of ``idx`` (see the comment above), so
    ``jax.grad`` through it never builds a scatter: this is :func:`take_blocks` with blocks of
    one.
    """
    a = jnp.asarray(a)
    idx = jnp.asarray(idx)
    out = take_blocks(a, idx.reshape(-1), 1, 0, axis)  # (..., k, 1, ...)
    return out.reshape(a.shape[:axis] + idx.shape + a.shape[axis + 1:])


def put(a, idx, values, axis: int = 0):
    """``a`` with the slices at the 1-D indices ``idx`` along ``axis`` set to ``values``.

    ``values`` has ``a``'s shape with ``axis`` of length ``len(idx)``.  Indices outside
    ``[0, a.shape[axis])`` are dropped (nothing written), so a caller masks a write by giving
    it an out-of-range index.  Indices in range must be distinct.  The derivative is a masked
    copy plus a one-hot product (no scatter under ``jax.grad``; see the comment above): this is
    :func:`put_blocks` with blocks of one.
    """
    return put_blocks(a, idx, jnp.expand_dims(jnp.asarray(values), axis + 1), 1, 0, axis)


def _block_layout(n: int, size: int, offset: int, name: str) -> int:
    """Number of ``size``-long blocks from ``offset`` on an axis of length ``n`` (static check)."""
    if size < 1:
        raise InputError(f"{name}: size must be >= 1, got {size}")
    if not 0 <= offset <= n or (n - offset) % size:
        raise InputError(f"{name}: offset {offset} and size {size} do not cut an axis of length {n} "
                         f"into whole blocks")
    return (n - offset) // size


def _block_region(a, offset: int, nb: int, size: int, axis: int):
    """``a``'s blocks along ``axis`` as two axes (..., nb, size, ...)."""
    body = jax.lax.slice_in_dim(a, offset, offset + nb * size, axis=axis)
    return body.reshape(a.shape[:axis] + (nb, size) + a.shape[axis + 1:])


def _unblock(d, a_shape, offset: int, axis: int):
    """(..., nb, size, ...) back to one axis, zero-padded before ``offset`` to ``a_shape``."""
    d = d.reshape(a_shape[:axis] + (-1,) + a_shape[axis + 1:])
    pad = [(0, 0)] * d.ndim
    pad[axis] = (offset, a_shape[axis] - offset - d.shape[axis])
    return jnp.pad(d, pad) if offset or pad[axis][1] else d


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3, 4))
def take_blocks(a, blocks, size: int, offset: int = 0, axis: int = 0):
    """The ``size``-long blocks of ``a`` along ``axis`` that start at ``offset + size·b`` for
    each ``b`` in ``blocks`` (K,), block indices clipped into range: shape
    ``a.shape[:axis] + (K, size) + a.shape[axis+1:]`` (static ``size``, ``offset``, ``axis``;
    ``a.shape[axis] − offset`` a multiple of ``size``).

    The value is :func:`take`'s at the blocks' element indices; the derivative is a one-hot
    product over the blocks (K × blocks) instead of over the elements (K·size × length): for a
    filter's landmark blocks of size d, d² times fewer operations in a gradient, and no
    scatter either.
    """
    nb = _block_layout(a.shape[axis], size, offset, "take_blocks")
    b = jnp.clip(jnp.asarray(blocks, jnp.int32), 0, nb - 1)
    idx = offset + size * b[:, None] + jnp.arange(size, dtype=jnp.int32)[None, :]  # (K, size)
    return jnp.take(a, idx, axis=axis, mode="clip")


@take_blocks.defjvp
def _take_blocks_jvp(size, offset, axis, primals, tangents):
    a, blocks = primals
    da = tangents[0]
    nb = _block_layout(a.shape[axis], size, offset, "take_blocks")
    E = _one_hot(jnp.clip(jnp.asarray(blocks, jnp.int32), 0, nb - 1), nb, da.dtype)  # (K, nb)
    body = jnp.moveaxis(_block_region(da, offset, nb, size, axis), axis, 0)  # (nb, ..., size, ...)
    d = jnp.tensordot(E, body, axes=(1, 0))  # (K, ..., size, ...)
    return take_blocks(a, blocks, size, offset, axis), _place(d, axis, 1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3, 4, 5))
def put_blocks(a, blocks, values, size: int, offset: int = 0, axis: int = 0):
    """``a`` with its ``size``-long blocks along ``axis`` at ``offset + size·b`` (``b`` in
    ``blocks`` (K,)) set to ``values`` (``a.shape[:axis] + (K, size) + a.shape[axis+1:]``).

    Block indices outside ``[0, (a.shape[axis] − offset) / size)`` are dropped (nothing
    written); those in range must be distinct.  The value is a scatter of one window per block
    (XLA's CPU backend loops over a scatter's indices: K iterations, not K·size); the derivative
    is a masked copy plus a one-hot product over the blocks, d² times cheaper than the same write
    element by element (:func:`put`, the blocks-of-one case) for blocks of size d (see
    :func:`take_blocks`).
    """
    a = jnp.asarray(a)
    n = a.shape[axis]
    nb = _block_layout(n, size, offset, "put_blocks")
    b = jnp.asarray(blocks, jnp.int32)
    # a block out of range starts past the end: its window is dropped
    start = jnp.where((b >= 0) & (b < nb), offset + size * b, n)
    upd = jnp.moveaxis(jnp.asarray(values).astype(a.dtype), axis, 0)  # (K, ..., size, ...)
    dnums = jax.lax.ScatterDimensionNumbers(update_window_dims=tuple(range(1, a.ndim + 1)),
                                            inserted_window_dims=(), scatter_dims_to_operand_dims=(axis,))
    return jax.lax.scatter(a, start[:, None], upd, dnums, mode=jax.lax.GatherScatterMode.FILL_OR_DROP)


@put_blocks.defjvp
def _put_blocks_jvp(size, offset, axis, primals, tangents):
    a, blocks, values = primals
    da, _, dv = tangents
    n = a.shape[axis]
    nb = _block_layout(n, size, offset, "put_blocks")
    E = _one_hot(jnp.asarray(blocks, jnp.int32), nb, da.dtype)  # (K, nb); dropped blocks: zero rows
    keep_b = 1.0 - jnp.max(E, axis=0)  # (nb,)
    keep = jnp.concatenate([jnp.ones((offset,), da.dtype), jnp.repeat(keep_b, size)])
    shape = [1] * a.ndim
    shape[axis] = n
    dv = jnp.moveaxis(jnp.asarray(dv).astype(da.dtype), axis, 0)  # (K, ..., size, ...)
    d = _place(jnp.tensordot(E.T, dv, axes=(1, 0)), axis, 1)  # (..., nb, size, ...)
    return put_blocks(a, blocks, values, size, offset, axis), da * keep.reshape(shape) + _unblock(d, a.shape, offset, axis)


def small_matmul(A, B, limit: int = 16):
    """``A @ B`` for 2-D operands; when every dimension is at most ``limit`` (static), as a
    broadcast multiply and a sum, which XLA fuses with the operations around it — on the CPU a
    dot is a kernel call of its own, and a filter step's few 9×9 products cost more in calls
    than in arithmetic.  Larger operands use ``@``."""
    if max(A.shape + B.shape) > limit:
        return A @ B
    return jnp.sum(A[:, :, None] * B[None, :, :], axis=1)


def symmetrize(P):
    """Return (P + Pᵀ)/2."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def wrap_angle(a):
    """Wrap angles to [-π, π).  Smooth (derivative 1) away from ±π."""
    return (a + jnp.pi) % (2.0 * jnp.pi) - jnp.pi


def chol_solve(S, B):
    """Solve S X = B for symmetric positive-definite S through a Cholesky factor.

    Returns ``(X, ok)`` where ``ok`` is False when the factorisation failed
    (non-finite factor), so callers can raise a status flag instead of NaNs.
    """
    L = jnp.linalg.cholesky(symmetrize(S))
    ok = jnp.all(jnp.isfinite(L))
    X = jax.scipy.linalg.cho_solve((L, True), B)
    return X, ok


def det_small(A):
    """Determinant of (..., d, d) matrices, d ≤ 3, in closed form (elementwise, fuses)."""
    d = A.shape[-1]
    if d == 1:
        return A[..., 0, 0]
    if d == 2:
        return A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    if d == 3:
        return (
            A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
            - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
            + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
        )
    raise ValueError("closed-form determinant only for d <= 3")


def inv_small(A):
    """``(A⁻¹, det A)`` of (..., d, d) matrices, d ≤ 3, by the adjugate.

    No LAPACK call: under ``vmap`` a batched ``jnp.linalg`` factorisation of tiny
    matrices becomes one library call per matrix, this stays elementwise.  A
    singular ``A`` gives the adjugate (divided by 1) and ``det == 0``: callers test
    ``det``.
    """
    d = A.shape[-1]
    det = det_small(A)
    e = lambda i, j: A[..., i, j]  # noqa: E731
    if d == 1:
        adj = jnp.ones_like(A)
    elif d == 2:
        adj = jnp.stack([jnp.stack([e(1, 1), -e(0, 1)], -1),
                         jnp.stack([-e(1, 0), e(0, 0)], -1)], -2)
    else:
        def c(i, j):  # cofactor (i, j)
            r = [k for k in range(3) if k != i]
            s = [k for k in range(3) if k != j]
            m = e(r[0], s[0]) * e(r[1], s[1]) - e(r[0], s[1]) * e(r[1], s[0])
            return m if (i + j) % 2 == 0 else -m

        adj = jnp.stack([jnp.stack([c(j, i) for j in range(3)], -1) for i in range(3)], -2)
    safe = jnp.where(det != 0, det, jnp.ones((), A.dtype))
    return adj / safe[..., None, None], det


def cholesky_small(S):
    """Lower Cholesky factor of (..., d, d) symmetric positive-definite matrices, d ≤ 4, unrolled
    at trace time into scalar arithmetic that XLA fuses (no LAPACK call per matrix under
    ``vmap``).  Reads the lower triangle; a matrix that is not positive definite gives NaN
    entries, as ``jnp.linalg.cholesky``."""
    d = S.shape[-1]
    if d > 4:
        raise ValueError("closed-form Cholesky only for d <= 4")
    zero = jnp.zeros(S.shape[:-2], S.dtype)
    L = [[zero] * d for _ in range(d)]
    for j in range(d):
        L[j][j] = jnp.sqrt(S[..., j, j] - sum(L[j][k] * L[j][k] for k in range(j)))
        for i in range(j + 1, d):
            L[i][j] = (S[..., i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    return jnp.stack([jnp.stack(row, -1) for row in L], -2)


_INT_OF_SIZE = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}


def pow2_factors(m):
    """``(down1, down2, up)`` for magnitudes ``m`` ≥ 0 (any shape, float): up = 2^e, the power of
    two at or below m, and down1·down2 = 2^−e, both factors normal numbers (2^−127 alone is
    subnormal in float32, and XLA flushes subnormals to zero); all three are 1 where m is 0,
    subnormal or not finite.  Multiplying by a power of two is exact, so x·down1·down2 has the
    mantissas of x (a computation on it gives the same bits, scaled) while its squares neither
    overflow nor underflow.  The factors carry no derivative (they are piecewise constant)."""
    m = jax.lax.stop_gradient(m)
    info = jnp.finfo(m.dtype)
    itype = _INT_OF_SIZE[np.dtype(m.dtype).itemsize]
    emask, bias = (1 << info.nexp) - 1, int(info.maxexp) - 1
    E = (jax.lax.bitcast_convert_type(m, itype) >> info.nmant) & emask  # biased exponent of m
    e = jnp.where((E > 0) & (E < emask), E - bias, 0)  # zero, subnormal, inf, NaN: no scaling

    def pow2(k):  # 2^k for -bias < k <= bias (a normal number)
        return jax.lax.bitcast_convert_type(((k + bias) << info.nmant).astype(itype), m.dtype)

    a = (-e) // 2
    return pow2(a), pow2(-e - a), pow2(e)


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm with a finite gradient at 0 (the gradient there is 0).  A NaN or Inf
    entry gives NaN or Inf, never 0 (``NaN > 0`` is false: a test on positivity turned a NaN
    point into a zero range that a sensor model reported as a visible return)."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    zero = sq == 0
    safe_sq = jnp.where(zero, 1.0, sq)
    return jnp.where(zero, 0.0, jnp.sqrt(safe_sq))


# ---------------------------------------------------------------------------
# Host-side validation (raise InputError before jit)
# ---------------------------------------------------------------------------

def check_scalar(value, name: str, *, finite: bool = True, lower=None, strict: bool = False) -> float:
    """``value`` as a float when it is a scalar (never NaN; finite when ``finite``; above ``lower``,
    strictly when ``strict``); else :class:`InputError` naming ``name``.  Host-side, for the
    numbers systems keep in their ``Params`` (gates, thresholds, variances)."""
    if lower == 0 and finite:
        want = "a positive finite scalar" if strict else "a non-negative finite scalar"
    elif lower is None and not finite:
        want = "a number"
    else:
        want = ("a finite scalar" if finite else "a scalar") + (
            "" if lower is None else f" {'>' if strict else '>='} {lower:g}")
    try:
        a = check_numbers(value, name)
    except InputError:
        raise InputError(f"{name}: expected {want}, got {value!r}") from None
    ok = a.shape == () and not np.isnan(a) and (not finite or np.isfinite(a))
    if ok and lower is not None:
        ok = bool(a > lower) if strict else bool(a >= lower)
    if not ok:
        raise InputError(f"{name}: expected {want}, got {value!r}")
    return float(a)


def _dtype_of(x):
    """``x``'s dtype without converting an array; None for a list of tracers or non-numbers."""
    dt = getattr(x, "dtype", None)
    if dt is not None:
        return np.dtype(dt)
    if not is_concrete(x):
        return None
    try:
        return np.asarray(x).dtype
    except (TypeError, ValueError):
        return None


def check_real(x, name: str, *, allow_bool: bool = True) -> None:
    """:class:`InputError` naming ``name`` when ``x`` is complex (casting it to a real dtype
    dropped the imaginary part with only a warning), or bool unless ``allow_bool``.  The dtype
    is static: checked under ``jit`` too."""
    dt = _dtype_of(x)
    if dt is None:
        return
    if dt.kind == "c":
        raise InputError(f"{name}: expected a real array, got dtype {dt}")
    if dt.kind == "b" and not allow_bool:
        raise InputError(f"{name}: expected numbers, got dtype bool")


def reworded(check, message: str, upper: float = float("inf")):
    """``check()`` (one of this module's checks: the rule lives there) with its
    :class:`InputError` replaced by ``message`` (a caller's wording, e.g. naming its CLI flag);
    a result above ``upper`` raises ``message`` too.  Host-side."""
    try:
        value = check()
    except InputError:
        raise InputError(message) from None
    if not value <= upper:
        raise InputError(message)
    return value


def check_key(key, name: str = "key", raw_shape=None) -> None:
    """:class:`InputError` naming ``name`` unless ``key`` is a PRNG key: a typed key
    (``jax.random.key``, 0-d) or the raw uint32 key data of ``jax.random.PRNGKey`` (1-D; of
    shape ``raw_shape`` when given).  Static (dtype and shape): an int seed raised JAX's bare
    ``TypeError`` from inside the sampler."""
    dt = getattr(key, "dtype", None)
    if dt is not None and jax.dtypes.issubdtype(dt, jax.dtypes.prng_key):
        if np.ndim(key) == 0:
            return
    elif (dt is not None and np.dtype(dt) == np.uint32 and np.ndim(key) == 1
          and (raw_shape is None or np.shape(key) == tuple(raw_shape))):
        return
    raise InputError(f"{name}: expected a PRNG key (jax.random.PRNGKey(seed) or jax.random.key(seed)), "
                     f"got {key!r}"[:300])


def check_float_dtype(dtype, name: str = "dtype"):
    """``dtype`` as a ``jnp.dtype`` when it names a floating dtype, else :class:`InputError`
    naming ``name`` (an integer dtype truncated what it held, a bogus name was a bare
    TypeError).  Whether float64 is usable (x64) is the caller's rule."""
    try:
        dt = jnp.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or not jnp.issubdtype(dt, jnp.floating):
        raise InputError(f"{name}: expected a floating dtype (float32 or float64), got {dtype!r}")
    return dt


def check_numbers(value, name: str) -> np.ndarray:
    """``value`` as a float64 NumPy array, or :class:`InputError` naming ``name`` when it is not
    numbers (a string, even "1.5"; None; a ragged list; a dict): host-side, before any check of its shape or
    values, so such a value never reaches NumPy's bare ``could not convert`` error."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected numbers, got {value!r}") from None
    if raw.dtype.kind == "c":  # float64 of it dropped the imaginary part with only a warning
        raise InputError(f"{name}: expected a real array, got dtype {raw.dtype}")
    try:
        # NumPy would parse "1.5" (so a typo in a file could pass) and turn None into NaN
        if raw.dtype.kind in "US" or (raw.dtype.kind == "O" and not all(
                isinstance(e, numbers.Number) for e in raw.reshape(-1))):
            raise TypeError
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected numbers, got {value!r}") from None


def list_array(x, name: str):
    """A Python list or tuple of numbers as a JAX array (its dtype as ``jnp.asarray`` gives it:
    ``jnp.result_type`` of a list raised a bare "Cannot determine dtype"); anything else is
    returned unchanged.  A list that is not numbers (ragged, strings) is an :class:`InputError`
    naming ``name``."""
    if not isinstance(x, (list, tuple)):
        return x
    try:
        return jnp.asarray(x)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected an array of numbers, got {x!r}"[:300]) from None


def float_array(x, name: str):
    """``x`` as a JAX array of an inexact dtype: an array keeps its floating dtype (an integer or
    bool one becomes JAX's default float), a list or a number is converted, and a concrete value
    that is not numbers (a string, None, a ragged list) or complex is an :class:`InputError`
    naming ``name``.  Traced values pass through (their dtype is known, their values are not)."""
    check_real(x, name)
    if not isinstance(x, (jax.Array, np.ndarray)) or x.dtype.kind not in "biuf":
        if is_concrete(x):
            check_numbers(x, name)
    if type(x) is np.ndarray:  # converted on the host: no eager program
        return to_jax(x if x.dtype.kind in "fc" else x.astype(jnp.result_type(float)))
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))


def check_mask(mask, name: str) -> None:
    """Raise InputError naming ``name`` unless ``mask`` is bool or 0/1 integers (a float 0.5 or
    an integer 2 was read as True).  The dtype is checked always (it is known under ``jit``),
    an integer mask's values when it is concrete; None passes; a list is read with NumPy."""
    if mask is None:
        return
    dt = getattr(mask, "dtype", None)
    dt = np.asarray(mask).dtype if dt is None else np.dtype(dt)
    if not (dt == np.bool_ or np.issubdtype(dt, np.integer)):
        raise InputError(f"{name}: expected a bool mask (or 0/1 integers), got dtype {dt}")
    if dt != np.bool_ and is_concrete(mask):
        a = np.asarray(mask)
        bad = a[(a != 0) & (a != 1)]
        if bad.size:
            raise InputError(f"{name}: expected a bool mask (or 0/1 integers), got the value {bad.flat[0]}")


def check_whole_ids(ids, name: str, used=None):
    """Raise InputError when a concrete floating ``ids`` holds a non-finite or fractional value
    on the entries in ``used`` (bool, broadcast to ``ids``; default all): casting it to int would
    truncate it onto another id.  Integer arrays and traced values pass (nothing to check)."""
    if not is_concrete(ids) or not np.issubdtype(np.asarray(ids).dtype, np.floating):
        return
    a = np.asarray(ids)
    if used is not None:
        a = a[np.broadcast_to(np.asarray(used, bool), a.shape)]  # unused entries may hold anything
    if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
        raise InputError(f"{name}: expected whole-number landmark ids on the rows in use (a fractional "
                         "or non-finite id would be truncated onto another landmark)")


def check_shape(x, shape, name: str):
    """Raise InputError unless ``x`` has ``shape`` (``None`` entries match any size)."""
    xs = np.shape(x)
    if len(xs) != len(shape) or any(s is not None and s != a for s, a in zip(shape, xs)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{name}: expected shape {want}, got {tuple(xs)}")
    return x


def check_psd(M, name: str, strict: bool = False, tol: float = 1e-12, valid=None, stack: bool = False):
    """Raise InputError unless ``M`` is a finite symmetric PSD (PD if strict) matrix or, with
    ``stack``, a stack of them (``(K, n, n)`` also accepted: the first bad one is named
    ``name[k]``, all checked at once).

    Tolerances, relative to the largest magnitude (at least 1): symmetry 1e-9, eigenvalues
    ``tol`` (with ``strict``, relative to the largest magnitude itself: the smallest eigenvalue
    must exceed ``tol`` times it; a badly scaled matrix, one with a diagonal entry at most
    ``tol`` times its largest entry such as ``diag(1e200, 1)``, also passes when the smallest
    eigenvalue of ``D^-1/2 M D^-1/2``, ``M`` scaled to a unit diagonal, exceeds ``tol``); a
    lower-precision input (float32) may also be off by 100 ulp of its own dtype (relative to
    its largest entry) in symmetry and below zero.  Without ``strict``, a negative direction is
    also judged against the entries it is made of: the eigenvector ``v`` of the smallest
    eigenvalue is refused when ``v' M v < -max(tol max(1, w), 100 ulp w)``, ``w = |v|' |M| |v|``
    (rounding the entries moves ``v' M v`` by at most a relative rounding times ``w``), so
    ``diag(1e13, -1)`` is refused (``w = 1``) while a PSD matrix rounded entry by entry (to
    float32, say) still passes.  So a matrix that is symmetric
    and PSD to its working precision passes.  ``valid`` (``(..., n)`` bool):
    only the rows and columns in use are checked (a masked measurement's row of a per-step R
    may hold anything, NaN included).
    """
    A = check_numbers(M, name)
    dt = np.asarray(M).dtype
    if A.ndim not in ((2, 3) if stack else (2,)) or A.shape[-1] != A.shape[-2]:
        raise InputError(f"{name}: expected a square matrix, got shape {A.shape}")
    # rounding room of a lower-precision input: 100 ulp of its dtype, relative to its magnitude
    ulp = 100 * np.finfo(dt).eps if np.issubdtype(dt, np.floating) and np.finfo(dt).bits < 64 else 0.0
    S = A.reshape((-1,) + A.shape[-2:])
    if valid is not None:
        v = np.broadcast_to(np.asarray(valid, bool), A.shape[:-1]).reshape(S.shape[:2])
        S = np.where(v[:, :, None] & v[:, None, :], S, np.eye(A.shape[-1])[None])  # unused rows: identity
    if S.size == 0:
        return M

    def where(bad):
        k = int(np.argmax(bad))
        return name + (f"[{k}]" if A.ndim == 3 else "")

    bad = ~np.all(np.isfinite(S), axis=(1, 2))
    if bad.any():
        raise InputError(f"{where(bad)}: contains NaN or Inf")
    mag = np.max(np.abs(S), axis=(1, 2))
    scale = np.maximum(1.0, mag)
    bad = np.max(np.abs(S - S.transpose(0, 2, 1)), axis=(1, 2)) > np.maximum(1e-9 * scale, ulp * mag)
    if bad.any():
        raise InputError(f"{where(bad)}: not symmetric")
    # halves first: S + S.T overflowed for entries beyond 9e307 (NaN eigenvalues, which passed);
    # the same bits otherwise (halving is exact, and rounding commutes with it)
    lo = np.linalg.eigvalsh(0.5 * S + 0.5 * S.transpose(0, 2, 1)).min(axis=1)
    # strict: relative to the largest entry only (a well-conditioned matrix of small entries,
    # e.g. an IMU bias density of 1e-14, is positive definite: a floor of 1e-12 refused it)
    bad = ~(lo > tol * mag) if strict else ~(lo >= -np.maximum(tol * scale, ulp * mag))
    if not strict and (lo < 0).any():
        bad |= _negative_beyond_rounding(S, lo < 0, tol, ulp)
    rel = None
    if strict and bad.any():
        # a badly scaled matrix (variances 1e200 and 1) is PD, but a variance below tol times
        # the largest entry is beneath the relative floor, which cannot see it ("smallest
        # eigenvalue 1" refused): such a matrix is judged again scaled to a unit diagonal (the
        # scaling Cholesky's accuracy depends on), by the same tol.  Matrices whose variances
        # all lie within 1/tol of the largest entry are judged as before.
        spread = np.min(np.diagonal(S, axis1=1, axis2=2), axis=1) <= tol * mag
        if (bad & spread).any():
            rel = np.where(spread, _unit_diagonal_min_eig(S), -np.inf)
            bad &= ~(rel > tol)
    if bad.any():
        k = int(np.argmax(bad))
        what = "positive definite" if strict else "positive semi-definite"
        why = ("" if rel is None or not (spread[k] and lo[k] > 0)
               else f"; {rel[k]:.3g} scaled to a unit diagonal: numerically singular")
        raise InputError(f"{where(bad)}: not {what} (smallest eigenvalue {lo[k]:.3g}{why})")
    return M


def _negative_beyond_rounding(S, cand, tol: float, ulp: float):
    """Per matrix of the stack ``S`` (finite, symmetric to check_psd's tolerance): True where
    ``cand`` and the eigenvector ``v`` of its smallest eigenvalue witnesses a negative direction
    beyond the rounding of the entries it is made of: ``v' S v < -room`` with ``w = |v|' |S| |v|``
    (what rounding each entry by a relative ``e`` can move ``v' S v`` by, at most ``e w``) and
    ``room = max(tol max(1, w), max(ulp, 4 n eps) w)``.  For any PSD matrix ``v' S v >= 0``
    exactly, so a PSD matrix, or one rounded from it entry by entry (float32: ``ulp``), is never
    refused here, whatever the accuracy of ``eigh``; ``diag(1e13, -1)``, which the tolerance
    relative to the largest eigenvalue let through, is (``v = e_2``, ``w = 1``)."""
    out = np.zeros(S.shape[0], bool)
    idx = np.flatnonzero(cand)
    H = 0.5 * S[idx] + 0.5 * S[idx].transpose(0, 2, 1)
    v = np.linalg.eigh(H)[1][:, :, 0]  # (the eigenvector of the smallest eigenvalue)
    with np.errstate(over="ignore", invalid="ignore"):  # entries near 1e308: inf or NaN, never refused
        q = np.einsum("ki,kij,kj->k", v, H, v)
        w = np.einsum("ki,kij,kj->k", np.abs(v), np.abs(H), np.abs(v))
        room = np.maximum(tol * np.maximum(1.0, w), max(ulp, 4 * S.shape[-1] * np.finfo(np.float64).eps) * w)
        out[idx] = q < -room
    return out


def _unit_diagonal_min_eig(S):
    """Per matrix of the stack ``S`` (finite, symmetric to check_psd's tolerance): the smallest
    eigenvalue of ``D^-1/2 S D^-1/2``, ``D`` its diagonal (same inertia as ``S``: PD exactly
    when ``S`` is); -inf where a diagonal entry is <= 0 or the scaled matrix is not finite
    (an off-diagonal entry beyond the geometric mean of its diagonal pair: not PD)."""
    d = np.diagonal(S, axis1=1, axis2=2)
    pos = np.all(d > 0, axis=1)
    r = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    with np.errstate(over="ignore", invalid="ignore"):
        H = (S * r[:, :, None]) * r[:, None, :]
        H = 0.5 * H + 0.5 * H.transpose(0, 2, 1)
    ok = pos & np.all(np.isfinite(H), axis=(1, 2))
    out = np.full(S.shape[0], -np.inf)
    if ok.any():
        out[ok] = np.linalg.eigvalsh(H[ok]).min(axis=1)
    return out


def is_concrete(*xs) -> bool:
    """True when no leaf of ``xs`` is a tracer: the values are known now, so a helper can build
    its result on the host (NumPy) instead of compiling a tiny program op by op."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def check_finite(x, name: str) -> None:
    """When ``x`` is known now (no tracer), :class:`InputError` "``name``: contains NaN or Inf"
    unless every entry is finite; a traced ``x`` passes (its values are not known)."""
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise InputError(f"{name}: contains NaN or Inf")


def to_jax(x):
    """``jnp.asarray(x)``, with a NumPy array moved by ``device_put``: JAX 0.10 lifts a NumPy
    array through an eager identity program (``jit(stage)``), compiled once per shape and dtype
    (~15-20 ms each in a fresh process), where ``device_put`` compiles nothing.  Same dtype
    (canonicalised the same way), a copy, not weakly typed, uncommitted; anything else (a JAX
    array, a tracer, a list, a Python number) goes to ``jnp.asarray`` unchanged."""
    if type(x) is np.ndarray and x.dtype.kind in "biufc":
        return jax.device_put(x)
    return jnp.asarray(x)


def host_array(x, dtype):
    """``x`` as an array of ``dtype``: made on the host when ``x`` is known now (``device_put``
    runs no eager program, while ``jnp.asarray(scalar, dtype)`` compiles a conversion), traced
    otherwise, so callers stay usable under ``jit`` / ``grad``.  A JAX array already of
    ``dtype`` is returned as it is (no round trip through the host)."""
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and x.dtype == np.dtype(dtype):
        return x
    if is_concrete(x):
        return jax.device_put(np.asarray(x, dtype=np.dtype(dtype)))
    return jnp.asarray(x, dtype)
