"""Generic extended Kalman filter core: predict, masked/gated update, whole-run scan.

This is the reference filter of jaxslam.  It never names a paper's model: the
FastSLAM per-particle landmark filters, the bias Kalman filter and small-state
systems call it with their own ``f`` and ``h``; the EKF-SLAM engine
(:mod:`jaxslam.filters.ekf_slam`) uses the same algebra on gathered blocks.
The equations are the textbook discrete EKF as written in paper 003, eq. 4-10
and paper 000, eq. 26-28 and 37-43, with the decisions below.

Decisions (where the papers are silent or where jaxslam departs from them)
-------------------------------------------------------------------------
* Discrete time.  ``predict`` propagates ``x' = f(x, u, *args)`` and
  ``P' = F P Fᵀ + Q`` (paper 003 eq. 4-5).  A continuous-time model (paper 000
  eq. 27) must be discretised by the caller (``f`` integrates over the step,
  ``Q`` is the discrete covariance).  An optional noise Jacobian ``L`` gives
  ``P' = F P Fᵀ + L Q Lᵀ``.
* Jacobians come from :func:`jax.jacfwd` of the model, evaluated in the same
  pass as the model itself (``has_aux``), never from hand derivations.
* Covariance update: the factored Joseph form
  ``(I − K H) P (I − K H)ᵀ + K R Kᵀ`` replaces paper 000 eq. 43
  (``P − K E Kᵀ``) and paper 003 eq. 10 (``(I − K H E) P``, whose ``E`` is a
  typo).  It is evaluated as ``A − (A Hᵀ) Kᵀ + K R Kᵀ`` with
  ``A = P − K (H P)``: the same product, associated so that it costs
  O(n² m) rather than O(n³); the result is symmetrised once.
* Gain: ``K = P Hᵀ S⁻¹`` from one Cholesky solve of the innovation
  covariance ``S`` with the right-hand sides ``[H P | ν]`` (gain and NIS share
  the factor); an explicit inverse is never formed.
* Masks, not branches: an invalid measurement component gets a zero row of
  ``H``, a zero innovation and a unit ``R`` block (zero cross terms).  The
  resulting ``S`` is block-diagonal (valid block, identity), so the gain
  columns of invalid components are exactly zero and the update equals the
  update with only the valid rows.  The measurement of an invalid component
  is replaced by its prediction *before* the residual is formed, so NaN/Inf
  garbage there never reaches the arithmetic (nor its gradient).
* Gating: the NIS ``νᵀ S⁻¹ ν`` is compared with a chi-square threshold.  The
  threshold is either a number (same for every call, traced under ``jit``) or
  a callable ``gate(dof) -> threshold``, useful when masks change the number
  of valid components: :func:`chi2_gate` builds one from a host-computed
  float64 table (``lambda d: jaxslam.stats.chi2_ppf(0.99, d)`` also works
  but adds about 2 s of compilation per runner for the incomplete gamma).
  A gated update leaves the state unchanged and sets ``errors.GATED``.
* Failures never produce silent NaNs: if the Cholesky factor of ``S`` is not
  finite (``errors.NOT_PSD``) or the posterior is not finite
  (``errors.NON_FINITE``), the prior is returned unchanged and flagged.  A NaN/Inf in ``S``
  (from the prior, ``H`` or ``R``) is ``NON_FINITE`` alone, and a finite ``S`` that does not
  factor ``NOT_PSD`` alone, in all four generic filters
  (:func:`jaxslam.filters.gaussian.failure_status`).
* ``UpdateInfo.accepted`` is True exactly when the state was changed: at least
  one valid component, not gated, numerically sound.
* ``update_batch`` processes M measurements of the same model jointly (one
  stacked update, fixed shapes).  Each measurement is gated on its *marginal*
  NIS (its own block ``S_ii`` of the joint innovation covariance, against the
  prior), and the gated ones are masked out of the joint update.  The
  sequential variant (``sequential=True``, one ``lax.scan`` over
  measurements) gates each measurement against the state updated by the
  previous ones; for a linear model without gating both give the same
  posterior.
* ``filter_scan`` ordering: step t predicts with ``u_t`` and then updates with
  ``z_t``; ``(x0, P0)`` is the estimate *before* the first control, and
  ``means[t]`` is the filtered estimate after ``z_t``.  With
  ``predict_first=False`` the step updates with ``z_t`` first (``(x0, P0)`` is
  the prior at the time of ``z_0``), stores the filtered estimate, then
  predicts with ``u_t``.
* dtype: every function computes in the dtype of ``state.mean``; ``Q``, ``R``
  and ``z`` are cast to it so a float32 filter stays float32 inside a scan.

Which entry point to use: the single-step ``predict``/``update`` are for
users who drive their own loop or embed the filter in a simulation scan;
for a whole recorded run use ``filter_scan`` (one ``lax.scan``; a Python loop
over jitted steps pays 50-100 µs per call).
"""

from __future__ import annotations

import math
import statistics
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..errors import InputError, check_flag, check_int
from ..linalg import check_mask, check_psd, check_scalar, is_concrete, symmetrize, value_and_jacfwd, wrap_angle
from ..stats import chi2_ppf_np
from ..compilation import call_compiled
from . import gaussian as _g
from .gaussian import (
    Gate,
    Gaussian,
    GaussianFilter,
    Posterior,
    UpdateInfo,
    call_residual,
    check_gate,
    check_gate_size,
    check_measurement,
    check_real,
    check_num_iter,
    check_state,
    check_transition_out,
    check_update_args,
    finalize as _finalize,
    scalar_measurement,
    innovation_solve,
    masked_innovation,
    process_noise,
)

__all__ = [
    "Gaussian",
    "UpdateInfo",
    "Posterior",
    "predict",
    "predict_additive",
    "update",
    "update_batch",
    "filter_scan",
    "make_filter",
    "linear_update",
    "linear_update_shared",
    "GaussianFilter",
    "angle_residual",
    "chi2_gate",
    "validate_gaussian",
    "validate_noise_cov",
]

Array = Any


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def angle_residual(angle_mask) -> Callable[[Array, Array], Array]:
    """Build a residual ``ν(z, ẑ)`` that wraps the chosen components to [−π, π).

    Args:
        angle_mask: (m,) bools (sequence or array); True marks a component in
            radians whose difference must be wrapped (bearing, azimuth, yaw).

    Returns:
        ``residual(z, zhat) -> (m,)`` = ``z − ẑ`` with the angle components
        passed through :func:`jaxslam.linalg.wrap_angle` (derivative 1 away
        from ±π, so it is safe under ``grad``).  Works on any leading batch
        axes of ``z``/``zhat``.  A mask that is not bool (or 0/1 integers) or not
        1-D is an :class:`InputError` naming ``angle_mask``, and so is a residual
        whose last axis differs from the mask's length (a length-1 mask was
        broadcast onto every component).
    """
    check_mask(angle_mask, "angle_mask")
    am = np.asarray(angle_mask, dtype=bool)
    if am.ndim != 1:
        raise InputError(f"angle_mask: expected shape (m,) (one flag per component), got {am.shape}")

    def residual(z, zhat):
        d = z - zhat
        if np.shape(d)[-1:] != am.shape:
            raise InputError(f"angle_mask: has {am.shape[0]} entries, but the residual has shape "
                             f"{tuple(np.shape(d))}")
        return jnp.where(am, wrap_angle(d), d)

    return residual


def chi2_gate(prob: float, max_dof: int) -> Callable[[Array], Array]:
    """A gate ``dof -> χ²_prob(dof)`` from a table computed once on the host.

    Pass it as ``gate=`` to :func:`update`, :func:`update_batch` or
    :func:`filter_scan` when masks change the number of valid components.
    The table (float64, :func:`jaxslam.stats.chi2_ppf_np`) costs nothing
    inside ``jit``, unlike evaluating :func:`jaxslam.stats.chi2_ppf` there.

    Args:
        prob: gate probability, e.g. 0.99 (a consistent measurement is
            rejected with probability 1 − prob).
        max_dof: largest number of valid components (the measurement size m).

    Returns:
        ``gate(dof)`` giving the threshold for ``dof`` in 1..max_dof (+inf for
        dof 0, where nothing is updated anyway); its ``max_dof`` attribute lets
        the updates refuse a measurement with more components
        (:class:`InputError` naming ``gate``).  Beyond the table — a traced mask
        letting more than ``max_dof`` components through, which the updates cannot
        see before running — the threshold is the Wilson–Hilferty approximation of
        the quantile (exact for dof 2; from dof 3 on within 0.7 % of it for
        0.5 ≤ prob ≤ 0.995 and 3.5 % up to 0.9999, but poor for small prob: 1.2 % at 0.3,
        7 % at 0.05, 34 % at 0.01, so build a gate of prob < 0.5 for m); it was the table's
        last value (χ²(2) for a 5-component NIS).
        ``max_dof`` must be an int >= 1 (:class:`InputError` naming it; 1.5, True
        and "2" were truncated or parsed).
    """
    if isinstance(prob, (bool, np.bool_, str, bytes)) or not 0.0 < float(prob) < 1.0:
        raise InputError(f"prob: must be in (0, 1), got {prob!r}")
    max_dof = check_int(max_dof, "max_dof")
    table = np.array([np.inf] + [chi2_ppf_np(prob, d) for d in range(1, max_dof + 1)])
    z_p = statistics.NormalDist().inv_cdf(float(prob))
    chi2_2 = -2.0 * math.log1p(-float(prob))  # the exact quantile for 2 dof

    def gate(dof):
        thr = jnp.asarray(table)
        d = jnp.asarray(dof)
        k = jnp.maximum(d, 1).astype(thr.dtype)
        c = 2.0 / (9.0 * k)
        beyond = jnp.where(d == 2, chi2_2, k * (1.0 - c + z_p * jnp.sqrt(c)) ** 3)
        return jnp.where(d > max_dof, beyond.astype(thr.dtype), thr[jnp.clip(d, 0, max_dof)])

    gate.max_dof = max_dof
    return gate


def _default_residual(z, zhat):
    return z - zhat


def linear_update(x, P, nu, H, R, mask):
    """Kalman correction for a given Jacobian ``H`` and residual ``ν``, invalid components neutralised.

    The algebra of :func:`update` without the model: the iterated update and the
    iterated smoother call it with their own linearisation.

    Args:
        x: (n,) prior mean.  P: (n, n) prior covariance.
        nu: (m,) residual (0 on invalid components).  H: (m, n) measurement
        Jacobian.  R: (m, m).  mask: (m,) bool validity.

    Returns:
        (x_post, P_post, S, nu_m, nis, ok, logdet) with ``ok`` the Cholesky flag.
    """
    xs, P_post, S, num, nis, ok, logdet = linear_update_shared(x[None], P, nu[None], H, R, mask)
    return xs[0], P_post, S, num[0], nis[0], ok, logdet


def linear_update_shared(xs, P, nus, H, R, mask):
    """:func:`linear_update` of B means that share one prior covariance and one model.

    When the covariance does not depend on the data (a linear-Gaussian sub-state
    carried by every particle of a Rao-Blackwellised filter: same A, Q, H, R for
    all), the gain and the posterior covariance are the same for every mean.  One
    Cholesky factorisation and one solve with B + n right-hand sides serve all of
    them, and the means move by one (B, m) × (m, n) product; ``vmap(update)``
    would solve one triangular system per mean instead.  Equal to B separate
    updates.

    Args:
        xs: (B, n) prior means.  P: (n, n) shared prior covariance.
        nus: (B, m) residuals.  H: (m, n).  R: (m, m).  mask: (m,) bool, shared.

    Returns:
        ``(xs_post (B, n), P_post, S, nus_m (B, m), nis (B,), ok, logdet)``: the
        covariance, ``S``, ``ok`` and ``log det S`` are shared.
    """
    dtype = xs.dtype
    m = nus.shape[-1]
    n = xs.shape[-1]
    mm = mask[:, None] & mask[None, :]
    Hm = jnp.where(mask[:, None], H, jnp.zeros((), dtype))
    num = jnp.where(mask, nus, jnp.zeros((), dtype))
    Rm = jnp.where(mm, R, jnp.eye(m, dtype=dtype))
    HP = Hm @ P  # (m, n): the only product with the full P on the gain path
    S = symmetrize(HP @ Hm.T + Rm)
    X, ok, logdet = innovation_solve(S, jnp.concatenate([HP, num.T], axis=1))
    K = X[:, :n].T  # (n, m) = P Hᵀ S⁻¹ (P symmetric)
    W = X[:, n:]  # (m, B) = S⁻¹ νᵀ
    nis = jnp.sum(num.T * W, axis=0)
    xs_post = xs + num @ K.T
    # Factored Joseph form (I − KH) P (I − KH)ᵀ + K R Kᵀ, associated as
    # A − (A Hᵀ) Kᵀ + K R Kᵀ with A = P − K (H P): O(n² m), same product.
    A = P - K @ HP
    P_post = symmetrize(A - (A @ Hm.T) @ K.T + K @ Rm @ K.T)
    return xs_post, P_post, S, num, nis, ok, logdet


# ---------------------------------------------------------------------------
# Predict
# ---------------------------------------------------------------------------

def predict(state: Gaussian, f: Callable, u, Q, *args, noise_jac=None, return_status: bool = False):
    """EKF time update (paper 003 eq. 4-5; discrete form of paper 000 eq. 26-28).

    ``x' = f(x, u, *args)``, ``F = ∂f/∂x`` at the prior mean (``jax.jacfwd``),
    ``P' = F P Fᵀ + Q`` or, with a noise Jacobian ``L``, ``F P Fᵀ + L Q Lᵀ``;
    the result is symmetrised.

    Args:
        state: prior :class:`Gaussian`, mean (n,), cov (n, n).
        f: discrete transition ``f(x (n,), u, *args) -> (n,)`` over one step
            (it integrates the dynamics; units are the model's).
        u: control/input of the step (any pytree, e.g. IMU sample).
        Q: (n, n) discrete process-noise covariance, or (q, q) with
            ``noise_jac``.
        *args: extra arguments passed to ``f`` (and ``noise_jac``).
        noise_jac: None, an (n, q) matrix ``L``, or a callable
            ``L(x, u, *args) -> (n, q)`` evaluated at the prior mean.
        return_status: static; also return the int32 status word of the prediction:
            ``NON_FINITE`` when the predicted mean or a variance is not finite, ``NOT_PSD``
            when a variance is negative or ``Q`` has a negative variance (a traced negative
            ``Q``; a concrete one is an :class:`InputError`).  The moments are returned as
            computed; a run skips such a prediction (the step keeps the belief it started from
            and makes no update: :mod:`jaxslam.filters.gaussian`).

    Returns:
        Predicted :class:`Gaussian` in the dtype of ``state.mean`` (and the status).  Called
        eagerly it is compiled once per model (:func:`jaxslam.compilation.call_compiled`): a
        loop of eager steps runs compiled programs.
    """
    return_status = check_flag(return_status, "return_status")
    state, Q = _g.check_predict_call(state, Q)  # the values known now (the compiled step sees them traced)

    def step(opts, state, Q):
        u, a, nj = opts
        g = _predict(state, f, u, Q, *a, noise_jac=nj)
        if not return_status:
            return g
        i32 = jnp.int32
        bad_mean = jnp.where(jnp.all(jnp.isfinite(g.mean)), i32(0), i32(errors.NON_FINITE))
        q_neg = jnp.where(_g.negative_variance(Q), i32(errors.NOT_PSD), i32(0))
        return g, _g.predicted_status(g.cov) | bad_mean | q_neg

    return call_compiled(("ekf.predict", f, return_status), step, (state, Q), (u, args, noise_jac), after=2)


def _predict(state: Gaussian, f: Callable, u, Q, *args, noise_jac=None) -> Gaussian:
    """:func:`predict`'s computation (its checks of shapes; values are checked by the caller)."""
    x, P = check_state(state)
    dtype = x.dtype
    xn, F = value_and_jacfwd(lambda v: jnp.asarray(f(v, u, *args)))(x)
    check_transition_out(xn, x.shape[0])
    xn = xn.astype(dtype)
    F = F.astype(dtype)
    Q = process_noise(Q, x, u, args, noise_jac)
    return Gaussian(xn, symmetrize(F @ P @ F.T + Q))


def predict_additive(state: Gaussian, f: Callable, u, Q, L, *args) -> Gaussian:
    """Time update with a noise Jacobian: ``P' = F P Fᵀ + L Q Lᵀ``.

    Same as ``predict(state, f, u, Q, *args, noise_jac=L)``; ``L`` is an
    (n, q) matrix or a callable ``L(x, u, *args)``; ``Q`` is (q, q), e.g. the
    covariance of the IMU noise entering through ``L``.
    """
    return predict(state, f, u, Q, *args, noise_jac=L)


# ---------------------------------------------------------------------------
# Update
# ---------------------------------------------------------------------------

def update(
    state: Gaussian,
    z,
    h: Callable,
    R,
    *args,
    residual: Optional[Callable] = None,
    mask=None,
    gate: Gate = None,
    num_iter: int = 1,
    tol=None,
):
    """EKF measurement update with masks, a chi-square gate and optional iterations.

    Paper 003 eq. 6-9 and paper 000 eq. 37-42; the covariance uses the
    factored Joseph form instead of paper 000 eq. 43 / paper 003 eq. 10.

    ``ẑ = h(x, *args)``, ``H = ∂h/∂x`` (``jax.jacfwd``), ``ν = residual(z, ẑ)``,
    ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹`` (Cholesky), ``x⁺ = x + K ν``,
    ``P⁺ = (I − K H) P (I − K H)ᵀ + K R Kᵀ`` (symmetrised).

    **Iterated EKF** (``num_iter > 1``): Gauss–Newton on the measurement.  From
    ``x₀ = x``, iterate ``x_{i+1} = x + K_i (residual(z, h(x_i)) − H_i (x − x_i))``
    with ``H_i = ∂h/∂x (x_i)`` and ``K_i`` the gain for ``H_i``; this minimises
    ``‖z − h(x')‖²_{R⁻¹} + ‖x' − x‖²_{P⁻¹}`` (the MAP of one update).  The
    covariance uses the last linearisation.  ``num_iter`` is static (the
    number of linearisations, 1 = the plain EKF, as dynamax's ``num_iter``).
    The NIS, ``S`` and the gate use the linearisation at the prior (so gating
    is the same with or without iterations).  ``errors.NOT_CONVERGED`` is set
    when the last step still moved a component by more than ``tol`` prior
    standard deviations (default 1e-6 in float64, 1e-3 in float32).

    Args:
        state: prior :class:`Gaussian`, mean (n,), cov (n, n).
        z: (m,) measurement, in the units of ``h``'s output.
        h: measurement model ``h(x (n,), *args) -> (m,)``.
        R: (m, m) measurement-noise covariance, positive definite (or, for m = 1, a
            scalar variance > 0); a concrete one is checked (:class:`InputError` naming
            ``R``).
        *args: extra arguments of ``h`` (e.g. a landmark position).
        residual: ``residual(z, ẑ) -> (m,)``; default ``z − ẑ``.  Use
            :func:`angle_residual` for components in radians.
        mask: (m,) bool, True for valid components (default: all valid).
            Invalid components contribute nothing, whatever ``z`` holds there.
        gate: None (no gate), a chi-square threshold on the NIS, or a callable
            ``gate(dof) -> threshold``.  When the NIS exceeds it the state is
            returned unchanged and ``errors.GATED`` is set.  A concrete gate must be a positive
            number (:class:`InputError`); a traced one that is not > 0 (NaN included) gates the
            update and also sets ``errors.NON_FINITE``.
        num_iter: static int ≥ 1, linearisations (iterated EKF when > 1).
        tol: convergence tolerance of the iterations, in prior σ (traced; a finite number > 0 when
            known now: InputError otherwise; a traced NaN sets NOT_CONVERGED).

    Returns:
        ``(posterior Gaussian, UpdateInfo)``.  On a failed Cholesky or a negative
        posterior variance (``NOT_PSD``: e.g. an indefinite prior under ``jit``, where it is
        not checked) or a non-finite posterior (``NON_FINITE``) the prior is returned
        unchanged.  Called eagerly it is compiled once per model
        (:func:`jaxslam.compilation.call_compiled`).
    """
    check_num_iter(num_iter)
    state, z, R, mask = _g.check_update_call(state, z, R, mask, gate)  # the values known now
    if tol is not None and is_concrete(tol):  # NaN or inf never flagged NOT_CONVERGED, -1 always
        check_scalar(tol, "tol", lower=0, strict=True)

    def step(opts, state, z, R, mask):
        a, g, t = opts
        return _update(state, z, h, R, *a, residual=residual, mask=mask, gate=g, num_iter=num_iter, tol=t)

    return call_compiled(("ekf.update", h, residual, num_iter), step, (state, z, R, mask), (args, gate, tol),
                         after=2)


def _update(state: Gaussian, z, h: Callable, R, *args, residual=None, mask=None, gate: Gate = None,
            num_iter: int = 1, tol=None):
    """:func:`update`'s computation (shape checks; values are checked by the caller)."""
    state = check_state(state)
    x, P = state
    dtype = x.dtype
    check_update_args(z, R, mask)
    z, h = scalar_measurement(z, h)
    z = jnp.asarray(z, dtype=dtype)
    R = jnp.asarray(R, dtype=dtype)
    m = z.shape[-1]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    res = _default_residual if residual is None else residual

    def linearise(v):
        zhat, H = value_and_jacfwd(lambda w: jnp.asarray(h(w, *args)))(v)
        return zhat.astype(dtype), H.astype(dtype)

    zhat, H = linearise(x)
    check_measurement(z, zhat, R, mask)
    check_gate_size(gate, m, mask)
    nu = masked_innovation(z, zhat, mask, res)
    dof = jnp.sum(mask).astype(jnp.int32)
    # The NIS (hence the gate) does not depend on whether the update is
    # finally applied, so one correction serves both.
    x_post, P_post, S, num, nis, ok, logdet = linear_update(x, P, nu, H, R, mask)
    # a NaN/Inf in the S factored (from P, H or R's valid block) is NON_FINITE, not NOT_PSD
    finite_in = jnp.all(jnp.isfinite(S))
    extra = None
    if int(num_iter) > 1:
        def gn(carry, _):
            xi, _, ok_so_far, _, fin = carry
            zi, Hi = linearise(xi)
            nui = masked_innovation(z, zi, mask, res) - jnp.where(
                mask, Hi @ (x - xi), jnp.zeros((), dtype))
            xn, Pn, Si, _, _, oki, _ = linear_update(x, P, nui, Hi, R, mask)
            # one failed linearisation fails the update
            return (xn, Pn, ok_so_far & oki, xi, fin & jnp.all(jnp.isfinite(Si))), None

        (x_post, P_post, ok_it, x_prev, finite_in), _ = jax.lax.scan(
            gn, (x_post, P_post, ok, x, finite_in), None, length=int(num_iter) - 1)
        ok = ok & ok_it
        tol_v = jnp.asarray((1e-6 if dtype == jnp.float64 else 1e-3) if tol is None else tol, dtype)
        sig = jnp.sqrt(jnp.maximum(jnp.diagonal(P), jnp.finfo(dtype).tiny))
        moved = jnp.max(jnp.abs(x_post - x_prev) / sig)
        # not (moved <= tol): a traced NaN tolerance (or a NaN step) counts as not converged
        extra = jnp.where(moved <= tol_v, jnp.int32(0), jnp.int32(errors.NOT_CONVERGED))
    if gate is None:
        gated = jnp.asarray(False)
    else:  # a traced threshold that is not > 0 (NaN) gates the update and flags NON_FINITE
        gated, g_status = _g.gate_test(gate, nis, dof, dtype)
        extra = g_status if extra is None else extra | g_status
    post, accepted, status = _finalize(state, x_post, P_post, ok, gated, dof, extra, finite_in=finite_in)
    # a failed factorisation reports NIS 0 (not NaN); its step's log-likelihood is NaN, with
    # the status saying why (gaussian.step_log_likelihood)
    nis = jnp.where(ok, nis, jnp.zeros((), dtype))
    return post, UpdateInfo(nis, dof, num, S, accepted, status,
                            jnp.where(ok & (dof > 0), logdet, jnp.zeros((), dtype)))


def update_batch(
    state: Gaussian,
    zs,
    h: Callable,
    R,
    *args,
    masks=None,
    residual: Optional[Callable] = None,
    gate: Gate = None,
    sequential: bool = False,
):
    """Update with M independent measurements of one model, fixed shapes.

    The M measurements (e.g. ranges to M landmarks, some absent) are stacked
    into one joint update (paper 000 eq. 34-43 stack landmarks the same way):
    ``H = [H_1; ...; H_M]``, ``R = blockdiag(R_1, ..., R_M)``.  Masked
    measurements contribute nothing.  Each measurement is gated on its
    marginal NIS ``ν_iᵀ S_ii⁻¹ ν_i`` against the prior; gated ones are removed
    from the joint update.  With ``sequential=True`` the measurements are
    applied one after another in a ``lax.scan`` (each gated against the state
    left by the previous ones); cost O(M) small solves instead of one
    (M m)-sized solve.

    Args:
        state: prior :class:`Gaussian`, mean (n,), cov (n, n).
        zs: (M, m) measurements.
        h: ``h(x (n,), *a) -> (m,)`` where ``a`` are the per-measurement
            slices of ``args``.  Shared constants are closed over in ``h``.
        R: (m, m) shared or (M, m, m) per-measurement noise covariance.
        *args: per-measurement arguments of ``h``, each with leading axis M
            (e.g. (M, 2) landmark positions).
        masks: None (all valid), (M,) bool per measurement or (M, m) bool per
            component.
        residual: as in :func:`update`.
        gate: as in :func:`update`, applied per measurement.
        sequential: static bool; joint (default) or sequential processing.

    Returns:
        ``(posterior Gaussian, UpdateInfo)`` with per-measurement fields:
        nis (M,), dof (M,), innovation (M, m), S (M, m, m) (the diagonal
        blocks ``S_ii``), accepted (M,), status (M,).  In joint mode a
        numerical failure of the joint update (``NOT_PSD``/``NON_FINITE``) is
        reported on every valid measurement and the prior is kept.  Called eagerly it is
        compiled once per model (:func:`jaxslam.compilation.call_compiled`, at the model's
        second call as :func:`update`).
    """
    state, zs, R, masks, sequential = _check_batch(state, zs, R, args, masks, gate, sequential)

    def step(opts, state, zs, R, masks, args):
        return _update_batch(state, zs, h, R, *args, masks=masks, residual=residual, gate=opts[0],
                             sequential=sequential)

    return call_compiled(("ekf.update_batch", h, residual, sequential), step, (state, zs, R, masks, args), (gate,),
                         after=2)


def _check_batch(state, zs, R, args, masks, gate, sequential):
    """:func:`update_batch`'s checks (shapes, and the values known now): ``(state, zs, R,
    masks (M, m) bool, sequential)`` in the state's dtype."""
    check_gate(gate)
    sequential = check_flag(sequential, "sequential")
    state = check_state(state)
    x = state.mean
    dtype = x.dtype
    check_real(zs, "zs")
    zs = jnp.asarray(zs, dtype=dtype)
    if zs.ndim != 2:
        raise InputError(f"zs: expected shape (M, m) (M measurements of size m), got {zs.shape}")
    M, m = zs.shape
    rs = tuple(np.shape(R))
    if rs not in ((m, m), (M, m, m)):
        raise InputError(f"R: expected shape ({m}, {m}) (shared) or ({M}, {m}, {m}) (per measurement), got {rs}")
    if is_concrete(R):
        check_psd(R, "R", strict=True, stack=len(rs) == 3)
    R = jnp.asarray(R, dtype=dtype)
    if masks is None:
        masks = jnp.ones((M, m), bool)
    else:
        check_mask(masks, "masks")
        masks = jnp.asarray(masks, bool)
        if masks.shape not in ((M,), (M, m)):
            raise InputError(f"masks: expected shape ({M},) or ({M}, {m}), got {masks.shape}")
        if masks.ndim == 1:
            masks = jnp.broadcast_to(masks[:, None], (M, m))
    check_gate_size(gate, m, masks)
    for i, a in enumerate(args):
        for leaf in jax.tree_util.tree_leaves(a):
            if np.ndim(leaf) < 1 or np.shape(leaf)[0] != M:
                raise InputError(f"args[{i}]: every per-measurement argument needs a leading axis of "
                                 f"size M = {M} (zs' rows), got shape {np.shape(leaf)}")
    return state, zs, R, masks, sequential


def _update_batch(state: Gaussian, zs, h: Callable, R, *args, masks=None, residual=None, gate: Gate = None,
                  sequential: bool = False):
    """:func:`update_batch`'s computation."""
    state, zs, R, masks, sequential = _check_batch(state, zs, R, args, masks, gate, sequential)
    x, P = state
    dtype = x.dtype
    M, m = zs.shape
    n = x.shape[0]
    Rs = jnp.broadcast_to(R, (M, m, m))
    res = _default_residual if residual is None else residual

    if sequential:
        def body(carry, inp):
            z_i, R_i, mask_i, a_i = inp
            post, info = _update(
                carry, z_i, h, R_i, *a_i, residual=res, mask=mask_i, gate=gate
            )
            return post, info

        return jax.lax.scan(body, state, (zs, Rs, masks, tuple(args)))

    def lin(a):
        return value_and_jacfwd(lambda v: jnp.asarray(h(v, *a)))(x)

    # (M, m), (M, m, n); axis_size: with nothing per measurement one linearisation is broadcast
    zhat, H = jax.vmap(lin, axis_size=M)(tuple(args))
    if tuple(zhat.shape[1:]) != (m,):
        raise InputError(f"h: the measurement model returned shape {tuple(zhat.shape[1:])}, but each row of "
                         f"zs has ({m},)")
    zhat = zhat.astype(dtype)
    H = H.astype(dtype)
    zhat_safe = jnp.where(masks, zhat, jnp.zeros((), dtype))
    z_safe = jnp.where(masks, zs, zhat_safe)
    nu = jax.vmap(lambda a, b: call_residual(res, a, b))(z_safe, zhat_safe)
    zero = jnp.zeros((), dtype)
    nu = jnp.where(masks, nu, zero)
    Hm = jnp.where(masks[:, :, None], H, zero)
    dof = jnp.sum(masks, axis=1).astype(jnp.int32)  # (M,)

    # Marginal innovation blocks for per-measurement NIS and gating.
    mm = masks[:, :, None] & masks[:, None, :]
    eye_m = jnp.eye(m, dtype=dtype)
    HP = jnp.einsum("kij,jl->kil", Hm, P)  # (M, m, n)
    S_ii = symmetrize(
        jnp.einsum("kil,kjl->kij", HP, Hm) + jnp.where(mm, Rs, eye_m)
    )
    w, ok_i, logdet_i = jax.vmap(innovation_solve)(S_ii, nu)
    nis = jnp.sum(nu * w, axis=1)
    valid = dof > 0
    g_status = jnp.zeros((M,), jnp.int32)
    if gate is None:
        gated = jnp.zeros((M,), bool)
    else:  # a traced threshold that is not > 0 (NaN) gates the measurement and flags NON_FINITE
        gated, g_status = jax.vmap(lambda d, v: _g.gate_test(gate, v, d, dtype))(dof, nis)

    keep = masks & ~gated[:, None]
    R_blk = jnp.einsum("ab,aij->aibj", jnp.eye(M, dtype=dtype), Rs).reshape(M * m, M * m)
    x_post, P_post, S_joint, _, _, ok, _ = linear_update(
        x, P, nu.reshape(M * m), Hm.reshape(M * m, n), R_blk,
        keep.reshape(M * m)
    )
    dof_total = jnp.sum(keep).astype(jnp.int32)
    post, any_acc, status_joint = _finalize(
        state, x_post, P_post, ok, jnp.asarray(False), dof_total,
        finite_in=jnp.all(jnp.isfinite(S_joint))
    )
    used = valid & ~gated
    accepted = used & any_acc
    status = jnp.where(gated, jnp.int32(errors.GATED), jnp.int32(0)) | jnp.where(
        used, status_joint, jnp.int32(0)
    ) | g_status
    # A failed marginal factorisation is a symptom of the same problem (NON_FINITE when its
    # S_ii held a NaN/Inf: gaussian.failure_status).
    fin_i = jnp.all(jnp.isfinite(S_ii), axis=(1, 2))
    status = status | jnp.where(valid & ~ok_i, jnp.where(fin_i, jnp.int32(errors.NOT_PSD),
                                                         jnp.int32(errors.NON_FINITE)), jnp.int32(0))
    logdet_i = jnp.where(valid & ok_i, logdet_i, jnp.zeros((), dtype))
    return post, UpdateInfo(nis, dof, nu, S_ii, accepted, status, logdet_i)


# ---------------------------------------------------------------------------
# Whole run
# ---------------------------------------------------------------------------

def make_filter(
    f: Optional[Callable],
    h: Callable,
    *args,
    residual: Optional[Callable] = None,
    gate: Gate = None,
    noise_jac=None,
    num_iter: int = 1,
    h_takes_input: bool = False,
) -> GaussianFilter:
    """The EKF as a :class:`jaxslam.filters.gaussian.GaussianFilter` for :func:`gaussian.run`.

    Args:
        f: transition ``f(x, u, *args) -> (n,)``, or None for a model whose
            state does not move (identity, ``P' = P + Q``).
        h: measurement model ``h(x, *args)``, or ``h(x, c, *args)`` with the
            step's input ``c`` when ``h_takes_input``.
        *args: shared extra arguments of both ``f`` and ``h``.
        residual, gate, num_iter: as in :func:`update`.  noise_jac: as in :func:`predict`.
        h_takes_input: static; ``h`` receives the per-step ``h_inputs`` of the run.

    Returns:
        ``GaussianFilter(predict, update)``; ``predict`` returns the cross-covariance
        ``P Fᵀ`` beside the predicted belief (what the RTS smoother needs).
    """
    check_num_iter(num_iter)
    check_gate(gate)
    h_takes_input = check_flag(h_takes_input, "h_takes_input")
    fm = (lambda x, u, *a: x) if f is None else f

    def pred(state, u, Q):
        x, P = state
        dtype = x.dtype
        xn, F = value_and_jacfwd(lambda v: jnp.asarray(fm(v, u, *args)))(x)
        check_transition_out(xn, x.shape[0])
        F = F.astype(dtype)
        Qd = process_noise(Q, x, u, args, noise_jac)
        PFt = P @ F.T
        xn = xn.astype(dtype)
        Pn = symmetrize(F @ PFt + Qd)
        # the prediction's status (the protocol's third output): NON_FINITE for a NaN/Inf, NOT_PSD
        # for a negative predicted variance or a negative variance in Q; the run's step then
        # keeps its belief (gaussian.make_step), as with every Gaussian filter
        finite = jnp.all(jnp.isfinite(xn)) & jnp.all(jnp.isfinite(Pn)) & jnp.all(jnp.isfinite(PFt))
        neg = (_g.predicted_status(Pn) == errors.NOT_PSD) | _g.negative_variance(Q)
        i32 = jnp.int32
        status = jnp.where(finite, jnp.where(neg, i32(errors.NOT_PSD), i32(0)), i32(errors.NON_FINITE))
        return Gaussian(xn, Pn), PFt, status

    def upd(state, z, mask, R, c):
        hh = (lambda x, *a: h(x, c, *a)) if h_takes_input else h
        return _update(state, z, hh, R, *args, residual=residual, mask=mask, gate=gate,
                       num_iter=num_iter)

    # a run of it compiles once per model, however often the filter is made again
    return _g.keyed_filter(
        GaussianFilter(pred, upd),
        lambda a, g, nj: make_filter(f, h, *a, residual=residual, gate=g, noise_jac=nj, num_iter=num_iter,
                                     h_takes_input=h_takes_input),
        (args, gate, noise_jac), ("ekf.make_filter", f, h, residual, num_iter, h_takes_input))


def filter_scan(
    f: Optional[Callable],
    h: Callable,
    x0,
    P0,
    us,
    zs,
    masks,
    Q,
    R,
    *args,
    residual: Optional[Callable] = None,
    gate: Gate = None,
    save_cov: bool = False,
    predict_first: bool = True,
    noise_jac=None,
    num_iter: int = 1,
    h_inputs=None,
    save_smoother: bool = False,
) -> Posterior:
    """Run predict + update over a whole sequence as one ``lax.scan``.

    Step t (``predict_first=True``): predict with ``u_t`` (:func:`predict`),
    then update with ``z_t`` under ``masks[t]`` (:func:`update`).  Jit it with
    ``f``, ``h``, ``residual``, a callable ``gate``, ``save_cov``,
    ``predict_first``, ``num_iter`` and ``save_smoother`` static; vmap it over runs.
    Called eagerly it is compiled once per model (:func:`jaxslam.compilation.call_compiled`):
    a second call with new numbers neither traces nor compiles.
    The same run as ``gaussian.run(make_filter(f, h, ...), ...)``.

    Args:
        f: transition ``f(x, u, *args) -> (n,)`` (None: the state does not move).
        h: measurement model ``h(x, *args) -> (m,)``, or ``h(x, c_t, *args)``
            when ``h_inputs`` is given.
        x0: (n,) initial mean.  P0: (n, n) initial covariance.
        us: controls with leading axis T (array or pytree; None if unused).
        zs: (T, m) measurements.
        masks: (T, m) bool validity (None: all valid).
        Q: (n, n) (or (q, q) with ``noise_jac``) process noise, or one per step
            (T, n, n); a scalar for a single noise input (n = 1, or q = 1), as in
            :func:`predict`.  R: (m, m) or (T, m, m) (a scalar for m = 1).  ``x0``, ``P0``,
            ``zs``, ``Q``, ``R`` must not be booleans (:class:`InputError` naming it).
        *args: shared extra arguments of both ``f`` and ``h``.
        residual, gate, num_iter: as in :func:`update`.
        save_cov: static; also stack full covariances (T, n, n).  Off by
            default to spare memory: the diagonals are always saved.
        predict_first: static; step order, see the module docstring.
        noise_jac: as in :func:`predict`.
        h_inputs: per-step inputs of the measurement model (leading axis T).
        save_smoother: static; save what :func:`jaxslam.filters.smoother.rts` needs.

    Returns:
        :class:`Posterior` in the dtype of ``x0`` (``log_likelihood`` per step included).  A
        failed prediction (a NaN/Inf: ``NON_FINITE``; a negative predicted variance or a traced
        ``Q`` with a negative variance: ``NOT_PSD``) is skipped, as in every Gaussian run: the
        step it fed keeps the belief the predict started from, makes no update (NIS 0) and
        carries the bits and a NaN log-likelihood; later steps go on from that belief (the
        NaN used to be carried to the end of the run).
    """
    flt = make_filter(f, h, *args, residual=residual, gate=gate, noise_jac=noise_jac,
                      num_iter=num_iter, h_takes_input=h_inputs is not None)
    return _g._run(flt, x0, P0, us, zs, masks, Q, R, h_inputs, predict_first, save_cov, save_smoother,
                   noise=_g.noise_size(x0, noise_jac))


# ---------------------------------------------------------------------------
# Host-side validation (before jit)
# ---------------------------------------------------------------------------

def validate_gaussian(mean, cov, name: str = "state") -> Gaussian:
    """Check a Gaussian on the host; raise :class:`InputError` naming ``name``.

    Args:
        mean: (n,) finite mean.
        cov: (n, n) finite symmetric PSD covariance.
        name: argument name used in error messages (``name.mean``,
            ``name.cov``).

    Returns:
        ``Gaussian(mean, cov)`` as jnp arrays (dtype preserved).
    """
    mu = np.asarray(mean)
    if mu.ndim != 1:
        raise InputError(f"{name}.mean: expected shape (n,), got {mu.shape}")
    if not np.issubdtype(mu.dtype, np.number) or not np.all(np.isfinite(mu)):
        raise InputError(f"{name}.mean: contains NaN or Inf or is not numeric")
    C = np.asarray(cov)
    n = mu.shape[0]
    if C.shape != (n, n):
        raise InputError(f"{name}.cov: expected shape ({n}, {n}), got {C.shape}")
    check_psd(C, f"{name}.cov")
    return Gaussian(jnp.asarray(mean), jnp.asarray(cov))


def validate_noise_cov(M, dim: int, name: str, strict: bool = False):
    """Check a (dim, dim) noise covariance (PSD, or PD if ``strict``) on the host.

    Use ``strict=True`` for a measurement covariance R (S must stay PD even
    when P is singular).  Raises :class:`InputError` naming ``name``.
    """
    A = np.asarray(M)
    if A.shape != (dim, dim):
        raise InputError(f"{name}: expected shape ({dim}, {dim}), got {A.shape}")
    check_psd(A, name, strict=strict)
    return M
