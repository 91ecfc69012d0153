"""Plots of paper 000's EKF-SLAM runs, after the paper's Figs. 7-11, plus NEES.

* ``*_trajectory3d``: left, the true / estimated / desired path and the true and
  estimated landmarks in 3D (Fig. 7; at the map's scale a 3σ of centimetres is
  invisible, so no ellipsoids are drawn there); right, the plan view (north-east)
  with the horizontal 3σ ellipses (axis-aligned, marginal variances) of the
  mapped landmarks at the end and of the robot every 5 s, drawn about the truth
  together with the estimate's offset, both magnified by the factor the panel
  states (:func:`magnification`): truth inside its ellipse ⇔ error inside 3σ;
* ``*_errors``: position, velocity and attitude errors with ±3σ bands — Figs. 8-10;
* ``*_landmarks`` (unknown map only; a known map has no landmark estimates):
  the final error of each mapped landmark, sorted, labelled by its id, against
  its 3√tr P; and per axis over time the median error over the mapped
  landmarks, the 5-95 % band and the median ±3σ (:func:`landmark_errors`) — Fig. 11
  as a summary instead of one unlabelled line per landmark;
* ``*_nees``: the Monte Carlo average NEES of the 9-state robot block per
  frame with its 95 % bounds, the 10 s window averages and the verdict of the
  flight average.
"""

from __future__ import annotations

import textwrap

import numpy as np

from ..errors import InputError
from ..linalg import check_numbers, check_scalar
from ..metrics import consistency_verdict as verdict
from ..metrics import steps_inside_text as steps_inside
from .flight import _ned_to_enu_up, _output_dir, keep_margins, plt, save

__all__ = ["landmark_errors", "magnification", "nees_figure", "plot_all"]

ROBOT_ELLIPSE_EVERY_S = 5.0


def magnification(sig3, span, fraction=0.025):
    """Factor (1, 2, 5, 10, 20, ...) that draws the median 3σ at about ``fraction`` of
    ``span``; 1 when it is visible already, no 3σ is positive or ``span`` is not a positive
    finite number (pure).  ``sig3`` and ``span`` (a scalar) that are not numbers are an
    :class:`~jaxslam.errors.InputError` naming them (they were NumPy's bare errors)."""
    fraction = check_scalar(fraction, "fraction", lower=0, strict=True)
    s = check_numbers(sig3, "sig3")
    span = check_numbers(span, "span")
    if span.ndim != 0:
        raise InputError(f"span: expected a scalar, got shape {span.shape}")
    span = float(span)
    s = s[np.isfinite(s) & (s > 0)]
    if s.size == 0 or not np.isfinite(span) or span <= 0:
        return 1
    want = fraction * span / float(np.median(s))
    if want <= 1:
        return 1
    e = 10 ** np.floor(np.log10(want))
    return int(max(m * e for m in (1, 2, 5) if m * e <= want))


def _ellipses_xy(centres, half_axes, n=25):
    """One NaN-separated polyline of axis-aligned ellipses (plan view: east right, north up)."""
    a = np.linspace(0, 2 * np.pi, n)
    xs, ys = [], []
    for c, h in zip(centres, half_axes):
        xs += list(c[1] + h[1] * np.cos(a)) + [np.nan]
        ys += list(c[0] + h[0] * np.sin(a)) + [np.nan]
    return np.asarray(xs), np.asarray(ys)


def _nanquantiles(x, qs):
    """Quantiles over axis 1 ignoring NaN (linear interpolation, as ``np.nanquantile``; NaN where
    a row has no finite value); ``np.nanpercentile`` took 0.17 s on a 50 s flight."""
    s = np.sort(x, axis=1)  # NaN last
    n = np.sum(np.isfinite(x), axis=1, keepdims=True)
    out = []
    for q in qs:
        pos = q * np.maximum(n - 1, 0)
        i0 = np.floor(pos).astype(int)
        i1 = np.minimum(i0 + 1, np.maximum(n - 1, 0))
        v0 = np.take_along_axis(s, i0, axis=1)
        v1 = np.take_along_axis(s, i1, axis=1)
        v = v0 + (pos - i0) * np.where(i1 > i0, v1 - v0, 0.0)
        out.append(np.where(n > 0, v, np.nan)[:, 0])
    return out


def landmark_errors(fl, lms, cfg):
    """What the ``*_landmarks`` figure shows, from one flight (pure NumPy).

    Returns a dict: ``ids`` (true landmark id of each mapped slot; with hidden ids the
    nearest true landmark at the end), ``final_err`` (‖l̂ − l‖ at the end) and ``final_3sig``
    (3√tr P) per mapped slot, sorted by decreasing final error; ``err`` (frames, slots, 3)
    signed error and ``sig3`` its per-axis 3σ, in the same order, NaN while a slot is unmapped.
    """
    fr = fl.est_frames
    active = np.asarray(fl.est_final.slam.active)
    slots = np.flatnonzero(active)
    L = np.asarray(fr.landmarks)[:, slots]  # (F, n, 3)
    V = np.maximum(np.asarray(fr.lm_var)[:, slots], 0)
    if cfg.association == "known":
        ids = np.asarray(fl.est_final.slam.ids)[slots]
    else:
        ids = np.argmin(np.linalg.norm(L[-1][:, None, :] - lms[None], axis=-1), axis=1)
    err = L - lms[ids][None]
    live = V[..., 0] > 0
    err = np.where(live[..., None], err, np.nan)
    sig3 = np.where(live[..., None], 3 * np.sqrt(V), np.nan)
    fe = np.linalg.norm(err[-1], axis=1)
    f3 = 3 * np.sqrt(V[-1].sum(axis=1))
    order = np.argsort(-np.nan_to_num(fe, nan=np.inf))
    return {"ids": ids[order], "final_err": fe[order], "final_3sig": f3[order], "err": err[:, order],
            "sig3": sig3[:, order]}


def plot_all(name, fl, lms, t, t_frames, anees_per_frame, cons, runs, directory, cfg):
    """Write the figures for one flight ``fl`` (NumPy) and the MC NEES; returns paths
    (``directory`` is made and checked writable first)."""
    _output_dir(directory, probe=True)
    p = plt()
    paths = []
    st = fl.est_steps
    truth = fl.truth[1:]
    fr = fl.est_frames
    active = fl.est_final.slam.active
    unknown = cfg.mode == "unknown" and fr.landmarks is not None
    L_hat = fr.landmarks[-1][active] if fr.landmarks is not None else np.zeros((0, 3))

    fig = p.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.plot(*_ned_to_enu_up(fl.ref[:, :3]), "k-.", lw=1, label="desired")
    ax.plot(*_ned_to_enu_up(fl.truth[:, :3]), "C0-", lw=1.4, label="true")
    ax.plot(*_ned_to_enu_up(st.mean[:, :3]), "C1--", lw=1.2, label="estimated")
    ax.scatter(*_ned_to_enu_up(lms), c="g", marker="^", s=22,
               label="landmarks (true)" if unknown else "landmarks (known map)")
    if unknown and len(L_hat):
        ax.scatter(*_ned_to_enu_up(L_hat), c="r", marker="x", s=22, label="landmarks (estimated)")
    ax.set_xlabel("north [m]")
    ax.set_ylabel("east [m]")
    ax.set_zlabel("altitude [m]")
    ax.set_title(f"{name}: trajectory and map (3σ: see the plan view)", fontsize=10)
    ax.legend(loc="upper left", fontsize=7)

    # plan view with honest, stated magnification of the 3σ ellipses and of the errors
    ax2 = fig.add_subplot(1, 2, 2)
    pts = np.concatenate([lms[:, :2], fl.truth[:, :2]])
    span = float(np.max(np.ptp(pts, axis=0)))
    every = max(1, round(ROBOT_ELLIPSE_EVERY_S / max(float(t[1] - t[0]), 1e-9)))
    rk = np.arange(every - 1, len(t), every)
    r_true = truth[rk, :2]
    r_est = st.mean[rk, :2]
    r_sig3 = 3 * np.sqrt(np.maximum(st.var[rk, :2], 0))
    if unknown and len(L_hat):
        info = landmark_errors(fl, lms, cfg)
        l_true = lms[info["ids"], :2]
        l_err = info["err"][-1, :, :2]
        l_sig3 = info["sig3"][-1, :, :2]
    else:
        info = None
        l_true = l_err = l_sig3 = np.zeros((0, 2))
    k = magnification(np.concatenate([l_sig3.ravel(), r_sig3.ravel()]), span)
    ax2.plot(fl.truth[:, 1], fl.truth[:, 0], "C0-", lw=1.2, label="true path")
    ax2.scatter(lms[:, 1], lms[:, 0], c="g", marker="^", s=20, zorder=3,
                label="landmarks (true)" if unknown else "landmarks (known map)")
    if len(l_true):
        ex, ey = _ellipses_xy(l_true, l_sig3 * k)
        ax2.plot(ex, ey, "r-", lw=0.8, label=f"landmark 3σ ellipse ×{k} (end)")
        off = l_true + k * np.nan_to_num(l_err)
        ax2.scatter(off[:, 1], off[:, 0], c="r", marker="x", s=18, zorder=4,
                    label=f"landmark estimate, offset ×{k}")
    ex, ey = _ellipses_xy(r_true, r_sig3 * k)
    ax2.plot(ex, ey, "C1-", lw=0.8, label=f"robot 3σ ellipse ×{k} (every {ROBOT_ELLIPSE_EVERY_S:g} s)")
    off = r_true + k * (r_est - r_true)
    ax2.scatter(off[:, 1], off[:, 0], c="C1", marker=".", s=30, zorder=4, label=f"robot estimate, offset ×{k}")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel("east [m]")
    ax2.set_ylabel("north [m]")
    ax2.grid(alpha=0.3)
    ax2.set_title(f"plan view: horizontal 3σ (marginal, axis-aligned) and estimate − truth, both ×{k}\n"
                  "about the truth: a truth outside its ellipse is an error beyond 3σ", fontsize=9)
    ax2.legend(fontsize=7, loc="upper right")
    keep_margins(fig, left=0.02, right=0.98, bottom=0.08, top=0.90, wspace=0.12)
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

    if info is not None:
        n = len(info["ids"])
        tf = (np.arange(fr.landmarks.shape[0]) + 1) * (t[-1] / fr.landmarks.shape[0])
        fig = p.figure(figsize=(12, 7.5))
        gs = fig.add_gridspec(2, 3, height_ratios=(1.0, 1.0))
        ax = fig.add_subplot(gs[0, :])
        x = np.arange(n)
        beyond = info["final_err"] > info["final_3sig"]
        ax.bar(x, info["final_err"], color=np.where(beyond, "C3", "C0"), width=0.8,
               label="final error ‖l̂ − l‖ (red: beyond 3√tr P)")
        ax.plot(x, info["final_3sig"], "k_", ms=12, mew=1.5, label="3√tr P (final)")
        ax.set_xticks(x)
        ax.set_xticklabels([str(int(i)) for i in info["ids"]], fontsize=7)
        ax.set_xlim(-0.7, n - 0.3)
        ax.set_xlabel("landmark id" + ("" if cfg.association == "known" else " (nearest true landmark)"))
        ax.set_ylabel("error [m]")
        ax.grid(alpha=0.3, axis="y")
        unmapped = sorted(set(range(len(lms))) - {int(i) for i in info["ids"]})
        ax.set_title(f"final error of each mapped landmark, sorted ({n} mapped of {len(lms)}; median "
                     f"{np.nanmedian(info['final_err']):.3f} m; {int(beyond.sum())} beyond 3√tr P)"
                     + (f"; not mapped: {', '.join(map(str, unmapped))}" if unmapped else ""), fontsize=9)
        ax.legend(fontsize=7)
        e, s3 = info["err"], info["sig3"]
        mapped = np.isfinite(e[:, :, 0])
        has = mapped.any(axis=1)
        lo_b, med, hi_b = _nanquantiles(e, (0.05, 0.5, 0.95))
        s_med = _nanquantiles(s3, (0.5,))[0]
        for j, axis_name in enumerate(["north", "east", "down"]):
            a = fig.add_subplot(gs[1, j])
            a.fill_between(tf[has], lo_b[has, j], hi_b[has, j], color="C0", alpha=0.25,
                           label="5-95 % of mapped landmarks")
            a.plot(tf[has], med[has, j], "C0-", lw=1.2, label="median error")
            a.plot(tf[has], s_med[has, j], "k-.", lw=0.8, label="± median 3σ")
            a.plot(tf[has], -s_med[has, j], "k-.", lw=0.8)
            a.axhline(0, color="0.5", lw=0.5)
            a.set_title(f"{axis_name} error [m]", fontsize=9)
            a.set_xlabel("time [s]")
            a.grid(alpha=0.3)
            if j == 0:
                a.set_ylabel("landmark error [m]")
                a.legend(fontsize=7)
        fig.suptitle(f"{name}: landmark errors (run 0)")
        keep_margins(fig, left=0.07, right=0.98, bottom=0.08, top=0.90, hspace=0.45, wspace=0.25)
        paths.append(save(fig, directory, f"{name}_landmarks"))

    paths.append(save(nees_figure(name, t_frames, fr.nees, anees_per_frame, cons, runs), directory, f"{name}_nees"))
    return paths


def nees_figure(name, t_frames, nees_one_run, anees_per_frame, cons, runs):
    """The Monte Carlo NEES figure: one run's NEES, the ANEES over ``runs`` runs against its
    per-step bounds, the 10 s window averages; the title gives the flight average's verdict and
    the share of steps inside.  Returns the (unsaved) figure."""
    from ..systems.ekf_slam_3d import CONSISTENCY_BLOCKS

    p = plt()
    lo, hi = cons["anees_bounds"]
    fig, ax = p.subplots(figsize=(10, 4))
    ax.semilogy(t_frames, np.maximum(np.asarray(nees_one_run, float), 1e-6), color="0.7", lw=0.5,
                label="NEES, one run")
    ax.semilogy(t_frames, anees_per_frame, "C0-", lw=1.0, label=f"ANEES over {runs} runs")
    ax.axhline(lo, color="C3", ls="--", lw=1, label="95 % bounds")
    ax.axhline(hi, color="C3", ls="--", lw=1)
    for w in cons.get("anees_windows", []):
        ax.hlines(w["anees"], w["t0_s"], w["t1_s"], colors="k", lw=2)
    ax.axhline(CONSISTENCY_BLOCKS["anees_dim"], color="g", ls=":", lw=0.8,
               label=f"expected ({CONSISTENCY_BLOCKS['anees_dim']})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"NEES ({CONSISTENCY_BLOCKS['anees_dim']} states)")
    detail = (f"flight average {cons['anees']:.2f} (consistency.anees): {verdict(cons['anees'], (lo, hi))}; "
              f"per step: {steps_inside(cons.get('anees_fraction_in_bounds'))}")
    ax.set_title(f"{name}: NEES of the {CONSISTENCY_BLOCKS['anees_block']}, {CONSISTENCY_BLOCKS['anees_dim']} "
                 "states (black bars: 10 s window averages)\n" + "\n".join(textwrap.wrap(detail, 120)), fontsize=9)
    ax.legend(fontsize=7)
    keep_margins(fig, left=0.09, right=0.98, bottom=0.12, top=0.86)
    return fig
