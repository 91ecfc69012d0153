"""Tunable targets: what is tuned, on which data, with which loss, evaluated how.

A :class:`Target` bundles the unconstrained parameters θ (a dict of vectors, see
:mod:`jaxslam.tuning.params`), a per-run loss ``loss_fn(θ, item)``, the training batch
(leading axis = runs), a held-out batch for the test-loss curve, and ``evaluate`` — the
held-out before/after comparison on the scenario itself (the same flights ``jaxslam run``
flies).  Factories build targets; :func:`get` looks them up by ``(scenario, target)``.

One module per target, each registering itself when imported (:func:`register_target`); the
registry imports them on first use, so ``jaxslam tune --help`` pays for none of them:

* :mod:`.ekfslam3d` — ``("ekfslam3d-unknown" | "ekfslam3d-known", "noise")``: paper 000's
  EKF-SLAM noise on recorded logs;
* :mod:`.figure8` — ``("track-figure8", "lqr")``: the DF-LQR weights through the closed loop;
* :mod:`.loop` — ``("ekfslam3d-unknown" | "ekfslam3d-known", "loop")``: the DF-LQR weights and/or
  the filter's noise through the closed loop with the EKF-SLAM estimator in it;
* :mod:`.linear_gaussian` — ``("linear-gaussian", "noise")``: the oracle (known Q, R);
* :mod:`.uwb` — ``("uwb-circle" | "uwb-square" | "uwb-rough", "noise")``: paper 003's Q;
* :mod:`.mrclam` — ``("mrclam", "noise")``: the planar EKF-SLAM's noise from real logs;
* :mod:`.util_uwb` — ``("util-uwb", "noise")``: the UTIL range-only filter's noise from its flight;
* :mod:`.plaza` — ``("plaza", "noise")``: the Plaza range-only SLAM's noise from its logs;
* :mod:`.victoria_park` — ``("victoria-park", "noise")``: Victoria Park's input and laser noise.

No paper covers tuning; each module states its decisions, and ``docs/tuning.md`` collects them.
Seeds: training runs use ``keys_for(seed, M)``, the held-out test runs ``keys_for(seed + 1, M)``
— the seeds of ``jaxslam run --seed seed+1``.
"""

from __future__ import annotations

import importlib
import math
from typing import Any, Callable, NamedTuple, Optional

import numpy as np

from ...errors import InputError

__all__ = ["Target", "register_target", "get", "available", "default_target", "REAL_LOG_SCENARIOS", "BUILTIN_MODULES",
           "DEFAULT_ROBOTS", "keys", "diag_list", "STUDENT_T_NU", "window_nll", "heldout_nll", "metrics_entry"]

#: ν of the Student-t range likelihood the range-only real-log targets (UTIL, Plaza) fit with (fixed).
STUDENT_T_NU = 5.0


def window_nll(res, weights=None):
    """Innovation NLL per scalar of a run's per-event ``res.nll`` / ``res.nll_dof`` (nats; no
    ground truth), over the events with weight 1 (``weights`` None: all; a list is read as an
    array); traceable.  An event of weight 0 adds nothing, even a NaN or Inf ``nll`` (0·NaN made
    the result NaN), as :func:`heldout_nll` ignores it; so does its gradient."""
    import jax.numpy as jnp

    if weights is not None:
        ws, ns = tuple(np.shape(weights)), tuple(np.shape(res.nll))
        try:
            ok = np.broadcast_shapes(ws, ns) == ns
        except ValueError:
            ok = False
        if not ok:
            raise InputError(f"weights: expected one weight per event, shape {ns}, got {ws}")
    w = jnp.asarray(1.0 if weights is None else weights)  # a list was a bare TypeError
    num = jnp.sum(jnp.where(w > 0, w * res.nll, 0.0))
    den = jnp.sum(jnp.where(w > 0, w * res.nll_dof, 0.0))
    return num / jnp.maximum(den, 1.0)


def heldout_nll(res, held=None) -> float:
    """:func:`window_nll` on the host (float64) over the events where ``held`` (a NumPy bool
    mask; None: every event)."""
    nl, nd = np.asarray(res.nll, np.float64), np.asarray(res.nll_dof, np.float64)
    if held is not None:
        h = np.asarray(held)
        if h.dtype != np.bool_ or h.shape != nl.shape:  # an int array would index, not mask
            raise InputError(f"held: expected a bool mask of shape {nl.shape} (one per event), "
                             f"got {h.dtype} of shape {h.shape}")
        nl, nd = nl[h], nd[h]
    return float(nl.sum() / max(nd.sum(), 1.0))


def metrics_entry(m: dict) -> dict:
    """One label of an ``evaluate`` result from its metric lists (no consistency block)."""
    return {"metrics": {k: np.asarray(v, np.float64) for k, v in m.items()}, "consistency": None}

#: the target modules the registry imports on first use
BUILTIN_MODULES = ("ekfslam3d", "figure8", "linear_gaussian", "uwb", "mrclam", "util_uwb", "plaza", "victoria_park", "loop")

#: the built-in targets as their modules register them, ``{(scenario, target): losses}``: what
#: ``jaxslam tune`` checks its arguments against before JAX or any target module is imported
#: (each module registers with its entry here; ``tests/tuning/test_tuning_cli.py`` checks both agree)
DECLARED = {
    ("ekfslam3d-known", "loop"): ("cost",),
    ("ekfslam3d-known", "noise"): ("nll", "mse", "nees"),
    ("ekfslam3d-unknown", "loop"): ("cost",),
    ("ekfslam3d-unknown", "noise"): ("nll", "mse", "nees"),
    ("linear-gaussian", "noise"): ("nll", "mse", "nees"),
    ("mrclam", "noise"): ("nll",),
    ("plaza", "noise"): ("nll",),
    ("track-figure8", "lqr"): ("cost",),
    ("util-uwb", "noise"): ("nll",),
    ("uwb-circle", "noise"): ("mse", "nees"),
    ("uwb-rough", "noise"): ("mse", "nees"),
    ("uwb-square", "noise"): ("mse", "nees"),
    ("victoria-park", "noise"): ("nll",),
}

#: scenarios whose targets learn from real logs (``--data``, ``--window``; MRCLAM and Plaza also ``--robots``)
REAL_LOG_SCENARIOS = ("mrclam", "util-uwb", "plaza", "victoria-park")

#: the training and held-out robots (Plaza: sequences) of the real-log targets that take
#: ``--robots`` / ``--test-robots``, ``{scenario: {"robots": ..., "test_robots": ...}}``: the
#: defaults of their factories (:func:`.mrclam.mrclam_noise`, :func:`.plaza.plaza_noise`) and what
#: ``jaxslam tune`` counts the training logs by (and its help states) before JAX or any target
#: module is imported; the other real-log targets train on one log
DEFAULT_ROBOTS = {
    "mrclam": {"robots": (1, 2, 3, 4), "test_robots": (5,)},
    "plaza": {"robots": (1,), "test_robots": (2,)},
}


class Target(NamedTuple):
    """A tuning problem (host-side container; see the module docstring).

    scenario, target, loss: names (e.g. ``"ekfslam3d-unknown"``, ``"noise"``, ``"nll"``).
    specs: {name: :class:`~jaxslam.tuning.params.CovSpec`} of the tuned matrices.
    theta0: {name: (p,) array} starting point.
    loss_fn: ``loss_fn(theta, item) -> ()`` per run (jit/vmap/grad-safe).
    train: training batch (pytree, leading axis = runs).
    test: held-out batch of the same form (or None): the test-loss curve.
    physical: ``physical(theta) -> params container`` (e.g. a system's ``Params``).
    evaluate: ``evaluate({label: physical}) -> {label: {"metrics": {name: (runs,)},
      "consistency": dict | None}}`` on held-out runs of the scenario itself.
    references: {label: physical} extra rows of the evaluation (e.g. ``"q_imu"``).
    to_params: ``to_params(physical) -> dict`` loadable by ``jaxslam run --params``.
    describe: ``describe(theta) -> {name: [floats]}`` physical values tracked in the history.
    config: every setting used (JSON-ready).
    eval_command: the command (``jaxslam run`` or ``jaxslam dataset``) that runs the tuned
      parameters, ``TUNED.json`` standing for the parameter file and ``DIR`` for the data folder.
    eval_note: what that command's figures cover when they differ from the table's (optional).
    log_objective: optimise log(mean loss) (positive losses; see :func:`~jaxslam.tuning.optimize.fit`).
    sequential: the loss and gradient of each training item run after the other (``lax.map``),
      not vmapped: the compiled step is smaller (one log's program, not a batched one) and, for
      the EKF-SLAM logs, faster per step too (4 logs: compile 19.0 → 14.6 s, step 1.57 → 1.36 s).
    after_references: optional ``after_references(physical_after) -> {label: physical}``: rows
      built from the result and evaluated beside it (e.g. the tuned weights flown with the
      reference noise, which separates what each tuned part did).
    """

    scenario: str
    target: str
    loss: str
    specs: dict
    theta0: dict
    loss_fn: Callable
    train: Any
    test: Any
    physical: Callable
    evaluate: Callable
    references: dict
    to_params: Callable
    describe: Callable
    config: dict
    eval_command: str = ""
    log_objective: bool = False
    sequential: bool = False  # evaluate the training items one after another (lax.map)
    after_references: Optional[Callable] = None
    eval_note: str = ""

    def references_for(self, physical_after) -> dict:
        """Every reference row of the evaluation of ``physical_after``: :attr:`references` and
        those :attr:`after_references` builds from the result."""
        extra = {} if self.after_references is None else self.after_references(physical_after)
        return {**self.references, **extra}


_FACTORIES: dict = {}
_LOADED = False


def register_target(scenario: str, target: str, factory: Callable, losses: tuple) -> None:
    """Make ``factory(loss=..., train_runs=..., test_runs=..., seed=..., dtype=..., **kw) -> Target``
    available as ``jaxslam tune SCENARIO --target TARGET`` with the given ``losses``."""
    _FACTORIES[(scenario, target)] = (factory, tuple(losses))


def _load() -> None:
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    try:
        for mod in BUILTIN_MODULES:
            importlib.import_module(f"{__name__}.{mod}")
    except BaseException:
        _LOADED = False  # a later call retries and raises the same error again
        raise


def available() -> dict:
    """{(scenario, target): losses} of every target: those registered and the built-in ones
    (from :data:`DECLARED`, so this imports no target module and no JAX)."""
    found = {k: v[1] for k, v in _FACTORIES.items()}
    if not _LOADED:
        found = {**DECLARED, **found}
    return dict(sorted(found.items()))


def default_target(scenario: str):
    """The target ``jaxslam tune SCENARIO`` builds without ``--target``: ``"noise"`` where the
    scenario has it, else its first registered one; None for a scenario with no target."""
    found = list(_FACTORIES) + ([k for k in DECLARED if k not in _FACTORIES] if not _LOADED else [])
    names = [t for (s, t) in found if s == scenario]
    return "noise" if "noise" in names else (names[0] if names else None)


def get(scenario: str, target: str, loss: str, **kw) -> Target:
    """Build the target ``(scenario, target)`` with ``loss``; raises InputError naming the valid ones.

    ``kw`` goes to the target's factory.  A keyword no target takes is an :class:`InputError`
    naming it; so is one of the options ``jaxslam tune`` shares between targets
    (``train_runs``, ``seed``, ``cov``, ``tune_r``, ``structure``, ``eval_duration``, ...)
    given to a target that does not use it — except None, or the value the CLI passes when
    its flag is not given (``cov="diag"``, ``tune_r=False``, ``structure="qc"``,
    ``filter="ekf"``, ``checkpoint=True``, ``eval_duration=50.0``), which change nothing.
    """
    for name, value in (("scenario", scenario), ("target", target), ("loss", loss)):
        if not isinstance(value, str):  # a list was a bare "unhashable type" TypeError
            raise InputError(f"{name}: expected a name (str), got {value!r}"[:300])
    _load()
    if (scenario, target) not in _FACTORIES:
        valid = ", ".join(f"{s} --target {t}" for s, t in sorted(_FACTORIES))
        raise InputError(f"no tuning target {target!r} for scenario {scenario!r}; available: {valid}")
    factory, losses = _FACTORIES[(scenario, target)]
    if loss not in losses:
        raise InputError(f"--loss: {scenario} --target {target} supports {', '.join(losses)}; got {loss!r}")
    return factory(loss=loss, **kw)


def keys(seed: int, runs: int):
    """The PRNG keys of ``runs`` runs from ``seed`` (those of ``jaxslam run --seed seed``)."""
    from ...linalg import check_int
    from ...sim.monte_carlo import keys_for

    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise InputError(f"seed: expected an int, got {seed!r}")
    return keys_for(int(seed), check_int(runs, "runs", lower=1))


def diag_list(M) -> list:
    """The diagonal of a matrix as floats (for a target's ``describe``)."""
    from ...linalg import check_numbers

    a = check_numbers(M, "M")
    if a.ndim != 2:
        raise InputError(f"M: expected a matrix, got shape {a.shape}")
    return [float(v) for v in np.diag(a)]


#: keywords the ``jaxslam tune`` CLI passes to every simulation target (a target may ignore
#: those it does not use); any other keyword a target does not take is a typo
_CLI_SHARED_KEYWORDS = frozenset({"train_runs", "test_runs", "seed", "dtype", "eval_duration", "checkpoint",
                                 "cov", "tune_r", "structure", "filter", "train_duration"})

#: the values the CLI passes for the shared keywords when their flag is not given: a target that
#: does not use the keyword accepts it with this value (it changes nothing); the others (and any
#: other value) are refused by name.  ``train_runs``, ``test_runs``, ``seed`` and ``train_duration``
#: have none: every simulation target uses the first three, and the CLI passes ``train_duration``
#: (``--duration``) only to the targets that fly; it passes none of them to a real-log target.
_CLI_NEUTRAL = {"eval_duration": 50.0, "checkpoint": True, "cov": "diag", "tune_r": False, "structure": "qc",
                "filter": "ekf"}


def _is_neutral(key: str, value) -> bool:
    """``value`` of the shared keyword ``key`` changes nothing: None (not given) or the CLI's default."""
    if value is None:
        return True
    if key not in _CLI_NEUTRAL:
        return False
    n = _CLI_NEUTRAL[key]
    if isinstance(n, bool):
        return isinstance(value, (bool, np.bool_)) and bool(value) == n
    if isinstance(n, str):
        return isinstance(value, str) and value == n
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
            and float(value) == n)


def _check_keywords(ignored: dict, target: str) -> None:
    """Raise InputError naming the keywords in ``ignored`` (a factory's ``**kw`` rest): one not
    among :data:`_CLI_SHARED_KEYWORDS` is a typo (a misspelled option never silently falls
    back); a shared one is an option this target does not use, refused unless it is None or
    holds the value the CLI passes by default (:data:`_CLI_NEUTRAL`), so that ``seed=7`` or
    ``tune_r=True`` never silently does nothing."""
    bad = sorted(set(ignored) - _CLI_SHARED_KEYWORDS)
    if bad:
        raise InputError(f"{bad[0]}: unknown keyword(s) {bad} for tuning target {target}")
    unused = sorted(k for k, v in ignored.items() if not _is_neutral(k, v))
    if unused:
        raise InputError(f"{unused[0]}: tuning target {target} does not use {', '.join(unused)} (it would be "
                         f"ignored); got {', '.join(f'{k}={ignored[k]!r}' for k in unused)}"[:400])


def _check_duration(value, name: str, lower: float) -> float:
    """``value`` (seconds) as a float: a finite real number (not a bool) >= ``lower``; else
    InputError "``name``: must be at least ``lower`` s" (a string or None was a bare TypeError)."""
    ok = (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
          and math.isfinite(value) and value >= lower)
    if not ok:
        raise InputError(f"{name}: must be at least {lower:g} s, got {value}"[:300])
    return float(value)


def _fixed_mode(factory: Callable, mode: str, target: str) -> Callable:
    """``factory`` with ``mode`` set by the scenario's name (``ekfslam3d-{mode}``): a ``mode``
    keyword is an InputError naming it (it was a bare "multiple values" TypeError)."""
    def build(**kw):
        if "mode" in kw:
            raise InputError(f"mode: unknown keyword for tuning target ekfslam3d-{mode} --target {target} "
                             f"(the scenario name sets it); got mode={kw['mode']!r}"[:300])
        return factory(mode=mode, **kw)

    return build


def _check_window(t_max):
    """``t_max`` (a fit window [s], ``--window``) as a float: None, or a finite number > 0; else
    InputError naming ``t_max`` (a string was a bare TypeError, NaN an error about another name)."""
    if t_max is None:
        return None
    from ...linalg import check_scalar, reworded

    return reworded(lambda: check_scalar(None if isinstance(t_max, (bool, np.bool_)) else t_max, "t_max",
                                         lower=0, strict=True),
                    f"t_max: expected the fit window in seconds (--window), a finite number > 0 or None, "
                    f"got {t_max!r}"[:300])


def dataset_eval_command(dataset: str, robots) -> str:
    """The command that runs a tuned file on each of ``robots`` of ``dataset`` (``jaxslam dataset``
    takes one ``--robot``): one command per robot, joined by ``&&`` (the real-log reports named the
    first robot alone, so a second held-out robot was never named)."""
    return " && ".join(f"jaxslam dataset {dataset} --data DIR --robot {int(r)} --params TUNED.json" for r in robots)


def _check_robots(value, name: str, flag: str, allow_empty: bool) -> tuple:
    """``value`` as a tuple of robot numbers listed once each, else InputError naming ``name``
    and ``flag``: :func:`jaxslam.data.catalogue.robot_list`."""
    from ...data.catalogue import robot_list

    return robot_list(value, name, flag, allow_empty=allow_empty)
