"""Sigma-point (unscented / cubature) Gaussian filter with the EKF's signatures, masks and gate.

Generic: the model enters through ``f(x, u, *args)`` and ``h(x, *args)`` exactly as in
:mod:`jaxslam.filters.ekf`, and a run is the same :func:`jaxslam.filters.gaussian.run`, so a
sigma-point filter is usable wherever the EKF is (whole-run scans, vmapped Monte Carlo,
``jax.grad`` of the log-likelihood, the RTS smoother of :mod:`jaxslam.filters.smoother`).

Equations
---------
Sigma points of ``N(x̄, P)`` with ``P = L Lᵀ`` (Cholesky): ``χ_i = x̄ + c L e_i``,
``χ_{n+i} = x̄ − c L e_i`` and, for the unscented rule, ``χ_0 = x̄``; weights ``W^m``, ``W^c``.

*Unscented* (scaled UT, Wan & van der Merwe 2000): ``λ = α² (n + κ) − n``, ``c = √(n + λ)``,
``W^m_0 = λ / (n + λ)``, ``W^c_0 = W^m_0 + 1 − α² + β``, ``W_i = 1 / (2 (n + λ))``.
*Cubature* (Arasaratnam & Haykin 2009): ``2n`` points, ``c = √n``, ``W_i = 1 / (2n)``.

Predict: ``X_i = f(χ_i, u)``, ``x̄' = Σ W^m X_i``, ``P' = Σ W^c (X_i − x̄')(X_i − x̄')ᵀ + Q``,
and the cross-covariance ``C = Σ W^c (χ_i − x̄)(X_i − x̄')ᵀ`` (what the RTS smoother needs).
Update: ``Z_i = h(χ_i)``, ``ẑ = Σ W^m Z_i``, ``S = Σ W^c (Z_i − ẑ)(Z_i − ẑ)ᵀ + R``,
``C_xz = Σ W^c (χ_i − x̄)(Z_i − ẑ)ᵀ``, ``K = C_xz S⁻¹`` (Cholesky), ``x⁺ = x̄ + K ν``,
``P⁺ = P − K S Kᵀ`` (symmetrised).

Decisions
---------
* Default rule: unscented with ``α = 1, β = 2, κ = 0``: ``λ = 0``, so ``W^m_0 = 0``,
  ``W^c_0 = 2`` and the other points sit at ±√n standard deviations.  The often quoted
  ``α = 1e-3`` makes ``W_0 ≈ −10⁶``: the covariance is then a difference of huge terms and
  loses definiteness in float32; filterpy's ``MerweScaledSigmaPoints`` asks the user for
  α (its docs suggest 1e-3 too).  We follow Wan & van der Merwe's formulas; the values are
  arguments of :func:`unscented`.
* Residuals: the user's ``residual(z, ẑ)`` is used for the innovation *and* for the spread
  ``Z_i − ẑ``, so angle components wrap in both.  The sigma-point mean of an angle is the
  weighted mean of the raw values (fine away from ±π, as the EKF's ``h`` is).
* Additive noise: ``Q`` and ``R`` are added, not augmented into the sigma points; with
  ``noise_jac`` L the predict adds ``L Q Lᵀ`` evaluated at the prior mean.
* Masks and gate exactly as the EKF (:mod:`jaxslam.filters.gaussian`): invalid components get
  zero rows of ``C_xz`` and a unit row/column of ``S``, so their gain columns vanish.
* Failures never produce NaN: a non-finite Cholesky factor of ``P`` (``NOT_PSD``) or a
  non-finite result (``NON_FINITE``) keeps the prior and sets the status bit.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp

from ..errors import InputError
from ..linalg import symmetrize
from . import gaussian as _g
from .gaussian import (
    Gate,
    Gaussian,
    GaussianFilter,
    Posterior,
    UpdateInfo,
    finalize,
    innovation_solve,
    masked_innovation,
    threshold,
)

__all__ = [
    "SigmaRule",
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


class SigmaRule(NamedTuple):
    """A sigma-point rule (static): ``kind`` "unscented" | "cubature" and its parameters."""

    kind: str = "unscented"
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0


def unscented(alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaRule:
    """The scaled unscented rule (2n + 1 points; module docstring)."""
    if not alpha > 0:
        raise InputError(f"alpha: must be > 0, got {alpha}")
    return SigmaRule("unscented", float(alpha), float(beta), float(kappa))


def cubature() -> SigmaRule:
    """The third-degree spherical-radial cubature rule (2n points, equal weights)."""
    return SigmaRule("cubature")


def _weights(rule: SigmaRule, n: int, dtype):
    if rule.kind == "cubature":
        w = jnp.full((2 * n,), 1.0 / (2 * n), dtype)
        return w, w, float(n) ** 0.5
    if rule.kind != "unscented":
        raise InputError(f"points: unknown sigma-point rule {rule.kind!r} (unscented, cubature)")
    lam = rule.alpha**2 * (n + rule.kappa) - n
    if n + lam <= 0:
        raise InputError(f"points: n + λ = {n + lam:g} must be > 0 (raise alpha or kappa)")
    wi = 1.0 / (2.0 * (n + lam))
    wm = jnp.concatenate([jnp.asarray([lam / (n + lam)], dtype), jnp.full((2 * n,), wi, dtype)])
    wc = wm.at[0].add(1.0 - rule.alpha**2 + rule.beta)
    return wm, wc, (n + lam) ** 0.5


def sigma_points(mean, cov, rule: SigmaRule = SigmaRule()):
    """Sigma points and weights of ``N(mean, cov)``.

    Returns ``(points (N, n), Wm (N,), Wc (N,), ok)``; ``ok`` is False when the Cholesky
    factor of ``cov`` is not finite (the points are then computed from an identity factor
    and must not be used).
    """
    n = mean.shape[0]
    dtype = mean.dtype
    wm, wc, c = _weights(rule, n, dtype)
    L = jnp.linalg.cholesky(symmetrize(cov))
    ok = jnp.all(jnp.isfinite(L))
    L = jnp.where(ok, L, jnp.eye(n, dtype=dtype))
    D = c * L.T  # rows: c L e_i
    pts = jnp.concatenate([mean + D, mean - D], 0)
    if rule.kind == "unscented":
        pts = jnp.concatenate([mean[None], pts], 0)
    return pts, wm, wc, ok


def predict_with_cross(state: Gaussian, f: Optional[Callable], u, Q, *args,
                       points: SigmaRule = SigmaRule(), noise_jac=None):
    """Sigma-point time update; returns ``(Gaussian, cross)`` with ``cross = Cov(x, x')`` (n, n)."""
    x, P = state
    dtype = x.dtype
    fm = (lambda v, u_, *a: v) if f is None else f
    pts, wm, wc, ok = sigma_points(x, P, points)
    X = jax.vmap(lambda p: fm(p, u, *args))(pts).astype(dtype)
    xm = wm @ X
    dX = X - xm
    dx = pts - x
    Qd = jnp.asarray(Q, dtype)
    if noise_jac is not None:
        Lm = noise_jac(x, u, *args) if callable(noise_jac) else noise_jac
        Lm = jnp.asarray(Lm, dtype)
        Qd = Lm @ Qd @ Lm.T
    Pn = symmetrize((dX * wc[:, None]).T @ dX + Qd)
    C = (dx * wc[:, None]).T @ dX
    good = ok & jnp.all(jnp.isfinite(xm)) & jnp.all(jnp.isfinite(Pn))
    # A failed prediction keeps the prior moments (flagged by the next update's status).
    return Gaussian(jnp.where(good, xm, x), jnp.where(good, Pn, P)), jnp.where(good, C, P)


def predict(state: Gaussian, f: Optional[Callable], u, Q, *args,
            points: SigmaRule = SigmaRule(), noise_jac=None) -> Gaussian:
    """Sigma-point time update (module docstring); same arguments as ``ekf.predict`` plus ``points``."""
    return predict_with_cross(state, f, u, Q, *args, points=points, noise_jac=noise_jac)[0]


def _default_residual(z, zhat):
    return z - zhat


def update(state: Gaussian, z, h: Callable, R, *args, residual: Optional[Callable] = None,
           mask=None, gate: Gate = None, points: SigmaRule = SigmaRule()):
    """Sigma-point measurement update with masks and a χ² gate (module docstring).

    Same arguments and returns as :func:`jaxslam.filters.ekf.update` (``points`` picks the
    rule): ``(posterior Gaussian, UpdateInfo)``; on a failed factorisation (``NOT_PSD``) or a
    non-finite posterior (``NON_FINITE``) the prior is returned unchanged.
    """
    x, P = state
    dtype = x.dtype
    z = jnp.asarray(z, dtype)
    R = jnp.asarray(R, dtype)
    m = z.shape[-1]
    n = x.shape[0]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    res = _default_residual if residual is None else residual
    pts, wm, wc, ok_pts = sigma_points(x, P, points)
    Z = jax.vmap(lambda p: h(p, *args))(pts).astype(dtype)
    zhat = wm @ Z
    dZ = jax.vmap(lambda zi: res(zi, zhat))(Z)
    zero = jnp.zeros((), dtype)
    dZ = jnp.where(mask[None, :], dZ, zero)
    dx = pts - x
    mm = mask[:, None] & mask[None, :]
    S = symmetrize(jnp.where(mm, (dZ * wc[:, None]).T @ dZ + R, jnp.eye(m, dtype=dtype)))
    Cxz = (dx * wc[:, None]).T @ dZ  # (n, m), zero columns where masked
    nu = masked_innovation(z, zhat, mask, res)
    X, ok, logdet = innovation_solve(S, jnp.concatenate([Cxz.T, nu[:, None]], axis=1))
    K = X[:, :n].T  # C S⁻¹
    nis = jnp.dot(nu, X[:, n])
    x_post = x + K @ nu
    P_post = symmetrize(P - K @ S @ K.T)
    dof = jnp.sum(mask).astype(jnp.int32)
    ok = ok & ok_pts
    gated = (dof > 0) & (nis > threshold(gate, dof, dtype)) if gate is not None else jnp.asarray(False)
    post, accepted, status = finalize(state, x_post, P_post, ok, gated, dof)
    logdet = jnp.where(ok & (dof > 0), logdet, zero)
    return post, UpdateInfo(nis, dof, nu, S, accepted, status, logdet)


def make_filter(f: Optional[Callable], h: Callable, *args, residual: Optional[Callable] = None,
                gate: Gate = None, noise_jac=None, points: Optional[SigmaRule] = None,
                h_takes_input: bool = False) -> GaussianFilter:
    """The sigma-point filter as a :class:`jaxslam.filters.gaussian.GaussianFilter`.

    Same arguments as :func:`jaxslam.filters.ekf.make_filter` (``points``: the rule, default
    :func:`unscented`).
    """
    rule = SigmaRule() if points is None else points

    def pred(state, u, Q):
        return predict_with_cross(state, f, u, Q, *args, points=rule, noise_jac=noise_jac)

    def upd(state, z, mask, R, c):
        hh = (lambda x, *a: h(x, c, *a)) if h_takes_input else h
        return update(state, z, hh, R, *args, residual=residual, mask=mask, gate=gate, points=rule)

    return GaussianFilter(pred, upd)


def filter_scan(f: Optional[Callable], h: Callable, x0, P0, us, zs, masks, Q, R, *args,
                residual: Optional[Callable] = None, gate: Gate = None, save_cov: bool = False,
                predict_first: bool = True, noise_jac=None, points: Optional[SigmaRule] = None,
                h_inputs=None, save_smoother: bool = False) -> Posterior:
    """Sigma-point filter over a whole sequence as one ``lax.scan``.

    The arguments and the :class:`~jaxslam.filters.gaussian.Posterior` are those of
    :func:`jaxslam.filters.ekf.filter_scan`; ``points`` picks the rule (static).  With
    ``save_smoother`` the cross-covariances are the sigma-point ones, so
    :func:`jaxslam.filters.smoother.rts` is then the unscented RTS smoother.
    """
    flt = make_filter(f, h, *args, residual=residual, gate=gate, noise_jac=noise_jac,
                      points=points, h_takes_input=h_inputs is not None)
    return _g.run(flt, x0, P0, us, zs, masks, Q, R, h_inputs=h_inputs, predict_first=predict_first,
                  save_cov=save_cov, save_smoother=save_smoother)

