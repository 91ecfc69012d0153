"""2D range-bearing FastSLAM 1.0 and 2.0 on real logs (UTIAS MRCLAM, Victoria Park; issue 9).

A *system* module: it plugs the planar motion models (:mod:`jaxslam.dynamics.planar`) and
the 2D range-bearing sensor (:mod:`jaxslam.sensors.range_bearing2d`) into the one particle
core (:mod:`jaxslam.filters.fastslam`).  Nothing here is a filter of its own.

A whole log is one jitted ``lax.scan`` over the events of an
:class:`~jaxslam.data.events.EventLog`.  Event k:

1. **Propagate** every particle over ``dt_k`` with the input ``u_k``
   (:func:`jaxslam.filters.fastslam.propagate`): ``s' = f(s, u, Δt) + J_u δu + w`` with
   ``δu ~ N(0, M)``, ``M = M_c/Δt`` for held rates (:func:`planar.step_input_cov`; M_c a
   density, so the pose noise ``J_u M J_uᵀ`` scales with Δt and splitting an interval at a
   measurement time leaves it unchanged), ``M = M_c`` on input events of ``"increment"``
   logs (0 on measurement-only events), and ``w ~ N(0, diag(q)·Δt)`` a pose-noise floor
   (``q`` a density; per increment for ``"increment"``).  The input noise is pushed through
   the Jacobian ``J_u = ∂f/∂u`` (``jax.jacfwd``) rather than through ``f`` itself: with
   ``M = M_c/Δt`` a very short interval draws a very large δu, which ``tan α`` of the
   Ackermann model would not survive; to first order the two are the same.
2. Only on events with a measurement (``lax.cond``; on the CPU an always-on update costs
   the update on every odometry event): **associate**, **update** the landmark EKFs and
   weights (:func:`fastslam.observe_update`), and **resample** when
   ``N_eff < params.resample_threshold·N``
   (:func:`fastslam.maybe_resample`).

With ``Config.proposal="optimal"`` (FastSLAM 2.0) step 1 moves each particle's Gaussian
instead of drawing (mean ``f(s, u, Δt)``, covariance ``F Σ Fᵀ + J_u M J_uᵀ + diag(q)·Δt``,
:func:`_moment_fn`), and step 2 draws the pose from that Gaussian updated by the sightings of
the particle's mapped landmarks (:func:`fastslam.propose_optimal`), then updates the landmark
EKFs at the drawn pose (``weights="none"``: the weight is the proposal's predictive density).

Data association (``Config.association``):

* ``"known"``: the log's ids (MRCLAM barcodes mapped to landmark numbers), shared by all
  particles, straight into the core.  With ``slot_by_id`` (default) id j lives in slot j
  (ids ≥ capacity are counted as capacity overflow).
* ``"ml"``: per-particle maximum likelihood (Montemerlo et al. 2002, FastSLAM 1.0 with
  unknown association).  Each particle compares each detection of the event with every
  landmark of *its own* map by the Mahalanobis distance ``d² = νᵀ S⁻¹ ν``,
  ``S = H Σ Hᵀ + R`` (the same S as the landmark update), against the map as it was before
  the event: ``d²_min ≤ params.gate`` → that landmark; ``d²_min > params.new_threshold`` (or an empty map)
  → a new landmark with the next id of the particle's own counter; in between → ignored
  (counted in ``gated``).  Ids are the particle's registration order, so id j lives in slot
  j (the core's ``slot_by_id``).  The per-particle ids go into the core by ``vmap``-ing
  :func:`fastslam.observe_update` over particles (each particle a one-particle set); the
  log-likelihoods it returns are then added to the whole set's weights with
  :func:`fastslam.reweight`, together with ``Params.log_p_new`` per new landmark (the
  likelihood charged for "this is a new landmark"; 0 is the core's convention).  No core
  change was needed.

Each particle also counts how often each of its landmarks was used (``aux``, resampled with
the particle): the result reports the best particle's counts, so a map can be filtered by
the number of observations (Victoria Park's tree detector has false positives; no landmark
is ever deleted here).

Results are pure functions of ``(key, log, pose0, config, params)``; ``config`` is static
(hashable: sizes and switches), ``params`` traced — the noise and the thresholds (gate,
new-landmark threshold, resampling threshold), so a new value never recompiles (float32 or
float64 follows ``pose0``'s dtype).  The dataset settings (MRCLAM, Victoria Park) are in
:mod:`jaxslam.data.presets`.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics import planar
from .. import errors
from ..errors import InputError, check_flag
from ..filters import consistency as cons
from ..filters import fastslam as fs
from ..linalg import check_int, check_key, check_mask, check_scalar, inv_small, is_concrete, symmetrize, value_and_jacfwd, wrap_angle
from ..sensors import range_bearing2d as rb
from .planar_ekf_slam import Log, check_matrices, log_from_events, validate_log

__all__ = [
    "ANGLE_MASK",
    "MODEL",
    "Config",
    "Params",
    "Log",
    "Event",
    "State",
    "StepOut",
    "Result",
    "init",
    "step",
    "log_from_events",
    "default_params",
    "THRESHOLDS",
    "motion_fn",
    "associate_ml",
    "run",
]

Array = Any

ANGLE_MASK = (False, False, True)
"""Pose (x, y, φ): φ is an angle."""

MODEL = fs.LandmarkModel(lm_dim=2, meas_dim=2, observe=rb.observe, inverse=rb.inverse,
                         residual=rb.residual)
"""The 2D range-bearing landmark model of the particle core."""

_MOTIONS = planar.MOTIONS
_ASSOC = ("known", "ml")
_PROPOSALS = ("motion", "optimal")


class Config(NamedTuple):
    """Static choices (hashable; a change recompiles): sizes, counts and switches (the gate,
    new-landmark and resampling thresholds are :class:`Params` fields).

    motion: "unicycle" (u = (v, ω) held rates, MRCLAM) | "ackermann" (u = (v_e, α) held,
        Victoria Park, ``geometry``) | "increment" (u = (d, dθ) per input event).
    n_particles: N.
    capacity: landmark slots per particle.
    K: measurement rows per event the run expects (must equal the log's K).
    association: "known" | "ml" (module docstring).
    weights: the core's weights, "exact" (log N(ν; 0, S)) or "mean" (log N(ν; 0, R)).
    proposal: "motion" (default; FastSLAM 1.0: each particle moved by a draw of the motion
        noise at every event) | "optimal" (FastSLAM 2.0: each particle carries its pose mean
        and the linearised motion covariance since its last draw, and on an event with rows
        draws its pose from the Gaussian given the sightings of its mapped landmarks, weighted
        by their predictive density; :func:`jaxslam.filters.fastslam.propose_optimal`; "ml"
        associates with the pose covariance in S before the draw).
    robust: Student-t measurement model with ``params.robust_nu`` degrees of freedom (default 5)
        in each particle's landmark update and weight (the core's ``robust``): an outlier is
        down-weighted, never cut off; use it without ``params.gate``.
    slot_by_id: "known" only: id j in slot j (default); False = first free slot.
    geometry: Ackermann geometry (``planar.VICTORIA_PARK``).
    """

    motion: str = "unicycle"
    n_particles: int = 100
    capacity: int = 32
    K: int = 1
    association: str = "known"
    weights: str = "exact"
    proposal: str = "motion"
    robust: bool = False
    slot_by_id: bool = True
    geometry: planar.AckermannGeometry = planar.VICTORIA_PARK


class Params(NamedTuple):
    """Traced numbers (differentiable leaves): the noise, then the thresholds (:data:`THRESHOLDS`;
    an optional one is off at None, and None ↔ a number changes the pytree — a switch that
    traces once more; a new number does not).

    M_c: (2, 2) input-noise density [(m/s)²·s, (rad/s)²·s] for held rates (for
        "ackermann": speed (m/s)²·s, steering rad²·s); per-increment covariance for
        "increment".
    pose_floor: (3,) pose-noise floor density [m²/s, m²/s, rad²/s] (per increment for
        "increment").
    R: (2, 2) range-bearing measurement covariance [m², rad²].
    P0: (3, 3) covariance of the initial particle cloud around ``pose0``.
    log_p_new: () log-likelihood charged per new landmark ("ml"; 0 = core convention).
    gate: () optional chi-square threshold on d² (2 dof).  "ml": the association gate (None:
        9.21, 99 %).  "known": the core's NIS gate (default None: no gate).
    new_threshold: () "ml" only: d²_min above which a detection starts a new landmark
        (default 13.8, 99.9 %); must be ≥ the gate.
    resample_threshold: () resample when N_eff < threshold·N (default 0.5); None resamples at
        every update.
    robust_nu: () Student-t degrees of freedom (``config.robust``; default None: 5).
    prune_window_s: () "ml" only: optional tentative-landmark pruning window [s] (default None:
        off; the planar EKF's rule, per particle).  A landmark of a particle's map that this
        particle has not matched (used in an update) at least ``prune_min_obs`` times within
        ``prune_window_s`` seconds of registering it (matches at events where its age is at
        most the window) is removed from that particle's map at the next event with rows
        (slot freed for a later landmark) and counted in ``Result.pruned``; one that has is
        confirmed and never removed.
    prune_min_obs: () matches a tentative landmark needs within the window (default 2).
    """

    M_c: Array
    pose_floor: Array
    R: Array
    P0: Array
    log_p_new: Array
    gate: Optional[Array] = None
    new_threshold: Array = 13.8
    resample_threshold: Optional[Array] = 0.5
    robust_nu: Optional[Array] = None
    prune_window_s: Optional[Array] = None
    prune_min_obs: Array = 2.0


#: The :class:`Params` fields that are thresholds (scalars; the rest is noise).
THRESHOLDS = ("gate", "new_threshold", "resample_threshold", "prune_window_s", "prune_min_obs")


class Result(NamedTuple):
    """Output of :func:`run` (T events, cap slots).

    pose_mean: (T, 3) weighted mean pose after each event (circular mean of φ).
    pose_best: (T, 3) pose of the highest-weight particle after each event.
    neff: (T,) N_eff after each event (before a resampling of that event).
    map: :class:`jaxslam.filters.fastslam.LandmarkMap` of the final best particle.
    n_obs: (cap,) int32 updates + registration of each slot of that particle.
    used, registered, gated: () measurements that updated a landmark / registered one /
        were gated (or, "ml", fell between gate and new_threshold), summed over the run
        and averaged over particles.
    outliers: () "known" with ``config.robust``: used rows whose d² exceeds the Student-t's
        own 99 % quantile (d = 2: ν (0.01^(−2/ν) − 1), 26.5 at ν = 5), averaged over
        particles; else 0.
    pruned: () tentative landmarks removed (``params.prune_window_s``), averaged over particles.
    overflow: () int32 measurements of new landmarks that found no slot (max over particles).
    resamples: () int32 resampling events.  underflow: () int32 weight-underflow recoveries.
    status: () int32 :mod:`jaxslam.errors` bit flags; "known" with ``params.gate`` or
        ``config.robust``: ``DIVERGED`` when more than 10 % of the sightings of mapped landmarks
        were gated or outliers (over used + gated rows, summed over particles;
        :data:`jaxslam.filters.consistency.DIVERGED_FRACTION`), the EKF's rule.
    log_marginal: () Σ of the core's incremental log marginal likelihoods ("known"; for
        "ml" the per-particle sum without the new-landmark term).
    particles: final :class:`jaxslam.filters.fastslam.Particles`.
    """

    pose_mean: Array
    pose_best: Array
    neff: Array
    map: Any
    n_obs: Array
    used: Array
    registered: Array
    gated: Array
    outliers: Array
    pruned: Array
    overflow: Array
    resamples: Array
    underflow: Array
    status: Array
    log_marginal: Array
    particles: Any


def default_params(sigma_r: float = 0.1, sigma_b: float = 0.01, sigma_v: float = 0.05,
                   sigma_w: float = 0.05, floor: tuple = (1e-6, 1e-6, 1e-6),
                   pose0_sigma: tuple = (0.01, 0.01, 0.005), log_p_new: float = 0.0,
                   dtype=None) -> Params:
    """Params from standard deviations (``sigma_v``/``sigma_w`` are input-noise *density*
    roots, e.g. m/s·√s; defaults are placeholders, the dev script states its sources).  Known
    numbers are checked: the standard deviations finite and >= 0 (a negative one was squared
    into a valid variance), ``floor`` 3 finite densities >= 0, ``pose0_sigma`` 3 finite standard
    deviations >= 0; :class:`InputError` naming it."""
    for name, v in (("sigma_r", sigma_r), ("sigma_b", sigma_b), ("sigma_v", sigma_v), ("sigma_w", sigma_w)):
        if is_concrete(v):
            check_scalar(v, name, lower=0)
    for name, v in (("floor", floor), ("pose0_sigma", pose0_sigma)):
        if is_concrete(v):
            a = np.asarray(v, np.float64)
            if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < 0):
                raise InputError(f"{name}: expected 3 finite numbers >= 0, got {a.tolist()}")
    f = (lambda x: jnp.asarray(x, dtype)) if dtype is not None else jnp.asarray
    return Params(
        M_c=f(np.diag([sigma_v ** 2, sigma_w ** 2])),
        pose_floor=f(np.asarray(floor, float)),
        R=f(np.diag([sigma_r ** 2, sigma_b ** 2])),
        P0=f(np.diag(np.square(np.asarray(pose0_sigma, float)))),
        log_p_new=f(float(log_p_new)),
    )


def motion_fn(config: Config):
    """The motion model ``f(s, u, dt)`` of ``config.motion``."""
    if config.motion not in _MOTIONS:
        raise InputError(f"config.motion: expected one of {_MOTIONS}, got {config.motion!r}")
    return planar.motion_model(config.motion, config.geometry)


def _validate_params(params: Params, config: Config):
    """Concrete matrices as the planar EKF's (M_c, R, P0 shape and PSD, R positive definite; a
    negative P0 used to make every pose NaN), pose_floor finite and >= 0, thresholds numbers
    (not NaN), gate > 0, resample_threshold a fraction of N in (0, 1], new_threshold ≥ the gate
    ("ml"), log_p_new finite."""
    check_matrices({"M_c": params.M_c, "R": params.R, "P0": params.P0}, "params", diagonal_ok=False)
    pf = np.asarray(params.pose_floor, np.float64)
    if pf.shape != (3,) or not np.all(np.isfinite(pf)) or np.any(pf < 0):
        raise InputError(f"params.pose_floor: expected 3 finite densities >= 0, got {pf.tolist()}")
    thr = {f: check_scalar(getattr(params, f), f"params.{f}", finite=False)
           for f in THRESHOLDS if getattr(params, f) is not None}
    if "new_threshold" not in thr:
        raise InputError("params.new_threshold: expected a number, got None")
    if "gate" in thr and not thr["gate"] > 0:  # a gate <= 0 gated every row (DIVERGED)
        raise InputError(f"params.gate: need > 0 (or None), got {thr['gate']}")
    if "resample_threshold" in thr and not 0 < thr["resample_threshold"] <= 1:  # a fraction of N
        raise InputError(f"params.resample_threshold: expected None or a fraction in (0, 1], got "
                         f"{thr['resample_threshold']}")
    if params.robust_nu is not None:
        check_scalar(params.robust_nu, "params.robust_nu", lower=0, strict=True)
    # a NaN (or infinite) charge per new landmark made every weight NaN (or every particle that
    # registers one impossible)
    check_scalar(params.log_p_new, "params.log_p_new")
    if params.prune_window_s is not None:
        if not thr["prune_window_s"] > 0:
            raise InputError(f"params.prune_window_s: need > 0, got {thr['prune_window_s']}")
        m = thr.get("prune_min_obs")
        if m is None or not (m >= 1 and m == np.floor(m)):
            raise InputError(f"params.prune_min_obs: a count of matches, expected a whole number >= 1, got {m}")
    if config.association == "ml":
        g = thr.get("gate", 9.21)
        if thr["new_threshold"] < g:
            raise InputError(f"params.new_threshold ({thr['new_threshold']}) must be >= gate ({g})")


def _check_prune(config: Config, params: Params):
    """Pruning is for "ml" association (static: checked under ``jit`` too, by :func:`run` and
    :func:`init`; with known ids the rows' ids are not slots of a particle's own map)."""
    if params.prune_window_s is not None and config.association != "ml":
        raise InputError("params.prune_window_s: tentative-landmark pruning needs association='ml' "
                         f"(got {config.association!r}: known ids need no pruning)")


def _validate(config: Config):
    if config.motion not in _MOTIONS:
        raise InputError(f"config.motion: expected one of {_MOTIONS}, got {config.motion!r}")
    if config.association not in _ASSOC:
        raise InputError(f"config.association: expected one of {_ASSOC}, got {config.association!r}")
    # a float size was truncated silently (16.5 -> 16, True -> 1)
    check_int(config.n_particles, "config.n_particles", what="an int (particles)")
    check_int(config.capacity, "config.capacity", what="an int (landmark slots)")
    check_int(config.K, "config.K", what="an int (rows per event)")
    # static switches: a string "no" (or any other non-bool) is truthy and silently turned them on
    check_flag(config.robust, "config.robust")
    check_flag(config.slot_by_id, "config.slot_by_id")
    if config.proposal not in _PROPOSALS:
        raise InputError(f"config.proposal: expected one of {_PROPOSALS}, got {config.proposal!r}")


# ---------------------------------------------------------------------------
# Proposal
# ---------------------------------------------------------------------------

def _sample_fn(f, increment: bool):
    def sample(pose, aux, key, u, dt, is_in, L_M, floor):
        dtype = pose.dtype
        k1, k2 = jax.random.split(key)
        mean = f(pose, u, dt)
        Ju = jax.jacfwd(lambda uu: f(pose, uu, dt))(u)
        e1 = jax.random.normal(k1, (L_M.shape[0],), dtype)
        e2 = jax.random.normal(k2, (3,), dtype)
        if increment:
            s_u = jnp.where(is_in, jnp.ones((), dtype), jnp.zeros((), dtype))
            s_f = s_u
        else:
            pos = dt > 0
            s_u = jnp.where(pos, jax.lax.rsqrt(jnp.where(pos, dt, jnp.ones((), dtype))),
                            jnp.zeros((), dtype))
            s_f = jnp.sqrt(jnp.maximum(dt, jnp.zeros((), dtype)))
        s = mean + Ju @ (L_M @ e1) * s_u + jnp.sqrt(floor) * s_f * e2
        return s.at[2].set(wrap_angle(s[2])), aux

    return sample


def _moment_fn(f, increment: bool):
    """The "optimal" proposal's prediction: the pose mean moved by ``f`` and its covariance by
    the same noise model as :func:`_sample_fn` draws from, linearised:
    Σ' = F Σ Fᵀ + J_u M Jᵤᵀ·s_u² + diag(floor)·s_f² (aux[2] holds Σ)."""
    def moments(pose, aux, key, u, dt, is_in, L_M, floor):
        del key
        dtype = pose.dtype
        mean, (F, Ju) = value_and_jacfwd(lambda s, uu: f(s, uu, dt), argnums=(0, 1))(pose, u)
        if increment:
            s_u2 = jnp.where(is_in, jnp.ones((), dtype), jnp.zeros((), dtype))
            s_f2 = s_u2
        else:
            pos = dt > 0
            s_u2 = jnp.where(pos, 1.0 / jnp.where(pos, dt, jnp.ones((), dtype)), jnp.zeros((), dtype))
            s_f2 = jnp.maximum(dt, jnp.zeros((), dtype))
        JL = Ju @ L_M
        cov = F @ aux[2] @ F.T + (JL @ JL.T) * s_u2 + jnp.diag(floor) * s_f2
        return mean.at[2].set(wrap_angle(mean[2])), aux[:2] + (symmetrize(cov),) + aux[3:]

    return moments


# ---------------------------------------------------------------------------
# Data association
# ---------------------------------------------------------------------------

def associate_ml(pose, mean, cov, active, counter, z, mask, R, gate, new_threshold, pose_cov=None,
                 free_slots: bool = False):
    """Maximum-likelihood association of one particle (module docstring).

    Args:
        pose: (3,).  mean (cap, 2), cov (cap, 2, 2), active (cap,): the particle's map.
        counter: () int32 next new-landmark id.  z: (K, 2) detections, mask: (K,).
        R: (2, 2).  gate, new_threshold: d² thresholds.
        pose_cov: optional (3, 3) covariance of the particle's pose (the "optimal" proposal's
            Gaussian before its draw): S gains G_s Σ_s G_sᵀ, G_s = ∂h/∂pose.
        free_slots: static; new landmarks take the particle's free slots in order (pruning
            frees slots) instead of the ids ``counter``, ``counter + 1``, …; a new landmark
            beyond the free slots gets id ``cap`` (capacity overflow).  ``counter'`` still
            counts the new landmarks.

    Returns:
        ``(ids (K,) int32 (−1 = not used), counter', is_new (K,), ambiguous (K,))``.
    """
    dtype = mean.dtype

    def pred(l):
        zh, (Gs, H) = value_and_jacfwd(rb.observe, argnums=(0, 1))(pose, l)
        return zh, H, Gs

    zhat, H, Gs = jax.vmap(pred)(mean)  # (cap, 2), (cap, 2, 2), (cap, 2, 3)
    S = H @ cov @ jnp.swapaxes(H, -1, -2) + R
    if pose_cov is not None:
        S = S + Gs @ pose_cov @ jnp.swapaxes(Gs, -1, -2)
    Sinv, det = inv_small(S)
    ok = (det > 0) & (S[..., 0, 0] > 0)  # positive definite (Sylvester); the rest is +inf below
    valid = mask & jnp.all(jnp.isfinite(z), axis=1)
    zs = jnp.where(valid[:, None], z, jnp.zeros((), dtype))
    nu = jax.vmap(lambda zk: jax.vmap(lambda zh: rb.residual(zk, zh))(zhat))(zs)  # (K, cap, 2)
    d2 = jnp.einsum("kci,cij,kcj->kc", nu, Sinv, nu)
    d2 = jnp.where((active & ok)[None, :], d2, jnp.inf)
    best = jnp.argmin(d2, axis=1).astype(jnp.int32)
    dmin = jnp.min(d2, axis=1)
    matched = valid & (dmin <= gate)
    new = valid & (dmin > new_threshold)
    amb = valid & ~matched & ~new
    rank = (jnp.cumsum(new.astype(jnp.int32)) - 1).astype(jnp.int32)
    if free_slots:
        cap = mean.shape[0]
        free = jnp.nonzero(~active, size=z.shape[0], fill_value=cap)[0].astype(jnp.int32)
        new_ids = free[jnp.clip(rank, 0, z.shape[0] - 1)]
    else:
        new_ids = counter + rank
    ids = jnp.where(matched, best, jnp.where(new, new_ids, -1)).astype(jnp.int32)
    return ids, (counter + jnp.sum(new.astype(jnp.int32))).astype(jnp.int32), new, amb


def _observe_per_particle(p: fs.Particles, z, ids, mask, R, weights, robust=None):
    """The core's observe_update with per-particle ids (N, K): vmap over one-particle sets."""
    i32 = jnp.int32
    dtype = p.log_w.dtype

    def one(pose, mean, cov, active, slot_ids, lm_ids):
        q = fs.Particles(pose=pose[None], aux=(), lm_mean=mean[None], lm_cov=cov[None],
                         active=active[None], ids=slot_ids[None], log_w=jnp.zeros((1,), dtype),
                         status=jnp.zeros((), i32), overflow=jnp.zeros((), i32),
                         underflow=jnp.zeros((), i32), resamples=jnp.zeros((), i32))
        q2, info = fs.observe_update(q, MODEL, z, lm_ids, mask, R, None, weights=weights,
                                     gate=None, slot_by_id=True, robust=robust)
        return (q2.lm_mean[0], q2.lm_cov[0], q2.active[0], q2.ids[0], info.loglik[0],
                info.used[0], info.registered[0], info.status, q2.overflow)

    mean, cov, active, sids, ll, used, reg, st, ovf = jax.vmap(one)(
        p.pose, p.lm_mean, p.lm_cov, p.active, p.ids, ids)
    p = p._replace(lm_mean=mean, lm_cov=cov, active=active, ids=sids,
                   status=p.status | jnp.bitwise_or.reduce(st),
                   overflow=p.overflow + jnp.max(ovf))
    return p, ll, used, reg


# ---------------------------------------------------------------------------
# Run
# ---------------------------------------------------------------------------

class Event(NamedTuple):
    """One event of a :class:`Log` (the slice :func:`step` takes)."""

    dt: Array  # ()
    u: Array  # (2,)
    is_input: Array  # () bool
    z: Array  # (K, 2)
    ids: Array  # (K,)
    mask: Array  # (K,)


#: The state between events: the particle set (:class:`jaxslam.filters.fastslam.Particles`;
#: ``aux`` holds each particle's new-landmark counter and per-slot observation counts).
State = fs.Particles


class StepOut(NamedTuple):
    """What :func:`step` reports for its event (stacked by :func:`run`)."""

    pose_mean: Array  # (3,) weighted mean pose (circular mean of φ)
    pose_best: Array  # (3,) pose of the highest-weight particle
    neff: Array  # () N_eff before this event's resampling
    used: Array  # () int32 rows that updated a landmark, summed over particles
    registered: Array  # () int32
    gated: Array  # () int32
    log_marginal: Array  # () incremental log marginal likelihood
    outliers: Array  # () int32 used rows beyond the Student-t's 99 % quantile ("known", robust)
    pruned: Array  # () int32 tentative landmarks removed, summed over particles


def _validate_log(log: Log, config: Config):
    # the planar EKF's checks of the same Log: shapes, at least one event (an empty log failed
    # with an IndexError); when known, dt finite >= 0 (a negative dt ran backwards, unflagged), u
    # and pose0 finite (inside jit the scan keeps a particle whose proposal is not finite and
    # flags NON_FINITE), whole-number ids on the rows in use
    validate_log(log)
    T = np.shape(log.dt)[0]
    if np.shape(log.z) != (T, int(config.K), 2):  # and the configured K rows per event
        raise InputError(f"log.z: expected shape ({T}, {config.K}, 2), got {np.shape(log.z)}")
    if log.is_input is not None:  # one flag per event (a wrong length failed inside the scan; 0.5 was True)
        if np.shape(log.is_input) != (T,):
            raise InputError(f"log.is_input: expected shape ({T},) (one flag per event), got {np.shape(log.is_input)}")
        check_mask(log.is_input, "log.is_input")


def init(log: Log, config: Config, params: Params, *, key) -> State:
    """N particles drawn around ``log.pose0`` with covariance ``params.P0`` (``key``), empty maps."""
    _check_prune(config, params)
    dtype = jnp.asarray(log.pose0).dtype
    N, cap = int(config.n_particles), int(config.capacity)
    L_P0 = jnp.linalg.cholesky(params.P0 + 1e-15 * jnp.eye(3, dtype=dtype))
    poses0 = log.pose0[None, :] + jax.random.normal(key, (N, 3), dtype) @ L_P0.T
    poses0 = poses0.at[:, 2].set(wrap_angle(poses0[:, 2]))
    aux0 = (jnp.zeros((N,), jnp.int32), jnp.zeros((N, cap), jnp.int32))
    if config.proposal == "optimal":  # each particle's pose covariance since its last draw
        aux0 = aux0 + (jnp.zeros((N, 3, 3), dtype),)
    if params.prune_window_s is not None:  # per slot: age since registration, matches, confirmed
        aux0 = aux0 + (jnp.zeros((N, cap), dtype), jnp.zeros((N, cap), jnp.int32), jnp.zeros((N, cap), bool))
    return fs.init(poses0, N, cap, 2, aux=aux0, aux_per_particle=True)


def _prune(p: fs.Particles, active_before, pids, used, ip: int, params: Params):
    """Tentative-landmark bookkeeping and pruning of every particle after an update (the planar
    EKF's rule, ``params.prune_window_s``).  aux[ip:ip + 3] = (age since registration (N, cap),
    matches within the window (N, cap), confirmed (N, cap)).  A slot registered in this event
    starts at age 0 with no match; a row used on a slot no older than the window counts one
    match; a tentative slot older than the window is confirmed (≥ ``prune_min_obs`` matches) or
    removed (inactive, id −1, its counts cleared; the slot is free for the next new landmark).
    Returns (particles, landmarks removed summed over particles)."""
    age, n_match, confirmed = p.aux[ip:ip + 3]
    cap = age.shape[1]
    new = p.active & ~active_before
    age = jnp.where(new, jnp.zeros((), age.dtype), age)
    n_match = jnp.where(new, 0, n_match)
    confirmed = confirmed & ~new
    win = jnp.asarray(params.prune_window_s, age.dtype)

    def add(nm, a, sid, u):
        s = jnp.clip(sid, 0, cap - 1)
        return nm.at[s].add((u & (sid >= 0) & (sid < cap) & (a[s] <= win)).astype(jnp.int32))

    n_match = jax.vmap(add)(n_match, age, pids, used)
    due = p.active & ~confirmed & (age > win)
    drop = due & (n_match < jnp.asarray(params.prune_min_obs, age.dtype))
    confirmed = confirmed | (due & ~drop)
    nobs = jnp.where(drop, 0, p.aux[1])
    aux = (p.aux[0], nobs) + p.aux[2:ip] + (age, jnp.where(drop, 0, n_match), confirmed) + p.aux[ip + 3:]
    p = p._replace(active=p.active & ~drop, ids=jnp.where(drop, -1, p.ids), aux=aux)
    return p, jnp.sum(drop, dtype=jnp.int32)


def step(state: State, event: Event, config: Config, params: Params, *, key):
    """One event: every particle's proposal over ``event.dt``, then (when the event has rows)
    association, landmark updates, reweighting and resampling.  Returns ``(state, StepOut)``."""
    p = state
    dtype = p.pose.dtype
    N, cap = int(config.n_particles), int(config.capacity)
    ml = config.association == "ml"
    f = motion_fn(config)
    optimal = config.proposal == "optimal"
    sample = (_moment_fn if optimal else _sample_fn)(f, config.motion == "increment")
    eye2 = jnp.eye(2, dtype=dtype)
    L_M = jnp.linalg.cholesky(params.M_c + 1e-12 * eye2)
    floor = jnp.maximum(params.pose_floor, jnp.zeros((), dtype))
    R = params.R
    gate_ml = jnp.asarray(9.21 if params.gate is None else params.gate, dtype)
    new_thr = jnp.asarray(params.new_threshold, dtype)
    thr = params.resample_threshold
    zero_i = jnp.zeros((), jnp.int32)
    prune = params.prune_window_s is not None
    ip = 3 if optimal else 2  # first of the pruning entries of aux (init)
    if config.robust:
        nu_t = jnp.asarray(5.0 if params.robust_nu is None else params.robust_nu, dtype)
        # the Student-t's own 99 % quantile of d² in two dimensions: P(d² > x) = (1 + x/ν)^(−ν/2)
        out_gate = nu_t * (jnp.asarray(0.01, dtype) ** (-2.0 / nu_t) - 1.0)
    else:
        nu_t = None

    def draw(p, k_res, z, row_ids, mask):
        """The "optimal" proposal's draw at an event with rows; the pose covariance restarts at 0.
        Returns (p, resampling key, proposal log-likelihoods, log marginal)."""
        k_res, k_draw = jax.random.split(k_res)
        p, ll, log_marg, _ = fs.propose_optimal(p, MODEL, z, row_ids, mask, R, p.aux[2], k_draw,
                                                slot_by_id=config.slot_by_id or ml, angle_mask=ANGLE_MASK,
                                                gate=None if ml else params.gate, robust=nu_t)
        return p._replace(aux=p.aux[:2] + (jnp.zeros_like(p.aux[2]),) + p.aux[3:]), k_res, ll, log_marg

    def update(p, k_res, z, ids, mask):
        counter, nobs = p.aux[:2]
        active_before = p.active
        if ml:
            assoc = jax.vmap(functools.partial(associate_ml, free_slots=prune),
                             in_axes=(0, 0, 0, 0, 0, None, None, None, None, None, 0 if optimal else None))
            pids, counter, _, amb = assoc(p.pose, p.lm_mean, p.lm_cov, p.active, counter,
                                          z, mask, R, gate_ml, new_thr, p.aux[2] if optimal else None)
            if optimal:
                p, k_res, ll_prop, _ = draw(p, k_res, z, pids, mask)
            p, ll, used, reg = _observe_per_particle(p, z, pids, mask, R, "none" if optimal else config.weights,
                                                     nu_t)
            if optimal:
                ll = ll_prop
            n_new = jnp.sum(reg.astype(dtype), axis=1)
            log_marg = jax.scipy.special.logsumexp(p.log_w + ll)
            p = fs.reweight(p, ll + n_new * params.log_p_new)
            gated = amb
            outl = jnp.zeros_like(used)
        else:
            if optimal:
                p, k_res, ll_prop, log_marg = draw(p, k_res, z, ids, mask)
            p, info = fs.observe_update(p, MODEL, z, ids, mask, R, None,
                                        weights="none" if optimal else config.weights,
                                        gate=params.gate, slot_by_id=config.slot_by_id, robust=nu_t)
            if optimal:
                p = fs.reweight(p, ll_prop)
            else:
                log_marg = info.log_marginal
            pids = jnp.broadcast_to(ids, (N, ids.shape[0]))
            used, reg, gated = info.used, info.registered, info.gated
            outl = used & (info.nis > out_gate) if config.robust else jnp.zeros_like(used)
        hit = (used | reg)

        def count(nb, sid_row, slot_row, hit_row):
            # slot of each measurement: its id with slot_by_id, else look it up
            if ml or config.slot_by_id:
                s = jnp.clip(sid_row, 0, cap - 1)
            else:
                s = jnp.argmax(slot_row[None, :] == sid_row[:, None], axis=1)
            return nb.at[s].add(hit_row.astype(jnp.int32))

        if prune:  # a slot registered in this event starts afresh (a freed slot can be reused)
            nobs = jnp.where(p.active & ~active_before, 0, nobs)
        nobs = jax.vmap(count)(nobs, pids, p.ids, hit)
        p = p._replace(aux=(counter, nobs) + p.aux[2:])
        n_pruned = zero_i
        if prune:
            p, n_pruned = _prune(p, active_before, pids, used, ip, params)
        ne = fs.neff(p)
        p = fs.maybe_resample(p, k_res, thr)
        stats = (jnp.sum(used).astype(jnp.int32), jnp.sum(reg).astype(jnp.int32),
                 jnp.sum(gated).astype(jnp.int32), log_marg, jnp.sum(outl).astype(jnp.int32), n_pruned)
        return p, ne, stats

    def skip(p, k_res, z, ids, mask):
        return p, fs.neff(p), (zero_i, zero_i, zero_i, jnp.zeros((), dtype), zero_i, zero_i)

    k_prop, k_res = jax.random.split(key)
    p = fs.propagate(p, k_prop, sample, event.u, event.dt, event.is_input, L_M, floor)
    if prune:  # the age of every mapped landmark since its registration
        age = jnp.where(p.active, p.aux[ip] + jnp.maximum(event.dt, 0), p.aux[ip])
        p = p._replace(aux=p.aux[:ip] + (age,) + p.aux[ip + 1:])
    # Only rows with finite values make an event an update (the "optimal" proposal redraws every
    # particle at one): non-finite rows are masked out, as the core would, and flagged here.
    finite = jnp.all(jnp.isfinite(event.z), axis=-1)
    p = p._replace(status=p.status | jnp.where(jnp.any(event.mask & ~finite), jnp.int32(errors.MASKED_INPUT),
                                                 jnp.int32(0)))
    mask = event.mask & finite
    p, ne, stats = jax.lax.cond(jnp.any(mask), update, skip, p, k_res, event.z, event.ids, mask)
    mu, _ = fs.estimate(p, ANGLE_MASK)
    best = p.pose[jnp.argmax(p.log_w)]
    return p, StepOut(pose_mean=mu, pose_best=best, neff=ne, used=stats[0], registered=stats[1],
                      gated=stats[2], log_marginal=stats[3], outliers=stats[4], pruned=stats[5])


def run(log: Log, config: Config, params: Params, *, key) -> Result:
    """A whole log in one jitted ``lax.scan`` of :func:`step` (module docstring).

    Args:
        log: :class:`Log` with ``u`` (T, 2), ``z`` (T, K, 2) as (range [m], bearing [rad],
            counter-clockwise from the sensor's forward axis), ``ids`` (T, K) (used by "known"
            only), ``pose0`` (3,) (its float dtype sets the run's dtype), ``is_input`` (T,)
            (increments; default: every event).
        config: :class:`Config` (static).  params: :class:`Params`.  key: PRNG key (required).

    Raises:
        InputError: bad config, or log shapes that disagree with it.
    """
    if key is None:
        raise InputError("key: planar FastSLAM draws particles; give a PRNG key")
    # one key: an int seed, float key data or a batch of keys failed inside the sampler
    check_key(key, "key")
    _validate(config)
    _check_prune(config, params)
    if is_concrete(params):
        _validate_params(params, config)
    _validate_log(log, config)
    pose0 = jnp.asarray(log.pose0)
    dtype = pose0.dtype if jnp.issubdtype(pose0.dtype, jnp.floating) else jnp.result_type(float)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), params)
    T = np.shape(log.dt)[0]
    is_in = jnp.ones((T,), bool) if log.is_input is None else jnp.asarray(log.is_input, bool)
    log = Log(dt=jnp.asarray(log.dt, dtype), u=jnp.asarray(log.u, dtype), z=jnp.asarray(log.z, dtype),
              ids=jnp.asarray(log.ids, jnp.int32), mask=jnp.asarray(log.mask, bool), pose0=pose0.astype(dtype),
              is_input=is_in)
    return _run(key, log, params, config)


@functools.partial(jax.jit, static_argnums=(3,))
def _run(key, log: Log, params: Params, config: Config) -> Result:
    dtype = log.pose0.dtype
    N = int(config.n_particles)
    T = log.dt.shape[0]
    k0, k_run = jax.random.split(key)
    p0 = init(log, config, params, key=k0)
    keys = jax.random.split(k_run, T)
    events = Event(dt=log.dt, u=log.u, is_input=log.is_input, z=log.z, ids=log.ids, mask=log.mask)

    def body(p, x):
        ev, k = x
        return step(p, ev, config, params, key=k)

    p, out = jax.lax.scan(body, p0, (events, keys))
    i = jnp.argmax(p.log_w)
    status = p.status
    if config.association == "known" and (params.gate is not None or config.robust):
        # Known ids behind a gate or a Student-t model: the same rule as the EKF's
        # (jaxslam.filters.consistency): more than 10 % of the sightings of mapped landmarks
        # gated or beyond the model's 99 % quantile (summed over particles) means the particle
        # set stopped being consistent with its noise model.
        n_gated = jnp.sum(out.gated)
        status = status | cons.status_bits(n_gated + jnp.sum(out.outliers), jnp.sum(out.used) + n_gated)
    return Result(
        pose_mean=out.pose_mean, pose_best=out.pose_best, neff=out.neff, map=fs.best_map(p), n_obs=p.aux[1][i],
        used=jnp.sum(out.used).astype(dtype) / N, registered=jnp.sum(out.registered).astype(dtype) / N,
        gated=jnp.sum(out.gated).astype(dtype) / N, outliers=jnp.sum(out.outliers).astype(dtype) / N,
        pruned=jnp.sum(out.pruned).astype(dtype) / N, overflow=p.overflow, resamples=p.resamples,
        underflow=p.underflow, status=status, log_marginal=jnp.sum(out.log_marginal), particles=p,
    )
