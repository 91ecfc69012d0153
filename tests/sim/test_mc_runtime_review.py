"""Review tests: Monte Carlo runner, progress bar, process settings, distributed docs.

Every expectation is independent of the code under test: keys from ``jax.random.fold_in``
called per index, hand-written progress lines, trace counts of a Python side effect.
"""

import io
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from jaxslam import runtime
from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim import distributed, monte_carlo

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _fn(key):
    return {"a": jax.random.normal(key, (3,))}


def _fn_detail(key):
    x = jax.random.normal(key, (2,))
    return {"a": x.sum(), "detail": {"x": x}}


# -- monte_carlo.run: a program_key with several devices must not retrace every call --------

_MULTI = textwrap.dedent("""
    import os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    from jaxslam import runtime; runtime.configure_process(cache=False)
    import jax
    import numpy as np
    from jaxslam.sim import monte_carlo
    traces = [0]
    def fn(key):
        traces[0] += 1
        return {"a": jax.random.normal(key, (3,))}
    outs = [monte_carlo.run(fn, s, 5, devices=jax.devices(), program_key={"review": "u4"})
            for s in range(3)]
    ref = np.stack([np.asarray(jax.random.normal(jax.random.fold_in(jax.random.PRNGKey(2), i), (3,)))
                    for i in range(5)])
    assert outs[0].n_devices == 2
    assert np.array_equal(outs[2].out["a"], ref), "values"
    print("TRACES", traces[0])
""")


def test_program_key_on_several_devices_traces_once():
    env = dict(os.environ, PYTHONPATH=ROOT)
    p = subprocess.run([sys.executable, "-c", _MULTI], capture_output=True, text=True, timeout=300,
                       env=env, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "TRACES 1" in p.stdout, p.stdout + p.stderr[-1000:]


# -- monte_carlo.run: argument checks ---------------------------------------------------------

@pytest.mark.parametrize("bad", ["no", "yes", 1, None])
def test_detail_must_be_a_bool(bad):
    with pytest.raises(InputError, match=r"^detail: "):
        monte_carlo.run(_fn_detail, 0, 2, detail=bad)


def test_detail_numpy_bool_is_accepted():
    r = monte_carlo.run(_fn_detail, 0, 2, detail=np.bool_(True))
    x0 = np.asarray(jax.random.normal(jax.random.fold_in(jax.random.PRNGKey(0), 0), (2,)))
    np.testing.assert_array_equal(r.out["detail"]["x"], x0)


@pytest.mark.parametrize("bad", [object(), "bar", 3])
def test_progress_without_update_is_an_input_error_before_compiling(bad):
    traced = []

    def fn(key):
        traced.append(1)
        return _fn(key)

    with pytest.raises(InputError, match=r"^progress: "):
        monte_carlo.run(fn, 0, 2, progress=bad)
    assert not traced


@pytest.mark.parametrize("env", ["2_0", "١", "0x2"])
def test_mc_threads_env_takes_decimal_digits_only(env, monkeypatch):
    monkeypatch.setenv("JAXSLAM_MC_THREADS", env)
    with pytest.raises(InputError, match=r"^JAXSLAM_MC_THREADS: "):
        monte_carlo.default_threads()


def test_mc_threads_env_plain_digits(monkeypatch):
    monkeypatch.setenv("JAXSLAM_MC_THREADS", " 3 ")
    assert monte_carlo.default_threads() == 3


# -- keys_for: bit-equal to per-index fold_in, and new run counts reuse a compiled fold ------

def test_keys_for_equals_fold_in_per_index_and_does_not_compile_per_count():
    base = jax.random.PRNGKey(11)
    ref = np.stack([np.asarray(jax.random.fold_in(base, i)) for i in range(20)])
    monte_carlo.keys_for(11, 9)  # the 16-key program
    before = monte_carlo._fold_in_all._cache_size()
    for runs in (10, 11, 12, 13, 14, 15, 16):
        k = monte_carlo.keys_for(11, runs)
        assert k.shape == (runs, 2)
        np.testing.assert_array_equal(k, ref[:runs])
    assert monte_carlo._fold_in_all._cache_size() == before
    assert monte_carlo.keys_for(11, 0).shape == (0, 2)
    np.testing.assert_array_equal(monte_carlo.keys_for(11, 1), ref[:1])


def test_run_results_equal_a_python_loop_of_single_runs():
    ref = np.stack([np.asarray(_fn(jax.random.fold_in(jax.random.PRNGKey(4), i))["a"]) for i in range(7)])
    for kw in ({}, {"chunk": 3}, {"cpu_batching": "loop", "threads": 2}):
        r = monte_carlo.run(_fn, 4, 7, **kw)
        assert r.runs == 7 and not r.interrupted
        np.testing.assert_allclose(r.out["a"], ref, rtol=1e-12, atol=0)


# -- Progress ---------------------------------------------------------------------------------

class _Clock:
    t = 0.0

    def __call__(self):
        return self.t


class _Tty(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("width", [0, -3, 2.7, "30", True])
def test_progress_width_must_be_a_positive_int(width):
    with pytest.raises(InputError, match=r"^width: "):
        Progress(4, width=width)


def test_progress_numpy_width_is_accepted():
    s, c = io.StringIO(), _Clock()
    p = Progress(4, "x", stream=s, clock=c, width=np.int64(4))
    c.t = 2.0
    p.update(2)
    p.close()
    assert s.getvalue() == "x [##..] 2/4 00:02 ETA 00:02\n"  # close repeats nothing on a pipe


def test_progress_on_a_terminal_redraws_the_bar_after_a_note_when_closed():
    s, c = _Tty(), _Clock()
    p = Progress(10, "x", stream=s, clock=c, width=10)
    c.t = 2.0
    p.update(3)
    p.note("hello")
    c.t = 3.0
    p.close()
    assert s.getvalue() == ("\r\x1b[Kx [###.......] 3/10 00:02 ETA 00:05"
                            "\r\x1b[Khello\n"
                            "\r\x1b[Kx [###.......] 3/10 00:03 ETA 00:07\n")


def test_progress_on_a_terminal_silent_run_prints_nothing_even_after_a_note():
    s, c = _Tty(), _Clock()
    p = Progress(10, "x", stream=s, clock=c)
    p.note("hi")
    p.close()
    assert s.getvalue() == "\r\x1b[Khi\n"


# -- runtime ----------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", ["no", "false", 0, None])
def test_configure_process_cache_must_be_a_bool(bad, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    from jaxslam import compilation

    monkeypatch.setattr(compilation, "enable_cache", lambda *a, **k: None)  # no side effect
    with pytest.raises(InputError, match=r"^cache: "):
        runtime.configure_process(cache=bad)


def test_runtime_import_and_configure_leave_x64_alone():
    code = ("import jaxslam.runtime as r; r.configure_process(cache=False); import jax; "
            "print('X64', jax.config.jax_enable_x64)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=ROOT, JAX_ENABLE_X64="0"), cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "X64 False" in p.stdout


# -- distributed: the docstring says how blocks are padded --------------------------------------

def test_distributed_docstring_describes_the_padding_the_runner_uses():
    assert "repeats of its last key" not in distributed.__doc__
    assert "next run indices" in distributed.__doc__
    assert distributed.block(7, 3, 2) == (6, 3)  # 7 runs over 3: blocks of ceil(7/3) = 3


@pytest.mark.parametrize("name", ["delay_s", "min_interval_s", "log_interval_s"])
@pytest.mark.parametrize("bad", [float("nan"), -1.0, float("inf"), True, "1", None])
def test_progress_delays_must_be_finite_seconds(name, bad):
    with pytest.raises(InputError, match=rf"^{name}: "):
        Progress(4, **{name: bad})


def test_progress_numpy_seconds_pass():
    s, c = io.StringIO(), _Clock()
    p = Progress(4, "x", stream=s, clock=c, delay_s=np.float32(1.5), log_interval_s=np.int64(5))
    c.t = 1.0
    p.update(1)  # within the delay: silent
    assert s.getvalue() == ""
    assert p.delay_s == 1.5


# -- loop batching with threads: a run without "detail" is an InputError whichever finishes first

def test_loop_threads_missing_detail_is_an_input_error_for_every_run():
    import time

    first = monte_carlo.keys_for(0, 1)[0]

    def slow_first(k):  # run 0 finishes last, so another run's output is checked first
        if np.array_equal(np.asarray(k), first):
            time.sleep(0.5)
        return np.float32(0)

    def fn(key):
        d = jax.pure_callback(slow_first, jax.ShapeDtypeStruct((), np.float32), key)
        return jax.random.normal(key, ()) + d  # not a dict

    import threading

    with pytest.raises(InputError, match=r"^fn: with detail=True"):
        monte_carlo.run(fn, 0, 6, cpu_batching="loop", threads=2, detail=True)
    # the error is raised once the runs in flight have finished: no worker outlives the call
    assert not [t for t in threading.enumerate() if t.name.startswith("jaxslam-mc-")]


def test_loop_threads_error_of_a_run_waits_for_the_runs_in_flight():
    import threading
    import time

    keys = monte_carlo.keys_for(3, 2)

    def host(k):
        if np.array_equal(np.asarray(k), keys[0]):
            time.sleep(0.6)  # run 0 is still in flight when run 1 fails
        elif np.array_equal(np.asarray(k), keys[1]):
            raise ValueError("run 1 fails")
        return np.float32(0)

    def fn(key):
        return {"a": jax.pure_callback(host, jax.ShapeDtypeStruct((), np.float32), key)}

    with pytest.raises(Exception, match="run 1 fails"):
        monte_carlo.run(fn, 3, 2, cpu_batching="loop", threads=2)
    assert not [t for t in threading.enumerate() if t.name.startswith("jaxslam-mc-")]
