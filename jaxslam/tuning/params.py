"""Unconstrained parametrisations of covariance (and weight) matrices.

Gradient descent works on an unconstrained vector θ; the matrix it stands for is
positive definite for every θ, so no step can leave the feasible set and no
projection or clipping of eigenvalues is ever needed.

* **log-diagonal** (n parameters): M = diag(exp θ).  For diagonal noise (the papers'
  tables are all diagonal) and LQR weights.  Adam's steps are then relative changes of
  each variance, which suits variances spanning many decades (paper 000's Table 7 Q is
  10³-10⁷ times the IMU-derived one).
* **log-Cholesky** (n(n+1)/2 parameters): M = L Lᵀ with L = diag(exp θ_diag) · C, C unit
  lower triangular with strictly lower part θ_off (row-major order of
  ``numpy.tril_indices(n, -1)``).  L is lower triangular with a positive diagonal, and
  every symmetric positive-definite M has exactly one such factor (the Cholesky factor),
  so the map is a bijection onto the PD cone and round trips are exact up to rounding.

Decisions (no paper covers tuning):

* A zero variance (Table 7's P0, an IMU density of 0) has no logarithm.  The
  constructors raise :class:`~jaxslam.errors.InputError` on a matrix they cannot represent
  (a non-positive diagonal entry; a matrix that is not positive definite) unless a finite
  ``floor`` > 0 is given, which the two forms apply differently: the log-diagonal form raises
  only the entries below ``floor`` to it (the others are kept exactly), the log-Cholesky form
  adds ``floor``·I to the whole matrix, a positive-definite one included (every eigenvalue
  moves up by ``floor``).  The shift is intended: a matrix has no "entries below the floor"
  that could be raised alone without breaking its positive definiteness or changing its
  eigenvectors, and M + floor·I is the nearest lift that keeps them.  It is harmless for a
  *starting point* (the optimiser may drive the matrix back down as far as it likes, and no
  target of this package passes a floor), but it changes a PD M by floor relative to its
  smallest eigenvalue: give the log-Cholesky form a floor only for a semi-definite M, well
  below the eigenvalues that matter.
* The off-diagonal parameters are those of the *unit* factor C (L_ij = exp(θ_ii) θ_ij),
  not the raw entries of L: they are dimensionless, so one Adam step changes a correlation
  by the same relative amount whatever the units of M.  With raw entries (the textbook
  log-Cholesky), a step of 0.1 on an entry of a factor whose diagonal is 0.2 rotated the
  matrix by tens of percent, and NLL tuning of a correlated R fell into a degenerate local
  minimum (a near-singular R with a spurious correlation) that the scaled form avoids.
* Functions follow the dtype of their input; the host-side constructors (``*_from_*``)
  validate with NumPy and return arrays in the requested dtype.

:class:`CovSpec` names one tuned matrix (its parametrisation and size), so a target can
hold several (e.g. Q and R) in a dict pytree of θ vectors, which optax handles directly.
"""

from __future__ import annotations

import warnings

from typing import Mapping, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import check_float_dtype, check_int, check_numbers, check_psd, check_scalar, float_array, reworded

__all__ = [
    "CovSpec",
    "n_params",
    "log_diag_from_cov",
    "cov_from_log_diag",
    "log_chol_from_cov",
    "cov_from_log_chol",
    "theta_from_cov",
    "cov_from_theta",
    "pack",
    "unpack",
]

KINDS = ("diag", "chol")


class CovSpec(NamedTuple):
    """A tuned symmetric positive-definite matrix (static: hashable, not traced).

    kind: ``"diag"`` (log-diagonal, n parameters) or ``"chol"`` (log-Cholesky,
      n(n+1)/2 parameters).
    n: matrix size.
    """

    kind: str
    n: int


def _check_kind(kind):
    if kind not in KINDS:
        raise InputError(f"kind: expected one of {KINDS}, got {kind!r}")


def _check_spec(spec) -> None:
    """InputError unless ``spec`` is a CovSpec-like (kind, n) with a known kind and an int n ≥ 1."""
    if not isinstance(spec, CovSpec):
        raise InputError(f"spec: expected a CovSpec(kind, n), got {spec!r}")
    _check_kind(spec[0])
    check_int(spec[1], "n", lower=1, what="a matrix size (int)")


def n_params(spec: CovSpec) -> int:
    """Number of unconstrained parameters of ``spec``."""
    _check_spec(spec)
    return spec.n if spec.kind == "diag" else spec.n * (spec.n + 1) // 2


def _as_matrix(M, name):
    a = check_numbers(M, name)
    if a.ndim == 1:
        a = np.diag(a)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise InputError(f"{name}: expected a square matrix or a vector of diagonal values, got shape {a.shape}")
    if a.size == 0:  # (log-Cholesky failed with a bare ValueError; no CovSpec has n = 0)
        raise InputError(f"{name}: expected a matrix of size n >= 1, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or Inf")
    return a


def _check_floor(floor) -> float:
    """``floor`` as a float when it is a finite number > 0, else InputError naming ``floor``
    (an infinite floor made θ infinite)."""
    return reworded(lambda: check_scalar(floor, "floor", lower=0, strict=True),
                    f"floor: must be > 0 and finite, got {floor!r}")


def _check_dtype(dtype):
    """``dtype`` (None: JAX's default float, resolved now — float32 without x64 — so that the
    range check of :func:`_check_exp_range` is that of the dtype θ gets) when it names a floating
    dtype, else InputError naming ``dtype``: an integer dtype truncated θ (log 3 became 1), a
    bogus name gave a bare TypeError."""
    return jnp.dtype(jnp.result_type(float)) if dtype is None else check_float_dtype(dtype)


def _check_names(arg: str, given, specs, what: str) -> None:
    """InputError naming ``arg`` unless ``given`` is a dict whose names are ``specs``' (a list
    gave a bare TypeError; a misspelt or extra name was silently ignored)."""
    if not isinstance(given, Mapping):
        raise InputError(f"{arg}: expected a dict {{name: {what}}}, got {type(given).__name__}")
    extra = sorted(set(given) - set(specs), key=str)
    if extra:
        raise InputError(f"{arg}: unknown name(s) {extra}; the specs name {sorted(specs, key=str)}")


def log_diag_from_cov(M, floor: float | None = None, dtype=None, name: str = "M"):
    """θ (n,) = log diag(M) for a diagonal matrix (or a vector of variances).

    Off-diagonal entries of ``M`` are dropped (the parametrisation has none), with a
    ``UserWarning`` naming ``name`` when one is not negligible (above 1e-12 of the largest
    diagonal entry); entries ≤ 0 raise :class:`InputError` naming ``name`` unless ``floor`` > 0
    is given, which replaces every diagonal entry below it (the others are kept).  Host-side
    (NumPy in, ``dtype`` out: a floating dtype — an integer one would truncate θ —; default:
    JAX's default float dtype, as ``jnp.asarray`` gives it).
    """
    dtype = _check_dtype(dtype)
    a = _as_matrix(M, name)
    off = np.abs(a - np.diag(np.diag(a)))
    if off.size and off.max() > 1e-12 * max(np.abs(np.diag(a)).max(), np.finfo(float).tiny):
        warnings.warn(f"{name}: the log-diagonal parametrisation drops the off-diagonal entries "
                      f"(largest |{name}_ij| = {off.max():.3g}); use CovSpec('chol', n) to keep them",
                      UserWarning, stacklevel=2)
    d = np.diag(a).copy()
    if floor is not None:
        d = np.maximum(d, _check_floor(floor))
    if np.any(d <= 0):
        raise InputError(f"{name}: log-diagonal parametrisation needs positive diagonal entries, "
                         f"got {d.tolist()} (pass floor=... to start zero entries at a small value)")
    _check_exp_range(np.log(d), dtype, name)
    return jnp.asarray(np.log(d), dtype)


def _check_exp_range(log_values, dtype, name: str) -> None:
    """:class:`InputError` naming ``name`` when a log-variance's exp is 0 or inf in ``dtype``
    (its matrix would be singular or infinite: float32 holds ~1e-38 to ~3e38)."""
    ft = np.finfo(np.dtype(dtype))
    lo, hi = np.log(ft.tiny), np.log(ft.max)
    bad = (log_values < lo) | (log_values > hi)
    if np.any(bad):
        v = float(np.exp(log_values[np.argmax(bad)]))
        raise InputError(f"{name}: a variance of {v:.3g} is outside {np.dtype(dtype).name}'s range "
                         f"({ft.tiny:.3g} to {ft.max:.3g}): its matrix would be singular or infinite")


def cov_from_log_diag(theta):
    """M = diag(exp θ) (n, n); positive definite for every θ (n,) whose exp neither underflows
    nor overflows in its dtype (|θ| below ~87 in float32, ~708 in float64)."""
    theta = float_array(theta, "theta")
    if theta.ndim != 1:  # jnp.diag of a matrix would return its diagonal, not a matrix
        raise InputError(f"theta: expected a vector (n,) of log-variances, got shape {tuple(theta.shape)}")
    return jnp.diag(jnp.exp(theta))


def _tril(n):
    return np.tril_indices(n, -1)


def log_chol_from_cov(M, floor: float | None = None, dtype=None, name: str = "M"):
    """θ (n(n+1)/2,) = [log diag L, strictly-lower C] of M's Cholesky factor L = diag(L) C.

    ``M`` must be symmetric positive definite (a float32 ``M`` symmetric to 100 ulp of float32,
    as :func:`~jaxslam.linalg.check_psd` allows, is symmetrised first).  With ``floor`` > 0 the factor is that of
    M + floor·I — *always*, a positive-definite M included (every eigenvalue moves up by
    ``floor``; module docstring): it lets a semi-definite M (a zero variance) start, and should
    be small against the eigenvalues that matter.  ``dtype``: a floating dtype, as
    :func:`log_diag_from_cov`.  Raises :class:`InputError` naming ``name``.
    """
    dtype = _check_dtype(dtype)
    a = _as_matrix(M, name)
    n = a.shape[0]
    src = np.asarray(M).dtype
    if src.kind == "f" and src.itemsize < 8:
        # a float32 M symmetric to its own precision (100 ulp, as linalg.check_psd allows a
        # float32 input) is symmetrised: its float64 copy failed check_psd's 1e-9 as "not symmetric"
        mag = np.abs(a).max()
        if np.abs(a - a.T).max() <= 100 * np.finfo(src).eps * mag:
            a = 0.5 * (a + a.T)
    if floor is not None:
        a = a + _check_floor(floor) * np.eye(n)
    check_psd(a, name, strict=True)
    L = np.linalg.cholesky(0.5 * (a + a.T))
    r, c = _tril(n)
    C = L / np.diag(L)[:, None]
    _check_exp_range(2 * np.log(np.diag(L)), dtype, name)  # (the variances of the factor's diagonal)
    return jnp.asarray(np.concatenate([np.log(np.diag(L)), C[r, c]]), dtype)


def cov_from_log_chol(theta, n: int):
    """M = L Lᵀ, L = diag(exp θ_d) C (n, n) from θ (n(n+1)/2,); PD for every θ whose exp
    neither underflows nor overflows in its dtype (|θ_d| below ~43 in float32, ~354 in float64)."""
    n = check_int(n, "n", lower=1, what="a matrix size (int)")
    theta = float_array(theta, "theta")
    if tuple(theta.shape) != (n * (n + 1) // 2,):
        raise InputError(f"theta: expected shape ({n * (n + 1) // 2},) for n = {n}, got {tuple(theta.shape)}")
    r, c = _tril(n)
    C = jnp.eye(n, dtype=theta.dtype).at[r, c].set(theta[n:])
    L = jnp.exp(theta[:n])[:, None] * C
    return L @ L.T


def theta_from_cov(spec: CovSpec, M, floor: float | None = None, dtype=None, name: str = "M"):
    """θ for ``spec`` from a matrix (host-side; see the two constructors)."""
    _check_spec(spec)
    a = _as_matrix(M, name)
    if a.shape != (spec.n, spec.n):
        raise InputError(f"{name}: expected shape ({spec.n}, {spec.n}), got {a.shape}")
    if spec.kind == "diag":
        return log_diag_from_cov(a, floor, dtype, name)
    return log_chol_from_cov(M, floor, dtype, name)  # M itself: its float32 dtype has a say


def cov_from_theta(spec: CovSpec, theta):
    """The matrix of θ under ``spec`` (jit/vmap/grad-safe; dtype of θ).  θ must hold
    :func:`n_params` entries (a static check: :class:`InputError` naming ``theta``)."""
    k = n_params(spec)
    theta = float_array(theta, "theta")
    if tuple(np.shape(theta)) != (k,):
        raise InputError(f"theta: CovSpec({spec.kind!r}, {spec.n}) needs shape ({k},), got "
                         f"{tuple(np.shape(theta))}")
    if spec.kind == "diag":
        return cov_from_log_diag(theta)
    return cov_from_log_chol(theta, spec.n)


def pack(specs: dict, mats: dict, floors: dict | None = None, dtype=None) -> dict:
    """{name: θ} for {name: CovSpec} and {name: matrix} (host-side).

    ``specs``, ``mats`` and ``floors`` (optional, {name: floor} for some of the names) are
    dicts over the same names: a missing matrix, or a name of ``mats`` / ``floors`` that no
    spec has (a typo), is an :class:`InputError` naming the argument.
    """
    if not isinstance(specs, Mapping):
        raise InputError(f"specs: expected a dict {{name: CovSpec}}, got {type(specs).__name__}")
    _check_names("mats", mats, specs, "matrix")
    floors = {} if floors is None else floors
    _check_names("floors", floors, specs, "floor")
    dtype = _check_dtype(dtype)
    missing = set(specs) - set(mats)
    if missing:
        raise InputError(f"mats: no matrix for {sorted(missing)}")
    return {k: theta_from_cov(s, mats[k], floors.get(k), dtype, name=k) for k, s in specs.items()}


def unpack(specs: dict, thetas: dict) -> dict:
    """{name: matrix} for {name: CovSpec} and {name: θ} (jit/grad-safe).  ``thetas`` must be a
    dict over exactly ``specs``' names (a missing or an unknown name: :class:`InputError`)."""
    if not isinstance(specs, Mapping):
        raise InputError(f"specs: expected a dict {{name: CovSpec}}, got {type(specs).__name__}")
    _check_names("thetas", thetas, specs, "θ vector")
    missing = set(specs) - set(thetas)
    if missing:
        raise InputError(f"thetas: no parameters for {sorted(missing)}")
    return {k: cov_from_theta(s, thetas[k]) for k, s in specs.items()}
