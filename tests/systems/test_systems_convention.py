"""Every system module follows the one convention written in :mod:`jaxslam.systems`: the same
names, the same argument order, ``key`` keyword-only, a static hashable ``Config``, a jitted
module-level ``_run`` whose cache a second call with new numbers does not grow (checked per
system in ``tests/test_compile_once.py``)."""

from __future__ import annotations

import importlib
import inspect

import pytest

from jaxslam import systems

NAMES = ("Config", "Params", "Log", "Event", "State", "StepOut", "Result", "init", "step", "run")


def _signature(fn):
    sig = inspect.signature(fn)
    pos = [p.name for p in sig.parameters.values()
           if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    kw = [p.name for p in sig.parameters.values() if p.kind == p.KEYWORD_ONLY]
    return pos, kw


def test_the_package_lists_every_system_module_and_loads_them_lazily():
    import pkgutil

    found = {m.name for m in pkgutil.iter_modules(systems.__path__)}
    assert found == set(systems.SYSTEMS) | {"biased_range", "estimator"}
    assert set(systems.SYSTEMS) <= set(dir(systems))
    assert systems.util_range is importlib.import_module("jaxslam.systems.util_range")
    with pytest.raises(AttributeError, match="no_such_system"):
        systems.no_such_system  # noqa: B018


@pytest.mark.parametrize("name", systems.SYSTEMS)
def test_system_follows_the_convention(name):
    mod = importlib.import_module(f"jaxslam.systems.{name}")
    missing = [n for n in NAMES if not hasattr(mod, n)]
    assert not missing, f"{name} lacks {missing}"
    assert _signature(mod.init) == (["log", "config", "params"], ["key"])
    assert _signature(mod.step) == (["state", "event", "config", "params"], ["key"])
    assert _signature(mod.run) == (["log", "config", "params"], ["key"])
    # Config is static: a hashable NamedTuple (it keys the jit cache).
    assert hasattr(mod.Config, "_fields")
    for cls in ("Params", "Log", "Event", "StepOut", "Result"):
        assert hasattr(getattr(mod, cls), "_fields"), f"{name}.{cls} is not a NamedTuple"
    # One jitted program per system, config static.
    assert hasattr(mod._run, "_cache_size"), f"{name}._run is not jitted"
    # Every public name of the convention is documented.
    for n in NAMES:
        obj = getattr(mod, n)
        doc = inspect.getdoc(obj) or ""
        if inspect.isclass(obj) and doc.startswith(f"{obj.__name__}("):
            doc = ""  # only the NamedTuple's generated one
        assert doc.strip(), f"{name}.{n} has no docstring"


@pytest.mark.parametrize("name", systems.SYSTEMS)
def test_config_is_hashable(name):
    mod = importlib.import_module(f"jaxslam.systems.{name}")
    assert hash(mod.Config()) == hash(mod.Config())  # every field has a default
