"""UWB range-only EKF-SLAM benchmark (paper 003): runs/second vmapped vs sequential vs a NumPy twin.

Run with ``python -m jaxslam bench uwb [--json benchmarks/results/uwb.json] [options]``
(float64: the CLI enables x64 and pins OpenBLAS to one thread unless the user set
``OPENBLAS_NUM_THREADS``; the JSON records the setting).

Two parts, for every batch size M in ``--runs``:

``filter``  the filter alone on M simulated logs of the chosen scenario (default
   ``uwb-circle``, SLAM, squared range, paper noise; 126 steps after a 21-sample
   start-up): ``jax.jit(jax.vmap(run))`` over the M logs (one call), M calls of the
   jitted single-log ``run``, and the NumPy twin (``numpy_uwb.run``, the same filter
   in the paper's state order with hand Jacobians) looped over the logs.  Sequential
   and twin times are measured over min(M, ``--seq-max``) / min(M, ``--twin-max``)
   logs and scaled to M (each log costs the same); the JSON says so.  The twin and
   the package are compared on the first log (max |Δ| of the robot means).

``mc``      a whole Monte Carlo run (simulate → filter → metrics, what
   ``jaxslam run uwb-circle`` does): ``jax.jit(jax.vmap(one_run))`` over M keys, in
   chunks of at most ``--mc-chunk`` (250) runs as ``jaxslam.sim.monte_carlo.run`` does,
   vs M sequential calls of the jitted single run.  (A single 1000-run call of this
   program hung inside XLA's CPU runtime twice on the shared 2-core machine: all threads
   idle in futex waits, no CPU time used.)

Medians over ``--repeats`` after one warm-up call (the NumPy twin: over min(``--repeats``, 2));
``block_until_ready`` on every JAX result; compile times reported apart (``vmap_compile_s``:
the first call of the program for that batch shape; a batch size that reuses an earlier
one's program, e.g. ``--runs 250,1000`` with ``--mc-chunk 250``, reports that compile time).
A batch size given twice in ``--runs`` is run once.  ``load_average`` records how busy the
machine was (shared 2-core machines make timings noisy).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from timing import int_list, median_s

DESCRIPTION = ("Paper 003 UWB range-only EKF-SLAM: runs/s of jax.vmap vs sequential jitted runs vs "
               "a NumPy twin (filter alone and whole Monte Carlo runs)")

TARGETS = {"vmap_vs_twin_at_100": 10.0, "vmap_vs_sequential_at_100": 2.0}


def add_arguments(parser):
    """Benchmark options (defaults: about a minute on 2 CPU cores)."""
    parser.add_argument("--runs", default="1,10,100,1000", help="batch sizes M (default 1,10,100,1000)")
    parser.add_argument("--scenario", default="circle", choices=("circle", "square", "rough"))
    parser.add_argument("--mode", default="slam", choices=("slam", "localization"))
    parser.add_argument("--model", default="squared", choices=("squared", "range"))
    parser.add_argument("--filter", default="paper", choices=("paper", "matched"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed repeats (median; default 3; the NumPy twin uses min(REPEATS, 2))")
    parser.add_argument("--seq-max", type=int, default=50,
                        help="sequential jitted calls actually timed per M (default 50)")
    parser.add_argument("--twin-max", type=int, default=10,
                        help="NumPy twin runs actually timed per M (default 10)")
    parser.add_argument("--parts", default="filter,mc", help="comma list: filter, mc")
    parser.add_argument("--mc-chunk", type=int, default=250,
                        help="Monte Carlo runs per vmapped call (default 250)")


def _progress(msg):
    print(f"[bench uwb] {msg}", file=sys.stderr, flush=True)


def run(args):
    """Run the selected parts; returns the bench JSON dict (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)  # standalone use; the CLI has set it already
    import numpy_uwb as tw

    from jaxslam.errors import InputError
    from jaxslam.sim import monte_carlo
    from jaxslam.sim.scenarios import uwb as S
    from jaxslam.systems import uwb_slam_2d as U

    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    if not parts:
        raise InputError(f"--parts: no part given (got {args.parts!r}); choose filter, mc")
    if parts - {"filter", "mc"}:
        raise InputError(f"--parts: unknown part(s) {sorted(parts - {'filter', 'mc'})}; choose filter, mc")
    Ms = list(dict.fromkeys(int_list(args.runs, "--runs")))  # a repeated size: one row, not two
    for flag, v in (("--repeats", args.repeats), ("--seq-max", args.seq_max), ("--twin-max", args.twin_max)):
        if v < 1:
            raise InputError(f"{flag}: must be >= 1, got {v}")
    opts = dict(mode=args.mode, model=args.model, noise="uniform", filter=args.filter, duration=None, dt=1.0,
                anchors=3, startup_speed=0.15, max_range=0.0, chunk=None)
    one_run, flight, cfg, fp, setup = S.build(args.scenario, opts, jnp.float64)
    anchors = jnp.asarray(setup.anchors)
    load = {"before": list(os.getloadavg())}
    results, out = [], {"targets": []}
    Mmax = max(Ms)
    keys = monte_carlo.keys_for(args.seed, Mmax)
    case = f"uwb-{args.scenario} {args.mode} {args.model} ({setup.ts.shape[0]} steps)"

    if "filter" in parts:
        _progress(f"simulating {Mmax} logs")
        logs = jax.jit(jax.vmap(lambda k: S.simulate(k, setup, jnp.float64).log))(keys)
        logs = jax.block_until_ready(logs)
        def with_anchors(log):
            return log._replace(anchors=anchors) if cfg.mode == "localization" else log

        single = jax.jit(lambda log: U.run(with_anchors(log), cfg, fp))
        batched = jax.jit(jax.vmap(lambda log: U.run(with_anchors(log), cfg, fp)))
        log0 = jax.tree.map(lambda a: a[0], logs)
        t0 = time.perf_counter()
        res0 = jax.block_until_ready(single(log0))
        compile_single = time.perf_counter() - t0
        ref0 = tw.run(jax.tree.map(np.asarray, log0), cfg, fp, np.asarray(anchors))
        agree = float(np.max(np.abs(np.asarray(res0.steps.mean) - ref0["mean"])))
        rows = []
        compiled = {}
        for M in Ms:
            lm = jax.tree.map(lambda a: a[:M], logs)
            if M not in compiled:
                t0 = time.perf_counter()
                jax.block_until_ready(batched(lm))
                compiled[M] = time.perf_counter() - t0
            _progress(f"filter: M = {M}")
            t_vmap = median_s(lambda: jax.block_until_ready(batched(lm)), args.repeats)
            n_seq = min(M, args.seq_max)
            seq_logs = [jax.tree.map(lambda a, i=i: a[i], logs) for i in range(n_seq)]
            t_seq = median_s(lambda: [jax.block_until_ready(single(l_)) for l_ in seq_logs],
                            args.repeats) / n_seq * M
            n_tw = min(M, args.twin_max)
            np_logs = [jax.tree.map(np.asarray, l_) for l_ in seq_logs[:n_tw]] if n_tw <= n_seq else \
                [jax.tree.map(lambda a, i=i: np.asarray(a[i]), logs) for i in range(n_tw)]
            tw.run(np_logs[0], cfg, fp, np.asarray(anchors))  # one untimed warm-up call of the twin
            t_tw = median_s(lambda: [tw.run(l_, cfg, fp, np.asarray(anchors)) for l_ in np_logs],
                           max(1, min(args.repeats, 2))) / n_tw * M
            row = {"runs": M, "vmap_s": t_vmap, "vmap_runs_per_s": M / t_vmap, "vmap_compile_s": compiled[M],
                   "sequential_s": t_seq, "sequential_runs_per_s": M / t_seq, "sequential_timed": n_seq,
                   "twin_s": t_tw, "twin_runs_per_s": M / t_tw, "twin_timed": n_tw,
                   "speedup_vs_twin": t_tw / t_vmap, "speedup_vs_sequential": t_seq / t_vmap,
                   "sequential_vs_twin": t_tw / t_seq}
            rows.append(row)
            results.append({"case": f"filter {case}, M={M}, vmap", "params": {"runs": M},
                            "jaxslam_s": t_vmap, "reference": "NumPy twin (numpy_uwb.run) looped over the logs",
                            "reference_s": t_tw, "speedup": t_tw / t_vmap})
            results.append({"case": f"filter {case}, M={M}, sequential jitted", "params": {"runs": M},
                            "jaxslam_s": t_seq, "reference": "NumPy twin (numpy_uwb.run) looped over the logs",
                            "reference_s": t_tw, "speedup": t_tw / t_seq})
        out["filter"] = {"compile_single_s": compile_single, "twin_max_abs_diff_mean": agree, "rows": rows,
                         "note": "sequential and twin times are measured over *_timed logs and scaled to M"}
        by = {r["runs"]: r for r in rows}
        if 100 in by:
            for key, name in (("speedup_vs_twin", "vmap_vs_twin_at_100"),
                              ("speedup_vs_sequential", "vmap_vs_sequential_at_100")):
                v = by[100][key]
                out["targets"].append({"name": f"filter M = 100: {key}", "target": f">= {TARGETS[name]:g}x",
                                       "value": v, "met": bool(v >= TARGETS[name])})

    if "mc" in parts:
        single = jax.jit(one_run)
        t0 = time.perf_counter()
        jax.block_until_ready(single(keys[0]))
        compile_single = time.perf_counter() - t0
        batched = jax.jit(jax.vmap(one_run))
        rows = []
        compiled = {}  # chunk size -> compile time of its program (a later M with that chunk reuses it)
        for M in Ms:
            # Chunks of at most --mc-chunk runs, as jaxslam.sim.monte_carlo.run does (one
            # 1000-run call of this program hung inside XLA's CPU runtime on the 2-core machine).
            chunk = min(M, args.mc_chunk)
            n_chunks = -(-M // chunk)
            km = keys[:M]
            if n_chunks * chunk > M:  # pad the last chunk (its extra runs are timed too, as in monte_carlo)
                km = jnp.concatenate([km, jnp.repeat(keys[M - 1:M], n_chunks * chunk - M, axis=0)])
            parts_k = [km[c * chunk:(c + 1) * chunk] for c in range(n_chunks)]
            if chunk not in compiled:
                _progress(f"monte carlo: M = {M} (compiling {chunk} runs)")
                t0 = time.perf_counter()
                jax.block_until_ready(batched(parts_k[0]))
                compiled[chunk] = time.perf_counter() - t0
            comp = compiled[chunk]
            _progress(f"monte carlo: M = {M}")
            t_vmap = median_s(lambda: [jax.block_until_ready(batched(k_)) for k_ in parts_k], args.repeats)
            n_seq = min(M, args.seq_max)
            t_seq = median_s(lambda: [jax.block_until_ready(single(keys[i])) for i in range(n_seq)],
                            args.repeats) / n_seq * M
            rows.append({"runs": M, "chunk": chunk, "chunks": n_chunks, "vmap_s": t_vmap,
                         "vmap_runs_per_s": M / t_vmap, "vmap_compile_s": comp, "sequential_s": t_seq, "sequential_runs_per_s": M / t_seq, "sequential_timed": n_seq,
                         "speedup": t_seq / t_vmap})
            results.append({"case": f"monte carlo {case} (simulate+filter+metrics), M={M}", "params": {"runs": M},
                            "jaxslam_s": t_vmap, "reference": "M sequential calls of the jitted single run",
                            "reference_s": t_seq, "speedup": t_seq / t_vmap})
        out["monte_carlo"] = {"compile_single_s": compile_single, "rows": rows}

    load["after"] = list(os.getloadavg())
    out["load_average"] = load
    out["config"] = {"scenario": args.scenario, "mode": args.mode, "model": args.model, "filter": args.filter,
                     "steps": int(setup.ts.shape[0]), "startup_samples": int(setup.startup_pos.shape[0]),
                     "anchors": int(setup.anchors.shape[0]), "dtype": "float64",
                     "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS")}
    out["notes"] = ["medians after a warm-up call; speedup = reference_s / jaxslam_s",
                    "the NumPy twin processes only the valid measurements of mapped anchors; the JAX filter "
                    "has static shapes (all N ranges, masked)",
                    "timings depend on the machine's load: see load_average"]
    print("targets:")
    for t in out["targets"]:
        print(f"  [{'met' if t['met'] else 'MISSED'}] {t['name']}: {t['value']:.3g}x (target {t['target']})")
    return {"results": results, **out}


if __name__ == "__main__":
    sys.exit("run this benchmark through the CLI: python -m jaxslam bench uwb [options]")
