"""Shared pieces of the figures: consistency verdicts in words, fixed margins.

A NEES/NIS value is compared with its two-sided 95 % χ² bounds; outside them the figure says
which way and what that means, as the console report of ``jaxslam run`` does.  matplotlib is
imported only by :func:`keep_margins`.
"""

from __future__ import annotations

import math

__all__ = ["keep_margins", "verdict"]

_MEANS = {
    "nees": ("below: conservative, covariance larger than the errors",
             "above: over-confident, errors larger than the covariance"),
    "nis": ("below: innovations smaller than predicted, R or P too large",
            "above: innovations larger than predicted, R or P too small or outliers"),
}


def verdict(value, bounds, kind: str = "nees") -> str:
    """``"ok"``, ``"OUTSIDE (below: conservative, ...)"`` or ``"undefined"``.

    Args:
      value: the statistic (None or NaN: undefined).
      bounds: ``(lo, hi)`` (None entries or NaN: undefined).
      kind: ``"nees"`` or ``"nis"`` (what an OUTSIDE verdict means).
    """
    try:
        v = float(value)
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):
        return "undefined"
    if not all(math.isfinite(x) for x in (v, lo, hi)):
        return "undefined"
    if lo <= v <= hi:
        return "ok"
    return f"OUTSIDE ({_MEANS[kind][0 if v < lo else 1]})"


def keep_margins(fig, **margins):
    """Fix the margins of ``fig``'s subplot grids (``left``, ``right``, ``bottom``, ``top``,
    ``wspace``, ``hspace``) so that :func:`jaxslam.plotting.flight.save`'s default
    ``subplots_adjust`` leaves them alone: they are set on each grid, which then ignores the
    figure's.  No layout engine is set, so the figure is still drawn once."""
    grids = []
    for ax in fig.axes:
        spec = ax.get_subplotspec()
        if spec is not None:
            gs = spec.get_topmost_subplotspec().get_gridspec()
            if all(gs is not g for g in grids):
                grids.append(gs)
    for gs in grids:
        gs.update(**margins)
    return fig
