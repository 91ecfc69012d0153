"""A scenario driven from Python (``registry.get(name).run(...)``, the modules' public ``build`` /
``run_scenario``, :func:`jaxslam.sim.simulate.simulate`) checks its arguments as the command line
does: ``params``, ``options``, ``dtype`` and ``plots`` are :class:`InputError` s naming the
argument or option, before anything compiles.  Before, a misspelt ``params`` section or option
ran with the defaults, ``"False"`` switched a flag on, float64 silently computed in float32 and
a negative ramp or range was flown as 0 / unlimited."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import attitude, ekfslam3d, fastslam, lineslam, registry
from jaxslam.sim.scenarios import uwb
from jaxslam.sim.scenarios.tracking import controller_from_dict, controller_to_dict, make_setup, paper000_figure8
from jaxslam.sim.simulate import simulate
from jaxslam.control import dflqr

EKF_OPTS = {"duration": 5.0, "q": "imu", "association": "known", "capacity": 64, "landmarks": 40,
            "max_obs": 16, "control_on": "estimate", "accel": "3axis", "altitude": 3.0, "no_feedforward": False}


def _run(name, options=None, **kw):
    args = dict(runs=1, seed=0, dtype=np.float32, options={"duration": 0.15} if options is None else options,
                progress=Progress.null())
    args.update(kw)
    return registry.get(name).run(**args)


# ------------------------------------------------------------------ 1. params from Python


@pytest.mark.parametrize("params, needle", [
    ({"bogus": 1}, r"^params: unknown key\(s\) \['bogus'\]"),
    ({"controler": {"kp": [1, 2, 3]}}, r"^params: unknown key\(s\) \['controler'\]"),
    ({"controller": {"kp": ["1.5", "2", "3"]}}, r"^params: controller\.kp: expected numbers"),
    ({"controller": {"kp": [1.0, 2.0]}}, r"^params: controller\.kp: expected 3"),
])
def test_run_checks_params_like_the_cli(params, needle):
    with pytest.raises(InputError, match=needle):
        _run("track-figure8", params=params)
    with pytest.raises(InputError, match=r"^params: "):  # by position too
        registry.get("track-figure8").run(1, 0, np.float32, {"duration": 0.15}, Progress.null(), params)


def test_params_of_scenarios_without_a_schema_and_of_build():
    with pytest.raises(InputError, match=r"^params: scenario 'attitude-smc' takes no --params file"):
        _run("attitude-smc", options={}, params={"noise": {}})
    with pytest.raises(InputError, match=r"^params: unknown key\(s\) \['nosie'\]"):
        ekfslam3d.build(EKF_OPTS, "unknown", jnp.float32, params={"nosie": {}})
    with pytest.raises(InputError, match=r"^params: unknown key\(s\) \['filtre'\]"):
        lineslam.build({}, np.float32, params={"filtre": {}})
    with pytest.raises(InputError, match=r"^params\.controller\.kp: expected numbers"):
        controller_from_dict({"kp": ["1.5", "2", "3"]}, dflqr.paper000_params())


# ------------------------------------------------------------------ 2. build's options


@pytest.mark.parametrize("change, needle", [
    ({"no_feedforward": "False"}, r"^--no-feedforward \(options\['no_feedforward'\]\): expected bool"),
    ({"capacity": 64.9}, r"^--capacity \(options\['capacity'\]\): expected int"),
    ({"landmarks": True}, r"^--landmarks \(options\['landmarks'\]\): expected int"),
    ({"landmarks": 0}, r"^--landmarks \(options\['landmarks'\]\): expected >= 1"),
    ({"duration": "5"}, r"^--duration \(options\['duration'\]\): expected float"),
    ({"control_on": "Estimate"}, r"^--control-on \(options\['control_on'\]\): expected one of"),
    ({"accel": "xyz"}, r"^--accel \(options\['accel'\]\): expected one of"),
    ({"altitude": float("nan")}, r"^--altitude \(options\['altitude'\]\): expected a finite number"),
    ({"assocation": "nn"}, r"^options: unknown key\(s\) \['assocation'\]"),
])
def test_ekfslam3d_build_checks_its_options(change, needle):
    with pytest.raises(InputError, match=needle):
        ekfslam3d.build({**EKF_OPTS, **change}, mode="unknown", dtype=jnp.float32)
    with pytest.raises(InputError, match=needle):
        ekfslam3d.run_scenario("ekfslam3d-known", "known", 1, 0, np.float32, {**EKF_OPTS, **change}, None)


def test_other_builds_check_their_options():
    with pytest.raises(InputError, match=r"^mode: expected one of \['known', 'unknown'\]"):
        ekfslam3d.build(EKF_OPTS, mode="nown", dtype=jnp.float32)
    with pytest.raises(InputError, match=r"^--particles \(options\['particles'\]\): expected int"):
        fastslam.build({"particles": 2.0}, np.float32)
    with pytest.raises(InputError, match=r"^--particles \(options\['particles'\]\): expected >= 1"):
        fastslam.run_scenario(1, 0, np.float32, {"particles": 0}, None)
    with pytest.raises(InputError, match=r"^--capacity \(options\['capacity'\]\): expected int"):
        lineslam.build({"capacity": 1.5}, np.float32)
    with pytest.raises(InputError, match=r"^options: unknown key\(s\) \['tilt'\]"):
        lineslam.run_scenario(1, 0, np.float32, {"tilt": 1.0}, None)
    with pytest.raises(InputError, match=r"^options: unknown key\(s\) \['mdoe'\]"):
        uwb.build("circle", {"mdoe": "slam"}, np.float32)
    with pytest.raises(InputError, match=r"^--smooth \(options\['smooth'\]\): expected bool"):
        uwb.run_scenario("circle", 1, 0, np.float32, {"smooth": "no"}, None)
    with pytest.raises(InputError, match=r"^scenario: expected one of"):
        uwb.build("triangle", {}, np.float32)
    with pytest.raises(InputError, match=r"^--gains \(options\['gains'\]\): expected one of"):
        attitude.build({"gains": "paper"}, np.float32)
    with pytest.raises(InputError, match=r"^--tau-max \(options\['tau_max'\]\): expected float"):
        attitude.run_scenario(1, 0, np.float32, {"tau_max": "0.2"}, None)


# ------------------------------------------------------------------ 3. dtype


@pytest.mark.parametrize("dtype", [np.float16, "int32", jnp.bfloat16, np.complex64, None, "nope"])
def test_run_refuses_other_dtypes(dtype):
    with pytest.raises(InputError, match=r"^dtype: expected float32 or float64"):
        _run("track-figure8", dtype=dtype)
    with pytest.raises(InputError, match=r"^dtype: expected float32 or float64"):
        ekfslam3d.build(EKF_OPTS, "unknown", dtype)


def test_float64_needs_x64():
    with jax.enable_x64(False):
        with pytest.raises(InputError, match=r"^dtype: float64 needs JAX's 64-bit mode.*jax_enable_x64"):
            _run("track-figure8", dtype=np.float64)
        with pytest.raises(InputError, match=r"^dtype: float64 needs"):
            lineslam.build({}, jnp.float64)
        # float32 passes the dtype check: the (bad) options are what fails
        with pytest.raises(InputError, match=r"^options: unknown key"):
            _run("track-figure8", options={"bogus": 1}, dtype=np.float32)
    with pytest.raises(InputError, match=r"^options: unknown key"):  # x64 on: float64 is fine
        _run("track-figure8", options={"bogus": 1}, dtype=np.float64)


# ------------------------------------------------------------------ 4. duration flown


def test_config_records_the_duration_flown():
    """0.15 s is one LiDAR frame (0.1 s) of flight: the config says so beside the 0.15 asked for
    (a Python ``params`` equal to the defaults is accepted as before)."""
    params = {"controller": controller_to_dict(dflqr.paper000_params())}
    r = _run("track-figure8", options={"duration": 0.15}, params=params)
    assert r.config["duration_s"] == 0.15 and r.config["duration_flown_s"] == 0.1
    assert r.metrics["track_pos_rmse_m"].shape == (1,) and np.all(np.isfinite(r.metrics["track_pos_rmse_m"]))
    opts = {**registry.default_options(attitude.SCENARIO), "duration": 0.0104, "dt": 0.001}
    _, _, setup = attitude.build(opts, np.float32)
    assert setup["steps"] == 10 and setup["duration_flown_s"] == 0.01


# ------------------------------------------------------------------ 5. meaningless values


def test_meaningless_values_are_refused():
    with pytest.raises(InputError, match=r"^--ramp \(options\['ramp'\]\): expected >= 0"):
        _run("track-figure8", options={"duration": 0.15, "ramp": -1.0})
    with pytest.raises(InputError, match=r"^ramp: "):
        paper000_figure8(3.0, -1.0)
    for alt in (float("nan"), float("inf")):
        with pytest.raises(InputError, match=r"^altitude: "):
            paper000_figure8(alt, 0.0)
    with pytest.raises(InputError, match=r"^--max-range \(options\['max_range'\]\): expected >= 0"):
        registry.check_options(registry.get("uwb-circle"), {"max_range": -5.0})
    assert registry.check_options(registry.get("uwb-circle"), {"max_range": 0.0})["max_range"] == 0.0
    with pytest.raises(InputError, match=r"^plots: expected True or False, got 'yes'"):
        _run("track-figure8", plots="yes")
    with pytest.raises(InputError, match=r"^plots: expected True or False"):
        lineslam.run_scenario(1, 0, np.float32, {}, None, plots=1)
    setup = make_setup(paper000_figure8(), jnp.float32)
    key = jax.random.PRNGKey(0)
    for kw, needle in (({"feedforward": "no"}, r"^feedforward: expected True or False"),
                       ({"feedforward": 0}, r"^feedforward: expected True or False"),
                       ({"checkpoint": "yes"}, r"^checkpoint: expected True or False")):
        with pytest.raises(InputError, match=needle):
            simulate(setup, key, 1, 10, **kw)
    with pytest.raises(InputError, match=r"option 'x': lower"):  # lower of a str option: a broken scenario
        registry.register(registry.Scenario("bad-lower", "d", (registry.Option("x", str, "a", "h", lower=0),),
                                            lambda **kw: None))


# ------------------------------------------------------------------ 6, 7, 8


def test_huge_integer_option_is_an_input_error():
    with pytest.raises(InputError, match=r"^--duration \(options\['duration'\]\): expected a finite number"):
        registry.check_options(registry.get("track-figure8"), {"duration": 10**400})


def test_control_on_is_an_input_error():
    setup = make_setup(paper000_figure8(), jnp.float32)
    with pytest.raises(InputError, match=r"^control_on: expected 'truth' or 'estimate', got 'est'"):
        simulate(setup, jax.random.PRNGKey(0), 1, 10, control_on="est")
    with pytest.raises(InputError, match=r"^control_on: 'estimate' needs an estimator"):
        simulate(setup, jax.random.PRNGKey(0), 1, 10, control_on="estimate")


def test_lidar_measurements_take_the_flights_dtype():
    lms = jnp.asarray(np.random.RandomState(0).uniform(-5, 5, (4, 3)), jnp.float64)
    setup = make_setup(paper000_figure8(), jnp.float32, landmarks=lms)
    fl = jax.eval_shape(lambda k: simulate(setup, k, 1, 10), jax.random.PRNGKey(0))
    assert fl.truth.dtype == jnp.float32 and fl.lidar_y.dtype == jnp.float32
