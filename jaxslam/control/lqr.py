"""Continuous-time algebraic Riccati equation and LQR gain in JAX, with implicit derivatives.

Paper 000, eq. 10-13: the LQR of the flat model minimises ∫ r̃ᵀQ̃r̃ + ũᵀR̃ũ dt; its gain is
K = R̃⁻¹BᵀP̃ with P̃ the stabilising solution of AᵀP + PA − PBR⁻¹BᵀP + Q = 0.

Forward solver (no SciPy at run time):

1. Matrix sign function of the Hamiltonian H = [[A, −G], [−Q, −Aᵀ]], G = BR⁻¹Bᵀ (R⁻¹ by
   Cholesky), by the scaled Newton iteration Z ← (cZ + (cZ)⁻¹)/2 with determinant scaling
   c = |det Z|^(−1/2n), in a ``lax.while_loop`` (at most 100 iterations, stop when the relative
   change is below 10·2n·eps).  The stable invariant subspace [I; P] gives P from the
   consistent overdetermined system [W12; W22 + I] P = −[W11 + I; W21] (least squares).
2. Two Newton–Kleinman refinement steps from that (stabilising) P:
   (A − GP)ᵀP⁺ + P⁺(A − GP) + Q + PGP = 0, which restore full working precision.

Lyapunov equations are solved by a Kronecker-product linear system of size n² (LU), adequate
for the small state dimensions here (n ≲ 30; the paper's n = 7 costs a 49×49 solve).

Derivatives: :func:`care` is a ``jax.custom_jvp``.  Differentiating the CARE at the solution
gives the Lyapunov equation A_clᵀ dP + dP A_cl + C = 0, A_cl = A − GP,
C = dQ + dAᵀP + P dA − (P dB K + Kᵀ dBᵀ P − Kᵀ dR K), K = R⁻¹BᵀP.  The tangent is linear in
(dA, dB, dQ, dR) and built from transposable operations, so forward *and* reverse mode work
(reverse by JAX's transposition of the linear solve); the iterations are never differentiated.

Decisions:

* Only the symmetric parts of Q and R enter the cost, so :func:`care` symmetrises both first;
  derivatives with respect to a non-symmetric perturbation are therefore well defined (they are
  those of the symmetric part), which makes finite-difference checks meaningful.
* Failure is reported, not hidden: with ``return_status=True`` a boolean ``ok`` is returned,
  False when P is non-finite, the relative CARE residual exceeds √eps, P is not positive
  semi-definite (the stabilising solution is the unique PSD one for stabilisable (A, B) and
  detectable (A, Q)), or the closed loop A − B K is not Hurwitz (:func:`is_hurwitz`; with
  Q = 0 and an unstable A, P = 0 solves the CARE but stabilises nothing).  A non-finite P (and
  a non-finite gain K, from a singular traced R) is replaced by zeros so no NaN propagates; a
  Newton–Kleinman refinement step is kept only while P stays positive semi-definite.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..compilation import call_compiled
from ..dynamics._checks import real_numbers
from ..errors import InputError
from ..linalg import check_psd, check_real, check_shape, is_concrete, symmetrize

__all__ = ["care", "lqr_gain", "lyapunov", "is_hurwitz", "validate_weights"]

_MAX_SIGN_ITER = 100
_NEWTON_STEPS = 2


def lyapunov(A, C):
    """Solve Aᵀ X + X A + C = 0 for X (n, n) by a Kronecker linear system of size n².

    ``A``: (n, n), ``C``: (n, n).  Unique when no two eigenvalues of A sum to zero (true for
    Hurwitz A).  Linear in C (transposable), used for the CARE refinement and its derivative.
    """
    sa = tuple(np.shape(A))
    if len(sa) != 2 or sa[0] != sa[1] or tuple(np.shape(C)) != sa:
        raise InputError(f"A, C: expected two square matrices of one size, got {sa} and {tuple(np.shape(C))}")
    check_real(A, "A")
    check_real(C, "C")
    A, C = jnp.asarray(A), jnp.asarray(C)  # nested lists had no .shape / .T
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    # Row-major vec: vec(AᵀX) = (Aᵀ ⊗ I) vec X, vec(XA) = (I ⊗ Aᵀ) vec X.
    M = jnp.kron(A.T, eye) + jnp.kron(eye, A.T)
    return jnp.linalg.solve(M, -C.reshape(n * n)).reshape(n, n)


def _gain_matrix(B, R):
    """R⁻¹Bᵀ (m, n) through a Cholesky factor of R."""
    L = jnp.linalg.cholesky(R)
    return jsl.cho_solve((L, True), B.T)


def _sign_solve(A, G, Q):
    """Stabilising CARE solution from the matrix sign function of the Hamiltonian."""
    n = A.shape[0]
    dtype = A.dtype
    eps = jnp.finfo(dtype).eps
    H = jnp.block([[A, -G], [-Q, -A.T]])
    tol = 10.0 * (2 * n) * eps

    def cond(state):
        _, k, rel = state
        return (k < _MAX_SIGN_ITER) & (rel > tol)

    def body(state):
        Z, k, _ = state
        # The sign-function Newton step Z ← (cZ + (cZ)⁻¹)/2 needs the inverse itself of the
        # (non-symmetric) Hamiltonian iterate; no covariance is inverted here.
        Zi = jnp.linalg.inv(Z)
        _, logdet = jnp.linalg.slogdet(Z)
        c = jnp.exp(-logdet / (2 * n))
        c = jnp.where(jnp.isfinite(c), c, 1.0)
        Zn = 0.5 * (c * Z + Zi / c)
        rel = jnp.sum(jnp.abs(Zn - Z)) / jnp.maximum(jnp.sum(jnp.abs(Zn)), jnp.finfo(dtype).tiny)
        return Zn, k + 1, rel

    W, _, _ = jax.lax.while_loop(cond, body, (H, jnp.asarray(0), jnp.asarray(jnp.inf, dtype)))
    eye = jnp.eye(n, dtype=dtype)
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + eye], axis=0)
    rhs = -jnp.concatenate([W[:n, :n] + eye, W[n:, :n]], axis=0)
    P = jnp.linalg.lstsq(lhs, rhs)[0]
    return symmetrize(P)


def _care_solve(A, B, Q, R):
    G = B @ _gain_matrix(B, R)
    P = _sign_solve(A, G, Q)
    for _ in range(_NEWTON_STEPS):
        Acl = A - G @ P
        Pn = symmetrize(lyapunov(Acl, Q + P @ G @ P))
        # A Newton-Kleinman step from a P whose closed loop is not stable converges to another,
        # indefinite solution of the CARE (float32, a weight near zero: the sign iteration's P
        # inaccurate in one block, and the steps turned a decoupled gain destabilising); the
        # stabilising solution is the PSD one, so a step is kept only while it stays PSD.
        e = jnp.linalg.eigvalsh(jnp.where(jnp.all(jnp.isfinite(Pn)), Pn, 0.0))
        keep = jnp.all(jnp.isfinite(Pn)) & (e[0] >= -jnp.sqrt(jnp.finfo(P.dtype).eps) * jnp.abs(e[-1]))
        P = jnp.where(keep, Pn, P)
    return P


@jax.custom_jvp
def _care(A, B, Q, R):
    return _care_solve(A, B, Q, R)


@_care.defjvp
def _care_jvp(primals, tangents):
    A, B, Q, R = primals
    dA, dB, dQ, dR = tangents
    P = _care(A, B, Q, R)
    RiBt = _gain_matrix(B, R)
    K = RiBt @ P
    Acl = A - B @ K
    C = dQ + dA.T @ P + P @ dA - (P @ dB @ K + K.T @ dB.T @ P - K.T @ dR @ K)
    dP = lyapunov(Acl, C)
    return P, dP


def _status(A, B, Q, R, P):
    """ok flag: finite, small relative residual, PSD, stabilising (see module docstring)."""
    A, B, Q, R, P = (jax.lax.stop_gradient(x) for x in (A, B, Q, R, P))
    dtype = P.dtype
    eps = jnp.finfo(dtype).eps
    G = B @ _gain_matrix(B, R)
    AP = A.T @ P
    PGP = P @ G @ P
    res = AP + AP.T - PGP + Q
    fro = jnp.linalg.norm
    scale = fro(Q) + 2.0 * fro(AP) + fro(PGP)
    rel = fro(res) / jnp.maximum(scale, jnp.finfo(dtype).tiny)
    finite = jnp.all(jnp.isfinite(P))
    Ps = jnp.where(finite, P, 0.0)
    lam_min = jnp.linalg.eigvalsh(Ps)[0]
    psd = lam_min >= -jnp.sqrt(eps) * jnp.maximum(jnp.max(jnp.abs(Ps)), 1.0)
    # The closed loop A − GP must be Hurwitz (the *stabilising* solution): with Q = 0 and an
    # unstable A, P = 0 solves the CARE with no residual but stabilises nothing.
    return finite & (rel <= jnp.sqrt(eps)) & psd & is_hurwitz(A - G @ Ps)


def is_hurwitz(A):
    """() bool: every eigenvalue of the square ``A`` has a negative real part.  Lyapunov's test:
    the solution X of AᵀX + XA = −I is finite and positive definite (no ``eig``, which has no
    GPU kernel; one n²×n² solve).  Held constant under differentiation; jit- and vmap-safe."""
    A = jax.lax.stop_gradient(jnp.asarray(A))
    X = symmetrize(lyapunov(A, jnp.eye(A.shape[-1], dtype=A.dtype)))
    ok = jnp.all(jnp.isfinite(X))
    return ok & (jnp.linalg.eigvalsh(jnp.where(ok, X, 0.0))[0] > 0)


# Called on concrete matrices (a scenario's gains, computed on the host) the solver's while
# loop would be traced again at every call; jitted, it is traced once per shape and dtype
# (inside another trace it is inlined as before).
_care_jit = jax.jit(_care)


def _check_shapes(A, B, Q, R):
    """Static shapes of a CARE: A (n, n), B (n, m), Q (n, n), R (m, m) (free under ``jit``);
    :class:`InputError` naming the argument."""
    sa, sb = tuple(np.shape(A)), tuple(np.shape(B))
    if len(sa) != 2 or sa[0] != sa[1]:
        raise InputError(f"A: expected a square (n, n) matrix, got shape {sa}")
    n = sa[0]
    if len(sb) != 2 or sb[0] != n:
        raise InputError(f"B: expected shape ({n}, m) (A's rows), got {sb}")
    m = sb[1]
    for M, nm, k in ((Q, "Q", n), (R, "R", m)):
        if tuple(np.shape(M)) != (k, k):
            raise InputError(f"{nm}: expected shape ({k}, {k}), got {tuple(np.shape(M))}")


def care(A, B, Q, R, *, return_status: bool = False):
    """Stabilising solution P of AᵀP + PA − PBR⁻¹BᵀP + Q = 0; paper 000 eq. 13.

    ``A``: (n, n), ``B``: (n, m), ``Q``: (n, n) symmetric PSD, ``R``: (m, m) symmetric PD
    (only their symmetric parts are used).  Returns P (n, n) in the common dtype of the inputs;
    with ``return_status=True`` returns ``(P, ok)`` where ``ok`` is a boolean scalar (False on
    non-convergence, P then zeroed if non-finite).  Differentiable in A, B, Q and R, forward
    and reverse mode, by implicit differentiation.  Jit/vmap-safe; validate weights on the host
    with :func:`validate_weights`.  Called eagerly it is compiled once per shape and dtype
    (:func:`jaxslam.compilation.call_compiled`; the status and the gain op by op made a first
    ``dflqr.gain`` take 2.3 s).
    """
    A, B, Q, R = _checked(A, B, Q, R)
    return call_compiled(("lqr.care", bool(return_status)), lambda *m: _care_full(*m, return_status),
                         (A, B, Q, R), after="auto")


def _checked(A, B, Q, R):
    """:func:`care`'s checks (shapes; values when known now) and the four matrices in their
    common floating dtype."""
    _check_shapes(A, B, Q, R)
    for M, nm in ((A, "A"), (B, "B"), (Q, "Q"), (R, "R")):
        check_real(M, nm, allow_bool=False)  # static dtype: complex lost its imaginary part
    if is_concrete(A, B):  # a NaN or Inf in A or B used to give P = K = 0 silently
        for M, nm in ((A, "A"), (B, "B")):
            if not np.all(np.isfinite(real_numbers(M, nm))):
                raise InputError(f"{nm}: contains NaN or Inf")
    if is_concrete(Q, R):  # values known now (an eager call): a NaN Q used to give K = 0, P = 0
        validate_weights(Q, R)
    dtype = jnp.result_type(A, B, Q, R)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return tuple(jnp.asarray(x, dtype) for x in (A, B, Q, R))


def _care_full(A, B, Q, R, return_status: bool):
    Q = symmetrize(Q)
    R = symmetrize(R)
    P = _care_jit(A, B, Q, R)
    finite = jnp.all(jnp.isfinite(P))
    P = jnp.where(finite, P, jnp.zeros_like(P))
    if return_status:
        return P, _status(A, B, Q, R, P)
    return P


def lqr_gain(A, B, Q, R, *, return_status: bool = False):
    """Continuous-time LQR gain K = R⁻¹BᵀP and Riccati matrix P; paper 000 eq. 12-13.

    Shapes as in :func:`care`; returns ``(K (m, n), P (n, n))`` (plus ``ok`` with
    ``return_status=True``).  The optimal feedback is ũ = −K r̃.  Differentiable in A, B, Q, R.
    Called eagerly it is compiled once per shape and dtype, as :func:`care`.
    """
    A, B, Q, R = _checked(A, B, Q, R)
    return call_compiled(("lqr.lqr_gain", bool(return_status)), lambda *m: _lqr_gain(*m, return_status),
                         (A, B, Q, R), after="auto")


def _lqr_gain(A, B, Q, R, return_status: bool):
    out = _care_full(A, B, Q, R, return_status)
    P = out[0] if return_status else out
    dtype = P.dtype
    R = symmetrize(jnp.asarray(R, dtype))
    K = _gain_matrix(jnp.asarray(B, dtype), R) @ P
    # a traced R that is singular or indefinite: its Cholesky factor is NaN, so K is too, while P
    # was zeroed — zeros, as P, and ok False (no NaN reaches the controller)
    K_ok = jnp.all(jnp.isfinite(K))
    K = jnp.where(K_ok, K, jnp.zeros_like(K))
    if return_status:
        return K, P, out[1] & K_ok
    return K, P


def validate_weights(Q, R, n=None, m=None, names=("Q", "R")):
    """Host-side check of LQR weights (raise :class:`jaxslam.errors.InputError`).

    ``Q`` must be a finite symmetric PSD (n, n) matrix and ``R`` a finite symmetric PD (m, m)
    matrix; ``n`` / ``m`` (optional) fix the expected sizes.  ``names`` are used in the
    messages (e.g. ``("Q_tilde", "R_tilde")``).  Returns ``(Q, R)`` unchanged.
    """
    qn, rn = names
    for M, nm, size in ((Q, qn, n), (R, rn, m)):
        check_real(M, nm, allow_bool=False)
        if np.ndim(M) != 2:
            raise InputError(f"{nm}: expected a square matrix, got shape {np.shape(M)}")
        if size is not None:
            check_shape(M, (size, size), nm)
    check_psd(Q, qn, strict=False)
    check_psd(R, rn, strict=True)
    return Q, R
