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
    code = ("import os; os.environ.pop('XLA_FLAGS', None); import jaxslam.cli, jax; "
            "import jax.numpy as jnp; jnp.ones(1).block_until_ready(); print(os.environ['XLA_FLAGS'])")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert runtime.XLA_WORKAROUND_FLAGS[0] in out.stdout
    assert "already started" not in out.stderr
