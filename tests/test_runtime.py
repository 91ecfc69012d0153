"""jaxslam.runtime: entry-point process settings (OpenBLAS threads, XLA workaround flags)."""

import os
import subprocess
import sys

import jax
import pytest

from jaxslam import runtime


def test_configure_process_keeps_user_choices_and_adds_missing_flags(monkeypatch):
    # Start JAX's backend first: it reads XLA_FLAGS once, and aborts on flags it does not know.
    jax.numpy.ones(1).block_until_ready()
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")
    given = ("--xla_cpu_enable_concurrency_optimized_scheduler=true --xla_cpu_use_fusion_emitters=true "
             "--xla_cpu_multi_thread_eigen=true")
    monkeypatch.setenv("XLA_FLAGS", given)
    out = runtime.configure_process(cache=False)
    assert out["OPENBLAS_NUM_THREADS"] == "3"
    assert os.environ["XLA_FLAGS"] == given
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS")
    with pytest.warns(RuntimeWarning, match="already started"):
        runtime.configure_process(cache=False)
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_multi_thread_eigen=true", *runtime.XLA_WORKAROUND_FLAGS]
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"


def test_cli_sets_flags_before_jax_starts():
    """Importing the CLI package changes nothing; calling its ``main`` configures the process
    before JAX's backend starts."""
    code = ("import os; os.environ.pop('XLA_FLAGS', None); import jaxslam.cli; "
            "assert 'XLA_FLAGS' not in os.environ, 'import-time side effect'; "
            "jaxslam.cli.main(['cache', 'info', '--json']); "
            "import jax.numpy as jnp; jnp.ones(1).block_until_ready(); print(os.environ['XLA_FLAGS'])")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert runtime.XLA_WORKAROUND_FLAGS[0] in out.stdout
    assert "already started" not in out.stderr


def _fresh(code, **env_over):
    """Run ``code`` in a new interpreter with none of the entry points' settings."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("XLA_FLAGS", "OPENBLAS_NUM_THREADS", "JAXSLAM_LAPACK_THREADS")}
    env.update(env_over)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


def test_import_pins_lapack_pool_and_changes_nothing_else():
    code = ("import os, jax; before = (os.environ.get('XLA_FLAGS'), jax.config.jax_enable_x64); "
            "import jaxslam; from jaxslam import runtime; "
            "print(runtime.lapack_threads(), before == (os.environ.get('XLA_FLAGS'), jax.config.jax_enable_x64))")
    assert _fresh(code) == "1 True"
    # A user's own choice stands; JAXSLAM_LAPACK_THREADS=0 opts out, =2 sets two.
    assert _fresh(code, OPENBLAS_NUM_THREADS="2") == "2 True"
    assert _fresh(code, JAXSLAM_LAPACK_THREADS="2") == "2 True"


def test_vmapped_filter_program_runs_without_configure_process():
    """The README's library path in a new interpreter, without configure_process(): a vmapped
    Monte Carlo batch of paper 000's EKF-SLAM (Cholesky and triangular solves on every frame;
    the kind of program that hung before the LAPACK pool was pinned) runs to the end, and its
    compiled program got the library's CPU options."""
    code = (
        "import jax, jax.numpy as jnp, numpy as np\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "from jaxslam.sim.scenarios import ekfslam3d\n"
        "from jaxslam.sim import monte_carlo\n"
        "opts = dict(duration=1.0, q='imu', association='known', capacity=40, landmarks=40, max_obs=16,\n"
        "            control_on='estimate', accel='3axis', altitude=3.0, no_feedforward=False)\n"
        "one_run, *_ = ekfslam3d.build(opts, mode='unknown', dtype=jnp.float64)\n"
        "res = monte_carlo.run(one_run, seed=0, runs=4, chunk=4)\n"
        "m = res.out['metrics']['pos_rmse_m']\n"
        "print(m.shape[0], bool(np.all(np.isfinite(m))), res.chunk)\n")
    # The suite's compile-time flag (LLVM optimisation off, conftest.py) is kept: it is not one of
    # the library's settings, and without it this one compile took 25-30 s of the suite's budget.
    speed = [f for f in os.environ.get("XLA_FLAGS", "").split() if f.startswith("--xla_backend_optimization_level")]
    assert _fresh(code, XLA_FLAGS=" ".join(speed)) == "4 True 4"
