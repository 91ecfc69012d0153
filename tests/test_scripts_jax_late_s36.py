"""The last six scripts that imported JAX at the top read their arguments first: --help and a
usage error exit before JAX loads (as tests/test_scripts_s36.py checks for the nine converted
before them), and the helpers that callers outside main use keep working with their defaults.
Oracles by hand: argparse exits 0 for --help and 2 for an unknown option; JAX must not be in
sys.modules after either; plaza_range.PARAMS' p0_pos 0.1 m, p0_th 0.02 rad, sigma_bias0 5 m."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np
import pytest
from script_modules import JAX_PROBE as _PROBE, load_script

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = str(ROOT / "tests" / "data")

LATE = ["study_plaza_smoothing", "study_range_only", "study_util_anchor_bias", "study_victoria_park_ekf",
        "reproduce_plaza_smoothing", "reproduce_tuning"]
# the arguments a script requires, so that the usage error is the unknown option's
REQUIRED = {"reproduce_plaza_smoothing": ["--data", DATA], "study_util_anchor_bias": ["0.1", "5", "none"]}


def _probe(script, *argv):
    return subprocess.run([sys.executable, "-c", _PROBE, str(ROOT / "scripts" / f"{script}.py"), *argv],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)


@pytest.mark.parametrize("script", LATE)
@pytest.mark.parametrize("argv, code", [(["--help"], 0), (["--no-such-option"], 2)])
def test_help_and_usage_errors_exit_before_jax_loads(script, argv, code):
    # each imported JAX (and the systems) at the top: both answers came after it loaded
    r = _probe(script, *(REQUIRED.get(script, []) if code == 2 else []), *argv)
    assert r.returncode == code, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1] == "no jax", r.stderr[-2000:]
    if code == 0:
        assert r.stdout.startswith(f"usage: {script}.py"), r.stdout[:200]
    else:
        assert f"{script}.py: error: unrecognized arguments: --no-such-option" in r.stderr, r.stderr[-2000:]


def test_plaza_smoothing_unknown_config_before_jax_loads():
    # the configuration table is built from plaza_range.PARAMS (JAX): its names are checked without it
    r = _probe("study_plaza_smoothing", "--configs", "nope")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and lines[-1] == "no jax", r.stderr[-2000:]
    assert lines[0].startswith("study_plaza_smoothing.py: error: --configs: unknown configuration(s) nope; "
                               "choose from gn-plain, lm-gauss, "), lines[0]


def test_plaza_smoothing_config_table_after_the_import():
    m = load_script("study_plaza_smoothing", "late")
    m._import_jax()
    assert tuple(m.CFG) == m.CONFIG_NAMES and len(m.CONFIG_NAMES) == 15
    assert m.CFG["huber"].start == "lm-gauss" and m.CFG["huber"].sigma_r == 1.2
    assert m.CFG["lm-gauss"].start_sig == (0.1, 0.02)
    assert set(m.QUICK) <= set(m.CONFIG_NAMES)


def test_plaza_smoothing_problem_defaults_are_the_filters_prior():
    # start_sig / sigma_bias0 defaulted to pr.PARAMS at definition: now None, resolved inside
    m = load_script("study_plaza_smoothing", "late2")
    m._import_jax()
    T = 3
    prep = {"pose0": np.zeros(3), "ekf_beacons": np.zeros((4, 2)), "dt": np.ones(T), "u": np.zeros((T, 2)),
            "zr": np.zeros((T, 2)), "slot": np.zeros((T, 2), np.int32), "valid": np.zeros((T, 2), bool)}
    pb = m.problem(prep, m.NZ)
    np.testing.assert_allclose(np.diag(np.asarray(pb.P0))[:6], [0.01, 0.01, 0.0004, 25.0, 0.0, 0.0], rtol=1e-12)
    pb = m.problem(prep, m.NZ, start_sig=(1.0, 2.0), sigma_bias0=3.0)
    np.testing.assert_allclose(np.diag(np.asarray(pb.P0))[:4], [1.0, 1.0, 4.0, 9.0], rtol=1e-12)


def test_victoria_park_helpers_keep_working_from_outside_main():
    # the interpreter investigations: load(), make_log(), run() with its float32 default
    # (dtype=jnp.float32 was a default bound at import; now None, resolved after JAX loads)
    m = load_script("study_victoria_park_ekf", "late")
    m.load(DATA)
    log = m.make_log()
    out, r = m.run(m.presets.victoria_park_config(), m.presets.victoria_park_params(), log, time_it=False,
                   quiet=True)
    assert r.pose.dtype == np.float32 and out["finite"] and out["status"] == 0
    assert out["run_s"] is None and out["n_meas"] > 0


class _Reached(Exception):
    pass


@pytest.mark.parametrize("study, system, call", [("util", "util_range", lambda m, f64: m.util(f64)),
                                                 ("plaza", "plaza_range", lambda m, f64: m.plaza(1, f64))])
def test_range_only_studies_default_to_the_shipped_params(monkeypatch, study, system, call):
    # params=ur.PARAMS / pr.PARAMS were defaults bound at import: now None, resolved after JAX loads
    import importlib

    import jax.numpy as jnp

    mod = importlib.import_module(f"jaxslam.systems.{system}")
    seen = []

    def fake_run(log, cfg, params):
        seen.append(params)
        raise _Reached

    monkeypatch.setattr(mod, "run", fake_run)
    m = load_script("study_range_only", "late")
    m.DATA = DATA
    with pytest.raises(_Reached):
        call(m, jnp.float64)
    expected = mod.PARAMS._replace(gate=9.0) if study == "util" else mod.PARAMS
    assert seen == [expected]


def test_plaza_smoothing_study_says_which_beacon_the_ekf_never_initialised():
    # s36: prepare() indexed the EKF's beacons with an IndexError traceback when a beacon was never
    # initialised (the short Plaza 1 excerpt); now one line and exit 1, as reproduce_plaza_smoothing
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "study_plaza_smoothing.py"), "--data", DATA,
                        "--robot", "1", "--configs", "lm-gauss"], capture_output=True, text=True, timeout=600)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1, r.stderr[-2000:]
    assert lines[0].startswith("study_plaza_smoothing.py: error: --robot 1: Plaza 1: the EKF never initialised "
                               "beacon(s) "), lines
