"""NumPy twin of paper 003's range-only UWB EKF-SLAM (jaxslam.systems.uwb_slam_2d).

The reference of ``jaxslam bench uwb`` and an independent oracle of the tests:
written directly from the paper, in the paper's own state order (eq. 14)

    x = [x, y, v_x, v_y, l_1x, l_1y, ..., l_Nx, l_Ny, α, β, θ, w_α, w_β, w_θ]

with F of eq. 15 (explicit Δt), the hand Jacobians of eq. 18 (squared range) or
∂d/∂(x, y) = (p − l)/d (plain range), the joint observation of eq. 20 (the valid
UWB rows of mapped anchors stacked over the three gyro rows), the Kalman gain of
eq. 7-8 through ``numpy.linalg.solve`` and the Joseph form
(I − K H) P (I − K H)ᵀ + K R Kᵀ (errata of eq. 10).  The start-up uses
``numpy.linalg.lstsq`` on eq. 26's first column (the line) and the general
trilateration ``numpy.linalg.lstsq`` on eq. 26 (sign-corrected) — the same
decisions as the package (module docstrings there), none of its code.

Float64 only.  ``run(log, cfg, params, anchors)`` returns per-step robot means and
covariances in the *engine* order, so results compare directly.
"""

from __future__ import annotations

import numpy as np

__all__ = ["perm_engine_to_paper", "startup", "trilaterate", "run"]

NR = 10


def perm_engine_to_paper(N):
    """x_paper = x_engine[perm]."""
    return np.asarray([0, 1, 2, 3] + list(range(NR, NR + 2 * N)) + list(range(4, NR)))


def _idx(N):
    """Paper-order indices: pos, vel, landmark i -> (2,), angles, rates."""
    ang = 4 + 2 * N
    return {"pos": [0, 1], "vel": [2, 3], "ang": [ang, ang + 1, ang + 2],
            "rate": [ang + 3, ang + 4, ang + 5], "lm": lambda i: [4 + 2 * i, 5 + 2 * i]}


def _valid(z, m):
    with np.errstate(invalid="ignore"):
        return m & np.isfinite(z) & (np.where(np.isfinite(z), z, 0.0) > 0)


def _sqvar(d, s2):
    return 4.0 * d * d * s2 + 2.0 * s2 * s2


def trilaterate(points, ranges, valid, range_var=None, min_points=3, min_spread=0.0):
    """Eq. 22-26 (A rows 2 (a_k − a_1)), numpy.linalg.lstsq; returns (x, cov, ok)."""
    idx = np.flatnonzero(valid)
    d = points.shape[1]
    if idx.size == 0:
        return np.zeros(d), np.zeros((d, d)), False
    a1, d1 = points[idx[0]], ranges[idx[0]]
    rest = idx[1:]
    A = 2.0 * (points[rest] - a1)
    b = d1 ** 2 - ranges[rest] ** 2 + np.sum(points[rest] ** 2, 1) - a1 @ a1
    if rest.size == 0:
        return np.zeros(d), np.zeros((d, d)), False
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    sv = np.linalg.svd(A, compute_uv=False)
    P = points[idx]
    c = P - P.mean(0)
    lam = np.linalg.eigvalsh(c.T @ c / idx.size)
    spread = np.sqrt(max(lam[0], 0.0))
    ok = (idx.size >= min_points) and sv[-1] > np.sqrt(np.finfo(float).eps) * sv[0] and spread >= min_spread
    cov = np.zeros((d, d))
    if range_var is not None and ok:
        pinv = np.linalg.pinv(A)
        v = _sqvar(ranges, range_var)
        Sb = v[idx[0]] * np.ones((rest.size, rest.size)) + np.diag(v[rest])
        cov = pinv @ Sb @ pinv.T
    return x, cov, bool(ok)


def startup(zs, ms, cfg, params):
    """Paper 003 Sec. III-D start-up: returns (L (N,2), C (N,2,2), init (N,), ref)."""
    Ts, N = zs.shape
    a, b = cfg.start_anchor, cfg.end_anchor
    ok = _valid(zs, ms)
    L = np.zeros((N, 2))
    C = np.zeros((N, 2, 2))
    init = np.zeros(N, bool)
    if not ok[:, b].any():
        return L, C, init, -1
    xs = -np.where(ok[:, b], zs[:, b], 0.0)
    D = zs[np.argmax(ok[:, b]), b]
    s2 = float(params.range_var)
    best, best_y2 = -1, -1.0
    sol = {}
    for i in range(N):
        if i in (a, b):
            continue
        v = ok[:, i] & ok[:, b]
        idx = np.flatnonzero(v)
        if idx.size < params.startup_min_points:
            continue
        x1, d1 = xs[idx[0]], zs[idx[0], i]
        rest = idx[1:]
        A = 2.0 * (xs[rest] - x1)[:, None]
        bb = d1 ** 2 - zs[rest, i] ** 2 + xs[rest] ** 2 - x1 ** 2
        if not np.any(A != 0):
            continue
        u = np.linalg.lstsq(A, bb, rcond=None)[0][0]
        y2 = np.mean(zs[idx, i] ** 2 - (u - xs[idx]) ** 2)
        if y2 <= 0:
            continue
        y = np.sqrt(y2)
        res = np.max(np.abs(np.sqrt((u - xs[idx]) ** 2 + y2) - zs[idx, i]))
        sol[i] = (u, y, res)
        if y2 > best_y2:
            best, best_y2 = i, y2
    init[b] = True
    if D > 0:
        L[a] = (-D, 0.0)
        C[a] = s2 * np.eye(2)
        init[a] = True
    if best >= 0:
        u, y, res = sol[best]
        L[best] = (u, y)
        C[best] = res ** 2 * np.eye(2)
        init[best] = True
    return L, C, init, best


def run(log, cfg, params, anchors=None):
    """Whole log; returns dict(mean (T,10), cov (T,10,10), landmarks (T,N,2), active (T,N), nis (T,))."""
    zs, ms = np.asarray(log.startup_ranges, float), np.asarray(log.startup_mask, bool)
    Z, Mk, G = np.asarray(log.ranges, float), np.asarray(log.range_mask, bool), np.asarray(log.gyro, float)
    T, N = Z.shape
    n = NR + 2 * N
    ix = _idx(N)
    perm = perm_engine_to_paper(N)
    inv = np.argsort(perm)
    Q = np.asarray(params.Q, float)  # engine robot order
    P0 = np.asarray(params.P0, float)
    rob = ix["pos"] + ix["vel"] + ix["ang"] + ix["rate"]  # paper indices of the engine's robot order
    x = np.zeros(n)
    P = np.zeros((n, n))
    P[np.ix_(rob, rob)] = P0
    active = np.zeros(N, bool)
    s2 = float(params.range_var)
    if cfg.mode == "slam":
        L, C, init, _ = startup(zs, ms, cfg, params)
        for i in np.flatnonzero(init):
            li = ix["lm"](i)
            x[li] = L[i]
            P[np.ix_(li, li)] = C[i]
        active = init.copy()
    else:
        A = np.asarray(anchors, float)
        ok = False
        for j in range(zs.shape[0] - 1, -1, -1):  # latest usable fix, inflated for the lag
            p0, c0, ok = trilaterate(A, zs[j], _valid(zs[j], ms[j]), s2)
            if ok:
                lag = (zs.shape[0] - 1 - j) * cfg.dt * params.init_speed_bound
                c0 = c0 + lag * lag * np.eye(2)
                break
        if not ok:
            p0 = A.mean(0)
            c0 = np.max(np.sum((A - p0) ** 2, 1)) * np.eye(2)
        x[ix["pos"]] = p0
        P[np.ix_(ix["pos"], ix["pos"])] = c0
        P[np.ix_(ix["pos"], ix["vel"] + ix["ang"] + ix["rate"])] = 0.0
        P[np.ix_(ix["vel"] + ix["ang"] + ix["rate"], ix["pos"])] = 0.0
        for i in range(N):
            x[ix["lm"](i)] = A[i]
        active[:] = True
    dt = float(cfg.dt)
    F = np.eye(n)
    F[0, 2] = F[1, 3] = dt
    for a_, w_ in zip(ix["ang"], ix["rate"]):
        F[a_, w_] = dt
    Qf = np.zeros((n, n))
    Qf[np.ix_(rob, rob)] = Q
    Rg = float(params.r_gyro)
    W = cfg.buffer_size
    buf_pos, buf_pv = np.zeros((W, 2)), np.zeros(W)
    buf_r, buf_v = np.zeros((W, N)), np.zeros((W, N), bool)
    count = 0
    out = {"mean": np.zeros((T, NR)), "cov": np.zeros((T, NR, NR)), "landmarks": np.zeros((T, N, 2)),
           "active": np.zeros((T, N), bool), "nis": np.zeros(T)}
    for k in range(T):
        # prediction (eq. 1, 4-5 with eq. 12/15)
        x = F @ x
        P = F @ P @ F.T + Qf
        P = 0.5 * (P + P.T)
        # joint observation (eq. 20): valid UWB rows of mapped anchors, then the gyro rows
        ok = _valid(Z[k], Mk[k]) & active
        rows_h, rows_H, rows_z, rows_R = [], [], [], []
        p = x[ix["pos"]]
        if cfg.model == "range" and params.near_gate is not None:  # near-anchor gate (package docs)
            for i in np.flatnonzero(ok):
                if np.sum((x[ix["lm"](i)] - p) ** 2) < params.near_gate ** 2 * s2:
                    ok[i] = False
        for i in np.flatnonzero(ok):
            li = ix["lm"](i)
            l = x[li]
            dvec = p - l
            d = np.sqrt(dvec @ dvec)
            Hi = np.zeros(n)
            if cfg.model == "squared":
                rows_h.append(d * d)
                Hi[ix["pos"]] = 2.0 * dvec  # eq. 18
                Hi[li] = -2.0 * dvec
                rows_z.append(Z[k, i] ** 2 - (s2 if cfg.debias else 0.0))
                rows_R.append(_sqvar(Z[k, i], s2) if cfg.r_scaled else float(params.r_range))
            else:
                rows_h.append(d)
                g = dvec / d if d > 0 else np.zeros(2)
                Hi[ix["pos"]] = g
                Hi[li] = -g
                rows_z.append(Z[k, i])
                rows_R.append(float(params.r_range))
            rows_H.append(Hi)
        if np.all(np.isfinite(G[k])) and active.any():
            for j in range(3):
                Hi = np.zeros(n)
                Hi[ix["rate"][j]] = 1.0
                rows_H.append(Hi)
                rows_h.append(x[ix["rate"][j]])
                rows_z.append(G[k, j])
                rows_R.append(Rg)
        if rows_H:
            H = np.asarray(rows_H)
            R = np.diag(rows_R)
            nu = np.asarray(rows_z) - np.asarray(rows_h)
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T  # eq. 8 (S symmetric)
            x = x + K @ nu
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K @ R @ K.T
            P = 0.5 * (P + P.T)
            out["nis"][k] = nu @ np.linalg.solve(S, nu)
        # delayed initialisation (SLAM)
        if cfg.mode == "slam" and cfg.delayed_init:
            if k % cfg.buffer_stride == 0:
                j = count % W
                okr = _valid(Z[k], Mk[k])
                buf_pos[j] = x[ix["pos"]]
                buf_pv[j] = 0.5 * (P[0, 0] + P[1, 1])
                buf_r[j] = np.where(okr, Z[k], 0.0)
                buf_v[j] = okr
                count += 1
            filled = np.arange(W) < count
            pvar = buf_pv[filled].mean() if filled.any() else 0.0
            for i in range(N):
                if active[i]:
                    continue
                li_ok = buf_v[:, i] & filled
                pos_i, cov_i, ok_i = trilaterate(buf_pos, buf_r[:, i], li_ok, s2, params.delayed_min_points,
                                                 params.min_spread)
                if ok_i:
                    li = ix["lm"](i)
                    x[li] = pos_i
                    P[li, :] = 0.0
                    P[:, li] = 0.0
                    P[np.ix_(li, li)] = cov_i + pvar * np.eye(2)
                    active[i] = True
        xe = x[inv]
        Pe = P[np.ix_(inv, inv)]
        out["mean"][k] = xe[:NR]
        out["cov"][k] = Pe[:NR, :NR]
        out["landmarks"][k] = xe[NR:].reshape(N, 2)
        out["active"][k] = active
    return out
