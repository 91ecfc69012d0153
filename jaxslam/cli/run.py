"""``jaxslam run SCENARIO``: a scenario's Monte Carlo runs, its table, JSON and plots.

x64 is switched on here (unless ``--float32``) before any scenario module is imported, so
module-level constants get the right dtype; each scenario gets its own parser built from
``Scenario.options``, so ``jaxslam run NAME --help`` lists that scenario's options and
``--params`` keys.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import pathlib
import sys

from jaxslam import files

from .common import (PROG, Parser, UsageError, compile_timing, echo, finite_float, fmt, int_at_least,
                     native_stdout_to_stderr, positive_int, raise_if_interrupted, seed_int)

__all__ = ["command", "format_run_report"]


def _add_run_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=positive_int, default=1, metavar="N",
                   help="number of Monte Carlo runs (default: 1)")
    p.add_argument("--seed", type=seed_int, default=0, metavar="S",
                   help="seed of the first PRNG key; runs are split from it (default: 0)")
    p.add_argument("--float32", action="store_true",
                   help="compute in float32 (default: float64, with jax_enable_x64 switched on)")
    p.add_argument("--json", metavar="PATH", help="write the run JSON here (parent folders are created)")
    p.add_argument("--plots", metavar="DIR", help="write the scenario's PNG figures into DIR")
    p.add_argument("--quiet", action="store_true",
                   help="print nothing on stdout and no progress bar (errors still go to stderr)")
    p.add_argument("--params", metavar="FILE",
                   help="JSON file of parameter overrides ('jaxslam tune' writes them); its keys "
                        "are checked before the run and listed by 'jaxslam run SCENARIO --help'")
    p.add_argument("--debug", action="store_true",
                   help="print the traceback of an internal failure (also JAXSLAM_DEBUG=1)")
    p.add_argument("--threads", type=positive_int, default=None, metavar="T",
                   help="host threads running flights at once where a scenario loops over its runs on "
                        "a CPU (ekfslam3d-*, fastslam-helix); results do not depend on it (default: "
                        "$JAXSLAM_MC_THREADS, else the cores, at most 8; 1 per process in a group)")
    g = p.add_argument_group("several processes (jax.distributed; the runs split in blocks, results "
                             "gathered; process 0 prints and writes)")
    g.add_argument("--processes", type=positive_int, default=None, metavar="P",
                   help="start P processes on this machine (loopback coordinator) and split the runs")
    g.add_argument("--coordinator", metavar="HOST:PORT",
                   help="a cluster: the coordinator's address (process 0 listens there)")
    g.add_argument("--num-processes", type=positive_int, default=None, metavar="P",
                   help="a cluster: the number of processes in the group")
    g.add_argument("--process-id", type=int_at_least(0), default=None, metavar="I",
                   help="a cluster: this process's index, 0 to P-1")


def _scenario_list_text() -> str:
    from jaxslam.sim.scenarios import registry

    return ", ".join(registry.names()) or "(none registered)"


def _escape(text: str) -> str:
    return text.replace("%", "%%")


def _add_option(group, opt) -> None:
    flags = [opt.flag] + ([f"--{opt.name}"] if "_" in opt.name else [])
    help_text = _escape(opt.help.strip())
    if opt.type is bool:
        if opt.default:
            group.add_argument(*flags, dest=opt.name, action=argparse.BooleanOptionalAction,
                               default=True, help=help_text + " (default: on)")
        else:
            group.add_argument(*flags, dest=opt.name, action="store_true", default=False,
                               help=help_text)
        return
    # An option whose help already states its default (e.g. "default: all") is not told twice.
    shown = "" if "default:" in help_text else " (default: %(default)s)"
    # a float option is finite (a scenario that checks its own range still gets no NaN)
    kind = opt.type
    if opt.type is float:
        kind = finite_float
    elif opt.type is int and opt.lower is not None:
        kind = int_at_least(opt.lower)
    kw = dict(dest=opt.name, type=kind, default=opt.default, help=help_text + shown)
    if opt.choices is not None:
        kw["choices"] = opt.choices
    else:
        kw["metavar"] = opt.name.upper()
    group.add_argument(*flags, **kw)


def _run_parser(scenario=None, help_params: bool = False) -> Parser:
    if scenario is None:
        p = Parser(
            prog=f"{PROG} run",
            usage=f"{PROG} run SCENARIO [options] [scenario options]",
            description="Run a scenario: simulate, filter, report metrics over Monte Carlo runs.",
            epilog=f"scenarios: {_scenario_list_text()}\n"
                   f"'{PROG} run SCENARIO --help' lists the options of that scenario.",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
    else:
        epilog = None
        if help_params:  # built only for --help: the schema comes from the scenario's defaults
            import numpy as np

            from jaxslam import paramfile
            from jaxslam.sim.scenarios import registry

            if scenario.params is None:
                epilog = f"--params FILE: {scenario.name} takes no --params file."
            else:
                schema = scenario.params(registry.default_options(scenario), np.dtype(np.float64))
                epilog = ("--params FILE: a JSON object with these sections and keys (matrices as\n"
                          "nested lists or their diagonals; every key optional; 'jaxslam tune'\n"
                          "writes such files):\n" + paramfile.describe(schema))
        p = Parser(prog=f"{PROG} run {scenario.name}", description=scenario.description,
                    usage=f"{PROG} run {scenario.name} [options] [scenario options]", epilog=epilog,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", metavar="SCENARIO", help="scenario name (see 'jaxslam list')")
    _add_run_common(p)
    if scenario is not None and scenario.options:
        group = p.add_argument_group(f"options of scenario {scenario.name}")
        for opt in scenario.options:
            _add_option(group, opt)
    return p


def command(rest: list[str]) -> int:
    """``jaxslam run SCENARIO [options]``."""
    with contextlib.ExitStack() as stack:  # what a process of a group changes, undone on return
        return _command(rest, stack)


def _command(rest: list[str], stack: contextlib.ExitStack) -> int:
    _hear_launcher_interrupts()  # a process that --processes started tells it of a Ctrl-C
    base = Parser(prog=f"{PROG} run", add_help=False)
    base.add_argument("scenario", nargs="?")
    base.add_argument("-h", "--help", action="store_true")
    _add_run_common(base)
    pre, _ = base.parse_known_args(rest)
    from jaxslam import paramfile
    from jaxslam.sim.scenarios import registry
    from jaxslam.sim.scenarios.builtin import Declared

    if pre.scenario is None:
        if pre.help:
            _run_parser().print_help()
            return 0
        raise UsageError(f"{PROG} run: missing SCENARIO; valid scenarios: {_scenario_list_text()}")
    # The scenario's name and options from its declaration (sim/scenarios/builtin.py): an
    # unknown name, a mistyped option or a value the option refuses exits here, before JAX
    # is imported (1.2-2.3 s) and before any output folder is made.
    try:
        declared = registry.declared(pre.scenario)
    except registry.InputError:
        i = rest.index(pre.scenario) if pre.scenario in rest else 0
        if i > 0 and rest[i - 1].startswith("-") and rest[i - 1] not in base._option_string_actions:
            # `run --anchors 4 uwb-circle`: a scenario's option before the name, whose value was read as it
            raise UsageError(f"{PROG} run: SCENARIO comes first, then its options ('{PROG} run SCENARIO "
                             f"[options]'); got {' '.join(rest[:i + 1])!r} before a scenario name") from None
        raise
    if pre.help and isinstance(declared, Declared) and declared.params_sections is None:
        # a built-in without a --params file: its declaration is its whole help (no JAX, no
        # scenario module: 1.4 s, against 8 s through the module)
        p = _run_parser(declared)
        p.epilog = f"--params FILE: {declared.name} takes no --params file."
        p.print_help()
        return 0
    if not pre.help:
        early = _run_parser(declared).parse_args(rest)
        registry.check_options(declared, {opt.name: getattr(early, opt.name) for opt in declared.options})

    group = None if pre.help else _process_group(pre)  # --help prints; it starts or joins no group
    leader = group in (None, "launch") or group[2] == 0
    # What needs no scenario is checked before JAX is imported (a second, not three): the
    # --params file's JSON, then every output path (its folder created, a probe written).
    raw_params = json_path = plots_dir = None
    if not pre.help:
        raw_params = paramfile.load(pre.params) if pre.params else None
        if raw_params is not None and isinstance(declared, Declared):  # its top level, still without JAX
            paramfile.check_sections(raw_params, declared.params_sections, target=declared.name)
        json_path = files.prepare_file("--json", pre.json) if pre.json is not None and leader else None
        files.distinct_outputs(json=json_path, folders={"plots": pre.plots}, inputs={"params": pre.params})
        plots_dir = files.prepare_dir("--plots", pre.plots) if pre.plots is not None and leader else None
    if group == "launch":  # after those checks: a bad path fails here, not in one of the group
        return _launch_local(rest, pre.processes)

    # x64 before any scenario module is imported (module-level constants take its dtype).
    import jax
    import numpy as np

    # a Ctrl-C during JAX's start-up, whose exception its gc callback dropped: stop before a group
    # is joined (the others would wait for this process) or anything compiles
    raise_if_interrupted()
    if not pre.float32:
        jax.config.update("jax_enable_x64", True)
    if group is not None:  # join the group before any JAX computation
        from jaxslam.sim import distributed

        # what the CPU collectives (gloo) print on descriptor 1 ("[Gloo] Rank 0 is connected ...") goes
        # to stderr, not into the table, or with --quiet nowhere; until the run's collectives are over
        stack.enter_context(native_stdout_to_stderr(null=pre.quiet))
        distributed.initialize(*group)

    from jaxslam import io
    from jaxslam.progress import Progress

    scenario = registry.get(pre.scenario)
    args = _run_parser(scenario, help_params=pre.help).parse_args(rest)
    if not leader:
        args.quiet = True  # process 0 prints and writes
    options = {opt.name: getattr(args, opt.name) for opt in scenario.options}
    dtype = np.dtype(np.float32 if args.float32 else np.float64)

    # The --params keys against the scenario's own parameters, before anything compiles.
    params = registry.check_params(scenario, raw_params, options, dtype) if raw_params is not None else None

    from jaxslam import compilation
    from jaxslam.sim import monte_carlo

    # --threads reaches monte_carlo.run's default through its variable, for this run only (an
    # in-process caller's later runs keep their own)
    with _environment("JAXSLAM_MC_THREADS", None if args.threads is None else str(args.threads)):
        monte_carlo.default_threads()  # a bad $JAXSLAM_MC_THREADS fails here, before anything compiles
        progress = Progress(args.runs, label=scenario.name, enabled=not args.quiet)
        try:
            with compilation.account() as acct:
                try:
                    kw = {"plots": plots_dir is not None} if _accepts(scenario.run, "plots") else {}
                    result = scenario.run(runs=args.runs, seed=args.seed, dtype=dtype, options=options,
                                          progress=progress, params=params, **kw)
                finally:
                    progress.close()
        except KeyboardInterrupt:
            if group is None:
                raise  # before the first chunk finished: "jaxslam: interrupted", exit 130
            # every process of the group ends here (distributed.settle); process 0 says so
            if leader:
                print(f"{PROG} run: interrupted; the runs of a group of processes are all or nothing: "
                      "none kept, nothing written", file=sys.stderr, flush=True)
            return 130
    # the group's collectives are over: descriptor 1 is stdout again for what is written now
    # (--json /dev/stdout opens the path, which went to stderr)
    stack.close()
    if not isinstance(result, registry.ScenarioResult):
        raise TypeError(f"scenario {scenario.name!r} returned {type(result).__name__}, "
                        "expected ScenarioResult")
    if not result.interrupted:
        raise_if_interrupted()  # a Ctrl-C whose exception was dropped: exit 130, nothing written

    report = io.run_json(scenario.name, args.runs, args.seed, dtype, result)
    if group is not None:
        report["config"]["processes"] = group[1]  # the runs were split over this many processes
    report["timing"]["main_program_compile_s"] = report["timing"]["compile_s"]
    report["timing"].update(compile_timing(acct.result))
    notes = _run_notes(result, report["runs"])
    if notes:
        report["notes"] = notes
    if not args.quiet:
        echo(format_run_report(report))
        for note in notes:
            echo(f"note: {note}")
    written = []
    if json_path is not None:
        written.append(io.write_json(json_path, report))
    if result.interrupted:  # keep what finished, skip the plots, exit as interrupted
        where = f"; wrote them to {json_path}" if json_path is not None else " (no --json: not saved)"
        print(f"{PROG} run: interrupted after {report['runs']} of {args.runs} runs; the table covers "
              f"the finished runs{where}" + (" (marked \"interrupted\": true)" if json_path else "")
              + ("; plots skipped" if plots_dir is not None else ""), file=sys.stderr, flush=True)
        return 130
    if plots_dir is not None:
        if result.plot is None:
            print(f"{PROG} run: scenario {scenario.name!r} has no plots; --plots ignored", file=sys.stderr)
        else:
            import time

            import matplotlib

            matplotlib.use("Agg")  # files only; never open a window
            t0 = time.perf_counter()
            pngs = [pathlib.Path(p) for p in (result.plot(plots_dir) or [])]
            report["timing"]["plots_s"] = time.perf_counter() - t0
            written.extend(pngs)
            if json_path is not None:  # again, now with the plotting time
                io.write_json(json_path, report)
            if not args.quiet:
                echo(f"plots: {len(pngs)} file(s) in {report['timing']['plots_s']:.1f} s")
    if not args.quiet:
        for path in written:
            echo(f"wrote {path}")
    return 0


@contextlib.contextmanager
def _environment(name: str, value):
    """Within: ``$name`` set to ``value`` (None: left as it is); restored after."""
    if value is None:
        yield
        return
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


def _process_group(pre):
    """None (one process), "launch" (--processes P > 1: start a group here), or the
    ``(coordinator, num_processes, process_id)`` this process joins."""
    cluster = (pre.coordinator, pre.num_processes, pre.process_id)
    if pre.processes is not None and any(v is not None for v in cluster):
        raise UsageError(f"{PROG} run: --processes starts its own group; it does not take --coordinator, "
                         "--num-processes or --process-id")
    if pre.processes is not None:
        return "launch" if pre.processes > 1 else None
    if all(v is None for v in cluster):
        return None
    if any(v is None for v in cluster):
        raise UsageError(f"{PROG} run: a process group needs all of --coordinator, --num-processes and "
                         "--process-id")
    if pre.process_id >= pre.num_processes:
        raise UsageError(f"{PROG} run: --process-id: expected 0 to {pre.num_processes - 1}, got {pre.process_id}")
    return cluster if pre.num_processes > 1 else None


# The launcher of --processes P (_launch_local).  A Ctrl-C on a terminal reaches every process
# of the foreground group: the launcher and the P processes it started.  Process 0 acts on it
# when its compiled call in flight returns (seconds, during a compilation), and the group agrees
# on it before any gather (distributed.settle), so the launcher waits for process 0's own report
# (subprocess.call killed it 0.25 s after the Ctrl-C).  A Ctrl-C that reached the launcher alone
# (kill -INT PID) is passed on, to each process that did not hear one: each tells the launcher
# through a pipe, written by Python's C-level signal handler the moment a signal arrives
# (signal.set_wakeup_fd; even in a compiled call), so no process gets it twice.  The processes
# start with SIGINT blocked and unblock it once the command's own handler is in place: a Ctrl-C
# while Python and the command's modules start (0.3 s) printed a traceback (the first 0.05 s,
# Python's own start-up, a "Fatal Python error"); blocked, it waits, then ends the process
# with the command's one line and exit 130.
_HEARD_ENV = "JAXSLAM_LAUNCHER_SIGNAL_FD"  # the pipe's descriptor in a process the launcher started
_HEARD_WAIT_S = 0.5  # after its Ctrl-C, the launcher waits this long for the processes to say so
_STUCK_AFTER_S = 5.0  # process 0 still running this long after a worker ended with an error is stopped
_STOP_GRACE_S = 5.0  # SIGTERM, then SIGKILL after this long


def _hear_launcher_interrupts() -> None:
    """In a process started by ``--processes``: the signals this process receives are announced
    on the launcher's pipe (``$JAXSLAM_LAUNCHER_SIGNAL_FD``), and SIGINT, which the launcher
    blocked while this process started, is unblocked (a Ctrl-C that came meanwhile is acted on
    here: ``KeyboardInterrupt``); anywhere else nothing."""
    import signal

    fd = os.environ.pop(_HEARD_ENV, None)
    if fd is None:
        return
    if fd.isdigit():
        try:
            os.set_blocking(int(fd), False)
            signal.set_wakeup_fd(int(fd), warn_on_full_buffer=False)
        except (OSError, ValueError):  # not a pipe of ours, or not the main thread: nothing said
            pass
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _launch_local(rest, processes: int) -> int:
    """``--processes P``: P copies of this command on this machine, one group on the loopback
    (process 0 in the foreground prints and writes; its exit code is returned, or the first
    failing worker's).

    Ctrl-C: the launcher waits for process 0 to report it (exit 130; a group's runs are all or
    nothing, nothing is written), passing it on to the processes it did not reach; a second
    Ctrl-C stops them all (SIGTERM, SIGKILL after ``_STOP_GRACE_S``).  No process is left running
    when this returns."""
    import signal
    import subprocess
    import tempfile

    from jaxslam.sim import distributed  # (JAX-free until a group is joined)

    from .common import raise_if_interrupted

    argv = []
    skip = False
    for a in rest:  # drop --processes P / --processes=P
        if skip:
            skip = False
        elif a == "--processes":
            skip = True
        elif not a.startswith("--processes="):
            argv.append(a)
    coord = f"127.0.0.1:{distributed.free_port()}"

    def cmd(i):
        return [sys.executable, "-m", "jaxslam", "run", *argv, "--coordinator", coord,
                "--num-processes", str(processes), "--process-id", str(i)]

    # A Ctrl-C so far reached this process alone (Python may have dropped its exception): no group
    # is started (it used to start, run to its end and replace the --json).
    raise_if_interrupted()
    # the workers' stderr is kept aside: process 0 says what they would repeat, and a worker's
    # own failure is printed after the run
    errs = [tempfile.TemporaryFile(mode="w+") for _ in range(1, processes)]
    procs, heard = [], []
    try:
        try:
            # the processes start with SIGINT blocked (they inherit the mask; _hear_launcher_interrupts
            # unblocks it); a Ctrl-C meanwhile reaches the launcher when the mask is restored, every
            # process it started being in procs by then
            mask = getattr(signal, "pthread_sigmask", None)
            before = mask(signal.SIG_BLOCK, {signal.SIGINT}) if mask else None
            try:
                for i in [*range(1, processes), 0]:
                    r, w = os.pipe()
                    heard.insert(0 if i == 0 else len(heard), r)
                    try:
                        p = subprocess.Popen(cmd(i), stdout=None if i == 0 else subprocess.DEVNULL,
                                             stderr=None if i == 0 else errs[i - 1], pass_fds=(w,),
                                             env={**os.environ, _HEARD_ENV: str(w)})
                    finally:
                        os.close(w)
                    procs.insert(0 if i == 0 else len(procs), p)
            finally:
                if mask:
                    mask(signal.SIG_SETMASK, before)
            for r in heard:
                os.set_blocking(r, False)
        except BaseException:  # a Ctrl-C (or a failed start) before the group is complete
            _stop(procs)
            raise
        return _wait_group(procs, heard, errs)
    finally:
        if any(p.poll() is None for p in procs):  # an exception of our own: none is left running
            _stop(procs, grace_s=0.0)
        for fd in heard:
            os.close(fd)
        for e in errs:
            e.close()


def _exit_code(code: int) -> int:
    """A child's exit status as a shell reports it (killed by signal N: 128 + N)."""
    return 128 - code if code < 0 else code


def _wait_group(procs, heard, errs) -> int:
    """Wait for the group started by :func:`_launch_local` (``procs[0]`` is process 0; ``heard``
    the read ends of their pipes); the command's exit code."""
    import signal
    import subprocess
    import time

    from .common import raise_if_interrupted

    p0, workers = procs[0], procs[1:]
    got = [False] * len(procs)  # a signal reached that process (its pipe said so)
    interrupted_at = failed_at = None
    passed_on = stuck = False
    while p0.poll() is None:
        try:
            if interrupted_at is None:
                raise_if_interrupted()  # one whose exception Python dropped
            p0.wait(timeout=0.1)
        except subprocess.TimeoutExpired:
            pass
        except KeyboardInterrupt:
            if interrupted_at is not None:  # the second Ctrl-C: stop them now
                _stop(procs)
                return 130
            interrupted_at = time.monotonic()
        for k, fd in enumerate(heard):
            with contextlib.suppress(BlockingIOError, OSError):
                got[k] = got[k] or signal.SIGINT in os.read(fd, 64)
        now = time.monotonic()
        if interrupted_at is not None and not passed_on and now - interrupted_at >= _HEARD_WAIT_S:
            passed_on = True  # to those the Ctrl-C did not reach (it was sent to the launcher alone)
            for p, g in zip(procs, got):
                if not g and p.poll() is None:
                    p.send_signal(signal.SIGINT)
        if failed_at is None and any(w.poll() not in (None, 0) for w in workers):
            failed_at = now
        if failed_at is not None and now - failed_at >= _STUCK_AFTER_S:
            # a worker ended with an error (or a Ctrl-C) outside the group's collectives: process 0
            # would wait for it in the next one (minutes, until gloo or the coordinator gives up)
            stuck = True
            _stop([p0])
    rc = _exit_code(p0.returncode)
    # a process 0 that exits 0 has gathered and written: a Ctrl-C the launcher heard meanwhile
    # changes nothing (130 says "nothing written")
    interrupted = rc == 130 or (interrupted_at is not None and rc != 0)
    if rc != 0:  # the workers end too (a Ctrl-C reached them as well) or would wait for process 0
        _stop(workers, wait_s=_STOP_GRACE_S if interrupted else 0.0)
    else:  # they end after the gather
        for w in workers:
            try:
                w.wait()
            except KeyboardInterrupt:  # the run is written; a Ctrl-C only stops them sooner
                interrupted_at = time.monotonic()
                _stop(workers)
                break
    if interrupted:
        return 130
    if rc == 0 and interrupted_at is not None:
        return 0  # written; the workers' codes are those of the Ctrl-C that stopped them after it
    codes = [_exit_code(w.returncode) for w in workers]
    bad = [(i, c) for i, c in enumerate(codes) if c != 0]
    if (rc == 0 or stuck) and bad:
        i, c = bad[0]
        errs[i].seek(0)
        tail = [ln for ln in errs[i].read().splitlines() if ln.strip()][-1:]
        print(f"{PROG} run: process {i + 1} of {len(procs)} exited with {c}"
              + (f": {tail[0]}" if tail else ""), file=sys.stderr)
        rc = c
    return rc


def _stop(procs, wait_s: float = 0.0, grace_s: float | None = None) -> None:
    """End ``procs``: up to ``wait_s`` for them to end by themselves, then SIGTERM, then SIGKILL
    after ``grace_s`` (default ``_STOP_GRACE_S``); returns when none is running (a Ctrl-C meanwhile
    goes to SIGKILL at once)."""
    import subprocess
    import time

    grace_s = _STOP_GRACE_S if grace_s is None else grace_s
    for step, seconds in (("wait", wait_s), ("terminate", grace_s)):
        if step == "terminate":
            for p in procs:
                if p.poll() is None:
                    p.terminate()
        end = time.monotonic() + seconds
        try:
            for p in procs:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=max(0.0, end - time.monotonic()))
        except KeyboardInterrupt:
            break
    for p in procs:
        if p.poll() is None:
            p.kill()
    for p in procs:
        while True:
            try:
                p.wait()  # SIGKILL: moments
                break
            except KeyboardInterrupt:
                pass


def _run_notes(result, runs: int) -> list:
    """Notes for the run report: metrics that are not finite in some or all runs (their summary
    is null or leaves those runs out), and runs that are identical (the scenario draws no noise)."""
    import numpy as np

    notes = []
    if result.metrics:
        bad = {k: int(np.sum(~np.isfinite(np.asarray(v, float).reshape(runs, -1)).any(axis=1)))
               for k, v in result.metrics.items() if np.size(v) and np.shape(v)[:1] == (runs,)}
        none = sorted(k for k, n in bad.items() if n == runs)
        some = sorted(f"{k} ({n} of {runs})" for k, n in bad.items() if 0 < n < runs)
        if none:
            from jaxslam.sim.scenarios.tracking import SETTLED_AFTER_S

            notes.append(f"not finite in any run (null in the summary): {', '.join(none)}"
                         + (f"; the *_settled metrics cover the flight after its settling time (t > "
                            f"{SETTLED_AFTER_S:g} s), which this flight does not reach (a longer --duration)" if any("settled" in k for k in none)
                            else ""))
        if some:
            notes.append(f"not finite in some runs (left out of the summary): {', '.join(some)}")
    return notes + _identical_runs_note(result, runs)


def _identical_runs_note(result, runs: int) -> list:
    import numpy as np

    if runs < 2 or not result.metrics:
        return []
    if not any(np.isfinite(np.asarray(m, float)).any() for m in result.metrics.values()):
        return []  # every run diverged: equal NaNs say nothing about random draws
    same = all(np.array_equal(v, np.broadcast_to(np.asarray(v).reshape(-1)[:1], np.shape(v)), equal_nan=True)
               for v in (np.asarray(m) for m in result.metrics.values()))
    if not same:
        return []
    return [f"all {runs} runs gave identical metrics: this scenario has no random draw under these "
            "options (every run flies the same flight), so the statistics describe one flight"]


def _accepts(fn, name: str) -> bool:
    """Whether ``fn`` takes the keyword ``name`` (scenarios registered before ``plots`` existed
    do not; they plot by themselves)."""
    import inspect

    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name or p.kind is p.VAR_KEYWORD for p in params)



def _consistency_lines(cons: dict) -> list:
    """One line per statistic of the run JSON's ``consistency``: what it covers (``S_block``,
    ``S_dim``; docs/cli.md), its value against its bounds, and what an OUTSIDE verdict means.

    A statistic ``key`` (a number) finds its companions as ``key_bounds`` / ``key_block`` /
    ``key_dim`` / ``key_steps_inside`` or under its stem (``nis_mean`` -> ``nis_bounds``);
    reports written before the ``_block`` entries existed print without them.  A time-averaged
    ANEES is judged against the per-step bounds, so its line adds the per-step check
    (``key_steps_inside``: the fraction of steps inside) where the report has it.
    """
    from jaxslam.metrics import consistency_verdict, steps_inside_text

    out = []
    for key, value in cons.items():
        if key.endswith(("_bounds", "_block", "_dim", "_steps_inside")) or isinstance(value, (str, bool, list, dict)):
            continue
        stem = key.removesuffix("_mean")

        def part(suffix, key=key, stem=stem):
            return cons.get(f"{key}{suffix}", cons.get(f"{stem}{suffix}"))

        bounds, block, dim = part("_bounds"), part("_block"), part("_dim")
        kind = "nis" if stem.startswith("nis") else "nees" if "nees" in stem else None
        if block is not None:
            if kind == "nis":
                label = f"mean NIS of {block}" + (f", expected {_fmt_dim(dim)}" if dim is not None else "")
            else:
                label = f"{'ANEES' if kind == 'nees' else key} of {block}"
                if dim is not None:
                    label += f", {_fmt_dim(dim)} state{'' if dim == 1 else 's'}"
            text = f"{label} [{key}]: {fmt(value)}"
        else:
            text = f"{key} {fmt(value)}"
        steps = part("_steps_inside")
        if steps is not None:
            text += " (time average)"
        if bounds is not None and len(bounds) == 2:
            lo, hi = (float("nan") if b is None else float(b) for b in bounds)
            v = float("nan") if value is None else float(value)
            text += f" in [{fmt(lo)}, {fmt(hi)}] "
            word = consistency_verdict(v, (lo, hi), kind)
            text += "undefined (no value or no bounds)" if word == "undefined" else word
        if steps is not None:
            text += f"; per step: {steps_inside_text(steps)}"
        out.append(text)
    return out


def _fmt_dim(dim) -> str:
    return str(int(dim)) if float(dim).is_integer() else fmt(dim)


def format_run_report(report: dict) -> str:
    from jaxslam.io import format_table

    lines = [
        (f"scenario {report['scenario']}: {report['runs']} run(s), seed {report['seed']}, "
         f"{report['dtype']}"),
        "",
        format_table(report["metrics"]),
    ]
    cons = report.get("consistency")
    if cons:
        lines += ["", "consistency (two-sided 95 % chi-square bounds):"]
        lines += ["  " + line for line in _consistency_lines(cons)]
    if report.get("flags"):
        lines.append("flags: " + ", ".join(f"{k}={v}" for k, v in report["flags"].items()))
    t = report["timing"]
    cache = t.get("cache") or {}
    served = (f" ({cache.get('hits', 0)} of {cache.get('hits', 0) + cache.get('misses', 0)} programs "
              "from the compilation cache)") if cache.get("dir") else " (compilation cache off)"
    lines.append(f"timing: compile {fmt(t['compile_s'])} s{served if 'cache' in t else ''}, "
                 f"run {fmt(t['run_s'])} s, {fmt(t['runs_per_s'])} runs/s")
    return "\n".join(lines)
