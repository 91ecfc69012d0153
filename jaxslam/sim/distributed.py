"""Monte Carlo over several processes with JAX's own distributed runtime.

``jax.distributed.initialize`` joins this process to a group (one coordinator address, the
group size, this process's index); :func:`jaxslam.sim.monte_carlo.run` then gives each process
a contiguous block of the runs, runs it on its own devices exactly as a single process would
(run i still uses ``fold_in(PRNGKey(seed), i)``, so it is the same flight however many
processes share the batch; vmapped, a block's batch shape differs from one process's chunk, so
the figures agree to rounding, as between chunk sizes in ``monte_carlo.run``) and gathers every block to every process with
``multihost_utils.process_allgather``.  Nothing is scheduled by hand: JAX's coordination service
starts the group and its collectives move the results (on CPUs the ``gloo`` collectives,
selected by :func:`initialize` before the backend starts).

Usage: ``jaxslam run SCENARIO --runs N --processes P`` starts P processes on this machine
(loopback coordinator, a free port); on a cluster start one process per host with
``--coordinator HOST:PORT --num-processes P --process-id I`` (process 0 prints and writes the
JSON and plots; the others only compute).  From Python, call :func:`initialize` first in every
process, then ``monte_carlo.run`` with the same arguments in each.

Decisions: blocks, not strides (the first run, whose record feeds the plots, is process 0's);
each block is padded to the same length with the keys of the next run indices (the collective
needs equal shapes; the padding is computed and dropped); a Ctrl-C is not handled per block:
the distributed run is all or nothing.  Before the gather every process says how its block ended
(:func:`settle`, one small collective that each process reaches whatever happened), so a Ctrl-C
in any of them ends the run with ``KeyboardInterrupt`` in all of them (an error: that error in
its process, a ``RuntimeError`` naming it in the others) instead of a gather of blocks of
different lengths (gloo aborted the processes) or of equal partial ones (a batch of the wrong
runs, not marked interrupted).

A Ctrl-C must not make one process leave the group's collectives while the others wait in one
(until gloo or the coordinator gives up, or the launcher stops them): :func:`settle` and
:func:`gather` hold a SIGINT that arrives while they run (before their collective, a
``KeyboardInterrupt`` there skipped it) and act on it when the collective is done.  One that
arrives before :func:`settle` chose this process's word is an interrupted block; after it, with
every block finished, the group goes on to the gather, and the Ctrl-C is re-delivered when
:func:`gather` has gathered (in ``jaxslam run``: exit 130, nothing written).  The caller's
bytecodes around them (after its block, before :func:`settle`; between :func:`settle` and
:func:`gather`) are held too when it runs all three in one :func:`section`
(:func:`jaxslam.sim.monte_carlo.run` does): the block runs in :meth:`Section.block`, where a
Ctrl-C acts as usual, and the section holds a SIGINT from the block's end (a Ctrl-C there, or
before the block, is an interrupted block) until the section is left, where one held after
:func:`settle` is re-delivered.  What is left: the bytecodes of the caller before it enters the
section (a Ctrl-C there, in one process only, leaves the others waiting in :func:`settle`;
under ``--processes`` the launcher stops them 5 s after that process ended).

Importing this module does not import JAX (the launcher of ``--processes`` uses
:func:`free_port`).
"""

from __future__ import annotations

import contextlib
import signal
import socket
import threading
from typing import Optional

import numpy as np

from ..errors import InputError, check_int

__all__ = ["initialize", "active", "is_leader", "block", "section", "Section", "settle", "gather", "free_port"]


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join the group (``jax.distributed.initialize``); call before any JAX computation.

    ``coordinator`` "HOST:PORT" (process 0 listens there); ``num_processes`` ≥ 1;
    ``process_id`` in [0, num_processes).  Selects the gloo CPU collectives first, so CPU-only
    machines can gather results."""
    num_processes = check_int(num_processes, "--num-processes", lower=1, what="an integer")
    try:
        pid = check_int(process_id, "--process-id", lower=0)
    except InputError:
        pid = -1
    if not 0 <= pid < num_processes:
        raise InputError(f"--process-id: expected 0 to {num_processes - 1}, got {process_id!r}")
    process_id = pid
    host, _, port = str(coordinator).rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--coordinator: expected HOST:PORT, got {coordinator!r}")
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=str(coordinator), num_processes=num_processes,
                               process_id=process_id)


def active() -> bool:
    """True when this process belongs to a group of more than one."""
    import jax

    return jax.process_count() > 1


def is_leader() -> bool:
    """Process 0 (or a single process): the one that prints and writes."""
    import jax

    return jax.process_index() == 0


def block(runs: int, num_processes: Optional[int] = None, index: Optional[int] = None) -> tuple:
    """``(start, size)``: this process's contiguous block of ``runs`` run indices, ``size`` the
    common (padded) block length ``ceil(runs / P)``; ``start`` may pass ``runs`` for the last
    processes of a small batch (their block is all padding).  ``runs`` ≥ 0, ``num_processes``
    ≥ 1 and ``index`` in [0, num_processes) are ints (NumPy's too; not bools), else an
    :class:`InputError` naming the argument."""
    import jax

    runs = check_int(runs, "runs", lower=0)
    P = jax.process_count() if num_processes is None else check_int(num_processes, "num_processes")
    i = jax.process_index() if index is None else check_int(index, "index", lower=0)
    if i >= P:
        raise InputError(f"index: expected 0 to {P - 1} (a process of {P}), got {index!r}")
    size = -(-runs // P)  # ceil(runs / P), exact for any int
    return i * size, size


_FINISHED, _INTERRUPTED, _FAILED = 0, 1, 2
_held_interrupt = False  # a Ctrl-C that settle held after every block finished; gather re-delivers it
_section: Optional["Section"] = None  # the section holding SIGINT now (main thread), if any


class Section:
    """A process's block, :func:`settle` and :func:`gather` as one section that a Ctrl-C cannot
    leave between them (module docstring); made by :func:`section`."""

    def __init__(self):
        self._heard = []  # the SIGINTs held (noted, not acted on)
        self._holding = True
        self._previous = None  # the handler the section replaced (None: it installed none)
        self._outer = None

    def _on_sigint(self, signum, frame):
        if self._holding:
            self._heard.append(signum)
        else:  # in the block: the handler the section replaced acts (Python's: KeyboardInterrupt)
            self._previous(signum, frame)

    def block(self, fn, *args, **kwargs):
        """``fn(*args, **kwargs)``: this process's block, where a Ctrl-C acts as without the section
        (``KeyboardInterrupt``); one held before it raises ``KeyboardInterrupt`` here (an
        interrupted block).  The section holds SIGINT again from the moment ``fn`` returns or
        raises (its result or exception then goes on with no Ctrl-C in between)."""
        try:
            self._holding = False
            if self._heard:  # a Ctrl-C since the section began
                self._heard.clear()
                raise KeyboardInterrupt
            return fn(*args, **kwargs)
        finally:
            self._holding = True

    def __enter__(self):
        global _section
        previous = signal.getsignal(signal.SIGINT)
        if threading.current_thread() is threading.main_thread() and callable(previous):
            # (as _sigint_held: only in the main thread, over a handler of Python's)
            self._previous, self._outer, _section = previous, _section, self
            signal.signal(signal.SIGINT, self._on_sigint)  # holding: a Ctrl-C now is noted
        return self

    def __exit__(self, exc_type, exc, tb):
        global _section
        if self._previous is None:
            return False
        _section = self._outer
        signal.signal(signal.SIGINT, self._previous)
        if self._heard and exc_type is None:  # held after settle: the batch is gathered, act on it
            self._heard.clear()
            signal.raise_signal(signal.SIGINT)
        return False  # (with an exception on its way the run already ends: a Ctrl-C held is dropped)


def section() -> Section:
    """``with distributed.section() as s:`` run the block with ``s.block(fn, ...)``, then
    :func:`settle` and :func:`gather` within: a SIGINT is held from the block's end to the
    section's end, so no Ctrl-C makes this process leave between the block and the collectives
    (module docstring).  A Ctrl-C held before :func:`settle` chose this process's word makes the
    block interrupted; one held after it is re-delivered when the section is left after the
    gather.  Outside the main thread, or with SIGINT ignored, it holds nothing."""
    return Section()


def _holding_section() -> Optional[Section]:
    """The section that holds SIGINT in this thread now, if any."""
    sec = _section
    if sec is not None and sec._holding and threading.current_thread() is threading.main_thread():
        return sec
    return None


@contextlib.contextmanager
def _sigint_held():
    """Within: a SIGINT is noted in the list this yields, not acted on; on exit the previous
    handler is back (the caller acts on what was noted).  Only in the main thread (where Python
    runs its handlers, so where a ``KeyboardInterrupt`` can land) and over a handler of Python's
    (SIGINT ignored stays ignored).  Within a :func:`section` holding SIGINT: the section's list
    (held before the caller began, too), and the section goes on holding on exit."""
    sec = _holding_section()
    if sec is not None:
        yield sec._heard
        return
    heard = []
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(previous):
        yield heard
        return
    signal.signal(signal.SIGINT, lambda signum, frame: heard.append(signum))
    try:
        yield heard
    finally:
        signal.signal(signal.SIGINT, previous)


def _redeliver_sigint() -> None:
    """The SIGINT held meanwhile, to the handler now in place (Python's: ``KeyboardInterrupt``
    here; ``jaxslam`` counts it too); within a :func:`section`, when the section is left."""
    sec = _holding_section()
    if sec is not None:
        sec._heard.append(signal.SIGINT)
        return
    signal.raise_signal(signal.SIGINT)


def settle(error: Optional[BaseException] = None) -> None:
    """Every process of the group says how its block ended, in one collective each reaches
    (call it in every process, after the block, whatever happened; then :func:`gather`).

    ``error``: None (this block finished), a ``KeyboardInterrupt`` (a Ctrl-C: its block is
    partial) or the exception its block raised.  Returns only when every block finished;
    else this process raises its own ``error``, or ``KeyboardInterrupt`` when another process
    was interrupted (the run is all or nothing), or a ``RuntimeError`` naming the process that
    failed (its own error output says why).

    A Ctrl-C while it runs is held until its collective is done: one before this process's
    word is chosen makes its block interrupted; one after it, when every block finished, is
    re-delivered by :func:`gather` once the group has gathered (module docstring)."""
    global _held_interrupt
    _held_interrupt = False
    with _sigint_held() as heard:
        from jax.experimental import multihost_utils

        if error is None and heard:
            error = KeyboardInterrupt()  # a Ctrl-C before the word was chosen
        code = (_FINISHED if error is None else _INTERRUPTED if isinstance(error, KeyboardInterrupt)
                else _FAILED)
        codes = np.asarray(multihost_utils.process_allgather(np.array([code], np.int32), tiled=False)).reshape(-1)
        late = bool(heard) and code == _FINISHED  # after the word: the others go on to the gather
        heard.clear()  # (acted on here, or by gather through _held_interrupt)
    if error is not None:
        raise error
    if (codes == _INTERRUPTED).any():
        raise KeyboardInterrupt
    if (codes == _FAILED).any():
        i = int(np.argmax(codes == _FAILED))
        raise RuntimeError(f"process {i} of the group ({codes.size} processes) failed in its block of runs")
    _held_interrupt = late


def gather(out, runs: int):
    """Every process's block of per-run outputs (a pytree of NumPy arrays, leading axis = the
    block) gathered into the whole batch, in run order, trimmed to ``runs``.

    A Ctrl-C while it runs, or one :func:`settle` held, is acted on when the batch is
    gathered: ``KeyboardInterrupt`` (in every process it reached; the others have the batch)."""
    global _held_interrupt
    import jax

    heard = []
    try:
        with _sigint_held() as heard:
            from jax.experimental import multihost_utils

            g = multihost_utils.process_allgather(out, tiled=False)  # (P, size, ...) per leaf
    finally:
        held, _held_interrupt = _held_interrupt or bool(heard), False
        if held:
            _redeliver_sigint()
    return jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[2:])[:runs], g)


def free_port() -> int:
    """A TCP port free on the loopback interface now (for a one-machine group: the launcher of
    ``jaxslam run ... --processes P`` takes its coordinator's port here, without importing JAX)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
