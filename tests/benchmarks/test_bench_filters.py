"""benchmarks/bench_filters.py: its NumPy EKF reference is the same filter, and the run returns
the bench JSON shape (a tiny run: ten small programs and the eager calls with the cache off)."""

import argparse
import pathlib
import sys

import jax
import numpy as np
import pytest


sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_filters  # noqa: E402


def test_numpy_reference_equals_ekf_filter_scan():
    from jaxslam.filters import ekf

    us, zs = bench_filters._simulate(60)
    import jax.numpy as jnp

    def f(x, u):
        return jnp.asarray(bench_filters.F) @ x + jnp.asarray(bench_filters.G) @ u

    def h(x):
        d = x[:2] - jnp.asarray(bench_filters.BEACON)
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    post = ekf.filter_scan(f, h, bench_filters.X0, bench_filters.P0, us, zs, None, bench_filters.Q,
                           bench_filters.R, residual=ekf.angle_residual([False, True]))
    np.testing.assert_allclose(np.asarray(post.means), bench_filters._numpy_ekf(us, zs), atol=1e-10)


def test_bench_run_shape():
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64")
    # 5 loop steps (1 FastSLAM step): the uncompiled references run op by op, ~1 s a FastSLAM step
    out = bench_filters.run(argparse.Namespace(steps=30, repeats=1, lag=5, iters=2, eager="off", loop_steps=5))
    cases = [r["case"] for r in out["results"]]
    assert cases[0] == "ekf" and "rts_pass" in cases and "numpy_ekf_loop" in cases
    assert out["results"][-1]["max_abs_diff_means"] < 1e-10
    assert out["targets"][0]["name"] == "rts_pass_vs_filter"
    eager = {(r["case"], r["persistent_cache"]): r for r in out["eager_calls"]}
    assert {c for c, _ in eager} == {"ekf", "ukf", "ekf+rts", "fixed_lag_5", "iterated_smoother_2",
                                     "ekf_step_loop_5", "ukf_step_loop_5", "sqrt_ekf_step_loop_5",
                                     "sqrt_ukf_step_loop_5", "ekf_slam_step_loop_5",
                                     "fastslam_step_loop_1"}
    assert ("ekf", False) in eager and ("ekf", True) not in eager  # --eager off: the cache-off rows only
    assert bench_filters._eager_calls({}, 1, "none") == []
    assert all(r["first_call_s"] > 0 and r["repeat_s"] > 0 and r["repeat_uncompiled_s"] > 0
               for r in eager.values())
