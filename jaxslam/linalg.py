"""Numerically careful linear algebra shared by every filter.

Covariance hygiene (STYLE.md): symmetrise after updates, Cholesky-based solves
(never an explicit inverse), the factored Joseph form, and angle wrapping for
residuals.  All functions are pure, jit/vmap-safe and follow their inputs'
dtype.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .errors import InputError

__all__ = [
    "is_concrete",
    "value_and_jacfwd",
    "symmetrize",
    "wrap_angle",
    "chol_solve",
    "safe_norm",
    "check_psd",
    "check_shape",
]


def value_and_jacfwd(fun, argnums=0):
    """``fun``'s value and forward-mode Jacobian from one trace of ``fun``.

    ``value_and_jacfwd(f, argnums)(*args) -> (f(*args), jacfwd(f, argnums)(*args))``, but
    ``f`` is traced once (its primal comes out of the forward pass as ``has_aux``), where
    calling ``f`` and ``jax.jacfwd(f)`` separately traces, lowers and compiles it twice.
    """

    def wrapped(*args):
        def both(*a):
            y = fun(*a)
            return y, y

        jac, val = jax.jacfwd(both, argnums=argnums, has_aux=True)(*args)
        return val, jac

    return wrapped


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


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm with a finite gradient at 0 (the gradient there is 0)."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    nonzero = sq > 0
    safe_sq = jnp.where(nonzero, sq, 1.0)
    return jnp.where(nonzero, jnp.sqrt(safe_sq), 0.0)


# ---------------------------------------------------------------------------
# Host-side validation (raise InputError before jit)
# ---------------------------------------------------------------------------

def check_shape(x, shape, name: str):
    """Raise InputError unless ``x`` has ``shape`` (``None`` entries match any size)."""
    xs = np.shape(x)
    if len(xs) != len(shape) or any(s is not None and s != a for s, a in zip(shape, xs)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{name}: expected shape {want}, got {tuple(xs)}")
    return x


def check_psd(M, name: str, strict: bool = False, tol: float = 1e-12):
    """Raise InputError unless ``M`` is a finite symmetric PSD (PD if strict) matrix."""
    A = np.asarray(M, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise InputError(f"{name}: expected a square matrix, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise InputError(f"{name}: contains NaN or Inf")
    scale = max(1.0, float(np.max(np.abs(A)))) if A.size else 1.0
    if not np.allclose(A, A.T, atol=1e-9 * scale, rtol=0):
        raise InputError(f"{name}: not symmetric")
    w = np.linalg.eigvalsh(0.5 * (A + A.T)) if A.size else np.zeros(0)
    lo = w.min() if w.size else 0.0
    if strict and lo <= tol * scale:
        raise InputError(f"{name}: not positive definite (smallest eigenvalue {lo:.3g})")
    if lo < -tol * scale:
        raise InputError(f"{name}: not positive semi-definite (smallest eigenvalue {lo:.3g})")
    return M


def is_concrete(*xs) -> bool:
    """True when no leaf of ``xs`` is a tracer: the values are known now, so a helper can build
    its result on the host (NumPy) instead of compiling a tiny program op by op."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))
