"""Tuning losses: innovation likelihood (no truth), state error (truth), NEES consistency.

All losses are per run (scalars; :mod:`jaxslam.tuning.optimize` averages them over a
batch of runs) and differentiable in the filter's noise parameters.

* :func:`innovation_nll` — the negative log-likelihood of the innovations (prediction
  error decomposition): for the filter's innovations ν_k with covariances S_k,
  −log p(z_1:K) = ½ Σ_k (ν_kᵀ S_k⁻¹ ν_k + log det S_k + m_k log 2π).  It needs neither
  ground truth nor noise densities, so it works on real logs: the filter scores its own
  predictions of the next measurements.  For a linear-Gaussian model it is the exact
  log-likelihood of Q and R, so its minimiser is the maximum-likelihood estimate.
* :func:`mse` — mean squared state error against the truth (simulation only); weights
  pick and scale the state components (units of each component squared).
* :func:`nees_loss` — (log(ANEES / n))², zero when the time-averaged NEES equals the state
  dimension.  Consistency alone does not identify Q (a large Q with large errors can be
  consistent), so it is meant as a regulariser or to calibrate one scale factor.

Decisions (no paper covers tuning):

* NLL is normalised by the number of scalar measurements Σ m_k, so its size does not
  depend on the log length (learning rates transfer between short and long logs); the
  constant ½ log 2π per measurement is kept, so the value is a true per-measurement
  negative log density.
* The EKF-SLAM engine's update reports the NIS and log det S of its joint update
  (``UpdateInfo.nis``, ``.logdet``), which the tuning targets read;
  :func:`slam_innovation_terms` recomputes both from the prior independently (the same
  gathered blocks, a dense joint S) and serves as their check (a test matches it to the
  engine's to 1e-9).  Unmapped
  landmarks (first sightings, registered rather than updated) carry no likelihood term:
  their measurement is absorbed into the new landmark's mean.
* The NEES loss uses the log of the time average, so under- and over-confidence by the
  same factor cost the same.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..filters import ekf_slam as es
from ..linalg import check_int, check_mask, check_psd, float_array, is_concrete, symmetrize

__all__ = [
    "nll_terms",
    "slam_innovation_terms",
    "innovation_nll",
    "mse",
    "nees_loss",
]


def _same_shape(x, shape, name: str, what: str):
    if tuple(jnp.shape(x)) != tuple(shape):
        raise InputError(f"{name}: expected shape {tuple(shape)} ({what}), got {tuple(jnp.shape(x))}")


def _mask(mask, shape, name: str = "mask"):
    """``mask`` as a bool array of ``shape`` (InputError naming it otherwise): bool or 0/1
    integers, as :func:`nll_terms`'s (a float or a 2 entry was counted by its value); a concrete
    mask that selects nothing is refused (its loss would be 0/0)."""
    if not (hasattr(mask, "dtype") and hasattr(mask, "shape")):
        mask = jnp.asarray(mask)
    _same_shape(mask, shape, name, "one entry per step")
    check_mask(mask, name)
    if is_concrete(mask) and mask.size and not np.any(np.asarray(mask)):
        raise InputError(f"{name}: selects no step (all False); the loss would be undefined")
    return mask.astype(bool)


def nll_terms(nu, S, mask=None):
    """(NIS, log det S, dof) of one innovation; the pieces of :func:`innovation_nll`.

    ``nu`` (m,), ``S`` (m, m) with invalid components already given an identity
    row/column (as :func:`jaxslam.filters.ekf.update` reports S) so they add 0 to
    log det; ``mask`` (m,) bool (or 0/1 integers) selects the valid components (default
    all).  Returns three scalars in nu's dtype (dof as float; a float64 S with a float32 ``nu``
    no longer promotes the NIS and log det to float64).  An empty innovation (m = 0) gives
    (0, 0, 0).  Known now, a float mask or
    other integers, and an S that is not symmetric positive definite, are :class:`InputError`
    naming it (a non-PD S gave NaN); traced values are not checked.
    """
    nu, S = float_array(nu, "nu"), float_array(S, "S")
    if nu.ndim != 1:
        raise InputError(f"nu: expected shape (m,), got {tuple(nu.shape)}")
    dtype = nu.dtype
    m = nu.shape[-1]
    _same_shape(S, (m, m), "S", "m × m for m = len(nu)")
    if is_concrete(S) and m:  # a non-PD S would give a silent NaN through its Cholesky factor
        check_psd(S, "S", strict=True)
    if mask is not None:
        mask = jnp.asarray(mask) if not hasattr(mask, "shape") else mask
        _same_shape(mask, (m,), "mask", "one entry per component of nu")
        # as the systems' masks: bool or 0/1 integers (a 2 or 0.5 entry miscounted the dof)
        check_mask(mask, "mask")
        mask = mask.astype(bool)
    mask = jnp.ones((m,), bool) if mask is None else mask
    nu = jnp.where(mask, nu, 0.0)
    Lc = jnp.linalg.cholesky(symmetrize(S))
    w = jax.scipy.linalg.solve_triangular(Lc, nu, lower=True)
    nis = jnp.sum(w * w)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(Lc)))
    return nis.astype(dtype), logdet.astype(dtype), jnp.sum(mask).astype(dtype)


def slam_innovation_terms(state: es.SlamState, model: es.SlamModel, z, slots, valid, R, params=None):
    """(NIS, log det S, dof) of a joint EKF-SLAM update, from the prior ``state``.

    Paper 000 eq. 37-39: S = H P Hᵀ + R over the K measurements (K, d_z) of the landmarks
    in ``slots`` (K,) where ``valid`` (K,) (only mapped, finite measurements may be
    valid — the same mask :func:`jaxslam.filters.ekf_slam.update` uses).  H is sparse
    (robot block and one landmark block per measurement), so S is formed from the gathered
    (n_r + K·d_l)² block of P, never from the full covariance.  ``R`` (d_z, d_z) or
    (K, d_z, d_z).  Invalid rows get identity in S (adding 0 to log det) and zero innovation.
    Shapes (static) and ``valid``'s dtype (bool or 0/1 integers) are checked: :class:`InputError`
    naming the argument (a float ``valid`` failed inside with a TypeError).
    """
    nr, dl, dz = model.robot_dim, model.lm_dim, model.meas_dim
    if jnp.ndim(z) != 2 or jnp.shape(z)[1] != dz:
        raise InputError(f"z: expected shape (K, {dz}) (one measurement per row), got {tuple(jnp.shape(z))}")
    K = z.shape[0]
    _same_shape(slots, (K,), "slots", "one slot per row of z")
    _same_shape(valid, (K,), "valid", "one entry per row of z")
    check_mask(valid, "valid")
    valid = jnp.asarray(valid).astype(bool)
    cap = state.active.shape[0]
    dtype = state.x.dtype
    slots = jnp.clip(slots.astype(jnp.int32), 0, cap - 1)
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    z = jnp.where(valid[:, None], z, 0.0).astype(dtype)
    s = state.x[:nr]
    L = state.x[nr:].reshape(cap, dl)[slots]

    def one(l):
        zh = model.observe(s, l, params)
        Hs, Hl = jax.jacfwd(model.observe, argnums=(0, 1))(s, l, params)
        return zh, Hs, Hl

    zh, Hs, Hl = jax.vmap(one)(L)
    res = model.residual if model.residual is not None else (lambda a, b: a - b)
    nu = jax.vmap(res)(z, zh)
    idx = jnp.concatenate([jnp.arange(nr), es.slot_indices(slots, model).reshape(-1)])
    Psub = state.P[idx[:, None], idx[None, :]]  # (nr + K dl)²
    # H on the gathered block: robot columns, then a block diagonal of the landmark Jacobians.
    Hl_blk = jnp.einsum("kzj,kq->kzqj", Hl, jnp.eye(K, dtype=dtype)).reshape(K * dz, K * dl)
    H = jnp.concatenate([Hs.reshape(K * dz, nr), Hl_blk], axis=1)
    vv = jnp.repeat(valid, dz)
    H = H * vv[:, None]
    R_blk = jnp.einsum("kzw,kq->kzqw", R, jnp.eye(K, dtype=dtype)).reshape(K * dz, K * dz)
    S = H @ Psub @ H.T + R_blk * (vv[:, None] & vv[None, :]) + jnp.diag(jnp.where(vv, 0.0, 1.0))
    return nll_terms(nu.reshape(-1), S, vv)


def innovation_nll(nis, logdet, dof):
    """Per-measurement innovation NLL of one run: ½ Σ (NIS + log det S + m log 2π) / Σ m.

    ``nis``, ``logdet``, ``dof``: (K,) per update (from :func:`nll_terms` or
    :func:`slam_innovation_terms`); updates with dof = 0 add nothing.  Units: nats per
    scalar measurement.  Needs no ground truth.
    """
    nis, logdet, dof = float_array(nis, "nis"), float_array(logdet, "logdet"), float_array(dof, "dof")
    _same_shape(logdet, nis.shape, "logdet", "one per update, as nis")
    _same_shape(dof, nis.shape, "dof", "one per update, as nis")
    if is_concrete(dof) and not np.all(np.asarray(dof) >= 0):  # a NaN count made the loss NaN
        raise InputError("dof: expected counts >= 0 (measurements per update)")
    dtype = nis.dtype
    tot = jnp.maximum(jnp.sum(dof), 1.0)
    ll = 0.5 * (nis + logdet + dof * jnp.asarray(math.log(2.0 * math.pi), dtype))
    return jnp.sum(jnp.where(dof > 0, ll, 0.0)) / tot


def mse(err, weights=None, mask=None):
    """Mean over time of Σ_i w_i e_i² for errors ``err`` (T, n) against the truth.

    ``weights`` (n,) or a number, default ones (units: each component's unit squared, so choose
    weights that make them commensurate); ``mask`` (T,) bool (or 0/1 integers) selects the
    steps counted: the others never enter, not even a NaN error there (nor its gradient).
    A 1-D ``err`` is an :class:`InputError` (is it T steps of one component or one step of n?
    Give (T, 1) or (1, n)).
    """
    err = float_array(err, "err")
    if err.ndim < 2 or err.size == 0:
        raise InputError(f"err: expected a non-empty (T, n) array of errors (one row per step; (T, 1) for "
                         f"one component), got shape {tuple(err.shape)}")
    if not jnp.issubdtype(err.dtype, jnp.inexact):
        err = err.astype(jnp.result_type(float))
    dtype = err.dtype
    if weights is not None:
        weights = float_array(weights, "weights")
        if weights.ndim > 1 or (weights.ndim == 1 and weights.shape[0] != err.shape[-1]):
            raise InputError(f"weights: expected a number or shape ({err.shape[-1]},) (one per state "
                             f"component), got {tuple(weights.shape)}")
        if is_concrete(weights) and not np.all(np.asarray(weights) >= 0):
            raise InputError("weights: expected non-negative weights (a negative one rewards error)")
    if mask is not None:
        mask = _mask(mask, err.shape[:-1])
    w = jnp.ones(err.shape[-1], dtype) if weights is None else jnp.asarray(weights, dtype)
    if mask is None:
        return jnp.mean(jnp.sum(err * err * w, axis=-1))
    # where, not a product with the mask: NaN · 0 is NaN (a masked-out diverged step leaked in),
    # and the error is zeroed before squaring so its gradient there is 0 too
    e = jnp.where(mask[..., None], err, 0.0)
    sq = jnp.sum(e * e * w, axis=-1)
    m = mask.astype(dtype)
    return jnp.sum(jnp.where(mask, sq, 0.0)) / jnp.maximum(jnp.sum(m), 1.0)


def nees_loss(nees, n: int, mask=None):
    """(log(mean_t NEES_t / n))² for one run's NEES series (T,) of an n-dimensional state.

    Zero when the time-averaged NEES equals n (a consistent filter); ``mask`` (T,) bool (or
    0/1 integers) selects the steps counted (e.g. frames after a settling time).  A known
    negative NEES on a counted step (a quadratic form is >= 0) is an :class:`InputError` (its log
    was a silent NaN).
    """
    nees = float_array(nees, "nees")
    if nees.size == 0:
        raise InputError(f"nees: expected a non-empty NEES series, got shape {tuple(nees.shape)}")
    if is_concrete(n):
        check_int(n, "n", lower=1, what="a state dimension (int)")
    if mask is not None:
        mask = _mask(mask, nees.shape)
    if is_concrete(nees) and (mask is None or is_concrete(mask)):
        counted = np.asarray(nees) if mask is None else np.asarray(nees)[np.asarray(mask, bool)]
        if np.any(counted < 0):  # (a step the mask leaves out is not read)
            raise InputError(f"nees: expected values >= 0 (NEES is a quadratic form), got min "
                             f"{float(np.nanmin(counted))}")
    dtype = nees.dtype
    if mask is None:
        a = jnp.mean(nees)
    else:
        m = mask.astype(dtype)
        a = jnp.sum(jnp.where(mask, nees, 0.0)) / jnp.maximum(jnp.sum(m), 1.0)
    return jnp.log(a / jnp.asarray(n, dtype)) ** 2
