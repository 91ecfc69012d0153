"""Prototype of a faster EKF-SLAM engine step (a proposal for jaxslam/filters/ekf_slam.py).

Not part of the package: ``bench_ekfslam --parts proto`` times it against the
engine and ``tests/benchmarks/test_bench_twin.py`` checks that it computes the
same filter (agreement with the NumPy twin to 1e-8).  Same algebra as the
engine; only where the work happens changes:

1. ``predict_fast``: the non-finite guard selects between the new and old
   *blocks* (P_rr, P_rl, s) before they are written.  The engine selects
   between the whole new and old covariance (``jnp.where(ok, P, state.P)``),
   which reads and writes all n² entries every IMU step and makes the
   prediction O(n²) instead of O(n).
(Items 1-2 have since been adopted by the engine, jaxslam/filters/ekf_slam.py.)

2. ``update_fast``: (a) the Joseph form grouped as A − (A Hᵀ − K R) Kᵀ (one
   n²·m product fewer than A − (A Hᵀ) Kᵀ + (K R) Kᵀ); (b) the gain through the
   explicit m×m inverse of the innovation covariance from its Cholesky factor,
   K = (P Hᵀ) S⁻¹ (an XLA matmul), instead of a LAPACK triangular solve with n
   right-hand sides (jaxlib's LAPACK runs on OpenBLAS, whose threads, unless
   pinned, stall for ~20 ms per call on a busy 2-core machine).
3. ``update_bucketed``: the valid measurements are compacted to the front and
   the joint update runs at the smallest static size in ``buckets`` that holds
   them (``lax.switch``), so a frame with 5 mapped observations pays for 8, not
   for max_obs = 16.  Still ONE joint update: the estimates do not change.
4. ``register_fast``: rejected candidates are scattered out of bounds
   (``mode="drop"``) instead of selecting old/new rows (which made XLA copy P
   per candidate), and a ``while_loop`` visits only the candidates present
   (most frames have none) instead of a fixed max_obs-long scan.
6. ``update_active_block``: slots fill first-free and inactive ones have zero
   covariance, so the update of the leading block that holds every active slot
   is exact; a ``lax.switch`` over capacity/8, /4, /2, /1 picks the block, and
   the update costs O(n_active²·m) instead of O(capacity²·m).

5. ``make_model_fused``: the paper-000 model with its 3×3 matrix-vector
   products (C v, D ω, Cᵀ(l − ρ), C ϱ) written as elementwise multiply + sum.
   Same values (bitwise here), but XLA fuses them into the surrounding loop
   fusions instead of emitting one tiny dot kernel each; under ``jacfwd`` (9
   tangents through 4 RK4 stages) the prediction step went from ~260 kernels
   to far fewer and from ~52 µs to ~20 µs on the 2-core CPU.

``filter_log_fast`` is ``jaxslam.systems.ekf_slam_3d.filter_log`` (known-id
association, gate off) built on these steps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam import errors
from jaxslam.filters import ekf_slam as es
from jaxslam.geometry.euler import dcm_from_euler, euler_rate_matrix
from jaxslam.linalg import symmetrize, wrap_angle
from jaxslam.sensors import lidar3d
from jaxslam.systems import ekf_slam_3d as sys3d

__all__ = ["predict_fast", "update_fast", "update_bucketed", "register_fast", "filter_log_fast",
           "make_model_fused", "f_cont_fused", "process_noise_fused"]


# ---------------------------------------------------------------------------
# The paper-000 model with fusible matrix-vector products (same equations as
# jaxslam.systems.ekf_slam_3d / jaxslam.sensors.lidar3d)
# ---------------------------------------------------------------------------

def _mv(M, v):
    """M v as multiply + reduce (XLA fuses it; a 3×3 dot is a kernel of its own)."""
    return jnp.sum(M * v[None, :], axis=-1)


def f_cont_fused(s, imu, g, accel_mode="3axis"):
    """sys3d.f_cont with fusible products."""
    v, e, w = s[3:6], s[6:9], imu[3:6]
    f_b = imu[0:3]
    if accel_mode == "az":
        f_b = jnp.zeros_like(f_b).at[2].set(f_b[2])
    C = dcm_from_euler(e)
    g = jnp.asarray(g, s.dtype)
    return jnp.concatenate([_mv(C, v), -jnp.cross(w, v) + g * C[2, :] + f_b, _mv(euler_rate_matrix(e), w)])


def motion_fused(s, u, params):
    """sys3d.motion (RK4, first-order hold) on f_cont_fused."""
    dt, g, accel_mode = params
    a, b = u[:6], u[6:]
    dt = jnp.asarray(dt, s.dtype)

    def f(x, tau):
        return f_cont_fused(x, a + (b - a) * tau, g, accel_mode)

    k1 = f(s, 0.0)
    k2 = f(s + 0.5 * dt * k1, 0.5)
    k3 = f(s + 0.5 * dt * k2, 0.5)
    k4 = f(s + dt * k3, 1.0)
    s_new = s + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s_new.at[6:9].set(wrap_angle(s_new[6:9]).at[1].set(s_new[7]))


def process_noise_fused(s, imu, noise, dt, g, accel_mode="3axis"):
    """sys3d.process_noise on f_cont_fused."""
    G = jax.jacfwd(lambda lam: f_cont_fused(s, lam, g, accel_mode))(imu)
    return (noise.Qc + G @ noise.Qimu @ G.T) * jnp.asarray(dt, s.dtype)


def _observe_fused(s, l, params):
    C = dcm_from_euler(s[6:9])
    c = jnp.sum(C * (l - s[0:3])[:, None], axis=0)  # Cᵀ (l − ρ)
    return lidar3d.spherical_from_cartesian(c)


def _inverse_fused(s, z, params):
    C = dcm_from_euler(s[6:9])
    return _mv(C, lidar3d.cartesian_from_spherical(z)) + s[0:3]


def make_model_fused():
    """sys3d.make_model() with the fusible model functions."""
    return sys3d.make_model()._replace(motion=motion_fused, observe=_observe_fused,
                                       inverse=_inverse_fused)


def _flag_if(cond, bit):
    return jnp.where(cond, jnp.int32(bit), jnp.int32(0))


def predict_fast(state, model, u, Q, params=None):
    """es.predict with the non-finite guard applied to the written blocks only (O(n))."""
    nr = model.robot_dim
    s = state.x[:nr]

    def f(s_):
        return model.motion(s_, u, params)

    s_new, F = f(s), jax.jacfwd(f)(s)
    Prr = state.P[:nr, :nr]
    Prl = state.P[:nr, nr:]
    Prr_new = symmetrize(F @ Prr @ F.T + Q)
    Prl_new = F @ Prl
    ok = jnp.all(jnp.isfinite(s_new)) & jnp.all(jnp.isfinite(Prr_new)) & jnp.all(jnp.isfinite(Prl_new))
    Prr_new = jnp.where(ok, Prr_new, Prr)
    Prl_new = jnp.where(ok, Prl_new, Prl)
    s_new = jnp.where(ok, s_new, s)
    P = jax.lax.dynamic_update_slice(state.P, jnp.concatenate([Prr_new, Prl_new], axis=1), (0, 0))
    P = jax.lax.dynamic_update_slice(P, Prl_new.T, (nr, 0))
    return state._replace(x=state.x.at[:nr].set(s_new), P=P,
                          status=state.status | _flag_if(~ok, errors.NON_FINITE))


def update_fast(state, model, z, slots, mask, R, params=None):
    """es.update (gate off) with the grouped Joseph form and an m×m inverse for the gain."""
    nr, dl, cap = model.robot_dim, model.lm_dim, state.active.shape[0]
    dz = model.meas_dim
    K = z.shape[0]
    m = K * dz
    dtype = state.x.dtype
    slots = jnp.clip(slots.astype(jnp.int32), 0, cap - 1)
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, dz, dz))
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    valid = mask & state.active[slots] & finite
    z_safe = jnp.where(valid[:, None], z, 0.0).astype(dtype)
    s = state.x[:nr]
    L = state.x[nr:].reshape(cap, dl)[slots]

    def one(l):
        zh = model.observe(s, l, params)
        Hs, Hl = jax.jacfwd(model.observe, argnums=(0, 1))(s, l, params)
        return zh, Hs, Hl

    zh, Hs, Hl = jax.vmap(one)(L)
    res = jax.vmap(model.residual)(z_safe, zh)
    idx = es.slot_indices(slots, model)
    P = state.P
    vv = jnp.repeat(valid.astype(dtype), dz)
    VV = vv[:, None] * vv[None, :]

    def gather_ht(M):
        # M Hᵀ from the columns H touches, (n, m)
        out = jnp.einsum("ni,kzi->nkz", M[:, :nr], Hs) + jnp.einsum("nkj,kzj->nkz", M[:, idx], Hl)
        return out.reshape(-1, m) * vv[None, :]

    PHt = gather_ht(P)
    HPHt = (jnp.einsum("kzi,im->kzm", Hs, PHt[:nr])
            + jnp.einsum("kzj,kjm->kzm", Hl, PHt[idx])).reshape(m, m)
    R_blk = jnp.zeros((K, dz, K, dz), dtype).at[jnp.arange(K), :, jnp.arange(K), :].set(R).reshape(m, m)
    R_used = R_blk * VV
    S = HPHt * VV + R_used + jnp.diag(1.0 - vv)
    nu = res.reshape(m) * vv
    Lc = jnp.linalg.cholesky(symmetrize(S))
    Sinv = jax.scipy.linalg.cho_solve((Lc, True), jnp.eye(m, dtype=dtype))
    Kg = PHt @ Sinv  # (n, m) = P Hᵀ S⁻¹
    # Guard on the small quantities (O(n·m)): with P, P Hᵀ and K finite, the
    # covariance products are finite, so no O(n²) check/select of the result
    # is needed; a rejected update zeroes the gain, which leaves x and P
    # exactly unchanged (P is exactly symmetric).
    ok = jnp.all(jnp.isfinite(Lc)) & jnp.all(jnp.isfinite(Kg)) & jnp.all(jnp.isfinite(nu))
    Kg = jnp.where(ok, Kg, 0.0)
    x_new = state.x + Kg @ jnp.where(ok, nu, 0.0)
    A = P - Kg @ PHt.T  # (I − K H) P
    AHt = gather_ht(A)  # (I − K H) P Hᵀ
    # The barrier keeps XLA from fusing the transposed read of symmetrize into the
    # matmul's consumer (measured 1.4x slower at n = 777 without it).
    P_new = symmetrize(jax.lax.optimization_barrier(A - (AHt - Kg @ R_used) @ Kg.T))
    status = state.status | _flag_if(~ok, errors.NON_FINITE)
    return state._replace(x=x_new, P=P_new, status=status)


def update_bucketed(state, model, z, slots, mask, R, params=None, buckets=(4, 8, 16)):
    """One joint update at the smallest static size in ``buckets`` holding the valid measurements.

    ``buckets`` must be increasing and end at K = z.shape[0] (every K fits the last).
    No valid measurement: the update is skipped (identity branch).
    """
    K = z.shape[0]
    buckets = tuple(b for b in buckets if b < K) + (K,)
    cap = state.active.shape[0]
    sl = jnp.clip(slots.astype(jnp.int32), 0, cap - 1)
    valid = mask & state.active[sl] & jnp.all(jnp.isfinite(z), axis=-1)
    order = jnp.argsort(~valid, stable=True)
    z, slots, valid = z[order], slots[order], valid[order]
    count = jnp.sum(valid)
    R = jnp.asarray(R)
    per_meas_R = R.ndim == 3
    if per_meas_R:
        R = R[order]

    def branch(b):
        def f(st):
            Rb = R[:b] if per_meas_R else R
            return update_fast(st, model, z[:b], slots[:b], valid[:b], Rb, params)
        return f

    branches = [lambda st: st] + [branch(b) for b in buckets]
    bounds = jnp.asarray(buckets)
    which = jnp.where(count == 0, 0, 1 + jnp.searchsorted(bounds, count, side="left"))
    return jax.lax.switch(which, branches, state)


def update_active_block(state, model, z, slots, mask, R, params=None, fractions=(8, 4, 2, 1)):
    """update_fast on the leading block of the state that holds every active slot.

    Slots are filled first-free, so the active landmarks occupy the leading slots,
    and inactive slots have zero covariance with everything: the update of the
    leading n_b = n_r + b·d_l block is exact and costs O(n_b²·m) instead of
    O(n²·m).  b is the smallest of capacity/8, /4, /2, /1 that covers the highest
    active slot, chosen at run time with ``lax.switch`` (one branch per size).
    """
    nr, dl, cap = model.robot_dim, model.lm_dim, state.active.shape[0]
    sizes = sorted({max(1, cap // f) for f in fractions} | {cap})
    top = jnp.max(jnp.where(state.active, jnp.arange(cap) + 1, 0))  # slots in use from the front

    def branch(b):
        nb = nr + b * dl

        def f(st):
            sub = st._replace(x=st.x[:nb], P=st.P[:nb, :nb], active=st.active[:b], ids=st.ids[:b])
            sl = jnp.where(slots < b, slots, 0)
            new = update_fast(sub, model, z, sl, mask & (slots < b), R, params)
            return st._replace(x=jax.lax.dynamic_update_slice(st.x, new.x, (0,)),
                               P=jax.lax.dynamic_update_slice(st.P, new.P, (0, 0)),
                               status=new.status)
        return f

    which = jnp.searchsorted(jnp.asarray(sizes), top, side="left")
    return jax.lax.switch(jnp.clip(which, 0, len(sizes) - 1), [branch(b) for b in sizes], state)


def register_fast(state, model, z, lm_ids, mask, R, params=None):
    """es.register with the per-candidate guard on the written rows/columns only (O(n))."""
    nr, dl, cap = model.robot_dim, model.lm_dim, state.active.shape[0]
    dtype = state.x.dtype
    K = z.shape[0]
    n = state.x.shape[0]
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K, model.meas_dim, model.meas_dim))

    def body(st, inp):
        zk, idk, mk, Rk = inp
        finite = jnp.all(jnp.isfinite(zk))
        zk = jnp.where(finite, zk, 0.0).astype(dtype)
        free = ~st.active
        has_free = jnp.any(free)
        slot = jnp.argmax(free)
        s = st.x[:nr]
        l = model.inverse(s, zk, params)
        Gs, Gz = jax.jacfwd(model.inverse, argnums=(0, 1))(s, zk, params)
        Pll = symmetrize(Gs @ st.P[:nr, :nr] @ Gs.T + Gz @ Rk @ Gz.T)
        Plx = Gs @ st.P[:nr, :]
        good = mk & finite & has_free & jnp.all(jnp.isfinite(l)) & jnp.all(jnp.isfinite(Pll))
        start = nr + slot * dl
        row = jax.lax.dynamic_update_slice(Plx, Pll, (0, start))
        # rejected candidates scatter out of bounds (dropped): no O(n²) select
        rid = jnp.where(good, start + jnp.arange(dl), n)
        P = st.P.at[rid, :].set(row, mode="drop")
        P = P.at[:, rid].set(row.T, mode="drop")
        x = st.x.at[rid].set(l, mode="drop")
        active = st.active.at[slot].set(jnp.where(good, True, st.active[slot]))
        ids = st.ids.at[slot].set(jnp.where(good, jnp.int32(idk), st.ids[slot]))
        over = mk & finite & ~has_free
        st = st._replace(
            x=x, P=P, active=active, ids=ids,
            overflow=st.overflow + over.astype(jnp.int32),
            status=st.status | _flag_if(over, errors.CAPACITY_OVERFLOW)
            | _flag_if(mk & ~finite, errors.MASKED_INPUT),
        )
        return st, None

    # Only the candidates present are visited: they are moved to the front (stable,
    # so the registration order is the engine's) and a while_loop stops after them;
    # most frames have none, and a fixed-length scan would pay K iterations.
    order = jnp.argsort(~mask, stable=True)
    zc, idc, mc, Rc = z[order], lm_ids.astype(jnp.int32)[order], mask[order], R[order]
    count = jnp.sum(mask)

    def loop_body(carry):
        i, st = carry
        st, _ = body(st, (zc[i], idc[i], mc[i], Rc[i]))
        return i + 1, st

    _, state = jax.lax.while_loop(lambda c: c[0] < count, loop_body, (jnp.int32(0), state))
    return state


def filter_log_fast(noise, cfg, s0, imu, y, ids, visible, lidar_every, landmarks_true=None,
                    buckets=(4, 8, 16), fused=True):
    """``ekf_slam_3d.filter_log`` (known ids, no gate) on the fast steps.

    ``buckets``: None — ``update_fast`` at the full max_obs size (no switch);
    ``"active"`` — ``update_active_block``; a tuple — ``update_bucketed`` with
    these measurement-count sizes.
    ``fused=False`` uses the package's model functions instead of the fusible ones.
    Returns (final SlamState, means (T, 9)).
    """
    model = make_model_fused() if fused else sys3d.make_model()
    pnoise = process_noise_fused if fused else sys3d.process_noise
    mparams = (cfg.dt, cfg.g, cfg.accel_mode)
    dtype = s0.dtype
    F, L = visible.shape
    M = min(cfg.max_obs, L)
    st = es.init(s0, noise.P0.astype(dtype), cfg.capacity, 3)
    if cfg.mode == "known":
        Lt = landmarks_true.shape[0]
        st = st._replace(x=st.x.at[9:9 + 3 * Lt].set(landmarks_true.reshape(-1).astype(dtype)),
                         active=st.active.at[:Lt].set(True),
                         ids=st.ids.at[:Lt].set(jnp.arange(Lt, dtype=jnp.int32)))
    ids = jnp.broadcast_to(ids, (F, L))
    imu_prev = imu[:-1].reshape(F, lidar_every, 6)
    imu_now = imu[1:].reshape(F, lidar_every, 6)
    R = noise.R.astype(dtype)

    def propagate(st, ab):
        a, b = ab
        Qd = pnoise(st.x[:9], 0.5 * (a + b), noise, cfg.dt, cfg.g, cfg.accel_mode)
        st = predict_fast(st, model, jnp.concatenate([a, b]), Qd, mparams)
        return st, st.x[:9]

    def frame(st, inp):
        a, b, yf, idf, vf = inp
        st, means = jax.lax.scan(propagate, st, (a, b))
        order = jnp.argsort(~vf, stable=True)[:M]
        y_s, id_s, vis_s = yf[order], idf[order], vf[order]
        slots, mapped = es.associate_known(st, id_s, vis_s)
        if buckets == "active":
            st = update_active_block(st, model, y_s, slots, mapped, R, mparams)
        elif buckets is None:
            st = update_fast(st, model, y_s, slots, mapped, R, mparams)
        else:
            st = update_bucketed(st, model, y_s, slots, mapped, R, mparams, buckets)
        if cfg.mode == "unknown":
            st = register_fast(st, model, y_s, id_s, vis_s & ~mapped, R, mparams)
        return st, means

    st, means = jax.lax.scan(frame, st, (imu_prev, imu_now, y, ids, visible))
    return st, means.reshape(-1, 9)
