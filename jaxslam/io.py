"""Reports: metric summaries, the ``run`` JSON of docs/cli.md, JSON files, text tables.

Host-side only (NumPy and the standard library); nothing here is traced.

Decisions
- Non-finite values are never dropped.  A run whose metric is NaN (a diverged
  filter) makes that metric's mean, median, p95 and max NaN, so one bad run is
  visible in every summary statistic; :func:`format_table` adds a line saying how
  many runs were non-finite.  (A finite-only mean would hide divergence.)
- JSON has no NaN or infinity, so :func:`write_json` writes every non-finite
  float as ``null`` (strict JSON that every parser reads).  ``per_run`` keeps its
  length, so the position of a ``null`` tells which run failed.
- ``p95`` is ``numpy.percentile(x, 95)`` with linear interpolation between runs (towards an
  infinite run the interpolation is infinite, where NumPy's ``inf - inf`` would give NaN).
- ``runs_per_s`` is ``runs / run_s`` (``null`` if ``run_s`` is not positive);
  ``run_s`` excludes compilation, which ``compile_s`` reports.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import platform
from typing import Any, Mapping

import numpy as np

from jaxslam.errors import InputError
from jaxslam.files import atomic_write

__all__ = [
    "summarize_metrics",
    "run_json",
    "to_jsonable",
    "write_json",
    "format_table",
    "machine_info",
    "RUN_JSON_KEYS",
]

# Top-level keys of the `run` JSON, in the order docs/cli.md gives ("consistency" omitted when None).
RUN_JSON_KEYS = (
    "scenario", "runs", "seed", "dtype", "config", "metrics",
    "consistency", "flags", "timing", "versions", "interrupted", "runs_requested", "notes",
)


def _per_run(values, name) -> np.ndarray:
    """A metric's per-run values as float64 (None: NaN, as NumPy reads it), or InputError naming
    the metric when they are not numbers (a string, even "1.5", is refused)."""
    try:
        raw = np.asarray(values)
        if raw.dtype.kind in "US" or (raw.dtype.kind == "O" and any(isinstance(v, (str, bytes))
                                                                    for v in raw.ravel())):
            raise TypeError
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"metrics[{name!r}]: expected numbers (per-run values), got {values!r}"[:300]) from None


def _p95(x: np.ndarray) -> float:
    """``numpy.percentile(x, 95)`` (linear) of NaN-free values; with an infinity among the two
    runs it interpolates between, the limit of the interpolation (NumPy's ``inf - inf`` gives
    NaN): towards ``inf`` it is ``inf``, from ``-inf`` it is ``-inf`` (``-inf`` to ``inf``: NaN)."""
    if np.isfinite(x).all():
        return float(np.percentile(x, 95))
    lo = float(np.percentile(x, 95, method="lower"))
    hi = float(np.percentile(x, 95, method="higher"))
    if lo == hi:
        return lo
    if math.isinf(lo) and math.isinf(hi):
        return math.nan
    if math.isinf(lo) or math.isinf(hi):
        return lo if math.isinf(lo) else hi
    return float(np.percentile(x, 95))  # the infinities lie outside the pair


def summarize_metrics(metrics: Mapping[str, Any]) -> dict[str, dict]:
    """Summary statistics of per-run metrics.

    Args:
      metrics: name (with units, e.g. ``"pos_rmse_m"``) -> per-run values, shape
        ``(runs,)`` (a scalar counts as one run).

    Returns:
      ``{name: {"mean", "median", "p95", "max": float, "per_run": [float, ...]}}``.
      NaN propagates: if any run is NaN the four statistics are NaN.

    Raises:
      InputError: a metric is not one-dimensional or is empty.
    """
    if not isinstance(metrics, Mapping):
        raise InputError(f"metrics: expected a mapping of name -> per-run values, got {type(metrics).__name__}")
    out: dict[str, dict] = {}
    for name, values in metrics.items():
        x = _per_run(values, name)
        if x.ndim == 0:
            x = x.reshape(1)
        if x.ndim != 1:
            raise InputError(f"metrics[{name!r}]: expected per-run values of shape (runs,), got {x.shape}")
        if x.size == 0:
            raise InputError(f"metrics[{name!r}]: no values")
        if np.isnan(x).any():
            stats = dict(mean=math.nan, median=math.nan, p95=math.nan, max=math.nan)
        else:
            stats = dict(
                mean=float(np.mean(x)),
                median=float(np.median(x)),
                p95=_p95(x),
                max=float(np.max(x)),
            )
        out[str(name)] = {**stats, "per_run": [float(v) for v in x]}
    return out


def run_json(scenario_name: str, runs: int, seed: int, dtype, result) -> dict:
    """The ``run`` JSON (docs/cli.md) for a :class:`~jaxslam.sim.scenarios.registry.ScenarioResult`.

    Keys, in order: ``scenario, runs, seed, dtype, config, metrics, consistency``
    (omitted if ``result.consistency`` is None)``, flags, timing`` (``compile_s, run_s,
    runs_per_s``)``, versions`` (``jaxslam, jax``), then the sections of ``result.extra``.
    An interrupted batch (``result.interrupted``) has ``runs`` = the finished runs (what
    every summary is over), ``runs_requested`` and ``"interrupted": true`` after ``runs``.

    The returned dict may hold NaN floats (a diverged run); :func:`write_json`
    writes them as ``null``.

    Raises:
      ValueError: ``result.extra`` reuses a standard key (a scenario bug).
    """
    import jax  # the JSON records the JAX version; callers of run_json already run JAX

    import jaxslam

    timing = {k: float(v) for k, v in dict(result.timing).items()}
    compile_s = timing.pop("compile_s", math.nan)
    run_s = timing.pop("run_s", math.nan)
    interrupted = bool(result.interrupted)
    requested = int(runs)
    if interrupted:  # the summaries are over the finished runs only
        runs = min((len(np.atleast_1d(v)) for v in dict(result.metrics).values()), default=0)
    runs_per_s = runs / run_s if run_s > 0 else math.nan
    out: dict[str, Any] = {
        "scenario": str(scenario_name),
        "runs": int(runs),
        **({"runs_requested": requested, "interrupted": True} if interrupted else {}),
        "seed": int(seed),
        "dtype": np.dtype(dtype).name,
        "config": to_jsonable(dict(result.config), nonfinite_to_none=False),
        "metrics": summarize_metrics(result.metrics),
    }
    if result.consistency is not None:
        out["consistency"] = to_jsonable(dict(result.consistency), nonfinite_to_none=False)
    out["flags"] = {str(k): int(v) for k, v in dict(result.flags).items()}
    out["timing"] = {"compile_s": compile_s, "run_s": run_s, "runs_per_s": runs_per_s, **timing}
    out["versions"] = {"jaxslam": jaxslam.__version__, "jax": jax.__version__}
    for key, value in dict(result.extra).items():
        if key in out or key in RUN_JSON_KEYS:
            raise ValueError(f"ScenarioResult.extra reuses the standard run JSON key {key!r}")
        out[str(key)] = to_jsonable(value, nonfinite_to_none=False)
    return out


def to_jsonable(obj: Any, nonfinite_to_none: bool = True) -> Any:
    """Plain-Python copy of ``obj`` for :func:`json.dump`.

    NumPy / JAX scalars and arrays become numbers and (nested) lists, tuples
    become lists, paths and dtypes become strings, dataclasses and NamedTuples
    become dicts, and (if ``nonfinite_to_none``) non-finite floats become ``None``
    (JSON ``null``).

    Mapping keys become ``str(key)``; two keys of one mapping that would become the same
    string (``1`` and ``"1"``) are refused rather than one of them being lost.

    Raises:
      TypeError: an object with no JSON form (complex numbers, arbitrary classes).
      InputError: two keys of a mapping have the same string form.
    """
    rec = lambda v: to_jsonable(v, nonfinite_to_none)  # noqa: E731
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) or not nonfinite_to_none else None
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return rec(float(obj))
    if isinstance(obj, np.complexfloating):
        raise TypeError(f"cannot write complex value {obj!r} to JSON")
    if isinstance(obj, np.dtype):
        return obj.name
    if isinstance(obj, type):
        return np.dtype(obj).name if issubclass(obj, np.generic) else obj.__name__
    if isinstance(obj, pathlib.PurePath):
        return str(obj)
    if isinstance(obj, Mapping):
        out, first = {}, {}
        for k, v in obj.items():
            name = str(k)
            if name in first:
                raise InputError(f"obj: keys {first[name]!r} and {k!r} of one mapping are both written as "
                                 f"the JSON key {name!r} (one would be lost)")
            first[name] = k
            out[name] = rec(v)
        return out
    if hasattr(obj, "_asdict"):  # NamedTuple
        return {k: rec(v) for k, v in obj._asdict().items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: rec(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [rec(v) for v in obj]
    if hasattr(obj, "__array__") or isinstance(obj, np.ndarray):  # jax.Array, np.ndarray
        arr = np.asarray(obj)
        if arr.ndim == 0:
            return rec(arr.item())
        return [rec(v) for v in arr.tolist()]
    raise TypeError(f"cannot write object of type {type(obj).__name__} to JSON")


def _dumps(obj, level: int = 0) -> str:
    """Indented strict JSON with lists of scalars on one line (``per_run`` stays compact)."""
    pad, inner = "  " * level, "  " * (level + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list) and any(isinstance(v, (dict, list)) for v in obj):
        return "[\n" + ",\n".join(inner + _dumps(v, level + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def write_json(path, obj) -> pathlib.Path:
    """Write ``obj`` as indented, strict JSON (non-finite -> ``null``); create parent folders.

    Returns:
      The path written.

    Raises:
      InputError: the file or its folder cannot be written.
    """
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise InputError(f"path: expected a file path, got {path!r}")
    path = pathlib.Path(path)
    text = _dumps(to_jsonable(obj)) + "\n"
    try:
        atomic_write(path, lambda f: f.write(text))  # never leave a half-written JSON behind
    except OSError as e:  # (first: atomic_write's failed write is an InputError and an OSError)
        raise InputError(f"path: cannot write JSON to {str(path)!r}: {e.strerror or e}") from None
    except ValueError as e:  # an InputError (a file where a folder is due: files.atomic_write says
        # which), or Python's own for a NUL byte in the path ("embedded null byte")
        raise InputError(f"path: cannot write JSON to {str(path)!r}: {str(e).removeprefix('path: ')}") from None
    return path


def _fmt_num(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 1e-3):
        return f"{x:.4g}"
    return f"{x:.4f}"


def format_table(summary: Mapping[str, Mapping[str, Any]]) -> str:
    """Aligned text table of a :func:`summarize_metrics` result.

    Columns: metric, mean, median, p95, max (one row per metric).  Metrics with
    non-finite runs get a note line below the table naming how many.
    """
    header = ("metric", "mean", "median", "p95", "max")
    if not isinstance(summary, Mapping):
        raise InputError(f"summary: expected a summarize_metrics result (mapping), got {type(summary).__name__}")
    for name, s in summary.items():
        missing = [k for k in header[1:] if not isinstance(s, Mapping) or k not in s]
        if missing:
            raise InputError(f"summary[{name!r}]: missing {', '.join(missing)} (expected a summarize_metrics result)")
    rows = [header]
    notes = []
    for name, s in summary.items():
        rows.append((str(name),) + tuple(_fmt_num(s[k]) for k in ("mean", "median", "p95", "max")))
        per_run = s.get("per_run", [])
        bad = sum(1 for v in per_run if v is None or not math.isfinite(v))
        if bad:
            notes.append(f"note: {name}: {bad} of {len(per_run)} runs non-finite")
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = []
    for j, r in enumerate(rows):
        cells = [r[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(r[1:], widths[1:])]
        lines.append("  ".join(cells).rstrip())
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines + notes)


def machine_info() -> dict:
    """Host description for benchmark JSON: OS, CPU, cores, Python, NumPy, JAX backend."""
    info = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "xla_flags": os.environ.get("XLA_FLAGS"),
    }
    try:
        import jax

        info["jax"] = jax.__version__
        info["jax_backend"] = jax.default_backend()
        info["devices"] = [str(d) for d in jax.devices()]
    except Exception as e:  # a benchmark JSON without JAX details beats no JSON
        info["jax_error"] = f"{type(e).__name__}: {e}"
    return info
