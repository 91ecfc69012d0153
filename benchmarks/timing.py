"""Timing helper shared by the benchmarks (not itself a benchmark: ``jaxslam bench`` runs ``bench_*.py``).

``jaxslam bench`` puts this folder on ``sys.path`` while a benchmark runs, so ``from timing
import median_s`` works there.
"""

from __future__ import annotations

import statistics
import time

__all__ = ["median_s", "int_list"]


def median_s(fn, repeats: int) -> float:
    """Median wall time [s] of ``repeats`` calls of ``fn()`` (``fn`` blocks on its own results);
    ``repeats`` must be an int >= 1 (else an ``InputError`` naming it, not a StatisticsError)."""
    from jaxslam.errors import check_int

    check_int(repeats, "repeats")
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def int_list(text, flag: str = "option", allow_empty: bool = False) -> list:
    """A comma list of integers >= 1 (batch sizes, particle counts; an empty text: none, where
    ``allow_empty``), or an ``InputError`` naming ``flag`` (the CLI's exit 2, not an internal
    error)."""
    from jaxslam.errors import InputError

    try:
        values = [int(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        values = [0]
    if (not values and not allow_empty) or (values and min(values) < 1):
        raise InputError(f"{flag}: expected comma-separated integers >= 1, got {text!r}")
    return values
