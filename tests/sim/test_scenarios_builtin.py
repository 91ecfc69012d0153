"""The built-in scenarios' declarations (jaxslam/sim/scenarios/builtin.py) against what their
modules register, and the registry's declaration-only answers (no scenario module, no JAX)."""

import os
import pathlib
import subprocess
import sys

import numpy as np
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
        schema = None if s.params is None else s.params(registry.default_options(s), np.dtype(np.float64))
        assert decl.params_sections == (None if schema is None else tuple(schema)), name
        assert decl.module in scenarios.BUILTIN_MODULES, name
    assert {d.module for d in builtin.DECLARED.values()} == set(scenarios.BUILTIN_MODULES)
    # and no built-in module registers a scenario that is not declared
    by_modules = {n for n, s in registered.items() if s.run.__module__ in scenarios.BUILTIN_MODULES}
    assert by_modules == set(builtin.DECLARED)


def test_declared_defaults_written_out_equal_the_constants_they_stand_for():
    from jaxslam.control import smc
    from jaxslam.sim.scenarios import ekfslam3d

    att = {o.name: o.default for o in builtin.DECLARED["attitude-smc"].options}
    assert (att["duration"], att["dt"], att["tau_max"]) == (smc.DURATION_S, smc.DT_S, smc.TAU_MAX_APPB)
    for mode in ("unknown", "known"):
        lm = {o.name: o.default for o in builtin.DECLARED[f"ekfslam3d-{mode}"].options}["landmarks"]
        assert lm == ekfslam3d.N_LANDMARKS
    # the flights' shortest --duration is one sensor frame of their own module
    from jaxslam.sim.scenarios import fastslam, tracking

    frame = {"track-figure8": tracking.DT * tracking.FRAME_STEPS, "track-helix": tracking.DT * tracking.FRAME_STEPS,
             "ekfslam3d-unknown": tracking.DT * tracking.FRAME_STEPS, "ekfslam3d-known": ekfslam3d.DT * ekfslam3d.FRAME_STEPS,
             "fastslam-helix": fastslam.DT * fastslam.LIDAR_EVERY}
    for name, shortest in frame.items():
        lower = {o.name: o.lower for o in builtin.DECLARED[name].options}["duration"]
        assert lower == shortest, name


def test_check_options_takes_a_declaration_and_declared_fails_like_get():
    decl = builtin.DECLARED["uwb-circle"]
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


def _fresh(code, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.split()


def test_names_and_declarations_import_no_scenario_module_and_no_jax(tmp_path):
    code = ("import sys\n"
            "from jaxslam.sim.scenarios import registry\n"
            "names = registry.names()\n"
            "decl = registry.declared('fastslam-helix')\n"
            "opts = registry.check_options(decl, {'particles': 7})\n"
            "try:\n"
            "    registry.declared('no-such-scenario')\n"
            "except registry.InputError as e:\n"
            "    before = str(e)\n"
            "loaded = [m for m in sys.modules if m.startswith('jaxslam.sim.scenarios.') and\n"
            "          m.rsplit('.', 1)[1] not in ('registry', 'builtin', 'option')]\n"
            "print(len(names), type(decl).__name__, opts['particles'], loaded, 'jax' in sys.modules)\n"
            "try:\n"
            "    registry.get('no-such-scenario')  # imports the modules\n"
            "except registry.InputError as e:\n"
            "    print(str(e) == before, registry.names() == names)")
    assert _fresh(code, tmp_path) == [str(len(builtin.DECLARED)), "Declared", "7", "[]", "False", "True", "True"]


def test_a_builtin_scenario_unregistered_is_gone_from_names_and_declared_too(tmp_path):
    # a scenario module imported directly (not through the registry's loader) registers its
    # scenarios; one of them unregistered must not come back from the declarations
    code = ("from jaxslam.sim.scenarios import registry, uwb\n"
            "registry.unregister('uwb-circle')\n"
            "def fails(f):\n"
            "    try:\n"
            "        f('uwb-circle')\n"
            "    except registry.InputError:\n"
            "        return True\n"
            "    return False\n"
            "print('uwb-circle' in registry.names(), fails(registry.declared), fails(registry.get),\n"
            "      'uwb-circle' in registry.names(), 'uwb-square' in registry.names())\n"
            "registry.register(uwb._SCENARIOS['circle'])\n"
            "print('uwb-circle' in registry.names(), fails(registry.declared))")
    assert _fresh(code, tmp_path) == ["False", "True", "True", "False", "True", "True", "False"]


def test_a_builtin_name_registered_or_unregistered_before_the_builtins_load(tmp_path):
    # Before the built-ins loaded (lazily, on the first get), register() of a built-in's name
    # succeeded and the next get() then failed for every scenario (the module's own register
    # refused the taken name, again at each retry); unregister() did nothing.
    code = ("import dataclasses\n"
            "from jaxslam.sim.scenarios import registry\n"
            "from jaxslam.sim.scenarios.builtin import DECLARED\n"
            "def mine(**kw):\n"
            "    raise RuntimeError('not run here')\n"
            "try:\n"
            "    registry.register(registry.Scenario('uwb-circle', 'mine', (), mine))\n"
            "except registry.InputError as e:\n"
            "    print('refused', 'already registered' in str(e))\n"
            "s = registry.register(registry.Scenario('uwb-circle', 'mine', (), mine), replace=True)\n"
            "print(registry.get('uwb-circle').description, registry.get('uwb-square').name)\n"
            "registry.unregister('track-helix')\n"
            "print('track-helix' in registry.names(), 'track-figure8' in registry.names())")
    assert _fresh(code, tmp_path) == ["refused", "True", "mine", "uwb-square", "False", "True"]


def test_scenario_options_may_not_take_the_names_of_the_run_command_s_own_options():
    # --threads, --processes, --coordinator, --num-processes, --process-id were missing: a
    # scenario option of that name registered, and 'jaxslam run' then failed with an internal
    # argparse conflict when a user ran it
    from jaxslam.cli import run as cli_run

    own = {a.dest for a in cli_run._run_parser()._actions} - {"scenario"}
    assert own <= registry.RESERVED_OPTION_NAMES, own - registry.RESERVED_OPTION_NAMES
    for name in sorted(own):
        opt = registry.Option(name, int, 1, "x")
        with pytest.raises(InputError, match=name):
            registry.register(registry.Scenario("reserved-test", "x", (opt,), lambda **kw: None))


def test_help_of_a_builtin_without_params_file_needs_no_jax_and_is_the_full_help(tmp_path):
    # 'jaxslam run attitude-smc --help' imported JAX and the scenario module (8 s against 1.4 s)
    code = ("import contextlib, io, sys\n"
            "from jaxslam import cli\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out):\n"
            "    rc = cli.main(['run', '{name}', '--help'])\n"
            "print(rc, 'jax' in sys.modules)\n"
            "import jax\n"
            "jax.config.update('jax_enable_x64', True)\n"
            "from jaxslam.cli import run\n"
            "full = run._run_parser(registry.get('{name}'), help_params=True).format_help()\n"
            "print(out.getvalue() == full, 'takes no --params file' in full)")
    for name, d in builtin.DECLARED.items():
        if d.params_sections is None:
            src = code.replace("{name}", name).replace("from jaxslam import cli\n",
                                                       "from jaxslam import cli\nfrom jaxslam.sim.scenarios import registry\n")
            assert _fresh(src, tmp_path) == ["0", "False", "True", "True"], name
