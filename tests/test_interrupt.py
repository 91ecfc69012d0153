"""Ctrl-C keeps what is finished: Monte Carlo chunks, tuning steps; files are never truncated.

* :func:`jaxslam.sim.monte_carlo.run` — a ``KeyboardInterrupt`` raised between chunks (here by
  a progress object, deterministically) returns the finished chunks, marked interrupted;
  one raised before any chunk finished propagates.  The finished runs' values equal those
  of an uninterrupted batch (run i always uses ``fold_in(seed, i)``).
* ``jaxslam run`` in a subprocess sent a real SIGINT mid-batch: exit 130, a valid JSON with
  the finished runs, ``"interrupted": true``, ``runs`` < ``runs_requested``.  The scenario is
  registered by the subprocess itself (a user's own scenario through the public registry):
  each run does a fixed amount of matrix work, so the batch lasts seconds and compiles in
  well under a second.
* ``jaxslam tune``: an interrupt after three steps writes the tune JSON and the params file
  with the parameters reached so far, marked interrupted, and exits 130.
* ``files.atomic_write``: a writer that fails half way leaves the old file as it was.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli, files, paramfile
from jaxslam.progress import Progress
from jaxslam.sim import monte_carlo


def _fn(key):
    return {"x": jax.random.normal(key, (3,)), "n": jnp.sum(jax.random.uniform(key, (4,)))}


class _StopAt:
    """A progress object whose ``update`` raises KeyboardInterrupt at its ``at``-th call."""

    def __init__(self, at):
        self.at, self.calls = at, 0

    def update(self, n_done):
        self.calls += 1
        if self.calls == self.at:
            raise KeyboardInterrupt


@pytest.mark.parametrize("batching,threads", [("vmap", None), ("loop", 1), ("loop", 2)])
def test_monte_carlo_keeps_finished_chunks(batching, threads):
    full = monte_carlo.run(_fn, seed=5, runs=10, chunk=2, cpu_batching=batching, threads=threads)
    assert full.runs == 10 and not full.interrupted
    part = monte_carlo.run(_fn, seed=5, runs=10, chunk=2, cpu_batching=batching, progress=_StopAt(3),
                           threads=threads)
    if threads == 2:
        # update() runs after each finished run; the runs in flight then finish, and the longest
        # finished prefix is kept (how many got done meanwhile depends on the scheduler)
        assert 3 <= part.runs <= 10 and part.interrupted == (part.runs < 10) and part.threads == 2
    else:
        done = 6 if batching == "vmap" else 3  # update() runs after each chunk (vmap) or run (loop)
        assert part.interrupted and part.runs == done
    done = part.runs
    assert part.out["x"].shape == (done, 3)
    np.testing.assert_array_equal(part.out["x"], full.out["x"][:done])
    np.testing.assert_array_equal(part.out["n"], full.out["n"][:done])


def test_threaded_loop_interrupt_lets_the_runs_in_flight_finish():
    # A fake compiled run: run 1 is slow (0.3 s), the others take 5 ms.  Two threads: the Ctrl-C
    # (at the second finished run) comes while run 1 is still in flight; it finishes and is kept,
    # with the prefix before it, and no new run starts after the interrupt.
    def compiled(i):
        time.sleep(0.3 if int(i) == 1 else 0.005)
        return {"i": np.asarray(int(i))}

    outs = monte_carlo._loop_runs(compiled, np.arange(200), 2, False, _StopAt(2))
    got = [int(o["i"]) for o in outs]
    assert got == list(range(len(got))) and 3 <= len(got) <= 5, got


class _StopWhileCompiling:
    """A progress object interrupted during compilation (nothing finished yet)."""

    def update(self, n_done):  # pragma: no cover - never reached
        raise AssertionError("no chunk may finish")

    @contextlib.contextmanager
    def compiling(self):
        yield
        raise KeyboardInterrupt


@pytest.mark.parametrize("batching,threads", [("vmap", None), ("loop", 1), ("loop", 2)])
def test_monte_carlo_interrupt_before_any_chunk_propagates(batching, threads):
    with pytest.raises(KeyboardInterrupt):
        monte_carlo.run(_fn, seed=0, runs=4, chunk=2, progress=_StopWhileCompiling(), cpu_batching=batching,
                        threads=threads)


_SLOW_SCENARIO = textwrap.dedent("""
    import signal, sys
    # Ctrl-C as a terminal delivers it: a suite started as a background job without job control
    # ((cmd &) in a script) has SIGINT ignored, this process inherits that, and Python then
    # installs no KeyboardInterrupt handler at all.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import jax, jax.numpy as jnp, numpy as np
    from jaxslam import cli
    from jaxslam.sim import monte_carlo
    from jaxslam.sim.scenarios import registry

    def one(key):  # a fixed amount of matrix work per run (~0.1 s on one core)
        a = jax.random.normal(key, (160, 160)) / 160.0
        b = jax.lax.fori_loop(0, 400, lambda i, m: jnp.tanh(m @ a), a)
        return {"val": jnp.sum(b), "first": a[0, 0]}

    def run(*, runs, seed, dtype, options, progress, params):
        mc = monte_carlo.run(one, seed, runs, chunk=2, progress=progress)
        return registry.ScenarioResult(
            config={}, metrics={"val": mc.out["val"], "first": mc.out["first"]}, consistency=None,
            flags={}, timing={"compile_s": mc.compile_s, "run_s": mc.run_s}, interrupted=mc.interrupted)

    registry.register(registry.Scenario("slow-test", "fixed matrix work per run", (), run))
    sys.exit(cli.main(sys.argv[1:]))
""")


def test_sigint_mid_run_writes_the_finished_runs(tmp_path):
    out = tmp_path / "out" / "run.json"
    out.parent.mkdir()
    out.write_text('{"old": true}\n')  # replaced atomically by the interrupted run's JSON
    env = {**os.environ, "JAXSLAM_CACHE": "0"}
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_SCENARIO, "run", "slow-test", "--runs", "400",
                             "--json", str(out)], stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env=env)
    # The bar writes a line on a pipe when the first chunk is done (after its 1 s delay): wait
    # for a line showing progress, then interrupt.
    seen, t0 = "", time.monotonic()
    while time.monotonic() - t0 < 120:
        line = proc.stderr.readline()
        seen += line
        if "/400" in line and "] 0/400" not in line:
            break
        if not line and proc.poll() is not None:
            break
    assert proc.poll() is None, f"the run ended before it could be interrupted: {seen}"
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=120)
    err = seen + rest
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert "interrupted after" in err and "runs" in err
    rep = json.loads(out.read_text())
    assert rep["interrupted"] is True and rep["runs_requested"] == 400
    assert 2 <= rep["runs"] < 400 and rep["runs"] % 2 == 0  # whole chunks of 2
    assert len(rep["metrics"]["val"]["per_run"]) == rep["runs"]
    assert list(out.parent.iterdir()) == [out]  # no temporary file left behind
    # The finished runs are the first runs of the batch: run 0's draw equals a direct call.
    first = float(jax.random.normal(monte_carlo.keys_for(0, 1)[0], (160, 160))[0, 0] / 160.0)
    assert rep["metrics"]["first"]["per_run"][0] == pytest.approx(first, rel=1e-6)


_DROPPED_SIGINT = textwrap.dedent("""
    import signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal delivers it (above)
    import numpy as np
    from jaxslam import cli
    from jaxslam.sim.scenarios import registry

    class CtrlCInAFinaliser:
        def __del__(self):  # Python drops an exception raised here ("Exception ignored in ...")
            signal.raise_signal(signal.SIGINT)

    def run(*, runs, seed, dtype, options, progress, params):
        CtrlCInAFinaliser()  # collected at once: the Ctrl-C's KeyboardInterrupt is dropped
        print("the scenario went on", file=sys.stderr)
        return registry.ScenarioResult(
            config={}, metrics={"val": np.zeros(runs)}, consistency=None, flags={},
            timing={"compile_s": 0.0, "run_s": 0.0}, interrupted=False)

    registry.register(registry.Scenario("dropped-sigint", "a Ctrl-C whose exception Python drops", (), run))
    sys.exit(cli.main(sys.argv[1:]))
""")


def test_a_ctrl_c_python_drops_still_stops_the_command_before_it_writes(tmp_path):
    # JAX's gc callback at start-up swallowed early Ctrl-Cs this way: the command ran on and
    # replaced the existing --json.  The command's SIGINT handler counts them.
    out = tmp_path / "run.json"
    out.write_text('{"old": true}\n')
    proc = subprocess.run([sys.executable, "-c", _DROPPED_SIGINT, "run", "dropped-sigint", "--runs", "2",
                           "--json", str(out)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "JAXSLAM_CACHE": "0"})
    assert "the scenario went on" in proc.stderr  # the KeyboardInterrupt was dropped by Python
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.rstrip().endswith("jaxslam: interrupted")
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert out.read_text() == '{"old": true}\n'


def test_counting_interrupts_restores_the_default_handler():
    from jaxslam.cli import common

    # Ctrl-C as a terminal delivers it (a suite started in the background has SIGINT ignored,
    # and then the command leaves the handler alone: checked last)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _counting_interrupts_round_trip(common)
    finally:
        signal.signal(signal.SIGINT, before)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with common.counting_interrupts():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def _counting_interrupts_round_trip(common):
    hook = sys.unraisablehook
    with common.counting_interrupts():
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
        assert sys.unraisablehook is not hook
        common.raise_if_interrupted()  # no Ctrl-C yet: nothing
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):  # counted, so raised again where it is read
            common.raise_if_interrupted()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler and sys.unraisablehook is hook
    common.raise_if_interrupted()  # the count ends with the command


def test_tune_interrupt_keeps_the_steps_done(tmp_path, capsys, monkeypatch):
    calls = {"n": 0}
    real_update = Progress.update

    def update(self, n_done):  # the tune loop's bar: interrupt at the third step's record
        if self.label.startswith("tune"):
            calls["n"] += 1
            if calls["n"] == 3:
                raise KeyboardInterrupt
        return real_update(self, n_done)

    monkeypatch.setattr(Progress, "update", update)
    j, p = tmp_path / "t.json", tmp_path / "p.json"
    rc = cli.main(["tune", "linear-gaussian", "--loss", "nll", "--steps", "20", "--train-runs", "1",
                   "--test-runs", "1", "--json", str(j), "--params-out", str(p)])
    err = capsys.readouterr().err
    assert rc == 130, err
    assert "interrupted (Ctrl-C) at step 2 of 20 (3 of 21 evaluations" in err and "no held-out evaluation" in err
    rep = json.loads(j.read_text())
    assert rep["interrupted"] is True and rep["steps_done"] == 3 and len(rep["history"]) == 3
    assert "before" not in rep and "after" not in rep  # no evaluation was run
    params = json.loads(p.read_text())
    assert params["interrupted"] is True and params["scenario"] == "linear-gaussian"
    assert params["noise"] == rep["params_after"]["noise"] == rep["noise"]
    # Still a valid --params file (the interrupted marker is accepted provenance).
    schema = {"noise": {k: np.asarray(v) for k, v in params["noise"].items()}}
    assert paramfile.check(params, schema, target="linear-gaussian") == {"noise": params["noise"]}


def test_atomic_write_leaves_the_old_file_when_the_writer_fails(tmp_path):
    target = tmp_path / "r.json"
    target.write_text("old\n")

    def half(f):
        f.write("new, but")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        files.atomic_write(target, half)
    assert target.read_text() == "old\n"
    assert list(tmp_path.iterdir()) == [target]
    files.atomic_write(target, lambda f: f.write("new\n"))
    assert target.read_text() == "new\n"
    assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_atomic_write_follows_links_and_never_replaces_a_device(tmp_path):
    # a rename over the path used to replace a symlink with a file (its target untouched) and,
    # run as root, /dev/null itself with a regular file
    import os
    import stat

    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "t.json"
    target.write_text("old\n")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    files.atomic_write(link, lambda f: f.write("new\n"))
    assert link.is_symlink() and target.read_text() == "new\n"
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)
    files.atomic_write(os.devnull, lambda f: f.write("discarded\n"))
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)  # still the device
