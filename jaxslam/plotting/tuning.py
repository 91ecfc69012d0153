"""Tuning plots: loss curves, parameter trajectories, held-out before/after.

Input is the ``tune`` JSON dict (:mod:`jaxslam.cli.tune`) or its pieces; matplotlib
is imported lazily (Agg).  Every function returns the Figure; :func:`plot_all` writes PNGs.
"""

from __future__ import annotations

import math
import numbers
import textwrap

import numpy as np

from ..errors import InputError
from ..linalg import check_int
from .flight import _output_dir, keep_margins, plt, save

__all__ = ["before_after", "choose_panels", "loss_curves", "param_trajectories", "plot_all", "reference_values"]


def _is_number(v) -> bool:
    """A real number (an int, a float, a NumPy scalar; not a bool, not a numeric string)."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _check_report(report, keys, name: str = "report") -> None:
    """InputError unless ``report`` is a dict holding ``keys`` (a ``tune`` JSON report); with
    ``before`` and ``after`` among them, their statistics are checked too (:func:`_check_sides`)."""
    if not isinstance(report, dict):
        raise InputError(f"{name}: expected a tune report (dict), got {type(report).__name__}")
    missing = [k for k in keys if k not in report]
    if missing:
        raise InputError(f"{name}: missing key(s) {missing} (expected a 'jaxslam tune --json' report)")
    for k in ("before", "after"):
        if k in keys and not (isinstance(report[k], dict) and isinstance(report[k].get("metrics"), dict)):
            raise InputError(f"{name}: '{k}' must hold a 'metrics' object")
    if "before" in keys and "after" in keys:
        _check_sides(report, name)


def _check_mean(entry, where: str) -> None:
    """InputError naming ``where`` unless ``entry`` is a metric summary whose ``mean`` is a number
    or None (JSON's null for NaN)."""
    if not isinstance(entry, dict) or "mean" not in entry:
        raise InputError(f"{where}: expected a summary {{'mean': number, ...}}, got {entry!r}"[:300])
    if not (entry["mean"] is None or _is_number(entry["mean"])):
        raise InputError(f"{where}['mean']: expected a number or null, got {entry['mean']!r}"[:300])


def _check_sides(report, name: str = "report") -> None:
    """What :func:`choose_panels` reads of a report, checked up front (InputError naming the key):
    every metric of ``before`` is a summary with a numeric ``mean`` (or null) and is in ``after``
    too; a numeric consistency statistic of ``before`` is a number or null in ``after``, its
    bounds two numbers; the references (``{label: {"metrics": {...}}}``) hold numeric means;
    ``history`` (when present) is a list of step records."""
    before, after = report["before"], report["after"]
    for side in ("before", "after"):
        for m, entry in report[side]["metrics"].items():
            _check_mean(entry, f"{name}['{side}']['metrics'][{m!r}]")
    gone = [m for m in before["metrics"] if m not in after["metrics"]]
    if gone:
        raise InputError(f"{name}['after']['metrics']: missing {gone} (in 'before'; both sides are "
                         "evaluated on the same held-out runs)")
    for side in ("before", "after"):
        cons = report[side].get("consistency")
        if cons is not None and not isinstance(cons, dict):
            raise InputError(f"{name}['{side}']['consistency']: expected an object or null, got {cons!r}"[:300])
    cb, ca = before.get("consistency") or {}, after.get("consistency") or {}
    for k, v in cb.items():
        if not _is_number(v) or k not in ca:
            continue
        if not (ca[k] is None or _is_number(ca[k])):
            raise InputError(f"{name}['after']['consistency'][{k!r}]: expected a number or null, got {ca[k]!r}"[:300])
    for k, b in ca.items():
        if k.endswith("_bounds") and b is not None and not (
                isinstance(b, (list, tuple)) and len(b) == 2 and all(v is None or _is_number(v) for v in b)):
            raise InputError(f"{name}['after']['consistency'][{k!r}]: expected [low, high] numbers, got {b!r}"[:300])
    refs = report.get("references")
    if refs is not None and not isinstance(refs, dict):
        raise InputError(f"{name}['references']: expected an object {{label: report}}, got {type(refs).__name__}")
    for label, r in (refs or {}).items():
        if not (isinstance(r, dict) and isinstance(r.get("metrics"), dict)):
            raise InputError(f"{name}['references'][{label!r}]: must hold a 'metrics' object")
        for m in before["metrics"]:
            if m in r["metrics"]:
                _check_mean(r["metrics"][m], f"{name}['references'][{label!r}]['metrics'][{m!r}]")
        rc = r.get("consistency")
        if rc is not None and not isinstance(rc, dict):
            raise InputError(f"{name}['references'][{label!r}]['consistency']: expected an object or null, "
                             f"got {rc!r}"[:300])
        for k, v in (rc or {}).items():
            if _is_number(cb.get(k)) and k in ca and not (v is None or _is_number(v)):
                raise InputError(f"{name}['references'][{label!r}]['consistency'][{k!r}]: expected a number "
                                 f"or null, got {v!r}"[:300])
    if "history" in report:
        _check_history(report["history"], f"{name}['history']")


def _check_history(history, name: str = "history") -> None:
    """InputError unless ``history`` is a list of records (dicts), each with a ``step``, whose
    ``loss`` / ``test_loss`` are numbers or null where given."""
    if not isinstance(history, (list, tuple)):
        raise InputError(f"{name}: expected a list of step records, got {type(history).__name__}")
    for i, h in enumerate(history):
        if not isinstance(h, dict) or "step" not in h:
            raise InputError(f"{name}: record {i} is not a step record with a 'step' (got {h!r})"[:300])
        for k in ("step", "loss", "test_loss"):
            v = h.get(k)
            if not (v is None and k != "step" or _is_number(v)):
                raise InputError(f"{name}: record {i}'s {k!r} is not a number (got {v!r})"[:300])


def _check_params(history, name: str = "history") -> list:
    """The records of ``history`` that hold ``params``, checked: each ``params`` is an object
    with the names of the first, each entry a flat list of numbers (null: NaN) as long as the
    first record's; else InputError naming ``name`` and the record."""
    recs = [(i, h) for i, h in enumerate(history) if "params" in h]
    if not recs:
        return []
    first = recs[0][1]["params"]
    if not isinstance(first, dict) or not first:
        raise InputError(f"{name}: record {recs[0][0]}'s 'params' must be an object {{name: [values]}}, "
                         f"got {first!r}"[:300])
    lengths = {}
    for i, h in recs:
        params = h["params"]
        if not isinstance(params, dict) or set(params) != set(first):
            got = list(params) if isinstance(params, dict) else params
            raise InputError(f"{name}: record {i}'s 'params' names {got!r}, expected {list(first)} "
                             f"(record {recs[0][0]}'s)"[:300])
        for k, v in params.items():
            flat = isinstance(v, (list, tuple)) or (isinstance(v, np.ndarray) and v.ndim == 1)
            if not (flat and len(v) and all(e is None or _is_number(e) for e in v)):
                raise InputError(f"{name}: record {i}'s params[{k!r}] must be a non-empty list of numbers, "
                                 f"got {v!r}"[:300])
            if lengths.setdefault(k, len(v)) != len(v):
                raise InputError(f"{name}: record {i}'s params[{k!r}] has {len(v)} values, record "
                                 f"{recs[0][0]}'s {lengths[k]}")
    return [h for _, h in recs]


def loss_curves(history, title="Tuning loss"):
    """Training loss per step (line) and held-out loss where recorded (markers)."""
    _check_history(history)
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


def _symmetric_side(vals) -> int:
    """k when every row of ``vals`` (steps, k²) is a flattened symmetric k×k matrix (k > 1), else 0."""
    k = int(round(np.sqrt(vals.shape[1])))
    if k < 2 or k * k != vals.shape[1]:
        return 0
    m = vals.reshape(len(vals), k, k)
    return k if np.array_equal(m, np.swapaxes(m, 1, 2)) else 0


def reference_values(report: dict) -> dict:
    """The report's references with parameters (e.g. the linear-Gaussian target's ``true`` Q, R)
    in the history's layout: ``{label: {name: [values]}}`` — a matrix's diagonal where the history
    holds a diagonal, the whole matrix row-major where it holds the whole matrix."""
    hist = [h for h in report.get("history", []) if "params" in h]
    if not hist:
        return {}
    lengths = {k: len(v) for k, v in hist[0]["params"].items()}

    def find(tree, name):
        if isinstance(tree, dict):
            if name in tree and not isinstance(tree[name], dict):
                return tree[name]
            for v in tree.values():
                got = find(v, name)
                if got is not None:
                    return got
        return None

    out = {}
    for label, ref in (report.get("references") or {}).items():
        vals = {}
        for name, n in lengths.items():
            m = find(ref.get("params") if isinstance(ref, dict) else None, name)
            if m is None:
                continue
            try:
                a = np.asarray(m, float)
            except (TypeError, ValueError):
                continue
            if not np.all(np.isfinite(a)):
                continue
            if a.ndim == 2 and a.shape[0] == a.shape[1] and a.shape[0] == n:
                vals[name] = np.diag(a).tolist()
            elif a.size == n:
                vals[name] = a.ravel().tolist()
        if vals:
            out[label] = vals
    return out


def param_trajectories(history, reference=None, title="Parameter trajectories"):
    """One panel per tuned matrix: its entries against the step (log scale when all positive).

    A whole symmetric matrix (k² entries) shows its upper triangle only, labelled ``[i,j]``;
    entries beyond ten colours change line style.  ``reference``: optional ``{label: {name:
    [values]}}`` (or one ``{name: [values]}``); the first is drawn as dotted lines in each
    entry's colour and named in the title (e.g. the truth of the linear-Gaussian target, or the
    IMU-derived Q); a reference entry that is null or not a finite number is not drawn.
    """
    _check_history(history)
    recs = _check_params(history)
    if not recs:
        raise InputError("history holds no 'params' records")  # (a ValueError, as before)
    names = list(recs[0]["params"])
    if reference and not any(isinstance(v, dict) for v in reference.values()):
        reference = {"reference": reference}
    # one reference drawn (dotted in each entry's colour): more would not be told apart
    reference = dict(list((reference or {}).items())[:1])
    p = plt()
    fig, axes = p.subplots(len(names), 1, figsize=(8.5, 3.2 * len(names)), squeeze=False)
    steps = [h["step"] for h in recs]
    drawn = set()
    styles = ("-", "--", "-.")  # dotted is the reference's
    for ax, name in zip(axes[:, 0], names):
        vals = np.array([h["params"][name] for h in recs], float)
        k = _symmetric_side(vals)
        idx = [i * k + j for i in range(k) for j in range(i, k)] if k else list(range(vals.shape[1]))
        positive = np.all(vals[:, idx] > 0)
        for c, i in enumerate(idx):
            colour, label = f"C{c % 10}", (f"{name}[{i // k},{i % k}]" if k else f"{name}[{i}]")
            ax.plot(steps, vals[:, i], lw=1.2, color=colour, ls=styles[(c // 10) % len(styles)], label=label)
            for ref_label, ref in reference.items():
                r = ref.get(name)
                ri = _num(r[i]) if r is not None and i < len(r) and (r[i] is None or _is_number(r[i])) \
                    else float("nan")  # (null, JSON's NaN, or not a number: nothing drawn)
                if np.isfinite(ri) and (not positive or ri > 0):
                    ax.axhline(ri, color=colour, ls=":", lw=1)
                    drawn.add(ref_label)
        if positive:
            ax.set_yscale("log")
        ax.set_ylabel(name + (" (upper triangle)" if k else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=1 + len(idx) // 12, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1, 0].set_xlabel("step")
    axes[0, 0].set_title(title + (f"\ndotted: {', '.join(sorted(drawn))}" if drawn else ""))
    fig.tight_layout()
    return fig


# What the before/after figure shows first (docs/tuning.md): the loss, the scenario's headline
# position error, the consistency statistics, then these metrics, then the rest alphabetically.
HEADLINE_METRICS = ("pos_rmse_m", "ate_m", "nominal_track_pos_rmse_settled_m", "nominal_track_pos_rmse_m",
                    "track_pos_rmse_settled_m", "track_pos_rmse_m")
CONSISTENCY_PRIORITY = ("anees", "nis_mean", "anees_robot")
METRIC_PRIORITY = ("nll", "nominal_closed_loop_cost", "closed_loop_cost", "pos_rmse_settled_m",
                   "landmark_rmse_m", "vel_rmse_mps", "att_rmse_deg", "yaw_rmse_deg", "outlier_fraction")
MAX_PANELS = 8
_NOTHING = ("report: nothing to compare before/after: no loss in 'history', no metrics and no consistency "
            "statistics")


def _loss_panel(report):
    hist = [h for h in report.get("history", []) if h.get("loss") is not None]
    if not hist:
        return None
    first, last = hist[0], hist[-1]
    held = first.get("test_loss") is not None and last.get("test_loss") is not None
    key = "test_loss" if held else "loss"
    return {"key": "loss", "kind": "loss", "bounds": None, "values": [first[key], last[key]],
            "title": f"loss '{report.get('loss', '?')}' ({'held-out' if held else 'training batch'}, "
                     f"step {first['step']} vs {last['step']})"}


def _headline(names):
    for m in HEADLINE_METRICS:
        if m in names:
            return m
    return next((m for m in names if "pos_rmse" in m or m.startswith("ate")), None)


def choose_panels(report, max_panels=MAX_PANELS):
    """The panels of :func:`before_after`, by priority, and the names left out (pure).

    Order: the loss (first and last recorded step), the headline position metric
    (:data:`HEADLINE_METRICS`, else the first ``*pos_rmse*`` / ``ate*``), the consistency
    statistics (:data:`CONSISTENCY_PRIORITY`, then any other), the metrics of
    :data:`METRIC_PRIORITY`, then the rest alphabetically.

    Returns:
      ``(panels, left_out)``: panels ``{"key", "kind": "loss" | "consistency" | "metric",
      "title", "values": [before, after, *references], "bounds": (lo, hi) | None}``; the
      names of the statistics that did not fit.
    """
    _check_report(report, ("before", "after"))
    max_panels = check_int(max_panels, "max_panels", lower=1)
    before, after = report["before"], report["after"]
    refs = list((report.get("references") or {}).values())
    cands = []
    lp = _loss_panel(report)
    if lp is not None:
        cands.append(lp)
    names = list(before["metrics"])

    def metric(m):
        return {"key": m, "kind": "metric", "title": m, "bounds": None,
                "values": [before["metrics"][m]["mean"], after["metrics"][m]["mean"]]
                + [r["metrics"].get(m, {}).get("mean") for r in refs]}

    head = _headline(names)
    if head is not None:
        cands.append(metric(head))
    cb, ca = before.get("consistency") or {}, after.get("consistency") or {}
    stats = [k for k, v in cb.items() if k in ca and _is_number(v)  # (NumPy scalars too, as _check_sides)
             and not k.endswith(("_bounds", "_block", "_dim", "_steps_inside"))]
    stats.sort(key=lambda k: (CONSISTENCY_PRIORITY.index(k) if k in CONSISTENCY_PRIORITY
                              else len(CONSISTENCY_PRIORITY), k))
    for k in stats:
        stem = k.removesuffix("_mean")
        b = ca.get(f"{k}_bounds", ca.get(f"{stem}_bounds"))
        block, dim = ca.get(f"{k}_block", ca.get(f"{stem}_block")), ca.get(f"{k}_dim", ca.get(f"{stem}_dim"))
        title = k
        if block is not None:
            what = f"{block}" + (f", {dim} states" if dim is not None and not stem.startswith("nis") else "")
            title += "\n" + "\n".join(textwrap.wrap(what, 44))
        cands.append({"key": k, "kind": "consistency", "title": title,
                      "bounds": tuple(b) if b is not None and len(b) == 2 else None,
                      "values": [cb[k], ca[k]] + [(r.get("consistency") or {}).get(k) for r in refs]})
    rest = [m for m in METRIC_PRIORITY if m in names and m != head]
    rest += sorted(m for m in names if m != head and m not in rest)
    cands += [metric(m) for m in rest]
    return cands[:max_panels], [c["key"] for c in cands[max_panels:]]


def _num(v):
    return float("nan") if v is None else float(v)


def before_after(report, metrics=None, title="Held-out evaluation", max_panels=MAX_PANELS):
    """Bars of held-out means (before, after, references): the panels of :func:`choose_panels`
    (or exactly ``metrics``), each titled with the change after vs before; consistency panels
    shade their 95 % bounds; a note names what did not fit."""
    _check_report(report, ("before", "after"))
    refs = report.get("references") or {}
    if metrics is not None:
        # any iterable of names but a string (a list, dict_keys, a NumPy array of str, a generator)
        names = None
        if not isinstance(metrics, (str, bytes)):
            try:
                names = list(metrics)
            except TypeError:  # not iterable
                names = None
        if names is None or not all(isinstance(m, str) for m in names):
            raise InputError(f"metrics: expected a list of statistic names, got {metrics!r}"[:300])
        metrics = [str(m) for m in names]
        if not metrics:
            raise InputError("metrics: expected at least one statistic name, got an empty list")
        panels, left_out = choose_panels(report, max_panels=10 ** 6)
        unknown = sorted(set(metrics) - {q["key"] for q in panels})
        if unknown:
            raise InputError(f"metrics: unknown statistic(s) {unknown}; the report has "
                             f"{', '.join(q['key'] for q in panels)}")
        panels = [q for q in panels if q["key"] in metrics]
        left_out = []
    else:
        panels, left_out = choose_panels(report, max_panels)
        if not panels:
            raise InputError(_NOTHING)
    p = plt()
    ncol = min(4, max(1, len(panels)))
    nrow = -(-len(panels) // ncol)
    fig, axes = p.subplots(nrow, ncol, figsize=(2.9 * ncol, 2.9 * nrow + 1.2), squeeze=False)
    labels = ["before", "after"] + list(refs)
    colors = [f"C{i}" for i in range(len(labels))]
    for ax, q in zip(axes.ravel(), panels):
        vals = [_num(v) for v in q["values"]]
        x = np.arange(len(vals))
        ax.bar(x, np.nan_to_num(vals), color=colors[:len(vals)])
        for xi, v in zip(x, vals):
            ax.text(xi, 0 if not np.isfinite(v) else v, "n/a" if not np.isfinite(v) else f"{v:.3g}",
                    ha="center", va="bottom", fontsize=7)
        shown = [v for v in vals if np.isfinite(v)]
        if q["bounds"] is not None and all(b is not None for b in q["bounds"]):
            lo, hi = (float(b) for b in q["bounds"])
            ax.axhspan(lo, hi, color="g", alpha=0.2, zorder=0, label="95 % bounds (after)")
            ax.legend(fontsize=6, loc="lower right")
            shown.append(hi)
        top = max(shown + [0.0])
        if np.isfinite(top) and top > 0:
            ax.set_ylim(top=1.15 * top)
        ax.set_xticks(x)
        ax.set_xticklabels(labels[:len(vals)], rotation=30, fontsize=8)
        b, a = vals[0], vals[1]
        change = f"after {100 * (a - b) / abs(b):+.1f} %" if np.isfinite(a) and np.isfinite(b) and b else ""
        if q["bounds"] is not None and np.isfinite(a) and all(v is not None for v in q["bounds"]):
            lo, hi = (float(v) for v in q["bounds"])
            change += ("; " if change else "") + ("inside the bounds" if lo <= a <= hi else
                                                  "below the bounds" if a < lo else "above the bounds")
        ax.set_title(q["title"] + (f"\n{change}" if change else ""), fontsize=8)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.suptitle(title, fontsize=11)
    note = ""
    if left_out:
        note = (f"showing {len(panels)} of {len(panels) + len(left_out)} statistics by priority (loss, "
                f"position error, consistency, then the rest); not shown: {', '.join(left_out)} "
                "(all in the printed table and the tune JSON)")
        fig.text(0.01, 0.01, "\n".join(textwrap.wrap(note, 170)), fontsize=7, va="bottom", color="0.25")
    h = 2.9 * nrow + 1.2
    keep_margins(fig, left=0.06, right=0.98, top=1 - 1.05 / h,
                 bottom=(0.55 + (0.15 * (1 + len(note) // 170) if note else 0)) / h, hspace=1.1, wspace=0.35)
    return fig


def plot_all(report, directory):
    """Write ``<scenario>_tune_loss.png``, ``_params.png`` and ``_before_after.png``; return paths.

    The report is checked and ``directory`` made and checked writable before any figure is drawn
    (an :class:`~jaxslam.errors.InputError` naming the report key or ``directory``).  The
    parameter figure is left out (only) when the history records no parameters (a target
    without ``describe``).
    """
    _check_report(report, ("scenario", "target", "loss", "history", "before", "after"))
    history = report["history"]
    has_params = bool(_check_params(history, "report['history']"))
    panels, _ = choose_panels(report)
    if not panels:
        raise InputError(_NOTHING)
    _output_dir(directory, probe=True)
    name = f"{report['scenario']}_{report['target']}_{report['loss']}"
    out = [save(loss_curves(history, title=f"{name}: loss"), directory, f"{name}_loss")]
    if has_params:
        out.append(save(param_trajectories(history, reference_values(report), title=f"{name}: parameters"),
                        directory, f"{name}_params"))
    out.append(save(before_after(report, title=f"{name}: held-out before/after"), directory,
                    f"{name}_before_after"))
    return out
