"""Gaussian filtering, the part every Gaussian filter shares: beliefs, the masked
correction, and one runner over a whole sequence.

The extended (:mod:`jaxslam.filters.ekf`) and sigma-point
(:mod:`jaxslam.filters.ukf`) filters differ only in how they compute the
predicted moments and the measurement moments.  What follows is common to both
and lives here once:

* **Beliefs and diagnostics**: :class:`Gaussian`, :class:`UpdateInfo`.
* **The masked, gated correction** from a prior ``(x, P)``, an innovation ``ν``,
  the cross-covariance ``C = Cov(x, z)`` and the innovation covariance
  ``S = Cov(z) + R`` (:func:`innovation_solve`, :func:`finalize`): invalid
  components get a zero row of ``C``, a zero innovation and a unit row/column of
  ``S``, so their gain columns are exactly zero; the NIS and ``log det S`` are
  taken over the valid block (identity elsewhere contributes 0 to both).
* **A filter as two functions** (:class:`GaussianFilter`, the
  ``init/update`` pair of optax or cuthbert's ``Filter`` object): ``predict(state,
  u, Q) -> (Gaussian, cross)`` with ``cross = Cov(x_prev, x_pred)`` and
  ``update(state, z, mask, R, c) -> (Gaussian, UpdateInfo)`` with ``c`` the
  step's input of the measurement model (or None).  :func:`run` drives either
  through one ``lax.scan``; :mod:`jaxslam.filters.smoother` consumes what it saves.

Decisions
---------
* Step order is an explicit, static argument of :func:`run`: ``predict_first=True``
  predicts with ``u_t`` then updates with ``z_t`` (``(x0, P0)`` is the belief
  *before* the first input); ``predict_first=False`` updates with ``z_t`` first
  (``(x0, P0)`` is the prior at the time of ``z_0``), stores the filtered
  belief, then predicts with ``u_t``.
* Per-step noise: ``Q`` may be ``(n, n)`` (or ``(q, q)``) or one matrix per step,
  ``(T, n, n)``; ``R`` likewise ``(m, m)`` or ``(T, m, m)``.  The choice is made
  from the rank, which is static under ``jit``.
* The per-step log-likelihood ``−½ (νᵀ S⁻¹ ν + log det S + d log 2π)`` is over
  the valid components (``d`` of them) and is reported whether or not the gate
  then rejected the update (it is the model's density of what was measured).
* Saved outputs are selectable: the diagonals of the filtered covariances
  always; full filtered covariances with ``save_cov``; the predicted moments and
  cross-covariances with ``save_smoother`` (what the RTS smoother needs).  With
  ``predict_first=False`` the entry ``t`` of the predicted moments is the prior
  that step ``t`` updated, and ``cross_covs[0]`` is zero (no prediction made it).
* A failed prediction (``NOT_PSD`` / ``NON_FINITE`` in the predict's status: a NaN/Inf, a
  negative predicted variance, a negative variance in a traced ``Q``) is skipped, in every
  filter's run (:func:`make_step`; the square-root runs follow the same rule): the belief it
  started from is handed on, and the step whose prior it was to be makes no update (its prior
  is unknown): that step's filtered moments are the belief it started from, its saved
  predicted moments too (cross-covariance its covariance), its NIS 0, its status the predict's
  bits and its log-likelihood NaN; the next step goes on from there.  The EKF's run used to
  carry the NaN (or negative variance) to every later step, and the sigma-point runs updated
  the previous step's belief with this step's ``z``.
"""

from __future__ import annotations

import weakref
from typing import Any, Callable, NamedTuple, Optional, Union

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import at_top_level, call_compiled, split_arrays
from ..errors import InputError, check_flag
from ..linalg import (check_finite, check_mask, check_numbers, check_psd, check_real, host_array, is_concrete, list_array,
                      symmetrize, to_jax)

__all__ = [
    "Gaussian",
    "UpdateInfo",
    "Posterior",
    "GaussianFilter",
    "run",
    "keyed_filter",
    "innovation_solve",
    "finalize",
    "failure_status",
    "masked_innovation",
    "threshold",
    "gate_test",
    "check_state",
    "state_pair",
    "check_gate",
    "check_gate_size",
    "call_residual",
    "check_num_iter",
    "predicted_status",
    "negative_variance",
    "check_noise_values",
    "check_update_args",
    "check_predict_call",
    "check_update_call",
    "scalar_measurement",
    "check_process_noise",
    "check_transition_out",
    "process_noise",
    "check_measurement",
    "check_real",
    "LOG_2PI",
]

Array = Any
Gate = Union[None, float, Array, Callable[[Array], Array]]
LOG_2PI = float(np.log(2.0 * np.pi))


class Gaussian(NamedTuple):
    """A Gaussian belief.

    Fields:
        mean: (n,) state mean, in the units of the model's state.
        cov: (n, n) symmetric positive semi-definite covariance.
    """

    mean: Array  # (n,)
    cov: Array  # (n, n)


class UpdateInfo(NamedTuple):
    """Diagnostics of one update (or, from a batch update, per measurement).

    Fields:
        nis: () normalised innovation squared ``νᵀ S⁻¹ ν`` over the valid
            components (0 when none is valid).
        dof: () int32, number of valid components (the NIS degrees of freedom).
        innovation: (m,) residual ``ν`` (0 on invalid components).
        S: (m, m) innovation covariance on the valid block, identity on invalid
            rows/columns.
        accepted: () bool, True when the update changed the state.
        status: () int32 bit flags from :mod:`jaxslam.errors` (``GATED``,
            ``NOT_PSD``, ``NON_FINITE``, ``NOT_CONVERGED``).
        logdet: () ``log det S`` over the valid block (0 when none is valid or
            the factorisation failed); None in a user-written filter's info:
            :func:`step_log_likelihood` then takes it from ``S``.
    """

    nis: Array
    dof: Array
    innovation: Array
    S: Array
    accepted: Array
    status: Array
    logdet: Array = None


class Posterior(NamedTuple):
    """Output of a whole run (:func:`run`, ``ekf.filter_scan``, ``ukf.filter_scan``).

    Fields:
        means: (T, n) filtered means.
        cov_diags: (T, n) diagonals of the filtered covariances (variances).
        covs: (T, n, n) filtered covariances (``save_cov`` or ``save_smoother``), else None.
        nis: (T,) NIS of each step's update (0 when nothing was valid).
        dof: (T,) int32 number of valid measurement components per step.
        status: (T,) int32 status bit flags per step.
        final: :class:`Gaussian` after the last step (full covariance).
        log_likelihood: (T,) per-step innovation log-likelihood (0 when nothing
            was valid, NaN where the update failed: see :func:`step_log_likelihood`);
            its sum is the marginal log-likelihood of the run.
        pred_means: (T, n) predicted means (``save_smoother``), else None.
        pred_covs: (T, n, n) predicted covariances (``save_smoother``), else None.
        cross_covs: (T, n, n) ``Cov(x_{t−1|t−1}, x_{t|t−1})`` of the prediction that
            produced ``pred_*[t]`` (``save_smoother``), else None.
    """

    means: Array
    cov_diags: Array
    covs: Optional[Array]
    nis: Array
    dof: Array
    status: Array
    final: Gaussian
    log_likelihood: Array = None
    pred_means: Optional[Array] = None
    pred_covs: Optional[Array] = None
    cross_covs: Optional[Array] = None


class GaussianFilter(NamedTuple):
    """A Gaussian filter as two pure functions (closures over the model).

    ``predict(state, u, Q) -> (Gaussian, cross)`` or ``(Gaussian, cross, status)``:
    time update with the step's input ``u`` and process noise ``Q``; ``cross`` (n, n)
    is ``Cov(x, x')`` of the prior and the predicted state (``P Fᵀ`` for an EKF).  A
    predict that keeps its prior on a failure (the sigma-point filter) returns the
    failure's ``status`` bits: :func:`run` adds them to the step's status, and a
    ``NOT_PSD`` / ``NON_FINITE`` predict makes the step's log-likelihood NaN.  Whatever the
    predict returns, a run skips a failed prediction (its status, or for a predict without
    one a NaN/Inf or negative predicted variance): the step it fed keeps the belief it
    started from and makes no update (module docstring).

    ``update(state, z, mask, R, c) -> (Gaussian, UpdateInfo)``: measurement
    update with validity ``mask`` (m,), noise ``R`` (m, m) and ``c`` the step's
    input of the measurement model (None when the model takes none).

    Build one with ``jaxslam.filters.ekf.make_filter`` or
    ``jaxslam.filters.ukf.make_filter``; run it with :func:`run`.
    """

    predict: Callable
    update: Callable


# ---------------------------------------------------------------------------
# The shared correction
# ---------------------------------------------------------------------------

def moment_dtype(x, M, x_name: str, m_name: str, empty_ok: bool = False):
    """The dtype a step computes a belief's ``x`` (n,) and its square matrix ``M`` (n, n) (a
    covariance or its factor) in, after checking their shapes (static: free under ``jit``;
    :class:`InputError` naming ``x_name`` / ``m_name``): the mean's floating dtype, an integer
    mean promoted to the matrix's (JAX's default float when that is an integer too; integer
    weights truncated every sigma-point weight to 0); a complex mean is refused.  An empty
    state (n = 0) is refused naming ``x_name`` (it ended in NumPy's "cannot reshape array of
    size 0") unless ``empty_ok`` (the caller then names its own error)."""
    xs, ms = tuple(np.shape(x)), tuple(np.shape(M))
    if len(xs) != 1:
        raise InputError(f"{x_name}: expected shape (n,), got {xs}")
    n = xs[0]
    if n == 0 and not empty_ok:
        raise InputError(f"{x_name}: expected a state of at least one component, got shape (0,)")
    if ms != (n, n):
        raise InputError(f"{m_name}: expected shape ({n}, {n}) (the mean's size), got {ms}")
    x_dt, m_dt = jnp.result_type(x), jnp.result_type(M)
    if not jnp.issubdtype(x_dt, jnp.inexact):
        x_dt = m_dt if jnp.issubdtype(m_dt, jnp.floating) else jnp.result_type(float)
    check_real(x, x_name)
    return x_dt


def state_pair(state, name: str = "state", second: str = "cov"):
    """``(mean, second)`` of a belief (a :class:`Gaussian`, a square-root one, or a plain pair),
    Python lists and tuples read as arrays (JAX's default float for numbers); else
    :class:`InputError` naming ``name``: None and bare arrays (a bare "cannot unpack"
    TypeError), the ``(belief, info)`` pair an update returns (NumPy's "inhomogeneous shape"
    ValueError), ragged lists (jnp.result_type of a list raised a bare TypeError).  Shapes,
    dtypes and values are left to the caller's checks."""
    if not isinstance(state, (tuple, list)) or len(state) != 2:
        raise InputError(f"{name}: expected a Gaussian (mean, {second}), got {type(state).__name__}"[:300])
    out = []
    for v, part in zip(state, ("mean", second)):
        if isinstance(v, tuple) and hasattr(v, "_fields"):  # a NamedTuple: a belief, not an array
            raise InputError(f"{name}: expected a Gaussian (mean, {second}), got a pair whose {part} is a "
                             f"{type(v).__name__} (an update returns (belief, info): pass its first item)")
        out.append(list_array(v, f"{name}.{part}"))
    return tuple(out)


def check_state(state, name: str = "state") -> Gaussian:
    """A belief as one step of a filter reads it: ``mean`` (n,) and ``cov`` (n, n) (shapes are
    static, so this is free under ``jit``), and, when the covariance is known now (an eager
    call), its values: finite, symmetric, positive semi-definite; a mean known now must be
    finite (a NaN mean was accepted and came back as a NaN posterior).  Raises :class:`InputError`
    naming ``name.mean`` / ``name.cov``.  An integer mean is promoted to the covariance's
    floating dtype (JAX's default float when that is an integer too), and the covariance is
    returned in the mean's dtype, so a step computes in one dtype whatever the caller mixed.
    """
    x, P = state_pair(state, name)
    x_dt = moment_dtype(x, P, f"{name}.mean", f"{name}.cov")
    p_dt = jnp.result_type(P)
    check_finite(x, f"{name}.mean")
    if is_concrete(P):
        check_psd(P, f"{name}.cov")
    x = host_array(x, x_dt) if is_concrete(x) and jnp.result_type(x) != x_dt else jnp.asarray(x)
    P = host_array(P, x_dt) if is_concrete(P) and p_dt != x_dt else jnp.asarray(P, x_dt)
    return Gaussian(x, P)


def check_noise_values(M, name: str, strict: bool = False):
    """When ``M`` (a square noise covariance, or the scalar or (1,) variance of one component)
    is known now, check its values (finite, symmetric, PSD; PD with ``strict``) and raise
    :class:`InputError` naming ``name`` (a scalar used to skip the check: a variance of −1 gave
    a posterior variance of −4.5e15 with status 0); traced: nothing (a failure then shows in
    the status flags).  Other shapes are left to the shape checks."""
    if not is_concrete(M):
        return
    if np.ndim(M) == 2:
        check_psd(M, name, strict=strict)
    elif np.ndim(M) < 2 and np.size(M) == 1:
        check_psd(np.reshape(check_numbers(M, name), (1, 1)), name, strict=strict)


def check_predict_call(state, Q):
    """What an eager ``predict`` of a Gaussian filter checks before its compiled step (which sees
    the values traced): the belief (:func:`check_state`) and a known ``Q``'s values
    (:func:`check_noise_values`).  Returns ``(state, Q)``: the checked belief, and ``Q`` as an
    array when it is a list (as a list it would reach the program as tracers, which the shape
    checks' NumPy calls cannot read)."""
    state = check_state(state)
    check_noise_values(Q, "Q")
    return state, list_array(Q, "Q")


def check_update_call(state, z, R, mask, gate, check_state=check_state):
    """What an eager ``update`` of a Gaussian filter checks before its compiled step: the gate,
    the belief, ``z``/``R``/``mask`` (:func:`check_update_args`) and, while the mask is known,
    that the gate's table covers the components it lets through.  ``check_state`` checks the
    belief (:func:`check_state` by default; the square-root filters pass theirs).  Returns
    ``(state, z, R, mask)``: the checked belief, and the lists among ``z``, ``R``, ``mask`` as
    arrays (as lists they would reach the program as tracers)."""
    check_gate(gate)
    state = check_state(state)
    check_update_args(z, R, mask)
    check_gate_size(gate, np.shape(z)[-1] if np.ndim(z) else 1, mask)
    return (state,) + tuple(map(list_array, (z, R, mask), ("z", "R", "mask")))


def check_update_args(z, R, mask):
    """The arguments one measurement update of every Gaussian filter checks first, in this order:
    ``R``'s values when known (:func:`check_noise_values`, positive definite), ``z`` real (a
    complex one lost its imaginary part), ``mask`` bool or 0/1 (:func:`jaxslam.linalg.check_mask`);
    :class:`InputError` naming the argument.  An empty ``z`` (m = 0) is refused first, naming
    ``z`` (it ended in NumPy's "cannot reshape array of size 0"): skip the update instead."""
    if np.ndim(z) >= 1 and np.shape(z)[-1] == 0:
        raise InputError(f"z: expected at least one measurement component, got shape {tuple(np.shape(z))} "
                         "(with nothing measured, skip the update)")
    check_noise_values(R, "R", strict=True)
    check_real(z, "z")
    check_mask(mask, "mask")


def scalar_measurement(z, h: Callable):
    """``(z, h)`` of one update with a scalar ``z`` read as the (1,) measurement of one
    component and a scalar output of ``h`` read as (1,) (``z.shape[-1]`` raised a bare
    IndexError); a non-scalar ``z`` is returned as it is."""
    if np.ndim(z) != 0:
        return z, h

    def h1(x, *a):
        out = jnp.asarray(h(x, *a))
        return jnp.reshape(out, (1,)) if out.ndim == 0 else out

    return jnp.reshape(jnp.asarray(z), (1,)), h1


def check_num_iter(num_iter):
    """The static number of linearisations of an update: an int >= 1 (1 = the plain EKF);
    :class:`InputError` naming ``num_iter`` (2.5 used to be truncated, 0 accepted)."""
    if isinstance(num_iter, bool) or not isinstance(num_iter, (int, np.integer)) or num_iter < 1:
        raise InputError(f"num_iter: must be an int >= 1 (1 = plain EKF), got {num_iter!r}")


def check_gate(gate: Gate):
    """A gate given as a number must be a positive χ² threshold (a NaN would switch gating off
    without a word: ``x > nan`` is False); callables and traced values pass.  A bool or a
    string is refused (``gate=True`` was read as the threshold 1.0)."""
    if gate is None or callable(gate):
        return
    if isinstance(gate, (bool, np.bool_, str, bytes)):
        raise InputError(f"gate: expected a χ² threshold (a number), a callable gate(dof) or None, "
                         f"got {gate!r}"[:300])
    if np.ndim(gate) != 0:  # static: a (2,) gate made the status and acceptance (2,) arrays
        raise InputError(f"gate: expected one χ² threshold (a scalar), a callable gate(dof) or None, "
                         f"got shape {np.shape(gate)}")
    if not is_concrete(gate):
        return
    g = float(np.asarray(gate))
    if not (np.isfinite(g) and g > 0):
        raise InputError(f"gate: must be a positive χ² threshold (or None), got {g}")


def check_gate_size(gate: Gate, m: int, mask=None):
    """A gate built for at most ``max_dof`` components (``ekf.chi2_gate``, which marks its
    callable with that size) must cover the components that can be valid (static): the
    measurement's ``m``, or the True entries of a ``mask`` known now (per row of a (M, m) mask);
    else :class:`InputError`
    naming ``gate`` (its table was clipped to ``max_dof`` and gated an m-dof NIS with the
    ``max_dof`` threshold, without a word).  A traced mask is not known: build the gate for
    ``m`` then (a step with more than ``max_dof`` valid components gets the gate's
    Wilson–Hilferty approximation of its quantile, :func:`jaxslam.filters.ekf.chi2_gate`)."""
    k = getattr(gate, "max_dof", None) if callable(gate) else None
    if k is None or int(m) <= int(k):
        return
    if mask is not None:
        if not is_concrete(mask):
            return
        valid = int(np.max(np.count_nonzero(np.atleast_2d(np.asarray(mask)), axis=-1), initial=0))
        if valid <= int(k):
            return
        raise InputError(f"gate: built for at most {k} valid components (chi2_gate's max_dof), but "
                         f"the mask lets {valid} through")
    raise InputError(f"gate: built for at most {k} valid components (chi2_gate's max_dof), but "
                     f"the measurement has {int(m)}")


def call_residual(residual: Callable, z, zhat):
    """``residual(z, ẑ)`` read as an array and checked to have ``ẑ``'s shape (static: free under
    ``jit``); else :class:`InputError` naming ``residual`` (a scalar residual was broadcast
    onto every component without a word)."""
    out = jnp.asarray(residual(z, zhat))
    exp = tuple(np.shape(zhat))
    if tuple(out.shape) != exp:
        raise InputError(f"residual: returned shape {tuple(out.shape)}, expected {exp}")
    return out


def threshold(gate: Gate, dof, dtype):
    """The gate's χ² threshold for ``dof`` valid components (number or callable)."""
    if callable(gate):
        return jnp.asarray(gate(dof), dtype=dtype)
    return jnp.asarray(gate, dtype=dtype)


def gate_test(gate: Gate, nis, dof, dtype):
    """``(gated, status)`` of an update's NIS against a (not None) gate: ``gated`` when some
    component is valid and the NIS exceeds :func:`threshold`, or the threshold is not > 0 (NaN
    included: ``nis > nan`` is False, so a traced NaN gate switched gating off with status 0);
    ``status`` (int32) is ``NON_FINITE`` for such a threshold (a concrete one is refused by
    :func:`check_gate`; a traced one cannot be), else 0."""
    thr = threshold(gate, dof, dtype)
    bad = ~(thr > 0)
    has = dof > 0
    gated = has & ((nis > thr) | bad)
    return gated, jnp.where(has & bad, jnp.int32(errors.NON_FINITE), jnp.int32(0))


def masked_innovation(z, zhat, mask, residual):
    """``ν = residual(z, ẑ)`` with invalid components replaced *before* differencing.

    NaN/Inf garbage in an invalid component never reaches the arithmetic (nor
    its gradient); the invalid components of the result are 0.
    """
    zero = jnp.zeros((), zhat.dtype)
    zhat_safe = jnp.where(mask, zhat, zero)
    z_safe = jnp.where(mask, z, zhat_safe)
    return jnp.where(mask, call_residual(residual, z_safe, zhat_safe), zero)


def check_transition_out(xn, n: int):
    """The transition's output at the mean must be (n,) (static); else :class:`InputError`
    naming ``f`` (a scalar output gave a () mean beside an (n, n) covariance)."""
    if tuple(np.shape(xn)) != (n,):
        raise InputError(f"f: the transition returned shape {tuple(np.shape(xn))}, expected ({n},)")


def check_process_noise(Q, n: int, L=None):
    """Shape check of one prediction's noise (static shapes: free under ``jit``): ``Q`` (n, n),
    or (q, q) with a noise Jacobian ``L`` (n, q); a scalar is the variance of a single noise
    input (n = 1, or q = 1).  Returns ``Q`` as a matrix; raises :class:`InputError` naming it
    (a (1, 1) ``Q`` would otherwise broadcast onto every entry of an (n, n) covariance)."""
    q1 = n if L is None else (np.shape(L)[-1] if np.ndim(L) == 2 else None)
    if q1 == 1 and np.shape(Q) in ((), (1,)):
        Q = jnp.reshape(Q, (1, 1))
    qs = tuple(np.shape(Q))
    if is_concrete(Q) and len(qs) == 2:
        check_psd(Q, "Q")  # a concrete Q (an eager call; traced under jit: shapes only)
    if L is None:
        if qs != (n, n):
            raise InputError(f"Q: expected shape ({n}, {n}) (the state's size), got {qs}")
        return Q
    ls = tuple(np.shape(L))
    if len(ls) != 2 or ls[0] != n:
        raise InputError(f"noise_jac: expected shape ({n}, q) (the state's size rows), got {ls}")
    if qs != (ls[1], ls[1]):
        raise InputError(f"Q: expected shape ({ls[1]}, {ls[1]}) (noise_jac's columns), got {qs}")
    return Q


def process_noise(Q, x, u, args, noise_jac):
    """One prediction's additive noise, checked (:func:`check_process_noise`): ``Q`` (n, n), or
    ``L Q Lᵀ`` with the noise Jacobian ``noise_jac`` (an (n, q) matrix or ``L(x, u, *args)``),
    in the dtype of ``x``."""
    dtype = x.dtype
    Q = jnp.asarray(Q, dtype)
    L = None
    if noise_jac is not None:
        L = jnp.asarray(noise_jac(x, u, *args) if callable(noise_jac) else noise_jac, dtype)
    Q = check_process_noise(Q, x.shape[0], L)
    return Q if L is None else L @ Q @ L.T


def check_measurement(z, zhat, R, mask=None):
    """Shape check of one update (static shapes: free under ``jit``): the model's output
    ``zhat`` like ``z`` (m,), ``R`` (m, m) or a scalar when m = 1, ``mask`` (m,) when given.
    Raises :class:`InputError` naming the argument (a size mismatch would otherwise broadcast
    silently)."""
    zs, hs, rs = tuple(np.shape(z)), tuple(np.shape(zhat)), tuple(np.shape(R))
    if len(zs) != 1:
        raise InputError(f"z: expected shape (m,), got {zs}")
    m = zs[0]
    if hs != zs:
        raise InputError(f"h: the measurement model returned shape {hs}, but z has shape {zs}")
    if not (rs == (m, m) or (m == 1 and rs in ((), (1,)))):
        raise InputError(f"R: expected shape ({m}, {m}) (z's size), got {rs}")
    if mask is not None and tuple(np.shape(mask)) != (m,):
        raise InputError(f"mask: expected shape ({m},) (z's size), got {tuple(np.shape(mask))}")


def innovation_solve(S, B):
    """Solve ``S X = B`` by Cholesky; return ``(X, ok, logdet S)``.

    ``ok`` is False when the factor is not finite or has a zero pivot (``S`` not PD);
    ``logdet`` is then 0.  ``S`` must already be masked (identity on invalid rows/columns).
    """
    L = jnp.linalg.cholesky(symmetrize(S))
    # a guard: a backend whose Cholesky gives a finite factor with a zero pivot for a singular S
    # (CPU's returns NaN) would give an Inf/NaN solve: not PD either
    ok = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
    X = jax.scipy.linalg.cho_solve((L, True), B)
    d = jnp.where(ok, jnp.diagonal(L), jnp.ones((), L.dtype))
    logdet = 2.0 * jnp.sum(jnp.log(jnp.abs(d)))
    return X, ok, logdet


def failure_status(live, ok, finite_in, finite_out):
    """The ``NOT_PSD`` / ``NON_FINITE`` bits of a step, one rule for the four Gaussian filters
    (``ekf``, ``ukf``, ``sqrt_ekf``, ``sqrt_ukf``; int32): ``NON_FINITE`` when a NaN/Inf entered
    the step (``finite_in`` False: the matrix it factored, or the moments it started from) or
    its result is not finite although the factorisation held; ``NOT_PSD`` when a factorisation
    failed on finite numbers (an indefinite or singular matrix).  A NaN that makes a Cholesky
    factor NaN is the NaN's failure, not a covariance found indefinite, so ``NOT_PSD`` is not
    added for it (nor ``NON_FINITE`` for the NaN a failed factorisation of finite numbers
    produces).  Only where ``live`` (a valid component, not gated)."""
    i32 = jnp.int32
    return (jnp.where(live & ~ok & finite_in, i32(errors.NOT_PSD), i32(0))
            | jnp.where(live & (~finite_in | (ok & ~finite_out)), i32(errors.NON_FINITE), i32(0)))


def finalize(prior: Gaussian, x_post, P_post, ok, gated, dof, extra_status=None, finite_in=None):
    """Select posterior or prior and assemble the status bits.

    Returns ``(Gaussian, accepted, status)``: the posterior only when at least
    one component was valid, the gate passed, the factorisation held, no posterior variance is
    negative beyond √ε times the prior's largest variance (a float32 sigma-point update with a
    precise R and an ill-conditioned S rounds to a few 64 ε below zero: that is not a failure)
    and the result is finite; else the prior, with ``GATED`` / ``NOT_PSD`` / ``NON_FINITE``
    set.  The variance check is O(n) and catches an indefinite prior, whose negative variances
    are of the order of the prior's, that a traced call could not refuse (its ``S`` may still
    factor).  ``extra_status`` (int32) is OR-ed in (e.g. ``NOT_CONVERGED``
    from an iterated update).  ``finite_in`` (a bool, traced) is False when a NaN/Inf entered
    the step (the ``S`` it factored, the prior); given, the bits follow :func:`failure_status`
    (a NaN is ``NON_FINITE`` only, a finite matrix that does not factor ``NOT_PSD`` only);
    None (the iterated smoother) sets ``NOT_PSD`` for any failed factorisation and
    ``NON_FINITE`` for any non-finite result.
    """
    var = jnp.diagonal(P_post)
    scale = jnp.max(jnp.abs(jnp.diagonal(prior.cov)))
    # (NaN compares False here: a non-finite posterior is NON_FINITE, not also NOT_PSD)
    ok = ok & ~jnp.any(var < -jnp.sqrt(jnp.finfo(var.dtype).eps) * scale)
    finite = jnp.all(jnp.isfinite(x_post)) & jnp.all(jnp.isfinite(P_post))
    has = dof > 0
    accepted = has & ~gated & ok & finite
    mean = jnp.where(accepted, x_post, prior.mean)
    cov = jnp.where(accepted, P_post, prior.cov)
    i32 = jnp.int32
    if finite_in is None:
        fail = (jnp.where(has & ~gated & ~ok, i32(errors.NOT_PSD), i32(0))
                | jnp.where(has & ~gated & ~finite, i32(errors.NON_FINITE), i32(0)))
    else:
        fail = failure_status(has & ~gated, ok, finite_in, finite)
    status = jnp.where(gated, i32(errors.GATED), i32(0)) | fail
    if extra_status is not None:
        status = status | jnp.where(has, extra_status, i32(0))
    return Gaussian(mean, cov), accepted, status


def step_log_likelihood(info: UpdateInfo):
    """``−½ (NIS + log det S + dof log 2π)`` of one update: 0 with no valid component, NaN where
    the step failed (``NOT_PSD`` / ``NON_FINITE`` in ``info.status``: S did not factor, a
    posterior variance came out negative (:func:`finalize`), the result was not finite, or the step's predict failed — also with no valid component — so
    the likelihood is undefined and a run's sum must not hide it).
    An ``UpdateInfo`` without ``logdet`` (a user-written filter) gets it from ``info.S``."""
    dtype = info.nis.dtype
    dof = info.dof.astype(dtype)
    logdet = info.logdet
    if logdet is None:
        L = jnp.linalg.cholesky(symmetrize(jnp.asarray(info.S, dtype)))
        logdet = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(L))))
    ll = -0.5 * (info.nis + logdet + dof * jnp.asarray(LOG_2PI, dtype))
    failed = (info.status & jnp.int32(errors.NOT_PSD | errors.NON_FINITE)) != 0
    return jnp.where(failed, jnp.asarray(jnp.nan, dtype), jnp.where(info.dof > 0, ll, jnp.zeros((), dtype)))


# ---------------------------------------------------------------------------
# Whole run
# ---------------------------------------------------------------------------

def single_variance(M):
    """A scalar or (1,) noise ``M`` as the (1, 1) matrix of the one variance it is (on the host
    when known now, so an eager run adds no program; traced, a reshape)."""
    return np.reshape(np.asarray(M), (1, 1)) if is_concrete(M) else jnp.reshape(M, (1, 1))


def refuse_bool(x, name: str) -> None:
    """:class:`InputError` naming ``name`` when ``x`` is a bool, a bool array (NumPy's or JAX's,
    traced too: the dtype is static) or a list holding one (:func:`jaxslam.errors.has_bool`): a
    run read ``True`` as 1 (an ``x0``, ``P0``, ``Q`` or ``R`` of bools ran as numbers)."""
    if errors.has_bool(x):
        raise InputError(f"{name}: expected numbers, got booleans (True / False are not numbers)")


def check_run_numbers(x, name: str) -> None:
    """:class:`InputError` naming ``name`` unless a run's array ``x`` is real numbers: the dtype
    (complex refused, :func:`jaxslam.linalg.check_real`) always, and, when ``x`` is known now and
    is not already a numeric array (a list, a str or object array), its entries
    (:func:`jaxslam.linalg.check_numbers`).  Runs before any cast: a str ``x0`` or ``zs`` ended in
    a bare ``TypeError`` / ``ValueError`` there, a str ``P0`` was parsed as numbers and a complex
    ``P0`` lost its imaginary part with only a warning (``ekf.filter_scan``).  Booleans are
    refused (:func:`refuse_bool`)."""
    refuse_bool(x, name)
    check_real(x, name)
    if is_concrete(x) and not (isinstance(x, (np.ndarray, jax.Array)) and np.dtype(x.dtype).kind in "biuf"):
        check_numbers(x, name)


def run_dtype(x0):
    """The dtype a run computes in: ``x0``'s floating dtype (as JAX canonicalises it), else JAX's
    default float (an integer ``x0``).  Static: known under ``jit`` too."""
    dt = x0.dtype if hasattr(x0, "dtype") else np.asarray(x0).dtype
    dt = np.dtype(jax.dtypes.canonicalize_dtype(dt))
    return dt if np.issubdtype(dt, np.floating) else np.dtype(jnp.result_type(float))


def check_fits_dtype(M, name: str, dtype, valid=None, variances: bool = True, rows: bool = False) -> None:
    """When ``M`` (a covariance, or a stack of them: ``name[k]``) is known now, :class:`InputError`
    naming ``name`` unless the run's cast to ``dtype`` keeps it: an entry finite as given that
    overflows to inf in ``dtype``, or (``variances``) a positive diagonal entry that underflows to
    0 in it.  The values are judged as given (float64) before the cast, so ``diag(1e200, 1)``
    given to a float32 run passed and then failed every step (status flags, the prior kept).
    Non-finite entries are left to :func:`jaxslam.linalg.check_psd`; ``valid`` as there (the
    rows of masked measurements of a per-step R are not read).  With ``rows`` ``M`` is a run's
    (T, m) measurements ``zs`` (no variances): an entry is named ``name[t]``, and ``valid`` is
    the (T, m) mask (a masked entry may hold anything: it is never read).  A value already in
    ``dtype``, or a run in float64, has nothing to check."""
    dt = np.dtype(dtype)
    if M is None or not is_concrete(M) or getattr(M, "dtype", None) == dt or np.finfo(dt).bits >= 64:
        return
    A = check_numbers(M, name)
    if valid is not None and A.ndim == 3:
        v = np.broadcast_to(np.asarray(valid, bool), A.shape[:-1])
        A = np.where(v[:, :, None] & v[:, None, :], A, 0.0)
    elif valid is not None and rows:
        A = np.where(np.broadcast_to(np.asarray(valid, bool), A.shape), A, 0.0)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        C = A.astype(dt).astype(np.float64)
    stack = A.ndim == 3 or rows

    def fail(values, bad, what, how):
        idx = np.unravel_index(int(np.argmax(bad)), bad.shape)
        where = f"{name}[{idx[0]}]" if stack else name
        raise InputError(f"{where}: {what} {values[idx]:.3g} does not fit {dt.name}, the run's dtype "
                         f"(x0's): it {how}")

    over = np.isfinite(A) & ~np.isfinite(C)
    if over.any():
        fail(A, over, "entry", "overflows to inf")
    if variances and A.ndim >= 2:
        d = np.diagonal(A, 0, -2, -1)
        under = (d > 0) & (np.diagonal(C, 0, -2, -1) == 0)
        if under.any():
            fail(d, under, "variance", "underflows to 0")


def noise_size(x0, noise_jac):
    """``(q, by_jac)``: the size a run's ``Q`` must have, ``q``, (``x0``'s size, or the columns
    of an ``(n, q)`` array ``noise_jac``), and whether ``noise_jac`` sets it; ``q`` is None when
    only the step can tell (a callable ``noise_jac``, or a malformed ``x0`` / ``noise_jac``,
    which their own checks name)."""
    n = np.shape(x0)[0] if np.ndim(x0) == 1 else None
    if noise_jac is None:
        return n, False
    gs = np.shape(noise_jac) if not callable(noise_jac) else None
    return (gs[1] if gs is not None and len(gs) == 2 and gs[0] == n else None), True


def check_run_q_size(Q, q, by_jac: bool, T: int) -> None:
    """A run's ``Q`` against the size ``q`` of :func:`noise_size` (None: not checked here), one
    message for every Gaussian run: ``(q, q)`` or one per step ``(T, q, q)``; a scalar or (1,)
    ``Q`` is the variance of a single noise input (q = 1).  :class:`InputError` naming ``Q``."""
    if q is None or Q is None:
        return
    qs = tuple(np.shape(Q))
    if qs[-2:] != (q, q) and not (q == 1 and qs in ((), (1,))):
        why = " (noise_jac's columns)" if by_jac else ""
        raise InputError(f"Q: expected shape ({q}, {q}){why} or ({T}, {q}, {q}), got {qs}")


def check_run_inputs(x0, P0, zs, masks, Q, R, name_prefix="", q_optional: bool = False):
    """Host-side checks of a whole run's arrays, shared by every Gaussian filter's run
    (:func:`run`, ``sqrt_ekf.filter_scan``, ``sqrt_ukf.filter_scan``): ``x0``, ``P0``, ``zs``
    real numbers (:func:`check_run_numbers`); shapes; ``x0`` finite and ``P0``, ``Q`` PSD,
    ``R`` PD (a per-step ``R`` on the rows ``masks`` uses) where concrete, each representable in
    the run's dtype (:func:`check_fits_dtype`: no entry overflows, no variance underflows to 0
    in ``x0``'s dtype), and so the entries of a concrete ``zs`` that ``masks`` uses (no
    overflow).  A scalar ``R`` is
    the variance of the one measurement when m = 1 (so is a (1,) ``R``).  ``Q`` is checked for
    squareness and, as one matrix per step, for its count; its size against the state is the
    caller's (it depends on ``noise_jac``): a scalar or (1,) ``Q`` is the variance of a single
    noise input, as in one step's predict (``n = 1``, or a one-column ``noise_jac``).  None of
    ``x0``, ``P0``, ``zs``, ``Q``, ``R`` may be booleans (:func:`refuse_bool`).  With
    ``q_optional`` a ``Q`` of None is not checked (the caller has the noise from elsewhere, e.g.
    a square root ``Q_chol``).

    Raises :class:`InputError` naming the argument.  Under ``jit`` only the
    shapes and dtypes are checked (values are abstract).  Returns ``(T, m)``.
    """
    pre = name_prefix
    for v, nm in ((x0, "x0"), (P0, "P0"), (zs, "zs")):
        check_run_numbers(v, f"{pre}{nm}")
    for v, nm in ((Q, "Q"), (R, "R")):
        refuse_bool(v, f"{pre}{nm}")
    xs = np.shape(x0)
    if len(xs) != 1:
        raise InputError(f"{pre}x0: expected shape (n,), got {tuple(xs)}")
    n = xs[0]
    if n == 0:  # an empty state ended in NumPy's "cannot reshape array of size 0" (check_psd)
        raise InputError(f"{pre}x0: expected a state of at least one component, got shape (0,)")
    check_finite(x0, f"{pre}x0")
    if np.shape(P0) != (n, n):
        raise InputError(f"{pre}P0: expected shape ({n}, {n}), got {tuple(np.shape(P0))}")
    zsh = np.shape(zs)
    if len(zsh) != 2:
        raise InputError(f"{pre}zs: expected shape (T, m), got {tuple(zsh)}")
    T, m = zsh
    if m == 0:  # (a bare "cannot reshape array of size 0" from the R check, as for an empty state)
        raise InputError(f"{pre}zs: expected at least one measurement component, got shape {tuple(zsh)}")
    if masks is not None and np.shape(masks) != (T, m):
        raise InputError(f"{pre}masks: expected shape ({T}, {m}) like zs, got "
                         f"{tuple(np.shape(masks))}")
    check_mask(masks, f"{pre}masks")
    # a measurement in use that the run's dtype cannot hold (1e300 in float32 was an Inf: the step
    # flagged NON_FINITE); judged as given, as P0 / Q / R below
    check_fits_dtype(zs, f"{pre}zs", run_dtype(x0), valid=_zs_valid(zs, masks), variances=False, rows=True)
    rs = np.shape(R)
    if m == 1 and rs in ((), (1,)):
        R = np.reshape(R, (1, 1)) if is_concrete(R) else R  # a scalar variance of one measurement
    elif len(rs) not in (2, 3) or rs[-2:] != (m, m) or (len(rs) == 3 and rs[0] != T):
        # (the count before the values: the masks of a per-step R's check must match it)
        raise InputError(f"{pre}R: expected shape ({m}, {m}) or ({T}, {m}, {m}), got {tuple(rs)}")
    checks = [(P0, "P0", False), (R, "R", True)]
    if not (q_optional and Q is None):
        if tuple(np.shape(Q)) in ((), (1,)):  # the variance of a single noise input (one step's rule)
            Q = np.reshape(check_numbers(Q, f"{pre}Q"), (1, 1)) if is_concrete(Q) else jnp.reshape(Q, (1, 1))
        qs = tuple(np.shape(Q))
        if len(qs) not in (2, 3) or qs[-1] != qs[-2]:
            raise InputError(f"{pre}Q: expected a square matrix or one per step, got shape {qs}")
        if len(qs) == 3 and qs[0] != T:
            raise InputError(f"{pre}Q: one matrix per step needs {T} of them (zs has {T} steps), got shape {qs}")
        checks.insert(1, (Q, "Q", False))
    dtype = run_dtype(x0)
    for M, nm, strict in checks:
        if not is_concrete(M):
            continue
        # per-step R: only the rows of the measurements in use at that step (masked rows may
        # hold anything); every matrix of a stack is checked at once
        valid = np.asarray(masks, bool) if (nm == "R" and np.ndim(M) == 3 and masks is not None
                                            and is_concrete(masks)) else None
        check_psd(M, f"{pre}{nm}", strict=strict, valid=valid, stack=True)
        # judged as given (float64): the run then casts it to x0's dtype
        check_fits_dtype(M, f"{pre}{nm}", dtype, valid=valid)
    return T, m


def check_leading(tree, T: int, name: str):
    """Every leaf of ``tree`` (None: nothing) has the run's T steps on its leading axis, else an
    :class:`InputError` naming ``name`` (``lax.scan`` would say only that lengths disagree)."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        shp = np.shape(leaf)
        if len(shp) == 0 or shp[0] != T:
            where = jax.tree_util.keystr(path)
            raise InputError(f"{name}{where}: expected a leading axis of {T} steps (zs has {T}), "
                             f"got shape {tuple(shp)}")


def init_carry(x0, P0):
    """The scan carry of :func:`make_step` at the start of a run."""
    init = Gaussian(x0, P0)
    return (init, init, jnp.zeros(P0.shape, P0.dtype), jnp.zeros((), jnp.int32))


def make_step(flt: GaussianFilter, Q, R, q_step: bool, r_step: bool, predict_first: bool):
    """One step of a run as a scan body: ``step(carry, inp) -> (carry, (post, prior, cross, info))``.

    ``inp = (u, z, mask, Q_t, R_t, c)`` (``Q_t``/``R_t`` used when ``q_step``/``r_step``,
    else the shared ``Q``/``R``); ``prior`` is the belief that was updated and
    ``cross`` the cross-covariance of the prediction that produced it.  Shared by
    :func:`run` and the fixed-lag smoother so that both filter identically.  A predict's
    status (the protocol's optional third output) goes to the step whose prior it made: the
    same step with ``predict_first``, else the next one (the carry's last slot holds it); that
    step keeps the belief the failed predict started from and makes no update (module
    docstring: selected after the update, so a step whose predict held computes exactly what
    it did before the rule).
    """
    zero = jnp.zeros((), jnp.int32)
    i32 = jnp.int32

    def kept(status, g, cross, prev):
        """``(g, cross)`` (a predict's, or an update's belief and None), or ``prev`` (cross-covariance
        ``prev.cov``: no motion) where ``status`` says the predict failed."""
        bad = (status & i32(errors.NOT_PSD | errors.NON_FINITE)) != 0
        return (Gaussian(jnp.where(bad, prev.mean, g.mean), jnp.where(bad, prev.cov, g.cov)),
                None if cross is None else jnp.where(bad, prev.cov, cross))

    def predict(state, u, Qt):
        out = flt.predict(state, u, Qt)
        g, cross = out[:2]
        st = jnp.asarray(out[2], jnp.int32) if len(out) == 3 else zero
        return g, cross, st | predicted_status(g.cov)

    def step(carry, inp):
        state, _, cross_in, pending = carry
        u, z, mk, Qt, Rt, c = inp
        Qt = Qt if q_step else Q
        Rt = Rt if r_step else R
        # The step whose prior a failed predict made keeps the belief it started from and makes
        # no update (its prior is unknown), whatever the filter: the EKF's run carried the NaN /
        # negative-variance prediction to every later step, the sigma-point runs updated the
        # belief of the step before with this step's z.  Selected after the update, so a
        # successful step computes what it always did.
        if predict_first:
            prior, cross, p_status = predict(state, u, Qt)
            post, info = flt.update(prior, z, mk, Rt, c)
            post, _ = kept(p_status, post, None, state)
            prior, cross = kept(p_status, prior, cross, state)
            nxt, cross_next, pending_next = post, cross_in, zero
        else:
            prior, cross, p_status = state, cross_in, pending
            post, info = flt.update(state, z, mk, Rt, c)
            post, _ = kept(p_status, post, None, state)
            nxt, cross_next, pending_next = predict(post, u, Qt)
            # a failed predict hands on the belief it started from (the next step then keeps it)
            nxt, cross_next = kept(pending_next, nxt, cross_next, post)
        failed = (p_status & i32(errors.NOT_PSD | errors.NON_FINITE)) != 0
        info = info._replace(status=info.status | p_status, accepted=info.accepted & ~failed,
                             nis=jnp.where(failed, jnp.zeros_like(info.nis), info.nis))
        # The second carry slot holds the last filtered estimate, which with
        # predict_first=False differs from the (predicted) first slot.
        return (nxt, post, cross_next, pending_next), (post, prior, cross, info)

    return step


def negative_variance(M, mask=None):
    """True (a traced bool) when a noise covariance ``M`` ((k, k); ``mask`` (k,): only its valid
    entries) has a variance on its diagonal below zero beyond the rounding of one product sum,
    ``-64 k ε max|M|``: such an ``M`` is no covariance (a traced negative ``Q``: the covariance
    forms used it with status 0 where ``P + Q`` stayed PD; the square-root forms, which factor
    it, say ``NOT_PSD``).  A PSD matrix built in floating point (``G Qc Gᵀ`` of a singular
    ``Qc``: a diagonal entry of −1e-16 beside entries of order 1), which
    :func:`jaxslam.linalg.check_psd` accepts, is not flagged; ``diag(1, −1e-9)`` is.  A NaN in
    ``M`` is left to the NaN checks (``NON_FINITE``).  An indefinite ``M`` with a non-negative
    diagonal is not seen here (that needs a factorisation, and a singular ``Q`` such as
    ``diag(q, q, 0)`` is valid).  Used for ``Q`` in the predictions, where a shared ``Q`` costs
    nothing per step; a run's ``R`` is not checked so (measured: the check in each update made a
    two-state EKF run of 5000 steps ~25 % slower)."""
    M = jnp.asarray(M)
    M = M.reshape(1, 1) if M.ndim < 2 else M  # a scalar: the one variance
    dt = M.dtype if jnp.issubdtype(M.dtype, jnp.floating) else jnp.result_type(float)
    A = jnp.abs(M)
    if mask is not None:
        A = jnp.where(mask[:, None] & mask[None, :], A, jnp.zeros_like(A))
    scale = jnp.max(A) if A.size else jnp.zeros((), A.dtype)
    tol = (64 * M.shape[-1] * jnp.finfo(dt).eps) * scale
    neg = jnp.diagonal(M) < -tol.astype(A.dtype)  # (NaN compares False)
    return jnp.any(neg if mask is None else neg & mask)


def predicted_status(P):
    """Status bits of a predicted covariance, from its diagonal (O(n)): ``NON_FINITE`` when a
    variance is NaN/Inf, ``NOT_PSD`` when one is negative beyond √ε times the largest (a traced
    negative ``Q`` shrank the covariance and the step reported status 0)."""
    var = jnp.diagonal(P)
    scale = jnp.max(jnp.abs(var)) if var.size else jnp.zeros((), var.dtype)
    finite = jnp.all(jnp.isfinite(var))
    neg = jnp.any(var < -jnp.sqrt(jnp.finfo(var.dtype).eps) * scale)
    i32 = jnp.int32
    return jnp.where(~finite, i32(errors.NON_FINITE), jnp.where(neg, i32(errors.NOT_PSD), i32(0)))


def _zs_valid(zs, masks):
    """The (T, m) mask a check of ``zs``'s values reads before ``masks`` is checked: ``masks`` when
    it is a concrete bool or integer array of ``zs``'s shape, else None (every entry judged; a
    malformed ``masks`` is named by :func:`check_run_inputs`)."""
    if masks is None or not is_concrete(masks):
        return None
    a = np.asarray(masks)
    return a if a.shape == np.shape(zs) and a.dtype.kind in "biu" else None


def prepare_run(x0, P0, zs, masks, Q, R, noise=None):
    """Cast and check a run's arrays; ``(x0, P0, zs, masks, Q, R, q_step, r_step, T)``.  ``noise``:
    None, or :func:`noise_size`'s ``(q, by_jac)`` for :func:`check_run_q_size` (a run that knows
    its model's noise size: ``ekf`` / ``ukf`` ``filter_scan``)."""
    for v, nm in ((zs, "zs"), (x0, "x0"), (P0, "P0")):
        check_run_numbers(v, nm)  # before the casts to x0's (real) dtype
    # made on the host when known now (host_array): eagerly, each jnp conversion was a program
    x0 = to_jax(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    if np.ndim(P0) == 2:  # (as given: the cast below would turn 1e200 into inf, 1e-50 into 0)
        check_fits_dtype(P0, "P0", dtype)
    if np.ndim(zs) == 2:  # likewise a measurement (1e300 in a float32 run was an Inf: NON_FINITE)
        check_fits_dtype(zs, "zs", dtype, valid=_zs_valid(zs, masks), variances=False, rows=True)
    x0, P0, zs = (host_array(v, dtype) for v in (x0, P0, zs))
    T, m = check_run_inputs(x0, P0, zs, masks, Q, R)
    if noise is not None:
        check_run_q_size(Q, *noise, T)
    Q = host_array(Q, dtype)
    if Q.ndim < 2 and x0.shape[0] == 1:  # the variance of the one state component: (1, 1) now, so
        Q = Q.reshape(1, 1)  # the run is the one of a (1, 1) Q (same program, same numbers)
    # any other scalar or (1,) Q goes to the filter's predict as given: it reads it as one step
    # does (the variance of a one-column noise_jac's input, else an InputError naming Q)
    q_step = Q.ndim == 3  # (check_run_inputs refused every other rank and count)
    R = host_array(R, dtype)
    R = R.reshape(1, 1) if R.ndim < 2 else R
    r_step = R.ndim == 3
    masks = host_array(np.ones((T, m), bool) if masks is None else masks, bool)
    return x0, P0, zs, masks, Q, R, q_step, r_step, T


def run(
    flt: GaussianFilter,
    x0,
    P0,
    us,
    zs,
    masks,
    Q,
    R,
    *,
    h_inputs=None,
    predict_first: bool = True,
    save_cov: bool = False,
    save_smoother: bool = False,
) -> Posterior:
    """Run a :class:`GaussianFilter` over a whole sequence as one ``lax.scan``.

    Called eagerly the run is compiled once per filter (``flt``, hashable: two functions) and
    argument shapes (:func:`jaxslam.compilation.call_compiled`): a second call with new
    numbers neither traces nor compiles.  Under the caller's ``jit`` / ``vmap`` / ``grad`` it
    is the plain scan.

    Args:
        flt: the filter (``ekf.make_filter`` / ``ukf.make_filter``).
        x0: (n,) initial mean.  P0: (n, n) initial covariance.
        us: inputs with leading axis T (array or pytree), or None for a model
            without inputs.
        zs: (T, m) measurements.
        masks: (T, m) bool validity, or None (all valid).
        Q: (q, q) process noise, or (T, q, q) one per step; a scalar for a single noise
            input (n = 1, or q = 1), as the filter's one-step predict takes it.
        R: (m, m) measurement noise, or (T, m, m) one per step; a scalar for m = 1.
        h_inputs: None, or a pytree with leading axis T passed to the
            measurement model as its per-step input ``c_t``.
        predict_first: static; the step order (module docstring).
        save_cov: static; also stack the filtered covariances (T, n, n).
        save_smoother: static; also save the predicted moments and
            cross-covariances (and the filtered covariances) for
            :func:`jaxslam.filters.smoother.rts`.

    Returns:
        :class:`Posterior` in the dtype of ``x0``.  A failed prediction is skipped: the step it
        fed keeps the belief it started from, makes no update and carries the predict's status
        (module docstring).  A concrete ``zs`` entry in use that ``x0``'s dtype cannot hold
        (1e300 in float32) is an :class:`InputError` naming ``zs[t]``.
    """
    return _run(flt, x0, P0, us, zs, masks, Q, R, h_inputs, predict_first, save_cov, save_smoother)


def _run(flt, x0, P0, us, zs, masks, Q, R, h_inputs, predict_first, save_cov, save_smoother, noise=None):
    """:func:`run`, with ``noise`` as in :func:`prepare_run` (``ekf`` / ``ukf`` ``filter_scan``
    pass their model's noise size, so ``Q``'s is checked with the square-root runs' message)."""
    predict_first = check_flag(predict_first, "predict_first")
    save_cov = check_flag(save_cov, "save_cov")
    save_smoother = check_flag(save_smoother, "save_smoother")
    x0, P0, zs, masks, Q, R, q_step, r_step, T = prepare_run(x0, P0, zs, masks, Q, R, noise)
    check_leading(us, T, "us")
    check_leading(h_inputs, T, "h_inputs")
    build, arrays, key = filter_recipe(flt)

    def scan(arrays, x0, P0, us, zs, masks, Q, R, h_inputs):
        return _scan(build(*arrays), x0, P0, us, zs, masks, Q, R, h_inputs, q_step, r_step,
                     predict_first, save_cov or save_smoother, save_smoother)

    # called eagerly: compiled once per filter, options and shapes
    return call_compiled(("gaussian.run", key, q_step, r_step, predict_first, save_cov, save_smoother), scan,
                         (arrays, x0, P0, us, zs, masks, Q, R, h_inputs))


_RECIPES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def keyed_filter(flt: GaussianFilter, make: Callable, inputs, key) -> GaussianFilter:
    """Register how ``flt`` was made, so that a run of it compiles once per *model*.

    ``make(*inputs)`` must build the same filter (``flt`` is ``make(*inputs)``), and ``key``
    (hashable) must name everything ``make`` closes over.  The array leaves of ``inputs``
    become arguments of the compiled run (:func:`jaxslam.compilation.split_arrays`); the rest joins the key.
    Without this a run is keyed by ``flt``'s two functions, new with every ``make_filter``
    call: ``run(ekf.make_filter(f, h), ...)`` written inline compiled on every call.  Only
    eager calls register (under a transformation nothing is compiled apart).
    """
    if at_top_level():
        arrays, rebuild, skey = split_arrays(inputs)
        _RECIPES[flt.predict] = (flt.update, lambda *a: make(*rebuild(*a)), arrays, (key, skey))
    return flt


def filter_recipe(flt: GaussianFilter):
    """``(build, arrays, key)`` with ``build(*arrays)`` equal to ``flt``: the registered recipe
    of :func:`keyed_filter`, else ``flt`` itself, keyed by its two functions."""
    try:
        rec = _RECIPES.get(flt.predict)
    except TypeError:  # not weak-referenceable: no recipe
        rec = None
    if rec is not None and rec[0] is flt.update:
        return rec[1], rec[2], rec[3]
    return (lambda: flt), (), ("filter", flt)


def _scan(flt, x0, P0, us, zs, masks, Q, R, h_inputs, q_step, r_step, predict_first, keep_cov,
          save_smoother):
    step_fn = make_step(flt, Q, R, q_step, r_step, predict_first)

    def step(carry, inp):
        carry, (post, prior, cross, info) = step_fn(carry, inp)
        out = (
            post.mean,
            jnp.diagonal(post.cov),
            post.cov if keep_cov else None,
            info.nis,
            info.dof,
            info.status,
            step_log_likelihood(info),
            prior.mean if save_smoother else None,
            prior.cov if save_smoother else None,
            cross if save_smoother else None,
        )
        return carry, out

    xs = (us, zs, masks, Q if q_step else None, R if r_step else None, h_inputs)
    (_, final, _, _), outs = jax.lax.scan(step, init_carry(x0, P0), xs, length=zs.shape[0])
    means, diags, covs, nis, dof, status, ll, pm, pc, cc = outs
    return Posterior(means, diags, covs, nis, dof, status, final, ll, pm, pc, cc)
