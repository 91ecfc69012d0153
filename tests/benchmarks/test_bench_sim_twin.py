"""The NumPy twin of the closed-loop flight (tests/oracles/numpy_flight.py) vs jaxslam's simulate.

The twin is the oracle that ``bench sim`` compares like with like: it is written without
autodiff (closed-form trajectory derivatives, hand chain rule / jets for the feedforward,
SciPy's CARE for the gain), so agreement to 1e-8 in float64 means both do the same work.
The IMU noise is identical: ``bench_sim.imu_standard_normals`` reproduces the keys simulate
draws from, so the noisy IMU arrays are compared too (a wrong key schedule would differ by
the noise σ, ~0.03 m/s²).
"""

import argparse
import math
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

BENCH_DIR = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH_DIR))

import bench_sim  # noqa: E402
import numpy_flight  # noqa: E402

from jaxslam.control import dflqr, flatness, trajectories  # noqa: E402

DURATION = 3.0  # s: shared by the agreement and smoke tests so they share one compilation
N_FRAME = int(round(DURATION / (0.01 * bench_sim.LIDAR_EVERY)))
TOL = 1e-8


@pytest.fixture(scope="module")
def setup():
    return bench_sim.make_setup(jnp.float64)


def test_twin_trajectory_derivatives_match_jaxslam(setup):
    """Closed-form figure-8 derivatives (orders 0-4, yaw 0-2) = jaxslam's nested jvp."""
    traj_np = numpy_flight.Figure8Params.from_container(setup.traj)
    fd = jax.jit(lambda t: trajectories.flat_derivatives(setup.traj, t, 4))
    for t in (0.0, 0.37, 2.9, 6.1, 13.0, 24.4, 41.7):
        Y = np.asarray(fd(jnp.float64(t)))
        P, yaw = numpy_flight.flat_derivatives(traj_np, t)
        np.testing.assert_allclose(P, Y[:, 0:3], rtol=0, atol=TOL)
        # ψ itself may differ by 2π at the atan2 branch; compare wrapped.
        assert abs(math.remainder(yaw[0] - Y[0, 3], 2 * math.pi)) < TOL
        np.testing.assert_allclose(yaw[1:], Y[1:3, 3], rtol=0, atol=TOL)


def test_twin_feedforward_and_gain_match_jaxslam(setup):
    """Jet-arithmetic feedforward (Λ_d, ω_d, τ_ff) and SciPy's K = jaxslam's jvp / CARE."""
    traj_np = numpy_flight.Figure8Params.from_container(setup.traj)
    ctrl_np = numpy_flight.ControllerNp.from_params(setup.ctrl)
    ff = jax.jit(lambda t: flatness.feedforward(setup.traj, t, setup.ctrl.quad))
    for t in (0.0, 1.3, 7.7, 19.2):
        x_d, u_ff = (np.asarray(a) for a in ff(jnp.float64(t)))
        P, yaw = numpy_flight.flat_derivatives(traj_np, t)
        lam, omega, tau = numpy_flight.feedforward(P, yaw, ctrl_np.quad)
        np.testing.assert_allclose(lam[0:2], x_d[6:8], rtol=0, atol=TOL)
        np.testing.assert_allclose(omega, x_d[9:12], rtol=0, atol=TOL)
        np.testing.assert_allclose(tau, u_ff[1:4], rtol=0, atol=TOL)
    K_np = numpy_flight.lqr_gain(ctrl_np.Q, ctrl_np.R)
    np.testing.assert_allclose(K_np, np.asarray(dflqr.gain(setup.ctrl, jnp.float64)),
                               rtol=0, atol=1e-10)


def _agreement(setup, feedforward, x0=None):
    fn = jax.jit(bench_sim.jax_runner(setup, N_FRAME, bench_sim.LIDAR_EVERY, feedforward))
    key = jax.random.fold_in(jax.random.PRNGKey(0), 0)
    x0 = setup.x0 if x0 is None else jnp.asarray(x0)
    fl = fn(key, x0)
    noise = np.asarray(bench_sim.imu_standard_normals(key, N_FRAME))
    traj, ctrl, sigma, dt = bench_sim.numpy_inputs(setup)
    ref = numpy_flight.simulate(traj, ctrl, np.asarray(x0), dt, N_FRAME * bench_sim.LIDAR_EVERY,
                                sigma, noise, feedforward)
    # the flight is not trivial: it leaves the origin and the controller works
    assert np.max(np.abs(ref["truth"][:, 0:3])) > 1.0
    for name in ("t", "truth", "ref", "u", "imu"):
        np.testing.assert_allclose(np.asarray(getattr(fl, name)), ref[name], rtol=0, atol=TOL,
                                   err_msg=name)
    # the IMU noise really is there (σ_a ≈ 0.029 m/s²) and identical in both
    assert np.std(ref["imu"][1:, 0] - ref["imu"][:-1, 0]) > 0.01


def test_twin_closed_loop_agrees_with_simulate(setup):
    """3 s closed-loop flight with the flatness feedforward: truth, u, IMU, ref to 1e-8."""
    _agreement(setup, True)


@pytest.mark.slow
def test_twin_closed_loop_agrees_without_feedforward_and_offset_start(setup):
    """Paper's eq. 19 references (no feedforward), from an offset start (as the batch cases)."""
    x0 = bench_sim.batch_initial_states(1, 1, 0.5)[0]
    _agreement(setup, False, x0)


def _args(**kw):
    base = dict(duration=DURATION, batches="", repeats=1, numpy_repeats=1, numpy_batch_max=1,
                x0_spread=0.5, seed=0, no_feedforward=False, openblas_check=False,
                profile=False)
    base.update(kw)
    return argparse.Namespace(**base)


def _check_row(row, runs):
    for k in ("case", "params", "jaxslam_s", "reference", "reference_s", "speedup",
              "steps_per_s_jax", "steps_per_s_numpy", "compile_s"):
        assert k in row, k
    assert row["reference"] == "numpy loop"
    assert row["jaxslam_s"] > 0 and row["reference_s"] > 0 and row["compile_s"] > 0
    assert row["speedup"] == pytest.approx(row["reference_s"] / row["jaxslam_s"])
    steps = N_FRAME * bench_sim.LIDAR_EVERY
    assert row["params"]["steps"] == steps and row["params"]["runs"] == runs
    assert row["steps_per_s_jax"] == pytest.approx(runs * steps / row["jaxslam_s"])
    assert row["steps_per_s_numpy"] == pytest.approx(runs * steps / row["reference_s"])


def test_bench_run_returns_bench_json_shape():
    """Smoke test of bench_sim.run with a tiny config (shape only, no timing assertion)."""
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64 (tests/conftest.py enables it)")
    out = bench_sim.run(_args())
    assert out["benchmark"] == "sim"
    assert isinstance(out["machine"], dict) and "cpu_count" in out["machine"]
    assert [r["case"] for r in out["results"]] == ["single"]
    row = out["results"][0]
    _check_row(row, 1)
    assert row["max_abs_diff_truth"] < TOL and row["max_abs_diff_imu"] < TOL


@pytest.mark.slow
def test_bench_run_batch_case_shape():
    out = bench_sim.run(_args(batches="2"))
    assert [r["case"] for r in out["results"]] == ["single", "batch-2"]
    _check_row(out["results"][1], 2)
    assert out["results"][1]["params"]["numpy_runs_timed"] == 1
    # the vmapped run from an offset start is the NumPy run from the same start and noise
    assert out["results"][1]["max_abs_diff_truth"] < TOL
