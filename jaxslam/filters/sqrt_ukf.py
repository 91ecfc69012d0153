"""Square-root sigma-point filter: the UKF / cubature filter propagating a Cholesky factor.

The beliefs are :class:`jaxslam.filters.sqrt_ekf.SqrtGaussian` (``P = L Lᵀ``) and ``P`` is
never formed; the moments are those of :mod:`jaxslam.filters.ukf` (same rules, same masks,
gate and status flags), so in exact arithmetic both filters give the same estimates.

Equations (weights ``W^c_i ≥ 0`` required: the cubature rule, or the unscented rule with
``W^c_0 ≥ 0``, e.g. the default α = 1, β = 2, κ = 0)::

    X = [√W^c_i (χ_i − x̄)]  (n × N),   Y = [√W^c_i (Z_i − ẑ)]  (m × N)
    predict:  L' = tria([√W^c_i (f(χ_i) − x̄'),  L_Q])
    update:   A = Y Xᵀ (L Lᵀ)⁻¹ (the statistical linearisation of h; X Xᵀ = P exactly)
              E = Y − A X        (its residual; E Eᵀ = Σ_z − A P Aᵀ, the linearisation error)
              tria([[L_R, E, A L], [0, 0, L]]) = [[S^½, 0, 0], [K̄, L⁺, 0]]
              x⁺ = x̄ + K̄ S^{-½} ν,  NIS = ‖S^{-½} ν‖²

With ``R' = R + E Eᵀ`` the update is the linear square-root update of
:func:`jaxslam.filters.sqrt_ekf.update` with ``H = A``: ``A P Aᵀ + R' = Σ_z + R = S`` and
``P Aᵀ = X Yᵀ = C``, so the gain and the posterior are the sigma-point filter's, obtained from
one QR without the subtraction ``P − K S Kᵀ`` that can lose definiteness in float32.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError, check_flag
from ..linalg import check_numbers, check_psd, is_concrete, list_array, symmetrize
from .gaussian import (
    Gate,
    UpdateInfo,
    call_residual,
    check_gate,
    check_gate_size,
    check_measurement,
    check_noise_values,
    check_update_args,
    check_update_call,
    failure_status,
    scalar_measurement,
    single_variance,
    masked_innovation,
    gate_test,
)
from .sqrt_ekf import (SqrtGaussian, SqrtPosterior, _as_not_psd, _host_root, _kept, _mm, _noise_root, _tria,
                       _unfactored, check_state, psd_factor)
from .ukf import (
    SigmaPoints,
    _rule,
    check_transition,
    measurement_mean,
)

__all__ = ["predict", "update", "filter_scan"]

Array = Any


def _points(state: SqrtGaussian, rule: SigmaPoints):
    """Points from the factor itself (no Cholesky of P): ``(points, x − x̄, W^m, √W^c)``."""
    x = state.mean
    L = state.chol
    n = x.shape[0]
    wm, wc, c = rule.weights(n)
    if wc.min() < 0:
        raise InputError(f"points: the square-root form needs every covariance weight >= 0, got "
                         f"W^c_0 = {wc[0]:.3g} (use alpha=1, beta=2, kappa=0, or ukf.cubature())")
    D = jnp.asarray(c, x.dtype) * L.T
    dx = jnp.concatenate([D, -D], 0)
    if rule.has_center:
        dx = jnp.concatenate([jnp.zeros((1, n), x.dtype), dx], 0)
    return x + dx, dx, jnp.asarray(wm, x.dtype), jnp.asarray(np.sqrt(wc), x.dtype)


def predict(state: SqrtGaussian, f: Optional[Callable], u, Q, *args,
            points: Optional[SigmaPoints] = None, Q_chol=None, return_status: bool = False):
    """Square-root sigma-point time update (module docstring); ``Q`` a covariance or ``Q_chol`` a root.

    A non-finite predicted mean or factor (a NaN/Inf in a traced ``Q`` or ``f``'s output) keeps
    the prior and, with ``return_status`` (static), returns ``NON_FINITE`` beside it
    (``NOT_PSD`` when a finite traced ``Q`` has no real root: indefinite):
    ``(SqrtGaussian, status)``; :func:`filter_scan` adds it to the step's status.  The state
    (:func:`check_state`), the rule and, when known now, ``Q`` (symmetric PSD; for a
    one-component state a scalar is its variance, as in :func:`jaxslam.filters.ukf.predict`) or
    ``Q_chol`` (finite) are checked first: :class:`InputError` naming the argument.  Called eagerly it is
    compiled once per model (:func:`jaxslam.compilation.call_compiled`; a concrete ``Q`` is
    still factored on the host in float64 first).
    """
    rule = _rule(points)
    return_status = check_flag(return_status, "return_status")
    state, Q = _check_predict(state, Q, Q_chol)  # the values known now (the compiled step sees them traced)
    C = _host_root(Q, state.mean.dtype) if Q_chol is None else None
    Q, Q_chol = list_array(Q, "Q"), list_array(Q_chol, "Q_chol")  # lists would reach the program as tracers

    def step(opts, state, Q, Q_chol, C):
        u, a = opts
        return _predict(state, f, u, Q, a, rule, Q_chol, C, return_status)

    return call_compiled(("sqrt_ukf.predict", f, rule, return_status), step, (state, Q, Q_chol, C), (u, args),
                         after=2)


def _check_predict(state, Q, Q_chol):
    """The belief and the process noise of a predict: shapes, and the values known now.
    Returns ``(state, Q)``; a scalar (or (1,)) ``Q`` of a one-component state is the variance of
    its single noise input, as in :func:`jaxslam.filters.ukf.predict`, and becomes (1, 1)."""
    state = check_state(state)
    n = state.mean.shape[0]
    if Q_chol is None and Q is not None and n == 1 and np.shape(Q) in ((), (1,)):
        Q = jnp.reshape(check_numbers(Q, "Q") if is_concrete(Q) else Q, (1, 1))
    if Q_chol is None:
        qs = tuple(np.shape(Q))
        if qs != (n, n):
            raise InputError(f"Q: expected shape ({n}, {n}) (the state's size), got {qs}")
        check_noise_values(Q, "Q")  # an eager call (traced: the status speaks)
    elif np.ndim(Q_chol) != 2 or np.shape(Q_chol)[0] != n:
        raise InputError(f"Q_chol: expected shape ({n}, k), got {tuple(np.shape(Q_chol))}")
    elif is_concrete(Q_chol) and not np.all(np.isfinite(check_numbers(Q_chol, "Q_chol"))):
        raise InputError("Q_chol: contains NaN or Inf")
    return state, Q


def _predict(state, f, u, Q, args, rule, Q_chol, C, return_status):
    """:func:`predict`'s computation (its checks of shapes; ``C``: the root of ``Q`` when known)."""
    state, Q = _check_predict(state, Q, Q_chol)
    x = state.mean
    dtype = x.dtype
    fm = (lambda v, u_, *a: v) if f is None else f
    pts, _, wm, sw = _points(state, rule)
    X = check_transition(jax.vmap(lambda p: jnp.asarray(fm(p, u, *args)))(pts), pts.shape).astype(dtype)
    xm = wm @ X
    C = _noise_root(Q, Q_chol, dtype) if C is None else jnp.asarray(C, dtype)
    L = _tria(jnp.concatenate([((X - xm) * sw[:, None]).T, C], axis=1))
    good = jnp.all(jnp.isfinite(xm)) & jnp.all(jnp.isfinite(L))
    out = SqrtGaussian(jnp.where(good, xm, x), jnp.where(good, L, state.chol))
    if return_status:
        i32 = jnp.int32
        # a finite Q whose root is NaN is indefinite (a traced negative Q): NOT_PSD
        indef = (jnp.all(jnp.isfinite(jnp.asarray(Q, dtype))) & ~jnp.all(jnp.isfinite(C))
                 if Q_chol is None else jnp.asarray(False))
        return out, jnp.where(good, i32(0), jnp.where(indef, i32(errors.NOT_PSD), i32(errors.NON_FINITE)))
    return out


def update(state: SqrtGaussian, z, h: Callable, R, *args, residual: Optional[Callable] = None,
           mask=None, gate: Gate = None, points: Optional[SigmaPoints] = None):
    """Square-root sigma-point measurement update; same semantics as :func:`jaxslam.filters.ukf.update`.

    Returns ``(posterior SqrtGaussian, UpdateInfo)`` (``S`` formed from its factor, ``logdet``
    over the valid block).  A singular factor (``NOT_PSD``) or a non-finite posterior
    (``NON_FINITE``) keeps the prior, and so does a traced gate that is not > 0 (NaN included:
    ``GATED | NON_FINITE``).  As :func:`jaxslam.filters.ukf.update`, the state
    (:func:`check_state`), the rule, the gate and a concrete ``R`` (positive definite, or a
    scalar variance > 0 for one measurement) are checked first: :class:`InputError` naming the
    argument.  Called eagerly it is compiled once per model
    (:func:`jaxslam.compilation.call_compiled`).
    """
    rule = _rule(points)
    state, z, R, mask = check_update_call(state, z, R, mask, gate, check_state)  # the values known now

    def step(opts, state, z, R, mask):
        a, g = opts
        return _update(state, z, h, R, *a, residual=residual, mask=mask, gate=g, rule=rule)

    return call_compiled(("sqrt_ukf.update", h, residual, rule), step, (state, z, R, mask), (args, gate), after=2)


def _update(state, z, h, R, *args, residual=None, mask=None, gate: Gate = None, rule: SigmaPoints = None):
    """:func:`update`'s computation (shape checks; values are checked by the caller)."""
    x, L = check_state(state)
    dtype = x.dtype
    check_update_args(z, R, mask)
    z, h = scalar_measurement(z, h)
    z = jnp.asarray(z, dtype)
    R = jnp.asarray(R, dtype)
    m = z.shape[-1]
    n = x.shape[0]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    res = (lambda a, b: a - b) if residual is None else residual
    zero = jnp.zeros((), dtype)
    eye_m = jnp.eye(m, dtype=dtype)
    pts, dx, wm, sw = _points(SqrtGaussian(x, L), rule)
    Z = jax.vmap(lambda p: jnp.asarray(h(p, *args)))(pts).astype(dtype)
    zref = Z[0] if rule.has_center else jnp.asarray(h(x, *args), dtype)
    check_measurement(z, zref, R, mask)
    check_gate_size(gate, m, mask)
    Z, zhat = measurement_mean(Z, zref, wm, mask, res)
    dZ = jnp.where(mask[None, :], jax.vmap(lambda zi: call_residual(res, zi, zhat))(Z), zero)
    Xs = (dx * sw[:, None]).T  # (n, N)
    Ys = (dZ * sw[:, None]).T  # (m, N)
    # A = Y Xᵀ P⁻¹ by two triangular solves with L (P = L Lᵀ = X Xᵀ)
    d_ok = jnp.all(jnp.diagonal(L) > 0) & jnp.all(jnp.isfinite(L))
    Ls = jnp.where(d_ok, L, jnp.eye(n, dtype=dtype))
    YXt = _mm(Ys, Xs.T)  # (m, n) = Cᵀ
    tmp = jax.scipy.linalg.solve_triangular(Ls, YXt.T, lower=True)  # L⁻¹ C
    A = jax.scipy.linalg.solve_triangular(Ls.T, tmp, lower=False).T  # C P⁻¹... as (m, n)
    E = Ys - _mm(A, Xs)
    mm = mask[:, None] & mask[None, :]
    L_R = jnp.linalg.cholesky(symmetrize(jnp.where(mm, R, eye_m)))
    pre = jnp.block([[L_R, E, _mm(A, Ls)],
                     [jnp.zeros((n, m), dtype), jnp.zeros((n, E.shape[1]), dtype), Ls]])
    B = _tria(pre)
    S_half = jnp.where(mm, B[:m, :m], eye_m)
    Kbar = jnp.where(mask[None, :], B[m:, :m], zero)
    L_post = B[m:, m:m + n]
    d = jnp.diagonal(S_half)
    ok = d_ok & jnp.all(jnp.isfinite(S_half)) & jnp.all(d > 0)
    S_safe = jnp.where(ok, S_half, eye_m)
    nu = masked_innovation(z, zhat, mask, res)
    w = jax.scipy.linalg.solve_triangular(S_safe, nu, lower=True)
    nis = jnp.where(ok, jnp.dot(w, w), zero)  # a failed factor is NOT_PSD, never GATED
    x_post = x + _mm(Kbar, w)
    dof = jnp.sum(mask).astype(jnp.int32)
    g_status = jnp.int32(0)
    if gate is None:
        gated = jnp.asarray(False)
    else:  # a traced threshold that is not > 0 (NaN) gates the update and flags NON_FINITE
        gated, g_status = gate_test(gate, nis, dof, dtype)
    finite = jnp.all(jnp.isfinite(x_post)) & jnp.all(jnp.isfinite(L_post))
    # a NaN/Inf in the prior factor, the spread of h's outputs (a NaN mean's points) or R's valid
    # block is NON_FINITE, not NOT_PSD: the rule of the covariance filters (gaussian.failure_status)
    finite_in = (jnp.all(jnp.isfinite(L)) & jnp.all(jnp.isfinite(Ys))
                 & jnp.all(jnp.isfinite(jnp.where(mm, R, eye_m))))
    has = dof > 0
    accepted = has & ~gated & ok & finite
    i32 = jnp.int32
    status = (jnp.where(gated, i32(errors.GATED), i32(0))
              | failure_status(has & ~gated, ok, finite_in, finite)
              | g_status)
    post = SqrtGaussian(jnp.where(accepted, x_post, x), jnp.where(accepted, L_post, L))
    logdet = jnp.where(ok & has, 2.0 * jnp.sum(jnp.log(jnp.where(mask, jnp.abs(jnp.diagonal(S_safe)), 1.0))),
                       zero)
    return post, UpdateInfo(nis, dof, nu, symmetrize(_mm(S_half, S_half.T)), accepted, status, logdet)


def filter_scan(f: Optional[Callable], h: Callable, x0, P0, us, zs, masks, Q, R, *args,
                residual: Optional[Callable] = None, gate: Gate = None, predict_first: bool = True,
                points: Optional[SigmaPoints] = None, save_chol: bool = False) -> SqrtPosterior:
    """Square-root sigma-point filter over a whole sequence (one ``lax.scan``).

    Arguments as :func:`jaxslam.filters.sqrt_ekf.filter_scan` (``Q`` (n, n) or (T, n, n) is
    factored once per matrix before the scan, a scalar for n = 1 as in :func:`predict`; ``R``
    (m, m) or (T, m, m)) plus ``points``
    (static), without ``noise_jac`` and ``Q_chol``.  A predict that fails (non-finite;
    ``NOT_PSD`` for an indefinite traced ``Q``) is skipped, as in every Gaussian run: the step
    it fed keeps the belief the predict started from, makes no update (NIS 0) and carries the
    bits (it used to update that belief with its ``z``).  ``P0`` (and a concrete ``Q``) is
    factored as given, then cast to ``x0``'s dtype, as in
    :func:`jaxslam.filters.sqrt_ekf.filter_scan` (``P0`` used to be cast first).  With
    ``predict_first=False`` the first update factors ``P0`` itself, so a concrete ``P0`` must then be positive definite,
    as in :func:`jaxslam.filters.ukf.filter_scan` (:class:`InputError` naming ``P0``; a
    singular one used to fail that update with ``NOT_PSD``).  Returns
    :class:`~jaxslam.filters.sqrt_ekf.SqrtPosterior`.
    """
    from .gaussian import check_leading, check_run_inputs, check_run_q_size, noise_size

    rule = _rule(points)
    check_gate(gate)
    predict_first = check_flag(predict_first, "predict_first")
    save_chol = check_flag(save_chol, "save_chol")
    # what every Gaussian filter's run checks, before the casts (a str x0 or zs ended in a bare
    # TypeError there); Q's squareness and per-step count included, its size below
    T, m = check_run_inputs(x0, P0, zs, masks, Q, R)
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    x0 = x0.astype(dtype)
    zs = jnp.asarray(zs, dtype)
    n = x0.shape[0]
    if not predict_first and is_concrete(P0):
        # the first update's statistical linearisation needs P0⁻¹ (a zero variance: NOT_PSD)
        check_psd(P0, "P0", strict=True, tol=0.0)
    check_run_q_size(Q, *noise_size(x0, None), T)  # (the message of every Gaussian run)
    if n == 1 and np.shape(Q) in ((), (1,)):  # the variance of the one noise input, as in predict
        Q = single_variance(Q)
    check_leading(us, T, "us")
    masks = jnp.ones((T, m), bool) if masks is None else jnp.asarray(masks, bool)
    # factored as given, then cast (a concrete P0 on the host in float64, as sqrt_ekf.filter_scan
    # and the module's predicts do): it was cast first, so a float32 run started from the factor
    # of the rounded P0, not the nearest float32 factor of P0
    L0 = psd_factor(P0, dtype)
    q_step = np.ndim(Q) == 3
    CQ = _noise_root(Q, None, dtype)
    Ra = jnp.asarray(R, dtype)
    Ra = Ra.reshape(1, 1) if Ra.ndim < 2 else Ra  # a scalar variance of one measurement
    r_step = Ra.ndim == 3
    unf = _unfactored((P0, Q), (L0, CQ))  # an indefinite traced P0 or Q: NOT_PSD (sqrt_ekf._as_not_psd)

    def scan(opts, x0, L0, CQ, us, zs, masks, Ra, unf):
        args, gate = opts

        def step(carry, inp):
            # a failed predict keeps its prior and flags the step whose prior it made: this one
            # with predict_first, else the next (``pending``)
            state, _, pending = carry
            u, z, mk, cq, rt = inp
            cq = cq if q_step else CQ
            rt = rt if r_step else Ra
            if predict_first:
                state, p_status = predict(state, f, u, None, *args, points=rule, Q_chol=cq, return_status=True)
            else:
                p_status = pending
            post, info = update(state, z, h, rt, *args, residual=residual, mask=mk, gate=gate, points=rule)
            # the step whose prior a failed predict made keeps its belief and makes no update
            # (gaussian.make_step, the rule of every Gaussian run); selected after the update
            post = _kept(p_status, post, state)
            info = info._replace(nis=jnp.where(p_status != 0, jnp.zeros_like(info.nis), info.nis))
            if predict_first:
                nxt = post
            else:
                nxt, pending = predict(post, f, u, None, *args, points=rule, Q_chol=cq, return_status=True)
            out = (post.mean, jnp.sum(post.chol**2, axis=1), post.chol if save_chol else None,
                   info.nis, info.dof, info.status | p_status)
            return (nxt, post, pending), out

        xs = (us, zs, masks, CQ if q_step else None, Ra if r_step else None)
        init = SqrtGaussian(x0, L0)
        (_, final, _), (means, diags, chols, nis, dof, status) = jax.lax.scan(
            step, (init, init, jnp.zeros((), jnp.int32)), xs, length=zs.shape[0])
        return SqrtPosterior(means, diags, chols, nis, dof, _as_not_psd(status, unf), final)

    # called eagerly: compiled once per model, options and shapes
    return call_compiled(("sqrt_ukf.filter_scan", f, h, residual, rule, predict_first, save_chol, q_step,
                          r_step), scan, (x0, L0, CQ, us, zs, masks, Ra, unf), (args, gate))
