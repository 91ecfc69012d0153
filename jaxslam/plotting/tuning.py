"""Tuning plots: loss curves, parameter trajectories, held-out before/after.

Input is the ``tune`` JSON dict (:mod:`jaxslam.tuning.cli`) or its pieces; matplotlib
is imported lazily (Agg).  Every function returns the Figure; :func:`plot_all` writes PNGs.
"""

from __future__ import annotations

import math

import numpy as np

from .flight import plt, save

__all__ = ["loss_curves", "param_trajectories", "before_after", "plot_all"]


def loss_curves(history, title="Tuning loss"):
    """Training loss per step (line) and held-out loss where recorded (markers)."""
    p = plt()
    fig, ax = p.subplots(figsize=(7, 4))
    st = [h["step"] for h in history if h.get("loss") is not None]
    lo = [h["loss"] for h in history if h.get("loss") is not None]
    ax.plot(st, lo, "C0-", lw=1.5, label="training (batch mean)")
    te = [(h["step"], h["test_loss"]) for h in history if h.get("test_loss") is not None]
    if te:
        ax.plot(*zip(*te), "C1o--", ms=4, lw=1, label="held-out")
    sk = [(h["step"], h["loss"]) for h in history if h.get("skipped") and h.get("loss") is not None
          and math.isfinite(h["loss"])]
    if sk:
        ax.plot(*zip(*sk), "rx", ms=8, label="update skipped (non-finite gradient)")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def param_trajectories(history, reference=None, title="Parameter trajectories"):
    """One panel per tuned matrix: its diagonal entries (log scale) against the step.

    ``reference``: optional {name: [values]} drawn as dotted lines (e.g. the IMU-derived Q).
    """
    recs = [h for h in history if "params" in h]
    if not recs:
        raise ValueError("history holds no 'params' records")
    names = list(recs[0]["params"])
    p = plt()
    fig, axes = p.subplots(len(names), 1, figsize=(7, 3.2 * len(names)), squeeze=False)
    steps = [h["step"] for h in recs]
    for ax, name in zip(axes[:, 0], names):
        vals = np.array([h["params"][name] for h in recs], float)
        positive = np.all(vals > 0)
        for i in range(vals.shape[1]):
            ax.plot(steps, vals[:, i], lw=1.2, color=f"C{i % 10}", label=f"{name}[{i}]")
            if reference and name in reference and i < len(reference[name]):
                ax.axhline(reference[name][i], color=f"C{i % 10}", ls=":", lw=1)
        if positive:
            ax.set_yscale("log")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("step")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    return fig


def before_after(report, metrics=None, title="Held-out evaluation"):
    """Bars of held-out means (before, after, references) for a few metrics."""
    before, after = report["before"]["metrics"], report["after"]["metrics"]
    refs = report.get("references", {})
    metrics = metrics or list(before)[:6]
    p = plt()
    fig, axes = p.subplots(1, len(metrics), figsize=(2.6 * len(metrics), 3.4), squeeze=False)
    labels = ["before", "after"] + list(refs)
    for ax, m in zip(axes[0], metrics):
        vals = [before[m]["mean"], after[m]["mean"]] + [r["metrics"][m]["mean"] for r in refs.values()]
        ax.bar(range(len(vals)), vals, color=[f"C{i}" for i in range(len(vals))])
        ax.set_xticks(range(len(vals)))
        ax.set_xticklabels(labels, rotation=30, fontsize=8)
        ax.set_title(m, fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_all(report, directory):
    """Write ``<scenario>_tune_loss.png``, ``_params.png`` and ``_before_after.png``; return paths."""
    name = f"{report['scenario']}_{report['target']}_{report['loss']}"
    out = [save(loss_curves(report["history"], title=f"{name}: loss"), directory, f"{name}_loss")]
    try:
        out.append(save(param_trajectories(report["history"], title=f"{name}: parameters"),
                        directory, f"{name}_params"))
    except ValueError:
        pass
    out.append(save(before_after(report, title=f"{name}: held-out before/after"), directory,
                    f"{name}_before_after"))
    return out
