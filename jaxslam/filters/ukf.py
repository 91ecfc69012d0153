"""Sigma-point Gaussian filter (unscented; cubature as an option) with the EKF's signatures,
masks and gate.

Generic: the model enters through ``f(x, u, *args)`` and ``h(x, *args)`` exactly as in
:mod:`jaxslam.filters.ekf`, the correction is the shared masked one of
:mod:`jaxslam.filters.gaussian`, and a run is the same :func:`jaxslam.filters.gaussian.run`.
So a sigma-point filter is usable wherever the EKF is: single steps, whole-run scans, ``vmap``
over Monte Carlo runs, ``jax.grad`` of the log-likelihood, and the RTS / fixed-lag smoothers of
:mod:`jaxslam.filters.smoother` (with ``save_smoother`` the saved cross-covariances are the
sigma-point ones, so ``smoother.rts`` is then the unscented RTS smoother).

Equations
---------
**Sigma points** of ``N(x̄, P)``, ``x̄`` (n,), from the lower Cholesky factor ``P = L Lᵀ``
(:class:`SigmaPoints`, :func:`sigma_points`)::

    χ_i     = x̄ + c L e_i,   χ_{n+i} = x̄ − c L e_i      (i = 1..n)
    χ_0     = x̄                                          (unscented rule only)

*Unscented* (:func:`unscented`; the scaled unscented transform in the α, β, κ
parametrisation, the one of filterpy's ``MerweScaledSigmaPoints``), 2n + 1 points::

    λ = α² (n + κ) − n,  c = √(n + λ)
    W^m_0 = λ / (n + λ),  W^c_0 = W^m_0 + 1 − α² + β,  W^m_i = W^c_i = 1 / (2 (n + λ))

*Cubature* (:func:`cubature`; third-degree spherical-radial rule), 2n points, ``c = √n``,
``W^m_i = W^c_i = 1 / (2n)``.

**Predict** (:func:`predict`, :func:`predict_with_cross`), ``X_i = f(χ_i, u, *args)``::

    x̄' = Σ W^m_i X_i
    P'  = Σ W^c_i (X_i − x̄')(X_i − x̄')ᵀ + Q           (or + L Q Lᵀ with ``noise_jac``)
    C   = Σ W^c_i (χ_i − x̄)(X_i − x̄')ᵀ  = Cov(x, x')   (n, n), what the RTS smoother needs

**Update** (:func:`update`), ``Z_i = h(χ_i, *args)``, ``r = residual``::

    ẑ    = Z_ref + Σ W^m_i r(Z_i, Z_ref)          (Z_ref = h(x̄); = Σ W^m_i Z_i for r = z − ẑ)
    ΔZ_i = r(Z_i, ẑ),   ν = r(z, ẑ)
    S    = Σ W^c_i ΔZ_i ΔZ_iᵀ + R                 (m, m)
    C_xz = Σ W^c_i (χ_i − x̄) ΔZ_iᵀ               (n, m)
    K    = C_xz S⁻¹   (one Cholesky solve with [C_xzᵀ | ν]: gain and NIS share the factor)
    x⁺   = x̄ + K ν,   P⁺ = P − K S Kᵀ (symmetrised)

Decisions
---------
* **Default rule**: unscented with ``α = 1, β = 2, κ = 0``.  Then ``λ = 0``: ``W^m_0 = 0``,
  ``W^c_0 = 2``, the other 2n points sit at ±√n standard deviations with weight 1/(2n), and
  *every* covariance weight is ≥ 0, so ``P'`` and ``S`` are sums of PSD terms plus the noise.
  The weight formulas are the α, β, κ ones above (``W^c_0 = W^m_0 + 1 − α² + β``), but the
  default α departs from the small value (α = 1e-3, κ = 0) usually recommended with them:
  that gives ``λ ≈ −n``, ``W_0 ≈ −10⁶/n`` and points at ±1e-3·√n σ, so the covariance is a
  difference of terms of size 10⁶ P — cancellation costs six digits (all of float32's) and
  ``P'`` easily loses definiteness.  filterpy has no default (``MerweScaledSigmaPoints``
  requires α, β, κ; its documentation suggests α = 1e-3, β = 2, κ = 0 or 3 − n); its
  ``JulierSigmaPoints`` default (κ = 0) has our points and mean weights but ``W^c_0 = 0``.
  Every value is an argument of :func:`unscented`.
* **Spread from a Cholesky factor** of ``P`` (lower, ``jnp.linalg.cholesky``; the columns of
  ``L`` give the points).  If the factor is not finite (``P`` not PD, or not finite), the step
  keeps the prior, sets ``errors.NOT_PSD`` and produces no NaN: the points are then built from
  an identity factor and every result computed from them is discarded.  Consequently the
  sigma-point filter needs a positive-*definite* covariance where the EKF accepts a
  semi-definite one.
* **Residuals**: the user's ``residual(z, ẑ)`` forms the innovation *and* the spread
  ``ΔZ_i = residual(Z_i, ẑ)``; the predicted measurement is anchored at ``h(x̄)``, so with
  :func:`jaxslam.filters.ekf.angle_residual` a bearing near ±π has a correct ``ẑ``, spread
  and innovation (a plain weighted mean of values either side of ±π would not).  State means
  in the predict are plain weighted means (the EKF's ``f`` has no state difference either).
* **Noise is additive**, not augmented into the sigma points: ``Q`` (and ``R``) are added to
  the sigma-point covariances.  With ``noise_jac`` ``L`` (n, q), ``L Q Lᵀ`` is added, ``L``
  evaluated at the prior mean (a callable ``L(x̄, u, *args)``).  Noise entering ``f``
  nonlinearly is therefore linearised at the mean.
* ``f = None`` is the identity: ``x̄' = x̄``, ``P' = P + Q``, ``C = P`` exactly (no points).
* **Masks and gate exactly as the EKF** (:mod:`jaxslam.filters.gaussian`): invalid components
  get a zero ``ΔZ`` column (so zero rows/columns of ``S`` and zero columns of ``C_xz``), a
  unit diagonal in ``S`` and a zero innovation, so their gain columns are exactly zero and a
  fully masked update returns the prior unchanged; NaN/Inf in an invalid component of ``z``
  never reaches the arithmetic nor its gradient (in ``h``'s output it is replaced before the
  arithmetic too, but a NaN there would still poison ``jax.grad`` through ``h``).  The gate compares the NIS over the
  valid components with a number or ``gate(dof)`` (e.g. ``ekf.chi2_gate``); a gated update
  keeps the prior and sets ``errors.GATED``.
* Covariance update ``P − K S Kᵀ`` (not the Joseph form: there is no ``H``).  It can lose
  definiteness by rounding after a very informative update; the next step's factorisation
  then flags ``NOT_PSD`` rather than proceeding with NaN.
* **Failures of a predict**: a failed factor of ``P`` (``NOT_PSD``; ``NON_FINITE`` when ``P``
  holds a NaN/Inf: :func:`jaxslam.filters.gaussian.failure_status`), a negative variance in
  ``Q`` or in the prediction (``NOT_PSD``) or a non-finite predicted moment (``NON_FINITE``)
  keeps the prior moments (cross-covariance ``P``).  The
  filter's predict returns that status (the ``GaussianFilter`` protocol's optional third
  output), so inside a run the step carries the flag and a NaN log-likelihood (a summed NLL
  cannot hide it); :func:`predict` and :func:`predict_with_cross` return the status with
  ``return_status``.  A run makes no update in that step (the rule of every Gaussian run,
  :mod:`jaxslam.filters.gaussian`): it keeps the belief the predict started from.
* dtype: every function computes in the dtype of ``state.mean``; weights, ``Q``, ``R``, ``z``
  and the model outputs are cast to it.
* Cost per step: 2n + 1 (or 2n) evaluations of ``f`` and ``h`` (``vmap``-ed), one n×n and one
  m×m Cholesky; no Jacobians, so ``f`` and ``h`` need not be differentiable except under
  ``jax.grad`` of the run.
* The rule is static: build it once (``unscented(...)``, ``cubature()``) and close over it or
  pass it as a static argument; it is a ``NamedTuple`` of Python numbers and a string.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError, check_flag
from ..linalg import check_numbers, check_psd, is_concrete, symmetrize
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
    check_state,
    check_update_args,
    scalar_measurement,
    finalize,
    innovation_solve,
    masked_innovation,
    moment_dtype,
    process_noise,
)

__all__ = [
    "SigmaPoints",
    "SigmaSet",
    "unscented",
    "cubature",
    "sigma_points",
    "predict",
    "predict_with_cross",
    "update",
    "make_filter",
    "filter_scan",
]

Array = Any


class SigmaSet(NamedTuple):
    """Sigma points of one Gaussian and their weights.

    Fields:
        points: (N, n) sigma points, N = 2n + 1 (unscented, ``points[0]`` the mean) or 2n
            (cubature); rows ``1..n`` (resp. ``0..n−1``) are ``x̄ + c L e_i``, the next n
            ``x̄ − c L e_i``.
        wm: (N,) mean weights (sum 1).
        wc: (N,) covariance weights.
        ok: () bool, False when the Cholesky factor of the covariance is not finite; the
            points are then built from an identity factor and must not be used.
    """

    points: Array
    wm: Array
    wc: Array
    ok: Array


class SigmaPoints(NamedTuple):
    """A sigma-point rule: a static description, callable on a Gaussian.

    Build it with :func:`unscented` or :func:`cubature`.  ``rule(mean, cov)`` returns a
    :class:`SigmaSet` (points (N, n), weights ``wm``, ``wc`` (N,), factorisation flag) in the
    dtype of ``mean``.

    Fields:
        kind: "unscented" (2n + 1 points) or "cubature" (2n points).
        alpha, beta, kappa: the scaled unscented parameters (ignored by "cubature").
    """

    kind: str = "unscented"
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    @property
    def has_center(self) -> bool:
        """True when the rule includes the mean as a point (unscented)."""
        return self.kind == "unscented"

    def num_points(self, n: int) -> int:
        """N, the number of points for an n-dimensional Gaussian."""
        return 2 * n + 1 if self.has_center else 2 * n

    def weights(self, n: int):
        """Host-side float64 ``(wm (N,), wc (N,), c)`` with ``c`` the spread in σ units.

        Raises :class:`InputError` for an unknown rule, for n < 1 (no points), for a
        non-finite (or bool) α, β or κ (a rule built as ``SigmaPoints(...)`` directly skips the checks of
        :func:`unscented`) or for ``n + λ ≤ 0``.
        """
        if self.kind in ("cubature", "unscented") and not n >= 1:
            raise InputError(f"points: a sigma-point rule needs a state of at least one component, "
                             f"got n = {n}")
        if self.kind == "cubature":
            w = np.full((2 * n,), 1.0 / (2 * n))
            return w, w.copy(), float(np.sqrt(n))
        if self.kind != "unscented":
            raise InputError(f"points: unknown sigma-point rule {self.kind!r} "
                             "(unscented or cubature)")
        for v, nm in ((self.alpha, "alpha"), (self.beta, "beta"), (self.kappa, "kappa")):
            # (SigmaPoints("unscented", True) read as alpha = 1; a NaN beta gave NaN weights)
            if isinstance(v, (bool, np.bool_)) or not np.isfinite(float(v)):
                raise InputError(f"points: {nm} must be a finite number, got {v!r}")
        a, b, k = float(self.alpha), float(self.beta), float(self.kappa)
        lam = a * a * (n + k) - n
        if not n + lam > 0:
            raise InputError(f"points: n + λ = α²(n + κ) = {n + lam:g} must be > 0 for n = {n} "
                             "(raise alpha or kappa)")
        wm = np.full((2 * n + 1,), 1.0 / (2.0 * (n + lam)))
        wm[0] = lam / (n + lam)
        wc = wm.copy()
        wc[0] += 1.0 - a * a + b
        return wm, wc, float(np.sqrt(n + lam))

    def __call__(self, mean, cov) -> SigmaSet:
        return sigma_points(mean, cov, self)


def unscented(alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaPoints:
    """The scaled unscented rule, 2n + 1 points (weights in the module docstring).

    Args:
        alpha: spread, > 0; the points sit at ±α√(n + κ) σ.  Default 1 (module docstring:
            α = 1e-3 with κ = 0 makes ``W_0 ≈ −10⁶/n`` and is numerically fragile).
        beta: prior knowledge of the distribution; 2 is optimal for a Gaussian.  Enters only
            ``W^c_0``.
        kappa: secondary scaling; ``α²(n + κ)`` must be > 0 (checked when n is known).

    Returns:
        :class:`SigmaPoints` (static; hashable).
    """
    for v, nm in ((alpha, "alpha"), (beta, "beta"), (kappa, "kappa")):
        if isinstance(v, (bool, np.bool_)):  # True was read as 1.0
            raise InputError(f"{nm}: must be a finite number, got {v!r}")
        a = check_numbers(v, nm)  # a string (even "1") or None is not a number
        if a.shape != () or not np.isfinite(a):
            raise InputError(f"{nm}: must be a finite number, got {v!r}")
    if not float(alpha) > 0:
        raise InputError(f"alpha: must be > 0, got {alpha}")
    return SigmaPoints("unscented", float(alpha), float(beta), float(kappa))


def cubature() -> SigmaPoints:
    """The third-degree spherical-radial cubature rule: 2n points at ±√n σ, weights 1/(2n)."""
    return SigmaPoints("cubature", 1.0, 0.0, 0.0)


def _rule(points: Optional[SigmaPoints]) -> SigmaPoints:
    if points is None:
        return unscented()
    if not isinstance(points, SigmaPoints):
        raise InputError(f"points: expected a SigmaPoints rule (ukf.unscented() or "
                         f"ukf.cubature()), got {type(points).__name__}")
    return points


def _check_moments(mean, cov):
    """``(mean (n,), cov (n, n))`` of :func:`sigma_points` as arrays, shapes checked (static: free
    under ``jit``) with :class:`InputError` naming ``mean`` / ``cov``; an integer mean is
    promoted to the covariance's floating dtype (the default float when that is an integer too):
    integer weights truncated every weight to 0."""
    mean, cov = jnp.asarray(mean), jnp.asarray(cov)  # lists have no dtype
    m_dt = moment_dtype(mean, cov, "mean", "cov", empty_ok=True)  # n = 0: the rule's own error
    return jnp.asarray(mean, m_dt), jnp.asarray(cov, m_dt)


def sigma_points(mean, cov, points: Optional[SigmaPoints] = None) -> SigmaSet:
    """Sigma points and weights of ``N(mean, cov)`` under a rule (default :func:`unscented`).

    Args:
        mean: (n,) mean; its (floating) dtype is the dtype of the result (an integer mean is
            promoted to the covariance's floating dtype, or the default float).
        cov: (n, n) covariance, factored as ``L Lᵀ`` (lower Cholesky, after symmetrising).
        points: the rule.

    Returns:
        :class:`SigmaSet` ``(points (N, n), wm (N,), wc (N,), ok)``.
    """
    rule = _rule(points)
    mean, cov = _check_moments(mean, cov)
    dtype = mean.dtype
    n = mean.shape[0]
    wm, wc, c = rule.weights(n)
    L = jnp.linalg.cholesky(symmetrize(cov))
    ok = jnp.all(jnp.isfinite(L))
    L = jnp.where(ok, L, jnp.eye(n, dtype=dtype))
    D = jnp.asarray(c, dtype) * L.T  # row i: c L e_i
    pts = jnp.concatenate([mean + D, mean - D], axis=0)
    if rule.has_center:
        pts = jnp.concatenate([mean[None], pts], axis=0)
    return SigmaSet(pts, jnp.asarray(wm, dtype), jnp.asarray(wc, dtype), ok)


# ---------------------------------------------------------------------------
# Predict
# ---------------------------------------------------------------------------

def check_transition(X, shape):
    """The transition's outputs at the sigma points, ``X`` (N, n), against the points' ``shape``
    (static: free under ``jit``): :class:`InputError` naming ``f`` (an (N, 1) output used to be
    broadcast onto every state component without a word).  Shared with
    :func:`jaxslam.filters.sqrt_ukf.predict`."""
    got = tuple(np.shape(X)) if isinstance(X, (jax.Array, np.ndarray)) else None
    if got != tuple(shape):
        what = got[1:] if got is not None else type(X).__name__
        raise InputError(f"f: the transition returned shape {what}, expected ({shape[1]},)")
    return X


def _predict(state: Gaussian, f: Optional[Callable], u, Q, args, rule: SigmaPoints, noise_jac):
    """``(Gaussian, cross, status)`` of one sigma-point time update."""
    x, P = check_state(state)
    dtype = x.dtype
    Qd = process_noise(Q, x, u, args, noise_jac)
    q_neg = _g.negative_variance(Q)  # a traced Q with a negative variance: NOT_PSD, prior kept
    if f is None:
        Pn = symmetrize(P + Qd)
        finite = jnp.all(jnp.isfinite(Pn))
        p_status = jnp.where(finite, jnp.where(q_neg, jnp.int32(errors.NOT_PSD), _g.predicted_status(Pn)),
                             jnp.int32(errors.NON_FINITE))
        return (Gaussian(x, jnp.where(p_status == 0, Pn, P)), P, p_status)
    pts, wm, wc, ok = sigma_points(x, P, rule)
    X = check_transition(jax.vmap(lambda p: jnp.asarray(f(p, u, *args)))(pts), pts.shape).astype(dtype)  # (N, n)
    xm = wm @ X
    dX = X - xm
    dx = pts - x
    Pn = symmetrize((dX * wc[:, None]).T @ dX + Qd)
    C = (dx * wc[:, None]).T @ dX  # Cov(x, x')
    finite = jnp.all(jnp.isfinite(xm)) & jnp.all(jnp.isfinite(Pn)) & jnp.all(jnp.isfinite(C))
    # a negative predicted variance (a traced negative Q) is NOT_PSD: the prior is kept
    neg = (_g.predicted_status(Pn) == errors.NOT_PSD) | q_neg
    good = ok & finite & ~neg
    # a prior P with a NaN/Inf fails its factor: NON_FINITE, not NOT_PSD (gaussian.failure_status)
    status = _g.failure_status(jnp.asarray(True), ok & ~(finite & neg), jnp.all(jnp.isfinite(P)), finite)
    out = Gaussian(jnp.where(good, xm, x), jnp.where(good, Pn, P))
    return out, jnp.where(good, C, P), status


def predict_with_cross(state: Gaussian, f: Optional[Callable], u, Q, *args,
                       points: Optional[SigmaPoints] = None, noise_jac=None,
                       return_status: bool = False):
    """Sigma-point time update that also returns ``C = Cov(x, x')``.

    ``X_i = f(χ_i, u, *args)``, ``x̄' = Σ W^m X_i``, ``P' = Σ W^c (X_i − x̄')(X_i − x̄')ᵀ + Q``
    (symmetrised), ``C = Σ W^c (χ_i − x̄)(X_i − x̄')ᵀ`` — the predict of
    :func:`make_filter`'s ``GaussianFilter`` (``C`` is what the RTS smoother consumes).

    Args:
        state, f, u, Q, *args, noise_jac: as in :func:`predict`.
        points: the rule (default :func:`unscented`), static.
        return_status: static; also return the int32 status (``NOT_PSD`` / ``NON_FINITE``).

    Returns:
        ``(Gaussian, C (n, n))`` or ``(Gaussian, C, status)``.  On failure the prior moments
        and ``C = P`` (no NaN).
    """
    return_status = check_flag(return_status, "return_status")
    g, C, status = _predict_step(state, f, u, Q, args, _rule(points), noise_jac)
    return (g, C, status) if return_status else (g, C)


def predict(state: Gaussian, f: Optional[Callable], u, Q, *args,
            points: Optional[SigmaPoints] = None, noise_jac=None,
            return_status: bool = False):
    """Sigma-point time update (module docstring); the arguments of ``ekf.predict`` plus ``points``.

    ``x̄' = Σ W^m f(χ_i, u, *args)``, ``P' = Σ W^c (X_i − x̄')(X_i − x̄')ᵀ + Q`` or
    ``+ L Q Lᵀ`` with a noise Jacobian; the result is symmetrised.

    Args:
        state: prior :class:`Gaussian`, mean (n,), cov (n, n) positive definite.
        f: discrete transition ``f(x (n,), u, *args) -> (n,)`` over one step, or None
            (identity: ``P' = P + Q``).
        u: control/input of the step (any pytree).
        Q: (n, n) discrete process-noise covariance, or (q, q) with ``noise_jac``.
        *args: extra arguments passed to ``f`` (and ``noise_jac``).
        points: the rule (default :func:`unscented`), static.
        noise_jac: None, an (n, q) matrix ``L``, or a callable ``L(x, u, *args) -> (n, q)``
            evaluated at the prior mean (the noise is not augmented into the points).
        return_status: static; also return the int32 status word.

    Returns:
        Predicted :class:`Gaussian` in the dtype of ``state.mean`` (and the status).  If the
        factor of ``P`` is not finite (``NOT_PSD``) or the prediction is not finite
        (``NON_FINITE``) the prior is returned unchanged.
    """
    return_status = check_flag(return_status, "return_status")
    g, _, status = _predict_step(state, f, u, Q, args, _rule(points), noise_jac)
    return (g, status) if return_status else g


def _predict_step(state: Gaussian, f: Optional[Callable], u, Q, args, rule: SigmaPoints, noise_jac):
    """:func:`_predict` after the checks of values known now; called eagerly, compiled once per
    model (:func:`jaxslam.compilation.call_compiled`)."""
    state, Q = _g.check_predict_call(state, Q)  # the values known now (the compiled step sees them traced)

    def step(opts, state, Q):
        u, a, nj = opts
        return _predict(state, f, u, Q, a, rule, nj)

    return call_compiled(("ukf.predict", f, rule), step, (state, Q), (u, args, noise_jac), after=2)


# ---------------------------------------------------------------------------
# Update
# ---------------------------------------------------------------------------

def measurement_mean(Z, zref, wm, mask, residual):
    """Masked sigma-point measurements and their angle-safe mean ``ẑ = z_ref + Σ W^m r(Z_i, z_ref)``.

    ``Z`` (N, m) the transformed points, ``z_ref`` (m,) ``h(x̄)``; invalid components are
    zeroed first (NaN there never reaches the arithmetic).  Returns ``(Z_masked, ẑ)``;
    shared by :func:`update` and :func:`jaxslam.filters.sqrt_ukf.update`.
    """
    zero = jnp.zeros((), Z.dtype)
    Z = jnp.where(mask[None, :], Z, zero)
    zref = jnp.where(mask, zref, zero)
    return Z, zref + wm @ jax.vmap(lambda zi: call_residual(residual, zi, zref))(Z)


def _default_residual(z, zhat):
    return z - zhat


def update(
    state: Gaussian,
    z,
    h: Callable,
    R,
    *args,
    residual: Optional[Callable] = None,
    mask=None,
    gate: Gate = None,
    points: Optional[SigmaPoints] = None,
):
    """Sigma-point measurement update with masks and a chi-square gate.

    ``Z_i = h(χ_i, *args)``, ``ẑ = Σ W^m Z_i`` (anchored at ``h(x̄)``), ``ν = residual(z, ẑ)``,
    ``S = Σ W^c ΔZ_i ΔZ_iᵀ + R``, ``C = Σ W^c (χ_i − x̄) ΔZ_iᵀ`` with
    ``ΔZ_i = residual(Z_i, ẑ)``, ``K = C S⁻¹`` (Cholesky), ``x⁺ = x + K ν``,
    ``P⁺ = P − K S Kᵀ`` (symmetrised).

    Args:
        state: prior :class:`Gaussian`, mean (n,), cov (n, n) positive definite.
        z: (m,) measurement, in the units of ``h``'s output.
        h: measurement model ``h(x (n,), *args) -> (m,)``.
        R: (m, m) measurement-noise covariance, positive definite (or, for m = 1, a scalar
            variance > 0); a concrete one is checked (:class:`InputError` naming ``R``).
        *args: extra arguments of ``h`` (e.g. a landmark position).
        residual: ``residual(z, ẑ) -> (m,)``; default ``z − ẑ``.  Use
            :func:`jaxslam.filters.ekf.angle_residual` for components in radians (it also
            wraps the sigma-point spread).
        mask: (m,) bool, True for valid components (default: all valid).  Invalid
            components contribute nothing, whatever ``z`` (or ``h``) holds there.
        gate: None (no gate), a chi-square threshold on the NIS, or a callable
            ``gate(dof) -> threshold``.  When the NIS exceeds it the state is returned
            unchanged and ``errors.GATED`` is set.  A concrete gate must be a positive number
            (:class:`InputError`); a traced one that is not > 0 (NaN included) gates the
            update and also sets ``errors.NON_FINITE``.
        points: the rule (default :func:`unscented`), static.

    Returns:
        ``(posterior Gaussian, UpdateInfo)``.  If the factor of ``P`` or of ``S`` is not
        finite or a posterior variance is negative (``NOT_PSD``; NIS and ``logdet`` then 0 for
        a failed factor) or the posterior is not finite (``NON_FINITE``), the prior is
        returned unchanged.  Called eagerly it is compiled once per model
        (:func:`jaxslam.compilation.call_compiled`).
    """
    rule = _rule(points)
    state, z, R, mask = _g.check_update_call(state, z, R, mask, gate)  # the values known now

    def step(opts, state, z, R, mask):
        a, g = opts
        return _update(state, z, h, R, *a, residual=residual, mask=mask, gate=g, rule=rule)

    return call_compiled(("ukf.update", h, residual, rule), step, (state, z, R, mask), (args, gate), after=2)


def _update(state: Gaussian, z, h: Callable, R, *args, residual=None, mask=None, gate: Gate = None,
            rule: SigmaPoints):
    """:func:`update`'s computation (shape checks; values are checked by the caller)."""
    x, P = check_state(state)
    dtype = x.dtype
    check_update_args(z, R, mask)
    z, h = scalar_measurement(z, h)
    z = jnp.asarray(z, dtype)
    R = jnp.asarray(R, dtype)
    m = z.shape[-1]
    n = x.shape[0]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    res = _default_residual if residual is None else residual
    zero = jnp.zeros((), dtype)

    pts, wm, wc, ok_pts = sigma_points(x, P, rule)
    Z = jax.vmap(lambda p: jnp.asarray(h(p, *args)))(pts).astype(dtype)  # (N, m)
    zref = Z[0] if rule.has_center else jnp.asarray(h(x, *args), dtype)
    check_measurement(z, zref, R, mask)
    check_gate_size(gate, m, mask)
    Z, zhat = measurement_mean(Z, zref, wm, mask, res)
    dZ = jnp.where(mask[None, :], jax.vmap(lambda zi: call_residual(res, zi, zhat))(Z), zero)  # (N, m)
    dx = pts - x  # (N, n)
    mm = mask[:, None] & mask[None, :]
    S = symmetrize(jnp.where(mm, (dZ * wc[:, None]).T @ dZ + R, jnp.eye(m, dtype=dtype)))
    Cxz = (dx * wc[:, None]).T @ dZ  # (n, m); zero columns on invalid components
    nu = masked_innovation(z, zhat, mask, res)
    X, ok_s, logdet = innovation_solve(S, jnp.concatenate([Cxz.T, nu[:, None]], axis=1))
    K = X[:, :n].T  # C S⁻¹
    ok = ok_s & ok_pts
    nis = jnp.where(ok, jnp.dot(nu, X[:, n]), zero)
    x_post = x + K @ nu
    P_post = symmetrize(P - K @ S @ K.T)
    dof = jnp.sum(mask).astype(jnp.int32)
    if gate is None:
        gated, g_status = jnp.asarray(False), None
    else:  # a traced threshold that is not > 0 (NaN) gates the update and flags NON_FINITE
        gated, g_status = _g.gate_test(gate, nis, dof, dtype)
    # a NaN/Inf in P or S (the sigma points of a NaN mean, R's valid block) is NON_FINITE only
    finite_in = jnp.all(jnp.isfinite(P)) & jnp.all(jnp.isfinite(S))
    post, accepted, status = finalize(Gaussian(x, P), x_post, P_post, ok, gated, dof, g_status,
                                      finite_in=finite_in)
    logdet = jnp.where(ok & (dof > 0), logdet, zero)
    return post, UpdateInfo(nis, dof, nu, S, accepted, status, logdet)


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
    points: Optional[SigmaPoints] = None,
    h_takes_input: bool = False,
) -> GaussianFilter:
    """The sigma-point filter as a :class:`jaxslam.filters.gaussian.GaussianFilter`.

    Args:
        f: transition ``f(x, u, *args) -> (n,)``, or None for a model whose state does not
            move (identity, ``P' = P + Q``).
        h: measurement model ``h(x, *args)``, or ``h(x, c, *args)`` with the step's input
            ``c`` when ``h_takes_input``.
        *args: shared extra arguments of both ``f`` and ``h``.
        residual, gate: as in :func:`update`.  noise_jac: as in :func:`predict`.
        points: the rule (default :func:`unscented`), static.
        h_takes_input: static; ``h`` receives the per-step ``h_inputs`` of the run.

    Returns:
        ``GaussianFilter(predict, update)``; ``predict`` returns the sigma-point
        cross-covariance ``Cov(x, x')`` beside the predicted belief (what the RTS smoother
        needs) and the predict's status bits.
    """
    rule = _rule(points)
    check_gate(gate)
    h_takes_input = check_flag(h_takes_input, "h_takes_input")

    def pred(state, u, Q):
        return _predict(state, f, u, Q, args, rule, noise_jac)  # (Gaussian, cross, status)

    def upd(state, z, mask, R, c):
        hh = (lambda x, *a: h(x, c, *a)) if h_takes_input else h
        return _update(state, z, hh, R, *args, residual=residual, mask=mask, gate=gate, rule=rule)

    # a run of it compiles once per model, however often the filter is made again
    return _g.keyed_filter(
        GaussianFilter(pred, upd),
        lambda a, g, nj: make_filter(f, h, *a, residual=residual, gate=g, noise_jac=nj, points=rule,
                                     h_takes_input=h_takes_input),
        (args, gate, noise_jac), ("ukf.make_filter", f, h, residual, rule, h_takes_input))


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
    points: Optional[SigmaPoints] = None,
    h_inputs=None,
    save_smoother: bool = False,
) -> Posterior:
    """Run sigma-point predict + update over a whole sequence as one ``lax.scan``.

    Step t (``predict_first=True``): predict with ``u_t`` (:func:`predict`), then update with
    ``z_t`` under ``masks[t]`` (:func:`update`).  Jit it with ``f``, ``h``, ``residual``, a
    callable ``gate``, ``save_cov``, ``predict_first``, ``points`` and ``save_smoother``
    static; vmap it over runs.  Called eagerly it is compiled once per model
    (:func:`jaxslam.compilation.call_compiled`).  The same run as
    ``gaussian.run(make_filter(f, h, ...), ...)``.

    Args:
        f: transition ``f(x, u, *args) -> (n,)`` (None: the state does not move).
        h: measurement model ``h(x, *args) -> (m,)``, or ``h(x, c_t, *args)`` when
            ``h_inputs`` is given.
        x0: (n,) initial mean.  P0: (n, n) initial covariance (positive definite).
        us: controls with leading axis T (array or pytree; None if unused).
        zs: (T, m) measurements.
        masks: (T, m) bool validity (None: all valid).
        Q: (n, n) (or (q, q) with ``noise_jac``) process noise, or one per step (T, n, n);
            a scalar for a single noise input (n = 1, or q = 1), as in :func:`predict`.
            R: (m, m) or (T, m, m) (a scalar for m = 1).  ``x0``, ``P0``, ``zs``, ``Q``, ``R``
            must not be booleans (:class:`InputError` naming it).
        *args: shared extra arguments of both ``f`` and ``h``.
        residual, gate: as in :func:`update`.
        save_cov: static; also stack full covariances (T, n, n).
        predict_first: static; step order (see :mod:`jaxslam.filters.gaussian`).
        noise_jac: as in :func:`predict`.
        points: the rule (default :func:`unscented`), static.
        h_inputs: per-step inputs of the measurement model (leading axis T).
        save_smoother: static; save what :func:`jaxslam.filters.smoother.rts` needs (with
            the sigma-point cross-covariances: the unscented RTS smoother).

    Returns:
        :class:`Posterior` in the dtype of ``x0`` (``log_likelihood`` per step included).  A
        failed prediction is skipped, as in every Gaussian run: the step it fed keeps the
        belief the predict started from, makes no update (NIS 0) and carries the predict's
        bits and a NaN log-likelihood (that step used to update the previous step's belief
        with its ``z``).
    """
    _g.refuse_bool(P0, "P0")  # (before the PD check below reads True as 1)
    if is_concrete(P0) and np.ndim(P0) == 2 and np.size(P0):  # empty: gaussian.run names x0
        # the sigma points factor P: a singular P0 (a zero variance) would fail every step's
        # factorisation and keep the prior for the whole run
        check_psd(P0, "P0", strict=True, tol=0.0)
    flt = make_filter(f, h, *args, residual=residual, gate=gate, noise_jac=noise_jac,
                      points=points, h_takes_input=h_inputs is not None)
    return _g._run(flt, x0, P0, us, zs, masks, Q, R, h_inputs, predict_first, save_cov, save_smoother,
                   noise=_g.noise_size(x0, noise_jac))
