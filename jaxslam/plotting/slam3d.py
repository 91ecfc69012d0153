"""Plots of paper 000's EKF-SLAM runs, after the paper's Figs. 7-11, plus NEES.

* ``*_trajectory3d``: true / estimated / desired path, true and estimated
  landmarks with their final 3σ ellipsoids (axis-aligned, from the marginal
  variances) — Fig. 7;
* ``*_errors``: position, velocity and attitude errors with ±3σ bands — Figs. 8-10;
* ``*_landmarks``: landmark errors per axis over time with ±3σ — Fig. 11;
* ``*_nees``: the Monte Carlo average NEES per step with its 95 % bounds and
  the 10 s window averages.
"""

from __future__ import annotations

import numpy as np

from .flight import _ned_to_enu_up, plt, save

__all__ = ["plot_all"]


def _ellipsoid(ax, c, sig3, color):
    u, v = np.mgrid[0:2 * np.pi:12j, 0:np.pi:7j]
    x = c[0] + sig3[0] * np.cos(u) * np.sin(v)
    y = c[1] + sig3[1] * np.sin(u) * np.sin(v)
    z = c[2] + sig3[2] * np.cos(v)
    ax.plot_wireframe(x, y, -z, color=color, lw=0.4, alpha=0.6)


def plot_all(name, fl, lms, t, t_frames, anees_per_frame, cons, runs, directory, cfg):
    """Write the four figures for one flight ``fl`` (NumPy) and the MC NEES; returns paths."""
    p = plt()
    paths = []
    st = fl.est_steps
    truth = fl.truth[1:]
    fr = fl.est_frames
    active = fl.est_final.slam.active
    L_hat = fr.landmarks[-1][active] if fr.landmarks is not None else np.zeros((0, 3))
    L_var = fr.lm_var[-1][active] if fr.lm_var is not None else np.zeros((0, 3))

    fig = p.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*_ned_to_enu_up(fl.ref[:, :3]), "k-.", lw=1, label="desired")
    ax.plot(*_ned_to_enu_up(fl.truth[:, :3]), "C0-", lw=1.4, label="true")
    ax.plot(*_ned_to_enu_up(st.mean[:, :3]), "C1--", lw=1.2, label="estimated")
    ax.scatter(*_ned_to_enu_up(lms), c="g", marker="^", s=22, label="landmarks (true)")
    if len(L_hat):
        ax.scatter(*_ned_to_enu_up(L_hat), c="r", marker="x", s=22, label="landmarks (estimated)")
        for c, v in zip(L_hat, L_var):
            _ellipsoid(ax, c, 3 * np.sqrt(np.maximum(v, 0)), "r")
    ax.set_xlabel("north [m]")
    ax.set_ylabel("east [m]")
    ax.set_zlabel("altitude [m]")
    ax.set_title(f"{name}: trajectory and map (3σ ellipsoids)")
    ax.legend(loc="upper left", fontsize=7)
    paths.append(save(fig, directory, f"{name}_trajectory3d"))

    err = st.mean - truth[:, :9]
    err[:, 6:9] = (err[:, 6:9] + np.pi) % (2 * np.pi) - np.pi
    sig = np.sqrt(np.maximum(st.var, 0))
    fig, axs = p.subplots(3, 3, figsize=(12, 8), sharex=True)
    labels = [["x", "y", "z"], ["u", "v", "w"], ["φ", "θ", "ψ"]]
    units = ["m", "m/s", "deg"]
    for r in range(3):
        scale = np.degrees(1.0) if r == 2 else 1.0
        for c in range(3):
            i = 3 * r + c
            a = axs[r, c]
            a.plot(t, err[:, i] * scale, "C0-", lw=0.8, label="error")
            a.plot(t, 3 * sig[:, i] * scale, "C3-.", lw=0.8, label="±3σ")
            a.plot(t, -3 * sig[:, i] * scale, "C3-.", lw=0.8)
            a.set_title(f"{labels[r][c]} [{units[r]}]", fontsize=9)
            a.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=7)
    for a in axs[-1]:
        a.set_xlabel("time [s]")
    fig.suptitle(f"{name}: estimation errors with ±3σ (position, body velocity, attitude)")
    paths.append(save(fig, directory, f"{name}_errors"))

    if fr.landmarks is not None:
        ids = fl.est_final.slam.ids
        tf = (np.arange(fr.landmarks.shape[0]) + 1) * (t[-1] / fr.landmarks.shape[0])
        fig, axs = p.subplots(3, 1, figsize=(10, 8), sharex=True)
        for j in np.flatnonzero(active):
            true_l = lms[ids[j]] if cfg.association == "known" else lms[
                np.argmin(np.linalg.norm(lms - fr.landmarks[-1][j], axis=1))]
            e = fr.landmarks[:, j, :] - true_l
            s = 3 * np.sqrt(np.maximum(fr.lm_var[:, j, :], 0))
            live = fr.lm_var[:, j, 0] > 0
            for k in range(3):
                axs[k].plot(tf[live], e[live, k], lw=0.7)
                axs[k].plot(tf[live], s[live, k], "k-.", lw=0.4, alpha=0.5)
                axs[k].plot(tf[live], -s[live, k], "k-.", lw=0.4, alpha=0.5)
        for k, n in enumerate(["north", "east", "down"]):
            axs[k].set_ylabel(f"{n} error [m]")
            axs[k].grid(alpha=0.3)
        axs[-1].set_xlabel("time [s]")
        fig.suptitle(f"{name}: landmark errors over time with ±3σ (each line one landmark)")
        paths.append(save(fig, directory, f"{name}_landmarks"))

    lo, hi = cons["anees_bounds"]
    fig, ax = p.subplots(figsize=(10, 4))
    ax.semilogy(t_frames, np.maximum(fr.nees, 1e-6), color="0.7", lw=0.5, label="NEES, one run")
    ax.semilogy(t_frames, anees_per_frame, "C0-", lw=1.0, label=f"ANEES over {runs} runs")
    ax.axhline(lo, color="C3", ls="--", lw=1, label="95 % bounds")
    ax.axhline(hi, color="C3", ls="--", lw=1)
    for w in cons.get("anees_windows", []):
        ax.hlines(w["anees"], w["t0_s"], w["t1_s"], colors="k", lw=2)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("NEES (robot block, 9 dof)")
    ax.set_title(f"{name}: consistency (black bars: 10 s window averages)")
    ax.legend(fontsize=7)
    paths.append(save(fig, directory, f"{name}_nees"))
    return paths
