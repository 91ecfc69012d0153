"""Plots of paper 003's range-only UWB runs (one flight, plus the Monte Carlo NEES).

* ``*_path``: true and estimated path, true anchors, estimated anchors with
  their final 3σ covariance ellipses (in the comparison frame);
* ``*_startup``: the forced straight-line run — true positions and the
  positions the start-up assumes, (−d(k), 0) — and the anchors as the start-up
  initialised them, with 3σ ellipses (localisation: the initial LS fix);
* ``*_errors``: x, y, velocity and heading errors with ±3σ bands (roll and
  pitch only when the flight has them; a band is omitted, with a note, where it
  is not finite or wider than ±180° on an angle: see :func:`state_panels`,
  :func:`band`), the position error norm, the NIS, and each anchor's error over
  time (SLAM);
* ``*_nees``: per-step ANEES over the runs of the position (the headline
  ``consistency.anees``) and of the 10-state robot block (``anees_robot``), named,
  with their 95 % bounds and the verdict of their time averages.

NumPy inputs; matplotlib is imported lazily (Agg).
"""

from __future__ import annotations

import textwrap

import numpy as np

from ..errors import InputError
from ..linalg import check_int, check_numbers, check_scalar, check_shape
from ..metrics import consistency_verdict as verdict
from ..metrics import steps_inside_text as steps_inside
from .flight import _output_dir, closing_on_error, keep_margins, plt, save

__all__ = ["STATE_NAMES", "band", "ellipse_points", "nees_figure", "plot_all", "state_panels"]


def _check_gaussian2(mean, cov):
    """InputError unless ``mean`` is (2,) and ``cov`` (2, 2) with a symmetric part that is PSD to
    1e-3 of its largest eigenvalue (a filter's rounding, float32 included, passes with a wide
    margin, so the plots of a finished run are never lost to it; a negative variance, which
    would draw a zero-size ellipse, does not; the rest is clipped to 0).  A non-finite ``cov`` (a diverged run) is
    left to the plot, as before."""
    check_shape(check_numbers(mean, "mean"), (2,), "mean")
    c = check_shape(check_numbers(cov, "cov"), (2, 2), "cov")
    if np.all(np.isfinite(c)):
        w = np.linalg.eigvalsh(0.5 * (c + c.T))
        if w[0] < -1e-3 * max(float(np.max(np.abs(w))), 1e-300):
            raise InputError(f"cov: not positive semi-definite (smallest eigenvalue {w[0]:.3g})")


def ellipse_points(mean, cov, k=3.0, n=64):
    """(n, 2) points of the k-σ ellipse of a 2D Gaussian (mean (2,), cov (2, 2))."""
    _check_gaussian2(mean, cov)
    k = check_scalar(k, "k", lower=0)
    n = check_int(n, "n", lower=2)
    w, V = np.linalg.eigh(0.5 * (np.asarray(cov) + np.asarray(cov).T))
    w = np.sqrt(np.clip(w, 0.0, None))
    a = np.linspace(0, 2 * np.pi, n)
    circ = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.asarray(mean)[None, :] + k * (circ * w[None, :]) @ V.T


STATE_NAMES = ("x", "y", "v_x", "v_y", "roll", "pitch", "yaw", "w_roll", "w_pitch", "w_yaw")
# The NEES figure's panels: block name and where its time average sits in the run JSON.
NEES_BLOCKS = {"pos": ("position (x, y)", "headline: consistency.anees"),
               "robot": ("robot block (x, y, v_x, v_y, roll, pitch, yaw, 3 body rates)",
                         "consistency.anees_robot")}  # the names of sim.scenarios.uwb's JSON
ANGLE_BAND_LIMIT_DEG = 180.0


def state_panels(att_true, tol=1e-9):
    """State panels of the ``*_errors`` figure and notes on what is left out (pure).

    Args:
      att_true: (T, 3) true roll, pitch, yaw [rad] in the filter's reference.

    Returns:
      ``([(ylabel, state indices, unit scale, band limit or None), ...], [note, ...])``:
      x, y, v_x, v_y [m, m/s] and the heading (yaw) [deg] always; roll and pitch (one panel)
      only when the flight has roll or pitch motion: in a planar flight they are the
      integrated noise of two zero gyro rates, and the run's ``att_rmse_deg`` reports them.
      Angles carry a band limit of ±180° (a wider 3σ constrains nothing).
    """
    deg = 180.0 / np.pi
    lim = ANGLE_BAND_LIMIT_DEG
    panels = [("x error [m]", (0,), 1.0, None), ("y error [m]", (1,), 1.0, None),
              ("v_x error [m/s]", (2,), 1.0, None), ("v_y error [m/s]", (3,), 1.0, None),
              ("heading (yaw) error [deg]", (6,), deg, lim)]
    notes = []
    a = np.asarray(att_true, float)
    if a.size and np.nanmax(np.abs(a[:, :2])) > tol:
        panels.append(("roll, pitch error [deg]", (4, 5), deg, lim))
    else:
        notes.append("roll and pitch not drawn: this flight has no roll or pitch motion "
                     "(their errors are in att_rmse_deg)")
    return panels, notes


def band(sig3, t, limit=None, name="state"):
    """The ±3σ half-width to draw and a note when part of it is omitted (pure).

    Entries that are not finite, or (``limit`` given) wider than ``limit``, become NaN: a band
    wider than ±180° on an angle says the filter does not constrain it, and drawing it
    (±900° on the paper's Q) only flattens the error line.  Returns ``(band, note or None)``.
    """
    b = np.asarray(sig3, float).copy()
    t = np.asarray(t, float)
    bad_nf = ~np.isfinite(b)
    bad_wide = np.zeros_like(bad_nf) if limit is None else (np.isfinite(b) & (b > limit))
    b[bad_nf | bad_wide] = np.nan
    notes = []
    if bad_wide.any():
        t0 = t[np.argmax(bad_wide)]
        notes.append(f"{name}: 3σ exceeds ±{limit:g}° at {100 * bad_wide.mean():.0f} % of the steps "
                     f"(first at t = {t0:g} s): the filter does not constrain it there, band omitted")
    if bad_nf.any():
        notes.append(f"{name}: 3σ undefined (non-finite covariance) at {int(bad_nf.sum())} step(s), "
                     "band omitted there")
    return b, ("; ".join(notes) or None)


def _frame(sim, res, cfg):
    from ..systems.uwb_slam_2d import startup_frame

    if cfg.mode == "slam":
        M, o = startup_frame(sim.anchors, res.startup.ref_anchor, cfg.start_anchor, cfg.end_anchor)
        return np.asarray(M), np.asarray(o)
    return np.eye(2), np.zeros(2)


def plot_all(name, sim, res, ev, setup, cfg, per_step, cons, runs, directory):
    """Write the four figures; returns their paths (``directory`` is made and checked writable
    first; a figure that fails is closed, not left open in pyplot)."""
    _output_dir(directory, probe=True)
    with closing_on_error():
        return _plot_all(name, sim, res, ev, setup, cfg, per_step, cons, runs, directory)


def _plot_all(name, sim, res, ev, setup, cfg, per_step, cons, runs, directory):
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
    sm = None if res.smoothed is None else np.asarray(res.smoothed)
    if sm is not None:
        ax.plot(sm[:, 0], sm[:, 1], "C4-", lw=1.0, label="smoothed (RTS)")
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

    # --- errors with ±3σ: the states this flight exercises, bands only where they mean something
    x_t = np.concatenate([pos_t, tr[:, 2:4] @ M.T, tr[:, 4:10]], axis=1)
    err = np.asarray(st.mean) - x_t
    err[:, 4:7] = (err[:, 4:7] + np.pi) % (2 * np.pi) - np.pi
    sig = np.sqrt(np.clip(np.diagonal(np.asarray(st.cov), axis1=1, axis2=2), 0, None))
    panels, notes = state_panels(x_t[:, 4:7])
    n_extra = 3 if cfg.mode == "slam" else 2
    ncol = 3
    nrow = -(-(len(panels) + n_extra) // ncol)
    fig, axs = p.subplots(nrow, ncol, figsize=(12, 2.4 * nrow + 0.4), sharex=True)
    axs = axs.ravel()
    for a, (lab, idx, scale, limit) in zip(axs, panels):
        omitted = False
        why = set()  # why parts of the band were left out: "wide" (> limit), "undefined" (not finite)
        for j, i in enumerate(idx):
            a.plot(t, err[:, i] * scale, f"C{1 + j}-", lw=1, label=STATE_NAMES[i] if len(idx) > 1 else "error")
            raw = 3 * sig[:, i] * scale
            b, note = band(raw, t, limit, STATE_NAMES[i])
            if np.any(np.isfinite(b)):
                a.fill_between(t, -b, b, color=f"C{0 if j == 0 else 4}", alpha=0.2 if j == 0 else 0.12,
                               label="±3σ" if len(idx) == 1 else f"±3σ {STATE_NAMES[i]}")
            if note:
                notes.append(note)
                omitted = True
                if limit is not None and np.any(np.isfinite(raw) & (raw > limit)):
                    why.add("wide")
                if not np.all(np.isfinite(raw)):
                    why.add("undefined")
        if omitted:  # the y-range fits the errors, not what is left of the band
            e = np.abs(err[:, list(idx)] * scale)
            top = 1.3 * float(np.nanmax(e)) if np.any(np.isfinite(e)) else 1.0
            a.set_ylim(-max(top, 1e-3), max(top, 1e-3))
            # (a position or velocity panel has no limit: only an undefined band is left out there)
            where = " or ".join(([f"wider than ±{limit:g}°"] if "wide" in why else [])
                                + (["undefined"] if "undefined" in why else []))
            a.text(0.01, 0.97, f"3σ band omitted where {where} (see note)",
                   transform=a.transAxes, fontsize=6.5, va="top", color="0.3")
        a.set_ylabel(lab)
        a.legend(fontsize=6, loc="lower right", ncol=len(idx))
    k = len(panels)
    axs[k].plot(t, np.asarray(ev["series"]["pos_err_m"]), "k-", lw=1, label="‖error‖")
    if sm is not None:
        axs[k].plot(t, np.linalg.norm(sm[:, :2] - pos_t, axis=1), "C4-", lw=1, label="‖error‖ smoothed")
    axs[k].plot(t, 3 * np.sqrt(sig[:, 0] ** 2 + sig[:, 1] ** 2), "C0--", lw=0.8, label="3√(σx² + σy²)")
    axs[k].set_ylabel("‖position error‖ [m]")
    axs[k].legend(fontsize=6)
    axs[k + 1].plot(t, np.asarray(st.nis), "C2-", lw=0.8, label="NIS")
    axs[k + 1].plot(t, np.asarray(st.dof), "k:", lw=0.8, label="expected (dof)")
    axs[k + 1].set_ylabel("NIS (this run)")
    axs[k + 1].legend(fontsize=6)
    if cfg.mode == "slam":
        Ls = np.asarray(st.landmarks)
        acts = np.asarray(st.active)
        lmc = np.asarray(st.lm_cov)
        for i in range(anc_t.shape[0]):
            e = np.linalg.norm(Ls[:, i] - anc_t[i], axis=1)
            axs[k + 2].plot(t, np.where(acts[:, i], e, np.nan), f"C{i}-", lw=1, label=f"anchor {i}")
            sdev = np.sqrt(np.clip(np.trace(lmc[:, i], axis1=1, axis2=2), 0, None))
            axs[k + 2].plot(t, np.where(acts[:, i], sdev, np.nan), f"C{i}--", lw=0.8)
        axs[k + 2].plot([], [], "k--", lw=0.8, label="√tr P (dashed)")
        axs[k + 2].set_ylabel("anchor error ‖l̂ − l‖ [m]")
        axs[k + 2].legend(fontsize=6, ncol=2)
    n_used = len(panels) + n_extra
    for a in axs[n_used:]:
        a.axis("off")
    for a in axs[max(0, n_used - ncol):n_used]:  # the lowest panel of each column
        a.set_xlabel("t [s]")
        a.xaxis.set_tick_params(labelbottom=True)
    fig.suptitle(f"{name}: estimation errors of run 0 with ±3σ ({frame})")
    if notes:
        fig.text(0.01, 0.005, "\n".join(notes), fontsize=7, va="bottom", color="0.25")
    h = 2.4 * nrow + 0.4
    keep_margins(fig, left=0.07, right=0.98, top=1 - 0.55 / h, bottom=(0.45 + 0.13 * len(notes)) / h,
                 hspace=0.15, wspace=0.25)
    paths.append(save(fig, directory, f"{name}_errors"))

    # --- Monte Carlo NEES: both blocks, named; the position block is the headline
    paths.append(save(nees_figure(name, t, per_step, cons, runs), directory, f"{name}_nees"))
    return paths


def nees_figure(name, t, per_step, cons, runs):
    """The Monte Carlo NEES figure, both state blocks (position, the headline, and the robot
    block): the per-step ANEES against its bounds; each title gives the time average's verdict
    and the share of steps inside.  ``per_step``/``cons``: the scenario's ``consistency``
    outputs.  Returns the (unsaved) figure."""
    p = plt()
    fig, axs = p.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    for ax, key in zip(axs, ("pos", "robot")):
        c = cons[key]
        block = NEES_BLOCKS[key]
        ax.plot(t, per_step[key], "C0-", lw=1, label=f"ANEES per step over {runs} run(s)")
        ax.axhline(c["bounds"][0], color="k", ls="--", lw=0.8, label="95 % χ² bounds (per step)")
        ax.axhline(c["bounds"][1], color="k", ls="--", lw=0.8)
        ax.axhline(c["dof"], color="g", ls=":", lw=0.8, label=f"expected ({c['dof']})")
        ax.set_yscale("log")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(f"NEES, {c['dof']} states")
        text = (f"time average {c['anees']:.2f} ({block[1]}): "
                f"{verdict(c['anees'], c['bounds'])}; per step: {steps_inside(c['fraction_steps_in_bounds'])}")
        ax.set_title(f"{block[0]}, {c['dof']} states\n" + "\n".join(textwrap.wrap(text, 70)), fontsize=8.5)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"{name}: Monte Carlo NEES by state block")
    keep_margins(fig, left=0.08, right=0.98, bottom=0.12, top=0.74, wspace=0.22)
    return fig
