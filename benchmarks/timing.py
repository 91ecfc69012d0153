"""Helpers shared by the benchmarks (not itself a benchmark: ``jaxslam bench`` runs ``bench_*.py``):
timing, option lists, seeds and keys, LiDAR frames.

``jaxslam bench`` puts this folder on ``sys.path`` while a benchmark runs, so ``from timing
import median_s`` works there.  Importing it imports neither JAX nor ``jaxslam``.
"""

from __future__ import annotations

import math
import statistics
import time

__all__ = ["median_s", "int_list", "wrap_seed", "prng_key", "lidar_frames"]


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


def wrap_seed(seed, offset: int = 0) -> int:
    """``seed + offset`` as a signed 64-bit integer (two's complement): the seed a benchmark
    derives for one of its streams (``--seed`` plus a fixed offset per stream).

    ``--seed`` takes [0, 2**63) (``jaxslam bench`` checks it), so ``2**63 - 1 + offset`` is past
    int64 (``PRNGKey`` raised OverflowError).  It wraps to ``-2**63 + offset - 1``, the signed
    value of the same 64 bits, which is how :func:`jaxslam.sim.monte_carlo.seed_key` reads a
    seed.  Distinct values of ``seed + offset`` in [0, 2**64) stay distinct (``% 2**63`` sent
    ``2**63 - 1 + 7`` to 6, seed 6's own stream).  Every ``seed + offset < 2**63`` is
    returned unchanged.  ``seed``: an int >= -2**63, ``offset`` an int >= 0, else an
    ``InputError`` naming it.
    """
    from jaxslam.errors import check_int

    seed = check_int(seed, "seed", lower=-2**63)
    offset = check_int(offset, "offset", lower=0)
    bits = (seed + offset) & (2**64 - 1)
    return bits - 2**64 if bits >= 2**63 else bits


def prng_key(seed, offset: int = 0):
    """``jax.random.PRNGKey(wrap_seed(seed, offset))``: the key of a benchmark stream (see
    :func:`wrap_seed`; with x64 on, as ``jaxslam bench`` runs, the threefry key is the 64 bits
    ``[high word, low word]``).  Equal to ``PRNGKey(seed + offset)`` whenever that is < 2**63."""
    import jax

    return jax.random.PRNGKey(wrap_seed(seed, offset))


def lidar_frames(duration, flag: str = "duration", dt: float = 0.01, lidar_every: int = 10) -> int:
    """Whole LiDAR frames of ``lidar_every`` steps of ``dt`` s in ``duration`` s:
    ``round(duration / (dt * lidar_every))``, which must be >= 1 (a window of no frame was run
    as one frame, or crashed the run), else an ``InputError`` naming ``flag`` (the option)."""
    from jaxslam.errors import InputError

    period = dt * lidar_every
    try:  # a bool is no duration; NaN and inf hold no whole number of frames
        d = None if isinstance(duration, bool) else float(duration)
    except (TypeError, ValueError):
        d = None
    n = round(d / period) if d is not None and math.isfinite(d) else 0
    if not n >= 1:
        raise InputError(f"{flag}: must hold at least one LiDAR frame ({period:g} s), got {duration!r}")
    return int(n)
