"""Plots of paper 001's FastSLAM runs (``fastslam-helix``), after the paper's Figs. 7-13.

* ``*_cloud``: particle cloud (x-y, coloured by weight) and the weighted map with 3σ ellipses at
  four times (first frame, one third, two thirds, last frame), true path and landmarks — Fig. 7;
* ``*_path``: true vs estimated position (x, y, z over time and the 3D path) — Figs. 10, 12;
* ``*_bias``: accelerometer and gyroscope offset estimates (b̂0 + b̂1) vs truth with ±3σ — Fig. 9;
* ``*_neff``: effective sample size after every IMU and LiDAR weight update.

All functions take NumPy arrays (a :class:`~jaxslam.sim.scenarios.fastslam.Flight001` and a
:class:`~jaxslam.systems.fastslam_001.Result` converted with ``np.asarray``), return Figures,
and :func:`plot_all` writes PNGs.  Paper 001's world frame is z-up, so z is plotted as is.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, check_int
from .flight import _output_dir, plt, save

__all__ = ["particle_clouds", "path", "bias", "neff", "plot_all"]


def _frame_times(n_frames, k=4):
    return sorted(set(int(round(v)) for v in np.linspace(0, n_frames - 1, k)))


def particle_clouds(fl, res, landmarks, frames=None, title="particle cloud and map"):
    """Particle positions and map at chosen LiDAR frames (x-y plane).

    ``res.frames.particles`` (F, N, 3) must have been saved (``save_particles=True``; else an
    :class:`~jaxslam.errors.InputError`, a ValueError).  ``frames``: frame indices, ints in
    [0, F) (default: four spread over the flight); a negative or too large index is an
    InputError naming ``frames`` (−1 drew the last frame's cloud beside the truth at t = 0).
    Panel titles give the frame's time ``fl.t`` (it assumed 0.01 s steps).
    """
    fr = res.frames
    if fr.particles is None:
        raise InputError("particle positions were not saved (Config.save_particles=False)")
    F = fr.particles.shape[0]
    if frames is None:
        frames = _frame_times(F)
    else:
        try:
            frames = list(frames)
        except TypeError:
            raise InputError(f"frames: expected a list of frame indices, got {frames!r}"[:300]) from None
        frames = [check_int(f, "frames", lower=0, what="frame indices, ints") for f in frames]
        if not frames or max(frames) >= F:
            raise InputError(f"frames: expected indices in [0, {F}) (F = {F} frames saved), got {frames}"[:300])
    p = plt()
    every = (fl.truth.shape[0] - 1) // F
    fig, axs = p.subplots(2, len(frames), figsize=(4.2 * len(frames), 8.4), squeeze=False)
    for j, f in enumerate(frames):
        ax, zx = axs[0, j], axs[1, j]
        k = (f + 1) * every
        w = np.exp(fr.log_w[f])
        # Bottom row: the cloud itself (it is cm-sized beside the 4 m landmark square).
        zx.scatter(fr.particles[f, :, 0], fr.particles[f, :, 1], c=w, s=8, cmap="viridis")
        zx.plot(*fl.truth[k, 0:2], "k+", ms=12, mew=2, label="true position")
        zx.plot(*(w @ fr.particles[f, :, 0:2]), "rx", ms=10, mew=2, label="weighted mean")
        zx.set_xlabel("x [m]")
        zx.set_ylabel("y [m]")
        zx.set_aspect("equal", adjustable="datalim")
        zx.set_title("particle cloud (zoom)", fontsize=9)
        if j == 0:
            zx.legend(fontsize=7)
        ax.plot(fl.truth[:k + 1, 0], fl.truth[:k + 1, 1], "C0-", lw=1, label="true path")
        sc = ax.scatter(fr.particles[f, :, 0], fr.particles[f, :, 1], c=w, s=6, cmap="viridis",
                        label="particles")
        ax.plot(*fl.truth[k, 0:2], "k+", ms=10, label="true position")
        ax.scatter(landmarks[:, 0], landmarks[:, 1], c="g", marker="^", s=40,
                   label="landmarks (true)")
        mu, var = fr.map_mean[f], fr.map_var[f]
        ax.scatter(mu[:, 0], mu[:, 1], c="r", marker="x", s=30, label="map (weighted)")
        tt = np.linspace(0, 2 * np.pi, 40)
        for m, v in zip(mu, var):
            s = 3 * np.sqrt(np.maximum(v[:2], 0))
            ax.plot(m[0] + s[0] * np.cos(tt), m[1] + s[1] * np.sin(tt), "r-", lw=0.6)
        ax.set_title(f"t = {float(fl.t[k]):.1f} s" if every else f"frame {f}")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal", adjustable="datalim")
    fig.colorbar(sc, ax=axs[:, -1].tolist(), label="weight")
    axs[0, 0].legend(loc="lower left", fontsize=6)
    fig.suptitle(title)
    return fig


def path(fl, res, title="true vs estimated path"):
    """Position components over time and the 3D path (true, estimated)."""
    p = plt()
    t = fl.t[1:]
    est = res.steps.pose_mean
    sd = np.sqrt(np.maximum(res.steps.pose_var[:, 0:3], 0))
    fig = p.figure(figsize=(12, 7))
    for i, lab in enumerate("xyz"):
        ax = fig.add_subplot(3, 2, 2 * i + 1)
        ax.plot(fl.t, fl.truth[:, i], "C0-", lw=1.2, label="true")
        ax.plot(t, est[:, i], "C1--", lw=1, label="estimated")
        ax.fill_between(t, est[:, i] - 3 * sd[:, i], est[:, i] + 3 * sd[:, i], color="C1",
                        alpha=0.2, lw=0, label="±3σ (particles)")
        ax.set_ylabel(f"{lab} [m]")
        if i == 0:
            ax.legend(fontsize=7)
    ax.set_xlabel("t [s]")
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    ax3.plot(fl.truth[:, 0], fl.truth[:, 1], fl.truth[:, 2], "C0-", lw=1.2, label="true")
    ax3.plot(est[:, 0], est[:, 1], est[:, 2], "C1--", lw=1, label="estimated")
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m] (up)")
    ax3.legend(fontsize=7)
    fig.suptitle(title)
    return fig


def bias(fl, res, title="IMU offset estimates (b0 + b1) vs truth, ±3σ"):
    """Accelerometer and gyroscope total offsets, estimate ±3σ and truth, per axis."""
    p = plt()
    t = fl.t[1:]
    bm = res.steps.bias_mean
    tot = bm[:, 0:6] + bm[:, 6:12]
    sd = np.sqrt(np.maximum(res.steps.offset_var, 0))
    true = fl.offset[:, 0:6] + fl.offset[:, 6:12]
    fig, axs = p.subplots(2, 3, figsize=(13, 6), sharex=True)
    names = ["accel x [m/s²]", "accel y [m/s²]", "accel z [m/s²]",
             "gyro x [rad/s]", "gyro y [rad/s]", "gyro z [rad/s]"]
    for i, ax in enumerate(axs.ravel()):
        ax.plot(t, true[:, i], "k-", lw=1.2, label="true")
        ax.plot(t, tot[:, i], "C1-", lw=1, label="estimate")
        ax.fill_between(t, tot[:, i] - 3 * sd[:, i], tot[:, i] + 3 * sd[:, i], color="C1",
                        alpha=0.2, lw=0, label="±3σ")
        ax.set_title(names[i], fontsize=9)
        # finite samples only: one NaN made the limits NaN (matplotlib's bare ValueError)
        scale = max(5 * float(np.max(np.abs(true[:, i]), initial=0.0, where=np.isfinite(true[:, i]))), 1e-4)
        ax.set_ylim(-scale, scale)
    axs[0, 0].legend(fontsize=7)
    for ax in axs[1]:
        ax.set_xlabel("t [s]")
    fig.suptitle(title)
    return fig


def neff(fl, res, n_particles, title="effective sample size"):
    """N_eff after each IMU weight (steps) and each LiDAR weight (frames)."""
    p = plt()
    t = fl.t[1:]
    F = res.frames.neff.shape[0]
    every = t.shape[0] // F
    tf = t[every - 1::every]
    fig, ax = p.subplots(figsize=(9, 3.5))
    ax.plot(t, res.steps.neff, "C0-", lw=0.6, label="after IMU weight")
    ax.plot(tf, res.frames.neff, "C3.", ms=3, label="after LiDAR weight")
    ax.axhline(n_particles, color="k", lw=0.5)
    ax.set_yscale("log")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("N_eff")
    ax.legend(fontsize=7)
    ax.set_title(title)
    return fig


def plot_all(name, fl, res, landmarks, directory):
    """Write the four figures for one flight (NumPy pytrees); returns the PNG paths
    (``directory`` is made and checked writable first)."""
    _output_dir(directory, probe=True)
    N = res.final.particles.pose.shape[0]
    paths = []
    if res.frames.particles is not None:
        paths.append(save(particle_clouds(fl, res, landmarks, title=f"{name}: particles and map"),
                          directory, f"{name}_cloud"))
    paths.append(save(path(fl, res, title=f"{name}: true vs estimated path"), directory,
                      f"{name}_path"))
    paths.append(save(bias(fl, res, title=f"{name}: IMU offsets (b0 + b1) vs truth, ±3σ"),
                      directory, f"{name}_bias"))
    paths.append(save(neff(fl, res, N, title=f"{name}: effective sample size"), directory,
                      f"{name}_neff"))
    return paths
