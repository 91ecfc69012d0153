"""Plots of paper 003's range-only UWB runs (one flight, plus the Monte Carlo NEES).

* ``*_path``: true and estimated path, true anchors, estimated anchors with
  their final 3σ covariance ellipses (in the comparison frame);
* ``*_startup``: the forced straight-line run — true positions and the
  positions the start-up assumes, (−d(k), 0) — and the anchors as the start-up
  initialised them, with 3σ ellipses (localisation: the initial LS fix);
* ``*_errors``: x, y, velocity and attitude errors with ±3σ bands, and each
  anchor's error over time (SLAM);
* ``*_nees``: per-step ANEES over the runs (robot block and position) with
  their 95 % bounds.

NumPy inputs; matplotlib is imported lazily (Agg).
"""

from __future__ import annotations

import numpy as np

from .flight import plt, save

__all__ = ["ellipse_points", "plot_all"]


def ellipse_points(mean, cov, k=3.0, n=64):
    """(n, 2) points of the k-σ ellipse of a 2D Gaussian (mean (2,), cov (2, 2))."""
    w, V = np.linalg.eigh(0.5 * (np.asarray(cov) + np.asarray(cov).T))
    w = np.sqrt(np.clip(w, 0.0, None))
    a = np.linspace(0, 2 * np.pi, n)
    circ = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.asarray(mean)[None, :] + k * (circ * w[None, :]) @ V.T


def _frame(sim, res, cfg):
    from ..sim.scenarios.uwb import startup_frame

    if cfg.mode == "slam":
        M, o = startup_frame(sim.anchors, res.startup.ref_anchor, cfg.start_anchor, cfg.end_anchor)
        return np.asarray(M), np.asarray(o)
    return np.eye(2), np.zeros(2)


def plot_all(name, sim, res, ev, setup, cfg, per_step, cons, runs, directory):
    """Write the four figures; returns their paths."""
    p = plt()
    paths = []
    M, o = _frame(sim, res, cfg)
    tr = np.asarray(sim.truth)
    pos_t = (tr[:, :2] - o) @ M.T
    anc_t = (np.asarray(sim.anchors) - o) @ M.T
    st = res.steps
    t = np.asarray(setup.ts)
    frame = "start-up frame" if cfg.mode == "slam" else "anchor frame"

    # --- path and map
    fig, ax = p.subplots(figsize=(7, 6))
    ax.plot(pos_t[:, 0], pos_t[:, 1], "C0-", lw=1.5, label="true")
    ax.plot(st.mean[:, 0], st.mean[:, 1], "C1--", lw=1.2, label="estimated")
    su = (setup.startup_pos - o) @ M.T
    ax.plot(su[:, 0], su[:, 1], "k:", lw=1, label="start-up run")
    ax.scatter(anc_t[:, 0], anc_t[:, 1], c="g", marker="^", s=60, label="anchors (true)", zorder=3)
    act = np.asarray(st.active[-1])
    L = np.asarray(st.landmarks[-1])
    C = np.asarray(st.lm_cov[-1])
    if cfg.mode == "slam":
        ax.scatter(L[act, 0], L[act, 1], c="r", marker="x", s=50, label="anchors (estimated)", zorder=4)
        for i in np.flatnonzero(act):
            e = ellipse_points(L[i], C[i])
            ax.plot(e[:, 0], e[:, 1], "r-", lw=0.8)
    for i, a in enumerate(anc_t):
        ax.annotate(f"{i}", a, textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x [m] ({frame})")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{name} ({cfg.mode}, {cfg.model}): path and anchors (3σ)")
    ax.legend(fontsize=7, loc="best")
    paths.append(save(fig, directory, f"{name}_path"))

    # --- start-up phase
    fig, ax = p.subplots(figsize=(7, 5))
    ax.scatter(anc_t[:, 0], anc_t[:, 1], c="g", marker="^", s=60, label="anchors (true)", zorder=3)
    if cfg.mode == "slam":
        ax.plot(su[:, 0], su[:, 1], "C0o-", ms=3, lw=1, label="true start-up positions")
        sp = np.asarray(res.startup.positions)
        ax.plot(sp[:, 0], sp[:, 1] + 0.05, "C1x", ms=4, label="assumed (−d(k), 0) (offset +5 cm)")
        ini = np.asarray(res.startup.initialised)
        L0 = np.asarray(res.startup.landmarks)
        C0 = np.asarray(res.startup.cov)
        ax.scatter(L0[ini, 0], L0[ini, 1], c="r", marker="x", s=60, label="initialised anchors", zorder=4)
        for i in np.flatnonzero(ini):
            e = ellipse_points(L0[i], C0[i])
            ax.plot(e[:, 0], e[:, 1], "r-", lw=0.8)
        ax.set_title(f"{name}: forced straight-line start-up and LS trilateration (3σ)")
    else:
        rp = np.asarray(res.startup.robot_pos)
        e = ellipse_points(rp, np.asarray(res.startup.robot_cov))
        ax.plot(rp[0], rp[1], "rx", ms=8, label="initial LS fix")
        ax.plot(e[:, 0], e[:, 1], "r-", lw=0.8)
        ax.plot(pos_t[0, 0], pos_t[0, 1], "C0o", label="true position at t = Δt")
        ax.set_title(f"{name}: initial fix from the known anchors (3σ)")
    ax.set_aspect("equal")
    ax.set_xlabel(f"x [m] ({frame})")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=7)
    paths.append(save(fig, directory, f"{name}_startup"))

    # --- errors with ±3σ
    x_t = np.concatenate([pos_t, tr[:, 2:4] @ M.T, tr[:, 4:10]], axis=1)
    err = np.asarray(st.mean) - x_t
    err[:, 4:7] = (err[:, 4:7] + np.pi) % (2 * np.pi) - np.pi
    sig = np.sqrt(np.clip(np.diagonal(np.asarray(st.cov), axis1=1, axis2=2), 0, None))
    labels = ["x [m]", "y [m]", "v_x [m/s]", "v_y [m/s]", "roll [deg]", "pitch [deg]", "yaw [deg]"]
    nrow = 4 if cfg.mode == "slam" else 3
    fig, axs = p.subplots(nrow, 3, figsize=(12, 2.4 * nrow), sharex=True)
    axs = axs.ravel()
    for i, lab in enumerate(labels):
        scale = 180 / np.pi if i >= 4 else 1.0
        axs[i].plot(t, err[:, i] * scale, "C1-", lw=1)
        axs[i].fill_between(t, -3 * sig[:, i] * scale, 3 * sig[:, i] * scale, color="C0", alpha=0.2,
                            label="±3σ")
        axs[i].set_ylabel(lab)
    axs[7].plot(t, np.asarray(ev["series"]["pos_err_m"]), "k-", lw=1)
    axs[7].set_ylabel("‖position error‖ [m]")
    axs[8].plot(t, np.asarray(st.nis), "C2-", lw=0.8)
    axs[8].set_ylabel("NIS (this run)")
    if cfg.mode == "slam":
        Ls = np.asarray(st.landmarks)
        acts = np.asarray(st.active)
        for i in range(anc_t.shape[0]):
            e = np.linalg.norm(Ls[:, i] - anc_t[i], axis=1)
            axs[9].plot(t, np.where(acts[:, i], e, np.nan), lw=1, label=f"anchor {i}")
            sdev = np.sqrt(np.clip(np.trace(np.asarray(st.lm_cov)[:, i], axis1=1, axis2=2), 0, None))
            axs[10].plot(t, np.where(acts[:, i], sdev, np.nan), lw=1, label=f"anchor {i}")
        axs[9].set_ylabel("anchor error [m]")
        axs[10].set_ylabel("anchor √tr P [m]")
        axs[9].legend(fontsize=6)
        axs[11].axis("off")
    for a in axs[-3:]:
        a.set_xlabel("t [s]")
    axs[0].legend(fontsize=7)
    fig.suptitle(f"{name}: errors with ±3σ ({frame})")
    fig.tight_layout()
    paths.append(save(fig, directory, f"{name}_errors"))

    # --- Monte Carlo NEES
    fig, axs = p.subplots(1, 2, figsize=(11, 3.5), sharex=True)
    for ax, key in zip(axs, ("robot", "pos")):
        c = cons[key]
        ax.plot(t, per_step[key], "C0-", lw=1, label=f"ANEES over {runs} runs (mean {c['anees']:.2f})")
        ax.axhline(c["bounds"][0], color="k", ls="--", lw=0.8, label="95 % bounds")
        ax.axhline(c["bounds"][1], color="k", ls="--", lw=0.8)
        ax.axhline(c["dof"], color="g", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("t [s]")
        ax.set_title(f"NEES {key} ({c['dof']} states)")
        ax.legend(fontsize=7)
    paths.append(save(fig, directory, f"{name}_nees"))
    return paths
