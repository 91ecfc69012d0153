"""Square-root (Cholesky-factor) extended Kalman filter: predict, masked/gated update, scan.

The same filter as :mod:`jaxslam.filters.ekf`, but the belief carries a lower-triangular
factor ``L`` of the covariance, ``P = L Lᵀ``, instead of ``P`` itself, and ``P`` is never
formed.  Use it for float32 runs (GPU) of poorly observable or very precisely measured
systems, where a stored float32 covariance of large dynamic range (condition number
beyond ~1/eps ≈ 10⁷) rounds to a matrix that is singular or indefinite: a variance that
should be tiny comes out zero or negative, and the next innovation covariance can fail its
Cholesky factorisation.  A factor ``L`` represents a positive semi-definite matrix by
construction, and its entries carry the square root of the covariance's dynamic range.

State equations (identical to :mod:`jaxslam.filters.ekf`; units are the model's)::

    predict:  x' = f(x, u, *args),             P' = F P Fᵀ + G Q Gᵀ       (G = I by default)
    update:   ẑ = h(x, *args),  ν = residual(z, ẑ),  S = H P Hᵀ + R,
              K = P Hᵀ S⁻¹,  x⁺ = x + K ν,  P⁺ = P − K S Kᵀ

with ``F = ∂f/∂x`` and ``H = ∂h/∂x`` from :func:`jax.jacfwd` at the prior mean.

Decisions
---------
* **Orthogonal triangularisation (QR), not factor up/down-dates.**  Every step builds a
  *pre-array* ``A`` whose Gram matrix ``A Aᵀ`` holds the wanted covariances, and one
  Householder QR of ``Aᵀ`` turns it into a lower-triangular *post-array* ``B = A Θ``
  (``Θ`` orthogonal, so ``B Bᵀ = A Aᵀ``).  Householder QR is backward stable column by
  column, so the result is the exact factor of a pre-array perturbed by a few eps per
  column; ``B Bᵀ`` is positive semi-definite whatever the rounding.  It is one library
  call of fixed shape (jit/vmap/grad friendly), where rank-one Cholesky up/down-dates
  are sequential loops and a down-date can fail.

  - predict: ``A = [F L, G L_Q]`` (n × (n + k)), ``B = [L', 0]``, so ``L' L'ᵀ = F P Fᵀ + G Q Gᵀ``.
  - update (array algorithm)::

        A = [[L_R, H L],        B = A Θ = [[S^½,  0 ],
             [ 0,    L ]]                    [K̄,   L⁺]]

    Matching ``A Aᵀ = B Bᵀ`` block by block: ``S^½ S^½ᵀ = R + H P Hᵀ = S``,
    ``K̄ = P Hᵀ S^{-½ᵀ}`` (so the gain is ``K = K̄ S^{-½}``), and
    ``L⁺ L⁺ᵀ = P − K̄ K̄ᵀ = P − K S Kᵀ``.  The mean is ``x⁺ = x + K̄ w`` with
    ``w = S^{-½} ν`` (one triangular solve) and the NIS is ``νᵀ S⁻¹ ν = ‖w‖²``.
    The factor of ``S``, the gain and the posterior factor come out of one QR.

* **Sign convention.**  A triangular factor is unique only up to the signs of its columns;
  every factor returned here (of the predicted, updated, ``S`` and noise covariances) has a
  non-negative diagonal: the rows of the QR's ``R`` whose diagonal entry is negative are
  negated (a zero diagonal keeps its sign), which changes neither ``B Bᵀ`` nor the
  triangularity.  Results are therefore reproducible and comparable entry by entry.
* **Masks, in the array algorithm.**  As in :func:`jaxslam.filters.ekf.update`, an invalid
  component ``j`` gets a zero row of ``H``, a zero innovation and a unit ``R`` block (zero
  cross terms).  The factor ``L_R`` of that masked ``R`` then has unit row and column ``j``
  (Cholesky keeps the block structure), so row ``j`` of the pre-array is the unit vector
  ``e_j``.  Householder QR leaves such a row and column untouched (its reflectors have a
  zero in that position), so ``S^½`` has unit row/column ``j`` and column ``j`` of ``K̄``
  is ``P Hᵀ S^{-½ᵀ} e_j = P H_jᵀ = 0``: the update equals the update with the valid rows
  only.  The structure is also written explicitly after the QR (unit row/column of
  ``S^½``, zero gain column), so it holds exactly on any backend.  The measurement of an
  invalid component is replaced by its prediction *before* the residual is formed, so
  NaN/Inf garbage there never reaches the arithmetic (nor its gradient).
* **Noise covariances are given as covariances** (like :mod:`jaxslam.filters.ekf`) and
  factored inside: ``R`` per update (its masked version changes with the mask) by
  Cholesky, so ``R`` must be positive definite on the valid block (:func:`filter_scan`
  refuses a concrete one that is not with an :class:`InputError` naming ``R``; otherwise the
  update reports ``errors.NOT_PSD`` and keeps the prior, where the covariance form would
  accept a singular ``R`` when ``H P Hᵀ`` is PD); ``Q`` and covariances passed to
  :func:`from_gaussian` by :func:`psd_factor` (Cholesky, with an eigen-decomposition
  fallback for singular PSD matrices such as ``Q = diag(q, q, 0)``).  A concrete (non-traced)
  covariance is factored on the host in float64 before the cast to the filter's dtype, so a
  float32 filter starts from the most accurate float32 factor.  :func:`predict` and
  :func:`filter_scan` also accept ``Q_chol=``, any ``(·, k)`` square root ``C`` with
  ``Q = C Cᵀ``, which skips the factorisation; :func:`filter_scan` factors ``Q`` once for
  the whole run.
* **Gating and failures** follow :func:`jaxslam.filters.ekf.update`: the NIS is compared
  with a number or ``gate(dof)``; a gated update keeps the prior and sets
  ``errors.GATED``.  If the factor of ``S`` is not finite or has a zero diagonal (``S``
  singular) the prior is kept and ``errors.NOT_PSD`` is set; if the posterior is not
  finite, ``errors.NON_FINITE``.  A NaN/Inf in the pre-array's inputs (the prior factor,
  ``H``, ``R``'s valid block) is ``NON_FINITE`` only, as in the covariance forms
  (:func:`jaxslam.filters.gaussian.failure_status`; it used to be ``NOT_PSD`` only here and
  ``NOT_PSD | NON_FINITE`` there).  ``UpdateInfo.accepted`` is True exactly when the state
  changed.
* ``filter_scan`` ordering and outputs follow :func:`jaxslam.filters.ekf.filter_scan`
  (``predict_first``); the variances ``cov_diags`` are the squared row norms of ``L``.  A
  non-finite prediction adds ``errors.NON_FINITE`` to the status of the step whose prior it
  is, and is skipped, as in every Gaussian run (:mod:`jaxslam.filters.gaussian`): that step
  keeps the belief the predict started from and makes no update (NIS 0); the NaN factor used
  to be carried to the end of the run.
  A finite ``P0`` or ``Q`` that cannot be factored (indefinite; refused up front when known,
  traced otherwise) makes a NaN factor before the scan: the steps that meet it report
  ``NOT_PSD`` instead, as the covariance forms do for such an input.
* dtype: every function computes in the dtype of the mean; ``Q``, ``R``, ``z`` and the
  factor are cast to it.

Cost: the update QR is of an (m + n) square matrix, O((m + n)³), against the covariance
form's O(n² m); worth it where the float32 covariance form is not reliable, or where the
factor itself is wanted (sampling, log-determinants).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..errors import InputError, check_flag
from ..compilation import call_compiled
from ..linalg import (check_finite, check_numbers, check_psd, is_concrete, list_array, symmetrize,
                      value_and_jacfwd)
from .ekf import Gaussian, UpdateInfo
from .gaussian import (call_residual, check_gate, check_gate_size, check_leading, check_measurement, check_noise_values,
                       check_update_call, check_fits_dtype, check_run_inputs, check_run_numbers, check_run_q_size,
                       noise_size, run_dtype,
                       check_process_noise, check_transition_out, check_update_args, moment_dtype,
                       scalar_measurement, single_variance, state_pair, gate_test, failure_status)

__all__ = [
    "SqrtGaussian",
    "SqrtPosterior",
    "filter_scan",
    "from_gaussian",
    "predict",
    "psd_factor",
    "to_gaussian",
    "update",
]

Array = Any
Gate = None | float | Array | Callable[[Array], Array]

_HAS_LOGDET = "logdet" in UpdateInfo._fields
_HIGHEST = jax.lax.Precision.HIGHEST


def _mm(a, b):
    """Matrix product at full working precision (no TF32/bf16 passes on accelerators)."""
    return jnp.matmul(a, b, precision=_HIGHEST)


class SqrtGaussian(NamedTuple):
    """A Gaussian belief held as a Cholesky factor.

    Fields:
        mean: (n,) state mean, in the units of the model's state.
        chol: (n, n) lower-triangular ``L`` with non-negative diagonal, ``P = L Lᵀ``.
    """

    mean: Array  # (n,)
    chol: Array  # (n, n)


class SqrtPosterior(NamedTuple):
    """Output of :func:`filter_scan` over T steps.

    Fields:
        means: (T, n) filtered means.
        cov_diags: (T, n) diagonals of the filtered covariances (squared row norms of ``L``).
        chols: (T, n, n) filtered factors when ``save_chol=True``, else None.
        nis: (T,) NIS of each step's update (0 when nothing was valid).
        dof: (T,) int32 number of valid measurement components per step.
        status: (T,) int32 status bit flags per step (:mod:`jaxslam.errors`).
        final: :class:`SqrtGaussian` after the last step.
    """

    means: Array
    cov_diags: Array
    chols: Array | None
    nis: Array
    dof: Array
    status: Array
    final: SqrtGaussian


# ---------------------------------------------------------------------------
# Factors
# ---------------------------------------------------------------------------

def _sign_fix(R):
    """Negate the rows of an upper-triangular ``R`` whose diagonal is negative."""
    d = jnp.diagonal(R)
    return R * jnp.where(d < 0, -1, 1).astype(R.dtype)[:, None]


def _tria(A):
    """Lower-triangular ``B`` (n, n), diagonal ≥ 0, with ``B Bᵀ = A Aᵀ``; ``A`` is (n, k).

    One QR of ``Aᵀ = Θ U`` gives ``A Aᵀ = Uᵀ U``, so ``B = Uᵀ`` (sign-fixed).
    """
    n, k = A.shape
    At = A.T
    if k < n:  # a wide pre-array: pad with zero columns (rows of Aᵀ), same Gram matrix
        At = jnp.concatenate([At, jnp.zeros((n - k, n), A.dtype)], axis=0)
    U = jnp.linalg.qr(At, mode="r")
    return _sign_fix(U).T


def _tria_np(A):
    n, k = A.shape
    At = A.T if k >= n else np.concatenate([A.T, np.zeros((n - k, n))], axis=0)
    U = np.linalg.qr(At, mode="r")
    d = np.diagonal(U)
    return (U * np.where(d < 0, -1.0, 1.0)[:, None]).T


def _clip_tol(n, dtype):
    """Relative size of the negative eigenvalues that count as rounding: 10 n eps."""
    return 10.0 * n * float(jnp.finfo(dtype).eps)


def psd_factor(A, dtype=None):
    """Lower-triangular factor ``L`` (diagonal ≥ 0) of a symmetric PSD matrix, ``A = L Lᵀ``.

    Cholesky when ``A`` is positive definite.  A singular PSD ``A`` (Cholesky fails: a
    zero pivot) is factored from its eigen-decomposition ``V diag(w) Vᵀ`` as the
    triangularisation of ``V diag(√w)``; eigenvalues in ``[−10 n eps |w|_max, 0)``
    (rounding) count as 0, a more negative one (``A`` indefinite) or a NaN/Inf entry gives a
    NaN factor, which the next update reports (``errors.NON_FINITE``: the factor it meets is
    NaN; ``NOT_PSD`` in the runs, where the factored matrix was finite) rather than hiding.

    Args:
        A: (n, n) symmetric positive semi-definite matrix (it is symmetrised first).
        dtype: dtype of the result; default ``A``'s floating dtype.

    Returns:
        (n, n) lower-triangular factor.  A concrete ``A`` is factored on the host in
        float64 (NumPy) and cast; a traced one with ``jnp.linalg.cholesky`` and, only when
        that fails, ``eigh`` (``lax.cond``).  Gradients are those of the Cholesky factor
        for a positive definite ``A``.  Through a singular ``A`` they are not reliable
        (``eigh``'s derivative is singular at repeated eigenvalues, as in
        ``diag(q, q, 0)``): to differentiate with respect to a singular process noise,
        pass its square root as ``Q_chol`` (e.g. ``exp(θ / 2) · C``).
    """
    return _root(A, dtype, triangular=True)


def _root_np(A, dtype):
    """:func:`psd_factor` of a concrete ``A`` on the host, in float64 (NumPy; ``dtype``, the run's,
    sets only the rounding tolerance of a singular ``A``'s eigenvalues)."""
    M = np.asarray(A, dtype=np.float64)
    M = 0.5 * (M + M.T)
    n = M.shape[0]
    if not np.all(np.isfinite(M)):
        return np.full((n, n), np.nan)
    try:
        return np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(M)
        if w.size and w.min() < -_clip_tol(n, dtype) * np.max(np.abs(w)):
            return np.full((n, n), np.nan)
        return _tria_np(V * np.sqrt(np.clip(w, 0.0, None)))


def _root(A, dtype=None, triangular=True):
    """``psd_factor``; with ``triangular=False`` a singular ``A`` gives ``V diag(√w)``."""
    if dtype is None:
        dt = jnp.asarray(A).dtype
        dtype = dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)
    if is_concrete(A):
        return jnp.asarray(_root_np(A, dtype).astype(dtype))

    M = symmetrize(jnp.asarray(A, dtype))
    n = M.shape[0]
    finite = jnp.all(jnp.isfinite(M))  # a NaN/Inf entry gives a NaN factor, never a silent 0
    ok = jnp.all(jnp.isfinite(jnp.linalg.cholesky(M)))
    # Under vmap the cond becomes a select that evaluates both branches; each branch gets a
    # harmless input where it is not the one chosen, so no NaN/inf reaches the other's
    # gradient (eigh's derivative is singular at repeated eigenvalues, Cholesky's at a
    # singular matrix, √w's at w = 0).
    eye = jnp.eye(n, dtype=dtype)
    spread = jnp.diag(jnp.arange(1, n + 1, dtype=dtype))

    def chol_factor(M):
        return jnp.linalg.cholesky(jnp.where(ok, M, eye))

    def eig_factor(M):
        w, V = jnp.linalg.eigh(jnp.where(ok | ~finite, spread, M))
        bad = (jnp.min(w) < -_clip_tol(n, dtype) * jnp.max(jnp.abs(w))) | ~finite
        pos = w > 0
        B = V * jnp.where(pos, jnp.sqrt(jnp.where(pos, w, 1.0)), 0.0)
        if triangular:
            B = _tria(B)
        return jnp.where(bad, jnp.nan, B)

    return jax.lax.cond(ok, chol_factor, eig_factor, M)


def _noise_root(Q, Q_chol, dtype):
    """A square root ``C`` of the process noise, ``Q = C Cᵀ``, in ``dtype``: ``Q_chol`` as given,
    else :func:`_root` of ``Q`` (not triangularised; a concrete one factored on the host in
    float64 before the cast), one per matrix of a per-step (T, q, q) ``Q``.  Shared by the
    predicts and runs of this module and :mod:`jaxslam.filters.sqrt_ukf`."""
    if Q_chol is not None:
        return jnp.asarray(Q_chol, dtype)
    if Q is None:
        raise InputError("Q: a process-noise covariance (or Q_chol=) is required")
    if np.ndim(Q) == 3:
        if is_concrete(Q) and np.finfo(dtype).bits < 64:
            # each factored as given, then cast, as a single Q is (a float32 run factored the
            # rounded matrices in float32: a per-step Q of T equal matrices gave other numbers
            # than the one matrix); in float64 the cast changes nothing and the program is kept
            return jnp.asarray(np.stack([_root_np(q, dtype) for q in np.asarray(Q, np.float64)]).astype(dtype))
        return jax.vmap(lambda q: _root(q, dtype, triangular=False))(jnp.asarray(Q, dtype))
    return _root(Q, dtype, triangular=False)


def _unfactored(covs, roots):
    """True when a finite covariance of ``covs`` got a NaN root in ``roots`` (:func:`psd_factor`
    of an indefinite matrix, or of a traced one, before the scan): the runs then meet a NaN
    factor at every step from the one that uses it, and :func:`_as_not_psd` says ``NOT_PSD``
    for those steps, as the covariance filters do for such an input.  A pair with ``None`` is
    skipped; concrete values are judged on the host (no eager JAX operation)."""
    out = False
    for A, L in zip(covs, roots):
        if A is None:
            continue
        if is_concrete(A) and is_concrete(L):
            out = out or bool(np.all(np.isfinite(np.asarray(A, np.float64)))
                              and not np.all(np.isfinite(np.asarray(L, np.float64))))
        else:
            out = jnp.logical_or(out, jnp.all(jnp.isfinite(jnp.asarray(A))) & ~jnp.all(jnp.isfinite(L)))
    return jnp.asarray(out)


def _as_not_psd(status, unfactored):
    """The steps' ``status`` with ``NON_FINITE`` read as ``NOT_PSD`` where a finite P0 or Q could
    not be factored (:func:`_unfactored`): the NaN those steps met is the factor's, and the rule of
    the Gaussian filters (:func:`jaxslam.filters.gaussian.failure_status`) calls a finite
    covariance that fails to factor ``NOT_PSD``."""
    nf = jnp.int32(errors.NON_FINITE)
    return jnp.where(unfactored & ((status & nf) != 0), (status & ~nf) | jnp.int32(errors.NOT_PSD), status)


def _kept(status, pred, prior):
    """``pred``, or ``prior`` where a run's predict failed (``status`` not 0): the belief a failed
    predict started from is handed on, and the step it fed makes no update
    (:func:`jaxslam.filters.gaussian.make_step`: the rule of every Gaussian run; the NaN used to
    be carried to every later step)."""
    ok = status == 0
    return SqrtGaussian(jnp.where(ok, pred.mean, prior.mean), jnp.where(ok, pred.chol, prior.chol))


def check_state(state, name: str = "state") -> SqrtGaussian:
    """A square-root belief as one step reads it: ``mean`` (n,) and ``chol`` (n, n) (shapes are
    static, so this is free under ``jit``) and, when the factor is known now (an eager call),
    its values: finite (the mean too, when known now), lower-triangular (the update's
    triangular solves read only the lower triangle, so an entry above the diagonal was
    silently dropped), diagonal ≥ 0.  Raises
    :class:`InputError` naming ``name.mean`` / ``name.chol`` (a mismatch used to end in a
    concatenate or broadcast error).  An integer mean is promoted to the factor's floating
    dtype (the default float when that is an integer too), and the factor is returned in the
    mean's dtype, as :func:`jaxslam.filters.gaussian.check_state` does for a covariance."""
    x, L = state_pair(state, name, "chol")
    x, L = jnp.asarray(x), jnp.asarray(L)
    x_dt = moment_dtype(x, L, f"{name}.mean", f"{name}.chol")
    n = x.shape[0]
    check_finite(x, f"{name}.mean")
    if is_concrete(L):
        A = check_numbers(L, f"{name}.chol")
        if not np.all(np.isfinite(A)):
            raise InputError(f"{name}.chol: contains NaN or Inf")
        scale = max(1.0, float(np.max(np.abs(A)))) if A.size else 1.0
        if n > 1 and np.max(np.abs(np.triu(A, 1))) > 1e-12 * scale:
            raise InputError(f"{name}.chol: expected a lower-triangular factor L (P = L Lᵀ), got non-zero "
                             "entries above the diagonal")
        if n and np.min(np.diagonal(A)) < 0:
            raise InputError(f"{name}.chol: expected a factor with a non-negative diagonal, got "
                             f"{np.min(np.diagonal(A)):.3g} on it")
    return SqrtGaussian(jnp.asarray(x, x_dt), jnp.asarray(L, x_dt))


def from_gaussian(g: Gaussian) -> SqrtGaussian:
    """:class:`SqrtGaussian` of a :class:`~jaxslam.filters.ekf.Gaussian` (``psd_factor`` of its cov).

    An empty state (n = 0) is refused (:class:`InputError` naming ``g.mean``).
    """
    x = jnp.asarray(g.mean)
    n = x.shape[0] if x.ndim == 1 else None
    if n is None or np.shape(g.cov) != (n, n):
        raise InputError(f"g: expected an (n,) mean and an (n, n) cov, got {tuple(x.shape)} and {np.shape(g.cov)}")
    if n == 0:  # ended in NumPy's "cannot reshape array of size 0" (check_psd)
        raise InputError("g.mean: expected a state of at least one component, got shape (0,)")
    dtype = x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    check_finite(x, "g.mean")
    if is_concrete(g.cov):  # known now: refuse a NaN, asymmetric or indefinite cov (beyond
        check_psd(g.cov, "g.cov")  # check_psd's tolerance; a float32 cov just inside it may still factor to NaN)
    return SqrtGaussian(x.astype(dtype), psd_factor(g.cov, dtype))


def to_gaussian(s: SqrtGaussian) -> Gaussian:
    """:class:`~jaxslam.filters.ekf.Gaussian` with ``cov = L Lᵀ`` (symmetrised)."""
    L = jnp.asarray(s.chol)
    return Gaussian(s.mean, symmetrize(_mm(L, L.T)))


# ---------------------------------------------------------------------------
# Predict
# ---------------------------------------------------------------------------

def predict(state: SqrtGaussian, f: Callable, u, Q=None, *args, noise_jac=None,
            Q_chol=None) -> SqrtGaussian:
    """Square-root time update: ``x' = f(x, u, *args)``, ``L' L'ᵀ = F P Fᵀ + G Q Gᵀ``.

    ``F = ∂f/∂x`` at the prior mean (``jax.jacfwd``, one trace of ``f``).  The new factor
    is the triangularisation (one QR, diagonal made non-negative) of the n × (n + k)
    pre-array ``[F L, G C]``, ``C`` a square root of ``Q``; ``P`` is never formed.

    Args:
        state: prior :class:`SqrtGaussian`, mean (n,), chol (n, n) lower-triangular with a
            non-negative diagonal (:func:`check_state`: :class:`InputError` naming
            ``state.mean`` / ``state.chol``; values only when concrete).
        f: discrete transition ``f(x (n,), u, *args) -> (n,)`` over one step (it integrates
            the dynamics; a continuous model must be discretised by the caller), or None for
            a state that does not move (``L' L'ᵀ = P + G Q Gᵀ``).
        u: control/input of the step (any pytree).
        Q: (n, n) discrete process-noise covariance, or (q, q) with ``noise_jac``; factored
            here by :func:`psd_factor` (Cholesky; singular PSD allowed); a concrete one is
            checked (:class:`InputError` naming ``Q``).  Ignored when ``Q_chol`` is given
            (pass None).
        *args: extra arguments of ``f`` (and of a callable ``noise_jac``).
        noise_jac: None, an (n, q) matrix ``G``, or a callable ``G(x, u, *args) -> (n, q)``
            evaluated at the prior mean.
        Q_chol: optional (n, k) (or (q, k) with ``noise_jac``) square root ``C`` of the
            process noise, ``Q = C Cᵀ``; need not be triangular.  A concrete one must be
            finite (:class:`InputError` naming ``Q_chol``).

    Returns:
        Predicted :class:`SqrtGaussian` in the dtype of ``state.mean``.  Called eagerly it is
        compiled once per model (:func:`jaxslam.compilation.call_compiled`; a concrete ``Q`` is
        still factored on the host in float64 first).
    """
    state = check_state(state)  # the values known now (the compiled step sees them traced)
    C = None
    if Q_chol is None and Q is not None:
        check_noise_values(Q, "Q")
        C = _host_root(Q, state.mean.dtype)
    elif Q_chol is not None and is_concrete(Q_chol) and not np.all(np.isfinite(check_numbers(Q_chol, "Q_chol"))):
        # as filter_scan and sqrt_ukf.predict: a NaN root used to give a silent NaN factor
        raise InputError("Q_chol: contains NaN or Inf")
    Q, Q_chol = list_array(Q, "Q"), list_array(Q_chol, "Q_chol")  # lists would reach the program as tracers

    def step(opts, state, Q, Q_chol, C):
        u, a, nj = opts
        return _predict(state, f, u, Q, a, nj, Q_chol, C)

    return call_compiled(("sqrt_ekf.predict", f), step, (state, Q, Q_chol, C), (u, args, noise_jac), after=2)


def _host_root(Q, dtype):
    """:func:`_noise_root` of a concrete square ``Q`` (factored on the host in float64), else None."""
    if not is_concrete(Q):
        return None
    if np.ndim(Q) < 2 and np.size(Q) == 1:  # the variance of a single noise input (check_process_noise)
        Q = np.reshape(check_numbers(Q, "Q"), (1, 1))
    if np.ndim(Q) != 2 or np.shape(Q)[0] != np.shape(Q)[1]:
        return None
    return _root(Q, dtype, triangular=False)


def _predict(state, f, u, Q, args, noise_jac, Q_chol, C):
    """:func:`predict`'s computation (its checks of shapes; ``C``: the root of ``Q`` when known)."""
    x, L = check_state(state)
    dtype = x.dtype
    n = x.shape[0]
    G = None
    if noise_jac is not None:
        G = jnp.asarray(noise_jac(x, u, *args) if callable(noise_jac) else noise_jac, dtype)
    if Q_chol is None and Q is not None:
        # the shapes (noise_jac's too) and, in an eager call, the values, as ekf.predict
        Q = check_process_noise(Q, n, G)
    if G is not None and (G.ndim != 2 or G.shape[0] != n):
        raise InputError(f"noise_jac: expected shape ({n}, q) (the state's size rows), got {tuple(G.shape)}")
    q = n if G is None else G.shape[1]
    if Q_chol is not None and (np.ndim(Q_chol) != 2 or np.shape(Q_chol)[0] != q):
        rows = "the state's size" if G is None else "noise_jac's columns"
        raise InputError(f"Q_chol: expected shape ({q}, k) ({rows}), got {tuple(np.shape(Q_chol))}")
    if f is None:  # a state that does not move: x' = x, F = I
        xn, F = x, jnp.eye(x.shape[0], dtype=dtype)
    else:
        xn, F = value_and_jacfwd(lambda v: jnp.asarray(f(v, u, *args)))(x)
        check_transition_out(xn, n)
    xn = xn.astype(dtype)
    F = F.astype(dtype)
    C = _noise_root(Q, Q_chol, dtype) if C is None else jnp.asarray(C, dtype)
    if G is not None:
        C = _mm(G, C)
    return SqrtGaussian(xn, _tria(jnp.concatenate([_mm(F, L), C], axis=1)))


# ---------------------------------------------------------------------------
# Update
# ---------------------------------------------------------------------------

def _default_residual(z, zhat):
    return z - zhat


def update(
    state: SqrtGaussian,
    z,
    h: Callable,
    R,
    *args,
    residual: Callable | None = None,
    mask=None,
    gate: Gate = None,
):
    """Square-root measurement update with masks and a chi-square gate.

    ``ẑ = h(x, *args)``, ``H = ∂h/∂x`` (``jax.jacfwd``), ``ν = residual(z, ẑ)``.  One QR
    of the (m + n) square pre-array ``[[L_R, H L], [0, L]]`` gives ``[[S^½, 0], [K̄, L⁺]]``
    (module docstring): ``S = S^½ S^½ᵀ = H P Hᵀ + R``, ``w = S^{-½} ν``,
    ``x⁺ = x + K̄ w``, ``L⁺ L⁺ᵀ = P − K S Kᵀ``, NIS ``= ‖w‖²``.  Same semantics as
    :func:`jaxslam.filters.ekf.update`.

    Args:
        state: prior :class:`SqrtGaussian`, mean (n,), chol (n, n) lower-triangular with a
            non-negative diagonal (:func:`check_state`: :class:`InputError` naming
            ``state.mean`` / ``state.chol``; values only when concrete).
        z: (m,) measurement, in the units of ``h``'s output.
        h: measurement model ``h(x (n,), *args) -> (m,)``.
        R: (m, m) measurement-noise covariance, positive definite (factored here by
            Cholesky); a concrete one is checked (:class:`InputError` naming ``R``, as
            :func:`jaxslam.filters.sqrt_ukf.update`), a traced one that fails to factor on
            the valid block is reported as ``errors.NOT_PSD``.
        *args: extra arguments of ``h``.
        residual: ``residual(z, ẑ) -> (m,)``; default ``z − ẑ``
            (:func:`jaxslam.filters.ekf.angle_residual` for angles).
        mask: (m,) bool, True for valid components (default all valid).  Invalid
            components contribute nothing, whatever ``z`` holds there.
        gate: None, a chi-square threshold on the NIS, or a callable
            ``gate(dof) -> threshold`` (:func:`jaxslam.filters.ekf.chi2_gate`).  When the
            NIS exceeds it the prior is kept and ``errors.GATED`` is set.  A concrete gate must
            be a positive number (:class:`InputError`); a traced one that is not > 0 (NaN
            included) gates the update and also sets ``errors.NON_FINITE``.

    Returns:
        ``(posterior SqrtGaussian, UpdateInfo)``; ``UpdateInfo.S`` is ``S^½ S^½ᵀ`` (identity
        on invalid rows/columns) and, where the field exists, ``logdet`` is
        ``log det S`` over the valid block (``2 Σ log diag S^½``).  On a singular or
        non-finite ``S^½`` (``NOT_PSD``) or a non-finite posterior (``NON_FINITE``) the prior
        is returned unchanged.  Called eagerly it is compiled once per model
        (:func:`jaxslam.compilation.call_compiled`).
    """
    state, z, R, mask = check_update_call(state, z, R, mask, gate, check_state)  # the values known now

    def step(opts, state, z, R, mask):
        a, g = opts
        return _update(state, z, h, R, *a, residual=residual, mask=mask, gate=g)

    return call_compiled(("sqrt_ekf.update", h, residual), step, (state, z, R, mask), (args, gate), after=2)


def _update(state, z, h, R, *args, residual=None, mask=None, gate: Gate = None):
    """:func:`update`'s computation (shape checks; values are checked by the caller)."""
    x, L = check_state(state)
    dtype = x.dtype
    check_update_args(z, R, mask)
    z, h = scalar_measurement(z, h)
    z = jnp.asarray(z, dtype=dtype)
    R = jnp.asarray(R, dtype=dtype)
    m = z.shape[-1]
    n = x.shape[0]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    res = _default_residual if residual is None else residual
    zero = jnp.zeros((), dtype)
    eye_m = jnp.eye(m, dtype=dtype)

    zhat, H = value_and_jacfwd(lambda v: jnp.asarray(h(v, *args)))(x)
    check_measurement(z, zhat, R, mask)
    check_gate(gate)
    check_gate_size(gate, m, mask)
    zhat = zhat.astype(dtype)
    H = H.astype(dtype)
    # Replace invalid components by their prediction before differencing so NaN garbage
    # never enters the arithmetic (nor its gradient).
    zhat_safe = jnp.where(mask, zhat, zero)
    z_safe = jnp.where(mask, z, zhat_safe)
    nu = jnp.where(mask, call_residual(res, z_safe, zhat_safe), zero)
    Hm = jnp.where(mask[:, None], H, zero)
    mm = mask[:, None] & mask[None, :]
    L_R = jnp.linalg.cholesky(symmetrize(jnp.where(mm, R, eye_m)))
    dof = jnp.sum(mask).astype(jnp.int32)

    pre = jnp.block([[L_R, _mm(Hm, L)], [jnp.zeros((n, m), dtype), L]])
    B = _tria(pre)
    S_half = jnp.where(mm, B[:m, :m], eye_m)  # exact mask structure (module docstring)
    Kbar = jnp.where(mask[None, :], B[m:, :m], zero)
    L_post = B[m:, m:]

    d = jnp.diagonal(S_half)
    ok = jnp.all(jnp.isfinite(S_half)) & jnp.all(d > 0)
    S_safe = jnp.where(ok, S_half, eye_m)  # no inf/NaN on the rejected path (nor its grad)
    w = jax.scipy.linalg.solve_triangular(S_safe, nu, lower=True)
    nis = jnp.where(ok, jnp.dot(w, w), zero)  # a failed factor is NOT_PSD, never GATED
    x_post = x + _mm(Kbar, w)
    S = symmetrize(_mm(S_half, S_half.T))

    g_status = jnp.int32(0)
    if gate is None:
        gated = jnp.asarray(False)
    else:  # a traced threshold that is not > 0 (NaN) gates the update and flags NON_FINITE
        gated, g_status = gate_test(gate, nis, dof, dtype)
    finite = jnp.all(jnp.isfinite(x_post)) & jnp.all(jnp.isfinite(L_post))
    # a NaN/Inf in the pre-array's inputs (the prior factor, H, R's valid block) is NON_FINITE,
    # not NOT_PSD: the rule of the covariance filters (gaussian.failure_status)
    finite_in = (jnp.all(jnp.isfinite(L)) & jnp.all(jnp.isfinite(Hm))
                 & jnp.all(jnp.isfinite(jnp.where(mm, R, eye_m))))
    has = dof > 0
    accepted = has & ~gated & ok & finite
    i32 = jnp.int32
    status = (
        jnp.where(gated, i32(errors.GATED), i32(0))
        | failure_status(has & ~gated, ok, finite_in, finite)
        | g_status
    )
    post = SqrtGaussian(jnp.where(accepted, x_post, x), jnp.where(accepted, L_post, L))
    extra = {}
    if _HAS_LOGDET:
        pos = mask & (d > 0)
        logd = jnp.where(pos, jnp.log(jnp.where(pos, d, jnp.ones((), dtype))), zero)
        logd = jnp.where(mask & ~(d > 0) & ~jnp.isnan(d), -jnp.inf, logd)
        logd = jnp.where(mask & jnp.isnan(d), jnp.nan, logd)
        extra["logdet"] = 2.0 * jnp.sum(logd)
    return post, UpdateInfo(nis, dof, nu, S, accepted, status, **extra)


# ---------------------------------------------------------------------------
# Whole run
# ---------------------------------------------------------------------------

def _validate_scan(x0, P0, us, zs, masks, Q, R, noise_jac, Q_chol):
    """Shapes always (they are static under jit); values only when concrete.  What every
    Gaussian filter's run checks (``x0``, ``P0``, ``zs``, ``masks``, ``R``, a ``Q`` given as a
    covariance: :func:`jaxslam.filters.gaussian.check_run_inputs`), then this filter's own:
    ``us``, ``noise_jac``, ``Q_chol`` and ``Q``'s size and presence."""
    n = np.shape(x0)[0] if np.ndim(x0) == 1 else None
    T, _ = check_run_inputs(x0, P0, zs, masks, Q if Q_chol is None else None, R, q_optional=True)
    check_leading(us, T, "us")
    q = n
    if noise_jac is not None and not callable(noise_jac):
        gs = np.shape(noise_jac)
        if len(gs) != 2 or gs[0] != n:
            raise InputError(f"noise_jac: expected shape ({n}, q), got {tuple(gs)}")
        q = gs[1]
    if Q_chol is not None:
        cs = np.shape(Q_chol)
        if len(cs) != 2 or (noise_jac is None and cs[0] != n) or (
                noise_jac is not None and not callable(noise_jac) and cs[0] != q):
            raise InputError(f"Q_chol: expected shape ({'q' if noise_jac is not None else n}, k), "
                             f"got {tuple(cs)}")
        check_run_numbers(Q_chol, "Q_chol")
        check_finite(Q_chol, "Q_chol")
        # as given: the cast to x0's dtype would turn 1e200 into inf (every step then failed)
        check_fits_dtype(Q_chol, "Q_chol", run_dtype(x0), variances=False)
        return
    if Q is None:
        raise InputError("Q: a process-noise covariance (or Q_chol=) is required")
    # squareness, the per-step count and the values: check_run_inputs; the size here (a scalar
    # or (1,) Q: the variance of a single noise input, as in predict), in every run's words
    check_run_q_size(Q, *noise_size(x0, noise_jac), T)


def filter_scan(
    f: Callable,
    h: Callable,
    x0,
    P0,
    us,
    zs,
    masks,
    Q,
    R,
    *args,
    residual: Callable | None = None,
    gate: Gate = None,
    predict_first: bool = True,
    noise_jac=None,
    save_chol: bool = False,
    Q_chol=None,
) -> SqrtPosterior:
    """Run square-root predict + update over a whole sequence as one ``lax.scan``.

    Step t (``predict_first=True``): :func:`predict` with ``u_t``, then :func:`update` with
    ``z_t`` under ``masks[t]``; ``(x0, P0)`` is the estimate before the first control.
    With ``predict_first=False`` the step updates with ``z_t`` first (``(x0, P0)`` is the
    prior at the time of ``z_0``), stores the filtered estimate, then predicts with ``u_t``.
    ``P0`` and ``Q`` are factored once, before the scan (:func:`psd_factor`).  Jit it with
    ``f``, ``h``, ``residual``, a callable ``gate``, ``noise_jac`` if callable,
    ``predict_first`` and ``save_chol`` static; vmap it over runs.  Called eagerly it is
    compiled once per model (:func:`jaxslam.compilation.call_compiled`).

    Inputs are checked at this boundary (``InputError`` naming the argument): shapes
    always, finiteness and definiteness (``P0``, ``Q`` PSD, ``R`` PD) when the values are
    concrete (not traced).

    Args:
        f: transition ``f(x, u, *args) -> (n,)``, or None (the state does not move).
        h: measurement model ``h(x, *args) -> (m,)``.
        x0: (n,) initial mean, n >= 1.  P0: (n, n) initial covariance (PSD).
        us: controls with leading axis T (array or pytree; None if unused).
        zs: (T, m) measurements, m >= 1.
        masks: (T, m) bool validity (None: all valid).
        Q: (n, n) (or (q, q) with ``noise_jac``) process-noise covariance (PSD), one per
            step (T, n, n) (each factored before the scan), or None with ``Q_chol``; a scalar
            is the variance of a single noise input (n = 1, or q = 1), as in :func:`predict`.
        R: (m, m) measurement-noise covariance (PD), or one per step (T, m, m); a scalar is the
            variance of the one measurement when m = 1.
        *args: shared extra arguments of both ``f`` and ``h``.
        residual, gate: as in :func:`update`.
        predict_first: static; step order (above).
        noise_jac: as in :func:`predict`.
        save_chol: static; also stack the filtered factors (T, n, n).
        Q_chol: optional square root of ``Q`` (as in :func:`predict`).

    Returns:
        :class:`SqrtPosterior` in the dtype of ``x0``.  A failed (non-finite) prediction is
        skipped: the step it fed keeps the belief the predict started from and makes no update
        (NIS 0; module docstring).  A concrete ``zs`` entry in use that ``x0``'s dtype cannot
        hold is an :class:`InputError` naming ``zs[t]``; a concrete per-step ``Q`` is factored
        on the host in float64 before the cast, as a single ``Q`` and ``P0`` are.
    """
    predict_first = check_flag(predict_first, "predict_first")
    save_chol = check_flag(save_chol, "save_chol")
    _validate_scan(x0, P0, us, zs, masks, Q, R, noise_jac, Q_chol)
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    x0 = x0.astype(dtype)
    L0 = psd_factor(P0, dtype)
    q_step = Q_chol is None and np.ndim(Q) == 3
    if Q_chol is None and np.ndim(Q) < 2:  # the variance of a single noise input (_validate_scan)
        Q = single_variance(Q)
    C = _noise_root(Q, Q_chol, dtype)
    zs = jnp.asarray(zs, dtype=dtype)
    R = jnp.asarray(R, dtype=dtype)
    R = R.reshape(1, 1) if R.ndim < 2 else R  # a scalar: the variance of one measurement (m = 1)
    r_step = R.ndim == 3
    T, m = zs.shape
    masks = jnp.ones((T, m), bool) if masks is None else jnp.asarray(masks, bool)

    check_gate(gate)  # the value known now, checked now: the compiled run sees it traced
    unf = _unfactored((P0, None if Q_chol is not None else Q), (L0, C))

    def scan(opts, x0, L0, C, us, zs, masks, R, unf):
        args, gate, noise_jac = opts

        def pred(s, u, c):
            return predict(s, f, u, None, *args, noise_jac=noise_jac, Q_chol=c)

        def upd(s, z, mk, r):
            return update(s, z, h, r, *args, residual=residual, mask=mk, gate=gate)

        def pred_status(s):
            # a non-finite prediction (NaN/Inf from f or a traced noise) is NON_FINITE, as in
            # ekf.filter_scan (the step's update says so too: a NaN prior factor is NON_FINITE)
            finite = jnp.all(jnp.isfinite(s.mean)) & jnp.all(jnp.isfinite(s.chol))
            return jnp.where(finite, jnp.int32(0), jnp.int32(errors.NON_FINITE))

        def step(carry, inp):
            # the flag goes to the step whose prior the predict made: this one with
            # predict_first, else the next (``pending``)
            state, _, pending = carry
            u, z, mk, c, r = inp
            c = c if q_step else C
            r = r if r_step else R
            # the step whose prior a failed predict made keeps its belief and makes no update
            # (gaussian.make_step, the rule of every Gaussian run); selected after the update
            if predict_first:
                prior = pred(state, u, c)
                p_status = pred_status(prior)
                post, info = upd(prior, z, mk, r)
                post = nxt = _kept(p_status, post, state)
            else:
                p_status = pending
                post, info = upd(state, z, mk, r)
                post = _kept(p_status, post, state)
                nxt = pred(post, u, c)
                pending = pred_status(nxt)
                nxt = _kept(pending, nxt, post)
            info = info._replace(nis=jnp.where(p_status != 0, jnp.zeros_like(info.nis), info.nis))
            out = (
                post.mean,
                jnp.sum(post.chol * post.chol, axis=1),
                post.chol if save_chol else None,
                info.nis,
                info.dof,
                info.status | p_status,
            )
            return (nxt, post, pending), out

        init = SqrtGaussian(x0, L0)
        (_, final, _), (means, diags, chols, nis, dof, status) = jax.lax.scan(
            step, (init, init, jnp.zeros((), jnp.int32)),
            (us, zs, masks, C if q_step else None, R if r_step else None)
        )
        return SqrtPosterior(means, diags, chols, nis, dof, _as_not_psd(status, unf), final)

    # called eagerly: compiled once per model, options and shapes
    return call_compiled(("sqrt_ekf.filter_scan", f, h, residual, predict_first, save_chol, q_step, r_step),
                         scan, (x0, L0, C, us, zs, masks, R, unf), (args, gate, noise_jac))
