"""Log-space importance weights and particle resampling (jit/vmap/grad-safe).

Generic particle-filter tools used by :mod:`jaxslam.filters.fastslam` (paper
001, Table 2 steps 3 and 6: normalised weights and resampling to N equally
weighted particles).  Paper 001 says "re-sample" without naming a scheme and
resamples at every step; jaxslam offers the four classical schemes (Douc,
Cappé & Moulines 2005) and a differentiable soft resampler, and the FastSLAM
core triggers resampling on an effective-sample-size threshold.

Decisions (the paper is silent)
-------------------------------
* Weights live in log space and are normalised by log-sum-exp
  (:func:`normalize`): a common offset of any size (all log-weights −1e4,
  which would underflow to 0 in linear space) cancels exactly.  When nothing
  can be normalised (every entry −inf or NaN; NaN entries are treated as −inf)
  the weights are reset to uniform and ``ok`` is False, so a filter never
  propagates NaN weights; callers count and flag the event.  The schemes (which
  return indices only) then draw from uniform weights; :func:`resample_ok`
  returns the indices with that ``ok`` flag.
* Every scheme maps ``n`` (static, default N) ordered uniforms ``u_1 ≤ … ≤
  u_n`` through the inverse CDF of the normalised weights (``searchsorted`` on
  the cumulative sum, last entry forced to exactly 1), so the returned
  ancestor indices are sorted ascending for multinomial, stratified and
  systematic resampling.  A zero-weight particle is never selected (a draw
  that rounds to 1 in float32 is held at the last particle with weight).

  - multinomial: ordered i.i.d. uniforms from normalised cumulative sums of
    n + 1 exponentials (O(n), no sort);
  - stratified: ``u_i = (i + U_i)/n`` with independent ``U_i``;
  - systematic: ``u_i = (i + U)/n`` with one ``U`` (lowest variance of the
    four in practice; the default);
  - residual: ``floor(n w_i)`` deterministic copies of particle i, and the
    remaining ``R = n − Σ floor(n w_i)`` draws **multinomial** on the residual
    weights ``n w_i − floor(n w_i)`` (Liu & Chen 1998).  ``R`` is traced, so
    with static shapes ``n`` i.i.d. (unsorted) draws are made and the first
    ``R`` used; the result is sorted.

  All schemes are unbiased: the expected number of offspring of particle i is
  ``n w_i`` (checked by a chi-square test in the test suite).
* Gradients: indices are integers; the schemes stop gradients through the
  weights (a discrete draw has no pathwise derivative).  :func:`soft` is the
  differentiable option.
* Soft resampling (Karkus, Hsu & Lee, "Particle filter networks", CoRL 2018):
  draw ancestors from ``q = α w + (1 − α)/N`` and give particle j the weight
  ``w_{a_j} / q_{a_j}`` (normalised).  For any α ∈ [0, 1] the set weighted by
  ``w/q`` before normalisation is properly weighted (an importance-sampling step);
  the normalised weights returned give the self-normalised estimate, consistent
  with an O(1/n) bias (exact for α = 1); ``α = 1`` is standard resampling (uniform new weights, hence zero
  gradient through them); ``α = 0`` draws uniformly and keeps the old weights
  (no degeneracy relief, full gradient).  Gradients flow through the new
  weights ``w/q`` (both ``w`` and ``q`` depend on the parameters) but not
  through the discrete indices: the gradient ignores the dependence of the
  ancestor draw on the parameters (the score-function term), which biases it;
  the bias shrinks as α → 0, the variance of the weights grows.
* Called eagerly (outside the caller's ``jit``), each scheme and :func:`soft` run a program
  compiled once per scheme, ``n`` and shapes (:func:`jaxslam.compilation.call_compiled`, on the
  first call): op by op a first call took 0.2-1.9 s and every later one 2-5 ms, now ~0.1-0.5 ms.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from ..compilation import call_compiled
from ..errors import InputError, check_int
from ..linalg import check_key, check_scalar, is_concrete

__all__ = [
    "normalize",
    "ess",
    "log_ess",
    "multinomial",
    "stratified",
    "systematic",
    "residual",
    "SCHEMES",
    "resample",
    "resample_ok",
    "soft",
]

Array = Any


def _float(log_w):
    log_w = jnp.asarray(log_w)
    if not jnp.issubdtype(log_w.dtype, jnp.floating):
        log_w = log_w.astype(jnp.result_type(float))
    return log_w


def normalize(log_w):
    """Normalise log-weights by log-sum-exp (paper 001, Table 2 step 3).

    Args:
        log_w: (N,) unnormalised log-weights (any finite offset; −inf allowed,
            NaN treated as −inf).

    Returns:
        ``(log_w_normalised (N,), ok ())``: ``logsumexp(log_w_normalised) = 0``.
        ``ok`` is False when no entry is finite-and-not −inf (all −inf/NaN) or
        the sum overflows (+inf entries); the weights are then uniform
        (``−log N``).  Safe under ``grad``: the failed branch never produces
        NaN cotangents.
    """
    log_w = _float(log_w)
    n = log_w.shape[-1]
    neg_inf = jnp.asarray(-jnp.inf, log_w.dtype)
    clean = jnp.where(jnp.isnan(log_w), neg_inf, log_w)
    top = jnp.max(clean, axis=-1, keepdims=True)
    ok = jnp.isfinite(top)
    # Shift by the (gradient-free: the result is shift invariant) maximum
    # first: subtracting a log-sum-exp of size 1e4 afterwards would lose
    # float32 precision.  Where the set is degenerate, feed a harmless input
    # so that the unused branch carries no NaN into the gradient.
    zero = jnp.zeros((), log_w.dtype)
    shifted = jnp.where(ok, clean - jax.lax.stop_gradient(jnp.where(ok, top, zero)), zero)
    lse = logsumexp(shifted, axis=-1, keepdims=True)
    uniform = jnp.full_like(log_w, -jnp.log(jnp.asarray(n, log_w.dtype)))
    out = jnp.where(ok, shifted - lse, uniform)
    return out, ok[..., 0]


def log_ess(log_w):
    """Log of the effective sample size ``−log Σ w̄²`` (w̄ normalised)."""
    lw, _ = normalize(log_w)
    return -logsumexp(2.0 * lw, axis=-1)


def ess(log_w):
    """Effective sample size ``N_eff = 1 / Σ w̄_i²`` of (N,) log-weights; in [1, N]."""
    return jnp.exp(log_ess(log_w))


def _cdf(log_w):
    """``(c, w)``: the normalised weights and their cumulative sum, forced to an exact 1 at the
    end so that u < 1 never falls off the table."""
    lw, _ = normalize(jax.lax.stop_gradient(_float(log_w)))
    w = jnp.exp(lw)
    c = jnp.cumsum(w)
    return c.at[-1].set(jnp.ones((), c.dtype)), w


def _invert(log_w, u):
    c, w = _cdf(log_w)
    n_in = c.shape[0]
    idx = jnp.searchsorted(c, u.astype(c.dtype), side="right")
    # A u that rounds to 1 (float32: (i + U)/n with i = n - 1, or a ratio of sums) or that falls
    # above a rounded cumulative sum would pick a trailing particle of zero weight: the last
    # particle with weight is the largest index any u may take.
    last = n_in - 1 - jnp.argmax(w[::-1] > 0)
    return jnp.minimum(jnp.clip(idx, 0, n_in - 1), last).astype(jnp.int32)


def _n(log_w, n):
    if n is None:
        return int(jnp.shape(log_w)[-1])
    return check_int(n, "n", what="a number of draws (an int)")


def _prep(key, log_w, n):
    """Static checks shared by the schemes: ``key`` a PRNG key, ``log_w`` a non-empty (N,)
    vector (under ``vmap`` a scheme sees one row), ``n`` an int >= 1.  Returns (log_w, n)."""
    check_key(key)
    if jnp.ndim(log_w) != 1 or jnp.shape(log_w)[0] == 0:
        raise InputError(f"log_w: expected shape (N,) with N >= 1 (vmap a scheme over a batch), "
                         f"got {jnp.shape(log_w)}")
    lw = _float(log_w)
    return lw, _n(lw, n)


def _sorted_uniforms(key, n, dtype):
    """n ordered i.i.d. U(0,1) draws in O(n): cumulated exponential spacings."""
    e = jax.random.exponential(key, (n + 1,), dtype=dtype)
    c = jnp.cumsum(e)
    return c[:-1] / c[-1]


def multinomial(key, log_w, n: Optional[int] = None):
    """Multinomial resampling: n i.i.d. ancestors from the weights, sorted.

    Args:
        key: PRNG key.  log_w: (N,) log-weights (normalised or not).
        n: static number of draws (default N).

    Returns:
        (n,) int32 ancestor indices, ascending.
    """
    return _compiled("multinomial", key, log_w, n)


def _multinomial(key, lw, n):
    return _invert(lw, _sorted_uniforms(key, n, lw.dtype))


def stratified(key, log_w, n: Optional[int] = None):
    """Stratified resampling: ``u_i = (i + U_i)/n``; sorted indices (n,) int32.

    ``U = jax.random.uniform(key, (n,), dtype)`` (dtype of ``log_w``).
    """
    return _compiled("stratified", key, log_w, n)


def _stratified(key, lw, n):
    U = jax.random.uniform(key, (n,), dtype=lw.dtype)
    u = (jnp.arange(n, dtype=lw.dtype) + U) / n
    return _invert(lw, u)


def systematic(key, log_w, n: Optional[int] = None):
    """Systematic resampling: ``u_i = (i + U)/n``; sorted indices (n,) int32.

    One ``U = jax.random.uniform(key, (), dtype)`` (dtype of ``log_w``), so a
    reference implementation given the same ``U`` reproduces the indices.
    Ancestor of draw i: the smallest j with ``u_i < Σ_{k≤j} w̄_k``.
    """
    return _compiled("systematic", key, log_w, n)


def _systematic(key, lw, n):
    U = jax.random.uniform(key, (), dtype=lw.dtype)
    u = (jnp.arange(n, dtype=lw.dtype) + U) / n
    return _invert(lw, u)


def residual(key, log_w, n: Optional[int] = None):
    """Residual resampling: ``floor(n w_i)`` copies + multinomial remainder.

    The ``R = n − Σ floor(n w_i)`` remaining ancestors are drawn multinomially
    from the residual weights ``n w_i − floor(n w_i)``.  Static shapes: n
    multinomial draws are always made and the first R used.

    Returns:
        (n,) int32 ancestor indices, ascending.
    """
    return _compiled("residual", key, log_w, n)


def _residual(key, lw_in, n):
    lw, _ = normalize(jax.lax.stop_gradient(lw_in))
    nw = n * jnp.exp(lw)
    # A few ulps of slack so that n·(1/n) rounding to 0.999… still gives one
    # deterministic copy; Σ floor stays ≤ n for n < 1/(4 eps) (2e6 in float32).
    counts = jnp.floor(nw * (1 + 4 * jnp.finfo(nw.dtype).eps))
    det_cdf = jnp.cumsum(counts.astype(jnp.int32))  # (N,)
    n_det = det_cdf[-1]
    j = jnp.arange(n, dtype=jnp.int32)
    det_idx = jnp.searchsorted(det_cdf, j, side="right").astype(jnp.int32)
    res_w = jnp.maximum(nw - counts, jnp.zeros((), nw.dtype))
    res_lw = jnp.where(res_w > 0, jnp.log(jnp.where(res_w > 0, res_w, 1.0)), -jnp.inf)
    # Unsorted i.i.d. draws: the first R of them are an i.i.d. sample of size R
    # (the first R of *sorted* draws would favour low indices).
    rest = _invert(res_lw, jax.random.uniform(key, (n,), dtype=lw.dtype))
    rest_idx = rest[jnp.clip(j - n_det, 0, n - 1)]
    idx = jnp.where(j < n_det, det_idx, rest_idx)
    return jnp.sort(jnp.clip(idx, 0, lw.shape[0] - 1)).astype(jnp.int32)


_BODIES = {"multinomial": _multinomial, "stratified": _stratified, "systematic": _systematic,
           "residual": _residual}


def _compiled(name, key, log_w, n):
    """A scheme's draw, its arguments checked (:func:`_prep`); called eagerly, through a program
    compiled once per scheme, ``n`` and shapes (:func:`jaxslam.compilation.call_compiled`: op by
    op a first call took 0.2-1.5 s and every later one 2-4 ms)."""
    lw, n = _prep(key, log_w, n)
    body = _BODIES[name]
    return call_compiled(("resampling." + name, n), lambda k, w: body(k, w, n), (key, lw), after="auto")


SCHEMES: Dict[str, Callable] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def _scheme(scheme):
    if callable(scheme):
        return scheme
    try:
        return SCHEMES[scheme]
    except KeyError:
        raise InputError(
            f"scheme: unknown resampling scheme {scheme!r}; choose one of {sorted(SCHEMES)}"
        ) from None


def resample(key, log_w, scheme="systematic", n: Optional[int] = None):
    """Ancestor indices (n,) int32 by a named scheme (see :data:`SCHEMES`) or a callable.

    When the weights cannot be normalised (every entry −inf or NaN, or a +inf entry) every
    scheme draws from uniform weights; :func:`resample_ok` also returns the ``ok`` flag that
    tells this fallback apart.
    """
    return _scheme(scheme)(key, log_w, n)


def resample_ok(key, log_w, scheme="systematic", n: Optional[int] = None):
    """:func:`resample` plus the ``ok`` flag of :func:`normalize`.

    Returns:
        ``(indices (n,) int32, ok ())``: ``ok`` is False when the weights could not be
        normalised (every entry −inf or NaN, or a +inf entry); the indices were then drawn
        from uniform weights.  Costs one more reduction over ``log_w``.
    """
    fn = _scheme(scheme)
    idx = fn(key, log_w, n)
    _, ok = normalize(jax.lax.stop_gradient(_float(log_w)))
    return idx, ok


def soft(key, log_w, alpha, scheme="multinomial"):
    """Soft (differentiable-weight) resampling (Karkus et al. 2018).

    Draws N ancestors ``a_j`` from ``q = α w̄ + (1 − α)/N`` and returns the new
    normalised log-weights ``log(w̄_{a_j} / q_{a_j})``.  See the module
    docstring for the bias of the gradient (indices carry none).

    Args:
        key: PRNG key.  log_w: (N,) log-weights.
        alpha: () mixture weight in [0, 1] (1 = standard resampling, 0 = uniform draw
            keeping the old weights).  A concrete value outside [0, 1] (or not finite) is an
            :class:`InputError`; a traced one is used as if clipped to [0, 1].
        scheme: scheme used to draw from ``q`` (default multinomial, as in
            Karkus et al.; "systematic" lowers the variance).

    Returns:
        ``(indices (N,) int32, new_log_w (N,) normalised)``.  Called eagerly it is compiled
        once per shape and scheme (:func:`jaxslam.compilation.call_compiled`; op by op the
        first call took 1.9 s).
    """
    log_w, _ = _prep(key, log_w, None)
    if jnp.ndim(alpha) != 0:
        raise InputError(f"alpha: expected a scalar mixture weight in [0, 1], got shape {jnp.shape(alpha)}")
    if is_concrete(alpha) and check_scalar(alpha, "alpha", lower=0) > 1.0:
        raise InputError(f"alpha: expected a mixture weight in [0, 1], got {alpha!r}")
    _scheme(scheme)
    return call_compiled(("resampling.soft", scheme), lambda *a: _soft(*a, scheme), (key, log_w, alpha),
                         after="auto")


def _soft(key, log_w, alpha, scheme):
    """:func:`soft`'s computation (its arguments checked by the caller)."""
    lw, _ = normalize(log_w)
    n = lw.shape[-1]
    a = jnp.asarray(alpha, lw.dtype)
    log_unif = -jnp.log(jnp.asarray(n, lw.dtype))
    # log q = log(α w + (1 − α)/N), written with logaddexp so that α = 0 or 1
    # stay finite and differentiable.
    tiny = jnp.finfo(lw.dtype).tiny
    log_a = jnp.log(jnp.maximum(a, tiny))
    log_1ma = jnp.log(jnp.maximum(1.0 - a, tiny))
    log_q = jnp.logaddexp(log_a + lw, log_1ma + log_unif)
    log_q = jnp.where(a >= 1.0, lw, jnp.where(a <= 0.0, jnp.full_like(lw, log_unif), log_q))
    idx = resample(key, log_q, scheme)
    new = lw[idx] - log_q[idx]
    new, _ = normalize(new)
    return idx, new
