"""The built-in scenarios' declarations (jaxslam/sim/scenarios/builtin.py) against what their
modules register, and the registry's declaration-only answers (no scenario module, no JAX)."""

import os
import pathlib
import subprocess
import sys

import pytest

from jaxslam.errors import InputError
from jaxslam.sim import scenarios
from jaxslam.sim.scenarios import builtin, registry

REPO = pathlib.Path(__file__).resolve().parents[2]


def test_every_module_registers_exactly_what_is_declared():
    registered = {s.name: s for s in registry.all_scenarios()}  # imports the modules
    assert set(builtin.DECLARED) <= set(registered)
    for name, decl in builtin.DECLARED.items():
        s = registered[name]
        assert (s.name, s.description, s.options) == (decl.name, decl.description, decl.options), name
        assert s.run.__module__ == decl.module, name  # the module named registers it
        assert decl.module in scenarios.BUILTIN_MODULES, name
    assert {d.module for d in builtin.DECLARED.values()} == set(scenarios.BUILTIN_MODULES)


def test_declared_defaults_written_out_equal_the_constants_they_stand_for():
    from jaxslam.control import smc
    from jaxslam.sim.scenarios import ekfslam3d

    att = {o.name: o.default for o in builtin.DECLARED["attitude-smc"].options}
    assert (att["duration"], att["dt"], att["tau_max"]) == (smc.DURATION_S, smc.DT_S, smc.TAU_MAX_APPB)
    for mode in ("unknown", "known"):
        lm = {o.name: o.default for o in builtin.DECLARED[f"ekfslam3d-{mode}"].options}["landmarks"]
        assert lm == ekfslam3d.N_LANDMARKS


def test_declared_answers_like_get_and_check_options_takes_a_declaration():
    decl = registry.declared("uwb-circle")
    assert registry.check_options(decl) == registry.default_options(registry.get("uwb-circle"))
    with pytest.raises(InputError, match=r"--max-range \(options\['max_range'\]\): expected >= 0.0"):
        registry.check_options(decl, {"max_range": -1.0})
    with pytest.raises(InputError) as by_get:
        registry.get("no-such-scenario")
    with pytest.raises(InputError) as by_declared:
        registry.declared("no-such-scenario")
    assert str(by_declared.value) == str(by_get.value)
    with pytest.raises(InputError, match="^name: expected a scenario name"):
        registry.declared(3)


def test_registered_scenarios_are_declared_and_named_too():
    s = registry.Scenario("declared-test", "one line", (registry.Option("k", int, 1, "k", lower=0),),
                          lambda **kw: None)
    registry.register(s, replace=True)
    try:
        assert registry.declared("declared-test") is s and "declared-test" in registry.names()
    finally:
        registry.unregister("declared-test")
    assert "declared-test" not in registry.names()


def test_names_and_declarations_import_no_scenario_module_and_no_jax(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    code = ("import sys\n"
            "from jaxslam.sim.scenarios import registry\n"
            "names = registry.names()\n"
            "opts = registry.check_options(registry.declared('fastslam-helix'), {'particles': 7})\n"
            "loaded = [m for m in sys.modules if m.startswith('jaxslam.sim.scenarios.') and\n"
            "          m.rsplit('.', 1)[1] not in ('registry', 'builtin', 'option')]\n"
            "print(len(names), opts['particles'], loaded, 'jax' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=60)
    assert proc.stdout.split() == [str(len(builtin.DECLARED)), "7", "[]", "False"], (proc.stdout, proc.stderr)
