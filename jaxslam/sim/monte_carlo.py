"""Monte Carlo runner: ``vmap`` over seeds, in chunks, sharded over every local device.

``run(fn, seed, runs)`` evaluates ``fn(key)`` — a pure, jit-able function of
one PRNG key returning a pytree of arrays (one flight: simulate → filter →
metrics) — for ``runs`` keys.  Runs are processed in chunks of ``chunk`` so
memory stays bounded (progress is reported per chunk); each chunk is one
compiled ``jit(vmap(fn))`` call, padded to the chunk size so the last one does
not recompile.

Devices: the chunk's leading (runs) axis is sharded over all local devices with
a 1-D ``jax.sharding.Mesh``; XLA partitions the vmapped computation, so the
same call uses every GPU a machine has (the chunk is padded to a multiple of
the device count).  Across hosts, start each process with
``jax.distributed.initialize()`` and pass ``devices=jax.devices()`` (global
devices): the same mesh then spans hosts — every process must call ``run``
with the same arguments.  On a CPU the sharding can be exercised with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (tested).

Timing separates compilation (``lower().compile()``) from execution, which is
measured with ``block_until_ready``.
"""

from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["MCResult", "run", "keys_for"]


class MCResult(NamedTuple):
    """Stacked per-run outputs (NumPy, leading axis = runs) and timings [s]."""

    out: object
    compile_s: float
    run_s: float
    n_devices: int
    chunk: int


def keys_for(seed: int, runs: int):
    """The ``runs`` PRNG keys of a Monte Carlo batch (run i uses fold_in(seed key, i))."""
    base = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(runs))


def run(fn: Callable, seed: int, runs: int, chunk: Optional[int] = None,
        progress=None, devices: Optional[Sequence] = None) -> MCResult:
    """Evaluate ``fn(key)`` for ``runs`` seeded keys; see the module docstring.

    Args:
      fn: key -> pytree of arrays (pure, jit-able).
      seed, runs: the batch (run i gets ``fold_in(PRNGKey(seed), i)``, so a run's
        result does not depend on the chunk size or device count).
      chunk: runs per compiled call (default: all runs, capped at 256).
      progress: optional object with ``update(n_done)`` (jaxslam.progress.Progress).
      devices: devices to shard over (default: ``jax.local_devices()``).
    """
    if runs < 1:
        raise ValueError(f"runs: must be >= 1, got {runs}")
    devices = list(devices) if devices is not None else jax.local_devices()
    nd = len(devices)
    chunk = min(runs, 256) if chunk is None else max(1, min(int(chunk), runs))
    chunk = int(math.ceil(chunk / nd) * nd)
    keys = keys_for(seed, runs)
    n_chunks = int(math.ceil(runs / chunk))
    pad = n_chunks * chunk - runs
    if pad:
        keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)], axis=0)

    batched = jax.vmap(fn)
    if nd > 1:
        mesh = Mesh(np.array(devices), ("runs",))
        shard = NamedSharding(mesh, PartitionSpec("runs"))
        jitted = jax.jit(batched, in_shardings=shard)
    else:
        shard = None
        jitted = jax.jit(batched)

    def place(k):
        return jax.device_put(k, shard) if shard is not None else k

    t0 = time.perf_counter()
    compiled = jitted.lower(place(keys[:chunk])).compile()
    compile_s = time.perf_counter() - t0

    outs = []
    t0 = time.perf_counter()
    for c in range(n_chunks):
        res = compiled(place(keys[c * chunk:(c + 1) * chunk]))
        res = jax.block_until_ready(res)
        outs.append(jax.tree.map(np.asarray, res))
        if progress is not None:
            progress.update(min((c + 1) * chunk, runs))
    run_s = time.perf_counter() - t0
    out = jax.tree.map(lambda *a: np.concatenate(a, axis=0)[:runs], *outs)
    return MCResult(out=out, compile_s=compile_s, run_s=run_s, n_devices=nd, chunk=chunk)
