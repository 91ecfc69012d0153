"""Real-data runs behind ``jaxslam dataset``: load → event log → one jitted scan → evaluation.

Each runner loads a dataset with its loader (:mod:`jaxslam.data`), merges the
streams into an :class:`~jaxslam.data.events.EventLog`, runs a system module's
``run`` (one ``lax.scan`` over the whole log), and evaluates the estimate
against the reference with :mod:`jaxslam.metrics`:

* ``ate_m``: position RMSE after the least-squares rigid alignment (Umeyama,
  SE(2) for planar logs, SE(3) for the UWB flight) over the samples where the
  reference exists (ground truth is interpolated linearly at estimate times,
  never extrapolated; GPS is compared at its own fix times);
* ``rpe_m`` / ``rpe_deg``: the pose RPE over 1 s (Sturm et al.) on a 10 Hz
  resampling of both trajectories, where headings exist; otherwise (GPS, UTIL
  positions) the translational RPE over pairs of samples 1 ± 0.1 s apart;
* ``map_err_m``: landmark position RMSE by id, in the trajectory's ATE frame
  (known maps only);
* ``dead_reckoning_ate_m``: the same ATE for the noise-free motion model
  integrated from the same start over the same events.

Timing: the run is called twice; ``run_s`` is the second call (from the jit
cache, ``block_until_ready``), ``compile_s`` the first call's extra time;
``load_s`` is parsing and event merging.
"""

from __future__ import annotations

import functools
import time
import types
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import metrics
from . import catalogue
from .events import merge_events
from ..dynamics._checks import real_numbers
from ..errors import InputError, check_run_dtype
from ..linalg import check_flag, check_int, check_scalar, reworded, to_jax
from ..paramfile import check_dataset_sections

__all__ = ["DatasetRun", "run_dataset", "to_json", "timed_run", "dead_reckoning", "evaluate_planar"]


class DatasetRun(NamedTuple):
    """Outcome of one real-data run (host-side NumPy / Python values).

    dataset: name; config: every setting used (JSON-ready); metrics: figures
    with units in their names; counts: measurements read / used / gated /
    rejected / registered; timing: load_s, compile_s, run_s; report: the
    loader's counts; evaluation: arrays for the plots (reference frame);
    trajectory: (t, positions, yaw or None) for TUM export; notes: caveats.
    """

    dataset: str
    config: dict
    metrics: dict
    counts: dict
    timing: dict
    report: dict
    evaluation: dict
    trajectory: tuple
    notes: list


def timed_run(fn: Callable, twice: bool = True):
    """Call ``fn()`` (a jitted run) twice: ``(out, compile_s, run_s)``.

    The first call compiles and runs, the second (the same program, from the
    jit cache) only runs; ``run_s`` is the second call with
    ``block_until_ready`` and ``compile_s`` the difference.  With
    ``twice=False`` (runs of minutes) the single call's time is ``run_s`` and
    ``compile_s`` is NaN (not separated).
    """
    if not callable(fn):
        raise InputError(f"fn: expected a callable (a jitted run taking no arguments), got {fn!r}"[:300])
    twice = check_flag(twice, "twice")
    t0 = time.perf_counter()
    if not twice:
        out = jax.block_until_ready(fn())
        return out, float("nan"), time.perf_counter() - t0
    jax.block_until_ready(fn())
    t1 = time.perf_counter()
    out = jax.block_until_ready(fn())
    t2 = time.perf_counter()
    return out, max(t1 - t0 - (t2 - t1), 0.0), t2 - t1


def dead_reckoning(motion, pose0, u, dt):
    """Noise-free integration of ``motion(s, u_k, dt_k)`` over an event log; (T, n) poses.

    ``u``: (T, m) inputs and ``dt``: (T,) steps, one per event (other shapes are an
    :class:`InputError` naming them).  jaxslam's own motion models (a module-level function
    of the package, or a ``functools.partial`` of one) run as one jitted program per model and
    shape: a second call compiles nothing.  Any other ``motion`` (a user's function, a lambda,
    a callable object) is traced at every call, so a change of what it reads (a global, a
    closure, its state) is always seen and nothing is kept for it."""
    if not callable(motion):
        raise InputError(f"motion: expected a callable motion(s, u, dt), got {motion!r}"[:300])
    if np.ndim(u) != 2:
        raise InputError(f"u: expected shape (T, m) (one input row per event), got {np.shape(u)}")
    if np.shape(dt) != (np.shape(u)[0],):
        raise InputError(f"dt: expected shape ({np.shape(u)[0]},) (one step per row of u), got {np.shape(dt)}")

    args = (to_jax(pose0), to_jax(u), to_jax(dt))
    if _own_motion(motion):  # (the eager scan compiled again at every call)
        return _dead_reckoning_jit(motion, *args)
    # a jit keyed on a user's function would serve a stale program when what it reads changes,
    # and keep one program (with the function) per fresh lambda: traced every call instead
    return _dead_reckoning_scan(motion, *args)


def _own_motion(motion) -> bool:
    """True for a pure motion model of this package: a module-level ``jaxslam`` function without
    a closure, or a ``functools.partial`` of one (the jit's key is the object itself)."""
    f = motion.func if isinstance(motion, functools.partial) else motion
    return (isinstance(f, types.FunctionType) and f.__closure__ is None
            and (f.__module__ or "").startswith("jaxslam.") and "<locals>" not in f.__qualname__
            and f.__name__ != "<lambda>")


def _dead_reckoning_scan(motion, pose0, u, dt):
    def body(s, inp):
        s = motion(s, inp[0], inp[1])
        return s, s

    _, poses = jax.lax.scan(body, pose0, (u, dt))
    return poses


_dead_reckoning_jit = jax.jit(_dead_reckoning_scan, static_argnums=0)


def _ackermann_motion(geom):
    """``planar.ackermann`` with the car's ``geom`` as a motion for :func:`dead_reckoning`.

    An :class:`~jaxslam.dynamics.planar.AckermannGeometry` of Python floats (the loader's) gets
    one cached ``functools.partial`` per geometry, so the jitted dead reckoning is compiled once
    per geometry, not per run.  The cache is keyed on the floats' exact bits: keyed on the
    geometry itself it served the partial of an *equal* geometry of other types (NumPy float64
    fields equal Python floats, ``-0.0`` equals ``0.0``, a plain tuple equals the NamedTuple),
    whose constants then set the dtypes of the run.  Any other geometry gets a plain function,
    traced at each call (nothing kept for it)."""
    from ..dynamics import planar

    if type(geom) is planar.AckermannGeometry and all(type(v) is float for v in geom):
        return _ackermann_partial(tuple(v.hex() for v in geom))
    return lambda s, u, dt: planar.ackermann(s, u, dt, geom)


@functools.lru_cache(maxsize=8)
def _ackermann_partial(bits: tuple):
    """The cached partial of :func:`_ackermann_motion`, for the geometry whose fields are the
    floats ``bits`` (``float.hex``: -0.0 and 0.0 differ)."""
    from ..dynamics import planar

    return functools.partial(planar.ackermann, geom=planar.AckermannGeometry(*map(float.fromhex, bits)))


def rpe_pairs(t, est, ref, lag_s: float = 1.0, tol_s: float = 0.1):
    """Translational RPE over pairs of samples ``lag_s ± tol_s`` apart (no interpolation).

    Each sample i is paired with the sample j nearest to ``t[i] + lag_s`` (the later one on a
    tie), kept when ``|t[j] - t[i] - lag_s| <= tol_s``.  For references sampled with gaps (GPS,
    a subset of a flight): a pair never spans a gap.  ``t``: (N,) finite, non-decreasing times
    [s]; ``est``, ``ref``: (N, d) positions; ``lag_s`` > 0 and 0 <= ``tol_s`` < ``lag_s`` (so a
    sample is never its own partner).  Returns ``(rpe [m], number of pairs)``; (NaN, 0) without
    any pair.  Bad arguments are an :class:`InputError` naming them.
    """
    lag = check_scalar(lag_s, "lag_s", lower=0, strict=True)
    tol = check_scalar(tol_s, "tol_s", lower=0)
    if not tol < lag:
        raise InputError(f"tol_s: expected less than lag_s ({lag:g}: a sample would pair with itself), got {tol_s!r}")
    t = _times(t, "t")
    est = _rows(est, "est", t.size)
    ref = _rows(ref, "ref", t.size, est.shape[1])
    if t.size == 0:
        return float("nan"), 0
    target = t + lag
    after = np.minimum(np.searchsorted(t, target), t.size - 1)  # first sample at/after t + lag (or the last)
    before = np.maximum(after - 1, 0)
    j = np.where(np.abs(t[after] - target) <= np.abs(t[before] - target), after, before)
    i = np.nonzero(np.abs(t[j] - target) <= tol)[0]
    j = j[i]
    if i.size == 0:
        return float("nan"), 0
    de = (est[j] - est[i]) - (ref[j] - ref[i])
    return float(np.sqrt(np.mean(np.sum(de ** 2, 1)))), int(i.size)


def _times(t, name: str) -> np.ndarray:
    """``t`` as a 1-D float64 array of finite, non-decreasing times, else :class:`InputError`
    naming ``name``."""
    t = real_numbers(t, name)
    if t.ndim != 1:
        raise InputError(f"{name}: expected a 1-D array of times, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: expected finite times, got NaN or Inf")
    if np.any(np.diff(t) < 0):
        raise InputError(f"{name}: expected non-decreasing times (sorted), got a step back at index "
                         f"{int(np.argmax(np.diff(t) < 0)) + 1}")
    return t


def _rows(a, name: str, n=None, width=None, widths=None) -> np.ndarray:
    """``a`` as a 2-D float64 array of ``n`` rows (None: any) of ``width`` columns (or one of
    ``widths``; None: any), else :class:`InputError` naming ``name``."""
    a = real_numbers(a, name)
    ok = a.ndim == 2 and (n is None or a.shape[0] == n)
    if ok and width is not None:
        ok = a.shape[1] == width
    if ok and widths is not None:
        ok = a.shape[1] in widths
    if not ok:
        cols = (str(width) if width is not None else " or ".join(map(str, widths)) if widths is not None else "d")
        raise InputError(f"{name}: expected shape ({'N' if n is None else n}, {cols}), got {a.shape}")
    return a


def evaluate_planar(t_est, est_pose, t_ref, ref, dr_pose=None, lm=None, lm_ids=None, lm_cov=None,
                    lm_true=None, lm_true_ids=None, ref_label="ground truth", at_ref_times=False):
    """ATE/RPE/map error of a planar estimate against a reference (host side).

    ``t_est`` (T,) and ``t_ref`` (N,): finite, non-decreasing times; ``est_pose`` (and
    ``dr_pose``) (T, 3) poses or (T, 2) positions; ``ref`` is (N, 3) poses or (N, 2) positions
    (GPS).  Against poses (``ref`` (N, 3)) ``est_pose`` must be poses too: the RPE compares
    headings.  With ``at_ref_times`` the estimate is interpolated at the reference times (sparse
    GPS fixes); otherwise the reference is interpolated at the estimate times inside its
    span.  Either way, reference rows holding NaN or Inf are left out (one NaN heading no
    longer cuts the evaluation at that row).  Returns ``(metrics dict, evaluation dict)`` with everything moved
    into the reference frame by the estimate's alignment.  An estimate that is NaN or Inf at
    some of the evaluated samples (a filter that lost finiteness) leaves the figures NaN and
    is counted in ``nonfinite_estimate_samples`` (absent when there is none).  Arrays of the
    wrong shape, and landmark ids the map error cannot pair (missing with ``lm`` and ``lm_true``
    both given, fractional, repeated), are an :class:`InputError` naming them (``lm_ids``,
    ``lm_true_ids``).
    """
    t_est = _times(t_est, "t_est")
    if t_est.size == 0:
        raise InputError("t_est: expected at least one estimate time, got none")
    est_pose = _rows(est_pose, "est_pose", t_est.size, widths=(2, 3))
    t_ref = _times(t_ref, "t_ref")
    ref = _rows(ref, "ref", t_ref.size, widths=(2, 3))
    if ref.shape[1] == 3 and est_pose.shape[1] != 3:  # (the RPE's error named no argument)
        raise InputError(f"est_pose: expected shape ({t_est.size}, 3) (poses: ref holds poses, (N, 3), and "
                         f"the RPE compares headings), got {est_pose.shape}")
    if dr_pose is not None:
        dr_pose = _rows(dr_pose, "dr_pose", t_est.size, widths=(2, 3))
    at_ref_times = check_flag(at_ref_times, "at_ref_times")
    if lm is not None:
        lm = _rows(lm, "lm", width=2) if np.size(lm) else None
    if lm is not None:
        if lm_ids is not None and np.shape(lm_ids) != (lm.shape[0],):
            raise InputError(f"lm_ids: expected one id per row of lm ({lm.shape[0]},), got shape {np.shape(lm_ids)}")
        if lm_cov is not None:
            lm_cov = real_numbers(lm_cov, "lm_cov")
        if lm_cov is not None and np.shape(lm_cov) != (lm.shape[0], 2, 2):
            raise InputError(f"lm_cov: expected shape ({lm.shape[0]}, 2, 2) (one per row of lm), got "
                             f"{np.shape(lm_cov)}")
    if lm_true is not None:
        lm_true = _rows(lm_true, "lm_true", width=2)
        if lm_true_ids is not None and np.shape(lm_true_ids) != (lm_true.shape[0],):
            raise InputError(f"lm_true_ids: expected one id per row of lm_true ({lm_true.shape[0]},), got "
                             f"shape {np.shape(lm_true_ids)}")
    has_heading = ref.shape[1] == 3
    if at_ref_times:
        keep = (t_ref >= t_est[0]) & (t_ref <= t_est[-1]) & np.all(np.isfinite(ref), axis=1)
        t = t_ref[keep]
        r = ref[keep]
        e = metrics.interp_poses(t, t_est, est_pose)
        d = metrics.interp_poses(t, t_est, dr_pose) if dr_pose is not None else None
    else:
        fin = np.all(np.isfinite(ref), axis=1)
        if not fin.all():  # (an all-finite reference is used as it is)
            t_ref, ref = t_ref[fin], ref[fin]
        if t_ref.size == 0:
            raise InputError("evaluation: fewer than 3 samples where estimate and reference overlap")
        r = metrics.interp_poses(t_est, t_ref, ref) if has_heading else np.stack(
            [np.interp(t_est, t_ref, ref[:, j], left=np.nan, right=np.nan) for j in range(2)], 1)
        keep = np.all(np.isfinite(r), axis=1)
        t, r, e = t_est[keep], r[keep], est_pose[keep]
        d = np.asarray(dr_pose, np.float64)[keep] if dr_pose is not None else None
    if t.size < 3:
        raise InputError("evaluation: fewer than 3 samples where estimate and reference overlap")
    R, tr, _ = metrics.umeyama(e[:, :2], r[:, :2])
    R, tr = np.asarray(R), np.asarray(tr)
    e_al = e[:, :2] @ R.T + tr
    out = {"ate_m": float(np.sqrt(np.mean(np.sum((e_al - r[:, :2]) ** 2, 1)))),
           "eval_samples": int(t.size)}
    n_bad = int(np.sum(~np.all(np.isfinite(e[:, :2]), axis=1)))
    if n_bad:  # said, not only a NaN ATE: the caller's notes name it (_nonfinite_notes)
        out["nonfinite_estimate_samples"] = n_bad
    # RPE over 1 s: poses on a 10 Hz grid; positions-only references (GPS, with gaps) over
    # pairs of samples 1 ± 0.1 s apart, never across an interpolated gap.
    if has_heading:
        grid = np.arange(t[0], t[-1], 0.1)
        if grid.size > 12:
            rt, rr = metrics.rpe_se2(metrics.interp_poses(grid, t, e), metrics.interp_poses(grid, t, r), lag=10)
            out["rpe_m"] = float(rt)
            out["rpe_deg"] = float(np.degrees(rr))
    else:
        rpe, n_pairs = rpe_pairs(t, e[:, :2], r[:, :2])
        if n_pairs:
            out["rpe_m"], out["rpe_pairs"] = rpe, n_pairs
    dr_al = None
    if d is not None:
        Rd, td, _ = metrics.umeyama(d[:, :2], r[:, :2])
        dr_al = d[:, :2] @ np.asarray(Rd).T + np.asarray(td)
        out["dead_reckoning_ate_m"] = float(np.sqrt(np.mean(np.sum((dr_al - r[:, :2]) ** 2, 1))))
    ev = {"t": t, "est_xy": e_al, "ref_xy": r[:, :2], "ref_label": ref_label, "dr_xy": dr_al,
          "est_path_xy": est_pose[:, :2] @ R.T + tr,
          "frame_note": f"estimate aligned to {ref_label} (SE(2) least squares)"}
    if lm is not None:
        ev["lm_xy"] = lm @ R.T + tr
        if lm_cov is not None:
            ev["lm_cov"] = np.einsum("ij,njk,lk->nil", R, np.asarray(lm_cov, np.float64), R)
        if lm_true is not None:
            me = metrics.map_error(lm, lm_ids, lm_true, lm_true_ids, transform=(R, tr),
                                   names=("lm", "lm_ids", "lm_true", "lm_true_ids"))
            out["map_err_m"] = me.rmse
            out["map_err_max_m"] = me.max
            out["landmarks_compared"] = int(me.ids.size)
    if lm_true is not None:
        ev["lm_true_xy"] = np.asarray(lm_true)
    ev["transform"] = (R, tr)
    return out, ev


_RUNNERS: dict = {}


def _register(name):
    def deco(fn):
        _RUNNERS[name] = fn
        return fn

    return deco


def run_dataset(name: str, data_dir, **options) -> DatasetRun:
    """Run dataset ``name`` (``mrclam``, ``victoria-park``, ``util-uwb``, ``plaza``) from ``data_dir``.

    Options (:data:`jaxslam.data.catalogue.OPTION_DEFAULTS`): robot, filter ("ekf" |
    "fastslam"), ids, anchors, tof, calibrated, particles, seed, params, and dtype.  An option
    set away from its default for a dataset it does not apply to is an :class:`InputError`
    (never silently ignored; :func:`jaxslam.data.catalogue.check_options`).  ``dtype``: float32
    or float64 (float64 only with JAX's x64 mode on, else an :class:`InputError`: it would
    compute in float32); left out, the dtype JAX computes in (float64 with x64 on, else float32).
    """
    if not isinstance(name, str) or name not in _RUNNERS:
        raise InputError(f"dataset: unknown name {name!r} (choose from {', '.join(sorted(_RUNNERS))})")
    catalogue.check_options(name, {k: v for k, v in options.items() if k != "dtype"})
    kw = {**catalogue.OPTION_DEFAULTS, **options}
    if kw["params"] is None:  # only the runners that read a --params file take the argument
        del kw["params"]
    return _RUNNERS[name](data_dir, **kw)


def dataset_params(obj, name: str) -> dict:
    """The ``noise`` entries of a ``--params`` object for dataset ``name`` (validated keys).

    The object is ``{"dataset": NAME, "noise": {...}}`` (``jaxslam tune NAME`` writes it, alone
    with ``--params-out`` or inside its report with ``--json``).  A file for another dataset, a
    missing ``dataset``/``noise`` entry or an unknown top-level key is an :class:`InputError`
    naming it; the ``noise`` keys are checked by the system's ``params_from_dict``.
    """
    check_dataset_sections(obj, name)
    if name in ("util-uwb", "plaza"):  # every key and value checked before any log is read
        from . import presets

        (presets.util_params_from_dict if name == "util-uwb" else presets.plaza_params_from_dict)(obj["noise"])
        return obj["noise"]
    from ..systems.planar_ekf_slam import Params, check_matrices, check_thresholds, params_from_dict
    from . import presets

    unknown = sorted(set(obj["noise"]) - set(Params._fields), key=str)
    if unknown:
        raise InputError(f"--params: noise: unknown key(s) {unknown}; expected some of {list(Params._fields)}")
    check_thresholds(obj["noise"], "--params: noise")  # gates, limits, pruning: before any log is read or compiled
    check_matrices(obj["noise"], "--params: noise")  # shapes and definiteness, likewise
    # every value (range_model, robust_nu, calib0, ...) against the run's preset, likewise
    dtype = _run_dtype(None)
    base = (presets.mrclam_params(dtype=dtype) if name == "mrclam" else presets.victoria_park_params(dtype=dtype))
    params_from_dict(obj["noise"], base, dtype=dtype, where="--params: noise")
    return obj["noise"]


#: ``"log"`` entries of a dataset ``--params`` file: how the log was built for the noise it holds.
LOG_OPTIONS = {"mrclam": {"odometry_delay": (0.0, 2.0)}}


def dataset_log_options(obj, name: str) -> dict:
    """The ``"log"`` entries of a (validated, :func:`dataset_params`) ``--params`` object.

    A file without them was fitted on the log as stamped: ``{}``.  An entry the dataset does not
    have, or a value outside its range, is an :class:`InputError` naming it.
    """
    if not isinstance(obj, dict):
        raise InputError(f"--params: expected a JSON object, got {type(obj).__name__}")
    opts = obj.get("log", {})
    if not isinstance(opts, dict):
        raise InputError(f"--params: key 'log' must be an object, got {type(opts).__name__}")
    allowed = LOG_OPTIONS.get(name, {})
    unknown = sorted(set(opts) - set(allowed), key=str)
    if unknown:
        raise InputError(f"--params: log: unknown key(s) {unknown}; {name} takes "
                         f"{sorted(allowed) or 'none'}")
    out = {}
    for k, (lo, hi) in allowed.items():
        if k in opts:
            v = opts[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (lo <= float(v) <= hi):
                raise InputError(f"--params: log.{k}: expected a number in [{lo:g}, {hi:g}], got {v!r}")
            out[k] = float(v)
    return out


def to_json(run: DatasetRun) -> dict:
    """The ``dataset`` JSON (docs/cli.md).

    A dict whose non-finite figures stay floats (NaN, e.g. ``timing.compile_s`` of a run timed
    once): write it with :func:`jaxslam.io.write_json`, which writes them as ``null``
    (``json.dumps`` would write the non-JSON token ``NaN``).
    """
    from .. import __version__

    return {
        "dataset": run.dataset,
        "config": run.config,
        "metrics": run.metrics,
        "counts": run.counts,
        "timing": run.timing,
        "loader_report": run.report,
        "notes": run.notes,
        "versions": {"jaxslam": __version__, "jax": jax.__version__},
    }


def _counts_common(status, extra: dict) -> dict:
    from ..errors import decode

    out = {k: int(v) for k, v in extra.items()}
    out["status_flags"] = ",".join(decode(status)) or "none"
    return out


def _class_fractions(counts: dict) -> dict:
    """Per landmark class, the fraction of rows cut off or disbelieved (EKF runs).

    mapped: rows of landmarks already in the map — ``outlier_fraction_mapped`` (d² beyond the
    χ²(2) 99 % gate; more than 10 % sets DIVERGED) and ``gated_fraction_mapped`` (cut off by a
    hard gate, if the run has one); new: first sightings — ``rejected_fraction_new`` (not
    registered: ambiguous, or a second row of the same id in one frame).
    """
    if "mapped_rows" not in counts:
        return {}
    new = max(counts["registered"] + counts["rejected"], 1)
    return {**_mapped_fractions(counts), "rejected_fraction_new": counts["rejected"] / new}


def _mapped_fractions(counts: dict) -> dict:
    """outlier_fraction_mapped and gated_fraction_mapped of :func:`_class_fractions`."""
    rows = max(counts["mapped_rows"], 1)
    return {"outlier_fraction_mapped": counts["mapped_outliers"] / rows,
            "gated_fraction_mapped": min(counts["gated"], counts["mapped_rows"]) / rows}


def _divergence_notes(status, rows="the sightings of mapped landmarks", gate="the chi2(2) 99 % gate") -> list:
    from ..errors import DIVERGED

    if int(status) & DIVERGED:
        return [f"DIVERGED: more than 10 % of {rows} were outliers (beyond {gate}): the run stopped being "
                "consistent with its noise model"]
    return []


def _range_outliers(res, counts: dict, m: dict, notes: list) -> None:
    """The range-only runs' outlier counts (rows of mapped anchors/beacons whose d² exceeds the
    range model's own 99 % quantile), their fractions, and the DIVERGED note."""
    counts["mapped_rows"] = int(np.sum(np.asarray(res.n_monitored)))
    counts["mapped_outliers"] = int(np.sum(np.asarray(res.n_outliers)))
    m.update(_mapped_fractions(counts))
    notes.extend(_divergence_notes(res.status, "the ranges of mapped anchors",
                                   "the range model's own 99 % quantile"))


def _run_dtype(dtype):
    """The run's dtype: ``None`` gives what JAX computes in (float64 with its x64 mode on, else
    float32); otherwise float32 or float64, float64 only with x64 on (it computed in float32
    while the report said float64): else :class:`InputError` naming ``dtype`` (the
    scenarios' rule, :func:`jaxslam.errors.check_run_dtype`)."""
    if dtype is None:
        return np.dtype(jax.dtypes.canonicalize_dtype(np.float64))
    return check_run_dtype(dtype)


def _nonfinite_notes(m: dict, what: str = "estimate") -> list:
    """A note when the evaluated estimate holds NaN or Inf (``nonfinite_estimate_samples`` of
    :func:`evaluate_planar`): its figures are then NaN, said rather than left to read as a number."""
    n = int(m.get("nonfinite_estimate_samples", 0))
    if not n:
        return []
    return [f"the {what} is NaN or Inf at {n} of the {m.get('eval_samples', '?')} evaluated samples: its error "
            "figures are NaN (status_flags says whether the filter flagged it)"]


def _config(name, filter, dtype, setting, **kw):
    return {"dataset": name, "filter": filter, "dtype": np.dtype(dtype).name, "setting": setting, **kw}


# ---------------------------------------------------------------------------
# UTIL UWB (range-only, 3D)
# ---------------------------------------------------------------------------

SMOOTHER_RTS = ("RTS over the EKF run: the robot trajectory smoothed backwards with the map held "
                "static (jaxslam.filters.ekf_slam.smooth_robot)")


def _smooth_config(smooth, what):
    """The config entries of ``--smooth`` (none without it, so the JSON is unchanged)."""
    return {"smooth": True, "smoother": what} if smooth else {}


def _add_smoothed(m, ev, ms, evs):
    """Put the smoother's figures beside the filter's: ``smoothed_<metric>`` keys, plot arrays."""
    for k in ("ate_m", "rpe_m", "rpe_deg", "pos_rmse_m", "pos_rmse_whole_m"):
        if k in ms:
            m["smoothed_" + k] = ms[k]
    ev["smooth_xy"] = evs["est_xy"]
    ev["smooth_path_xy"] = evs.get("est_path_xy", evs["est_xy"])


@_register("util-uwb")
def run_util_uwb(data_dir, robot=1, filter="ekf", ids="known", anchors=None, particles=None,
                 seed=0, dtype=None, tof=False, t_window=30.0, calibrated=False, smooth=False,
                 params=None):
    """UTIL TWR flight: constant-velocity range-only EKF with a bias state (``systems.util_range``).

    ``anchors``: "known" (default, surveyed) or "unknown" (SLAM after a start-up
    window); ``tof``: also use the downward laser height (then not range-only).  Noise: the
    fitted preset (``presets.UTIL_FITTED``, ``jaxslam tune util-uwb``); ``params``: a
    ``--params`` object replacing it.  ``t_window``: the start-up window of ``anchors="unknown"``
    [s], a positive finite number (else an :class:`InputError` naming it, before any file is read).
    """
    # (as run_dataset does: called directly, a misspelt choice ran as another method or was ignored)
    catalogue.check_options("util-uwb", dict(robot=robot, filter=filter, ids=ids, anchors=anchors,
                                             particles=particles, seed=seed, tof=tof, calibrated=calibrated,
                                             smooth=smooth, params=params))
    dtype = _run_dtype(dtype)
    if isinstance(t_window, (bool, np.bool_)):  # (True ran a 1 s window)
        raise InputError(f"t_window: expected a positive finite scalar, got {t_window!r}")
    t_window = check_scalar(t_window, "t_window", lower=0, strict=True)
    anchors = anchors or "known"
    from ..systems import util_range as ur
    from . import presets
    from .util_uwb import load_util, tag_positions

    prm = (presets.util_params() if params is None else
           presets.util_params_from_dict(dataset_params(params, "util-uwb")))

    t0 = time.perf_counter()
    d = load_util(data_dir, "twr_obs_log1")
    if np.size(d.twr_t) == 0:  # (--anchors unknown raised a bare IndexError; known named util_events)
        from .textfile import DataFormatError

        raise DataFormatError(f"{d.report['dir']}/uwb_twr.csv", None, "util-uwb: the flight has no two-way "
                              "ranges (uwb_twr.csv missing or without data rows): nothing to run")
    tag = tag_positions(d.gt_p, d.gt_q, d.tag_offset)
    load_s = time.perf_counter() - t0
    aid = np.asarray(d.anchor_id)
    hk = dict(tof_t=d.tof_t, tof=d.tof) if tof else {}
    if tof and np.size(d.tof_t) == 0:
        raise InputError("util-uwb: --tof given but the flight has no tof.csv")
    sensors = "ranges + ToF height" if tof else "ranges only"
    if anchors == "known":
        log = ur.util_events(d.twr_t, d.twr_anchor, d.twr_range, **hk)
        rlog = ur.log_from_events(log, aid, anchors=d.anchor_p, dtype=dtype)
        res, comp_s, run_s = timed_run(lambda: ur.run(rlog, ur.Config(smooth=smooth), prm))
        setting = f"known surveyed anchors, constant-velocity tag + common range bias ({sensors})"
        notes = []
    else:
        t_all = np.asarray(d.twr_t)
        # the window is measured from the flight's first whole second (of ranges or motion
        # capture; the shipped flight starts at 0.002 s: [0, 30] s), so a clock that starts
        # elsewhere is not refused
        w0 = float(np.floor(min(t_all[0], d.gt_t[0]))) if t_all.size else float(np.floor(d.gt_t[0]))
        t_end = w0 + t_window
        if not (d.gt_t[0] + 0.2 < t_end < min(d.gt_t[-1], t_all[-1]) - 1.0):
            raise InputError(f"util-uwb --anchors unknown: the {t_window:g} s start-up window [{w0:g}, {t_end:g}] s "
                             f"needs motion capture around its end and ranges after it; this flight has motion "
                             f"capture over [{d.gt_t[0]:.1f}, {d.gt_t[-1]:.1f}] s and ranges over "
                             f"[{t_all[0]:.1f}, {t_all[-1]:.1f}] s")
        in_win = (t_all <= t_end) & (t_all >= d.gt_t[0]) & (t_all <= d.gt_t[-1])
        per = {int(a): int(np.sum(np.asarray(d.twr_anchor)[in_win] == a)) for a in aid}
        few = sorted(a for a, n in per.items() if n < 10)
        if few:  # the start-up fits each anchor from its ranges in the window
            raise InputError(f"util-uwb --anchors unknown: anchors {few} have fewer than 10 ranges with motion "
                             f"capture in the start-up window [{w0:g}, {t_end:g}] s ({ {a: per[a] for a in few} }); "
                             "their positions cannot be fitted")
        # the start-up fits only ranges with motion capture (np.interp would hold the first
        # motion-capture position for ranges before it, as the window's count above leaves out)
        with_gt = t_all >= d.gt_t[0]
        t_all = t_all[with_gt]
        su_anchor = np.asarray(d.twr_anchor)[with_gt]
        su_range = np.asarray(d.twr_range)[with_gt]
        tag_at = np.stack([np.interp(t_all, d.gt_t, tag[:, j]) for j in range(3)], 1)
        # start velocity: central difference of the motion-capture tag over ±0.1 s
        v0 = np.array([(np.interp(t_end + 0.1, d.gt_t, tag[:, j]) - np.interp(t_end - 0.1, d.gt_t, tag[:, j]))
                       / 0.2 for j in range(3)])
        su = ur.startup(jnp.asarray(t_all, dtype), su_anchor.astype(int),
                        jnp.asarray(su_range, dtype), jnp.asarray(tag_at, dtype), aid, t_end,
                        v0=jnp.asarray(v0, dtype))
        log = ur.util_events(d.twr_t, d.twr_anchor, d.twr_range, t_start=t_end + 1e-9, **hk)
        rlog = ur.log_from_events(log, aid, startup=su, dtype=dtype)
        res, comp_s, run_s = timed_run(lambda: ur.run(rlog, ur.Config(smooth=smooth), prm))
        setting = (f"anchors unknown (SLAM); start-up: anchors + bias fitted to the ranges of "
                   f"[{w0:g}, {t_end:g}] s with motion-capture positions, then no motion capture "
                   f"({sensors})")
        notes = [f"motion capture is used in the start-up window [{w0:g}, {t_end:g}] s only; metrics cover "
                 f"t > {t_end:g} s"]
    t = np.asarray(log.t)
    true = np.stack([np.interp(t, d.gt_t, tag[:, j]) for j in range(3)], 1)
    est = np.asarray(res.pos, np.float64)
    # evaluate at range events (height-only events carry the same estimate, denser in z) inside
    # the motion capture's span: it is interpolated, never extrapolated
    rng_ev = np.any(log.mask & (log.ids >= 0), axis=1)
    in_gt = (t >= d.gt_t[0]) & (t <= d.gt_t[-1])
    n_out = int(np.sum(rng_ev & ~in_gt))
    rng_ev = rng_ev & in_gt
    t, true, est = t[rng_ev], true[rng_ev], est[rng_ev]
    air = (true[:, 2] > 0.3)
    if air.sum() < 3:
        raise InputError("util-uwb: fewer than 3 range events inside the motion capture's span while airborne "
                         f"(z > 0.3 m): nothing to evaluate (motion capture over [{d.gt_t[0]:.1f}, "
                         f"{d.gt_t[-1]:.1f}] s, ranges over [{log.t[0]:.1f}, {log.t[-1]:.1f}] s)")
    if n_out:
        notes.append(f"{n_out} range events lie outside the motion capture's span and are not evaluated "
                     "(check the files' clocks)")

    def position_metrics(est):
        err = np.linalg.norm(est - true, axis=1)
        R, tr, _ = metrics.umeyama(est[air], true[air])
        R, tr = np.asarray(R), np.asarray(tr)
        est_al = est @ R.T + tr
        out = {"pos_rmse_m": float(np.sqrt(np.mean(err[air] ** 2))),
               "pos_rmse_whole_m": float(np.sqrt(np.mean(err ** 2))),
               "ate_m": float(np.sqrt(np.mean(np.sum((est_al[air] - true[air]) ** 2, 1))))}
        n_bad = int(np.sum(~np.all(np.isfinite(est[air]), axis=1)))
        if n_bad:  # the figures are NaN: said (_nonfinite_notes), as evaluate_planar
            out["nonfinite_estimate_samples"] = n_bad
        rpe, n_pairs = rpe_pairs(t[air], est[air], true[air])
        if n_pairs:  # absent (not NaN) without a pair of samples 1 ± 0.1 s apart, as evaluate_planar
            out["rpe_m"], out["rpe_pairs"] = rpe, n_pairs
        return out, R, tr, est_al

    m, R, tr, est_al = position_metrics(est)
    notes += _nonfinite_notes({**m, "eval_samples": int(air.sum())})
    rp = {k: m.pop(k) for k in ("rpe_m", "rpe_pairs") if k in m}
    m.update(range_bias_m=float(res.bias_final), range_bias_sigma_m=float(res.bias_sigma), **rp)
    A = np.asarray(res.landmarks, np.float64)
    lid = np.asarray(res.landmark_ids)
    act = np.asarray(res.active)
    # the rows map_error compares: an anchor id of the survey and a finite position
    matched = int((np.isin(lid[act], aid) & np.all(np.isfinite(A[act]), axis=1)).sum()) if anchors == "unknown" else 0
    if anchors == "unknown" and matched < 3:  # a 3-D alignment needs three: said, the run kept
        notes.append(f"{matched} surveyed anchor(s) mapped: the anchor map error (aligned) needs 3, not computed")
    elif anchors == "unknown":
        names = ("the mapped anchors", "their ids", "the surveyed anchors", "the surveyed ids")
        me = metrics.map_error(A[act], lid[act], d.anchor_p, aid, names=names)
        raw = metrics.map_error(A[act], lid[act], d.anchor_p, aid, transform=(np.eye(3), np.zeros(3)), names=names)
        m["map_err_m"] = me.rmse
        m["map_err_max_m"] = me.max
        m["map_err_raw_m"] = raw.rmse
    n_h = int(np.sum(log.mask & (log.ids < 0)))
    counts = _counts_common(res.status, {"measurements": int(np.sum(log.mask)) - n_h, "used": res.n_used,
                                         "gated": res.n_gated, "rejected": 0,
                                         "registered": res.n_registered,
                                         # rows sharing a stamp beyond the log's K (1): never silent
                                         "dropped_beyond_K": log.stats["dropped_overflow"]})
    if tof:
        counts.update(height_measurements=n_h, height_used=int(res.n_height_used),
                      height_gated=int(res.n_height_gated))
    ev = {"t": t[air], "est_xy": est_al[air, :2], "ref_xy": true[air, :2],
          "ref_label": "motion capture (tag)", "dr_xy": None,
          "frame_note": "x-y view, estimate aligned to motion capture (SE(3))",
          "lm_xy": (A[act] @ R.T + tr)[:, :2] if anchors == "unknown" else None,
          "lm_true_xy": np.asarray(d.anchor_p)[:, :2], "lm_true_label": "surveyed anchors"}
    if smooth:
        sm = np.asarray(res.smoothed, np.float64)[:, :3][rng_ev]
        ms, _, _, sm_al = position_metrics(sm)
        _add_smoothed(m, ev, ms, {"est_xy": sm_al[air, :2]})
        counts["smoother_failed_steps"] = int(np.sum(np.asarray(res.smooth_status) != 0))
    notes.append("pos_rmse_m: no alignment (the anchors define the frame), airborne samples (z > 0.3 m)")
    _range_outliers(res, counts, m, notes)
    cfg = _config("util-uwb", "ekf", dtype, setting, anchors=anchors, tof=bool(tof), flight="twr_obs_log1",
                  **_smooth_config(smooth, SMOOTHER_RTS))
    cfg["noise"] = "--params file" if params is not None else (
        "learned: jaxslam tune util-uwb on the flight's first half (docs/datasets.md)")
    cfg["noise_values"] = presets.util_params_to_dict(prm)
    return DatasetRun("util-uwb", cfg,
                      m, counts, {"load_s": load_s, "compile_s": comp_s, "run_s": run_s},
                      dict(d.report), ev, (t, est, None), notes)


# ---------------------------------------------------------------------------
# CMU Plaza (range-only SLAM, 2D)
# ---------------------------------------------------------------------------

@_register("plaza")
def run_plaza_dataset(data_dir, robot=1, filter="ekf", ids="known", anchors=None, particles=None,
                      seed=0, dtype=None, tof=False, calibrated=False, smooth=False, params=None):
    """CMU Plaza 1/2 (``--robot`` picks the sequence): odometry + range-only SLAM with a bias state.

    ``anchors``: "unknown" (default: SLAM, beacons initialised by delayed
    trilateration) or "known" (localisation against the surveyed beacons).  Noise:
    ``presets.plaza_params()``; ``params``: a ``--params`` object (``jaxslam tune plaza``) replacing it.
    """
    catalogue.check_options("plaza", dict(filter=filter, ids=ids, anchors=anchors, particles=particles,
                                          seed=seed, tof=tof, calibrated=calibrated, smooth=smooth,
                                          params=params))  # (robot: checked below)
    dtype = _run_dtype(dtype)
    anchors = anchors or "unknown"
    from ..dynamics import planar
    from ..systems import plaza_range as pr
    from . import presets
    from .plaza import load_plaza

    prm = (presets.plaza_params() if params is None else
           presets.plaza_params_from_dict(dataset_params(params, "plaza")))

    robot = reworded(lambda: check_int(robot, "robot"),
                     f"plaza: --robot selects the sequence, 1 or 2 (got {robot!r})", upper=2)
    t0 = time.perf_counter()
    d = load_plaza(data_dir, robot)
    log = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
    load_s = time.perf_counter() - t0
    pose0 = np.asarray(d.start_pose(), np.float64)
    bid = np.asarray(d.node_id)
    beacons = np.asarray(d.node_xy, np.float64) if anchors == "known" else None
    rlog = pr.log_from_events(log, pose0, bid, beacons=beacons, dtype=dtype)
    res, comp_s, run_s = timed_run(lambda: pr.run(rlog, pr.Config(smooth=smooth), prm))
    est = np.concatenate([np.asarray(res.pos, np.float64), np.asarray(res.heading, np.float64)[:, None]], 1)
    dr = np.asarray(dead_reckoning(planar.odometry_increment, jnp.asarray(pose0), log.u, log.dt))
    gt = np.asarray(d.gt, np.float64).copy()
    gt[:, 2] = gt[:, 2] + d.heading_offset
    A = np.asarray(res.landmarks, np.float64)
    lid = np.asarray(res.landmark_ids)
    act = np.asarray(res.active)
    m, ev = evaluate_planar(log.t, est, d.gt_t, gt, dr_pose=dr, lm=A[act], lm_ids=lid[act],
                            lm_cov=np.asarray(res.landmark_cov)[act], lm_true=d.node_xy,
                            lm_true_ids=bid, ref_label="ground truth (GPS)")
    ev["lm_true_label"] = "surveyed beacons"
    if smooth:
        sm = np.asarray(res.smoothed, np.float64)[:, :3]
        ms, evs = evaluate_planar(log.t, sm, d.gt_t, gt, ref_label="ground truth (GPS)")
        if anchors == "known":
            ms["pos_rmse_m"] = _pos_rmse_in_span(sm, metrics.interp_poses(log.t, d.gt_t, gt))
        _add_smoothed(m, ev, ms, evs)
    if anchors == "known":
        m["pos_rmse_m"] = _pos_rmse_in_span(est, metrics.interp_poses(log.t, d.gt_t, gt))
        for k in ("map_err_m", "map_err_max_m", "landmarks_compared"):
            m.pop(k, None)
    elif act.sum() >= 2:
        me = metrics.map_error(A[act], lid[act], d.node_xy, bid)
        m["map_err_self_aligned_m"] = me.rmse
    m["range_bias_m"] = float(res.bias_final)
    m["range_bias_sigma_m"] = float(res.bias_sigma)
    counts = _counts_common(res.status, {"measurements": int(np.sum(log.mask)), "used": res.n_used,
                                         "gated": res.n_gated, "rejected": res.n_unmapped,
                                         "registered": res.n_registered})
    notes = ["map_err_m: beacons in the trajectory's ATE frame; map_err_self_aligned_m: beacons "
             "aligned to the survey by their own rigid fit",
             "rejected = ranges that arrived while their beacon was not yet initialised (buffered)"]
    what = "surveyed beacons (localisation)" if anchors == "known" else "unknown beacons (SLAM)"
    if anchors == "known":
        notes = ["pos_rmse_m: no alignment (the survey defines the frame)"]
    notes += _span_notes(d.dr_t, d.td_t, "odometry increments", "ranges", held=False) + _nonfinite_notes(m)
    _range_outliers(res, counts, m, notes)
    if smooth:
        counts["smoother_failed_steps"] = int(np.sum(np.asarray(res.smooth_status) != 0))
    cfg = _config("plaza", "ekf", dtype, f"Plaza {robot}: odometry + {what} + common range bias",
                  sequence=robot, anchors=anchors, **_smooth_config(smooth, SMOOTHER_RTS))
    cfg["noise"] = "--params file" if params is not None else (
        "hand-set (plaza_range.PARAMS; docs/datasets.md)" if presets.PLAZA_FITTED is None else
        "learned: jaxslam tune plaza (docs/datasets.md)")
    cfg["noise_values"] = presets.plaza_params_to_dict(prm)
    return DatasetRun("plaza", cfg,
                      m, counts, {"load_s": load_s, "compile_s": comp_s, "run_s": run_s},
                      dict(d.report), ev, (log.t, est[:, :2], est[:, 2]), notes)


def _pos_rmse_in_span(est, ref) -> float:
    """Unaligned position RMSE [m] of ``est`` (T, >=2) against ``ref`` (T, >=2; NaN outside the
    reference's span) over the samples where the reference exists.  An estimate that is NaN or
    Inf at one of them gives NaN (as ``ate_m``; ``nanmean`` hid it behind a finite figure)."""
    ref_xy = np.asarray(ref, np.float64)[:, :2]
    err = np.linalg.norm(np.asarray(est, np.float64)[:, :2] - ref_xy, axis=1)
    inside = np.all(np.isfinite(ref_xy), axis=1)
    if not np.all(np.isfinite(err[inside])):
        return float("nan")
    return float(np.sqrt(np.nanmean(err ** 2)))  # (the figure as before for a finite estimate)


# ---------------------------------------------------------------------------
# Planar range-bearing SLAM: MRCLAM and Victoria Park
# ---------------------------------------------------------------------------

def _planar_run(log, pose0, filter, cfg_ekf, prm_ekf, fs_kind, particles, seed, dtype, smooth=False):
    """Run EKF-SLAM or FastSLAM on a planar log.

    Returns (pose (T,3), map dict, counts, comp_s, run_s, status, smoothed pose (T, 3) or None).
    """
    if filter == "ekf":
        from ..systems import planar_ekf_slam as pe

        prm = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), prm_ekf)
        p0 = jnp.asarray(pose0, dtype)
        cfg_run = cfg_ekf._replace(smooth=bool(smooth))
        res, comp_s, run_s = timed_run(lambda: pe.run(pe.log_from_events(log, p0), cfg_run, prm))
        act = np.asarray(res.active)
        lm = {"xy": np.asarray(res.landmarks, np.float64)[act], "ids": np.asarray(res.ids)[act],
              "cov": np.asarray(res.landmark_covs, np.float64)[act]}
        counts = {"measurements": int(np.sum(np.asarray(res.n_meas)) + np.sum(np.asarray(res.n_limited))),
                  "used": int(np.sum(np.asarray(res.n_used))), "gated": int(np.sum(np.asarray(res.n_gated))),
                  "rejected": int(np.sum(np.asarray(res.n_rejected))),
                  "registered": int(np.sum(np.asarray(res.n_registered))),
                  "outside_limits": int(np.sum(np.asarray(res.n_limited))),
                  "dropped_beyond_K": int(np.sum(np.asarray(res.n_dropped))),
                  "landmarks_mapped": int(act.sum()), "overflow": int(res.overflow),
                  # rows of landmarks already mapped, and those beyond the χ²(2) 99 % gate (the
                  # fraction behind DIVERGED; gated or only down-weighted, as the update chose)
                  "mapped_rows": int(np.sum(np.asarray(res.n_monitored))),
                  "mapped_outliers": int(np.sum(np.asarray(res.n_outliers))),
                  "inflations": int(res.inflations)}
        counts["pruned"] = int(np.sum(np.asarray(res.n_pruned)))
        sm = None if res.smoothed is None else np.asarray(res.smoothed, np.float64)
        if sm is not None:
            counts["smoother_failed_steps"] = int(np.sum(np.asarray(res.smooth_status) != 0))
        return np.asarray(res.pose, np.float64), lm, counts, comp_s, run_s, res.status, sm
    from ..sim import monte_carlo
    from ..systems import planar_fastslam as pf

    cfg, prm, id_map, twice = fs_kind(particles)
    prm = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), prm)
    key = jnp.asarray(monte_carlo.seed_key(seed))  # the x64-on key of the seed whatever the dtype
    p0 = jnp.asarray(pose0, dtype)
    if id_map is not None:  # known ids: subject id_map[j] lives in slot j (the core's slot_by_id)
        log = log._replace(ids=_known_slots(log.ids, log.mask, id_map))
    res, comp_s, run_s = timed_run(lambda: pf.run(pf.log_from_events(log, p0), cfg, prm, key=key), twice=twice)
    mp = res.map
    act = np.asarray(mp.active)
    ids_out = np.asarray(mp.ids)[act]
    lm = {"xy": np.asarray(mp.mean, np.float64)[act], "ids": id_map[ids_out] if id_map is not None else ids_out,
          "cov": np.asarray(mp.cov, np.float64)[act]}
    counts = {"measurements": int(np.sum(log.mask)), "used": int(np.sum(np.asarray(res.used))),
              "gated": int(np.sum(np.asarray(res.gated))), "rejected": 0,
              "registered": int(np.sum(np.asarray(res.registered))),
              "landmarks_mapped": int(act.sum()), "overflow": int(res.overflow),
              "resamples": int(res.resamples)}
    if prm.prune_window_s is not None:  # tentative landmarks removed (per-particle mean)
        counts["pruned"] = int(round(float(res.pruned)))
    if cfg.association == "known" and (prm.gate is not None or cfg.robust):
        # the rows behind DIVERGED (planar_fastslam.Result.status): sightings of mapped
        # landmarks, used or gated, and those gated or beyond the Student-t's 99 % quantile
        # (per-particle means)
        counts["mapped_rows"] = counts["used"] + counts["gated"]
        counts["mapped_outliers"] = counts["gated"] + int(round(float(res.outliers)))
    return np.asarray(res.pose_mean, np.float64), lm, counts, comp_s, run_s, res.status, None


@_register("mrclam")
def run_mrclam(data_dir, robot=1, filter="ekf", ids="known", anchors=None, particles=None, seed=0,
               dtype=None, tof=False, calibrated=False, params=None, smooth=False):
    """UTIAS MRCLAM (as shipped: dataset 6): unicycle odometry + range-bearing to barcoded landmarks.

    The EKF's noise is the one learned from the logs (``presets.MRCLAM_FITTED``, the same
    for every robot); ``params``: a ``--params`` object (``jaxslam tune mrclam``) replacing it.
    ``calibrated``: apply the camera range model and odometry delay fitted on the first half
    of robot 1 (``presets.mrclam_log``) with the matching tight noise (EKF preset;
    FastSLAM keeps its own setting, ``presets.mrclam_fastslam_setup``).  The EKF with ids
    hidden prunes tentative landmarks (``presets.MRCLAM_NN_PRUNING``) unless ``params`` sets
    ``prune_window_s``.  What depends on the files is read from them (rows per event,
    landmark subjects and capacity: ``presets.mrclam_rows`` / ``mrclam_subjects``), so the
    command also runs on MRCLAM datasets laid out differently from dataset 6.
    """
    from ..dynamics import planar
    from ..systems import planar_ekf_slam as pe
    from . import presets
    from .mrclam import load_mrclam

    catalogue.check_options("mrclam", dict(filter=filter, ids=ids, anchors=anchors, particles=particles,
                                           seed=seed, tof=tof, calibrated=calibrated, smooth=smooth,
                                           params=params))  # (robot: checked below)
    dtype = _run_dtype(dtype)
    robot = reworded(lambda: check_int(robot, "robot"),
                     f"mrclam: --robot must be 1..5 (MRCLAM has five robots), got {robot!r}", upper=5)
    if particles is not None:
        particles = check_int(particles, "particles")
    if params is not None and calibrated:
        raise InputError("mrclam: --params and --calibrated do not combine (the calibrated log has "
                         "its own noise preset)")
    # the --params object checked (a JSON object, its keys and values) before its log entries are read
    noise = {} if params is None else dataset_params(params, "mrclam")
    # the log the noise was learned on: the shipped noise's, or the --params file's
    delay = (presets.MRCLAM_FITTED["odometry_delay"] if params is None
             else dataset_log_options(params, "mrclam").get("odometry_delay", 0.0))
    t0 = time.perf_counter()
    d = load_mrclam(data_dir, robot)
    # Run (and evaluate) where ground truth exists: robot 1's GT stops at +771.9 s.
    fs_learned = filter == "fastslam" and ids == "known"  # FastSLAM's default: the EKF's learned model
    # 8 rows per event (more for a log with more sightings in one frame: none dropped) and one
    # known-id slot per landmark subject (dataset 6: 6–20), read from the files
    K, capacity = presets.mrclam_layout([d])
    subjects = presets.mrclam_subjects(d)
    if calibrated:
        log, pose0 = presets.mrclam_log(d, K=K)
    elif fs_learned:  # the range model on the host (the EKF applies it inside the filter)
        log, pose0 = presets.mrclam_log(d, K=K, range_model=presets.MRCLAM_FITTED["range_model"], odometry_delay=delay)
    else:
        log, pose0 = presets.mrclam_raw_log(d, K=K, odometry_delay=delay)
    load_s = time.perf_counter() - t0
    assoc = "known" if ids == "known" else "nn"
    prm = presets.mrclam_params(robot, dtype=dtype, corrected=calibrated)
    if assoc != "known" and "prune_window_s" not in noise:  # ids hidden: spurious landmarks pruned
        prm = prm._replace(prune_window_s=presets.MRCLAM_NN_PRUNING[0], prune_min_obs=presets.MRCLAM_NN_PRUNING[1])
    if params is not None:
        prm = pe.params_from_dict(noise, prm, dtype=dtype, where="--params: noise")
    config = presets.mrclam_config(association=assoc, K=K, capacity=capacity if assoc == "known" else None)
    fs_kind = functools.partial(_mrclam_fastslam, robot, assoc=assoc, subjects=subjects, K=K)
    pose, lm, counts, comp_s, run_s, status, smoothed = _planar_run(
        log, pose0, filter, config, prm, fs_kind, particles, seed, dtype, smooth=smooth)
    dr = np.asarray(dead_reckoning(planar.unicycle, jnp.asarray(pose0), log.u, log.dt))
    m, ev = evaluate_planar(log.t, pose, d.gt_t, d.gt, dr_pose=dr, lm=lm["xy"],
                            lm_ids=lm["ids"] if assoc == "known" else None, lm_cov=lm["cov"],
                            lm_true=d.landmark_xy if assoc == "known" else None,
                            lm_true_ids=d.landmark_id, ref_label="Vicon ground truth", at_ref_times=True)
    if assoc != "known":
        ev["lm_true_xy"] = np.asarray(d.landmark_xy)
    if smoothed is not None:
        ms, evs = evaluate_planar(log.t, smoothed, d.gt_t, d.gt, ref_label="Vicon ground truth",
                                  at_ref_times=True)
        _add_smoothed(m, ev, ms, evs)
    m.update(_class_fractions(counts))
    counts["outside_window"] = int(log.stats["outside_window"])
    counts = _counts_common(status, counts)
    setting = (f"robot {robot}, {'known ids' if assoc == 'known' else 'ids hidden (Mahalanobis NN)'}, "
               f"{'calibrated camera/odometry model' if calibrated else 'learned range model applied to the log' if fs_learned else 'raw log'}, "
               f"{'FastSLAM 2.0 proposal, Student-t, ' if fs_learned else ''}"
               f"{log.stats['n_events']} events")
    cfg = _config("mrclam", filter, dtype, setting, robot=robot, ids=ids, calibrated=bool(calibrated),
                  odometry_delay_s=presets.MRCLAM_ODOMETRY_DELAY if calibrated else delay,
                  particles=particles if filter == "fastslam" else None, seed=seed,
                  **_smooth_config(smooth, SMOOTHER_RTS))
    cfg["thresholds"] = _planar_thresholds(filter, prm, fs_kind, particles)
    notes = ([f"evaluated at the {m['eval_samples']} ground-truth samples inside the run"]
             + _window_notes(log) + _mrclam_notes(d, log, pose0) + _nonfinite_notes(m)
             + _capacity_notes(status, counts)
             + _divergence_notes(status, gate=(
                 "the chi2(2) 99 % gate" if filter == "ekf" else "the particles' Student-t model's own 99 % quantile")))
    if filter == "ekf":
        cfg["capacity"] = int(config.capacity)
        cfg["noise"] = "--params file" if params is not None else (
            "calibrated preset" if calibrated else "learned: jaxslam tune mrclam on robots 1-5 (docs/datasets.md)")
    return DatasetRun("mrclam", cfg, m, counts, {"load_s": load_s, "compile_s": comp_s, "run_s": run_s},
                      dict(d.report), ev, (log.t, pose[:, :2], pose[:, 2]), notes)


def _span_notes(input_t, meas_t, inputs: str = "inputs", meas: str = "measurements", held: bool = True) -> list:
    """Notes when two streams' time spans disagree by more than 2 s (a cut file or a clock
    offset): inputs that end before the measurements (the last rate is held, or no increment
    arrives, for the rest) or start after them (the vehicle is taken as still until then)."""
    notes = []
    if np.size(input_t) == 0 or np.size(meas_t) == 0:
        return notes
    late_end = float(meas_t[-1]) - float(input_t[-1])
    if late_end > 2.0:
        notes.append(f"the {inputs} end {late_end:.1f} s before the last of the {meas}: "
                     + ("the last input is held" if held else "no motion is applied") + " for that long; "
                     "check the files' clocks or a cut file")
    late_start = float(input_t[0]) - float(meas_t[0])
    if late_start > 2.0:
        notes.append(f"the {inputs} start {late_start:.1f} s after the first of the {meas}: the vehicle is "
                     "taken as still until then; check the files' clocks or a cut file")
    return notes


def _mrclam_notes(d, log, pose0) -> list:
    """What a MRCLAM log from another dataset could hide, said: sightings beyond the rows per
    event (none with the runner's K), unknown barcodes, no landmark sighting at all, odometry
    gaps (the last rate is held through them), ground truth that starts after the run (the
    start pose is then taken later than the run starts)."""
    notes = []
    n = int(log.stats.get("dropped_overflow", 0))
    if n:
        notes.append(f"{n} landmark sightings beyond {log.z.shape[1]} rows in one camera frame were dropped")
    n = int(d.report.get("unknown_barcode_rows", 0))
    if n:
        notes.append(f"{n} measurement rows name barcodes that Barcodes.dat does not list; they were not used "
                     "(loader_report.unknown_barcode_lines)")
    n = int(d.report.get("nonpositive_range_rows", 0))
    if n:
        notes.append(f"{n} measurement rows have a range <= 0; they were not used "
                     "(loader_report.nonpositive_range_lines)")
    if not np.any(log.mask):
        notes.append("no landmark sighting in the run: its estimate is dead reckoning")
    t_in = np.asarray(log.t)[np.asarray(log.is_input, bool)]
    gaps = np.diff(t_in)
    long = gaps > 2.0
    if np.any(long):
        i = int(np.argmax(gaps))
        notes.append(f"the odometry has {int(long.sum())} gap(s) longer than 2 s (longest {gaps[i]:.1f} s after "
                     f"t = {t_in[i]:.1f} s); the last rate is held through each")
    late = float(d.gt_t[0]) - float(log.t[0])
    if late > 1.0:
        notes.append(f"ground truth starts {late:.1f} s after the run's first event: the start pose is the first "
                     "ground-truth pose, taken that much later")
    return notes


def _capacity_notes(status, counts) -> list:
    from ..errors import CAPACITY_OVERFLOW

    if int(status) & CAPACITY_OVERFLOW:
        return [f"CAPACITY_OVERFLOW: {counts.get('overflow', 0)} sightings of new landmarks found no free slot "
                "and were not mapped"]
    return []


def _window_notes(log) -> list:
    """A note when measurements fell outside the run's time span (odometry and ground truth)
    and were dropped: counted in ``counts.outside_window``, and said, since a log whose clocks
    disagree would otherwise look like a run that saw nothing."""
    n = int(log.stats.get("outside_window", 0))
    if not n:
        return []
    return [f"{n} of {n + int(log.stats['n_meas'])} measurements lie outside the run's time span "
            "(odometry / ground truth) and were dropped: check the files' clocks"]


def _planar_thresholds(filter, prm_ekf, fs_kind, particles) -> dict:
    """The run's gates, limits and pruning/resampling thresholds (the system's ``Params`` fields
    named in its ``THRESHOLDS``): the report's ``config.thresholds`` (None: off)."""
    from ..systems import planar_ekf_slam as pe
    from ..systems import planar_fastslam as pf

    prm, names = (prm_ekf, pe.THRESHOLDS) if filter == "ekf" else (fs_kind(particles)[1], pf.THRESHOLDS)
    return {k: None if getattr(prm, k) is None else float(np.asarray(getattr(prm, k))) for k in names}


def _known_slots(ids, mask, id_map):
    """Slot of each row for FastSLAM's known ids: j where ``id_map[j]`` is the row's subject;
    ``len(id_map)`` (past the capacity: the core counts it as overflow) for a masked row or a
    subject not in the table."""
    id_map = np.asarray(id_map)
    slot = np.searchsorted(id_map, ids)
    found = np.asarray(mask, bool) & (slot < id_map.size) & (id_map[np.minimum(slot, id_map.size - 1)] == ids)
    return np.where(found, slot, id_map.size).astype(np.int32)


def _mrclam_fastslam(robot, n, assoc, subjects, K):
    from .presets import mrclam_fastslam_setup

    known = assoc == "known"
    cfg, prm = mrclam_fastslam_setup(robot, n_particles=100 if n is None else n, association="known" if known else "ml",
                                     K=K, capacity=int(subjects.size) if known else None)
    # known ids: subject subjects[j] lives in slot j (dataset 6: subjects 6–20 → 0–14)
    return cfg, prm, subjects if known else None, True


@_register("victoria-park")
def run_victoria_park(data_dir, robot=1, filter="ekf", ids="known", anchors=None, particles=None, seed=0,
                      dtype=None, tof=False, calibrated=False, smooth=False, params=None):
    """ACFR Victoria Park: Ackermann car, laser tree detections, unknown association, GPS reference.

    ``params``: a ``--params`` object (``jaxslam tune victoria-park``) replacing the preset's noise."""
    from . import presets
    from .victoria_park import load_victoria_park

    catalogue.check_options("victoria-park", dict(robot=robot, filter=filter, ids=ids, anchors=anchors,
                                                  particles=particles, seed=seed, tof=tof,
                                                  calibrated=calibrated, smooth=smooth, params=params))
    dtype = _run_dtype(dtype)
    if particles is not None:
        particles = check_int(particles, "particles")
    noise = None if params is None else dataset_params(params, "victoria-park")  # before the log is read
    t0 = time.perf_counter()
    d = load_victoria_park(data_dir)
    det_t, det = d.det_t, d.det
    if filter == "fastslam":  # the EKF applies its range limits inside the run (and counts them)
        keep = (det[:, 0] >= 5.0) & (det[:, 0] <= 40.0)
        det_t, det = det_t[keep], det[keep]
    # FastSLAM's preset takes K = 17 rows per scan (the most in the shipped log after the range
    # limits); more are counted in log.stats["dropped_overflow"].  The EKF picks its K nearest.
    log = merge_events(d.input_t, d.inputs, det_t, det, K=17 if filter == "fastslam" else None,
                       input_mode="rate")
    load_s = time.perf_counter() - t0
    pose0 = np.zeros(3)
    prm = presets.victoria_park_params(dtype=dtype)
    if params is not None:
        from ..systems import planar_ekf_slam as pe

        prm = pe.params_from_dict(noise, prm, dtype=dtype, where="--params: noise")
    pose, lm, counts, comp_s, run_s, status, _ = _planar_run(
        log, pose0, filter, presets.victoria_park_config(), prm, lambda n: _vp_fastslam(n), particles, seed, dtype)
    motion = _ackermann_motion(d.geometry)
    dr = np.asarray(dead_reckoning(motion, jnp.asarray(pose0), log.u, log.dt))
    m, ev = evaluate_planar(log.t, pose, d.gps_t, d.gps, dr_pose=dr, lm=lm["xy"], lm_cov=lm["cov"],
                            ref_label="GPS", at_ref_times=True)
    # GPS quality: a fix that implies a speed above 8 m/s from either neighbour (the car's top
    # speed is 6.6 m/s, data README §2) is a GPS jump; the ATE over the remaining fixes is
    # reported beside the ATE over all fixes (which stays the headline figure).
    tg, gx = np.asarray(ev["t"]), np.asarray(ev["ref_xy"])
    v = np.hypot(*np.diff(gx, axis=0).T) / np.maximum(np.diff(tg), 1e-3)
    jump = np.zeros(tg.size, bool)
    jump[1:] |= v > 8.0
    jump[:-1] |= v > 8.0
    m["ate_gps_jumps_removed_m"] = float(metrics.ate(ev["est_xy"][~jump], gx[~jump]))
    m["gps_fixes_removed"] = int(jump.sum())
    ev["ref_suspect"] = jump  # marked on the error figure: the error there is the GPS's
    ev["ref_suspect_label"] = "GPS jump (> 8 m/s to a neighbouring fix)"
    # The presets were chosen on t < 500 s: the error of each part (whole-run alignment).
    m.update(split_ate(ev, 500.0, "500"))
    if filter == "fastslam":
        counts["measurements"] = int(d.det_t.size)
        counts["outside_limits"] = int(d.det_t.size - det_t.size)
        counts["dropped_beyond_K"] = int(log.stats["dropped_overflow"])
    m.update(_class_fractions(counts))
    counts = _counts_common(status, counts)
    cfg = _config("victoria-park", filter, dtype, f"unknown association, {log.stats['n_events']} events",
                  particles=particles if filter == "fastslam" else None, seed=seed)
    cfg["thresholds"] = _planar_thresholds(filter, prm, _vp_fastslam, particles)
    if filter == "ekf":
        cfg["noise"] = "--params file" if params is not None else "hand-set preset (chosen on t < 500 s; docs/datasets.md)"
    notes = ([f"ATE against the {m['eval_samples']} GPS fixes (SE(2)-aligned); GPS has no heading, so "
              "rpe_m is translational, over pairs of fixes 1 ± 0.1 s apart"]
             + _span_notes(d.input_t, d.det_t, "odometry inputs", "laser scans") + _nonfinite_notes(m)
             + _capacity_notes(status, counts) + _divergence_notes(status))
    if filter == "fastslam" and np.dtype(dtype) == np.float32:
        notes.append("FastSLAM on this log is less accurate in float32 when measured (ATE 5.52 m against 3.83 m "
                     "in float64; FastSLAM 1.0 diverged, 10.7 m with the map overflowing): prefer float64")
    return DatasetRun("victoria-park", cfg, m, counts,
                      {"load_s": load_s, "compile_s": comp_s, "run_s": run_s},
                      dict(d.report), ev, (log.t, pose[:, :2], pose[:, 2]), notes)


def split_ate(ev, t_cut: float, label: str) -> dict:
    """The position error of a run's reference fixes before and from ``t_cut`` [s, the log's
    clock, finite], under the whole run's alignment (``ev``: :func:`evaluate_planar`'s arrays
    ``t`` (N,), ``est_xy`` and ``ref_xy`` (N, 2)): ``{"ate_t_lt_<label>s_m": ...,
    "ate_t_ge_<label>s_m": ...}``; a side without a fix (a short log, an excerpt) is left out.
    Bad arguments are an :class:`InputError` naming them."""
    t_cut = check_scalar(t_cut, "t_cut")
    if not isinstance(label, str):
        raise InputError(f"label: expected a str (the keys' time label), got {label!r}"[:300])
    if not isinstance(ev, dict) or not {"t", "est_xy", "ref_xy"} <= set(ev):
        raise InputError("ev: expected evaluate_planar's evaluation dict (keys 't', 'est_xy', 'ref_xy')")
    tg = real_numbers(ev["t"], "ev['t']")
    if tg.ndim != 1:
        raise InputError(f"ev['t']: expected a 1-D array of times, got shape {tg.shape}")
    if not np.all(np.isfinite(tg)):  # a NaN time fell on neither side of the cut
        raise InputError("ev['t']: expected finite times, got NaN or Inf")
    est = _rows(ev["est_xy"], "ev['est_xy']", tg.size, 2)
    ref = _rows(ev["ref_xy"], "ev['ref_xy']", tg.size, 2)
    e2 = np.sum((est - ref) ** 2, 1)
    return {key: float(np.sqrt(np.mean(e2[part])))
            for key, part in ((f"ate_t_lt_{label}s_m", tg < t_cut), (f"ate_t_ge_{label}s_m", tg >= t_cut))
            if part.any()}


def _vp_fastslam(n):
    from .presets import victoria_park_fastslam_setup

    cfg, prm = victoria_park_fastslam_setup(n_particles=50 if n is None else n)
    return cfg, prm, None, False  # minutes per run: timed once, compilation included
