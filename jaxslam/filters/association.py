"""Data association for the EKF-SLAM engine: joint compatibility branch and bound (JCBB).

Neira & Tardós, "Data association in stochastic mapping using the joint compatibility test",
IEEE Trans. Robotics and Automation 17(6), 2001.  A hypothesis pairs each of the K
measurements of one scan with a mapped landmark or with nothing (a new landmark or clutter),
no landmark twice.  It is *jointly compatible* when the joint NIS of its m pairings, with the
full innovation covariance S = H P Hᵀ + R (robot–landmark and landmark–landmark
cross-covariances included), is below the χ²(m·d_z) quantile ``thresholds[m − 1]``.  JCBB
returns the jointly compatible hypothesis with the most pairings and, among those, the
smallest joint NIS — searched, as Neira & Tardós search, through hypotheses built
measurement by measurement in index order, a branch cut as soon as its partial hypothesis is
not jointly compatible.  The thresholds grow with m, so a hypothesis compatible as a whole
whose leading part is not (e.g. two pairings of d² 7 each, NIS 14 > 13.28, then a third of
0.5, NIS 14.5 < 16.81) is not found: the result can depend on the order of the measurements.

Inside ``jit`` and ``vmap`` the search has static shapes and a static budget:

* each measurement keeps its ``n_cand`` individually compatible landmarks of smallest
  Mahalanobis distance (marginal d² below ``gate``): the branching factor is ``n_cand + 1``
  (the last branch is "unpaired");
* the depth-first search is a ``lax.while_loop`` over an explicit stack (one node per
  iteration) that stops after ``budget`` nodes; ``exhausted`` says so, and the best
  hypothesis found so far is returned (the search visits the "pair" branches first, so the
  first leaf is the greedy nearest-neighbour hypothesis when it is jointly compatible);
* bound: a branch is cut when its pairings plus the measurements still to assign cannot
  beat the best count, or can only equal it with a joint NIS already no smaller (the NIS
  of a superset is never below that of its subset);
* the joint covariance of every candidate pair is formed once per scan from the gathered
  (n_r + K·n_cand·d_l)² block of P; a node factorises only its own (K·d_z)² sub-block.

With ``budget`` ≥ the size of the tree (``(n_cand + 1)^K`` leaves at most) the result equals
an exhaustive search over every hypothesis whose leading parts are all jointly compatible
(tested on random cases against a search over every hypothesis).  The engine never names a dataset: the
model supplies ``observe`` and ``residual``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError
from ..linalg import check_int, is_concrete, symmetrize
from .ekf_slam import SlamModel, SlamState, _check_associate, _check_options, marginal_d2, slot_indices

__all__ = ["JCBBResult", "jcbb", "individual_compatibility"]


class JCBBResult(NamedTuple):
    """slots (K,) int32 landmark slot paired with each measurement (−1: unpaired);
    paired (K,) bool; nis: () joint NIS of the chosen pairings; n_paired: () int32;
    nodes: () int32 search nodes visited; exhausted: () bool the budget ran out first;
    d2: (K,) smallest marginal Mahalanobis distance of each measurement (inf: none mapped);
    status: () int32 :mod:`jaxslam.errors` flags — ``NON_FINITE`` when a traced ``gate`` is not a
    finite number > 0 or a traced threshold is not > 0 (NaN included): such a value pairs
    nothing, and under ``jit`` it cannot be refused as a concrete one is (:class:`InputError`)."""

    slots: jax.Array
    paired: jax.Array
    nis: jax.Array
    n_paired: jax.Array
    nodes: jax.Array
    exhausted: jax.Array
    d2: jax.Array
    status: jax.Array


def _check_rows(state: SlamState, model: SlamModel, z, mask, R):
    """The engine's own checks of one scan (shapes static, R's values when concrete):
    ``(z (K, d_z), mask (K,) bool, R (K, d_z, d_z))``, or :class:`InputError` naming the
    argument (a state of another lm_dim, a wrong z, mask or R, a non-PSD R)."""
    return _check_associate(state, model, z, mask, R)


def _compatibility(state, model, z, mask, R, params):
    d2, pred = marginal_d2(state, model, z, mask, R, params)
    return jnp.where(jnp.isfinite(d2), d2, jnp.inf), pred


def individual_compatibility(state: SlamState, model: SlamModel, z, mask, R, params=None):
    """Marginal d² (K, cap) of every measurement against every mapped landmark (inf elsewhere),
    and the per-pair predictions (ẑ (cap, d_z), H_s (cap, d_z, n_r), H_l (cap, d_z, d_l), ν):
    the engine's :func:`~jaxslam.filters.ekf_slam.marginal_d2`, with non-finite d² excluded.

    z: (K, d_z); mask: (K,) bool; R: (d_z, d_z), (K, d_z, d_z) or, for d_z = 1, a scalar —
    checked as :func:`jcbb` checks them (:class:`InputError` naming the argument: a wrong R,
    z or mask was a broadcast or index error, a negative R was used)."""
    z, mask, R = _check_rows(state, model, z, mask, R)
    return _compatibility(state, model, z, mask, R, params)


def _check_thresholds(thresholds, K: int, dtype):
    """``thresholds`` (K,) joint χ² thresholds; their values when concrete: > 0, never NaN (a NaN
    or negative threshold made every pairing incompatible, so JCBB paired nothing)."""
    thr = jnp.asarray(thresholds, dtype)
    if thr.shape != (K,):
        raise InputError(f"thresholds: expected ({K},) joint χ² thresholds, one per number of pairings, "
                         f"got shape {thr.shape}")
    if is_concrete(thr):
        v = np.asarray(thr)
        bad = ~(v > 0)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(f"thresholds: expected positive joint χ² thresholds, got thresholds[{k}] = {v[k]}")
    return thr


def jcbb(state: SlamState, model: SlamModel, z, mask, R, params=None, *, gate, thresholds,
         n_cand: int = 3, budget: int = 256) -> JCBBResult:
    """Joint compatibility branch and bound over one scan (module docstring).

    Args:
      z: (K, d_z) measurements; mask: (K,) bool present.  R: (d_z, d_z) or (K, d_z, d_z).
      gate: individual-compatibility threshold on the marginal d² (e.g. χ²(d_z) 99 %).
      thresholds: (K,) joint thresholds, ``thresholds[m − 1]`` for m pairings (χ²(m·d_z)); > 0
        (a concrete NaN or non-positive one is an :class:`InputError`; a traced one, like a
        traced bad ``gate``, sets ``NON_FINITE`` in ``status``).
      n_cand, budget: static sizes (candidates kept per measurement, search nodes).

    Called eagerly it is compiled once per model and sizes
    (:func:`jaxslam.compilation.call_compiled`): uncompiled, each call traced and compiled its
    search loop again (0.3 s a call for two rows and three landmarks, 5.6 s the first, the
    programs kept).
    """
    z, mask, R, thr, C, budget = _check_jcbb(state, model, z, mask, R, gate, thresholds, n_cand, budget)
    return call_compiled(("association.jcbb", model, C, budget),
                         lambda opts, st, z, mask, R, thr: _jcbb(st, model, z, mask, R, opts[0], opts[1], thr, C,
                                                                 budget),
                         (state, z, mask, R, thr), (params, gate), after="auto")


def _check_jcbb(state: SlamState, model: SlamModel, z, mask, R, gate, thresholds, n_cand, budget):
    """:func:`jcbb`'s checks (shapes, and the values known now): ``(z, mask, R, thresholds, n_cand,
    budget)``."""
    # the engine's own checks (shapes static, values when concrete): a short `thresholds` was
    # index-clamped, a scalar R broadcast to a full matrix, a state of another lm_dim paired nothing
    z, mask, R = _check_rows(state, model, z, mask, R)
    C = check_int(n_cand, "n_cand")
    budget = check_int(budget, "budget")
    _check_options(gate=gate)
    if gate is None or callable(gate):
        raise InputError(f"gate: expected the individual-compatibility χ² threshold (a number), got {gate!r}")
    return z, mask, R, _check_thresholds(thresholds, z.shape[0], state.x.dtype), C, budget


def _jcbb(state: SlamState, model: SlamModel, z, mask, R, params, gate, thresholds, n_cand: int,
          budget: int) -> JCBBResult:
    """:func:`jcbb`'s computation."""
    nr, dl, dz = model.robot_dim, model.lm_dim, model.meas_dim
    z, mask, R, thr, C, budget = _check_jcbb(state, model, z, mask, R, gate, thresholds, n_cand, budget)
    K = z.shape[0]
    dtype = state.x.dtype
    d2, (zh, Hs, Hl, nu) = _compatibility(state, model, z, mask, R, params)
    cap = d2.shape[1]
    C = min(C, cap)
    # candidates: the C smallest individually compatible distances of each measurement
    neg, cand = jax.lax.top_k(-jnp.where(d2 < gate, d2, jnp.inf), C)  # (K, C)
    cand_ok = jnp.isfinite(neg)
    cand = cand.astype(jnp.int32)
    # joint covariance of every (measurement, candidate) pair with every other
    Hs_c = Hs[cand]  # (K, C, dz, nr)
    Hl_c = Hl[cand]  # (K, C, dz, dl)
    nu_c = jnp.take_along_axis(nu, cand[:, :, None], axis=1)  # (K, C, dz)
    idx = jnp.concatenate([jnp.arange(nr), slot_indices(cand.reshape(-1), model).reshape(-1)])
    Psub = state.P[idx[:, None], idx[None, :]]  # (nr + K C dl)²
    KC = K * C
    Hl_blk = jnp.einsum("azj,ab->azbj", Hl_c.reshape(KC, dz, dl), jnp.eye(KC, dtype=dtype)).reshape(KC * dz, KC * dl)
    H = jnp.concatenate([Hs_c.reshape(KC * dz, nr), Hl_blk], axis=1)
    S_all = (H @ Psub @ H.T).reshape(K, C, dz, K, C, dz)
    eyeK = jnp.eye(K, dtype=dtype)
    # + R on the measurement's own block (two candidates of one measurement never meet)
    S_all = S_all + eyeK[:, None, None, :, None, None] * R[:, None, :, None, None, :]
    eye_dz = jnp.eye(dz, dtype=dtype)
    big = jnp.asarray(jnp.inf, dtype)
    ar = jnp.arange(K)

    def joint_nis(assign):
        # assign (K,) int: candidate index 0..C-1, or C (unpaired / not yet assigned)
        on = assign < C
        a = jnp.clip(assign, 0, C - 1)
        Sg = S_all[ar[:, None], a[:, None], :, ar[None, :], a[None, :], :]  # (K, K, dz, dz)
        both = on[:, None] & on[None, :]
        Sg = jnp.where(both[:, :, None, None], Sg, eyeK[:, :, None, None] * eye_dz)
        Sg = Sg.transpose(0, 2, 1, 3).reshape(K * dz, K * dz)
        v = jnp.where(on[:, None], nu_c[ar, a], 0.0).reshape(K * dz)
        Lc = jnp.linalg.cholesky(symmetrize(Sg))
        w = jax.scipy.linalg.solve_triangular(Lc, v, lower=True)
        n = jnp.sum(w * w)
        return jnp.where(jnp.all(jnp.isfinite(Lc)), n, big)

    # Depth-first search with an explicit stack: depth d, assignment (K,), choice pointer (K,)
    # (the next branch to try at each depth: candidates 0..C-1, then C = unpaired, then done).
    class S(NamedTuple):
        d: jax.Array
        assign: jax.Array
        ptr: jax.Array
        m: jax.Array  # pairings in assign[:d]
        best: jax.Array
        best_m: jax.Array
        best_nis: jax.Array
        nodes: jax.Array
        nis: jax.Array  # (K + 1,) joint NIS of the pairings above each depth (nis[0] = 0)

    unassigned = jnp.full((K,), C, jnp.int32)
    s0 = S(d=jnp.int32(0), assign=unassigned, ptr=jnp.zeros((K,), jnp.int32), m=jnp.int32(0),
           best=unassigned, best_m=jnp.int32(0), best_nis=jnp.asarray(0.0, dtype), nodes=jnp.int32(0),
           nis=jnp.zeros((K + 1,), dtype))

    def used_slot(assign, d, j):
        a = jnp.clip(assign, 0, C - 1)
        on = (assign < C) & (ar < d)
        return jnp.any(on & (cand[ar, a] == j))

    def step(s):
        d = s.d
        at_leaf = d >= K

        def leaf(s):
            n = s.nis[K]  # computed on the way down
            better = (s.m > s.best_m) | ((s.m == s.best_m) & (n < s.best_nis))
            return s._replace(best=jnp.where(better, s.assign, s.best),
                              best_m=jnp.where(better, s.m, s.best_m),
                              best_nis=jnp.where(better, n, s.best_nis), d=d - 1)

        def branch(s):
            dd = jnp.clip(d, 0, K - 1)
            p = s.ptr[dd]
            done = p > C
            prev = s.assign[dd]
            m_prev = s.m - (prev < C).astype(jnp.int32)  # pairings before depth dd

            def backtrack(s):
                return s._replace(assign=s.assign.at[dd].set(C), ptr=s.ptr.at[dd].set(0), m=m_prev,
                                  d=d - 1)

            def try_branch(s):
                pair = p < C
                j = cand[dd, jnp.clip(p, 0, C - 1)]
                ok_pair = pair & mask[dd] & cand_ok[dd, jnp.clip(p, 0, C - 1)] & ~used_slot(s.assign, dd, j)
                assign = s.assign.at[dd].set(jnp.where(pair, p, C))
                m_new = m_prev + pair.astype(jnp.int32)
                remaining = (K - 1 - dd).astype(jnp.int32)
                # leaving measurement dd unpaired keeps the pairings above: their NIS is known
                n = jax.lax.cond(pair, lambda: joint_nis(assign), lambda: s.nis[dd])
                comp = (m_new == 0) | (n <= thr[jnp.maximum(m_new - 1, 0)])
                # bound: can this branch still beat the best?
                reach = m_new + remaining
                hope = (reach > s.best_m) | ((reach == s.best_m) & (n < s.best_nis))
                go = jnp.where(pair, ok_pair & comp & hope, hope)
                s = s._replace(ptr=s.ptr.at[dd].set(p + 1))
                return jax.lax.cond(go, lambda s: s._replace(assign=assign, m=m_new, d=d + 1,
                                                             nis=s.nis.at[dd + 1].set(n)),
                                    lambda s: s._replace(assign=s.assign.at[dd].set(C), m=m_prev), s)

            return jax.lax.cond(done, backtrack, try_branch, s)

        s = jax.lax.cond(at_leaf, leaf, branch, s)
        return s._replace(nodes=s.nodes + 1)

    def cond(s):
        return (s.d >= 0) & (s.nodes < budget)

    # The empty hypothesis is always jointly compatible: it is the starting "best".
    s = jax.lax.while_loop(cond, step, s0)
    exhausted = s.d >= 0
    best = s.best
    paired = best < C
    slots = jnp.where(paired, cand[ar, jnp.clip(best, 0, C - 1)], -1).astype(jnp.int32)
    g = jnp.asarray(gate, dtype)
    bad_opt = ~(jnp.isfinite(g) & (g > 0)) | jnp.any(~(thr > 0))
    status = jnp.where(bad_opt, jnp.int32(errors.NON_FINITE), jnp.int32(0))
    return JCBBResult(slots=slots, paired=paired, nis=s.best_nis, n_paired=s.best_m, nodes=s.nodes,
                      exhausted=exhausted, d2=jnp.min(d2, axis=1), status=status)
