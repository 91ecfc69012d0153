"""Plots of paper 004's line-feature SLAM runs (one flight plus the Monte Carlo NEES).

* ``*_scan``: one scan projected to the ground in the map frame (at the
  estimated pose), with the lines the filter holds for it drawn through the
  points, and the true walls;
* ``*_map``: true walls, estimated wall lines (clipped to the room's bounding
  box; thin dashed) and true vs estimated path;
* ``*_errors``: x, y and yaw errors with ±3σ bands, lines mapped over time;
* ``*_nees``: per-step pose ANEES over the runs with the 95 % bounds.

NumPy inputs; matplotlib is imported lazily (Agg).
"""

from __future__ import annotations

import textwrap

import numpy as np

from ..metrics import consistency_verdict, steps_inside, steps_inside_text
from ..errors import InputError
from ..linalg import check_int
from .flight import _output_dir, closing_on_error, plt, save

__all__ = ["clip_line", "plot_all"]


def clip_line(rho, theta, box):
    """End points (2, 2) of the line ρ = q·[cos θ, sin θ] inside box (xmin, xmax, ymin, ymax), or None."""
    n = np.array([np.cos(theta), np.sin(theta)])
    d = np.array([-n[1], n[0]])
    p0 = rho * n
    xmin, xmax, ymin, ymax = box
    ts = []
    for k, (lo, hi) in enumerate(((xmin, xmax), (ymin, ymax))):
        if abs(d[k]) > 1e-12:
            ts += [(lo - p0[k]) / d[k], (hi - p0[k]) / d[k]]
    pts = [p0 + t * d for t in ts]
    pts = [q for q in pts if xmin - 1e-9 <= q[0] <= xmax + 1e-9 and ymin - 1e-9 <= q[1] <= ymax + 1e-9]
    if len(pts) < 2:
        return None
    pts = np.array(pts)
    proj = pts @ d
    return np.stack([pts[np.argmin(proj)], pts[np.argmax(proj)]])


def _walls(ax, walls, **kw):
    for i, (a, b) in enumerate(np.asarray(walls)):
        ax.plot([a[0], b[0]], [a[1], b[1]], "k-", lw=2.5, label="true walls" if i == 0 else None, **kw)


def _lines_and_frame(ax, lines, active, box, label, lw, title):
    """Draw the active map lines clipped to ``box`` and set up the plan-view axes."""
    first = True
    for j in np.flatnonzero(np.asarray(active)):
        seg = clip_line(lines[j, 0], lines[j, 1], box)
        if seg is not None:
            ax.plot(seg[:, 0], seg[:, 1], "C3--", lw=lw, label=label if first else None)
            first = False
    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[2], box[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)


def plot_all(name, setup, cfg, log, res, per_step, bounds, directory, scan_index=None):
    """Write the four figures; returns their paths (``directory`` is made and checked writable
    first; a figure that fails is closed).  ``scan_index``: the scan of the ``*_scan`` figure,
    an int in [0, number of steps) (default: a third of the way), else InputError."""
    _output_dir(directory, probe=True)
    with closing_on_error():
        return _plot_all(name, setup, cfg, log, res, per_step, bounds, directory, scan_index)


def _plot_all(name, setup, cfg, log, res, per_step, bounds, directory, scan_index):
    from ..sensors import laser2d

    p = plt()
    paths = []
    st = res.steps
    t = np.asarray(setup.ts)
    if scan_index is not None:  # (a JAX array clamps an index past the end: another scan drawn)
        scan_index = check_int(scan_index, "scan_index", lower=0)
        if scan_index >= len(t):
            raise InputError(f"scan_index: expected an int < {len(t)} (the number of scans), got {scan_index}")
    tr = np.asarray(setup.truth)
    walls = np.asarray(setup.walls)
    box = (walls[..., 0].min() - 0.5, walls[..., 0].max() + 0.5, walls[..., 1].min() - 0.5,
           walls[..., 1].max() + 0.5)

    # --- one scan with its lines
    k = len(t) // 3 if scan_index is None else int(scan_index)
    import jax.numpy as jnp

    r = np.asarray(log.ranges[k])
    v = np.asarray(log.valid[k]) & np.isfinite(r)
    pts = np.asarray(laser2d.scan_points(jnp.asarray(np.where(v, r, 0.0)), jnp.asarray(v), cfg.spec,
                                         jnp.asarray(log.tilt[k]))[0])
    s = np.asarray(st.mean[k])
    c, sn = np.cos(s[4]), np.sin(s[4])
    Rm = np.array([[c, -sn], [sn, c]])
    pw = pts[v] @ Rm.T + s[:2]
    fig, ax = p.subplots(figsize=(7, 6))
    _walls(ax, walls)
    ax.plot(pw[:, 0], pw[:, 1], ".", ms=2, color="C0", label=f"scan {k} (t = {t[k]:.1f} s), ground-projected")
    _lines_and_frame(ax, st.lines[k], st.active[k], box, "estimated lines", 1.0,
                     f"{name}: scan and line features")
    ax.plot(s[0], s[1], "C1o", label="estimated pose")
    ax.plot(tr[k, 0], tr[k, 1], "kx", label="true pose")
    ax.legend(fontsize=7, loc="upper right")
    paths.append(save(fig, directory, f"{name}_scan"))

    # --- map
    fig, ax = p.subplots(figsize=(7, 6))
    _walls(ax, walls)
    _lines_and_frame(ax, st.lines[-1], st.active[-1], box, "estimated wall lines", 0.8,
                     f"{name}: map ({int(np.asarray(st.active[-1]).sum())} lines) and path")
    ax.plot(tr[:, 0], tr[:, 1], "C0-", lw=1.2, label="true path")
    ax.plot(st.mean[:, 0], st.mean[:, 1], "C1--", lw=1.2, label="estimated path")
    ax.legend(fontsize=7, loc="upper right")
    paths.append(save(fig, directory, f"{name}_map"))

    # --- errors with ±3σ
    e = np.asarray(st.mean) - tr
    e[:, 4] = (e[:, 4] + np.pi) % (2 * np.pi) - np.pi
    sig = np.sqrt(np.clip(np.diagonal(np.asarray(st.cov), axis1=1, axis2=2), 0, None))
    fig, axs = p.subplots(4, 1, figsize=(8, 9), sharex=True)
    for ax, i, lab, sc in ((axs[0], 0, "x error [m]", 1.0), (axs[1], 1, "y error [m]", 1.0),
                           (axs[2], 4, "yaw error [deg]", 180 / np.pi)):
        ax.plot(t, e[:, i] * sc, "C0", lw=1, label="error")
        ax.fill_between(t, -3 * sig[:, i] * sc, 3 * sig[:, i] * sc, color="C0", alpha=0.15, label="±3σ")
        ax.set_ylabel(lab)
        ax.grid(True, alpha=0.3)
    axs[0].legend(fontsize=7)
    axs[3].plot(t, np.asarray(st.active).sum(axis=1), "C2")
    axs[3].axhline(len(setup.lines), color="k", ls=":", lw=1, label="true lines")
    axs[3].set_ylabel("lines mapped")
    axs[3].set_xlabel("t [s]")
    axs[3].legend(fontsize=7)
    fig.suptitle(f"{name}: pose errors (one run)")
    paths.append(save(fig, directory, f"{name}_errors"))

    # --- NEES
    fig, ax = p.subplots(figsize=(8, 3.5))
    ax.plot(t, per_step, "C0", lw=1, label="pose ANEES (3 dof)")
    ax.axhline(bounds[0], color="k", ls="--", lw=0.8, label="95 % bounds")
    ax.axhline(bounds[1], color="k", ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("ANEES")
    per_step = np.asarray(per_step, float)
    avg, inside = float(np.mean(per_step)), steps_inside(per_step, bounds)
    ax.axhline(3, color="g", ls=":", lw=0.8, label="expected (3)")
    ax.set_title("\n".join(textwrap.wrap(f"{name}: pose ANEES over the runs; time average {avg:.2f}: "
                                         f"{consistency_verdict(avg, bounds)}; per step: "
                                         f"{steps_inside_text(inside)}", 95)), fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    paths.append(save(fig, directory, f"{name}_nees"))
    return paths
