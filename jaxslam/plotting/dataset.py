"""Plots of a real-data run (``jaxslam dataset``): path and map, and errors over time.

* ``<name>_path``: the reference path (ground truth, motion capture or GPS),
  the estimate in the reference frame after the ATE alignment, dead reckoning
  (aligned the same way, when given), the estimated map (with 3σ ellipses when
  covariances are given) and the true map (when known);
* ``<name>_errors``: the position error of the estimate (and of dead reckoning)
  against the reference over time, with the ATE as a line.

NumPy inputs; matplotlib is imported lazily (Agg).
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import InputError
from .flight import _output_dir, closing_on_error, plt, save
from .uwb import ellipse_points

__all__ = ["plot_run"]


def plot_run(run, directory, name=None):
    """Write the figures of a :class:`jaxslam.data.runners.DatasetRun`; returns their paths.

    ``name`` (default: the dataset, with the robot or sequence of a dataset that has several,
    e.g. ``mrclam_robot3``, and ``_fastslam`` / ``_hidden`` for those runs, so runs of
    different robots, filters and modes can share a folder) prefixes the files.  ``directory``
    is made and checked writable before any figure is drawn; a figure that fails (e.g. a
    landmark covariance that is not PSD: InputError) is closed, not left open in pyplot.
    Landmark 3σ ellipses are drawn for up to 400 landmarks (more would hide the map).
    """
    _output_dir(directory, probe=True)
    if name is not None and not (isinstance(name, str) and name and pathlib.PurePath(name).name == name):
        raise InputError(f"name: expected a plain file name (no folder part), got {name!r}"[:300])
    with closing_on_error():
        return _plot_run(run, directory, name)


def _plot_run(run, directory, name):
    p = plt()
    if name is None:
        name = run.dataset.replace("-", "_")
        which = run.config.get("robot", run.config.get("sequence"))
        if run.dataset in ("mrclam", "plaza") and which is not None:
            name += f"_robot{which}" if run.dataset == "mrclam" else f"{which}"
        # runs of other filters or modes of one log can share a folder too (the EKF's default
        # run keeps the plain name)
        if run.config.get("filter", "ekf") != "ekf":
            name += f"_{run.config['filter']}"
        if run.config.get("ids") == "hidden":
            name += "_hidden"
    ev = run.evaluation
    paths = []
    fig, ax = p.subplots(figsize=(8, 7))
    ref, est = np.asarray(ev["ref_xy"]), np.asarray(ev["est_xy"])
    # Sparse references with gaps (GPS) as dots: a line would invent a path across a dropout.
    ax.plot(ref[:, 0], ref[:, 1], "k." if "GPS" in ev["ref_label"] and ref.shape[1] == 2 and
            run.dataset == "victoria-park" else "k-", lw=0.8, ms=1.5, label=ev["ref_label"])
    path = np.asarray(ev["est_path_xy"]) if ev.get("est_path_xy") is not None else est  # full rate
    ax.plot(path[:, 0], path[:, 1], "C1-", lw=1.0, label=f"{run.config['filter']} estimate "
            f"(ATE {run.metrics['ate_m']:.3f} m)")
    if ev.get("smooth_path_xy") is not None:
        sp = np.asarray(ev["smooth_path_xy"])
        ax.plot(sp[:, 0], sp[:, 1], "C0-", lw=1.0,
                label=f"smoothed (ATE {run.metrics['smoothed_ate_m']:.3f} m)")
    if ev.get("dr_xy") is not None:
        dr = np.asarray(ev["dr_xy"])
        ax.plot(dr[:, 0], dr[:, 1], "C7:", lw=0.8,
                label=f"dead reckoning (ATE {run.metrics['dead_reckoning_ate_m']:.2f} m)")
    lm = ev.get("lm_xy")
    if lm is not None and len(lm):
        lm = np.asarray(lm)
        ax.plot(lm[:, 0], lm[:, 1], "C3+", ms=7, mew=1.2, label=f"estimated map ({lm.shape[0]})")
        covs = ev.get("lm_cov")
        if covs is not None and len(lm) <= 400:
            for i, (m, c) in enumerate(zip(lm, np.asarray(covs))):
                e = ellipse_points(m, c)
                ax.plot(e[:, 0], e[:, 1], "C3-", lw=0.5, alpha=0.6, label="3σ ellipses" if i == 0 else None)
    lt = ev.get("lm_true_xy")
    if lt is not None and len(lt):
        lt = np.asarray(lt)
        ax.plot(lt[:, 0], lt[:, 1], "ko", mfc="none", ms=8, label=ev.get("lm_true_label", "true landmarks"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{run.dataset} ({run.config['setting']})\n{ev['frame_note']}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    paths.append(save(fig, directory, f"{name}_path"))

    fig, ax = p.subplots(figsize=(9, 3.5))
    t = np.asarray(ev["t"])
    err = np.linalg.norm(est - ref, axis=1)
    # a reference with dropouts (GPS): the curves break across gaps over 2 s instead of drawing
    # a line through them (the path figure uses dots for the same reason)
    cut = np.flatnonzero(np.diff(t) > 2.0) + 1 if t.size else np.zeros(0, int)

    def broken(y):  # (t, y) with a NaN point inserted in every gap
        return (np.insert(t, cut, np.nan), np.insert(np.asarray(y, float), cut, np.nan)) if cut.size else (t, y)

    ax.plot(*broken(err), "C1-", lw=0.8, label="estimate")
    suspect = ev.get("ref_suspect")
    if suspect is not None and np.any(suspect):  # reference fixes that are themselves wrong (GPS jumps)
        s = np.asarray(suspect, bool)
        ax.plot(t[s], err[s], "x", color="C3", ms=4, mew=0.8,
                label=f"{int(s.sum())} × {ev.get('ref_suspect_label', 'suspect reference')}")
    ax.axhline(run.metrics["ate_m"], color="C1", ls="--", lw=0.8, label=f"ATE {run.metrics['ate_m']:.3f} m")
    if ev.get("smooth_xy") is not None:
        ax.plot(*broken(np.linalg.norm(np.asarray(ev["smooth_xy"]) - ref, axis=1)), "C0-", lw=0.8, label="smoothed")
        ax.axhline(run.metrics["smoothed_ate_m"], color="C0", ls="--", lw=0.8,
                   label=f"smoothed ATE {run.metrics['smoothed_ate_m']:.3f} m")
    if ev.get("dr_xy") is not None:
        ax.plot(*broken(np.linalg.norm(np.asarray(ev["dr_xy"]) - ref, axis=1)), "C7:", lw=0.8,
                label="dead reckoning")
        ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    horizontal = run.dataset == "util-uwb"  # the plotted error is x-y; its ATE is 3-D (SE(3))
    ax.set_ylabel("horizontal (x-y) position error [m]" if horizontal else "position error [m]")
    ax.set_title(f"{name}, {run.config.get('filter', 'ekf')}: error against {ev['ref_label']} (after alignment)"
                 + ("\nthe dashed ATE lines are the 3-D error (SE(3) alignment)" if horizontal else ""),
                 fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="best", fontsize=8)
    paths.append(save(fig, directory, f"{name}_errors"))
    return paths
