"""``jaxslam run ... --processes P``: the launcher on a Ctrl-C, and one-line progress labels.

The launcher used ``subprocess.call`` for process 0, which kills the child 0.25 s after a
Ctrl-C reaches the launcher; process 0 acts on a Ctrl-C only when its compiled call in flight
returns, and the group first agrees on it (``distributed.settle``), so it was killed before it
could report.  Most tests here start the launcher (``cli.main``) in a fresh session with the
group's processes replaced by a small script (no JAX: about a second each) that records every
SIGINT it receives and, like process 0 in a compiled call, acts on one a second late; one
test runs the real command.  14 of the 15 failed on the code before (not the label that has
no control character).
"""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from processes import finish as _finish

from jaxslam.errors import InputError
from jaxslam.progress import Progress

_MEMBER = textwrap.dedent("""
    import os, signal, sys, time
    i, logdir = sys.argv[1], sys.argv[2]
    mode = os.environ.get("MEMBER" + i, "late")
    heard = []
    signal.signal(signal.SIGINT, lambda s, f: heard.append(s))
    try:  # what `jaxslam run` does first
        from jaxslam.cli.run import _hear_launcher_interrupts
    except ImportError:
        pass
    else:
        _hear_launcher_interrupts()
    with open(os.path.join(logdir, "started" + i), "w") as f:
        f.write(str(os.getpid()))
    if mode == "quick":
        sys.exit(0)
    if mode == "fail":
        print("member failed", file=sys.stderr)
        sys.exit(3)
    if mode == "finishing":  # past its gather (process 0 has written): a Ctrl-C changes nothing
        time.sleep(1.5)
        sys.exit(0)
    end = time.monotonic() + 60
    while (mode in ("stubborn", "hang") or not heard) and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(1.0)  # acts on it late, as process 0 after its compiled call in flight
    with open(os.path.join(logdir, "ended" + i), "w") as f:
        f.write(str(len(heard)))
    sys.exit(130 if heard else 0)
""")

_LAUNCHER = textwrap.dedent("""
    import os, signal, subprocess, sys
    # Ctrl-C as a terminal delivers it (a suite started without job control ignores SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    member, logdir, out = sys.argv[1], sys.argv[2], sys.argv[3]
    real = subprocess.Popen

    class Member(real):  # the group's processes: the member script instead of `python -m jaxslam run`
        def __init__(self, args, *a, **kw):
            if "--process-id" in args:
                args = [sys.executable, "-c", member, args[args.index("--process-id") + 1], logdir]
            super().__init__(args, *a, **kw)

    subprocess.Popen = Member
    from jaxslam import cli, files
    from jaxslam.cli import run
    if hasattr(run, "_STUCK_AFTER_S"):
        run._STUCK_AFTER_S = 1.0
    if os.environ.get("DROPPED_CTRL_C"):
        prepare = files.prepare_file

        class CtrlCInAFinaliser:
            def __del__(self):  # Python drops the KeyboardInterrupt raised here
                signal.raise_signal(signal.SIGINT)

        def prepare_file(*a, **kw):
            CtrlCInAFinaliser()
            return prepare(*a, **kw)

        files.prepare_file = prepare_file
    sys.exit(cli.main(["run", "uwb-circle", "--runs", "4", "--processes", "2", "--json", out]))
""")


def _launch(tmp_path, modes, dropped=False):
    logdir = tmp_path / "log"
    logdir.mkdir()
    out = tmp_path / "out" / "run.json"
    out.parent.mkdir()
    out.write_text('{"old": true}\n')
    env = {**os.environ, **{f"MEMBER{i}": m for i, m in enumerate(modes)}}
    env.pop("DROPPED_CTRL_C", None)
    if dropped:
        env["DROPPED_CTRL_C"] = "1"
    proc = subprocess.Popen([sys.executable, "-c", _LAUNCHER, _MEMBER, str(logdir), str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    return proc, logdir, out


def _wait_started(proc, logdir, n=2):
    t0 = time.monotonic()
    while len(list(logdir.glob("started*"))) < n:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 60, "the group's processes did not start"
        time.sleep(0.02)
    time.sleep(0.3)  # each has set its SIGINT handler (written before "started")


def _ended(logdir):
    return {p.name: int(p.read_text()) for p in logdir.glob("ended*")}


@pytest.mark.parametrize("to", ["group", "launcher"])
def test_a_ctrl_c_waits_for_process_0s_own_report_and_reaches_each_process_once(tmp_path, to):
    # before: process 0 was killed 0.25 s after the Ctrl-C (no "ended0"), the worker terminated;
    # a Ctrl-C sent to the launcher alone never reached them
    proc, logdir, out = _launch(tmp_path, ["late", "late"])
    _wait_started(proc, logdir)
    (os.killpg if to == "group" else os.kill)(proc.pid, signal.SIGINT)
    _, err, left = _finish(proc)
    assert proc.returncode == 130, err
    assert left == []
    assert _ended(logdir) == {"ended0": 1, "ended1": 1}, err  # each heard one SIGINT, none twice
    assert "Traceback" not in err
    assert out.read_text() == '{"old": true}\n' and list(out.parent.iterdir()) == [out]


def test_process_0_killed_by_a_signal_exits_128_plus_the_signal(tmp_path):
    # (the OOM killer, kill -9 PID) before: its -9 was returned, and the command exited 247
    proc, logdir, _ = _launch(tmp_path, ["late", "late"])
    _wait_started(proc, logdir)
    os.kill(int((logdir / "started0").read_text()), signal.SIGKILL)
    _, err, left = _finish(proc)
    assert proc.returncode == 128 + signal.SIGKILL, err
    assert left == []


def test_a_worker_failing_outside_the_collectives_does_not_leave_process_0_waiting(tmp_path):
    # process 0 would wait for it in its next collective (before: for as long as it waited, here
    # a minute; in a real group until gloo or the coordinator gives up)
    proc, logdir, _ = _launch(tmp_path, ["hang", "fail"])
    t0 = time.monotonic()
    _, err, left = _finish(proc, timeout=20)
    assert proc.returncode == 3, err
    assert "process 1 of 2 exited with 3: member failed" in err
    assert left == [] and time.monotonic() - t0 < 15


def test_a_second_ctrl_c_stops_every_process(tmp_path):
    proc, logdir, _ = _launch(tmp_path, ["stubborn", "stubborn"])
    _wait_started(proc, logdir)
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(1.0)
    assert proc.poll() is None  # the first: the launcher waits for process 0
    os.killpg(proc.pid, signal.SIGINT)
    _, err, left = _finish(proc)
    assert proc.returncode == 130, err
    assert left == [] and _ended(logdir) == {}


def test_a_ctrl_c_python_dropped_before_the_launch_starts_no_process(tmp_path):
    # before: the group was started, ran to its end and replaced the --json (exit 0); the launcher
    # imported JAX (for a free port), whose gc callback dropped such a Ctrl-C
    proc, logdir, out = _launch(tmp_path, ["quick", "quick"], dropped=True)
    _, err, left = _finish(proc)
    assert proc.returncode == 130, err
    assert list(logdir.iterdir()) == [] and left == []
    assert out.read_text() == '{"old": true}\n' and list(out.parent.iterdir()) == [out]


def test_ctrl_c_to_the_process_group_of_a_real_run(tmp_path):
    """``jaxslam run uwb-circle --processes 2``: SIGINT to its process group while process 0
    compiles or runs its block: exit 130, process 0 says the group's runs are all or nothing,
    the --json as it was, no temporary file, no process left."""
    out = tmp_path / "out" / "x.json"
    out.parent.mkdir()
    out.write_text('{"old": true}\n')
    # 2000 runs in chunks of 2: each process calls its program 500 times (seconds), so the
    # Ctrl-C at the "compiling" line lands before the gather
    proc = subprocess.Popen([sys.executable, "-c", "import signal, sys\n"
                             "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
                             "from jaxslam import cli\nsys.exit(cli.main(sys.argv[1:]))",
                             "run", "uwb-circle", "--runs", "2000", "--chunk", "2", "--processes", "2",
                             "--json", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    seen, t0 = "", time.monotonic()
    try:
        while time.monotonic() - t0 < 120:
            line = proc.stderr.readline()
            seen += line
            if "compil" in line or "/2000" in line or not line:
                break
        assert proc.poll() is None, seen
        os.killpg(proc.pid, signal.SIGINT)
    finally:
        _, rest, left = _finish(proc, timeout=120)
    err = seen + rest
    assert proc.returncode == 130, err
    assert "jaxslam run: interrupted; the runs of a group of processes are all or nothing" in err
    assert "Traceback" not in err
    assert left == []
    assert out.read_text() == '{"old": true}\n' and list(out.parent.iterdir()) == [out]


# --------------------------------------------------------------------------- progress labels

def _bar_lines(**kw):
    t = iter(range(0, 1000, 2))
    s = io.StringIO()
    p = Progress(4, stream=s, clock=lambda: float(next(t)), delay_s=0.0, **kw)
    return p, s


@pytest.mark.parametrize("label,shown", [
    ("uwb\ncircle", "uwb circle"), ("a\r\n\tb", "a b"), ("\nmc\n", "mc"), ("x\x1b[2Ky", "x [2Ky"),
    ("p\u2028q\x85r\x7fs", "p q r s"), ("\n", ""), ("two  spaces ", "two  spaces "),
])
def test_a_label_is_one_line(label, shown):
    # before: the label was written as given: a newline split the bar's line, a carriage return
    # or an escape moved the cursor over it
    p, s = _bar_lines(label=label)
    assert p.label == shown
    p.update(2)
    p.close()
    lines = s.getvalue().split("\n")
    assert lines[-1] == "" and len(lines) == 3, s.getvalue()  # the update's line and close's
    assert all(ln.startswith(f"{shown} [" if shown else "[") for ln in lines[:-1]), s.getvalue()
    assert "\r" not in s.getvalue() and "\x1b" not in s.getvalue()


def test_a_label_set_later_and_the_compiling_text_are_one_line():
    # jaxslam tune sets bar.label during the run
    p, s = _bar_lines(label="tune")
    p.label = "tune loss\n1.5"
    assert p.label == "tune loss 1.5"
    with pytest.raises(InputError, match="^label: expected a str or None"):
        p.label = 5
    p.label = None
    assert p.label == ""
    q = Progress(4, "mc", stream=s, delay_s=0.0)
    with q.compiling("compiling\nnow"):
        time.sleep(0.6)  # the ticker writes its line after 0.25 s
    q.close()
    for line in s.getvalue().splitlines():
        assert "now" not in line or line.startswith("mc compiling now"), s.getvalue()
    assert "mc compiling now…" in s.getvalue()


def test_a_ctrl_c_to_the_launcher_after_process_0_finished_its_work_keeps_exit_0(tmp_path):
    # process 0 past its gather and its --json write exits 0: the command's code is 0, not 130
    # ("nothing written", docs/cli.md), whatever the launcher heard meanwhile
    proc, logdir, _ = _launch(tmp_path, ["finishing", "finishing"])
    _wait_started(proc, logdir)
    os.kill(proc.pid, signal.SIGINT)
    _, err, left = _finish(proc)
    assert proc.returncode == 0, err
    assert left == []
