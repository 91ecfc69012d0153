"""Scenario registry: what ``jaxslam list`` shows and ``jaxslam run NAME`` runs.

A scenario is a named, documented entry point that simulates (or loads) data,
runs an estimator over ``runs`` Monte Carlo runs and returns a
:class:`ScenarioResult`: per-run metrics, consistency statistics, status-flag
counts and timings.  The CLI turns a result into a table, the ``run`` JSON of
``docs/cli.md`` and plots; a user's script can call ``get(name).run(...)`` directly (a
partial ``options`` dict is completed with the defaults and checked: :func:`check_options`).

Concrete scenarios live in the modules of :mod:`jaxslam.sim.scenarios` and
register themselves at import time with :func:`register`.  The registry loads
them lazily (on the first :func:`get` or :func:`all_scenarios`), so ``jaxslam --help``
never pays for importing JAX or the filters; the built-in scenarios' names, descriptions
and options are declared in :mod:`jaxslam.sim.scenarios.builtin`, so :func:`names`,
:func:`declared` and :func:`check_options` on a declaration import neither (``jaxslam
list`` and a mistyped scenario option exit before JAX is imported).

Decisions
- Option names are Python identifiers; ``Option("noise_scale", ...)`` becomes
  ``--noise-scale`` on the command line (``--noise_scale`` is accepted too) and
  the key ``"noise_scale"`` in the ``options`` dict the scenario receives.
- A ``bool`` option is a flag: ``--name`` sets it (default ``False``); with a
  default of ``True`` the CLI offers ``--name/--no-name``.
- Option names that clash with the common ``run`` options (``runs``, ``seed``,
  ``float32``, ``json``, ``plots``, ``quiet``, ``params``, ``debug``, ``help``,
  ``scenario``)
  are rejected at registration, as are defaults of the wrong type or outside
  ``choices``: a broken scenario fails when it is defined, not when a user runs it.
- Registering a second scenario under a taken name raises unless
  ``replace=True`` (tests and notebooks re-register on purpose).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import keyword
import pathlib
from typing import Any, Callable

import numpy as np

from jaxslam import paramfile
from jaxslam.errors import InputError, check_flag, check_run_dtype

from .builtin import DECLARED
from .option import Option

__all__ = [
    "Option",
    "ScenarioResult",
    "Scenario",
    "RESERVED_OPTION_NAMES",
    "register",
    "unregister",
    "get",
    "declared",
    "names",
    "all_scenarios",
    "program_key",
    "check_params",
    "default_options",
    "check_options",
]

# Names used by the common `jaxslam run` options; a scenario option may not reuse them (the
# CLI's parser would refuse the second --NAME when a user runs it).
RESERVED_OPTION_NAMES = frozenset(
    {"runs", "seed", "float32", "json", "plots", "quiet", "params", "debug", "help", "h", "version",
     "scenario", "threads", "processes", "coordinator", "num_processes", "process_id"}
)

_OPTION_TYPES = (float, int, str, bool)


@dataclasses.dataclass
class ScenarioResult:
    """What a scenario's ``run`` returns (host-side NumPy / plain Python).

    Attributes:
      config: every parameter used, including the scenario options (JSON-ready).
      metrics: metric name with units (``"pos_rmse_m"``) -> per-run values, shape (runs,).
      consistency: ``{"anees", "anees_bounds": [lo, hi], "nis_mean", "nis_bounds": [lo, hi]}``
        plus, per statistic ``S`` (stem without ``_mean``), ``S_block`` (the state block or
        measurement rows it covers, text) and ``S_dim`` (the block's dimension = the value
        expected of a consistent filter; 1 for the NIS normalised per degree of freedom) and,
        for a time-averaged ANEES, ``S_steps_inside`` (the fraction of steps inside the per-step
        bounds);
        further statistics (e.g. ``anees_robot``) follow the same pattern (docs/cli.md);
        or ``None`` for a scenario without a filter (the JSON then omits the key).
      flags: counts summed over runs, e.g. ``{"capacity_overflow", "masked_measurements",
        "non_finite"}``.
      timing: ``{"compile_s", "run_s"}`` in seconds; the CLI adds ``runs_per_s``.
      plot: ``plot(directory) -> [written PNG paths]``, or ``None`` if the scenario has no plots.
      extra: further top-level JSON sections (must not reuse a standard key).
      interrupted: the batch was cut short by Ctrl-C; ``metrics`` hold the finished runs only.
    """

    config: dict
    metrics: dict[str, np.ndarray]
    consistency: dict | None
    flags: dict[str, int]
    timing: dict[str, float]
    plot: Callable[[pathlib.Path], list[pathlib.Path]] | None = None
    extra: dict = dataclasses.field(default_factory=dict)
    interrupted: bool = False


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A named scenario.

    Attributes:
      name: what ``jaxslam run NAME`` takes (lower case, ``[a-z0-9_-]``).
      description: one line for ``jaxslam list``.
      options: scenario-specific options, shown by ``jaxslam run NAME --help``.
      run: ``run(runs=int, seed=int, dtype=np.dtype, options=dict, progress=Progress,
        params=dict | None, plots=bool) -> ScenarioResult``.  ``options`` holds every option of
        ``options`` (defaults filled in: ``Scenario.run`` passes the caller's dict through
        :func:`check_options` first, so an unknown key is an error); ``params`` is the ``--params`` file's sections,
        checked by :func:`check_params` (``Scenario.run`` checks a Python caller's too, the
        messages starting ``params: ``); ``dtype`` is float32 or float64 (float64 only with
        JAX's x64 on; else ``InputError("dtype: ...")``); ``plots`` (a bool) says the caller will call ``result.plot``
        (the scenario then records the first run's flight in the same compiled program,
        instead of flying it again).
      params: ``params(options, dtype) -> {section: {key: default}}``, the scenario's default
        values of everything a ``--params`` file may set (host-side, NumPy or un-traced
        arrays); :mod:`jaxslam.paramfile` checks a file against it.  ``None``: the scenario
        takes no ``--params`` file.
    """

    name: str
    description: str
    options: tuple[Option, ...]
    run: Callable[..., ScenarioResult]
    params: Callable[[dict, Any], dict] | None = None

    def __post_init__(self):
        # ``run`` called from Python gets its arguments checked like the CLI's: ``options``
        # checked and completed (:func:`check_options`: an unknown or misspelt key used to be
        # ignored silently), ``dtype`` float32 or float64 (float64 only with JAX's x64 on: it
        # computed in float32 while the JSON said float64), ``params`` checked against the
        # scenario's schema as the CLI's ``--params`` (:func:`check_params`: a misspelt section
        # ran with the defaults) and ``plots`` a bool.
        raw = getattr(self.run, "_unchecked_run", self.run)  # dataclasses.replace: wrap anew
        if callable(raw):
            @functools.wraps(raw)
            def run(*args, **kw):
                args = list(args)

                def given(name):
                    i = _RUN_ARGS.index(name)
                    if i < len(args):
                        return True, args[i]
                    return (name in kw), kw.get(name)

                def put(name, value):
                    i = _RUN_ARGS.index(name)
                    if i < len(args):
                        args[i] = value
                    else:
                        kw[name] = value

                has_dtype, dtype = given("dtype")
                if has_dtype:
                    check_run_dtype(dtype)
                put("options", check_options(self, given("options")[1]))
                has_params, params = given("params")
                if has_params and params is not None:
                    put("params", _check_params(self, params, given("options")[1],
                                                dtype if has_dtype else np.float64, where="params"))
                has_plots, plots = given("plots")
                if has_plots:
                    check_flag(plots, "plots")
                return raw(*args, **kw)

            run._unchecked_run = raw
            object.__setattr__(self, "run", run)


# The positional order of a scenario's ``run`` arguments (``Scenario.run``'s docstring).
_RUN_ARGS = ("runs", "seed", "dtype", "options", "progress", "params", "plots")


def _checked_args(scenario: "Scenario", options, dtype, params=None, plots=False):
    """``(options, params)`` of a scenario module's public ``build`` / ``run_scenario`` checked
    as ``Scenario.run`` checks them: options completed and checked (:func:`check_options`),
    ``dtype`` float32 / float64, ``params`` against the scenario's schema, ``plots`` a bool."""
    options = check_options(scenario, options)
    check_run_dtype(dtype)
    check_flag(plots, "plots")
    if params is not None:
        params = _check_params(scenario, params, options, dtype, where="params")
    return options, params


def _duration_flown(steps: int, dt: float) -> float:
    """Seconds flown by ``steps`` steps of ``dt`` (a scenario's ``config["duration_flown_s"]``:
    its duration rounded to whole steps or sensor frames), without the float noise of the
    product (0.30000000000000004)."""
    return float(round(int(steps) * float(dt), 9))


_REGISTRY: dict[str, Scenario] = {}
_REMOVED: set[str] = set()  # names unregistered since they were registered (see names())
_BUILTIN_LOADED = False


def _check_option(scenario_name: str, opt: Any) -> None:
    where = f"scenario {scenario_name!r} option"
    if not isinstance(opt, Option):
        raise InputError(f"{where}s: expected Option instances, got {type(opt).__name__}")
    if not (isinstance(opt.name, str) and opt.name.isidentifier() and not keyword.iskeyword(opt.name)):
        raise InputError(f"{where} name {opt.name!r} is not a Python identifier")
    if opt.name in RESERVED_OPTION_NAMES:
        raise InputError(
            f"{where} {opt.name!r} clashes with a common run option "
            f"(reserved: {', '.join(sorted(RESERVED_OPTION_NAMES))})"
        )
    if opt.type not in _OPTION_TYPES:
        raise InputError(f"{where} {opt.name!r}: type must be float, int, str or bool, got {opt.type!r}")
    if opt.type is bool:
        if not isinstance(opt.default, bool):
            raise InputError(f"{where} {opt.name!r}: bool option needs a bool default")
        if opt.choices is not None:
            raise InputError(f"{where} {opt.name!r}: a bool option takes no choices")
        return
    ok_types = (int, float) if opt.type is float else (opt.type,)
    if opt.default is not None and (
        not isinstance(opt.default, ok_types) or isinstance(opt.default, bool)
    ):
        raise InputError(
            f"{where} {opt.name!r}: default {opt.default!r} is not of type {opt.type.__name__}"
        )
    if opt.lower is not None:
        if opt.type not in (int, float) or not isinstance(opt.lower, ok_types) or isinstance(opt.lower, bool):
            raise InputError(f"{where} {opt.name!r}: lower must be a number of an int or float option")
        if opt.default is not None and opt.default < opt.lower:
            raise InputError(f"{where} {opt.name!r}: default {opt.default!r} is below lower {opt.lower!r}")
    if opt.choices is not None:
        if not isinstance(opt.choices, tuple) or not opt.choices:
            raise InputError(f"{where} {opt.name!r}: choices must be a non-empty tuple")
        if opt.default is not None and opt.default not in opt.choices:
            raise InputError(
                f"{where} {opt.name!r}: default {opt.default!r} is not one of {opt.choices!r}"
            )


def register(scenario: Scenario, *, replace: bool = False) -> Scenario:
    """Add ``scenario`` to the registry and return it (usable as ``X = register(Scenario(...))``).

    Raises:
      InputError: the name is malformed or taken (unless ``replace``), an option is
        malformed, or two options share a name.
    """
    if not isinstance(scenario, Scenario):
        raise InputError(f"register: scenario must be a Scenario, got {type(scenario).__name__}")
    name = scenario.name
    if not (isinstance(name, str) and name and all(c.isalnum() or c in "_-" for c in name)
            and name == name.lower()):
        raise InputError(f"register: scenario name {name!r} must be lower case [a-z0-9_-]+")
    if not isinstance(scenario.description, str) or "\n" in scenario.description.strip():
        raise InputError(f"register: scenario {name!r} description must be one line of text")
    if not callable(scenario.run):
        raise InputError(f"register: scenario {name!r} run is not callable")
    seen: set[str] = set()
    for opt in tuple(scenario.options):
        _check_option(name, opt)
        if opt.name in seen:
            raise InputError(f"scenario {name!r}: option {opt.name!r} given twice")
        seen.add(opt.name)
    if name in DECLARED and name not in _REMOVED:
        # a built-in's name: its module registers first, so that this entry replaces it (or is
        # refused) now, not when the module loads on a later get()
        _load_builtin()
    if name in _REGISTRY and not replace and _REGISTRY[name] is not scenario:
        raise InputError(f"register: a scenario named {name!r} is already registered")
    _REGISTRY[name] = scenario
    _REMOVED.discard(name)
    return scenario


def unregister(name: str) -> None:
    """Remove a scenario (no error if absent); meant for tests and notebooks."""
    if name in DECLARED and name not in _REMOVED:
        _load_builtin()  # a built-in not loaded yet: removed now, not registered by a later load
    if _REGISTRY.pop(name, None) is not None:
        _REMOVED.add(name)  # a built-in one removed stays out of names() and declared() too


def _load_builtin() -> None:
    """Import the built-in scenario modules once, so that they register.

    ``jaxslam.sim.scenarios`` either imports its scenario modules itself or lists
    their module names in ``BUILTIN_MODULES`` (then they are imported here, on first
    use).  Import errors inside a scenario module are real bugs and propagate.
    """
    global _BUILTIN_LOADED
    if _BUILTIN_LOADED:
        return
    _BUILTIN_LOADED = True
    try:
        pkg = importlib.import_module("jaxslam.sim.scenarios")
        for mod in getattr(pkg, "BUILTIN_MODULES", ()):
            importlib.import_module(mod)
    except BaseException:
        _BUILTIN_LOADED = False  # let a later call retry and raise the same error again
        raise


def get(name: str) -> Scenario:
    """The scenario called ``name``.

    Raises:
      InputError: no such scenario; the message lists the valid names.
    """
    _load_builtin()
    if not isinstance(name, str):
        raise InputError(f"name: expected a scenario name (a string), got {type(name).__name__}")
    try:
        return _REGISTRY[name]
    except KeyError:
        raise _unknown(name) from None


def declared(name: str):
    """What the command line needs of scenario ``name`` before its module is imported: the
    registered :class:`Scenario`, else the built-in scenario's declaration
    (:class:`~jaxslam.sim.scenarios.builtin.Declared`: ``name``, ``description``,
    ``options``), with no scenario module and no JAX imported.  :func:`check_options` takes
    either.

    Raises:
      InputError: no such scenario, with the message of :func:`get`.
    """
    if not isinstance(name, str):
        raise InputError(f"name: expected a scenario name (a string), got {type(name).__name__}")
    if name in _REGISTRY:
        return _REGISTRY[name]
    if not _BUILTIN_LOADED and name in DECLARED and name not in _REMOVED:
        return DECLARED[name]
    raise _unknown(name)


def _unknown(name: str) -> InputError:
    valid = ", ".join(names()) or "(none registered)"
    return InputError(f"unknown scenario {name!r}; valid scenarios: {valid}")


def names() -> list[str]:
    """Sorted names of all scenarios: those registered and the built-in ones.  The built-in
    names come from their declarations (:mod:`jaxslam.sim.scenarios.builtin`), so this imports
    no scenario module and no JAX."""
    if _BUILTIN_LOADED:
        return sorted(_REGISTRY)
    # (a built-in module imported directly registers its scenarios without _load_builtin: one
    # of them unregistered since is in _REMOVED, and get() would not find it either)
    return sorted(set(_REGISTRY) | (set(DECLARED) - _REMOVED))


def all_scenarios() -> list[Scenario]:
    """All registered scenarios, sorted by name."""
    _load_builtin()
    return [_REGISTRY[n] for n in sorted(_REGISTRY)]


def program_key(name: str, options: dict, params, dtype) -> dict:
    """What determines a scenario's compiled Monte Carlo program besides the code and the
    PRNG keys (see :func:`jaxslam.compilation.compile_program`)."""
    return {"scenario": name, "options": dict(options), "params": params, "dtype": str(np.dtype(dtype))}


def default_options(scenario: Scenario) -> dict:
    """``{option name: default}`` of a scenario (what ``run`` receives when no option is given)."""
    return {opt.name: opt.default for opt in scenario.options}


def check_options(scenario: Scenario, options: dict | None = None) -> dict:
    """``options`` completed with the scenario's defaults and checked as the command line
    checks them (what a scenario's ``run`` does with the ``options`` it is given);
    ``scenario`` is a :class:`Scenario` or what :func:`declared` returns.

    An unknown key, a value of the wrong type (an ``int`` for a ``float`` option is fine, a
    ``bool`` never stands for a number), a value outside ``choices`` or below ``lower`` raise
    :class:`InputError` naming the option (``--flag (options['key'])``); ``None`` is accepted
    where it is the default.  The scenario's ``run`` checks the values' meaning (ranges).
    """
    if options is None:
        options = {}
    if not isinstance(options, dict):
        raise InputError(f"options: expected a dict of scenario options, got {type(options).__name__}")
    known = {opt.name: opt for opt in scenario.options}
    unknown = sorted(map(str, set(options) - set(known)))
    if unknown:
        raise InputError(f"options: unknown key(s) {unknown} for scenario {scenario.name!r}; "
                         f"its options: {sorted(known) or 'none'}")
    out = default_options(scenario)
    for key, value in options.items():
        opt = known[key]
        where = f"{opt.flag} (options[{key!r}])"  # as the scenarios' own messages name it
        if value is None and opt.default is None:
            out[key] = value
            continue
        ok_types = (int, float, np.integer, np.floating) if opt.type is float else (
            (bool, np.bool_) if opt.type is bool else ((int, np.integer) if opt.type is int else (str,)))
        if not isinstance(value, ok_types) or (opt.type is not bool and isinstance(value, (bool, np.bool_))):
            raise InputError(f"{where}: expected {opt.type.__name__}, got {value!r}")
        try:
            value = opt.type(value)
        except OverflowError:  # float(10**400)
            raise InputError(f"{where}: expected a finite number, got an integer too large for a "
                             f"float ({len(str(abs(value)))} digits)") from None
        if opt.type is float and not np.isfinite(value):
            raise InputError(f"{where}: expected a finite number, got {value!r}")
        if opt.choices is not None and value not in opt.choices:
            raise InputError(f"{where}: expected one of {list(opt.choices)}, got {value!r}")
        if opt.lower is not None and value < opt.lower:
            raise InputError(f"{where}: expected >= {opt.lower}, got {value!r}")
        out[key] = value
    return out


def check_params(scenario: Scenario, obj, options: dict | None = None, dtype=np.float64) -> dict | None:
    """The sections of a parsed ``--params`` file for ``scenario``, checked against its schema.

    Unknown keys, wrong shapes, non-PSD matrices, and a file written for another scenario
    raise :class:`InputError` naming the key (:func:`jaxslam.paramfile.check`).  Returns
    ``None`` when the file sets nothing.
    """
    return _check_params(scenario, obj, options, dtype, where="--params")


def _check_params(scenario: Scenario, obj, options: dict | None, dtype, where: str) -> dict | None:
    # check_params with the messages' prefix: "--params" (the CLI's file), "params" (the
    # argument of ``Scenario.run``).
    if obj is None:
        return None
    options = default_options(scenario) if options is None else options
    schema = None if scenario.params is None else scenario.params(options, np.dtype(dtype))
    return paramfile.check(obj, schema, target=scenario.name, where=where) or None
