"""Generic EKF-SLAM engine on a fixed-capacity, padded landmark map.

One engine serves every model (paper 000's 3D LiDAR quadcopter, paper 003's
range-only UWB, paper 004's line features, 2D range-bearing real data): a model
is a :class:`SlamModel` of pure functions, the filter never names a paper.

State layout (static shapes, so a change of noise never recompiles and a
change of capacity recompiles once)::

    x = [s (n_r), l_0 (d_l), l_1 (d_l), ..., l_{cap-1} (d_l)]      n = n_r + cap·d_l
    P = full (n, n) covariance; inactive slots have zero rows/columns

Inactive slots carry zero mean, zero covariance and zero cross-covariance, so
they never influence an active quantity: a run at capacity 40 and at capacity
128 gives the same estimates for the active landmarks, and slot order is
immaterial.

Speed (STYLE.md lessons, measured on a 2-core CPU):

* prediction touches only the robot block and the robot–landmark
  cross-covariance (P_rl ← F P_rl; paper 000 eq. 27-29 discretised), so its
  cost is O(n) in the map size, not O(n²);
* the update gathers the columns of P that the sparse H touches (robot block
  plus one landmark block per measurement): P Hᵀ costs O(n·k) for k observed
  landmarks, and the factored Joseph form
  (I − K H) P (I − K H)ᵀ + K R Kᵀ = A − (A Hᵀ − K R) Kᵀ,  A = P − K (P Hᵀ)ᵀ,
  written as the symmetric rank-2m correction P − ½ (K Gᵀ + G Kᵀ), G = P Hᵀ + A Hᵀ − K R
  (A's columns at H's support only), costs O(n²·k·d_z) — never a dense n×n product with H;
  ``joseph=False`` uses the standard form P − K S Kᵀ = P − (K L)(K L)ᵀ instead (S = L Lᵀ),
  a rank-m correction with half the products (:func:`sym_outer_update`);
* gains come from a Cholesky solve on the (k·d_z)-sized innovation
  covariance; P is symmetrised once per update;
* with ``active_only=True`` (``update``, ``predict`` and the nearest-neighbour d² table,
  :func:`marginal_d2`) the cost is set by the mapped
  landmarks, not the capacity (inactive slots are zero, and registration fills the lowest
  free slot): the gain on the smallest of three leading blocks and two row counts
  (``lax.switch``; P is not an operand, since a conditional that writes P makes XLA copy
  it), the covariance correction in 64-tiles and the prediction's P_rl in 64-wide strips up
  to the highest active slot (:func:`sym_rank_update`, :func:`robot_cross_update`).

Measurements are processed in static-size batches of ``K`` with a validity
mask: absent, non-finite, gated or unmapped measurements contribute nothing.
Failures never produce silent NaNs: a non-finite update is rejected (prior
kept) and flagged in ``status``; a landmark that finds no free slot is counted
in ``overflow`` and flagged ``CAPACITY_OVERFLOW``.

References: paper 000 eq. 21-53 (prediction eq. 26-29, update eq. 37-43,
registration eq. 44-53).  The engine's default covariance update is the factored
Joseph form; the paper's eq. 43 (P − K E Kᵀ) is ``joseph=False``, the default of
the paper-000 system (``ekf_slam_3d.Config``), where it was measured as safe as the
Joseph form; see docs/papers.md.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError
from ..linalg import (check_finite, check_int, check_mask, check_psd, check_scalar, check_whole_ids, cholesky_small,
                      is_concrete, list_array, put_blocks, small_matmul, symmetrize, take, take_blocks, to_jax,
                      value_and_jacfwd)
from ..stats import _student_t_nll, check_student_t_nu
from .gaussian import check_gate, check_gate_size, check_num_iter, check_real, threshold as _threshold

__all__ = [
    "SlamModel",
    "SlamState",
    "UpdateInfo",
    "init",
    "preload",
    "predict",
    "motion_and_jacobian",
    "update",
    "update_nll",
    "sym_rank_update",
    "sym_outer_update",
    "robot_cross_update",
    "update_robot",
    "register",
    "add_landmark",
    "associate_known",
    "first_of_each_id",
    "associate_nn",
    "marginal_d2",
    "joint_compatibility",
    "robot",
    "landmarks",
    "robot_cov",
    "landmark_covs",
    "slot_indices",
    "SmootherTerms",
    "smoother_terms",
    "smooth_robot",
]


class SlamModel(NamedTuple):
    """A SLAM model: sizes plus pure functions (static under ``jit``).

    motion(s, u, params) -> s'           discrete robot motion over one step
    observe(s, l, params) -> z (d_z,)    measurement of landmark ``l`` from robot ``s``
    inverse(s, z, params) -> l (d_l,)    inverse observation (registration); may be None
    residual(z, zhat) -> ν (d_z,)        innovation (wraps angle components)
    motion_jacobian(s, u, params) -> (s', F)   optional: the motion and F = ∂s'/∂s in one call
                                         (e.g. a closed form); None: forward-mode autodiff
    observe_jacobian(s, l, params) -> (z, H_s, H_l)   optional, likewise for ``observe``
    inverse_jacobian(s, z, params) -> (l, G_s, G_z)   optional, likewise for ``inverse``
    A model that gives a closed form should test it against ``jax.jacfwd`` of the plain function
    (paper 000's does: a gradient through the filter differentiates these Jacobians, and the
    closed forms' derivatives take far fewer kernels than autodiff's).
    """

    robot_dim: int
    lm_dim: int
    meas_dim: int
    motion: Callable
    observe: Callable
    inverse: Optional[Callable] = None
    residual: Optional[Callable] = None
    motion_jacobian: Optional[Callable] = None
    observe_jacobian: Optional[Callable] = None
    inverse_jacobian: Optional[Callable] = None


def motion_and_jacobian(model: SlamModel, s, u, params=None):
    """``(model.motion(s, u, params), ∂/∂s of it)``: the model's ``motion_jacobian`` when it has
    one, else forward-mode autodiff of ``motion``."""
    if model.motion_jacobian is not None:
        return model.motion_jacobian(s, u, params)
    return value_and_jacfwd(lambda s_: model.motion(s_, u, params))(s)


class SlamState(NamedTuple):
    """EKF-SLAM posterior with a padded map.

    x: (n,) mean; P: (n, n) covariance; active: (cap,) bool slot in use;
    ids: (cap,) int32 landmark id held by each slot (−1 when free);
    status: () int32 bit flags (jaxslam.errors) OR-ed since init;
    overflow: () int32 number of landmarks that found no free slot.
    """

    x: jax.Array
    P: jax.Array
    active: jax.Array
    ids: jax.Array
    status: jax.Array
    overflow: jax.Array


class UpdateInfo(NamedTuple):
    """Per-update diagnostics: joint NIS, log det S, degrees of freedom, used mask.

    ``nis``, ``logdet`` and ``dof`` are the terms of the update's innovation log-likelihood,
    −log p(ν) = ½ (NIS + log det S + dof · log 2π), over the measurements used (zero when
    none is, or the update was rejected); tuning by innovation likelihood reads them here
    instead of forming S a second time.
    """

    nis: jax.Array  # () joint normalised innovation squared
    dof: jax.Array  # () number of scalar measurements used
    used: jax.Array  # (K,) bool measurement used in the update
    gated: jax.Array  # (K,) bool rejected by the Mahalanobis gate
    logdet: jax.Array = None  # () log det of the joint innovation covariance of the used rows
    d2: jax.Array = None  # (K,) marginal NIS of each valid row, before gating and weighting
    row_logdet: jax.Array = None  # (K,) log det of each valid row's marginal S_i (R unweighted)
    rejected: jax.Array = None  # () True when rows were to be used but the update was rejected


# ---------------------------------------------------------------------------
# Construction and views
# ---------------------------------------------------------------------------

def init(robot_mean, robot_cov, capacity: int, lm_dim: int) -> SlamState:
    """Empty map with ``capacity`` landmark slots of dimension ``lm_dim``.

    ``robot_mean`` (n_r,) (an integer mean is cast to JAX's default float, as the generic
    filters do); ``robot_cov`` (n_r, n_r), checked finite, symmetric and PSD when concrete.
    A bad argument is an :class:`~jaxslam.errors.InputError` naming it."""
    robot_mean = to_jax(robot_mean)
    dtype = robot_mean.dtype if jnp.issubdtype(robot_mean.dtype, jnp.floating) else jnp.result_type(float)
    if robot_mean.ndim != 1:
        raise InputError(f"robot_mean: expected shape (n_r,), got {tuple(robot_mean.shape)}")
    nr = robot_mean.shape[0]
    if jnp.shape(robot_cov) != (nr, nr):
        raise InputError(f"robot_cov: expected shape ({nr}, {nr}) (robot_mean's size), got "
                         f"{tuple(jnp.shape(robot_cov))}")
    capacity, lm_dim = check_int(capacity, "capacity"), check_int(lm_dim, "lm_dim")
    check_finite(robot_mean, "robot_mean")
    if is_concrete(robot_cov):
        check_psd(robot_cov, "robot_cov")
    return _empty_map(robot_mean, to_jax(robot_cov), capacity, lm_dim, np.dtype(dtype))


@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _empty_map(robot_mean, robot_cov, capacity: int, lm_dim: int, dtype) -> SlamState:
    """:func:`init`'s state, one program per sizes and dtype (called eagerly, its six arrays
    were ten one-operation programs: 345-355 ms for a first call in a fresh process)."""
    nr = robot_mean.shape[0]
    n = nr + capacity * lm_dim
    x = jnp.zeros((n,), dtype).at[:nr].set(robot_mean.astype(dtype))
    P = jnp.zeros((n, n), dtype).at[:nr, :nr].set(robot_cov.astype(dtype))
    return SlamState(
        x=x,
        P=P,
        active=jnp.zeros((capacity,), bool),
        ids=jnp.full((capacity,), -1, jnp.int32),
        status=jnp.zeros((), jnp.int32),
        overflow=jnp.zeros((), jnp.int32),
    )


def preload(state: SlamState, model: SlamModel, means, covs=None, ids=None, mask=None) -> SlamState:
    """A known (or previously mapped) landmark set in the first N slots.

    ``means`` (N, d_l); ``covs`` (N, d_l, d_l) their marginal covariances (default zero: a
    surveyed map the filter never moves); ``ids`` (N,) int32 (default 0…N−1); ``mask`` (N,)
    bool: which to write (default all; a slot left out keeps its contents).  Each written
    slot gets no cross-covariance with the robot or any other slot, and is marked active.
    Static slices only (no scatter); N ≤ capacity is checked at trace time.  Called eagerly it
    is compiled once per map size (:func:`jaxslam.compilation.call_compiled`; op by op the
    first call took 1.3 s).
    """
    means = _check_preload(state, model, means, covs)
    nr, dl = model.robot_dim, model.lm_dim
    return call_compiled(("ekf_slam.preload", nr, dl), lambda *a: _preload(nr, dl, *a),
                         (state, means, covs, ids, mask), after="auto")


def _check_preload(state, model, means, covs):
    """:func:`preload`'s checks: sizes, and the values known now (finite means, PSD covs)."""
    nr, dl, cap = _sizes(state, model)
    _check_sizes(state, model)
    if is_concrete(means) and not np.all(np.isfinite(np.asarray(means, np.float64))):
        raise InputError("means: contains NaN or Inf")
    means = jnp.asarray(means, state.x.dtype)
    if means.ndim != 2 or means.shape[1] != dl:
        raise InputError(f"means: expected shape (N, {dl}) (the model's lm_dim), got {tuple(means.shape)}")
    N = means.shape[0]
    if N > cap:
        raise InputError(f"means: {N} landmarks do not fit the map's {cap} slots")
    if covs is not None and is_concrete(covs):
        check_psd(np.asarray(covs), "covs", stack=True)  # a marginal covariance must be one
    return means


def _preload(nr, dl, state, means, covs, ids, mask):
    """:func:`preload`'s computation (``nr``, ``dl``: the model's robot_dim and lm_dim)."""
    N = means.shape[0]
    covs = jnp.zeros((N, dl, dl), state.x.dtype) if covs is None else jnp.asarray(covs, state.x.dtype)
    ids = jnp.arange(N, dtype=jnp.int32) if ids is None else jnp.asarray(ids, jnp.int32)
    mask = jnp.ones((N,), bool) if mask is None else jnp.asarray(mask, bool)
    lo, hi = nr, nr + N * dl
    m_rows = jnp.repeat(mask, dl)  # (N·d_l,)
    x = state.x.at[lo:hi].set(jnp.where(m_rows, means.reshape(-1), state.x[lo:hi]))
    blk = jnp.einsum("iab,ij->iajb", covs, jnp.eye(N, dtype=state.x.dtype)).reshape(N * dl, N * dl)
    P = state.P
    keep = ~m_rows
    rows = jnp.where(keep[:, None], P[lo:hi, :], 0.0)  # written slots: no cross-covariance
    P = P.at[lo:hi, :].set(rows).at[:, lo:hi].set(rows.T)
    both = m_rows[:, None] & m_rows[None, :]
    P = P.at[lo:hi, lo:hi].set(jnp.where(both, blk, P[lo:hi, lo:hi]))
    active = state.active.at[:N].set(state.active[:N] | mask)
    new_ids = state.ids.at[:N].set(jnp.where(mask, ids, state.ids[:N]))
    return state._replace(x=x, P=P, active=active, ids=new_ids)


def _sizes(state: SlamState, model: SlamModel):
    nr, dl = model.robot_dim, model.lm_dim
    cap = state.active.shape[0]
    return nr, dl, cap


def _check_sizes(state: SlamState, model: SlamModel, name: str = "state"):
    """The state's arrays against the model (static shapes: free under ``jit``): ``x`` of size
    robot_dim + capacity·lm_dim, ``P`` square of that size.  Raises :class:`InputError`
    (a state built with another model's sizes would otherwise write landmarks into the wrong
    slots)."""
    nr, dl, cap = _sizes(state, model)
    n = nr + cap * dl
    xs, ps = tuple(np.shape(state.x)), tuple(np.shape(state.P))
    if xs != (n,) or ps != (n, n):
        raise InputError(f"{name}: x {xs} and P {ps} do not fit the model: robot_dim {nr} + capacity "
                         f"{cap} × lm_dim {dl} = {n} (was the state made by init with this model's "
                         f"lm_dim?)")


def _cast_u(u, dtype):
    """``u`` (an array, a pytree or None) with its floating leaves in ``dtype`` (the state's), as
    z, Q and R are cast: a float64 control must not promote (or, under ``lax``, break) a float32
    prediction.  Integer and bool leaves are left as they are."""
    def one(a):
        dt = getattr(a, "dtype", None)
        if dt is None:
            dt = np.asarray(a).dtype
        return jnp.asarray(a, dtype) if jnp.issubdtype(dt, jnp.floating) and dt != dtype else a
    return jax.tree_util.tree_map(one, u)


def _rows(z, ids, mask, dz: int, ids_name: str):
    """``(z (K, d_z), ids (K,) int32, mask (K,) bool)`` as arrays, shapes checked (static):
    :class:`InputError` naming the argument (a (K,) z with K = d_z would otherwise be read
    as K rows of one component each, and lists have no ``.shape``; a complex z lost its imaginary
    part with only a warning)."""
    check_real(z, "z")
    z = jnp.asarray(z)
    if z.ndim != 2 or z.shape[1] != dz or z.shape[0] < 1:
        raise InputError(f"z: expected shape (K, {dz}) (K ≥ 1 rows of the model's meas_dim), got "
                         f"{tuple(z.shape)}")
    K = z.shape[0]
    if ids is not None:  # None: rows without ids (an association's input)
        ids = jnp.asarray(ids)
        if tuple(ids.shape) != (K,):
            raise InputError(f"{ids_name}: expected shape ({K},) (one per row of z), got {tuple(ids.shape)}")
        if not jnp.issubdtype(ids.dtype, jnp.integer):
            raise InputError(f"{ids_name}: expected integers, got dtype {ids.dtype}")
        ids = ids.astype(jnp.int32)
    mask = jnp.asarray(mask)
    if tuple(mask.shape) != (K,):
        raise InputError(f"mask: expected shape ({K},) (one per row of z), got {tuple(mask.shape)}")
    check_mask(mask, "mask")
    return z, ids, mask.astype(bool)


def _check_options(gate=None, robust=None, num_iter: int = 1):
    """Static checks of an update's options: :class:`InputError` naming the option."""
    check_num_iter(num_iter)
    check_gate(gate)
    if robust is not None and is_concrete(robust) and np.ndim(robust) == 0:
        nu = float(np.asarray(robust))
        if not (nu > 0):  # NaN included
            raise InputError(f"robust: the Student-t degrees of freedom must be > 0 (or None), got {nu}")


def robot(state: SlamState, model: SlamModel):
    """Robot mean (n_r,)."""
    return state.x[: model.robot_dim]


def robot_cov(state: SlamState, model: SlamModel):
    """Robot covariance block (n_r, n_r)."""
    nr = model.robot_dim
    return state.P[:nr, :nr]


def landmarks(state: SlamState, model: SlamModel):
    """Landmark means (cap, d_l); inactive slots are zero (see ``state.active``)."""
    nr, dl, cap = _sizes(state, model)
    return state.x[nr:].reshape(cap, dl)


def slot_indices(slots, model: SlamModel):
    """State indices (K, d_l) of the landmark blocks in ``slots`` (K,)."""
    return model.robot_dim + slots[:, None] * model.lm_dim + jnp.arange(model.lm_dim)[None, :]


def landmark_covs(state: SlamState, model: SlamModel):
    """Marginal landmark covariances (cap, d_l, d_l)."""
    cap = state.active.shape[0]
    idx = slot_indices(jnp.arange(cap), model)
    return state.P[idx[:, :, None], idx[:, None, :]]


def _residual(model: SlamModel):
    return model.residual if model.residual is not None else (lambda z, zh: z - zh)


def _flag_if(cond, bit):
    return jnp.where(cond, jnp.int32(bit), jnp.int32(0))


# ---------------------------------------------------------------------------
# Prediction (paper 000 eq. 26-29, discretised)
# ---------------------------------------------------------------------------

def predict(state: SlamState, model: SlamModel, u, Q, params=None, *,
            active_only: bool = False) -> SlamState:
    """Propagate the robot through ``model.motion``; landmarks are static.

    P_rr ← F P_rr Fᵀ + Q,  P_rl ← F P_rl  (P_lr = P_rlᵀ); P_ll untouched.
    ``Q`` (n_r, n_r) is the discrete process noise of this step.  Cost is
    O(n_r²·n), independent of the map block; with ``active_only`` (static) O(n_r²·n_a), n_a
    the columns up to the highest active slot (:func:`robot_cross_update`).  A non-finite
    prediction keeps the prior and sets ``NON_FINITE`` in ``state.status``.
    Called eagerly it is compiled once per model (:func:`jaxslam.compilation.call_compiled`, ``after="auto"``).
    """
    _check_predict(state, model, Q)
    Q = list_array(Q, "Q")  # a list would reach the program as tracers
    return call_compiled(("ekf_slam.predict", model, active_only),
                         lambda opts, st, Q: _predict(st, model, opts[0], Q, opts[1], active_only)[0],
                         (state, Q), (u, params), after="auto")


def _check_predict(state: SlamState, model: SlamModel, Q):
    """:func:`predict`'s checks: the state's sizes, ``Q``'s shape and, when known, its values."""
    nr = model.robot_dim
    _check_sizes(state, model)
    if np.shape(Q) != (nr, nr):
        raise InputError(f"Q: expected shape ({nr}, {nr}) (the model's robot_dim), got {tuple(np.shape(Q))}")
    if is_concrete(Q):
        check_psd(np.asarray(Q), "Q")


def _predict(state: SlamState, model: SlamModel, u, Q, params, active_only: bool):
    """:func:`predict` and whether this prediction was finite (the state's status is sticky,
    so a run needs the step's own verdict)."""
    nr = model.robot_dim
    _check_predict(state, model, Q)
    s = state.x[:nr]
    s_new, F = motion_and_jacobian(model, s, _cast_u(u, state.x.dtype), params)
    if jnp.shape(s_new) != (nr,) or jnp.shape(F) != (nr, nr):
        # (static shapes: a u of the wrong size broadcast by the model shows here, not as an
        # XLA broadcasting error inside the update)
        raise InputError(f"model.motion: returned shape {tuple(jnp.shape(s_new))} (Jacobian "
                         f"{tuple(jnp.shape(F))}) for robot_dim {nr}; check u's shape "
                         f"{tuple(jnp.shape(u)) if not isinstance(u, (tuple, list, dict)) else '(a pytree)'}")
    Prr = state.P[:nr, :nr]
    Prl = state.P[:nr, nr:]
    Prr_new = symmetrize(small_matmul(small_matmul(F, Prr), F.T) + Q)
    ok = jnp.all(jnp.isfinite(s_new)) & jnp.all(jnp.isfinite(Prr_new)) & jnp.all(jnp.isfinite(F))
    # Reject a non-finite prediction block-wise: a select over the whole P would cost O(n²).
    s_new = jnp.where(ok, s_new, state.x[:nr])
    Prr_new = jnp.where(ok, Prr_new, Prr)
    x = state.x.at[:nr].set(s_new)
    status = state.status | _flag_if(~ok, errors.NON_FINITE)
    if active_only:
        P = jax.lax.dynamic_update_slice(state.P, Prr_new, (0, 0))
        P = robot_cross_update(P, jnp.where(ok, F, jnp.eye(nr, dtype=F.dtype)),
                               nr + _active_top(state) * model.lm_dim)
        return state._replace(x=x, P=P, status=status), ok
    Prl_new = jnp.where(ok, F @ Prl, Prl)
    P = state.P
    P = jax.lax.dynamic_update_slice(P, jnp.concatenate([Prr_new, Prl_new], axis=1), (0, 0))
    P = jax.lax.dynamic_update_slice(P, Prl_new.T, (nr, 0))
    return state._replace(x=x, P=P, status=status), ok


def _active_top(state: SlamState):
    """Slots in use from the front: 1 + the highest active slot (0 for an empty map); under
    ``vmap`` the batch's largest (see :func:`_batch_max`)."""
    cap = state.active.shape[0]
    return _batch_max(jnp.max(jnp.where(state.active, jnp.arange(1, cap + 1), 0)))


def _block_sizes(cap: int) -> list:
    """The leading slot blocks the active-block update and association choose from: capacity/8,
    /2 and all (sizes below 32 slots save less than their branch costs to compile)."""
    return sorted({c for c in (-(-cap // 8), -(-cap // 2), cap) if c >= min(cap, 32)})


def _block_index(sizes, top):
    """Index of the smallest of ``sizes`` that holds ``top`` slots (traced)."""
    return jnp.minimum(jnp.searchsorted(jnp.asarray(sizes), top, side="left"), len(sizes) - 1)


def _clamped_tile(k, t: int, n: int, lo: int = 0):
    """Start of the k-th ``t``-wide tile of [lo, n), the last one clamped to end at n, and which
    of its t entries are its own (not already covered by the tile before a clamped one)."""
    a = (lo + k * t).astype(jnp.int32)
    start = jnp.minimum(a, n - t)
    return start, start + jnp.arange(t) >= a


def _shared_bound(fn):
    """``fn(*arrays, bound)`` whose loop length is set by the traced ``bound``, with a batching
    rule: a vmapped batch runs every member's loop to the batch's largest bound (per-run loop
    lengths would make the loop select all of its carry at every iteration).  ``fn`` takes
    arrays with any leading batch axes (the rule passes the batched arrays as they are)."""
    wrapped = custom_vmap(fn)

    @wrapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        *arrays, bound = args
        arrays = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)
                  for a, b in zip(arrays, in_batched[:-1])]
        h = jnp.max(bound, axis=0) if in_batched[-1] else bound
        # ``fn`` takes the batch axis itself: under ``jax.vmap`` its slices and in-place
        # writes would become gathers and scatters.  Calling ``wrapped`` again lets an outer
        # vmap use this rule too.
        return wrapped(*arrays, h), True

    return wrapped


@jax.custom_jvp
def robot_cross_update(P, F, hi):
    """P with its robot–map blocks P_rl ← F P_rl and P_lr ← P_rlᵀ (n_r = F's size) over the
    columns n_r … ``hi`` − 1, in :data:`TILE`-wide strips (a loop whose length is set by the
    traced ``hi``); columns from ``hi`` on are untouched (zero for inactive slots).  Both
    strips are sums over k in one order, so a P symmetric to the bit stays so.  The
    derivative (custom JVP) is the dense formula's; under ``vmap`` the batch visits the
    strips of its largest ``hi``."""
    return _cross_tiled(P, F, hi)


def _cross_strips(P, F, hi):
    nr, n = F.shape[-1], P.shape[-1]  # P (..., n, n), F (..., nr, nr): leading axes a batch
    if n == nr:
        return P
    t = min(TILE, n - nr)
    nt = (jnp.maximum(jnp.asarray(hi, jnp.int32) - nr, 0) + t - 1) // t
    lead = P.shape[:-2]
    zl = (jnp.int32(0),) * len(lead)

    def strip(j, P):
        sb, new = _clamped_tile(j, t, n, nr)  # columns of a clamped strip already done keep theirs
        # Each write reads its own strip (no read of one region and write of another).
        z0 = jnp.int32(0)
        Rw = jax.lax.dynamic_slice(P, zl + (z0, sb), lead + (nr, t))  # P_rl strip (nr, t)
        Rn = sum(F[..., :, k, None] * Rw[..., k, None, :] for k in range(nr))
        P = jax.lax.dynamic_update_slice(P, jnp.where(new[None, :], Rn, Rw), zl + (z0, sb))
        Cl = jax.lax.dynamic_slice(P, zl + (sb, z0), lead + (t, nr))  # P_lr strip (t, nr)
        Cn = sum(Cl[..., :, k, None] * F[..., None, :, k] for k in range(nr))
        return jax.lax.dynamic_update_slice(P, jnp.where(new[:, None], Cn, Cl), zl + (sb, z0))

    return jax.lax.fori_loop(jnp.int32(0), nt, strip, P)


_cross_tiled = _shared_bound(_cross_strips)


@robot_cross_update.defjvp
def _robot_cross_update_jvp(primals, tangents):
    P, F, hi = primals
    dP, dF, _ = tangents
    nr, n = F.shape[0], P.shape[0]
    out = robot_cross_update(P, F, hi)
    moved = (jnp.arange(nr, n) < hi)[None, :]
    dRl = jnp.where(moved, dF @ P[:nr, nr:] + F @ dP[:nr, nr:], dP[:nr, nr:])
    dout = jax.lax.dynamic_update_slice(dP, dRl, (0, nr))
    return out, jax.lax.dynamic_update_slice(dout, dRl.T, (nr, 0))


# ---------------------------------------------------------------------------
# Update of observed, mapped landmarks (paper 000 eq. 37-43)
# ---------------------------------------------------------------------------

def _guard_inputs(valid, s, L):
    """Per-row inputs (s_k, L_k) that carry no derivative where ``valid`` is False.

    The observation of a masked row or an inactive slot (zero mean) is evaluated but
    discarded; at a singular point (e.g. the robot exactly on the zero landmark: atan2's
    derivative at (0, 0)) its value, Jacobian and derivatives are NaN, and NaN × 0 stays
    NaN.  Routing the invalid rows through ``stop_gradient`` keeps their NaN cotangents /
    tangents out of the shared robot block and the landmark means (a select, not a product),
    and :func:`_observe_batch` replaces their outputs by zeros.
    """
    K = L.shape[0]
    S = jnp.broadcast_to(s, (K,) + s.shape)
    S = jnp.where(valid[:, None], S, jax.lax.stop_gradient(S))
    L = jnp.where(valid[:, None], L, jax.lax.stop_gradient(L))
    return S, L


def _observe_batch(model, s, L, params, valid=None):
    """ẑ (K, d_z), H_s (K, d_z, n_r), H_l (K, d_z, d_l) for landmark means L (K, d_l).

    With ``valid`` (K,) bool, rows where it is False are evaluated on derivative-free
    inputs and returned as zeros (never NaN, also under grad / jvp; see _guard_inputs).
    """
    if valid is None:
        valid = jnp.ones(L.shape[:1], bool)
    S, L = _guard_inputs(valid, s, L)

    def one(s_k, l):
        if model.observe_jacobian is not None:
            return model.observe_jacobian(s_k, l, params)
        zh, (Hs, Hl) = value_and_jacfwd(model.observe, argnums=(0, 1))(s_k, l, params)
        return zh, Hs, Hl

    zh, Hs, Hl = jax.vmap(one)(S, L)
    zh = jnp.where(valid[:, None], zh, 0.0)
    Hs = jnp.where(valid[:, None, None], Hs, 0.0)
    Hl = jnp.where(valid[:, None, None], Hl, 0.0)
    return zh, Hs, Hl


def update(state: SlamState, model: SlamModel, z, slots, mask, R, params=None,
           gate=None, robust=None, row_stats: bool = False,
           num_iter: int = 1, tol=None, active_only: bool = False, joseph: bool = True):
    """Joint EKF update with K measurements of mapped landmarks.

    Args:
      z: (K, d_z) measurements (NaN allowed where masked).
      slots: (K,) int slot of the landmark each measurement observes; a slot outside
        [0, capacity) (−1: none) is no landmark, and a row with its mask set there is dropped
        and counted (``MASKED_INPUT``).
      mask: (K,) bool measurement present.  Measurements of inactive slots are dropped;
        those with non-finite entries too, counted via ``MASKED_INPUT``.
      R: (d_z, d_z) or (K, d_z, d_z) measurement covariance (a row the mask leaves out is not
        read, NaN included); called eagerly, a wrong shape or a selected row's R that is not
        symmetric PSD is an :class:`InputError` naming ``R[k]``.
      gate: optional chi-square threshold on each measurement's own NIS
        (d_z dof), or a callable ``gate(dof)`` such as :func:`jaxslam.filters.ekf.chi2_gate`
        (called with d_z; a callable raised a bare TypeError); gated measurements are dropped
        and flagged ``GATED``.  A concrete threshold must be > 0 (:class:`InputError`); a
        traced one that is not (NaN included) gates every row and sets ``NON_FINITE``
        (``UpdateInfo.rejected``) — a NaN gate used to switch gating off without a flag.
      robust: optional degrees of freedom ν (scalar, traced) of a Student-t measurement
        model: each row's R is divided by its EM weight w = (ν + d_z)/(ν + d²) ≤ 1 (d² its
        marginal NIS), so an outlier pulls the estimate less and less the further out it is,
        but is never cut off (a filter that has become over-confident still hears its
        measurements, unlike with a hard gate).  ν → ∞ is the Gaussian update.

      row_stats: also report each row's marginal NIS and log det (below) when neither a
        gate nor ``robust`` needs them (static; they cost a small Cholesky per row).
      num_iter: static number of linearisations (1 = EKF; > 1 = iterated EKF, Gauss–Newton
        on the joint update as :func:`jaxslam.filters.ekf.update`): each iteration
        re-linearises ``observe`` at the current robot and landmark estimates and re-solves
        from the prior; gating, weights, NIS and log det stay those of the prior's
        linearisation; the covariance uses the last one.  ``NOT_CONVERGED`` is set when the
        last iteration still moved a component by more than ``tol`` prior σ (default 1e-6
        float64, 1e-3 float32).

      active_only: static; compute the gain on the smallest leading block (capacity/8, /2 or
        all slots) that holds every active slot, with the valid rows moved to the front and
        the smaller of K/2 and K rows that holds them (one ``lax.switch``), and apply the
        covariance correction only to the rows and columns up to the highest active slot
        (:func:`sym_rank_update`).  Inactive slots have no covariance with anything, so this
        is the same update (the same estimates, to rounding) at a cost set by the mapped
        landmarks, not the capacity.  Differentiable in forward and reverse mode (the
        covariance correction's derivative is the dense one); under ``vmap`` the batch shares
        the block of its fullest map (a custom batching rule), so no branch or tile is run
        for one run and selected away for another.

      joseph: static; True (default): the covariance by the factored Joseph form
        (I − K H) P (I − K H)ᵀ + K R Kᵀ, a symmetric rank-2m correction of P.  False: the
        standard form P − K S Kᵀ = P − (K L)(K L)ᵀ (L the Cholesky factor of S), a rank-m
        correction with half the products — the same in exact arithmetic, PD only as long as
        rounding keeps it so (docs/papers.md measures both over 10⁵ steps).

    Returns (state, UpdateInfo).
    ``UpdateInfo.d2`` and ``row_logdet`` hold each row's marginal NIS and log det S_i before
    any weighting (the terms of a per-row likelihood); zeros unless ``gate``, ``robust`` or
    ``row_stats`` asked for them.
    Cost O(n²·K·d_z) through gathered columns (with ``active_only``, n of the leading block
    that holds the map for the correction of P, and O(n·(K·d_z)²) for the gain).
    Called eagerly it is compiled once per model and static options
    (:func:`jaxslam.compilation.call_compiled`, ``after="auto"``).
    """
    z, slots, mask, R = _check_update(state, model, z, slots, mask, R, gate, robust, num_iter)

    def step(opts, st, z, slots, mask, R):
        params, gate, robust, tol = opts
        return _update(st, model, z, slots, mask, R, params, gate, robust, row_stats, num_iter, tol,
                       active_only, joseph)

    return call_compiled(("ekf_slam.update", model, row_stats, num_iter, active_only, joseph), step,
                         (state, z, slots, mask, R), (params, gate, robust, tol), after="auto")


def _check_update(state: SlamState, model: SlamModel, z, slots, mask, R, gate, robust, num_iter: int):
    """:func:`update`'s checks, in order (shapes, and the values known now); returns
    ``(z, slots, mask, R)`` as arrays, R as one (d_z, d_z) matrix per row."""
    _check_sizes(state, model)
    _check_options(gate, robust, num_iter)
    check_gate_size(gate, model.meas_dim)
    z, slots, mask = _rows(z, slots, mask, model.meas_dim, "slots")
    return z, slots, mask, _rows_R(R, mask, z.shape[0], model.meas_dim, state.x.dtype)


def _update(state: SlamState, model: SlamModel, z, slots, mask, R, params, gate, robust, row_stats: bool,
            num_iter: int, tol, active_only: bool, joseph: bool):
    """:func:`update`'s computation."""
    z, slots, mask, R = _check_update(state, model, z, slots, mask, R, gate, robust, num_iter)
    nr, dl, cap = _sizes(state, model)
    dz = model.meas_dim
    K = z.shape[0]
    dtype = state.x.dtype
    in_range = (slots >= 0) & (slots < cap)  # −1 (or any slot outside the map): no landmark
    slots = jnp.clip(slots, 0, cap - 1)

    finite = jnp.all(jnp.isfinite(z), axis=-1)
    valid = mask & in_range & state.active[slots] & finite
    bad_input = (mask & in_range & state.active[slots] & ~finite) | (mask & ~in_range)
    z_safe = jnp.where(valid[:, None], z, 0.0).astype(dtype)
    # a row not used may carry any R, NaN included: it must not reach the joint S (0 · NaN)
    R = jnp.where(valid[:, None, None], R, jnp.eye(dz, dtype=dtype))

    s = state.x[:nr]
    P = state.P
    n = P.shape[0]
    K_all, m_all = K, K * dz

    def gather_PHt(Mr, Ml, Hs, Hl):
        # M Hᵀ for the sparse H from M's columns at H's support: (rows, K, dz)
        return jnp.einsum("ni,kzi->nkz", Mr, Hs) + jnp.einsum("nkj,kzj->nkz", Ml, Hl)

    def factors(nb, K, rows_in):
        """Gain and correction factors on the leading ``nb`` rows and the first ``K`` rows of
        ``rows_in`` (both static; rows of P beyond ``nb`` hold no covariance with the measured
        blocks when ``nb`` covers every active slot, rows of ``rows_in`` beyond ``K`` are not
        valid).  Outputs padded to n rows and the K_all measurement rows."""
        z_safe, slots, valid, R = (a[:K] for a in rows_in)
        m = K * dz
        L = take(state.x[nr:].reshape(cap, dl), slots, 0)
        zh, Hs, Hl = _observe_batch(model, s, L, params, valid)
        res = jnp.where(valid[:, None], jax.vmap(_residual(model))(z_safe, zh), 0.0)
        def rows(M, Hs, Hl):
            # rows of an (n, ...) array at H's support, contracted with H: H M
            Mr = M[:nr]  # (nr, K, dz)
            Ml = take_blocks(M, slots, dl, nr, 0)  # (K, dl, K, dz)
            return jnp.einsum("kzi,imw->kzmw", Hs, Mr) + jnp.einsum("kzj,kjmw->kzmw", Hl, Ml)

        # The columns of P's leading rows that the sparse H touches: all the update needs of
        # P besides the final correction, O(nb·K·d_l).
        Pr_b, Pl_b, x_b = P[:nb, :nr], take_blocks(P[:nb], slots, dl, nr, 1), state.x[:nb]
        PHt = gather_PHt(Pr_b, Pl_b, Hs, Hl)  # (nb, K, dz)
        HPHt = rows(PHt, Hs, Hl)  # (K, dz, K, dz)
        valid_ = valid
        # Individual gating on the marginal innovation covariance of each measurement.
        S_marg = jnp.einsum("kzkw->kzw", HPHt) + R
        if gate is not None or robust is not None or row_stats:
            S_safe = jnp.where(valid_[:, None, None], S_marg, jnp.eye(dz, dtype=dtype))
            d2_each, logdet_each = jax.vmap(_nis_logdet_small)(
                jnp.where(valid_[:, None], res, 0.0), S_safe)
            d2_each = jnp.where(valid_, d2_each, 0.0)
            logdet_each = jnp.where(valid_, logdet_each, 0.0)
        else:
            d2_each = logdet_each = jnp.zeros(valid_.shape, dtype)
        if gate is not None:
            # a threshold that is not > 0 (a traced NaN: d² > NaN is False, gating was off
            # without a word) gates every row; the status says NON_FINITE (below)
            thr = _threshold(gate, jnp.int32(dz), dtype)
            gated = valid_ & ((d2_each > thr) | ~(thr > 0))
            valid_ = valid_ & ~gated
        else:
            gated = jnp.zeros_like(valid_)
        if robust is not None:
            nu_t = jnp.asarray(robust, dtype)
            w = jnp.minimum((nu_t + dz) / (nu_t + d2_each), 1.0)
            R = R / jnp.where(valid_, w, 1.0)[:, None, None]

        vv = jnp.repeat(valid_.astype(dtype), dz)  # (K·dz,)
        VV = vv[:, None] * vv[None, :]
        R_blk = jnp.einsum("kzw,kj->kzjw", R, jnp.eye(K, dtype=dtype))  # block diagonal, no scatter
        R_used = R_blk.reshape(m, m) * VV

        def solve(PHt_, HPHt_, res_):
            PHt_f = PHt_.reshape(-1, m) * vv[None, :]
            S = HPHt_.reshape(m, m) * VV + R_used + jnp.diag(1.0 - vv)
            nu = res_.reshape(m) * vv
            # Gain through the explicit m×m inverse of S from its Cholesky factor: m is small,
            # and a triangular solve with n right-hand sides is far slower on CPU than one
            # (n, m)·(m, m) product.
            Lc = jnp.linalg.cholesky(symmetrize(S))
            Sinv = jax.scipy.linalg.cho_solve((Lc, True), jnp.eye(m, dtype=dtype))
            Kg = PHt_f @ Sinv  # (nb, m) = P Hᵀ S⁻¹
            chol_ok = jnp.all(jnp.isfinite(Lc))
            # Guard on the small quantities (O(n·m)): with P, P Hᵀ and K finite the correction
            # is finite, so no O(n²) check or select of it is needed.  A rejected update zeroes
            # the gain, which leaves x and P unchanged.
            ok = chol_ok & jnp.all(jnp.isfinite(Kg)) & jnp.all(jnp.isfinite(nu))
            Kg = jnp.where(ok, Kg, 0.0)
            x_new = x_b + Kg @ jnp.where(ok, nu, 0.0)
            return PHt_f, nu, Lc, Sinv, Kg, chol_ok, ok, x_new

        PHt_f, nu, Lc, Sinv, Kg, chol_ok, ok, x_new = solve(PHt, HPHt, res)
        Hs_f, Hl_f, Lc_f = Hs, Hl, Lc
        not_conv = jnp.asarray(False)
        if int(num_iter) > 1:
            c = (nb - nr) // dl

            def gn(carry, _):
                xi, _, _, _, _, _, _, ok_i = carry
                si = xi[:nr]
                Li = take(xi[nr:].reshape(c, dl), slots, 0)
                zi, Hs_i, Hl_i = _observe_batch(model, si, Li, params, valid_)
                lin = (jnp.einsum("kzi,i->kz", Hs_i, x_b[:nr] - si)
                       + jnp.einsum("kzj,kj->kz", Hl_i, L - Li))
                res_i = jnp.where(valid_[:, None], jax.vmap(_residual(model))(z_safe, zi) - lin, 0.0)
                PHt_i = gather_PHt(Pr_b, Pl_b, Hs_i, Hl_i)
                PHt_fi, _, Lc_i, _, Kg_i, _, ok_n, x_n = solve(PHt_i, rows(PHt_i, Hs_i, Hl_i), res_i)
                return (x_n, PHt_fi, Kg_i, Hs_i, Hl_i, Lc_i, xi, ok_i & ok_n), None

            (x_new, PHt_f, Kg, Hs_f, Hl_f, Lc_f, x_prev, ok_it), _ = jax.lax.scan(
                gn, (x_new, PHt_f, Kg, Hs, Hl, Lc, x_b, ok), None, length=int(num_iter) - 1)
            tol_v = jnp.asarray((1e-6 if dtype == jnp.float64 else 1e-3) if tol is None else tol, dtype)
            dP = jnp.diagonal(P)[:nb]
            sig = jnp.sqrt(jnp.maximum(dP, jnp.finfo(dtype).tiny))
            moved = jnp.max(jnp.where(dP > 0, jnp.abs(x_new - x_prev) / sig, 0.0))
            # a failed iteration keeps the prior (as a failed first solve does)
            x_new = jnp.where(ok_it, x_new, x_b)
            Kg = jnp.where(ok_it, Kg, 0.0)
            ok = ok & ok_it
            not_conv = ok & jnp.any(valid_) & (moved > tol_v)

        if joseph:
            # Factored Joseph form (I − K H) P (I − K H)ᵀ + K R Kᵀ = A − (A Hᵀ − K R) Kᵀ with
            # A = P − K (P Hᵀ)ᵀ, as a symmetric rank-2m correction P − ½ (K Gᵀ + G Kᵀ),
            # G = P Hᵀ + A Hᵀ − K R.  A's columns at H's support come without forming A.
            Ar = Pr_b - Kg @ PHt_f[:nr].T  # (nb, n_r)
            Al = Pl_b - jnp.einsum("nm,kjm->nkj", Kg, take_blocks(PHt_f, slots, dl, nr, 0))  # (nb, K, d_l)
            AHt = gather_PHt(Ar, Al, Hs_f, Hl_f).reshape(-1, m) * vv[None, :]
            G = PHt_f + AHt - Kg @ R_used
        else:
            # Standard form P − K S Kᵀ = P − U Uᵀ, U = K L (S = L Lᵀ; zero where rejected).
            G = Kg @ Lc_f

        def pad(a):  # rows beyond nb: no correction; columns beyond m: none
            a = jnp.concatenate([a, jnp.zeros((n - nb,) + a.shape[1:], a.dtype)]) if nb < n else a
            return jnp.pad(a, ((0, 0), (0, m_all - m))) if m < m_all else a

        def pad_k(a, v):  # measurement rows beyond K: invalid
            return jnp.concatenate([a, jnp.full((K_all - K,) + a.shape[1:], v, a.dtype)]) if K < K_all else a

        def pad_s(a, v):  # the joint innovation terms: identity rows for the missing ones
            if m == m_all:
                return a
            return jax.scipy.linalg.block_diag(a, v * jnp.eye(m_all - m, dtype=a.dtype))

        x_full = jnp.concatenate([x_new, state.x[nb:]]) if nb < n else x_new
        return (x_full, pad(Kg), pad(G), pad_k(nu.reshape(K, dz), 0.0).reshape(-1), pad_s(Lc, 1.0),
                pad_s(Sinv, 1.0), chol_ok, ok, not_conv, pad_k(valid_, False), pad_k(gated, False),
                pad_k(d2_each, 0.0), pad_k(logdet_each, 0.0))

    rows_in = (z_safe, slots, valid, R)
    if active_only:
        # The factors on the smallest leading block (capacity/8, /2, /1) holding every active
        # slot and the smaller count (K/2, K) holding the valid rows (moved to the front, order
        # kept), chosen at run time; P itself stays out of the switch (a conditional that
        # writes P would copy it) and its correction visits only the mapped rows' tiles.
        # (under vmap: the batch's largest, so one branch runs for the whole batch.)  Twelve
        # branches (with /4 and K/4) took the paper-000 run's compile from 3.1 to 5.1 s for
        # 0.005-0.02 s less run time.
        top = _active_top(state)
        # (row counts of fewer than 24 scalars save less than their branch costs to compile:
        # a small problem gets fewer branches, or none; the same for blocks, _block_sizes)
        sizes = _block_sizes(cap)
        which = _block_index(sizes, top)
        counts = sorted({max(1, -(-K_all // 2)), K_all}) if m_all >= 24 else [K_all]
        branches = [functools.partial(factors, nr + c * dl, k) for k in counts for c in sizes]
        if len(counts) == 1:
            out = jax.lax.switch(which, branches, rows_in)
        else:
            order = jnp.argsort(~valid, stable=True)
            n_valid = _batch_max(jnp.sum(valid, dtype=jnp.int32))
            which_k = jnp.minimum(jnp.searchsorted(jnp.asarray(counts), n_valid, side="left"),
                                  len(counts) - 1)
            out = jax.lax.switch(which_k * len(sizes) + which, branches,
                                 tuple(take(a, order, 0) for a in rows_in))
            # the per-row outputs back in the caller's row order (ν, L and S⁻¹ stay
            # compacted: NIS and log det do not depend on the order)
            inv = jnp.argsort(order)
            out = out[:9] + tuple(take(a, inv, 0) for a in out[9:])
    else:
        out = factors(n, K_all, rows_in)
    # a traced gate that is not > 0 (NaN included) with rows to use: every row gated, flagged
    # NON_FINITE and counted as rejected (one scalar test per update)
    gate_bad = (jnp.any(valid) & ~(_threshold(gate, jnp.int32(dz), dtype) > 0)) if gate is not None \
        else jnp.asarray(False)
    x_new, Kg, G, nu, Lc, Sinv, chol_ok, ok, not_conv, valid, gated, d2_each, logdet_each = out
    if active_only:
        # nothing to correct (no row used, or the update rejected): no tile is visited
        hi = jnp.where(ok & jnp.any(valid), nr + top * dl, 0)
        P_new = sym_rank_update(P, Kg, G, hi) if joseph else sym_outer_update(P, G, hi)
    else:
        P_new = symmetrize(_sym_rank_update_dense(P, Kg, G) if joseph else _sym_outer_update_dense(P, G))

    nu_ok = jnp.where(ok, nu, 0.0)
    nis = nu_ok @ (Sinv @ nu_ok)
    # Unused rows carry 1 on S's diagonal: they add log 1 = 0.
    logdet = 2.0 * jnp.sum(jnp.log(jnp.where(ok, jnp.diagonal(Lc), 1.0)))
    status = (
        state.status
        | _flag_if(~ok | gate_bad, errors.NON_FINITE)
        | _flag_if(~chol_ok, errors.NOT_PSD)
        | _flag_if(jnp.any(gated), errors.GATED)
        | _flag_if(jnp.any(bad_input), errors.MASKED_INPUT)
        | _flag_if(not_conv, errors.NOT_CONVERGED)
    )
    info = UpdateInfo(
        nis=jnp.where(ok, nis, 0.0),
        dof=jnp.where(ok, jnp.sum(valid) * dz, 0),
        used=valid & ok,
        gated=gated,
        logdet=jnp.where(ok, logdet, 0.0),
        d2=d2_each,
        row_logdet=logdet_each,
        rejected=(~ok & jnp.any(valid)) | gate_bad,
    )
    return state._replace(x=x_new, P=P_new, status=status), info


#: Tile size (rows and columns) of :func:`sym_rank_update`.
TILE = 64


def _sym_rank_update_dense(P, U, V):
    # one product: V Uᵀ = (U Vᵀ)ᵀ; its reverse-mode derivative is two products (the
    # cotangent of T + Tᵀ is symmetric), where U Vᵀ + V Uᵀ would give four
    T = U @ V.T
    return P - 0.5 * (T + T.T)


@jax.custom_jvp
def _sym_outer_update_dense(P, U):
    return P - U @ U.T


@_sym_outer_update_dense.defjvp
def _sym_outer_update_dense_jvp(primals, tangents):
    P, U = primals
    dP, dU = tangents
    dUUt = dU @ U.T  # the tangent as T + Tᵀ: its transpose is one product, not two
    return _sym_outer_update_dense(P, U), dP - (dUUt + dUUt.T)


@jax.custom_jvp
def sym_rank_update(P, U, V, hi):
    """P − ½ (U Vᵀ + V Uᵀ) for symmetric P (n, n) and U, V (n, r) whose rows from ``hi`` on
    are zero: only the leading ``hi`` rows and columns are visited, in :data:`TILE`-sized
    tiles of the upper triangle (a loop whose length is set by the traced ``hi``), each
    subtracted with its mirror, so a P symmetric to the bit stays so; beyond ``hi``, P is
    untouched.  Costs O(hi²·r) instead of O(n²·r); the derivative (custom JVP) is the dense
    formula's.  Under ``vmap`` every run visits the tiles of the batch's largest ``hi``
    (a custom batching rule: per-run loop lengths would select all of P at every tile)."""
    return _tiled_rank_update(P, U, V, hi)


@jax.custom_jvp
def sym_outer_update(P, U, hi):
    """P − U Uᵀ for symmetric P (n, n) and U (n, r) whose rows from ``hi`` on are zero, in the
    tiles of :func:`sym_rank_update` (half its products for the same r); the same symmetry,
    cost bound, derivative (the dense formula's, a custom JVP) and batching rule."""
    return _tiled_outer_update(P, U, hi)


@sym_outer_update.defjvp
def _sym_outer_update_jvp(primals, tangents):
    P, U, hi = primals
    dP, dU, _ = tangents
    dUUt = dU @ U.T
    return sym_outer_update(P, U, hi), dP - (dUUt + dUUt.T)


@custom_vmap
def _batch_max(a):
    """``a``; under ``vmap``, the batch's maximum, unbatched (so that a block size or a loop
    length chosen from it is one for the whole batch, not a select between per-run ones)."""
    return a


@_batch_max.def_vmap
def _batch_max_vmap(axis_size, in_batched, a):
    return (jnp.max(a, axis=0) if in_batched[0] else a), False


def _tile_loop(P, As, Bs, scale, hi):
    # P − scale · A Bᵀ (A = [As...], B = [Bs...] side by side; A Bᵀ symmetric) on the upper
    # triangle's tiles: one loop over the diagonal tiles, then one flat loop over the tile
    # pairs above it, each written with its mirror (no nested loop, no per-tile test for the
    # diagonal); the factors are sliced per tile and joined there (joining them whole would
    # copy (n, r) arrays on every call, even one with no tile).
    # P (..., n, n), As and Bs (..., n, r): leading axes a batch (see _shared_bound).
    n = P.shape[-1]
    t = min(TILE, n)
    nt = (jnp.asarray(hi, jnp.int32) + t - 1) // t
    # the pairs (i < j) ordered by j, so the first nt (nt − 1) / 2 are those of the first nt tiles
    ii, jj = np.tril_indices(-(-n // t), -1)[::-1]  # (i, j) = (col, row) of the lower triangle
    pair_i, pair_j = jnp.asarray(ii, jnp.int32), jnp.asarray(jj, jnp.int32)
    lead = P.shape[:-2]
    zl = (jnp.int32(0),) * len(lead)

    def mT(a):
        return jnp.swapaxes(a, -1, -2)

    def rows(fs, k):
        # rows of a clamped tile already covered by the previous tile get no correction
        s, m = _clamped_tile(k, t, n)
        return s, jnp.concatenate([jnp.where(m[:, None], jax.lax.dynamic_slice_in_dim(f, s, t, axis=-2), 0.0)
                                   for f in fs], axis=-1)

    # Each write reads its own tile (a read of one tile and a write of another would make XLA
    # copy P).
    def sub(P, D, sa, sb):
        return jax.lax.dynamic_update_slice(
            P, jax.lax.dynamic_slice(P, zl + (sa, sb), lead + (t, t)) - scale * D, zl + (sa, sb))

    def diagonal(i, P):
        s, A = rows(As, i)
        D = A @ mT(rows(Bs, i)[1])
        return sub(P, 0.5 * (D + mT(D)), s, s)  # symmetric to the bit

    def pair(p, P):
        (sa, A), (sb, B) = rows(As, pair_i[p]), rows(Bs, pair_j[p])
        D = A @ mT(B)
        return sub(sub(P, D, sa, sb), mT(D), sb, sa)

    P = jax.lax.fori_loop(jnp.int32(0), nt, diagonal, P)
    if ii.size == 0:  # one tile holds P
        return P
    return jax.lax.fori_loop(jnp.int32(0), nt * (nt - 1) // 2, pair, P)


_tiled_rank_update = _shared_bound(lambda P, U, V, hi: _tile_loop(P, (U, V), (V, U), 0.5, hi))
_tiled_outer_update = _shared_bound(lambda P, U, hi: _tile_loop(P, (U,), (U,), 1.0, hi))


@sym_rank_update.defjvp
def _sym_rank_update_jvp(primals, tangents):
    P, U, V, hi = primals
    dP, dU, dV, _ = tangents
    out = sym_rank_update(P, U, V, hi)
    T = dU @ V.T + dV @ U.T  # the tangent as T + Tᵀ: two products, and two in its transpose
    return out, dP - 0.5 * (T + T.T)


def update_robot(state: SlamState, model: SlamModel, observe, z, mask, R, params=None,
                 residual=None):
    """EKF update with a measurement of the robot block only, z = h(s) + v.

    For sensors that observe the vehicle and no landmark (paper 004's optical
    flow and gyro yaw rate, eq. 4.10 state V and ω).  ``observe(s, params)``
    -> (d_z,); ``z`` (d_z,); ``mask`` (d_z,) bool per component (a masked or
    non-finite component contributes nothing); ``R`` (d_z, d_z).  H = ∂h/∂s
    by forward-mode autodiff; the gain uses the gathered robot columns
    P[:, :n_r] Hᵀ and the factored Joseph form (cost O(n²·d_z)), as
    :func:`update`.  A failed factorisation or non-finite gain keeps the prior
    and sets ``NON_FINITE`` / ``NOT_PSD``; non-finite inputs set ``MASKED_INPUT``.
    Called eagerly, a mask that is not bool (or 0/1 integers) or an ``R`` that is not symmetric
    PSD on the masked-in components is an :class:`InputError` naming it.
    Works on any map (also an empty one).  Returns (state, UpdateInfo) with
    ``used``/``gated`` of shape (d_z,).  Called eagerly it is compiled once per model and
    ``observe`` (:func:`jaxslam.compilation.call_compiled`, ``after="auto"``).
    """
    _check_update_robot(np.shape(z), mask, R)
    return call_compiled(("ekf_slam.update_robot", model, observe, residual),
                         lambda opts, st, z, mask, R: _update_robot(st, model, observe, z, mask, R, opts[0], residual),
                         (state, z, mask, R), (params,), after="auto")


def _check_update_robot(z_shape, mask, R):
    """:func:`update_robot`'s checks of values known now: ``mask`` bool (or 0/1), ``R`` symmetric
    PSD on the masked-in components."""
    dz = z_shape[0]
    check_mask(mask, "mask")
    if is_concrete(R, mask) and np.shape(R) == (dz, dz):  # as update's: a used component's R PSD
        check_psd(R, "R", valid=np.broadcast_to(np.asarray(mask, bool), (dz,)))


def _update_robot(state: SlamState, model: SlamModel, observe, z, mask, R, params, residual):
    """:func:`update_robot`'s computation."""
    nr = model.robot_dim
    dtype = state.x.dtype
    z = jnp.asarray(z, dtype)
    dz = z.shape[0]
    _check_update_robot(z.shape, mask, R)
    mask = jnp.broadcast_to(jnp.asarray(mask, bool), (dz,))
    finite = jnp.isfinite(z)
    valid = mask & finite
    z_safe = jnp.where(valid, z, 0.0)
    s = state.x[:nr]
    zh, Hs = value_and_jacfwd(lambda s_: observe(s_, params))(s)
    res = (residual if residual is not None else (lambda a, b: a - b))(z_safe, zh)
    v = valid.astype(dtype)
    VV = v[:, None] * v[None, :]
    R_used = jnp.where(VV > 0, jnp.asarray(R, dtype), 0.0)  # a masked component's R (NaN too) unread
    PHt = (state.P[:, :nr] @ Hs.T) * v[None, :]  # (n, dz)
    S = (Hs @ PHt[:nr]) * VV + R_used + jnp.diag(1.0 - v)
    nu = res * v
    Lc = jnp.linalg.cholesky(symmetrize(S))
    Sinv = jax.scipy.linalg.cho_solve((Lc, True), jnp.eye(dz, dtype=dtype))
    Kg = PHt @ Sinv
    chol_ok = jnp.all(jnp.isfinite(Lc))
    ok = chol_ok & jnp.all(jnp.isfinite(Kg)) & jnp.all(jnp.isfinite(nu))
    Kg = jnp.where(ok, Kg, 0.0)
    nu_ok = jnp.where(ok, nu, 0.0)
    x_new = state.x + Kg @ nu_ok
    A = state.P - Kg @ PHt.T
    AHt = (A[:, :nr] @ Hs.T) * v[None, :]
    P_new = symmetrize(A - (AHt - Kg @ R_used) @ Kg.T)
    status = (
        state.status
        | _flag_if(~ok, errors.NON_FINITE)
        | _flag_if(~chol_ok, errors.NOT_PSD)
        | _flag_if(jnp.any(mask & ~finite), errors.MASKED_INPUT)
    )
    info = UpdateInfo(
        nis=jnp.where(ok, nu_ok @ (Sinv @ nu_ok), 0.0),
        dof=jnp.where(ok, jnp.sum(valid), 0),
        used=valid & ok,
        gated=jnp.zeros_like(valid),
        rejected=~ok & jnp.any(valid),
    )
    return state._replace(x=x_new, P=P_new, status=status), info


def _nis_logdet_small(nu, S):
    """(νᵀS⁻¹ν, log det S) of one small (d ≤ 4) SPD block by an unrolled Cholesky
    (:func:`jaxslam.linalg.cholesky_small`): no LAPACK call (a non-PD block gives NaN, as
    LAPACK would)."""
    n = S.shape[-1]
    if n > 4:
        L = jnp.linalg.cholesky(symmetrize(S))
        w = jax.scipy.linalg.solve_triangular(L, nu, lower=True)
        return jnp.sum(w * w), 2.0 * jnp.sum(jnp.log(jnp.diagonal(L)))
    L = cholesky_small(symmetrize(S))
    w = []  # forward substitution L w = ν, unrolled
    for i in range(n):
        w.append((nu[i] - sum(L[i, k] * w[k] for k in range(i))) / L[i, i])
    return sum(wi * wi for wi in w), 2.0 * sum(jnp.log(L[i, i]) for i in range(n))


def update_nll(info: UpdateInfo, dz: int, nu=None):
    """Innovation NLL of one :func:`update` from its :class:`UpdateInfo`: the Gaussian
    ½ (NIS + log det S + m log 2π) of the joint innovation, or with ``nu`` the sum of the used
    rows' Student-t terms (:func:`jaxslam.stats.student_t_nll`; the update must then be the
    ``robust=nu`` one, which reports each row's d² and log det S_i).  ``dz``: scalars per row.
    Returns ``(nll, scalars used)``."""
    dtype = info.nis.dtype
    if nu is None:
        nll = 0.5 * (info.nis + info.logdet + info.dof.astype(dtype) * math.log(2 * math.pi))
    else:
        check_student_t_nu(nu)  # the rows' d² are sums of squares: not checked per update
        nll = jnp.sum(jnp.where(info.used, _student_t_nll(info.d2, info.row_logdet, nu, dz), 0.0))
    return nll, (jnp.sum(info.used) * dz).astype(dtype)


def _nis_small(nu, S):
    return _nis_logdet_small(nu, S)[0]


# ---------------------------------------------------------------------------
# Registration of new landmarks (paper 000 eq. 44-53)
# ---------------------------------------------------------------------------

def add_landmark(state: SlamState, model: SlamModel, slot, mean, cov_ll, cov_lx, lm_id, ok=True):
    """Write a landmark into ``slot``: mean (d_l,), P_ll (d_l, d_l), P_lx (d_l, n).

    ``cov_lx`` is the cross-covariance with the whole state (its own block is
    overwritten by ``cov_ll``).  Nothing is written where ``ok`` is False.
    Used by :func:`register` and by systems with their own initialisers
    (e.g. trilateration for range-only SLAM).

    Shapes are checked (static), and when concrete, ``slot`` (an int in [0, capacity)) and
    ``cov_ll`` (symmetric PSD), ``mean`` and ``cov_lx`` (finite): :class:`InputError` naming the
    argument.  A traced ``slot`` outside the map is never clamped: nothing is written and
    ``MASKED_INPUT`` is set; a traced non-finite ``mean`` / ``cov_ll`` / ``cov_lx`` writes nothing
    and sets ``NON_FINITE`` (a NaN was written into the state, active, with status 0).
    """
    _check_sizes(state, model)
    nr, dl, cap = _sizes(state, model)
    n = state.x.shape[0]
    if is_concrete(slot):
        if np.ndim(slot) != 0 or not np.issubdtype(np.asarray(slot).dtype, np.integer):
            raise InputError(f"slot: expected an integer slot, got {slot!r}")
        if not 0 <= int(slot) < cap:
            raise InputError(f"slot: {int(slot)} is outside the map's slots [0, {cap})")
    elif jnp.ndim(slot) != 0 or not jnp.issubdtype(jnp.result_type(slot), jnp.integer):
        raise InputError(f"slot: expected an integer slot, got shape {jnp.shape(slot)} dtype "
                         f"{jnp.result_type(slot)}")
    for nm, a, want in (("mean", mean, (dl,)), ("cov_ll", cov_ll, (dl, dl)), ("cov_lx", cov_lx, (dl, n))):
        if tuple(jnp.shape(a)) != want:
            raise InputError(f"{nm}: expected shape {want} (lm_dim {dl}, state size {n}), got "
                             f"{tuple(jnp.shape(a))}")
    if not (is_concrete(ok) and not np.any(np.asarray(ok))):
        if is_concrete(cov_ll):
            check_psd(cov_ll, "cov_ll")
        check_finite(mean, "mean")
        check_finite(cov_lx, "cov_lx")
    dtype = state.x.dtype
    slot = jnp.asarray(slot, jnp.int32)
    in_map = (slot >= 0) & (slot < cap)
    status = state.status | _flag_if(jnp.asarray(ok, bool) & ~in_map, errors.MASKED_INPUT)
    ok = jnp.asarray(ok, bool) & in_map
    slot = jnp.clip(slot, 0, cap - 1)  # only read or written where ok (in the map)
    mean = jnp.asarray(mean, dtype)
    cov_ll = jnp.asarray(cov_ll, dtype)
    cov_lx = jnp.asarray(cov_lx, dtype)
    finite = jnp.all(jnp.isfinite(mean)) & jnp.all(jnp.isfinite(cov_ll)) & jnp.all(jnp.isfinite(cov_lx))
    status = status | _flag_if(ok & ~finite, errors.NON_FINITE)
    ok = ok & finite
    start = nr + slot * dl
    zero = jnp.zeros((), start.dtype)  # lax wants index arguments of one integer type
    row = jax.lax.dynamic_update_slice(cov_lx, cov_ll, (zero, start))  # (dl, n)
    P = state.P
    # Guard on the written rows/columns only (O(n)); a select over P would be O(n²).
    row = jnp.where(ok, row, jax.lax.dynamic_slice(P, (start, zero), (dl, n)))
    mean = jnp.where(ok, mean, jax.lax.dynamic_slice(state.x, (start,), (dl,)))
    P = jax.lax.dynamic_update_slice(P, row, (start, zero))
    P = jax.lax.dynamic_update_slice(P, row.T, (zero, start))
    x = jax.lax.dynamic_update_slice(state.x, mean, (start,))
    active = state.active.at[slot].set(jnp.where(ok, True, state.active[slot]))
    ids = state.ids.at[slot].set(jnp.where(ok, jnp.int32(lm_id), state.ids[slot]))
    return state._replace(x=x, P=P, active=active, ids=ids, status=status)


def register(state: SlamState, model: SlamModel, z, lm_ids, mask, R, params=None) -> SlamState:
    """Register K candidate landmarks (paper 000 eq. 44-53), written jointly.

    For each valid candidate k: l_k = g(s, z_k) (model.inverse), G_s,k = ∂g/∂s,
    G_z,k = ∂g/∂z, P_{l_k l_k} = G_s,k P_ss G_s,kᵀ + G_z,k R_k G_z,kᵀ (eq. 48),
    P_{l_k x} = G_s,k P_s,: (eq. 50) and P_{l_j l_k} = G_s,j P_ss G_s,kᵀ (j ≠ k).
    The k-th valid candidate takes the k-th free slot (lowest index first).  A
    candidate with no free slot increments ``overflow`` and sets
    ``CAPACITY_OVERFLOW`` — never silently lost.  ``R`` as :func:`update`'s (checked the same
    way when called eagerly).  Non-finite measurements are
    skipped and flagged ``MASKED_INPUT``; a candidate whose landmark or
    covariance is non-finite is skipped and takes no slot.

    All candidates are initialised from the same (unchanged) robot block, so this
    joint write equals registering them one after another (each seeing the
    previous ones' cross-covariances) exactly, at the cost of one (K·d_l, n)
    row block and one scatter of rows and columns: O(K·d_l·n) — no per-candidate
    pass over P.  A call with no candidate (``mask`` all False) skips the work, and a call on a
    full map only counts the refused candidates (``lax.cond``; under ``vmap`` the batch skips
    the work when no run has a candidate or none has a free slot).
    """
    if model.inverse is None:
        raise ValueError("register: this model has no inverse observation; use add_landmark")
    z, lm_ids, mask, R = _check_register(state, model, z, lm_ids, mask, R)
    return call_compiled(("ekf_slam.register", model),
                         lambda opts, st, z, lm_ids, mask, R: _register_joint(st, model, z, lm_ids, mask, R, opts[0]),
                         (state, z, lm_ids, mask, R), (params,), after="auto")


def _check_register(state: SlamState, model: SlamModel, z, lm_ids, mask, R):
    """:func:`register`'s checks (shapes, and the values known now); returns
    ``(z, lm_ids, mask, R)`` as arrays, R as one (d_z, d_z) matrix per row."""
    _check_sizes(state, model)
    z, lm_ids, mask = _rows(z, lm_ids, mask, model.meas_dim, "lm_ids")
    return z, lm_ids, mask, _rows_R(R, mask, z.shape[0], model.meas_dim, state.x.dtype)


def _register_joint(state: SlamState, model: SlamModel, z, lm_ids, mask, R, params) -> SlamState:
    """:func:`register`'s computation: the joint write, or only the count of refused
    candidates."""
    z, lm_ids, mask, R = _check_register(state, model, z, lm_ids, mask, R)
    any_cand = _batch_max(jnp.any(mask).astype(jnp.int32)) > 0
    any_free = _batch_max(jnp.any(~state.active).astype(jnp.int32)) > 0
    # Two branches, P untouched in the second (no candidate: it counts none).  A three-way
    # switch (nothing / refuse / register) made XLA copy P on every call: capacity 256 ran
    # 0.154 → 0.26 s on the benchmark's 50 s log.
    return jax.lax.cond(any_cand & any_free, lambda st: _register(st, model, z, lm_ids, mask, R, params),
                        lambda st: _refuse_all(st, z, mask), state)


def _refuse_all(state: SlamState, z, mask) -> SlamState:
    """:func:`_register` on a map with no free slot (or with no candidate): every finite
    candidate is refused (counted in ``overflow``), nothing is written — the same state,
    without its O(K·d_l·n) work."""
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    return _count_refused(state, mask & finite, mask & ~finite)


def _count_refused(state: SlamState, over, bad) -> SlamState:
    """``state`` with the candidates refused for want of a slot (``over``) counted in
    ``overflow`` and flagged ``CAPACITY_OVERFLOW``, and non-finite ones (``bad``) flagged
    ``MASKED_INPUT``."""
    return state._replace(
        overflow=state.overflow + jnp.sum(over, dtype=jnp.int32),
        status=state.status
        | _flag_if(jnp.any(over), errors.CAPACITY_OVERFLOW)
        | _flag_if(jnp.any(bad), errors.MASKED_INPUT),
    )


def _rows_R(R, mask, K: int, dz: int, dtype):
    """R as one (dz, dz) matrix per measurement row, (K, dz, dz), from (dz, dz), (1 or K, dz, dz)
    or, for dz = 1, a scalar.  A shape that does not fit is an :class:`InputError` naming ``R``;
    called eagerly (R and the mask concrete), so is a matrix of a row the mask selects that is not
    symmetric positive semi-definite (under ``jit`` such an R is not caught here: the update is
    rejected and flagged ``NOT_PSD`` only if the innovation covariance fails its Cholesky)."""
    shape = tuple(jnp.shape(R))
    if not (shape in ((dz, dz), (1, dz, dz), (K, dz, dz)) or (dz == 1 and shape in ((), (1,), (K, 1)))):
        raise InputError(f"R: expected shape ({dz}, {dz}) or ({K}, {dz}, {dz})"
                         + (" or a scalar" if dz == 1 else "") + f", got {shape}")
    if dz == 1 and len(shape) < 3:
        R = jnp.reshape(jnp.asarray(R), (-1, 1, 1))
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    if is_concrete(R) and is_concrete(mask):
        try:
            rows = np.broadcast_to(np.asarray(mask, bool), (K,))
        except ValueError:
            raise InputError(f"mask: expected shape ({K},), got {tuple(np.shape(mask))}") from None
        check_psd(R, "R", stack=True, valid=np.broadcast_to(rows[:, None], (K, dz)))
    return R


def _register(state: SlamState, model: SlamModel, z, lm_ids, mask, R, params) -> SlamState:
    nr, dl, cap = _sizes(state, model)
    dtype = state.x.dtype
    K = z.shape[0]
    dz = model.meas_dim
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    mask = jnp.asarray(mask, bool)

    finite = jnp.all(jnp.isfinite(z), axis=-1)
    cand = mask & finite
    zs = jnp.where(cand[:, None], z, 0.0).astype(dtype)
    s = state.x[:nr]
    P = state.P
    Pss = P[:nr, :nr]
    Psx = P[:nr, :]  # (nr, n)

    def one(s_k, zk, Rk):
        if model.inverse_jacobian is not None:
            l, Gs, Gz = model.inverse_jacobian(s_k, zk, params)
        else:
            l, (Gs, Gz) = value_and_jacfwd(model.inverse, argnums=(0, 1))(s_k, zk, params)
        Pll = symmetrize(Gs @ Pss @ Gs.T + Gz @ Rk @ Gz.T)
        return l, Gs, Pll

    S_in, z_in = _guard_inputs(cand, s, zs)  # non-candidates carry no derivative
    L, Gs, Pll = jax.vmap(one)(S_in, z_in, R)  # (K, dl), (K, dl, nr), (K, dl, dl)
    ok = cand & jnp.all(jnp.isfinite(L), axis=-1) & jnp.all(jnp.isfinite(Pll), axis=(-2, -1))

    # Slot assignment: the k-th ok candidate takes the k-th free slot.
    free = ~state.active
    n_free = jnp.sum(free, dtype=jnp.int32)
    rank = jnp.cumsum(ok, dtype=jnp.int32) - ok.astype(jnp.int32)  # ok candidates before k
    has_free = rank < n_free
    good = ok & has_free
    over = cand & ~has_free
    free_slots = jnp.nonzero(free, size=K, fill_value=0)[0].astype(jnp.int32)  # first K free slots
    slot = free_slots[jnp.clip(rank, 0, K - 1)]
    # Rows of the new landmarks: G_s,k P_s,: with the new–new block replaced by the joint one.
    W = jnp.einsum("kai,in->kan", Gs, Psx)  # (K, dl, n)
    B = jnp.einsum("kai,ij,mbj->kamb", Gs, Pss, Gs)  # (K, dl, K, dl) = G_s,k P_ss G_s,mᵀ
    B = 0.5 * (B + B.transpose(2, 3, 0, 1))  # exactly symmetric, as the sequential write
    eyeK = jnp.eye(K, dtype=dtype)[:, None, :, None]
    B = B * (1.0 - eyeK) + jnp.einsum("kab,km->kamb", Pll, eyeK[:, 0, :, 0])  # joint diagonal blocks
    # The blocks of the candidates not written get an out-of-range slot and are dropped.
    slot_w = jnp.where(good, slot, jnp.int32(cap))
    W = put_blocks(W, slot_w, B, dl, nr, 2)
    P = put_blocks(P, slot_w, W, dl, nr, 0)
    P = put_blocks(P, slot_w, W.transpose(2, 0, 1), dl, nr, 1)
    x = put_blocks(state.x, slot_w, L, dl, nr, 0)
    active = state.active.at[slot_w].set(True, mode="drop")
    ids = state.ids.at[slot_w].set(jnp.asarray(lm_ids).astype(jnp.int32), mode="drop")
    return _count_refused(state._replace(x=x, P=P, active=active, ids=ids), over, mask & ~finite)


# ---------------------------------------------------------------------------
# Data association
# ---------------------------------------------------------------------------

def first_of_each_id(lm_ids, mask):
    """``mask`` with only the first row of each id kept (ids compared among the masked rows):
    a landmark seen in several rows of one step before it is mapped is registered once, not
    into one slot per row.  (K,) int ids, (K,) bool mask; O(K²), K the rows of one step."""
    lm_ids = jnp.asarray(lm_ids)
    mask = jnp.asarray(mask, bool)
    K = lm_ids.shape[0]
    same = (lm_ids[:, None] == lm_ids[None, :]) & mask[None, :]
    earlier = jnp.tril(jnp.ones((K, K), bool), -1)
    return mask & ~jnp.any(same & earlier, axis=1)


def associate_known(state: SlamState, lm_ids, mask):
    """Known correspondences: slot of each id and whether it is mapped.

    Returns (slots (K,), mapped (K,) bool).  Unmapped valid ids are the
    candidates for registration (``mask & ~mapped``).  ``lm_ids`` (K,) and ``mask`` (K,) are
    checked for shape (static) and, when concrete, ``mask`` for a bool (or 0/1) dtype and
    ``lm_ids`` for whole numbers: :class:`InputError` naming the argument.
    """
    lm_ids = jnp.asarray(lm_ids)
    if lm_ids.ndim != 1:
        raise InputError(f"lm_ids: expected shape (K,), got {tuple(lm_ids.shape)}")
    K = lm_ids.shape[0]
    if tuple(jnp.shape(mask)) != (K,):
        raise InputError(f"mask: expected shape ({K},) (one per row of lm_ids), got {tuple(jnp.shape(mask))}")
    check_mask(mask, "mask")
    check_whole_ids(lm_ids, "lm_ids", mask if is_concrete(mask) else None)
    mask = jnp.asarray(mask, bool)
    eq = (state.ids[None, :] == lm_ids[:, None]) & state.active[None, :]
    mapped = jnp.any(eq, axis=1) & mask
    slots = jnp.argmax(eq, axis=1).astype(jnp.int32)
    return slots, mapped


def marginal_d2(state: SlamState, model: SlamModel, z, mask, R, params=None, active_only: bool = False):
    """Marginal d² (K, cap) of every measurement against every landmark slot, the table both
    nearest-neighbour and JCBB association read.

    S_kj = H_s P_ss H_sᵀ + H_s P_sl H_lᵀ + H_l P_ls H_sᵀ + H_l P_ll H_lᵀ + R_k for slot j;
    d²_kj = ν_kjᵀ S_kj⁻¹ ν_kj.  Entries of inactive slots, masked or non-finite rows are
    +inf.  An entry whose ``S_kj`` or ``ν_kj`` is not finite (a NaN or Inf in ``R_k``, or in the
    robot's or landmark j's mean or covariance blocks) is NaN, never a finite value: an
    infinite variance used to divide its component away and give a small d².  Inactive slots
    (zero mean) are evaluated on derivative-free inputs and replaced by ẑ = 0, S = I (finite,
    never NaN, also under grad / jvp).
    ``active_only`` (static): evaluate only the smallest leading block of slots (capacity/8, /2
    or all, as :func:`update`) that holds every active slot (one ``lax.switch``; under ``vmap``
    the batch's fullest map decides); the slots beyond it are inactive, so the table is the
    same (to rounding: another program), at a cost set by the mapped landmarks instead of the
    capacity.
    Returns ``(d2, (zh (cap, d_z), Hs (cap, d_z, n_r), Hl (cap, d_z, d_l), nu (K, cap, d_z)))``
    (the slots beyond the evaluated block: ẑ = 0, H = 0, ν = 0).  ``z``, ``mask`` and ``R`` are
    checked as :func:`associate_nn` checks them.  Called eagerly it is compiled once per model
    (:func:`jaxslam.compilation.call_compiled`, ``after="auto"``).
    """
    z, mask, R = _check_associate(state, model, z, mask, R)
    return call_compiled(("ekf_slam.marginal_d2", model, active_only),
                         lambda opts, st, z, mask, R: _marginal_d2(st, model, z, mask, R, opts[0], active_only),
                         (state, z, mask, R), (params,), after="auto")


def _marginal_d2(state: SlamState, model: SlamModel, z, mask, R, params, active_only: bool):
    """:func:`marginal_d2`'s computation (``z``, ``mask``, ``R`` checked by the caller)."""
    cap = state.active.shape[0]
    sizes = _block_sizes(cap) if active_only else [cap]
    blocks = [functools.partial(_marginal_d2_block, state, model, z, mask, R, params, c) for c in sizes]
    if len(blocks) == 1:
        return blocks[0]()
    return jax.lax.switch(_block_index(sizes, _active_top(state)), blocks)


def _marginal_d2_block(state: SlamState, model: SlamModel, z, mask, R, params, c: int):
    """:func:`marginal_d2` evaluated on the first ``c`` slots (static), padded to the capacity."""
    nr, dl, cap = _sizes(state, model)
    dtype = state.x.dtype
    K = z.shape[0]
    dz = model.meas_dim
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    s = state.x[:nr]
    L = state.x[nr:nr + c * dl].reshape(c, dl)
    idx = slot_indices(jnp.arange(c), model)  # (c, dl)
    Pss = state.P[:nr, :nr]
    Psl = state.P[:nr, idx]  # (nr, c, dl)
    Pll = state.P[idx[:, :, None], idx[:, None, :]]  # (c, dl, dl)
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    z_safe = jnp.where(finite[:, None], z, 0.0).astype(dtype)
    res_fn = _residual(model)
    act = state.active[:c]
    zh, Hs, Hl = _observe_batch(model, s, L, params, act)  # (c, dz), (c, dz, nr), (c, dz, dl)

    def per_landmark(Hs_j, Hl_j, Psl_j, Pll_j):
        return (Hs_j @ Pss @ Hs_j.T + Hs_j @ Psl_j @ Hl_j.T + Hl_j @ Psl_j.T @ Hs_j.T
                + Hl_j @ Pll_j @ Hl_j.T)

    Sx = jax.vmap(per_landmark, in_axes=(0, 0, 1, 0))(Hs, Hl, Psl, Pll)  # (c, dz, dz)
    Sx = jnp.where(act[:, None, None], Sx, jnp.eye(dz, dtype=dtype))
    nu = jax.vmap(lambda zk: jax.vmap(lambda zh_j: res_fn(zk, zh_j))(zh))(z_safe)  # (K, c, dz)
    d2 = jax.vmap(lambda nu_k, Rk: jax.vmap(lambda n, S_j: _nis_small(n, S_j + Rk))(nu_k, Sx))(nu, R)
    # a pair whose S or ν is not finite is NaN: an infinite variance (in R, or in P) otherwise gave
    # a small, finite d² (its component divided away) and a match
    pair_ok = (jnp.all(jnp.isfinite(Sx), axis=(1, 2))[None, :] & jnp.all(jnp.isfinite(R), axis=(1, 2))[:, None]
               & jnp.all(jnp.isfinite(nu), axis=-1))
    d2 = jnp.where(pair_ok, d2, jnp.asarray(jnp.nan, dtype))
    d2 = jnp.where(act[None, :] & (mask & finite)[:, None], d2, jnp.asarray(jnp.inf, dtype))
    if c < cap:  # the slots beyond the block are inactive: +inf, and zeros in the aux arrays
        pad = cap - c
        d2 = jnp.concatenate([d2, jnp.full((K, pad), jnp.inf, dtype)], axis=1)
        zh = jnp.concatenate([zh, jnp.zeros((pad, dz), dtype)])
        Hs = jnp.concatenate([Hs, jnp.zeros((pad, dz, nr), dtype)])
        Hl = jnp.concatenate([Hl, jnp.zeros((pad, dz, dl), dtype)])
        nu = jnp.concatenate([nu, jnp.zeros((K, pad, dz), dtype)], axis=1)
    return d2, (zh, Hs, Hl, nu)


def associate_nn(state: SlamState, model: SlamModel, z, mask, R, params=None,
                 gate: float = 11.34, new_threshold: float = 30.0, active_only: bool = False):
    """Nearest-neighbour association by Mahalanobis distance (ids hidden).

    For each measurement the active landmark with the smallest squared
    Mahalanobis distance d² (marginal innovation covariance
    H_s P_ss H_sᵀ + H_s P_sl H_lᵀ + H_l P_ls H_sᵀ + H_l P_ll H_lᵀ + R) is chosen.
    d² < ``gate`` → matched; d² > ``new_threshold`` (or no landmark mapped)
    → a new landmark; in between → ambiguous, discarded.  When two
    measurements choose the same landmark only the closer one keeps it (the
    other is discarded), so a joint update never uses a landmark twice.  ``active_only``
    (static): the d² table on the leading block of slots that holds the map
    (:func:`marginal_d2`); the same association (d² to rounding).

    Shapes (static) and, when concrete, ``mask`` (bool or 0/1) and ``R`` (symmetric PSD on the
    masked-in rows) are checked as :func:`update`'s: :class:`InputError` naming the argument.
    So are ``gate`` and ``new_threshold`` known now (numbers > 0, inf allowed).  A traced one
    that is not > 0 (NaN included) matches / registers nothing, and this function has no
    status to say so: check it, or use :func:`run`, which flags it ``NON_FINITE``.

    Non-finite input, under ``jit`` too (this function has no status output): a masked-in row
    whose ``z`` is not finite is neither matched nor new (``d2_min`` +inf); a row whose d² table
    met a NaN or Inf (its ``R``, or the robot's or a mapped landmark's mean or covariance:
    :func:`marginal_d2` gives NaN there) is neither matched nor new, with ``d2_min`` NaN.  A
    non-finite input can therefore never produce a match; :func:`update` then flags what it is
    handed.

    Returns (slots (K,), matched (K,) bool, new (K,) bool, d2_min (K,)).  Called eagerly it is
    compiled once per model (:func:`jaxslam.compilation.call_compiled`, ``after="auto"``).
    """
    z, mask, R = _check_associate(state, model, z, mask, R)
    _check_nn_thresholds(gate, new_threshold)
    return call_compiled(("ekf_slam.associate_nn", model, active_only),
                         lambda opts, st, z, mask, R: _associate_nn(st, model, z, mask, R, *opts, active_only),
                         (state, z, mask, R), (params, gate, new_threshold), after="auto")


def _check_nn_thresholds(gate, new_threshold, names=("gate", "new_threshold")):
    """The nearest-neighbour gate and new-landmark threshold, when known now: numbers > 0 (inf
    allowed: match all / register none; a NaN or a negative one matched nothing and registered
    nothing, without a word).  Traced values pass (their values are not known)."""
    for name, v in zip(names, (gate, new_threshold)):
        if is_concrete(v):
            check_scalar(v, name, finite=False, lower=0, strict=True)


def _check_associate(state: SlamState, model: SlamModel, z, mask, R):
    """:func:`associate_nn`'s checks (shapes, and the values known now), as :func:`update`'s;
    returns ``(z, mask, R)`` as arrays."""
    _check_sizes(state, model)
    z, _, mask = _rows(z, None, mask, model.meas_dim, "")
    return z, mask, _rows_R(R, mask, z.shape[0], model.meas_dim, state.x.dtype)


def _associate_nn(state: SlamState, model: SlamModel, z, mask, R, params, gate, new_threshold,
                  active_only: bool):
    """:func:`associate_nn`'s computation."""
    z, mask, R = _check_associate(state, model, z, mask, R)
    cap = state.active.shape[0]
    dtype = state.x.dtype
    K = z.shape[0]
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    d2, _ = _marginal_d2(state, model, z, mask, R, params, active_only)
    big = jnp.asarray(jnp.inf, dtype)
    slots = jnp.argmin(d2, axis=1).astype(jnp.int32)
    d2_min = jnp.min(d2, axis=1)
    # a non-finite input reached the row's table (a NaN entry: marginal_d2): neither matched
    # nor new, and d2_min NaN (said explicitly: not left to how min and argmin treat a NaN)
    usable = mask & finite & ~jnp.any(jnp.isnan(d2), axis=1)
    d2_min = jnp.where(mask & finite & ~usable, jnp.asarray(jnp.nan, dtype), d2_min)
    cand = usable & (d2_min < gate)
    # Mutual exclusion: a landmark keeps only its closest candidate measurement.
    d2_sel = jnp.where(cand, d2_min, big)
    best_for_slot = jnp.full((cap,), big, dtype).at[slots].min(d2_sel)
    matched = cand & (d2_sel <= best_for_slot[slots])
    # Break exact ties deterministically (first index wins).
    first = jnp.full((cap,), K, jnp.int32).at[slots].min(jnp.where(matched, jnp.arange(K, dtype=jnp.int32), K))
    matched = matched & (first[slots] == jnp.arange(K, dtype=jnp.int32))
    new = usable & (d2_min > new_threshold)
    return slots, matched, new, d2_min


def joint_compatibility(state: SlamState, model: SlamModel, z, slots, matched, R, params,
                        thresholds):
    """Joint-compatibility check of one scan's matches ("JCBB-lite", greedy).

    The joint innovation ν = (ν_1 … ν_m) of the matched rows and its full covariance
    S = H P Hᵀ + R (robot and landmark cross-covariances included) give the joint NIS
    ν S⁻¹ ν.  While it exceeds ``thresholds[m − 1]`` (e.g. χ²(2m) quantiles; (K,) array, m
    the number of rows still matched), the row whose removal lowers the joint NIS most is
    dropped: NIS_{−i} = NIS − a_iᵀ [(S⁻¹)_{ii}]⁻¹ a_i with a = S⁻¹ν (block i).  At most K
    iterations (fixed, jit-friendly).  Unlike full JCBB (Neira & Tardós 2001) no
    alternative pairings are searched: rows are only dropped, never re-assigned.

    ``thresholds`` must be one-dimensional with at least K entries (a shorter table was read
    past its end, clamped to its last entry); known now, its entries must be > 0 (a NaN dropped
    nothing, without a word): else :class:`InputError` naming ``thresholds``.  A traced table is
    not checked (and this function has no status).

    Non-finite input, under ``jit`` too (no status output: the return type is what callers
    unpack): a matched row whose innovation or own block of S is not finite (a NaN or Inf in its
    ``z`` or ``R``, in the robot's or its landmark's mean or covariance) is dropped before the
    test, and a joint NIS that is not a number (a NaN cross-covariance, an S that does not
    factor, a traced NaN threshold) counts as a failed test (it kept every row): rows are
    dropped until it is a number below the threshold.  Such rows come out in ``dropped``; a
    non-finite input never leaves a match.

    Returns (matched (K,) bool — a subset of the input, dropped (K,) bool, joint NIS).
    """
    nr, dl, cap = _sizes(state, model)
    dtype = state.x.dtype
    K, dz = z.shape[0], model.meas_dim
    if np.ndim(thresholds) != 1 or np.shape(thresholds)[0] < K:
        raise InputError(f"thresholds: expected shape ({K},) (one per number of matched rows), "
                         f"got {tuple(np.shape(thresholds))}")
    if is_concrete(thresholds):
        t = np.asarray(thresholds, dtype=float)[:K]
        if not np.all(t > 0):  # NaN included
            raise InputError(f"thresholds: expected χ² thresholds > 0, got {t[~(t > 0)][0]} "
                             f"at index {int(np.flatnonzero(~(t > 0))[0])}")
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    s = state.x[:nr]
    L = state.x[nr:].reshape(cap, dl)[slots]
    zh, Hs, Hl = _observe_batch(model, s, L, params, matched)
    res_fn = _residual(model)
    nu = jax.vmap(res_fn)(jnp.where(matched[:, None], z, 0.0).astype(dtype), zh)
    nu = jnp.where(matched[:, None], nu, 0.0)
    H = jnp.concatenate([Hs, Hl], axis=2)  # (K, dz, nr + dl)
    idx = jnp.concatenate([jnp.broadcast_to(jnp.arange(nr), (K, nr)),
                           slot_indices(slots, model)], axis=1)  # (K, nr + dl)
    Pb = state.P[idx[:, None, :, None], idx[None, :, None, :]]  # (K, K, nr+dl, nr+dl)
    Sb = jnp.einsum("iab,ijbc,jdc->ijad", H, Pb, H)  # (K, K, dz, dz)
    eyeK = jnp.eye(K, dtype=dtype)
    Sb = Sb + eyeK[:, :, None, None] * R[:, None]
    # a row whose own innovation or S block is not finite cannot be tested: dropped up front
    row_ok = (jnp.all(jnp.isfinite(nu), axis=-1)
              & jnp.all(jnp.isfinite(Sb[jnp.arange(K), jnp.arange(K)]), axis=(-2, -1)))
    thr = jnp.asarray(thresholds, dtype)
    eye_dz = jnp.eye(dz, dtype=dtype)
    eye_KD = jnp.eye(K * dz, dtype=dtype)

    def joint(m):
        keep2 = m[:, None] & m[None, :]
        S = jnp.where(keep2[:, :, None, None], Sb, eyeK[:, :, None, None] * eye_dz)
        S = S.transpose(0, 2, 1, 3).reshape(K * dz, K * dz)
        v = jnp.where(m[:, None], nu, 0.0).reshape(K * dz)
        # S⁻¹ itself is needed (its diagonal blocks rank the rows): through a Cholesky factor
        Si = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(symmetrize(S)), True), eye_KD)
        a = (Si @ v).reshape(K, dz)
        nis = v @ (Si @ v)
        Sii = Si.reshape(K, dz, K, dz)[jnp.arange(K), :, jnp.arange(K), :]  # (K, dz, dz)
        gain = jax.vmap(lambda A, b: b @ jnp.linalg.solve(A, b))(Sii, a)
        return nis, gain

    def step(_, m):
        nis, gain = joint(m)
        n = jnp.sum(m)
        # (a NaN joint NIS fails the test: `nis > thr` kept every row)
        bad = (n > 0) & ~(nis <= thr[jnp.maximum(n - 1, 0)])
        worst = jnp.argmax(jnp.where(m, gain, -jnp.inf))
        return jnp.where(bad, m & (jnp.arange(K) != worst), m)

    m = jax.lax.fori_loop(0, K, step, matched & row_ok)
    nis, _ = joint(m)
    return m, matched & ~m, nis


# ---------------------------------------------------------------------------
# Smoothing: RTS on the robot trajectory, the map being static
# ---------------------------------------------------------------------------

class SmootherTerms(NamedTuple):
    """What the RTS pass needs from one filtered step (:func:`smoother_terms`).

    robot: (n_r,) filtered robot mean; lm: (cap·d_l,) filtered map means;
    W: (n_r, cap·d_l) regression of the robot on the map, ``P_rm P_mm⁺`` over the
    mapped slots (0 on free or zero-variance ones); P_cond: (n_r, n_r)
    ``P_rr − W P_mr``, the robot covariance given the map; ids: (cap,) int32 the
    landmark id in each slot (−1 free), so a slot re-used after pruning is not
    mistaken for the landmark it held before; status: () int32, ``NOT_PSD`` where the
    map block did not factor (W is then 0: that step's map term is dropped, and
    :func:`smooth_robot` reports the flag), else 0.
    """

    robot: jax.Array
    lm: jax.Array
    W: jax.Array
    P_cond: jax.Array
    ids: jax.Array
    status: Any = None


def smoother_terms(state: SlamState, model: SlamModel) -> SmootherTerms:
    """The per-step terms of :func:`smooth_robot` from a filtered state (record them in the scan).

    Storage O(n_r · cap · d_l) per step instead of the O(n²) of a full covariance;
    cost one Cholesky of the map block (O((cap·d_l)³)), so it suits maps of tens of
    landmarks (a 200-landmark map costs ~10⁸ flops per step).
    """
    nr, dl, cap = _sizes(state, model)
    dtype = state.x.dtype
    Pmm = state.P[nr:, nr:]
    Prm = state.P[:nr, nr:]
    live = jnp.repeat(state.active, dl) & (jnp.diagonal(Pmm) > 0)
    Pmm_m = jnp.where(live[:, None] & live[None, :], Pmm, jnp.eye(cap * dl, dtype=dtype))
    Prm_m = jnp.where(live[None, :], Prm, 0.0)
    Lc = jnp.linalg.cholesky(symmetrize(Pmm_m))
    Wt = jax.scipy.linalg.cho_solve((Lc, True), Prm_m.T)
    ok = jnp.all(jnp.isfinite(Wt))
    W = jnp.where(ok, Wt.T, 0.0)
    P_cond = symmetrize(state.P[:nr, :nr] - W @ Prm_m.T)
    return SmootherTerms(state.x[:nr], state.x[nr:], W, P_cond,
                         jnp.where(state.active, state.ids, -1).astype(jnp.int32),
                         jnp.where(ok, jnp.int32(0), jnp.int32(errors.NOT_PSD)))


def smooth_robot(model: SlamModel, terms: SmootherTerms, us, Qs, final: SlamState,
                 params=None, difference: Optional[Callable] = None):
    """RTS-smoothed robot trajectory of an EKF-SLAM run whose map is static.

    With the state ``[r; m]``, ``r' = f(r, u) + w`` (``Q``) and ``m' = m``, the RTS
    gain's map rows are ``[0, I]`` (so the smoothed map is the final filtered map at
    every step) and its robot rows are

        G_rr = P_r|m Fᵀ (F P_r|m Fᵀ + Q)⁻¹,   G_rm = (I − G_rr F) W,

    with ``P_r|m`` and ``W`` of :class:`SmootherTerms`; hence

        r̂_t = r_t + G_rr (r̂_{t+1} − f(r_t, u_{t+1})) + G_rm (m_T − m_t),

    which is the full-state RTS mean exactly (tests/filters/test_filters_ekf_slam.py),
    at O(n_r² · cap · d_l) per step.  A landmark not yet mapped at step t has W = 0
    there (the limit of an infinitely wide prior); a landmark removed before the end
    (or whose slot holds another landmark at the end) contributes nothing.  Only means are smoothed (the smoothed covariance would need
    the map block of every step).

    Args:
        model: the run's :class:`SlamModel`.
        terms: :class:`SmootherTerms` stacked over T steps (filtered, after step t).
        us: (T, …) the inputs of each step's prediction (step t predicted with ``us[t]``).
        Qs: (T, n_r, n_r) each step's process noise, as given to :func:`predict`.
        final: the last filtered state (its map is the smoothed map).
        params: None, or per-step motion parameters with leading axis T (e.g. dt).
        difference: ``difference(a, b)`` of robot states (wrap headings), default ``a − b``.

    Returns:
        ``(robot_means (T, n_r), status (T,) int32)`` with ``NOT_PSD`` where a gain
        could not be formed (that step keeps its filtered robot mean plus the map term) or
        where the step's terms say the map block did not factor (``terms.status``).
    """
    nr = model.robot_dim
    dtype = terms.robot.dtype
    diff = (lambda a, b: a - b) if difference is None else difference
    dl = model.lm_dim
    ids_T = jnp.where(final.active, final.ids, -1)
    T = terms.robot.shape[0]
    eye = jnp.eye(nr, dtype=dtype)
    p_seq = params

    def body(rs_next, inp):
        r, lm, W, Pc, ids_t, u_n, Q_n, p_n = inp
        r_pred, F = motion_and_jacobian(model, r, u_n, p_n)
        A = symmetrize(F @ Pc @ F.T + Q_n)
        La = jnp.linalg.cholesky(A)
        Grr_t = jax.scipy.linalg.cho_solve((La, True), F @ Pc)  # A⁻¹ F P_r|m = G_rrᵀ
        ok = jnp.all(jnp.isfinite(Grr_t))
        Grr = jnp.where(ok, Grr_t.T, 0.0)
        Grm = (eye - Grr @ F) @ W
        same = jnp.repeat((ids_t >= 0) & (ids_t == ids_T), dl)  # held the same landmark at the end
        rs = r + Grr @ diff(rs_next, r_pred) + Grm @ jnp.where(same, final.x[nr:] - lm, 0.0)
        st = jnp.where(ok, jnp.int32(0), jnp.int32(errors.NOT_PSD))
        return rs, (rs, st)

    st_terms = jnp.zeros((T,), jnp.int32) if terms.status is None else terms.status
    if T == 1:
        return terms.robot, st_terms
    nxt = jax.tree_util.tree_map(lambda a: a[1:], (us, Qs, p_seq))
    xs = (terms.robot[:-1], terms.lm[:-1], terms.W[:-1], terms.P_cond[:-1], terms.ids[:-1]) + tuple(nxt)
    _, (rs, st) = jax.lax.scan(body, terms.robot[-1], xs, reverse=True)
    rs = jnp.concatenate([rs, terms.robot[-1:]], 0)
    st = jnp.concatenate([st, jnp.zeros((1,), jnp.int32)], 0)
    return rs, st | st_terms


# ---------------------------------------------------------------------------
# A whole sequence: the runner every simple model can use as is
# ---------------------------------------------------------------------------

class SlamLog(NamedTuple):
    """The inputs of :func:`run`: T steps, each a prediction then up to K measurement rows.

    u: inputs with leading axis T (an array or a pytree), or None for a model whose motion
      takes none (``motion(s, None, params)``).
    z: (T, K, d_z) measurements (NaN allowed where masked).
    ids: (T, K) int landmark id of each row (known association; −1 or masked: none); None
      with ``association="nn"``.
    mask: (T, K) bool row present, or None (all present).
    params: None, or a pytree with leading axis T handed to the model's functions as their
      ``params`` at that step (e.g. a per-step Δt).
    """

    u: Any
    z: jax.Array
    ids: Any = None
    mask: Any = None
    params: Any = None


class SlamRun(NamedTuple):
    """What :func:`run` returns (leading axis T: one entry per step, after its update).

    robot: (T, n_r) robot means; robot_cov: (T, n_r, n_r) with ``save_cov`` else None;
    landmarks: (T, cap, d_l) map means with ``save_map`` else None; nis, logdet: (T,) joint NIS
    and log det S of the step's update; dof: (T,) scalar measurements used; log_likelihood:
    (T,) −½ (NIS + log det S + dof · log 2π), the innovation log-likelihood (sum it for the
    sequence's; its gradient tunes Q and R), NaN at a step whose update or prediction was
    rejected (``NON_FINITE`` / ``NOT_PSD`` in the status), so a sum cannot hide it; n_used, n_gated,
    n_new: (T,) int32 rows used, gated, registered as new landmarks; final: the last
    :class:`SlamState`.
    """

    robot: jax.Array
    robot_cov: Any
    landmarks: Any
    nis: jax.Array
    logdet: jax.Array
    dof: jax.Array
    log_likelihood: jax.Array
    n_used: jax.Array
    n_gated: jax.Array
    n_new: jax.Array
    final: SlamState


def _check_run(state: SlamState, model: SlamModel, log: SlamLog, Q, R, association: str):
    if not isinstance(model, SlamModel):
        raise InputError(f"model: expected a SlamModel, got {type(model).__name__}")
    if not isinstance(state, SlamState):
        raise InputError(f"state: expected a SlamState (ekf_slam.init), got {type(state).__name__}")
    if not isinstance(log, SlamLog):
        raise InputError(f"log: expected a SlamLog, got {type(log).__name__}")
    if association not in ("known", "nn"):
        raise InputError(f"association: expected 'known' or 'nn', got {association!r}")
    nr, dz = model.robot_dim, model.meas_dim
    if jnp.shape(state.x)[0] != nr + state.active.shape[0] * model.lm_dim:
        raise InputError(f"state: its size {jnp.shape(state.x)[0]} is not robot_dim {nr} + capacity "
                         f"{state.active.shape[0]} × lm_dim {model.lm_dim}")
    zs = jnp.shape(log.z)
    check_real(log.z, "log.z")
    if len(zs) != 3 or zs[2] != dz:
        raise InputError(f"log.z: expected shape (T, K, {dz}), got {tuple(zs)}")
    T, K = zs[0], zs[1]
    if log.mask is not None and jnp.shape(log.mask) != (T, K):
        raise InputError(f"log.mask: expected shape ({T}, {K}) like log.z, got {tuple(jnp.shape(log.mask))}")
    check_mask(log.mask, "log.mask")  # before the ids check and R's rows read it as bool
    if association == "known":
        if log.ids is None or jnp.shape(log.ids) != (T, K):
            raise InputError(f"log.ids: expected shape ({T}, {K}) with association 'known', got "
                             f"{None if log.ids is None else tuple(jnp.shape(log.ids))}")
        check_whole_ids(log.ids, "log.ids", None if log.mask is None or not is_concrete(log.mask) else log.mask)
    for nm, tree in (("log.u", log.u), ("log.params", log.params)):
        for a in jax.tree_util.tree_leaves(tree):
            if jnp.ndim(a) == 0 or jnp.shape(a)[0] != T:
                raise InputError(f"{nm}: every leaf needs a leading axis of {T} steps, got shape "
                                 f"{tuple(jnp.shape(a))}")
    if not callable(Q):
        if jnp.shape(Q)[-2:] != (nr, nr) or jnp.ndim(Q) not in (2, 3) or (jnp.ndim(Q) == 3 and jnp.shape(Q)[0] != T):
            raise InputError(f"Q: expected shape ({nr}, {nr}) or ({T}, {nr}, {nr}) or a function "
                             f"Q(s, u, params), got {tuple(jnp.shape(Q))}")
    if jnp.shape(R)[-2:] != (dz, dz) or jnp.ndim(R) not in (2, 3) or (jnp.ndim(R) == 3 and jnp.shape(R)[0] != T):
        raise InputError(f"R: expected shape ({dz}, {dz}) or ({T}, {dz}, {dz}), got {tuple(jnp.shape(R))}")
    for M, nm, strict in ((Q, "Q", False), (R, "R", True)):
        if callable(M) or not is_concrete(M):
            continue
        valid = None
        if nm == "R" and jnp.ndim(M) == 3 and log.mask is not None and is_concrete(log.mask):
            # a step with every row masked uses no R: its matrix may hold anything
            valid = np.broadcast_to(np.any(np.asarray(log.mask, bool), axis=1)[:, None], (T, dz))
        check_psd(M, nm, strict=strict, valid=valid, stack=True)
    check_finite(state.x, "state.x")
    if is_concrete(state.P):
        # (sliced on the host: under a trace even a concrete array's slice would be traced)
        check_psd(np.asarray(state.P)[:nr, :nr], "state.P (robot block)")
    return T, K


def run(model: SlamModel, state: SlamState, log: SlamLog, Q, R, *, association: str = "known",
        gate=None, nn_gate=11.34, nn_new=30.0, register_new: bool = True, save_cov: bool = False,
        save_map: bool = False) -> SlamRun:
    """EKF-SLAM over a whole sequence as one ``lax.scan``: at each step :func:`predict`, associate
    (:func:`associate_known` by id, or :func:`associate_nn`), :func:`update` with the mapped rows,
    then :func:`register` the new ones (``register_new`` and a model with ``inverse``).

    Args:
        model: the :class:`SlamModel`.
        state: the start (:func:`init`, optionally :func:`preload` for a known or prior map).
        log: the :class:`SlamLog`.
        Q: (n_r, n_r), (T, n_r, n_r), or a function ``Q(s, u, params) -> (n_r, n_r)`` of the
            robot mean before the prediction (input-dependent noise).
        R: (d_z, d_z) or (T, d_z, d_z).
        association: static, "known" (``log.ids``) or "nn" (nearest neighbour, ids hidden,
            ``nn_gate`` / ``nn_new`` on the 3-σ scale of :func:`associate_nn`; a traced one that
            is not > 0, NaN included, sets ``NON_FINITE`` and a NaN log-likelihood at each step
            with a present row).
        gate: χ²(d_z) threshold on each row's NIS (None: off; a traced one that is not > 0
            gates every row, as :func:`update`'s).  Traced: changing it never
            recompiles.
        save_cov, save_map: static; also stack the robot covariances / the map means.

    A present row with a non-finite entry is not used (neither registered nor associated) and
    sets ``MASKED_INPUT``.  Shapes and (when concrete) Q, R are checked here: a bad argument is an
    :class:`~jaxslam.errors.InputError` naming it.  Jit-, vmap- and grad-safe (jit it with
    ``static_argnames=("model", "association", "register_new", "save_cov", "save_map")``).
    Called eagerly it is compiled once per model and options
    (:func:`jaxslam.compilation.call_compiled`).
    """
    _check_run(state, model, log, Q, R, association)
    dtype = state.x.dtype
    nr = model.robot_dim
    z = jnp.asarray(log.z, dtype)
    T, K = z.shape[0], z.shape[1]
    mask = jnp.ones((T, K), bool) if log.mask is None else jnp.asarray(log.mask, bool)
    ids = log.ids
    if ids is not None and is_concrete(ids) and np.issubdtype(np.asarray(ids).dtype, np.floating):
        ids = np.where(np.isfinite(np.asarray(ids)), np.asarray(ids), -1)  # a masked row's NaN id: none
    ids = jnp.full((T, K), -1, jnp.int32) if ids is None else jnp.asarray(ids, jnp.int32)
    q_fn = Q if callable(Q) else None
    Qa = None if q_fn else jnp.asarray(Q, dtype)
    Ra = jnp.asarray(R, dtype)
    q_step, r_step = Qa is not None and Qa.ndim == 3, Ra.ndim == 3
    can_register = register_new and model.inverse is not None

    _check_options(gate=gate)  # the value known now, checked now: the compiled run sees it traced
    if association != "known":
        _check_nn_thresholds(nn_gate, nn_new, ("nn_gate", "nn_new"))
    def scan(opts, state, u, z, ids, mask, params, Qa, Ra):
        gate, nn_gate, nn_new = opts
        dtype = state.x.dtype
        log = SlamLog(u, z, ids, mask, params)

        def body(st, inp):
            u, z_t, id_t, m_t, p_t, Q_t, R_t = inp
            if q_fn is not None:
                Q_t = q_fn(st.x[:nr], u, p_t)
            elif not q_step:
                Q_t = Qa
            R_t = R_t if r_step else Ra
            st, pred_ok = _predict(st, model, u, jnp.asarray(Q_t, dtype), p_t, False)
            if association == "known":
                slots, mapped = associate_known(st, id_t, m_t)
                # (a non-finite row registers nothing: it must not hide a good row of its id)
                new = first_of_each_id(id_t, m_t & ~mapped & (id_t >= 0) & jnp.all(jnp.isfinite(z_t), axis=-1))
            else:
                slots, mapped, new, _ = associate_nn(st, model, z_t, m_t, R_t, p_t, gate=nn_gate,
                                                     new_threshold=nn_new)
            # a present row with a non-finite entry is neither registered nor (nn) a candidate of the
            # association: flag it as update does for the rows it is handed (``MASKED_INPUT``), not
            # drop it silently (known ids: the row of a landmark not yet mapped)
            bad = jnp.any(m_t & ~jnp.all(jnp.isfinite(z_t), axis=-1))
            st = st._replace(status=st.status | _flag_if(bad, errors.MASKED_INPUT))
            if association != "known":
                # a traced nn_gate / nn_new that is not > 0 (NaN included) matched and registered
                # nothing without a word: NON_FINITE, and the step's likelihood NaN (below)
                nn_bad = jnp.any(m_t) & ~((jnp.asarray(nn_gate) > 0) & (jnp.asarray(nn_new) > 0))
                st = st._replace(status=st.status | _flag_if(nn_bad, errors.NON_FINITE))
            else:
                nn_bad = jnp.asarray(False)
            st, info = update(st, model, z_t, slots, mapped, R_t, p_t, gate=gate)
            if can_register:
                n_before = jnp.sum(st.active)
                st = register(st, model, z_t, id_t, new, R_t, p_t)
                n_new = (jnp.sum(st.active) - n_before).astype(jnp.int32)
            else:
                n_new = jnp.zeros((), jnp.int32)
            logdet = jnp.asarray(info.logdet, dtype)
            ll = -0.5 * (info.nis + logdet + info.dof * jnp.log(2.0 * jnp.pi).astype(dtype))
            # a rejected update (NON_FINITE / NOT_PSD in the status) or prediction has no
            # likelihood: NaN, as in the generic filters, so that a sum over the run (an NLL
            # loss) cannot hide it
            ll = jnp.where(info.rejected | ~pred_ok | nn_bad, jnp.asarray(jnp.nan, dtype), ll)
            out = (st.x[:nr], st.P[:nr, :nr] if save_cov else None,
                   landmarks(st, model) if save_map else None, info.nis, logdet, info.dof, ll,
                   jnp.sum(info.used).astype(jnp.int32), jnp.sum(info.gated).astype(jnp.int32), n_new)
            return st, out

        xs = (_cast_u(log.u, dtype), z, ids, mask, log.params, Qa if q_step else None, Ra if r_step else None)
        final, outs = jax.lax.scan(body, state, xs, length=z.shape[0])
        return SlamRun(*outs, final=final)

    # called eagerly: compiled once per model, options and shapes
    return call_compiled(("ekf_slam.run", model, association, q_fn, q_step, r_step, can_register, save_cov,
                          save_map), scan, (state, log.u, z, ids, mask, log.params, Qa, Ra), (gate, nn_gate, nn_new))


__all__ += ["SlamLog", "SlamRun", "run"]
