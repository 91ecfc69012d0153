"""Unit quaternions (Hamilton convention, scalar first).

Paper 004 ch. 3.1 and app. A (quaternion algebra, exp/log maps); the attitude
meaning follows paper 000 eq. 1: a unit quaternion q = [q0, q1, q2, q3]
represents the body-to-NED rotation C_NB, i.e.

    qrotate(q, v_B) = C_NB v_B = q ⊗ [0, v_B] ⊗ q*,
    dcm_from_quat(qmul(p, q)) = dcm_from_quat(p) @ dcm_from_quat(q).

Decisions (where the sources are silent or inconsistent):

* Hamilton product, scalar first (SciPy stores scalar last: convert with
  ``q[..., [1, 2, 3, 0]]``).
* q and −q are the same rotation (double cover).  ``qlog`` always returns the
  shortest rotation vector (angle in [0, π]): q and −q give the same result.
  ``quat_from_dcm`` returns the canonical sign q0 ≥ 0 (``qcanonical``); at
  q0 = 0 exactly (a rotation by π) the sign Shepperd's branch produced is
  kept, and either sign is correct.  ``quat_from_euler`` returns the smooth
  closed form without sign canonicalisation.
* Singular points use Taylor branches selected with a dtype-dependent
  threshold (θ² < √eps for ``qexp``, |q_v|²/q0² < √eps for ``qlog``), with the
  "double where" trick so values and gradients stay finite at the identity;
  at q0 ≈ 0 ``qlog`` is smooth through atan2.  ``quat_from_dcm`` uses
  Shepperd's method (pick the largest of 4q_k²) with ``jnp.where`` branches
  only, so it is jit/vmap-safe and its gradient is finite.
* ``euler_from_quat`` goes through the DCM, so it inherits the gimbal-lock
  convention of :func:`jaxslam.geometry.euler.euler_from_dcm` (φ = 0 at
  θ = ±90°).
* ``qlog`` accepts non-unit quaternions (the angle is atan2-based, so the
  norm drops out); ``qrotate`` and ``dcm_from_quat`` assume unit norm.
  ``qnormalize`` and ``qlog`` first divide q by the power of two at or below
  max|q_k| (exact: the result for an ordinary q is unchanged to the last bit),
  so a finite non-zero q of any magnitude works (float32 at 1e±20 used to
  overflow or underflow the squared norm: zeros, NaN or a zero log).  A concrete
  q whose largest entry is subnormal (float32 1e-40, float64 1e-310) is first
  scaled up exactly on the host (XLA flushes subnormals to zero: it returned
  NaN); under ``jit`` such a q is still read as zero.
* A zero quaternion has no rotation: given a concrete one (all four entries
  0), ``qnormalize``, ``qrotate``, ``dcm_from_quat``, ``euler_from_quat`` and
  ``qlog`` raise :class:`~jaxslam.errors.InputError` naming the argument, and
  ``quat_from_dcm`` refuses an all-zero matrix (they returned NaN, v itself, a
  zero matrix, zero angles or the identity).  Under ``jit`` / ``vmap`` /
  ``grad`` the values are not known and nothing is checked, and these functions
  have no status output: a traced zero q gives NaN from ``qnormalize`` and
  ``qlog``, but v unrotated from ``qrotate``, the zero matrix from
  ``dcm_from_quat`` and zero angles from ``euler_from_quat``, all silently.  A
  jitted caller that can meet one must check ‖q‖ > 0 itself.  The shipped one,
  the ``attitude-smc`` scenario (``control.smc.closed_loop``: ``qlog`` of the
  attitude error and ``qnormalize`` after each step), turns it into NaN norms,
  which its ``non_finite`` flag counts.
* A complex input is refused everywhere (:func:`jaxslam.linalg.check_real`;
  the dtype is static, so under ``jit`` too).

All functions accept leading batch dimensions (quaternions (..., 4), vectors
(..., 3), matrices (..., 3, 3)); binary operations broadcast their batch
dimensions.  Everything is jit/vmap/grad-safe and follows the input dtype.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import is_concrete, pow2_factors
from .euler import _inexact, _last_axis, _matrix33, euler_from_dcm

__all__ = [
    "qmul",
    "qconj",
    "qnormalize",
    "qrotate",
    "qcanonical",
    "quat_from_euler",
    "euler_from_quat",
    "dcm_from_quat",
    "quat_from_dcm",
    "qexp",
    "qlog",
]


def _small_threshold(dtype):
    """Squared-argument threshold below which Taylor branches are used.

    √eps keeps the truncated Taylor series exact to eps^1.5 and keeps the
    closed form away from the cancellation that spoils its gradient near 0.
    """
    return jnp.sqrt(jnp.finfo(dtype).eps)


@jax.jit
def _pow2_scaled(q):
    """``q`` (..., 4) times 2^−e, 2^e the power of two at or below max_k |q_k| (unscaled where that
    is 0, subnormal or not finite; :func:`jaxslam.linalg.pow2_factors`).  Scaling by a power of
    two is exact, so every later step (squares, sums, square roots, quotients, atan2) sees the
    same mantissas and the result of an ordinary quaternion is unchanged to the last bit, while
    the squared norm of a finite q of any magnitude neither overflows nor underflows.  The scale
    carries no derivative (it is piecewise constant): d(q 2^−e)/dq = 2^−e exactly."""
    d1, d2, _ = pow2_factors(jnp.max(jnp.abs(q), axis=-1, keepdims=True))
    return q * d1 * d2


_SAFE_RANGE = {}  # dtype -> (2^−e, 2^e), e = maxexp / 4: no squared norm over- or underflows


def _safe_range(dtype):
    r = _SAFE_RANGE.get(dtype)
    if r is None:
        if jnp.issubdtype(dtype, jnp.floating):
            e = float(jnp.finfo(dtype).maxexp // 4)
            r = (2.0 ** -e, 2.0 ** e)
        else:  # an integer quaternion: any non-zero max |q_k| (>= 1); a zero one is refused
            r = (1.0, np.inf)
        _SAFE_RANGE[dtype] = r
    return r


def _checked(q, name: str, fn: str):
    """``(q, rescale)``: :class:`InputError` when the concrete (..., 4) ``q`` holds a zero
    quaternion (all four entries 0: no rotation).  ``rescale`` is False when q is concrete and
    every max_k |q_k| lies in [2^−e, 2^e], e = maxexp/4 of its dtype (any non-zero value for an
    integer dtype), where the squared norm can neither overflow nor underflow:
    :func:`_pow2_scaled` would change nothing there, and an eager call saves its dispatch.  A
    traced ``q`` passes (its values are not known) and is always rescaled (exactly).  A few
    NumPy operations on the host: no JAX dispatch."""
    if not is_concrete(q):
        return q, True
    a = np.asarray(q)
    m = np.abs(a).max(axis=-1)
    lo, hi = _safe_range(a.dtype)
    if lo <= m <= hi if a.ndim == 1 else (m >= lo).all() and (m <= hi).all():
        return q, False  # the usual case: no zero, nothing to rescale
    zero = m == 0  # NaN is not zero (it stays NaN)
    if zero.any():
        i = tuple(int(j) for j in np.argwhere(zero)[0]) if zero.ndim else ()
        raise InputError(f"{fn}: {name} is a zero quaternion{f' (at index {i})' if i else ''}: "
                         "it has no rotation")
    return q, True


def _unsubnormal(q, rescale: bool):
    """``q`` with each concrete quaternion whose max_k |q_k| is subnormal (non-zero, below the
    dtype's smallest normal number) multiplied by 2^(nmant+1) on the host, in NumPy (exact: every
    entry becomes a normal number with the same mantissa bits).  XLA flushes subnormal inputs to
    zero, so :func:`_pow2_scaled` cannot rescale them and qnormalize / qlog of such a finite
    non-zero q returned NaN.  A traced q, or one with nothing subnormal, is returned as it is."""
    if not rescale or not is_concrete(q):
        return q
    a = np.asarray(q)
    if not jnp.issubdtype(a.dtype, jnp.floating):  # an integer q has no subnormal
        return q
    info = jnp.finfo(a.dtype)
    m = np.abs(a).max(axis=-1, keepdims=True)
    sub = (m > 0) & (m < info.tiny)
    if not sub.any():
        return q
    up = np.asarray(2.0 ** (int(info.nmant) + 1), dtype=a.dtype)
    return jnp.asarray(np.where(sub, a * up, a), dtype=a.dtype)


def _nonzero(q, name: str, fn: str):
    """``q``; :class:`InputError` when it is a concrete zero quaternion (:func:`_checked`)."""
    return _checked(q, name, fn)[0]


def _batch_shape(fn: str, a, aname: str, b, bname: str) -> None:
    """:class:`InputError` naming both arguments when the batch shapes of ``a`` and ``b`` (all
    but the last axis) do not broadcast (shapes are static: free under ``jit``); it was a bare
    TypeError / ValueError from inside the arithmetic."""
    try:
        np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    except ValueError:
        raise InputError(f"{fn}: {aname} and {bname} batch shapes {tuple(a.shape[:-1])} and "
                         f"{tuple(b.shape[:-1])} do not broadcast") from None


def qmul(p, q):
    """Hamilton product p ⊗ q, paper 004 app. A.

    ``p``, ``q``: (..., 4) scalar-first, broadcast against each other (batch shapes that do
    not broadcast are an :class:`~jaxslam.errors.InputError` naming both).
    Returns (..., 4) = [p0 q0 − p_v·q_v, p0 q_v + q0 p_v + p_v × q_v].
    The rotation of p ⊗ q is C(p) C(q) (apply q first).
    """
    p = _last_axis(p, 4, "p", "qmul")
    q = _last_axis(q, 4, "q", "qmul")
    _batch_shape("qmul", p, "p", q, "q")
    p0, p1, p2, p3 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    q0, q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
            p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
            p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
            p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0,
        ],
        axis=-1,
    )


def qconj(q):
    """Conjugate [q0, −q_v] (the inverse for a unit quaternion).  (..., 4)."""
    q = _last_axis(q, 4, "q", "qconj")
    return q * jnp.asarray([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def qnormalize(q):
    """q / ‖q‖ along the last axis.  (..., 4); undefined for q = 0.

    Any finite non-zero magnitude (q is first divided by a power of two near max|q_k|, exactly).
    A concrete zero quaternion is an :class:`~jaxslam.errors.InputError`.
    """
    q, rescale = _checked(_last_axis(q, 4, "q", "qnormalize"), "q", "qnormalize")
    return _normalize(_unsubnormal(q, rescale), rescale)


def _normalize(q, rescale: bool = True):
    if rescale and jnp.issubdtype(q.dtype, jnp.floating):
        q = _pow2_scaled(q)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def qcanonical(q):
    """Sign-canonical representative of ±q with q0 ≥ 0.  (..., 4).

    At q0 = 0 the input sign is kept (both signs are the same rotation).
    """
    q = _last_axis(q, 4, "q", "qcanonical")
    return jnp.where(q[..., :1] < 0, -q, q)


def qrotate(q, v):
    """Rotate body vectors into the reference frame: C_NB(q) v.

    ``q``: (..., 4) unit quaternion; ``v``: (..., 3) (broadcast; batch shapes that do not
    broadcast are an :class:`~jaxslam.errors.InputError`).  Returns
    (..., 3) = q ⊗ [0, v] ⊗ q*, computed as v + q0 t + q_v × t with
    t = 2 q_v × v (no 3×3 matrix is formed).  A concrete zero ``q`` is an
    :class:`~jaxslam.errors.InputError` (it returned v unrotated).
    """
    q = _nonzero(_last_axis(q, 4, "q", "qrotate"), "q", "qrotate")
    v = _last_axis(v, 3, "v", "qrotate")
    _batch_shape("qrotate", q, "q", v, "v")
    qv = q[..., 1:]
    qv, v = jnp.broadcast_arrays(qv, v)
    t = 2.0 * jnp.cross(qv, v)
    return v + q[..., :1] * t + jnp.cross(qv, t)


def dcm_from_quat(q):
    """Rotation matrix C_NB of a unit quaternion (Hamilton, scalar first).

    ``q``: (..., 4).  Returns (..., 3, 3) =
    (q0² − |q_v|²) I + 2 q_v q_vᵀ + 2 q0 [q_v]×.  A concrete zero ``q`` is an
    :class:`~jaxslam.errors.InputError` (it returned the zero matrix).
    """
    q = _nonzero(_last_axis(q, 4, "q", "dcm_from_quat"), "q", "dcm_from_quat")
    return _dcm(q)


def _dcm(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def quat_from_dcm(C):
    """Unit quaternion of a rotation matrix by Shepperd's method.

    ``C``: (..., 3, 3) rotation matrix C_NB.  Returns (..., 4), normalised,
    with q0 ≥ 0.  The component with the largest 4q_k² (from the trace and
    the diagonal) is taken from a square root and the other three from
    off-diagonal sums/differences divided by it, so no branch divides by a
    small number; branches are selected with ``jnp.where`` (jit/vmap-safe,
    finite gradients).  A concrete all-zero matrix (no rotation: it returned the identity) is an
    :class:`~jaxslam.errors.InputError`.
    """
    C = _inexact(_matrix33(C, "C", "quat_from_dcm"))
    if is_concrete(C):
        zero = ~np.any(np.asarray(C) != 0, axis=(-2, -1))
        if zero.any():
            i = tuple(int(j) for j in np.argwhere(zero)[0])
            raise InputError(f"quat_from_dcm: C is a zero matrix{f' (at index {i})' if i else ''}, "
                             "not a rotation")
    c00, c01, c02 = C[..., 0, 0], C[..., 0, 1], C[..., 0, 2]
    c10, c11, c12 = C[..., 1, 0], C[..., 1, 1], C[..., 1, 2]
    c20, c21, c22 = C[..., 2, 0], C[..., 2, 1], C[..., 2, 2]
    tr = c00 + c11 + c22
    s = jnp.stack([1 + tr, 1 + 2 * c00 - tr, 1 + 2 * c11 - tr, 1 + 2 * c22 - tr], axis=-1)
    k = jnp.argmax(s, axis=-1)
    # 4 q_k q_j for every pair, from off-diagonal terms.
    d01, d02, d03 = c21 - c12, c02 - c20, c10 - c01  # 4 q0 q1, 4 q0 q2, 4 q0 q3
    d12, d13, d23 = c01 + c10, c02 + c20, c12 + c21  # 4 q1 q2, 4 q1 q3, 4 q2 q3
    cands = []
    for i, rows in enumerate(
        [
            (None, d01, d02, d03),
            (d01, None, d12, d13),
            (d02, d12, None, d23),
            (d03, d13, d23, None),
        ]
    ):
        chosen = k == i
        # Double where: unchosen branches get a harmless radicand so neither
        # their value nor their gradient can be NaN/Inf.
        r = jnp.sqrt(jnp.where(chosen, s[..., i], 1.0))  # = 2 |q_i|
        comps = [r * 0.5 if d is None else d / (2.0 * r) for d in rows]
        cands.append(jnp.where(chosen[..., None], jnp.stack(comps, axis=-1), 0.0))
    q = cands[0] + cands[1] + cands[2] + cands[3]
    return qcanonical(_normalize(q))


def quat_from_euler(euler):
    """Quaternion of the 3-2-1 Euler angles, q = q_z(ψ) ⊗ q_y(θ) ⊗ q_x(φ).

    Paper 000 eq. 1 (C_NB = C3(ψ) C2(θ) C1(φ)); paper 004 eq. 3.4.
    ``euler``: (..., 3) [φ, θ, ψ] radians.  Returns (..., 4) unit quaternion
    (smooth closed form, sign not canonicalised).
    """
    euler = _last_axis(euler, 3, "euler", "quat_from_euler")
    h = 0.5 * euler
    cf, sf = jnp.cos(h[..., 0]), jnp.sin(h[..., 0])
    ct, st = jnp.cos(h[..., 1]), jnp.sin(h[..., 1])
    cp, sp = jnp.cos(h[..., 2]), jnp.sin(h[..., 2])
    return jnp.stack(
        [
            cf * ct * cp + sf * st * sp,
            sf * ct * cp - cf * st * sp,
            cf * st * cp + sf * ct * sp,
            cf * ct * sp - sf * st * cp,
        ],
        axis=-1,
    )


def euler_from_quat(q):
    """3-2-1 Euler angles [φ, θ, ψ] of a unit quaternion.  (..., 4) -> (..., 3).

    Through :func:`dcm_from_quat` and :func:`euler_from_dcm` (same ranges and
    gimbal-lock convention: φ = 0 at θ = ±90°).  A concrete zero ``q`` is an
    :class:`~jaxslam.errors.InputError` (it returned zero angles).
    """
    q = _last_axis(q, 4, "q", "dcm_from_quat")  # the wording tests/geometry asserts on
    return euler_from_dcm(_dcm(_nonzero(q, "q", "euler_from_quat")))


def qexp(rotvec):
    """Exponential map: rotation vector -> unit quaternion.  Paper 004 app. A.

    ``rotvec``: (..., 3) = θ u (radians, u unit axis).  Returns (..., 4)
    = [cos(θ/2), sin(θ/2) u].  Near θ = 0 a Taylor branch keeps the value and
    the gradient (dq/dr = [0; I/2] at 0) exact and finite.
    """
    r = _inexact(_last_axis(rotvec, 3, "rotvec", "qexp"))
    t2 = jnp.sum(r * r, axis=-1)
    small = t2 < _small_threshold(r.dtype)
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    half = 0.5 * t
    w_big = jnp.cos(half)
    k_big = jnp.sin(half) / t
    w_small = 1.0 - t2 / 8.0 + t2 * t2 / 384.0
    k_small = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0
    w = jnp.where(small, w_small, w_big)
    k = jnp.where(small, k_small, k_big)
    return jnp.concatenate([w[..., None], k[..., None] * r], axis=-1)


def qlog(q):
    """Logarithm map: quaternion -> shortest rotation vector.  Paper 004 app. A.

    ``q``: (..., 4), any finite non-zero norm (q is first divided by a power of two near
    max|q_k|, exactly).  Returns (..., 3) = θ u with
    θ = 2 atan2(|q_v|, |q0|) ∈ [0, π] (q and −q give the same result).  A
    Taylor branch near the identity keeps values and gradients finite; near
    q0 = 0 (θ ≈ π) the atan2 form is smooth.  At q0 = 0 exactly the result
    jumps between ±π u (inherent to the double cover).  A concrete zero ``q``
    is an :class:`~jaxslam.errors.InputError` (it returned NaN).
    """
    q, rescale = _checked(_last_axis(q, 4, "q", "qlog"), "q", "qlog")
    q = _unsubnormal(_inexact(q), rescale)
    q = qcanonical(_pow2_scaled(q) if rescale else q)
    w = q[..., 0]
    v = q[..., 1:]
    n2 = jnp.sum(v * v, axis=-1)
    small = n2 < _small_threshold(q.dtype) * w * w
    n2s = jnp.where(small, 1.0, n2)
    n = jnp.sqrt(n2s)
    k_big = 2.0 * jnp.arctan2(n, w) / n
    ws = jnp.where(small, w, 1.0)
    x2 = n2 / (ws * ws)
    # atan(x)/x = 1 − x²/3 + x⁴/5 − …
    k_small = (2.0 / ws) * (1.0 - x2 / 3.0 + x2 * x2 / 5.0)
    k = jnp.where(small, k_small, k_big)
    return k[..., None] * v
