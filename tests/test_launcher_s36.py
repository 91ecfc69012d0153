"""``python -m jaxslam`` and the processes of ``jaxslam run ... --processes P``: a Ctrl-C as they
start, gloo's line on stdout, the launcher's free port, and a Ctrl-C at the group's collectives.

Every test starts its own processes, which set Python's SIGINT handler first (CI started without
job control hands them SIGINT ignored).  Each failed on the code before (see the comments).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
from processes import finish as _finish

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Python's SIGINT handler, as a terminal's Ctrl-C finds it, and a Ctrl-C sent to this process at
# the import of module TARGET (at a known point, not after a guessed delay)
_CTRL_C_AT_IMPORT = textwrap.dedent("""
    import os, signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)

    class CtrlCAt:
        def __init__(self, name):
            self.name = name

        def find_spec(self, name, path=None, target=None):
            if name == self.name:
                sys.meta_path.remove(self)
                os.kill(os.getpid(), signal.SIGINT)
            return None
""")


# ------------------------------------------------------------------ 1. a Ctrl-C as they start

@pytest.mark.parametrize("target", ["jaxslam.cli", "jaxslam.compilation"])
def test_python_m_jaxslam_ctrl_c_before_main_handles_it_is_one_line(target):
    # before: a traceback and exit -2 (SIGINT): while __main__ imported jaxslam.cli (NumPy: the
    # first 0.3 s), and while main() configured the process before its own handler
    # (runtime.configure_process imports jaxslam.compilation)
    script = _CTRL_C_AT_IMPORT + textwrap.dedent(f"""
        sys.meta_path.insert(0, CtrlCAt({target!r}))
        import runpy
        sys.argv = ["jaxslam", "list"]
        runpy.run_module("jaxslam", run_name="__main__", alter_sys=True)
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert (p.returncode, p.stderr) == (130, "jaxslam: interrupted\n"), p.stderr
    assert p.stdout == ""


def test_the_console_script_ctrl_c_while_main_configures_the_process_is_one_line():
    # the installed `jaxslam` command calls jaxslam.cli.main itself (no __main__ around it):
    # runtime.configure_process ran before main's own handler (a traceback, exit -2)
    script = _CTRL_C_AT_IMPORT + textwrap.dedent("""
        from jaxslam.cli import main
        sys.meta_path.insert(0, CtrlCAt("jaxslam.compilation"))
        raise SystemExit(main(["list"]))
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert (p.returncode, p.stderr) == (130, "jaxslam: interrupted\n"), p.stderr
    assert p.stdout == ""


@pytest.mark.parametrize("when", ["python-start-up", "importing"])
def test_a_ctrl_c_reaching_a_group_process_as_it_starts_is_one_line(tmp_path, when):
    # Each process the launcher starts receives a SIGINT while Python starts (site) or while the
    # command's modules import.  Before: process 0 printed "Fatal Python error: init_import_site"
    # or a KeyboardInterrupt traceback on the terminal, and the command exited 1 or 130.  Now the
    # processes start with SIGINT blocked and unblock it in the command's handler.
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_CTRL_C_AT_IMPORT + textwrap.dedent("""
        if os.environ.get("JAXSLAM_LAUNCHER_SIGNAL_FD"):  # a process of the group, not the launcher
            if os.environ["WHEN"] == "python-start-up":
                os.kill(os.getpid(), signal.SIGINT)
            else:
                sys.meta_path.insert(0, CtrlCAt("jaxslam.cli"))
    """))
    out = tmp_path / "out" / "run.json"
    out.parent.mkdir()
    out.write_text('{"old": true}\n')
    env = {**os.environ, "WHEN": when,
           "PYTHONPATH": os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-c", "import signal, sys\n"
                             "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
                             "from jaxslam import cli\nsys.exit(cli.main(sys.argv[1:]))",
                             "run", "uwb-circle", "--runs", "2", "--processes", "2", "--json", str(out)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    stdout, err, left = _finish(proc, timeout=120)
    assert proc.returncode == 130, err
    assert err == "jaxslam: interrupted\n"  # process 0's line; the worker's stderr is kept aside
    assert stdout == "" and left == []
    assert out.read_text() == '{"old": true}\n' and list(out.parent.iterdir()) == [out]


def test_the_launcher_restores_its_own_signal_mask(tmp_path):
    # (the mask that its processes start with is the launcher's while it starts them)
    script = textwrap.dedent("""
        import signal, subprocess, sys
        signal.signal(signal.SIGINT, signal.default_int_handler)
        real = subprocess.Popen
        blocked = []

        class Member(real):  # a process of the group: one that exits at once
            def __init__(self, args, *a, **kw):
                blocked.append(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, set()))
                super().__init__([sys.executable, "-c", "pass"], *a, **kw)

        subprocess.Popen = Member
        from jaxslam import cli
        rc = cli.main(["run", "uwb-circle", "--runs", "2", "--processes", "2"])
        print(rc, blocked, signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, set()))
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert p.stdout.split("\n")[-2] == "0 [True, True] False", p.stderr


# ------------------------------------------------------------------ 2. gloo's line on stdout

def test_native_stdout_goes_to_stderr_and_python_stdout_stays():
    # before: no such helper (the group's processes printed gloo's line on stdout)
    script = textwrap.dedent("""
        import ctypes, os, sys
        from jaxslam.cli.common import native_stdout_to_stderr, reader_gone_safe_stdout
        libc = ctypes.CDLL(None)
        with reader_gone_safe_stdout():
            print("before", flush=True)
            with native_stdout_to_stderr():
                os.write(1, b"native\\n")
                libc.printf(b"c-stdio\\n")  # left in C's buffer (a pipe): flushed on the way out
                print("python", flush=True)
            print("after", flush=True)
            os.write(1, b"native after\\n")
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout == "before\npython\nafter\nnative after\n"
    assert p.stderr == "native\nc-stdio\n"


def test_quiet_sends_native_and_python_stdout_to_the_null_device_until_the_end():
    # review (s36): with null (--quiet) only descriptor 1 went to the null device; sys.stdout was
    # a copy of the real stdout, so a Python print reached it (the old silence_stdout dropped it)
    script = textwrap.dedent("""
        import os, sys
        from jaxslam.cli.common import native_stdout_to_stderr, reader_gone_safe_stdout
        with reader_gone_safe_stdout():
            with native_stdout_to_stderr(null=True):
                os.write(1, b"native\\n")
                print("python")
            print("after", flush=True)
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert (p.stdout, p.stderr) == ("after\n", "")


def test_a_group_run_prints_only_its_report_on_stdout(tmp_path):
    # before: stdout began "[Gloo] Rank 0 is connected to 1 peer ranks. Expected number of
    # connected peer ranks is : 1" (gloo, at the group's first collective)
    p = subprocess.run([sys.executable, "-m", "jaxslam", "run", "uwb-circle", "--runs", "2", "--processes", "2"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith("scenario uwb-circle: 2 run(s), seed 0, float64\n"), p.stdout
    assert "Gloo" not in p.stdout
    assert "[Gloo] Rank 0 is connected" in p.stderr  # routed, not hidden (jaxlib 0.10 prints it)


def test_json_to_dev_stdout_on_a_pipe_is_written_there(tmp_path):
    # review (s36): /dev/stdout on a pipe links to /proc/PID/fd/pipe:[N], which path resolution
    # cannot follow: "--json: cannot write into '/proc/PID/fd'", exit 2 (`... --json /dev/stdout | jq`)
    p = subprocess.run([sys.executable, "-m", "jaxslam", "run", "uwb-circle", "--runs", "1", "--duration", "2",
                        "--quiet", "--json", "/dev/stdout"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["scenario"] == "uwb-circle"


def test_a_group_run_writes_json_to_dev_stdout_on_stdout(tmp_path):
    # review (s36): descriptor 1 pointed at stderr for the whole command, so --json /dev/stdout
    # (atomic_write opens the path) wrote the JSON to stderr; the group's collectives are done
    # before the outputs are written, so descriptor 1 is stdout again by then
    p = subprocess.run([sys.executable, "-m", "jaxslam", "run", "uwb-circle", "--runs", "2", "--duration", "2",
                        "--processes", "2", "--quiet", "--json", "/dev/stdout"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["scenario"] == "uwb-circle"
    assert '"scenario"' not in p.stderr


# ------------------------------------------------------------------ 3. one free-port helper

def test_the_launcher_takes_its_port_from_distributed_free_port_without_jax():
    # before: run.py had its own _free_port, as distributed.py imported JAX at import
    script = textwrap.dedent("""
        import subprocess, sys
        from jaxslam.sim import distributed
        port = distributed.free_port()
        assert 0 < port < 65536 and "jax" not in sys.modules
        distributed.free_port = lambda: 4242
        seen = []

        def popen(args, *a, **kw):
            seen.append(args[args.index("--coordinator") + 1])
            raise OSError("not started")

        subprocess.Popen = popen
        from jaxslam import cli
        rc = cli.main(["run", "uwb-circle", "--runs", "2", "--processes", "2"])
        print(rc, seen, "jax" in sys.modules)
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split("\n")[-2] == "1 ['127.0.0.1:4242'] False", p.stdout + p.stderr
    assert "OSError: not started" in p.stderr


# ------------------------------------------------------------------ 4. a Ctrl-C at the collectives

_MEMBER = textwrap.dedent("""
    import signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import numpy as np
    from jaxslam.sim import distributed
    i, port, at, log = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
    distributed.initialize(f"127.0.0.1:{port}", 2, i)
    from jax.experimental import multihost_utils
    real, calls = multihost_utils.process_allgather, []

    def allgather(x, **kw):  # a Ctrl-C reaches process 0 just before collective `at` is entered
        calls.append(1)
        if i == 0 and len(calls) == at:
            signal.raise_signal(signal.SIGINT)
        return real(x, **kw)

    multihost_utils.process_allgather = allgather
    try:
        distributed.settle(None)
        said = "gathered " + repr(distributed.gather({"a": np.full((1,), float(i))}, 2)["a"].tolist())
    except KeyboardInterrupt:
        said = f"interrupted after {len(calls)} collectives"
    with open(log, "w") as f:
        f.write(said)
""")


@pytest.mark.parametrize("at", [1, 2], ids=["settle", "gather"])
def test_a_ctrl_c_between_the_check_and_the_collective_leaves_no_process_waiting(tmp_path, at):
    # before: process 0 raised KeyboardInterrupt there and left the collective (settle's, or the
    # gather's), so process 1 waited in it (until gloo or the coordinator gave up; here killed
    # 20 s after process 0 ended).  Now process 0 takes part and acts on the Ctrl-C when the batch
    # is gathered.
    from jaxslam.sim import distributed

    port = str(distributed.free_port())
    procs = [subprocess.Popen([sys.executable, "-c", _MEMBER, str(i), port, str(at), str(tmp_path / f"said{i}")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
             for i in range(2)]
    errs = []
    for p in procs:
        try:
            _, err, _ = _finish(p, timeout=60 if p is procs[0] else 20)
        except subprocess.TimeoutExpired:  # (killed by _finish)
            err = "still waiting in a collective"
        errs.append(err)
    said = {i: (tmp_path / f"said{i}").read_text() if (tmp_path / f"said{i}").exists() else None for i in range(2)}
    assert said == {0: "interrupted after 2 collectives", 1: "gathered [0.0, 1.0]"}, errs
    assert [p.returncode for p in procs] == [0, 0], errs


def test_json_to_dev_stdout_redirected_into_a_file_keeps_the_file(tmp_path):
    # review (s36): /dev/stdout leads to the file stdout is redirected into (`>> log.txt`), and
    # atomic_write replaced that file by a rename: its earlier content, the table and the "wrote"
    # line were lost; now the JSON is written on stdout's descriptor, after the rest
    log = tmp_path / "log.txt"
    log.write_text("EARLIER LOG LINE\n")
    with open(log, "a") as out:
        p = subprocess.run([sys.executable, "-m", "jaxslam", "run", "uwb-circle", "--runs", "1", "--duration", "2",
                            "--json", "/dev/stdout"], stdout=out, stderr=subprocess.PIPE, text=True, timeout=300,
                           cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    text = log.read_text()
    assert text.startswith("EARLIER LOG LINE\nscenario uwb-circle: 1 run(s)")
    start = text.index("\n{") + 1
    assert json.loads(text[start:text.index("\n}", start) + 2])["scenario"] == "uwb-circle"
    assert "wrote /dev/stdout" in text
