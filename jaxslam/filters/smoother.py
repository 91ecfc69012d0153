"""Gaussian smoothers over a filter run: Rauch–Tung–Striebel, fixed-lag, and the
iterated (Gauss–Newton) smoother of a whole trajectory.

Generic: the model enters only through a :class:`jaxslam.filters.gaussian.GaussianFilter`
(EKF or sigma-point) or, for the iterated smoother, through ``f`` and ``h``.  Called eagerly,
each smoother is compiled once per model and options
(:func:`jaxslam.compilation.call_compiled`).

Equations
---------
**RTS** (:func:`rts`), backwards from ``t = T − 2`` to 0, with the filtered
moments ``(m_t, P_t)``, the predicted moments ``(m⁻_{t+1}, P⁻_{t+1})`` and the
cross-covariance ``C_{t+1} = Cov(x_t, x⁻_{t+1})`` the filter saved
(``save_smoother=True``; ``C = P Fᵀ`` for the EKF, the sigma-point sum for the
UKF, so the same pass is the extended and the unscented RTS smoother)::

    G_t   = C_{t+1} (P⁻_{t+1})⁻¹                     (Cholesky solve, never an inverse)
    mˢ_t  = m_t + G_t (mˢ_{t+1} − m⁻_{t+1})
    Pˢ_t  = P_t + G_t (Pˢ_{t+1} − P⁻_{t+1}) G_tᵀ     (symmetrised)

and ``(mˢ_{T−1}, Pˢ_{T−1}) = (m_{T−1}, P_{T−1})``.

**Fixed lag** (:func:`fixed_lag`): the same filter and the same backward pass,
but over a window of the last ``L + 1`` steps carried inside the filter's scan,
so step ``t`` emits ``x_{t−L | t}``; the last window is smoothed completely at
the end.  Memory is O(L n²) whatever the run length; with ``L ≥ T − 1`` the
result is the RTS smoother's.

**Iterated smoother** (:func:`iterated`): Gauss–Newton on the whole
trajectory's MAP (the iterated extended Kalman smoother of Bell 1994).  Each
iteration linearises ``f`` and ``h`` about the previous smoothed trajectory
``x̄`` (not about the filter's running estimate), runs the Kalman filter of that
affine model and its RTS pass; the smoothed means are the next ``x̄``.  The
fixed point is the MAP of ``‖s₀ − x₀‖²_{P₀⁻¹} + Σ ‖s_{t+1} − f(s_t)‖²_{Q⁻¹} +
Σ ‖z_t − h(s_t)‖²_{R⁻¹}``; iterating only the backward pass (a filter
linearised at its own estimates, then smoothed) does not converge to it, which
is why dynamax removed its iterated EKS (its issue #398).  Options:

* ``robust``: iteratively reweighted least squares.  At ``x̄`` each valid
  component gets the whitened residual ``r = ν / √R_ii`` and the weight
  ``w(r)`` (:func:`huber_weight`, :func:`cauchy_weight`, :func:`tukey_weight`);
  the iteration uses ``R_w = D^{-½} R D^{-½}``, ``D = diag(w)``; a weight
  below 1e-12 masks the component.  The fixed point minimises the robust cost.
* ``damping`` (Levenberg–Marquardt): a pseudo-measurement ``s_t = x̄_t`` with
  covariance ``I / λ`` at every step, which shortens the Gauss–Newton step
  (λ → 0: Gauss–Newton).  It changes the iterates, not the fixed point; the covariances
  returned come from one more pass without it, linearised at the last iterate (the damped
  pass's hold the pseudo-measurements' information: too small).  The convergence test
  reads the damped pass's σ (stricter).
* Convergence: ``NOT_CONVERGED`` is set when the last iteration moved a state
  component by more than ``tol`` smoothed standard deviations.

Decisions
---------
* The iterated smoother smooths the initial state as well: with
  ``predict_first=True`` the state before the first input, ``s₋₁ ~ N(x₀, P₀)``,
  is part of the trajectory (``Smoothed.initial``).
* ``difference(a, b)`` (default ``a − b``) is used for every state difference
  of the backward pass, so heading components can be wrapped
  (e.g. ``angle_residual``).
* Failures never produce NaN: a step whose predicted covariance fails its
  Cholesky factorisation keeps the filtered moments and sets ``NOT_PSD``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError, check_flag
from ..linalg import check_int, check_scalar, is_concrete, symmetrize, value_and_jacfwd
from . import ekf as _ekf
from . import gaussian as _g
from .gaussian import Gaussian, GaussianFilter, Posterior, innovation_solve

__all__ = [
    "Smoothed",
    "rts",
    "fixed_lag",
    "iterated",
    "huber_weight",
    "cauchy_weight",
    "tukey_weight",
]

Array = Any


class Smoothed(NamedTuple):
    """A smoothed trajectory.

    Fields:
        means: (T, n) smoothed means.
        cov_diags: (T, n) diagonals of the smoothed covariances.
        covs: (T, n, n) smoothed covariances (``save_cov``), else None.
        status: (T,) int32 bit flags (``NOT_PSD`` where a backward step failed;
            the iterated smoother adds its filter's flags and ``NOT_CONVERGED``).
        initial: :class:`Gaussian` of the state before the first input
            (iterated smoother with ``predict_first=True``), else None.
        iterations: () int32 iterations run (iterated smoother), else None.
        step_sizes: (num_iter,) largest move of each iteration in smoothed σ
            (iterated smoother), else None.
    """

    means: Array
    cov_diags: Array
    covs: Optional[Array]
    status: Array
    initial: Optional[Gaussian] = None
    iterations: Optional[Array] = None
    step_sizes: Optional[Array] = None


def _sub(a, b):
    return a - b


def _backward(nxt, filt, pred, cross, difference):
    """One RTS step: (mˢ_{t+1}, Pˢ_{t+1}), (m_t, P_t), (m⁻_{t+1}, P⁻_{t+1}), C_{t+1}."""
    ms1, Ps1 = nxt
    m, P = filt
    pm, pc = pred
    X, ok, _ = innovation_solve(pc, cross.T)  # (P⁻)⁻¹ Cᵀ
    G = X.T
    dx = difference(ms1, pm)
    if np.shape(dx) != np.shape(ms1):  # static; a scalar was a bare ValueError from the matmul
        raise InputError(f"difference: must return a state difference of shape {np.shape(ms1)}, "
                         f"got shape {np.shape(dx)}")
    ms = m + G @ dx
    Ps = symmetrize(P + G @ (Ps1 - pc) @ G.T)
    good = ok & jnp.all(jnp.isfinite(ms)) & jnp.all(jnp.isfinite(Ps))
    ms = jnp.where(good, ms, m)
    Ps = jnp.where(good, Ps, P)
    st = jnp.where(good, jnp.int32(0), jnp.int32(errors.NOT_PSD))
    return (ms, Ps), st


def _backward_pass(means, covs, pred_means, pred_covs, cross_covs, difference):
    """RTS over stacked arrays (leading axis T); returns (means, covs, status)."""
    T = means.shape[0]
    last = (means[-1], covs[-1])

    def body(nxt, inp):
        m, P, pm, pc, cc = inp
        cur, st = _backward(nxt, (m, P), (pm, pc), cc, difference)
        return cur, (cur[0], cur[1], st)

    if T == 1:
        return means, covs, jnp.zeros((1,), jnp.int32)
    xs = (means[:-1], covs[:-1], pred_means[1:], pred_covs[1:], cross_covs[1:])
    _, (ms, Ps, st) = jax.lax.scan(body, last, xs, reverse=True)
    ms = jnp.concatenate([ms, means[-1:]], 0)
    Ps = jnp.concatenate([Ps, covs[-1:]], 0)
    st = jnp.concatenate([st, jnp.zeros((1,), jnp.int32)], 0)
    return ms, Ps, st


def rts(post: Posterior, *, difference: Optional[Callable] = None,
        save_cov: bool = True) -> Smoothed:
    """Rauch–Tung–Striebel smoother over a filter run (module docstring).

    Args:
        post: a :class:`Posterior` from a run with ``save_smoother=True``
            (``ekf.filter_scan``, ``ukf.filter_scan`` or ``gaussian.run``), with
            either step order.
        difference: ``difference(a, b)`` of two states (default ``a − b``).
        save_cov: static; also return the smoothed covariances (T, n, n).

    Returns:
        :class:`Smoothed` with ``status`` flagging failed backward steps.
    """
    if not all(hasattr(post, f) for f in ("means", "covs", "pred_means", "pred_covs", "cross_covs")):
        raise InputError(f"post: expected a Posterior of a filter run (ekf.filter_scan, ukf.filter_scan "
                         f"or gaussian.run with save_smoother=True), got {type(post).__name__}")
    _check_function(difference, "difference", "a function difference(a, b)")
    save_cov = check_flag(save_cov, "save_cov")  # static: a string "no" read as True
    if post.pred_covs is None or post.cross_covs is None or post.covs is None:
        raise InputError("post: the filter run must save what the smoother needs "
                         "(run it with save_smoother=True)")
    if jnp.ndim(post.means) != 2:
        raise InputError(f"post.means: expected shape (T, n), got {jnp.shape(post.means)}")
    if jnp.shape(post.means)[0] == 0:
        raise InputError("post: the filter run has no steps (T = 0): nothing to smooth")
    T, n = jnp.shape(post.means)
    for f, want in (("covs", (T, n, n)), ("pred_means", (T, n)), ("pred_covs", (T, n, n)),
                    ("cross_covs", (T, n, n))):
        if jnp.shape(getattr(post, f)) != want:
            raise InputError(f"post.{f}: expected shape {want} to match post.means {(T, n)}, "
                             f"got {jnp.shape(getattr(post, f))}")
    diff = _sub if difference is None else difference

    def backward(means, covs, pred_means, pred_covs, cross_covs):
        ms, Ps, st = _backward_pass(means, covs, pred_means, pred_covs, cross_covs, diff)
        return Smoothed(ms, jnp.diagonal(Ps, axis1=1, axis2=2), Ps if save_cov else None, st)

    # called eagerly: compiled once per difference function and shapes
    return call_compiled(("smoother.rts", diff, bool(save_cov)), backward,
                         (post.means, post.covs, post.pred_means, post.pred_covs, post.cross_covs))


def fixed_lag(
    flt: GaussianFilter,
    x0,
    P0,
    us,
    zs,
    masks,
    Q,
    R,
    *,
    lag: int,
    h_inputs=None,
    predict_first: bool = True,
    difference: Optional[Callable] = None,
) -> Smoothed:
    """Fixed-lag smoother: ``x_{t | min(t + lag, T − 1)}`` for every t, memory O(lag · n²).

    Runs the filter (the same step as :func:`jaxslam.filters.gaussian.run`) and,
    inside the same scan, the RTS pass over a window of the last ``lag + 1``
    steps (module docstring).  Compute O(T · lag · n³): every step re-runs the
    window's backward pass (``bench filters``: lag 20 costs 11.8× the filter).

    Args:
        flt: the filter (``ekf.make_filter`` / ``ukf.make_filter``).
        x0, P0, us, zs, masks, Q, R, h_inputs, predict_first: as in
            :func:`jaxslam.filters.gaussian.run`.
        lag: static int ≥ 0, the number of later steps each estimate uses
            (0 = the filter itself; ≥ T − 1 = the RTS smoother).
        difference: as in :func:`rts`.

    Returns:
        :class:`Smoothed` (``covs`` None: only the diagonals are kept, to bound memory).
    """
    lag = check_int(lag, "lag", lower=0, what="a whole number of steps")  # 2.5 or True is not a lag
    if not (callable(getattr(flt, "predict", None)) and callable(getattr(flt, "update", None))):
        raise InputError(f"flt: expected a GaussianFilter (ekf.make_filter, ukf.make_filter, ...), got {flt!r}"[:300])
    _check_function(difference, "difference", "a function difference(a, b)")
    predict_first = check_flag(predict_first, "predict_first")
    diff = _sub if difference is None else difference
    x0, P0, zs, masks, Q, R, q_step, r_step, T = _g.prepare_run(x0, P0, zs, masks, Q, R)
    if T == 0:
        raise InputError("zs: the run has no steps (T = 0): nothing to smooth")
    _g.check_leading(us, T, "us")
    _g.check_leading(h_inputs, T, "h_inputs")
    L = min(lag, T - 1)

    build, arrays, key = _g.filter_recipe(flt)

    def smooth(arrays, x0, P0, us, zs, masks, Q, R, h_inputs):
        flt = build(*arrays)
        n = x0.shape[0]
        dtype = x0.dtype
        step_fn = _g.make_step(flt, Q, R, q_step, r_step, predict_first)
        eye = jnp.eye(n, dtype=dtype)
        W = L + 1
        buf0 = (jnp.zeros((W, n), dtype), jnp.broadcast_to(eye, (W, n, n)),
                jnp.zeros((W, n), dtype), jnp.broadcast_to(eye, (W, n, n)),
                jnp.zeros((W, n, n), dtype), jnp.zeros((W,), jnp.int32))

        def smooth_window(buf):
            bm, bP, bpm, bpc, bcc, bst = buf
            return _backward_pass(bm, bP, bpm, bpc, bcc, diff)

        def step(carry, inp):
            fc, buf = carry
            fc, (post, prior, cross, info) = step_fn(fc, inp)
            new = (post.mean, post.cov, prior.mean, prior.cov, cross, info.status)
            buf = tuple(jnp.concatenate([b[1:], v[None]], 0) for b, v in zip(buf, new))
            if L == 0:
                out = (post.mean, jnp.diagonal(post.cov), info.status)
            else:
                ms, Ps, st = smooth_window(buf)
                out = (ms[0], jnp.diagonal(Ps[0]), st[0] | buf[5][0])
            return (fc, buf), out

        xs = (us, zs, masks, Q if q_step else None, R if r_step else None, h_inputs)
        (_, buf), (m_out, d_out, s_out) = jax.lax.scan(step, (_g.init_carry(x0, P0), buf0), xs,
                                                       length=zs.shape[0])
        if L == 0:
            return Smoothed(m_out, d_out, None, s_out)
        ms, Ps, st = smooth_window(buf)
        means = jnp.concatenate([m_out[L:], ms[1:]], 0)
        diags = jnp.concatenate([d_out[L:], jnp.diagonal(Ps[1:], axis1=1, axis2=2)], 0)
        status = jnp.concatenate([s_out[L:], st[1:] | buf[5][1:]], 0)
        return Smoothed(means, diags, None, status)

    # called eagerly: compiled once per filter, lag and shapes
    return call_compiled(("smoother.fixed_lag", key, diff, L, q_step, r_step, predict_first), smooth,
                         (arrays, x0, P0, us, zs, masks, Q, R, h_inputs))


# ---------------------------------------------------------------------------
# Robust weights (IRLS) for the iterated smoother
# ---------------------------------------------------------------------------

def huber_weight(k: float = 1.345) -> Callable[[Array], Array]:
    """Huber IRLS weight ``w(r) = min(1, k / |r|)`` of a whitened residual ``r``.

    ``k = 1.345`` gives 95 % efficiency at the Gaussian (Huber 1981).
    """
    if is_concrete(k):
        check_scalar(k, "k", lower=0, strict=True)

    def w(r):
        a = jnp.abs(r)
        return jnp.where(a <= k, jnp.ones_like(a), k / jnp.maximum(a, k))

    return w


def cauchy_weight(c: float = 2.3849) -> Callable[[Array], Array]:
    """Cauchy (Lorentzian) IRLS weight ``w(r) = 1 / (1 + (r / c)²)`` (c = 2.3849: 95 % efficiency)."""
    if is_concrete(c):
        check_scalar(c, "c", lower=0, strict=True)

    def w(r):
        return 1.0 / (1.0 + (r / c) ** 2)

    return w


def tukey_weight(c: float = 4.6851) -> Callable[[Array], Array]:
    """Tukey biweight ``w(r) = (1 − (r / c)²)²`` for ``|r| < c``, else 0 (c = 4.6851: 95 % efficiency).

    Components with weight 0 are masked (a redescending kernel: far outliers
    have no influence at all, so a good starting trajectory matters).
    """
    if is_concrete(c):
        check_scalar(c, "c", lower=0, strict=True)

    def w(r):
        u = (r / c) ** 2
        return jnp.where(u < 1.0, (1.0 - u) ** 2, jnp.zeros_like(u))

    return w


# ---------------------------------------------------------------------------
# Iterated (Gauss–Newton) smoother
# ---------------------------------------------------------------------------

def _prepend(tree, first):
    """Prepend ``first`` (a pytree like one slice of ``tree``) along the leading axis."""
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([b[None], a], 0), tree, first)


def _check_function(value, name: str, what: str) -> None:
    """None or a callable, else an :class:`InputError` naming ``name`` (a number made a bare
    ``TypeError`` deep in the trace)."""
    if value is not None and not callable(value):
        raise InputError(f"{name}: expected None or {what}, got {value!r}"[:300])


def iterated(
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
    num_iter: int = 10,
    init=None,
    h_inputs=None,
    residual: Optional[Callable] = None,
    difference: Optional[Callable] = None,
    robust: Optional[Callable] = None,
    damping=None,
    tol=None,
    predict_first: bool = True,
    noise_jac=None,
    save_cov: bool = False,
) -> Smoothed:
    """Iterated extended Kalman smoother: Gauss–Newton over the whole trajectory.

    Args:
        f: transition ``f(x, u, *args) -> (n,)`` (None: the state does not move).
        h: measurement ``h(x, *args)`` or ``h(x, c_t, *args)`` with ``h_inputs``.
        x0, P0, us, zs, masks, Q, R, h_inputs, predict_first: as in
            :func:`jaxslam.filters.ekf.filter_scan` (per-step ``Q``/``R`` allowed).
        *args: shared extra arguments of ``f`` and ``h``.
        num_iter: static, Gauss–Newton iterations (each a filter + RTS pass).
        init: (T, n) starting trajectory (e.g. a filter's or RTS smoother's
            means); default: the EKF filter's means (one extra pass).  With
            ``predict_first=True`` the state before the first input starts at ``x0``.
        residual: ``residual(z, ẑ)`` (angles), as in ``ekf.update``.
        difference: ``difference(a, b)`` of states, as in :func:`rts`.
        robust: None (least squares) or an IRLS weight ``w(r)`` of the whitened
            residual (:func:`huber_weight`, :func:`cauchy_weight`, :func:`tukey_weight`).
            A non-finite weight of a valid component masks it and sets ``NON_FINITE``.
        damping: None (Gauss–Newton) or λ > 0 (traced): Levenberg–Marquardt
            pseudo-measurements ``s_t = x̄_t`` with covariance ``I/λ``.
        tol: convergence tolerance in smoothed σ (default 1e-6 float64, 1e-3 float32); a
            traced NaN ``tol`` sets ``NOT_CONVERGED``.
        noise_jac: as in ``ekf.predict``.
        save_cov: static; also return the smoothed covariances.

    Returns:
        :class:`Smoothed` at the last iterate (``initial``, ``iterations``,
        ``step_sizes`` filled); ``NOT_CONVERGED`` on every step when the last
        iteration still moved the trajectory by more than ``tol``.
    """
    _g.check_num_iter(num_iter)  # 2.9 used to be truncated to 2, True taken as 1
    _check_function(residual, "residual", "a function residual(z, z_hat)")
    _check_function(difference, "difference", "a function difference(a, b)")
    predict_first, save_cov = check_flag(predict_first, "predict_first"), check_flag(save_cov, "save_cov")
    _check_function(robust, "robust", "an IRLS weight function w(r) (e.g. huber_weight())")
    if tol is not None:
        if np.ndim(tol) != 0:
            raise InputError(f"tol: expected a scalar tolerance in smoothed σ, got shape {np.shape(tol)}")
        if is_concrete(tol):  # a NaN tolerance suppressed NOT_CONVERGED
            check_scalar(tol, "tol", lower=0, strict=True)
    x0, P0, zs, masks, Q, R, q_step, r_step, T = _g.prepare_run(x0, P0, zs, masks, Q, R)
    if T == 0:
        raise InputError("zs: the run has no steps (T = 0): nothing to smooth")
    _g.check_leading(us, T, "us")
    dtype = x0.dtype
    n = x0.shape[0]
    fm = (lambda x, u, *a: x) if f is None else f
    hh = (lambda x, c, *a: h(x, c, *a)) if h_inputs is not None else (lambda x, c, *a: h(x, *a))
    res = _sub if residual is None else residual
    diff = _sub if difference is None else difference
    tol_v = jnp.asarray((1e-6 if dtype == jnp.float64 else 1e-3) if tol is None else tol, dtype)

    if init is None:
        post = _ekf.filter_scan(f, h, x0, P0, us, zs, masks, Q, R, *args, residual=residual,
                                predict_first=predict_first, noise_jac=noise_jac,
                                h_inputs=h_inputs)
        init = post.means
    init = jnp.asarray(init, dtype)
    if init.shape != (T, n):
        raise InputError(f"init: expected shape ({T}, {n}), got {init.shape}")

    if damping is not None and is_concrete(damping):
        check_scalar(damping, "damping", lower=0, strict=True)  # λ > 0 (a negative one fails later, NOT_PSD)
    lam = None if damping is None else jnp.asarray(damping, dtype)
    def solve(opts, x0, P0, us, zs, masks, Q, R, h_inputs, init, tol_v, lam):
        args, noise_jac = opts
        dtype = x0.dtype
        n = x0.shape[0]
        m = zs.shape[1]
        eye_n = jnp.eye(n, dtype=dtype)

        # Update-first form over states s_0..s_{K-1}: with predict_first the extra
        # s_0 is the state before the first input (no measurement).
        if predict_first:
            zs_a = jnp.concatenate([jnp.zeros((1, m), dtype), zs], 0)
            masks_a = jnp.concatenate([jnp.zeros((1, m), bool), masks], 0)
            us_a = None if us is None else jax.tree_util.tree_map(
                lambda a: jnp.concatenate([a, a[-1:]], 0), us)
            c_a = None if h_inputs is None else _prepend(
                h_inputs, jax.tree_util.tree_map(lambda a: a[0], h_inputs))
            Q_a = jnp.concatenate([Q, Q[-1:]], 0) if q_step else Q
            R_a = jnp.concatenate([R[:1], R], 0) if r_step else R
            nominal0 = jnp.concatenate([x0[None], init], 0)
        else:
            zs_a, masks_a, us_a, c_a, Q_a, R_a = zs, masks, us, h_inputs, Q, R
            nominal0 = init
        K = nominal0.shape[0]

        def lin_predict(state, inp, Qt):
            u, xb = inp
            m_, P = state
            fx, F = value_and_jacfwd(lambda v: fm(v, u, *args))(xb)
            F = F.astype(dtype)
            # The noise and shape checks of ekf.predict (static): with ``init`` given no EKF pass
            # runs, and a (1, 1) or (T, 1, 1) Q broadcast onto every entry of the (n, n) covariance.
            Qd = _g.process_noise(Qt, xb.astype(dtype), u, args, noise_jac)
            PFt = P @ F.T
            mean = fx.astype(dtype) + F @ diff(m_, xb)
            return Gaussian(mean, symmetrize(F @ PFt + Qd)), PFt

        def weights_at(xb, z, mk, Rt, c):
            zb = hh(xb, c, *args).astype(dtype)
            r = _g.masked_innovation(z, zb, mk, res) / jnp.sqrt(jnp.diagonal(Rt))
            w = robust(r)
            return jnp.where(mk, w, jnp.ones((), dtype))

        def lin_update(state, z, mk, Rt, inp):
            c, xb, lam = inp
            m_, P = state
            zb, H = value_and_jacfwd(lambda v: hh(v, c, *args))(xb)
            zb = zb.astype(dtype)
            H = H.astype(dtype)
            w_bad = jnp.asarray(False)
            if robust is not None:
                w = weights_at(xb, z, mk, Rt, c)
                w_bad = jnp.any(mk & ~jnp.isfinite(w))  # a NaN weight masked the component unflagged
                mk = mk & (w > 1e-12)
                sw = jnp.sqrt(jnp.maximum(w, 1e-12))
                Rt = Rt / (sw[:, None] * sw[None, :])
            nu = _g.masked_innovation(z, zb, mk, res) - jnp.where(
                mk, H @ diff(m_, xb), jnp.zeros((), dtype))
            xp, Pp, S, num, nis, ok, logdet = _ekf.linear_update(m_, P, nu, H, Rt, mk)
            dof = jnp.sum(mk).astype(jnp.int32)
            post, acc, status = _g.finalize(state, xp, Pp, ok, jnp.asarray(False), dof)
            if lam is not None:  # (traced: the key says whether there is one)
                dm = diff(xb, post.mean)
                xq, Pq, _, _, _, okq, _ = _ekf.linear_update(
                    post.mean, post.cov, dm, eye_n, eye_n / lam, jnp.ones((n,), bool))
                post2, _, st2 = _g.finalize(post, xq, Pq, okq, jnp.asarray(False), jnp.int32(n))
                post, status = post2, status | st2
            status = status | jnp.where(w_bad, jnp.int32(errors.NON_FINITE), jnp.int32(0))
            info = _g.UpdateInfo(nis, dof, num, S, acc, status, logdet)
            return post, info

        flt = GaussianFilter(lin_predict, lin_update)

        def one_pass(nominal, lam):
            step_fn = _g.make_step(flt, Q_a, R_a, q_step, r_step, False)
            u_in = (us_a, nominal)
            c_in = (c_a, nominal, jnp.broadcast_to(lam, (K,)) if lam is not None else None)
            xs = (u_in, zs_a, masks_a, Q_a if q_step else None, R_a if r_step else None, c_in)

            def body(carry, inp):
                carry, (post, prior, cross, info) = step_fn(carry, inp)
                return carry, (post.mean, post.cov, prior.mean, prior.cov, cross, info.status)

            _, (fm_, fP, pm, pc, cc, fst) = jax.lax.scan(body, _g.init_carry(x0, P0), xs, length=K)
            ms, Ps, bst = _backward_pass(fm_, fP, pm, pc, cc, diff)
            return ms, Ps, fst | bst

        def it(carry, _):
            nominal, _, _, _ = carry
            ms, Ps, st = one_pass(nominal, lam)
            sig = jnp.sqrt(jnp.maximum(jnp.diagonal(Ps, axis1=1, axis2=2), jnp.finfo(dtype).tiny))
            moved = jnp.max(jnp.abs(jax.vmap(diff)(ms, nominal)) / sig)
            return (ms, Ps, st, moved), moved

        zP = jnp.zeros((K, n, n), dtype)
        init_c = (nominal0, zP, jnp.zeros((K,), jnp.int32), jnp.asarray(jnp.inf, dtype))
        (ms, Ps, st, moved), sizes = jax.lax.scan(it, init_c, None, length=num_iter)
        if lam is not None:  # the covariances without the pseudo-measurements, at the last iterate
            _, Ps, st_cov = one_pass(ms, None)
            st = st | st_cov
        # not (moved <= tol): a NaN tolerance (traced) or a NaN step counts as not converged
        st = st | jnp.where(moved <= tol_v, jnp.int32(0), jnp.int32(errors.NOT_CONVERGED))
        initial = None
        if predict_first:
            initial = Gaussian(ms[0], Ps[0])
            ms, Ps, st = ms[1:], Ps[1:], st[1:]
        return Smoothed(ms, jnp.diagonal(Ps, axis1=1, axis2=2), Ps if save_cov else None, st,
                        initial, jnp.asarray(num_iter, jnp.int32), sizes)

    # called eagerly: compiled once per model, options and shapes
    return call_compiled(("smoother.iterated", f, h, residual, diff, robust, num_iter, predict_first, save_cov,
                          q_step, r_step, h_inputs is None, damping is None), solve,
                         (x0, P0, us, zs, masks, Q, R, h_inputs, init, tol_v, lam), (args, noise_jac))
