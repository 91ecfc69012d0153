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
"""

from __future__ import annotations

import socket
from typing import Optional

import jax
import numpy as np

from ..errors import InputError
from ..linalg import check_int

__all__ = ["initialize", "active", "is_leader", "block", "settle", "gather", "free_port"]


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
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=str(coordinator), num_processes=num_processes,
                               process_id=process_id)


def active() -> bool:
    """True when this process belongs to a group of more than one."""
    return jax.process_count() > 1


def is_leader() -> bool:
    """Process 0 (or a single process): the one that prints and writes."""
    return jax.process_index() == 0


def block(runs: int, num_processes: Optional[int] = None, index: Optional[int] = None) -> tuple:
    """``(start, size)``: this process's contiguous block of ``runs`` run indices, ``size`` the
    common (padded) block length ``ceil(runs / P)``; ``start`` may pass ``runs`` for the last
    processes of a small batch (their block is all padding).  ``runs`` ≥ 0, ``num_processes``
    ≥ 1 and ``index`` in [0, num_processes) are ints (NumPy's too; not bools), else an
    :class:`InputError` naming the argument."""
    runs = check_int(runs, "runs", lower=0)
    P = jax.process_count() if num_processes is None else check_int(num_processes, "num_processes")
    i = jax.process_index() if index is None else check_int(index, "index", lower=0)
    if i >= P:
        raise InputError(f"index: expected 0 to {P - 1} (a process of {P}), got {index!r}")
    size = -(-runs // P)  # ceil(runs / P), exact for any int
    return i * size, size


_FINISHED, _INTERRUPTED, _FAILED = 0, 1, 2


def settle(error: Optional[BaseException] = None) -> None:
    """Every process of the group says how its block ended, in one collective each reaches
    (call it in every process, after the block, whatever happened; then :func:`gather`).

    ``error``: None (this block finished), a ``KeyboardInterrupt`` (a Ctrl-C: its block is
    partial) or the exception its block raised.  Returns only when every block finished;
    else this process raises its own ``error``, or ``KeyboardInterrupt`` when another process
    was interrupted (the run is all or nothing), or a ``RuntimeError`` naming the process that
    failed (its own error output says why)."""
    from jax.experimental import multihost_utils

    code = (_FINISHED if error is None else _INTERRUPTED if isinstance(error, KeyboardInterrupt)
            else _FAILED)
    codes = np.asarray(multihost_utils.process_allgather(np.array([code], np.int32), tiled=False)).reshape(-1)
    if error is not None:
        raise error
    if (codes == _INTERRUPTED).any():
        raise KeyboardInterrupt
    if (codes == _FAILED).any():
        i = int(np.argmax(codes == _FAILED))
        raise RuntimeError(f"process {i} of the group ({codes.size} processes) failed in its block of runs")


def gather(out, runs: int):
    """Every process's block of per-run outputs (a pytree of NumPy arrays, leading axis = the
    block) gathered into the whole batch, in run order, trimmed to ``runs``."""
    from jax.experimental import multihost_utils

    g = multihost_utils.process_allgather(out, tiled=False)  # (P, size, ...) per leaf
    return jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[2:])[:runs], g)


def free_port() -> int:
    """A TCP port free on the loopback interface now (for a one-machine group)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
