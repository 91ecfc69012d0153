"""Timing helper shared by the benchmarks (not itself a benchmark: ``jaxslam bench`` runs ``bench_*.py``).

``jaxslam bench`` puts this folder on ``sys.path`` while a benchmark runs, so ``from timing
import median_s`` works there.
"""

from __future__ import annotations

import statistics
import time

__all__ = ["median_s"]


def median_s(fn, repeats: int) -> float:
    """Median wall time [s] of ``repeats`` calls of ``fn()`` (``fn`` blocks on its own results)."""
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)
