"""The biased range model and the result shared by the range-only systems (UTIL, Plaza).

Range model of :mod:`jaxslam.systems.util_range` and :mod:`jaxslam.systems.plaza_range` (the robot
state ends with the bias b)::

    z = ‖p − l‖ + b + v,   v ~ N(0, σ_r²)                                     (R1)

p the tag/robot position (first d entries of the robot state), l the anchor or
beacon (d = 3 UTIL, 2 Plaza), b a range bias common to all anchors, modelled
as a slow random walk ḃ = w_b, E[w_b²] = q_b [m²/s].  Ranges are gated one by
one on their own χ²(1) NIS (``gate``); gated rows are counted, never used.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..data.events import check_times
from ..filters import consistency as cons
from ..filters import ekf_slam as es
from ..errors import InputError
from ..linalg import check_mask, check_scalar, check_whole_ids, is_concrete, safe_norm
from ..stats import chi2_ppf_np, student_t_d2_ppf_np

__all__ = ["range_observe", "update_ranges", "resolve_outlier_gate", "Result", "OUTLIER_P"]


#: probability of the range model's own d² distribution below the outlier gate
OUTLIER_P = 0.99


def check_params(params, positive=(), nonneg=(), finite=(), where: str = "params") -> None:
    """The scalar noise fields of a range-only system's ``params`` that are known now (traced
    ones pass: a fit differentiates through them): ``positive`` ones finite and > 0 (standard
    deviations), ``nonneg`` finite and >= 0 (densities), ``finite`` finite; ``gate`` None or
    > 0.  Raises :class:`InputError` naming ``where.field`` (a negative σ used to run as its
    absolute value, a NaN density to end in a NON_FINITE flag)."""
    for names, lower, strict in ((positive, 0, True), (nonneg, 0, False), (finite, None, False)):
        for f in names:
            v = getattr(params, f)
            if v is not None and is_concrete(v):
                check_scalar(v, f"{where}.{f}", lower=lower, strict=strict)
    g = getattr(params, "gate", None)
    if g is not None and is_concrete(g):
        check_scalar(g, f"{where}.gate", lower=0, strict=True)


def check_positions(a, name: str) -> None:
    """Known positions (anchors, beacons, a start pose) must be finite when given as values."""
    if a is not None and is_concrete(a) and not np.all(np.isfinite(np.asarray(a, np.float64))):
        raise InputError(f"{name}: contains NaN or Inf")


def check_log(log, u_width=None, name: str = "log") -> None:
    """The per-event arrays of a range-only ``Log``: at least one event; ``t``, ``dt`` (T,);
    ``u`` (T, ``u_width``) when given; ``z`` (T, K, 1) of a floating dtype (it is the run's
    dtype: integer ranges made every parameter an integer); ``ids``, ``mask`` (T, K).  Shapes
    always (also traced); when known, dt finite and >= 0 (a negative dt ran backwards), t finite
    and non-decreasing, and the ids of the rows in use whole numbers (a fractional id was truncated onto another anchor);
    ``mask`` bool or 0/1 integers (also traced: a float mask failed inside with a TypeError, a 2 was read as True).
    Raises :class:`InputError` naming ``name.field`` (a mismatch used to fail inside the scan)."""
    zs = np.shape(log.z)
    if len(zs) != 3 or zs[2] != 1:
        raise InputError(f"{name}.z: expected shape (T, K, 1), got {zs}")
    T = zs[0]
    if np.shape(log.dt) != (T,):
        raise InputError(f"{name}.dt: expected shape ({T},) (T = {name}.z.shape[0]), got {np.shape(log.dt)}")
    if T == 0:
        raise InputError(f"{name}.dt: expected at least one event, got an empty log (T = 0)")
    if not jnp.issubdtype(jnp.result_type(log.z), jnp.floating):
        raise InputError(f"{name}.z: expected floating ranges (their dtype is the run's), got dtype "
                         f"{jnp.result_type(log.z)}")
    shapes = [("t", (T,)), ("ids", zs[:2]), ("mask", zs[:2])] + ([] if u_width is None else [("u", (T, u_width))])
    for f, shp in shapes:
        if np.shape(getattr(log, f)) != shp:
            hint = "T, K = " + f"{name}.z.shape[:2]" if len(shp) == 2 and f != "u" else f"T = {name}.z.shape[0]"
            raise InputError(f"{name}.{f}: expected shape {shp} ({hint}), got {np.shape(getattr(log, f))}")
    check_mask(log.mask, f"{name}.mask")
    if is_concrete(log.dt):
        dt = np.asarray(log.dt, np.float64)
        if not np.all(np.isfinite(dt)) or np.any(dt < 0):
            raise InputError(f"{name}.dt: must be finite and >= 0")
    if is_concrete(log.t):  # the run reports and is scored at these times: a step back misplaced them
        check_times(log.t, f"{name}.t")
    if is_concrete(log.ids, log.mask):
        check_whole_ids(log.ids, f"{name}.ids", used=log.mask)


def check_ids_vector(ids, name: str) -> int:
    """The anchors'/beacons' ids: one whole-number id per anchor, shape (N,); returns N."""
    if np.ndim(ids) != 1:
        raise InputError(f"{name}: expected shape (N,) (one id per anchor), got {np.shape(ids)}")
    check_whole_ids(ids, name)  # a fractional id matches no range: its ranges were lost
    return int(np.shape(ids)[0])


def check_unique_ids(ids, name: str) -> None:
    """Anchor/beacon ids must be distinct (a repeated id made every range of the second one
    vanish, uncounted)."""
    if is_concrete(ids):
        a = np.asarray(ids)
        u, c = np.unique(a, return_counts=True)
        if np.any(c > 1):
            raise InputError(f"{name}: repeated id(s) {u[c > 1].tolist()}")


def resolve_outlier_gate(params):
    """``params`` with ``outlier_gate`` filled where it is None: the 99 % quantile of the range
    model's own d² — χ²(1) (6.63) for Gaussian ranges (``nu`` None), F(1, ν) for Student-t
    ranges (16.26 at ν = 5) — computed on the host, so ``nu`` must then be a number, not traced.
    Also checks ν > 0 and a given ``outlier_gate`` >= 0 when they are numbers."""
    nu = params.nu
    if nu is not None and is_concrete(nu) and not float(nu) > 0:
        raise InputError(f"params.nu: Student-t degrees of freedom must be > 0, got {nu}")
    if params.outlier_gate is not None:
        if is_concrete(params.outlier_gate):  # a negative gate made every range an outlier (DIVERGED)
            check_scalar(params.outlier_gate, "params.outlier_gate", finite=False, lower=0)
        return params
    if nu is None:
        return params._replace(outlier_gate=chi2_ppf_np(OUTLIER_P, 1))
    if not is_concrete(nu):
        raise InputError("params.outlier_gate: give it when params.nu is traced (its default is computed on "
                         "the host from nu)")
    return params._replace(outlier_gate=student_t_d2_ppf_np(OUTLIER_P, float(nu)))


def _check_slots(st, slots, mapped) -> None:
    """``mapped`` bool or integer (dtype: also traced); with both known, the slots of the mapped
    rows inside the state's ``[0, capacity)``.  :class:`InputError` naming the argument."""
    check_mask(mapped, "mapped")
    if not is_concrete(slots, mapped):
        return
    cap = np.shape(st.active)[0]
    sl, mp = np.asarray(slots), np.asarray(mapped, bool)
    if sl.shape != mp.shape:  # the engine names the shape mismatch
        return
    bad = mp & ((sl < 0) | (sl >= cap))
    if np.any(bad):
        raise InputError(f"slots: mapped row(s) {np.flatnonzero(bad).tolist()} name slot(s) "
                         f"{sl[bad].tolist()} outside the state's [0, {cap}) landmark slots")


def update_ranges(st, model, z, slots, mapped, params):
    """The engine's update with the event's ranges of mapped anchors/beacons, as the range-only
    systems run it: R = σ_r², the hard χ²(1) ``params.gate`` (None: off), Student-t rows with
    ``params.nu`` (None: Gaussian).  Returns ``(state, info, nll, nll_dof, n_outliers)``:
    :func:`jaxslam.filters.ekf_slam.update_nll`'s terms (d_z = 1) and the rows offered whose
    marginal d² exceeds ``params.outlier_gate`` (filled by :func:`resolve_outlier_gate`).
    A known ``params.sigma_r`` must be > 0 (a negative one was squared into a valid R).
    ``mapped`` is a bool (or 0/1 integer) mask: a float one was read as ``!= 0`` (0.5 a mapped
    row); when ``slots`` and ``mapped`` are known, a mapped row's slot must lie in
    [0, capacity) (one outside was dropped by the engine and flagged ``MASKED_INPUT``)."""
    if is_concrete(params.sigma_r):
        check_scalar(params.sigma_r, "params.sigma_r", lower=0, strict=True)
    _check_slots(st, slots, mapped)
    R = jnp.reshape(params.sigma_r ** 2, (1, 1))
    st, info = es.update(st, model, z, slots, mapped, R, gate=params.gate, robust=params.nu, row_stats=True)
    nll, cnt = es.update_nll(info, 1, params.nu)
    n_out = cons.outliers(info.d2, mapped, params)
    return st, info, nll, cnt, n_out


def range_observe(s, l, params=None):
    """(R1): z = ‖p − l‖ + b with p = s[:d], d = len(l), b = s[-1]; returns (1,).  Shapes are
    checked (static, also under ``jit``): ``l`` (d,) and ``s`` (n,) with n ≥ d + 1."""
    s, l = jnp.asarray(s), jnp.asarray(l)  # lists have no .shape
    if l.ndim != 1 or l.shape[0] < 1:
        raise InputError(f"l: expected a landmark position of shape (d,), got {tuple(l.shape)}")
    d = l.shape[0]
    if s.ndim != 1 or s.shape[0] < d + 1:
        raise InputError(f"s: expected a state of shape (n,) with n >= d + 1 = {d + 1} (position, ..., "
                         f"bias), got {tuple(s.shape)}")
    # safe norm: finite gradient at p = l (never met on real data, but jacfwd must stay finite)
    return jnp.reshape(safe_norm(s[:d] - l) + s[-1], (1,))


def _cast_params(p, dtype):
    # None (a gate switched off) stays None: an empty pytree node, not a number
    return type(p)(*[None if v is None else jnp.asarray(v, dtype) for v in p])


class Result(NamedTuple):
    """Whole-log result of the range-only systems' ``run`` (JAX arrays).

    t: (T,) event times [s]; pos: (T, d) position estimates [m] after each event;
    pos_var: (T, d) their variances [m²]; heading: (T,) [rad] (Plaza; zeros for UTIL);
    bias: (T,) [m]; bias_var: (T,) [m²]; nis: (T,) joint NIS of the event's update;
    dof: (T,) its degrees of freedom; used: (T,) ranges used; gated: (T,) ranges gated;
    landmarks: (cap, d) final anchor/beacon means [m]; landmark_cov: (cap, d, d);
    landmark_ids: (cap,) id per slot (−1 free); active: (cap,) bool mapped;
    bias_final, bias_sigma: () [m]; n_used, n_gated, n_registered, n_unmapped: () int32
    (ranges used, gated, beacons registered, ranges that arrived for an unmapped beacon);
    height_used, height_gated: (T,) int32 ToF height rows used / gated per event (UTIL with
    height rows; zeros otherwise); n_height_used, n_height_gated: () int32 their totals;
    status: () int32 engine status bits (``jaxslam.errors``); final: engine state.
    ``nis``/``dof`` of an event with a height row add the height update's NIS and dof.
    smoothed: (T, n_r) RTS-smoothed robot states (``smooth=True``; the map held static,
    :func:`jaxslam.filters.ekf_slam.smooth_robot`), else None; smooth_status: (T,) int32.
    nll: (T,) innovation negative log-likelihood of the event's used ranges (nats; Gaussian,
    or the rows' Student-t terms when the system's ``Params.nu`` is set; height rows not
    included); nll_dof: (T,) the number of those ranges (None where a system does not report it).
    n_outliers: (T,) int32 ranges of mapped anchors whose marginal d² (before any gate or
    weighting) exceeds the system's outlier gate; n_monitored: (T,) those offered to the update;
    more than 10 % outliers over the run sets ``DIVERGED`` in ``status``.
    """

    t: jax.Array
    pos: jax.Array
    pos_var: jax.Array
    heading: jax.Array
    bias: jax.Array
    bias_var: jax.Array
    nis: jax.Array
    dof: jax.Array
    used: jax.Array
    gated: jax.Array
    landmarks: jax.Array
    landmark_cov: jax.Array
    landmark_ids: jax.Array
    active: jax.Array
    bias_final: jax.Array
    bias_sigma: jax.Array
    n_used: jax.Array
    n_gated: jax.Array
    n_registered: jax.Array
    n_unmapped: jax.Array
    height_used: jax.Array
    height_gated: jax.Array
    n_height_used: jax.Array
    n_height_gated: jax.Array
    status: jax.Array
    final: es.SlamState
    smoothed: Optional[jax.Array] = None
    smooth_status: Optional[jax.Array] = None
    nll: Optional[jax.Array] = None
    nll_dof: Optional[jax.Array] = None
    n_outliers: Optional[jax.Array] = None
    n_monitored: Optional[jax.Array] = None


def _result(t, outs, st, model, n_reg, n_unm, smoothed=None, smooth_status=None, nll=None, nll_dof=None,
            n_outliers=None, n_monitored=None):
    if len(outs) == 9:
        zi = jnp.zeros_like(outs[7])
        outs = tuple(outs) + (zi, zi)
    pos, pos_var, heading, bias, bias_var, nis, dof, used, gated, h_used, h_gated = outs
    nr = model.robot_dim
    return Result(
        t=t, pos=pos, pos_var=pos_var, heading=heading, bias=bias, bias_var=bias_var, nis=nis,
        dof=dof, used=used, gated=gated, height_used=h_used, height_gated=h_gated,
        n_height_used=jnp.sum(h_used).astype(jnp.int32),
        n_height_gated=jnp.sum(h_gated).astype(jnp.int32),
        landmarks=es.landmarks(st, model), landmark_cov=es.landmark_covs(st, model),
        landmark_ids=st.ids, active=st.active,
        bias_final=st.x[nr - 1], bias_sigma=jnp.sqrt(jnp.maximum(st.P[nr - 1, nr - 1], 0.0)),
        n_used=jnp.sum(used).astype(jnp.int32), n_gated=jnp.sum(gated).astype(jnp.int32),
        n_registered=jnp.asarray(n_reg, jnp.int32), n_unmapped=jnp.asarray(n_unm, jnp.int32),
        status=st.status, final=st, smoothed=smoothed, smooth_status=smooth_status, nll=nll, nll_dof=nll_dof,
        n_outliers=n_outliers, n_monitored=n_monitored)
