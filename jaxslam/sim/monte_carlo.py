"""Monte Carlo runner: ``vmap`` over seeds, in chunks, sharded over every local device.

``run(fn, seed, runs)`` evaluates ``fn(key)`` — a pure, jit-able function of
one PRNG key returning a pytree of arrays (one flight: simulate → filter →
metrics) — for ``runs`` keys.  Runs are processed in chunks of ``chunk`` so
memory stays bounded (progress is reported per chunk); each chunk is one
compiled ``jit(vmap(fn))`` call, padded to the chunk size so the last one does
not recompile.

Devices: the chunk's leading (runs) axis is sharded over all local devices with
a 1-D ``jax.sharding.Mesh`` and each device vmaps its own block (``shard_map``: the runs
are independent, nothing crosses devices), so the same call uses every GPU a machine has
(the chunk is padded to a multiple of the device count).  Across hosts, start each process with
``jax.distributed.initialize()`` and pass ``devices=jax.devices()`` (global
devices): the same mesh then spans hosts — every process must call ``run``
with the same arguments.  On a CPU the sharding can be exercised with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (tested; known problem, 2026-12-04:
with two forced host devices on a 2-core machine, 40 runs of ``ekfslam3d-unknown`` stopped
making progress inside XLA's CPU runtime (no collective in the program), while 16 finished
(before ``shard_map``, 12-16 runs already stopped, not every time) and generic programs with
Cholesky factors and triangular solves did not stop; it is a CPU-only test set-up, so one
device is the default there).  A group of processes
(``jax.distributed``, :mod:`jaxslam.sim.distributed`) splits the runs instead: with the
default ``devices``, each process runs one contiguous block on its own devices and the blocks
are gathered to every process (tested with two processes on this machine).

Batching: on an accelerator, runs are always vmapped.  On a CPU the scenario chooses
(``cpu_batching``): ``"vmap"`` pays where a run's state is small (UWB: 7.6× over sequential
calls), ``"loop"`` compiles the single run once and calls it per run — measured on paper
000's EKF-SLAM, 4 vmapped runs took the same 3.4 s as 4 calls of the single run, while the
vmapped program took 1.8 s longer to trace; the matrix work is already vectorised.
With ``"loop"``, ``threads`` host threads (default: the cores, at most
:data:`MAX_DEFAULT_THREADS`; ``$JAXSLAM_MC_THREADS``; 1 in a group of processes) call that one
compiled run concurrently, each taking the next run index, so a 2-core machine runs two flights
at a time (measured 2026-12-06 on 2 cores: 2000 two-second ``ekfslam3d-unknown`` flights 32.5 →
16.2 s, 20 five-second ``fastslam-helix`` flights 23.2 → 11.7 s).  Only the single-run program
is called from several threads: two *vmapped* programs executing at once stopped making
progress inside XLA's CPU runtime (no CPU load), the same hang as with two forced host devices.

Plots need one run's full record (truth, estimates, the map over time), which is far larger
than its metrics.  An output ``"detail"`` of ``fn`` is kept for the first run only, so a
scenario's plots come from the same compiled program as its metrics instead of a second
compilation (with ``"vmap"`` the chunk is capped at :data:`DETAIL_CHUNK` runs to bound it).

Interrupts: a Ctrl-C (``KeyboardInterrupt``) between chunks keeps the chunks already
finished (with threads: the runs in flight finish, and the longest finished prefix of runs is
kept): the result holds their runs (``runs`` < the runs asked for, ``interrupted``
true) and the caller reports them as such.  A Ctrl-C before the first chunk has finished
propagates.  (The signal is handled when the host regains control, i.e. after the compiled
call in flight returns.)  In a group of processes the run is all or nothing: a Ctrl-C in any
process raises ``KeyboardInterrupt`` in every one once each has ended its block (never a gather
of partial blocks; :func:`jaxslam.sim.distributed.settle`), and from the end of its block through
the gather a process holds a Ctrl-C (:func:`jaxslam.sim.distributed.section`), so none leaves the
others waiting in a collective.

Programs: the compiled batch of each ``fn`` is kept for as long as ``fn`` lives, so a second
``run`` of the same function (a new seed, more runs) neither traces nor compiles
(:func:`clear_programs` forgets them; with a ``program_key`` the persistent cache keeps them).

Timing separates compilation (trace, lower and compile; :mod:`jaxslam.compilation`
splits it) from execution, which is measured with ``block_until_ready``.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
import weakref
from typing import Callable, NamedTuple, Optional, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .. import compilation, runtime
from ..errors import InputError
from ..linalg import check_flag, check_int

__all__ = ["MCResult", "run", "keys_for", "seed_key", "clear_programs", "default_threads", "DETAIL_CHUNK", "MAX_DEFAULT_THREADS"]

DETAIL_CHUNK = 16  # runs per vmapped chunk when fn returns a "detail" output
MAX_DEFAULT_THREADS = 8  # "loop" batching's default thread count: the cores, at most this many


class MCResult(NamedTuple):
    """Stacked per-run outputs (NumPy, leading axis = runs; ``"detail"`` of run 0 unstacked)
    and timings [s]."""

    out: object
    compile_s: float  # trace + lower + compile of the batch program, wall clock
    run_s: float
    n_devices: int
    chunk: int  # runs per compiled call (1 with "loop" batching)
    runs: int  # runs finished: the runs asked for, unless interrupted
    interrupted: bool  # Ctrl-C arrived after at least one chunk (run) had finished
    threads: int = 1  # host threads that ran the runs ("loop" batching; 1 otherwise)


# fn -> {signature: compiled}: a second run() of the same fn (a new seed, more runs) neither
# traces nor compiles; entries go when fn does.  (With a program_key the programs are kept by
# compilation.compile_program instead, across processes too.)
_programs: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def clear_programs() -> None:
    """Forget the compiled programs :func:`run` keeps for the functions it was given."""
    _programs.clear()


def _remembered(fn, signature, build):
    try:
        per_fn = _programs.setdefault(fn, {})
    except TypeError:  # not weak-referenceable: compile every time
        return build()
    if signature not in per_fn:
        per_fn[signature] = build()
    return per_fn[signature]


@jax.jit
def _fold_in_all(base, idx):
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(idx)


def _check_seed(seed) -> int:
    """``seed`` as an int in [-2**63, 2**63) (a signed 64-bit integer, what ``PRNGKey`` takes
    with x64 on), else :class:`InputError` naming ``seed``."""
    try:
        v = check_int(seed, "seed", lower=-2**63)
    except InputError:
        v = None
    if v is None or v >= 2**63:
        raise InputError(f"seed: expected an int in [-2**63, 2**63), got {seed!r}")
    return v


def seed_key(seed: int) -> np.ndarray:
    """The raw key (uint32) of ``jax.random.PRNGKey(seed)`` as JAX makes it with
    ``jax_enable_x64`` on (the seed's 64 bits, two's complement), whatever the x64 setting:
    with x64 off ``PRNGKey`` truncates the seed to 32 bits (seeds 2**32 apart share a key, a
    negative seed gets another key).  ``seed``: an int in [-2**63, 2**63), else an
    :class:`InputError`.  The default threefry2x32 key is ``[high word, low word]``, rbg's that
    pair twice.  Other implementations hash the seed inside ``PRNGKey``: they take seeds in
    [0, 2**31), where the key is the same with x64 on or off (the x64 switch is the entry
    point's, never flipped here)."""
    seed = _check_seed(seed)
    bits = seed & (2**64 - 1)
    hi, lo = bits >> 32, bits & 0xFFFFFFFF
    impl = str(jax.config.jax_default_prng_impl)
    if impl == "threefry2x32":
        return np.array([hi, lo], dtype=np.uint32)
    if impl in ("rbg", "unsafe_rbg"):
        return np.array([hi, lo, hi, lo], dtype=np.uint32)
    if not 0 <= seed < 2**31:
        raise InputError(f"seed: expected an int in [0, 2**31) with the {impl} PRNG, got {seed}")
    return np.asarray(jax.random.PRNGKey(seed))


def keys_for(seed: int, runs: int):
    """The ``runs`` PRNG keys of a Monte Carlo batch (run i uses fold_in(seed key, i)).

    The seed key is ``jax.random.PRNGKey(seed)`` as made with ``jax_enable_x64`` on, whether
    or not x64 is on (every seed in [-2**63, 2**63) has its own key; other seeds are an
    :class:`InputError`).  Returned as a NumPy array (indexing it per run compiles nothing);
    the folds are one compiled program (one per power-of-two count of runs, so a new
    ``runs`` rarely compiles), not a chain of eager operations.
    """
    runs = check_int(runs, "runs", lower=0)
    # the folds run over a power-of-two count (at least 8), so new run counts reuse one of a
    # few compiled programs instead of compiling one per count; each key depends on its index
    # only, so the extra keys are dropped unchanged
    size = max(8, 1 << max(0, runs - 1).bit_length())
    return np.asarray(_fold_in_all(seed_key(seed), np.arange(size)))[:runs]


def run(fn: Callable, seed: int, runs: int, chunk: Optional[int] = None,
        progress=None, devices: Optional[Sequence] = None, *, cpu_batching: str = "vmap",
        detail: bool = False, program_key=None, threads: Optional[int] = None) -> MCResult:
    """Evaluate ``fn(key)`` for ``runs`` seeded keys; see the module docstring.

    Args:
      fn: key -> pytree of arrays (pure, jit-able); with ``detail`` a dict holding
        ``"detail"``, which is kept for the first run only.
      seed, runs: the batch: run i gets ``fold_in(PRNGKey(seed), i)`` (the key ``PRNGKey``
        makes with ``jax_enable_x64`` on, whatever the setting; ``seed`` in [-2**63, 2**63)),
        so run i is the same flight whatever the chunk size, the batching, the device count
        or ``runs``.  Bit for bit: a call repeated gives the same results, and with
        ``"loop"`` batching run i's result does not depend on ``threads`` or ``runs``.  A
        vmapped program is compiled for its batch shape (the chunk, each device's share of
        it), and XLA may round differently for another shape, so other chunk sizes (the
        default chunk follows ``runs``) or device counts, and ``"loop"`` against
        ``"vmap"``, agree to rounding only (``uwb-circle``, 20 s, float32: about 1e-7
        relative between chunk 3 and chunk 1).
      chunk: runs per compiled call (default: all runs; capped at 256, or ``DETAIL_CHUNK``
        with a ``"detail"`` output, whether given or not; rounded up to a multiple of the
        device count).  Ignored by ``"loop"`` batching.
      progress: None or an object with ``update(n_done)`` (jaxslam.progress.Progress; its
        ``compiling()`` block, when it has one, shows the compilation), else an
        :class:`InputError` naming ``progress``.
      devices: devices to shard over (default: ``jax.local_devices()``).
      cpu_batching: ``"vmap"`` or ``"loop"``, used when the devices are CPUs.
      detail: ``fn`` returns a ``"detail"`` entry (module docstring); True or False (NumPy's
        too), else an :class:`InputError` naming ``detail``.
      program_key: JSON-able description of everything ``fn`` depends on besides its key
        (scenario, options, parameters, dtype): the traced program is then kept in the
        persistent cache and a later process skips tracing
        (:func:`jaxslam.compilation.compile_program`).
      threads: host threads that call the compiled single run with ``"loop"`` batching
        (default :func:`default_threads`); ignored otherwise.  Results do not depend on it.
    """
    runs = check_int(runs, "runs")
    detail = check_flag(detail, "detail")
    if progress is not None and not callable(getattr(progress, "update", None)):
        raise InputError(f"progress: expected None or an object with update(n_done), got {type(progress).__name__}")
    threads = default_threads() if threads is None else check_int(threads, "threads", what="None or an int")
    chunk = None if chunk is None else check_int(chunk, "chunk", what="None or an int")
    if not isinstance(cpu_batching, str) or cpu_batching not in ("vmap", "loop"):
        raise InputError(f"cpu_batching: expected 'vmap' or 'loop', got {cpu_batching!r}")
    seed = _check_seed(seed)
    if devices is not None:
        try:  # an iterator is read once, here
            devices = list(devices)
        except TypeError:
            raise InputError(f"devices: expected a sequence of devices, got {type(devices).__name__}") from None
        if not devices:
            raise InputError("devices: an empty list (None: every local device)")
    if devices is None and jax.process_count() > 1:  # a group of processes: one block each
        from . import distributed

        # block -> settle -> gather in one section: from the block's end a Ctrl-C is held, so this
        # process reaches both collectives whenever it comes (distributed's module docstring)
        with distributed.section() as group:
            start, size = distributed.block(runs)
            try:
                # every block has the same length (the collective needs it): the last blocks run the
                # next indices' keys, whose results are dropped
                keys = keys_for(seed, jax.process_count() * size)[start:start + size]
                res = group.block(_run_keys, fn, keys, chunk,
                                  _GroupProgress(progress, jax.process_count(), runs),
                                  jax.local_devices(), cpu_batching, detail, program_key, threads)
            except BaseException as e:  # a Ctrl-C before a chunk finished, or an error: the group hears of it
                distributed.settle(e)  # raises e
            # all or nothing: a partial block (Ctrl-C) ends the run in every process, before the
            # gather (blocks of other lengths aborted gloo; equal partial ones gave the wrong runs)
            distributed.settle(KeyboardInterrupt() if res.interrupted else None)
            out = dict(res.out) if detail else res.out
            det = out.pop("detail") if detail else None
            out = distributed.gather(out, runs)  # a Ctrl-C held after settle: re-delivered as the section ends
            if detail:
                out["detail"] = det  # run 0's record: process 0's (the one that plots)
        return res._replace(out=out, runs=runs, interrupted=False)
    devices = devices if devices is not None else jax.local_devices()
    return _run_keys(fn, keys_for(seed, runs), chunk, progress, devices, cpu_batching, detail, program_key,
                     threads)


def default_threads() -> int:
    """Host threads of ``"loop"`` batching when :func:`run` is not told: ``$JAXSLAM_MC_THREADS``
    when set (a positive integer in decimal digits, else an :class:`InputError`), else 1 in a group of processes (each process already has its cores), else the
    cores this process may use, at most :data:`MAX_DEFAULT_THREADS`."""
    env = os.environ.get("JAXSLAM_MC_THREADS", "").strip()
    if env:
        # digits only: int() would also read "2_0" as 20 and "٣" as 3
        n = int(env) if env.isascii() and env.isdigit() else 0
        if n < 1:
            raise InputError(f"JAXSLAM_MC_THREADS: expected a positive integer, got {env!r}")
        return n
    if jax.process_count() > 1:
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_THREADS))


class _GroupProgress:
    """A process's progress over its block shown as the group's (every process runs its block
    at about the same pace): ``update(n)`` reports ``min(n · processes, runs)``."""

    def __init__(self, progress, processes: int, runs: int):
        self._p, self._k, self._runs = progress, processes, runs
        self.compiling = getattr(progress, "compiling", None)

    def update(self, n: int) -> None:
        if self._p is not None:
            self._p.update(min(n * self._k, self._runs))


def _with_detail(o):
    """``o``, the output of ``fn`` when ``detail=True``: a dict holding ``"detail"``."""
    if not isinstance(o, dict) or "detail" not in o:
        got = f"keys {sorted(o)}" if isinstance(o, dict) else type(o).__name__
        raise InputError(f"fn: with detail=True it must return a dict holding a 'detail' entry, got {got}")
    return o


def _program(fn, devices, has_detail, opts):
    """``(batched, jitted, sharding)``: ``vmap(fn)`` over a chunk of keys, and with several
    devices its jitted form that splits the chunk over them (``jitted``, ``sharding`` None for
    one device).  Only the first run's ``detail`` leaves the program."""
    def first_detail(o, keep):
        return {**_with_detail(o), "detail": jax.tree.map(keep, o["detail"])} if has_detail else o

    if len(devices) == 1:
        return (lambda k: first_detail(jax.vmap(fn)(k), lambda a: a[0])), None, None
    mesh = Mesh(np.array(devices), ("runs",))
    spec = PartitionSpec("runs")
    shard = NamedSharding(mesh, spec)
    # Each device runs its own block of runs under shard_map: the runs are independent, so no
    # value crosses devices.  A plain jit(vmap) with sharded keys let the partitioner turn a
    # reduction over the runs axis inside fn (the shared loop bound of a batched EKF-SLAM
    # update) into a cross-device all-reduce inside the scan, one per step.  check_vma off: a
    # run's scan may start its carry from constants that only its outputs make per-device.
    block = jax.shard_map(lambda k: first_detail(jax.vmap(fn)(k), lambda a: a[:1]),
                          mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)

    def batched(k):
        return first_detail(block(k), lambda a: a[0])

    return batched, jax.jit(batched, in_shardings=shard, compiler_options=opts), shard


def _loop_runs(compiled, keys, threads, has_detail, progress):
    """Run i = ``compiled(keys[i])`` for every key, on ``threads`` host threads (each takes the
    next run index; XLA runs without the GIL).  Returns the outputs in run order: all of them,
    or after a Ctrl-C the longest finished prefix (runs finished beyond a gap are dropped, at
    most ``threads`` - 1 of them).  A Ctrl-C before any run has finished propagates, as does
    the first error of a run (once the runs in flight have finished)."""
    runs = int(keys.shape[0])
    outs = [None] * runs

    def one(i):
        res = jax.block_until_ready(compiled(keys[i]))
        if has_detail:  # every run: with threads, a later run may finish before run 0
            _with_detail(res)
        if has_detail and i > 0:  # only run 0's detail is kept: never copied to the host
            res = {k: v for k, v in res.items() if k != "detail"}
        return jax.tree.map(np.asarray, res)

    def finished():
        n = 0
        while n < runs and outs[n] is not None:
            n += 1
        return outs[:n]

    if threads <= 1 or runs <= 1:
        try:
            for i in range(runs):
                outs[i] = one(i)
                if progress is not None:
                    progress.update(i + 1)
        except KeyboardInterrupt:
            if outs[0] is None:
                raise
        return finished()

    order = iter(range(runs))
    take = threading.Lock()
    stop = threading.Event()
    done: "queue.Queue" = queue.Queue()

    def worker():
        while not stop.is_set():
            with take:
                i = next(order, None)
            if i is None:
                return
            try:
                outs[i] = one(i)
            except BaseException as e:  # handed to the calling thread, which raises it
                stop.set()
                done.put(e)
                return
            done.put(i)

    pool = [threading.Thread(target=worker, name=f"jaxslam-mc-{j}", daemon=True)
            for j in range(min(threads, runs))]
    for t in pool:
        t.start()
    n_done = 0
    try:
        while n_done < runs:
            try:
                item = done.get(timeout=0.2)  # a timeout keeps Ctrl-C deliverable
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise item
            n_done += 1
            if progress is not None:
                progress.update(n_done)
    except KeyboardInterrupt:
        stop.set()
        for t in pool:  # the runs in flight finish; no new one starts
            t.join()
        if outs[0] is None:
            raise
        return finished()
    finally:
        # also before an error of a run propagates: the runs in flight finish first (no worker
        # thread outlives the call, still inside XLA when the interpreter exits)
        stop.set()
        for t in pool:
            t.join()
    return finished()


def _run_keys(fn, keys, chunk, progress, devices, cpu_batching, detail, program_key, threads=1) -> MCResult:
    """:func:`run` over the given keys (one per run) on ``devices``."""
    runs = int(keys.shape[0])
    nd = len(devices)
    has_detail = bool(detail)
    loop = nd == 1 and devices[0].platform == "cpu" and cpu_batching == "loop"
    opts = runtime.compiler_options()
    compiling = getattr(progress, "compiling", None)

    def compile_(f, arg, jitted=None):
        def build():
            if jitted is not None:  # sharded over several devices
                return jitted.lower(arg).compile()
            key = None if program_key is None else {"mc": program_key, "loop": loop, "detail": has_detail}
            return compilation.compile_program(f, (arg,), key=key, compiler_options=opts)

        def remembered():
            if program_key is not None and jitted is None:  # compile_program keeps it
                return build()
            sig = (loop, has_detail, tuple(d.id for d in devices), tuple(np.shape(arg)), str(np.asarray(arg).dtype),
                   tuple(sorted((opts or {}).items())), bool(jax.config.jax_enable_x64))
            return _remembered(fn, sig, build)

        t0 = time.perf_counter()
        if compiling is not None:
            with compiling():
                c = remembered()
        else:
            c = remembered()
        return c, time.perf_counter() - t0

    if loop:
        compiled, compile_s = compile_(fn, keys[0])
        t0 = time.perf_counter()
        outs = _loop_runs(compiled, keys, threads, has_detail, progress)
        run_s = time.perf_counter() - t0
        detail = outs[0].pop("detail") if has_detail else None
        out = jax.tree.map(lambda *a: np.stack(a, axis=0), *outs)
        if has_detail:
            out["detail"] = detail
        return MCResult(out=out, compile_s=compile_s, run_s=run_s, n_devices=nd, chunk=1,
                        runs=len(outs), interrupted=len(outs) < runs, threads=min(threads, runs))

    cap = DETAIL_CHUNK if has_detail else 256
    chunk = min(runs, cap) if chunk is None else min(chunk, runs, cap)
    chunk = int(math.ceil(chunk / nd) * nd)
    n_chunks = int(math.ceil(runs / chunk))
    pad = n_chunks * chunk - runs
    if pad:
        keys = np.concatenate([keys, np.repeat(keys[-1:], pad, axis=0)], axis=0)

    batched, jitted, shard = _program(fn, devices, has_detail, opts)

    def place(k):
        return jax.device_put(k, shard) if shard is not None else k

    compiled, compile_s = compile_(batched, place(keys[:chunk]), jitted)

    outs = []
    detail = None
    t0 = time.perf_counter()
    try:
        for c in range(n_chunks):
            res = compiled(place(keys[c * chunk:(c + 1) * chunk]))
            res = dict(jax.block_until_ready(res)) if has_detail else jax.block_until_ready(res)
            if has_detail:  # only the first chunk's detail is kept: never copied to the host otherwise
                d = res.pop("detail")
                detail = jax.tree.map(np.asarray, d) if c == 0 else detail
            outs.append(jax.tree.map(np.asarray, res))
            if progress is not None:
                progress.update(min((c + 1) * chunk, runs))
    except KeyboardInterrupt:
        if not outs:
            raise
    run_s = time.perf_counter() - t0
    done = min(len(outs) * chunk, runs)
    out = jax.tree.map(lambda *a: np.concatenate(a, axis=0)[:done], *outs)
    if has_detail:
        out["detail"] = detail
    return MCResult(out=out, compile_s=compile_s, run_s=run_s, n_devices=nd, chunk=chunk,
                    runs=done, interrupted=done < runs)
