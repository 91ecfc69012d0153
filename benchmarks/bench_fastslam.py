"""FastSLAM benchmark of paper 001: time per step per particle, JAX vs NumPy, Monte Carlo.

Run with ``python -m jaxslam bench fastslam [--json PATH] [--quick] [options]``
(float64: the CLI enables x64).  The filter is
:func:`jaxslam.systems.fastslam_001.step` with the ``fastslam-helix`` scenario's
default configuration (dynamics proposal + bias/drift KF, world-frame LiDAR,
exact weights, systematic resampling at N_eff < N/2, stage 2 regeneration,
4 pole landmarks, capacity 4), fed with one simulated helix flight of the
scenario (rotor speeds, IMU at 100 Hz, LiDAR at 10 Hz).  Every time is a mean
per step over whole LiDAR periods (9 IMU-only steps + 1 IMU + LiDAR step), from
a filter state warmed up over ``--warmup`` steps (maps registered).

Parts (``--parts``):

``step``  for each N in ``--particles`` (default 100, 500, 2000, 10000):
   * jaxslam, in a loop: ``--steps`` steps inside ONE jitted call (a
     ``lax.fori_loop``, i.e. the XLA while loop that ``lax.scan`` also becomes,
     writing every step's ``StepOut`` into a stacked buffer as a scan would),
     divided by the number of steps; state and buffer donated;
   * jaxslam, per call: the same compiled program called once per step
     (``count = 1``), ``block_until_ready`` after every call — what a user
     driving the step from Python pays, dispatch included.  (One program per N
     serves both, with dynamic loop bounds: one compilation instead of two on a
     machine where each took 45-80 s; its per-call CPU time matched a plain
     ``jit(step)`` call.)
   * the vectorised NumPy twin (``numpy_fastslam.step``, hand Jacobians, its
     own NumPy random draws inside the timed loop) on the same inputs from the
     same warmed-up state;
   * the per-particle Python loop (``numpy_fastslam.step_loop``: the twin's
     kernels called once per particle) measured at ``--loop-particles`` and
     scaled linearly to N (its per-particle work is independent of N; the
     set-level weight normalisation and resampling are vectorised O(N) and
     negligible); the JSON says so.
``mc``   Monte Carlo: M runs of the whole filter (``fastslam_001.run``, N =
   ``--mc-particles`` over ``--mc-duration`` s windows of the flight, one
   window and one key per run) as ``jax.jit(jax.vmap(run))`` calls on chunks of
   ``--mc-chunk`` runs vs sequential calls of the jitted single run (the
   batch-of-1 program), timed over ``--mc-seq-max`` runs and scaled to M; and
   the batch-of-1 program called from ``monte_carlo.default_threads()`` host
   threads at once, as the runner's ``"loop"`` batching does for ``jaxslam run
   fastslam-helix`` (all M runs timed, once).
``profile`` (opt-in) the step's cost broken into pieces at
   ``--profile-particles`` (the IMU and LiDAR stages, proposal RK4 and random
   draws, bias KF update, step output, landmark updates, position
   regeneration; the twin's stages), in wall and CPU time.

Every repeat runs the methods one after the other (interleaved), so a change of
the machine's load hits all of them alike, and every time is also recorded in
process CPU time (all threads), which other processes' load does not inflate;
the targets use wall-clock medians.

Compilation: each program is compiled once (the first, warm-up call), two at
a time in threads to use both cores; compile times are recorded (wall time of
the first call while another compile may run beside it).

OpenBLAS threads: measured with OpenBLAS on 1 thread (the ``jaxslam`` command
sets ``OPENBLAS_NUM_THREADS=1`` unless the user set it; otherwise the benchmark
re-runs itself in a fresh process with the variable set, as it acts only
before NumPy loads OpenBLAS).  The twin's only LAPACK calls are one 6×6
Cholesky and inverse per step.

Medians of ``--repeats`` repeats after warm-up, ``block_until_ready`` on every
JAX result.  Every target is recorded in ``targets`` (met or missed);
``load_average`` records how busy the machine was.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
from timing import int_list, lidar_frames, prng_key

DESCRIPTION = ("Paper 001 FastSLAM: time per step per particle (N = 100-10000) of the jitted "
               "step (in a loop and per call) vs a vectorised NumPy twin and a per-particle "
               "Python loop; vmap Monte Carlo of whole runs")

HERE = pathlib.Path(__file__).resolve().parent
LIDAR_EVERY = 10
DT = 0.01  # IMU step of the fastslam-helix scenario [s] (_setup checks it)

TARGETS = {"twin_speedup_at_2000": 3.0, "loop_speedup_at_2000": 50.0, "flat_ratio_max": 1.5}
"""Issue 19 asks for 3x the vectorised twin at N = 2000 (the first target, 2x, was missed at 0.59x)."""

_QUICK = {"particles": "500,2000", "steps": 50, "call_steps": 10, "twin_steps": 10,
          "repeats": 3, "mc_runs": "1,8", "mc_duration": 0.5}


def add_arguments(parser):
    """Benchmark options (defaults: ~4.5 min on a busy 2-core CPU, most of it compiling six
    programs; --quick ~2.5 min)."""
    parser.add_argument("--parts", default="step,mc",
                        help="comma list of step, mc, profile (default step,mc; profile is a "
                             "breakdown of the step's cost)")
    parser.add_argument("--quick", action="store_true",
                        help="smaller run: N = 500, 2000; fewer steps and repeats; M = 1, 8 "
                             "over 0.5 s windows (explicit options still win)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the flight and the filters")
    parser.add_argument("--particles", default=None,
                        help="particle counts N of the step part (default 100,500,2000,10000)")
    parser.add_argument("--warmup", type=int, default=20,
                        help="filter steps before timing (multiple of 10; default 20)")
    parser.add_argument("--steps", type=int, default=None,
                        help="steps inside one jitted loop (multiple of 10; default 50)")
    parser.add_argument("--call-steps", type=int, default=None,
                        help="steps timed one jitted call each (multiple of 10; default 20)")
    parser.add_argument("--twin-steps", type=int, default=None,
                        help="steps of the NumPy twin per repeat (multiple of 10; default 20)")
    parser.add_argument("--loop-particles", type=int, default=20,
                        help="N at which the per-particle Python loop is measured (default 20)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed repeats (median; default 3); the mc part uses min(REPEATS, 2), "
                             "the profile part max(5, 3 * REPEATS)")
    parser.add_argument("--mc-runs", default=None, help="Monte Carlo batch sizes M (default 1,8,32)")
    parser.add_argument("--mc-particles", type=int, default=100, help="N of each MC run (default 100)")
    parser.add_argument("--mc-duration", type=float, default=None,
                        help="flight window of each MC run [s] (default 1)")
    parser.add_argument("--mc-chunk", type=int, default=8,
                        help="runs per vmapped call (default 8: M = 32 is four calls)")
    parser.add_argument("--mc-seq-max", type=int, default=8,
                        help="sequential single runs actually timed per M (scaled to M; default 8)")
    parser.add_argument("--profile-particles", type=int, default=2000,
                        help="N of the profile part (default 2000)")


def _fill_defaults(args):
    """A copy of ``args`` with the defaults (or ``--quick``'s) of the options left ``None``,
    the step counts checked; the caller's namespace is not changed."""
    args = argparse.Namespace(**vars(args))
    base = {"particles": "100,500,2000,10000", "steps": 50, "call_steps": 20, "twin_steps": 20,
            "repeats": 3, "mc_runs": "1,8,32", "mc_duration": 1.0}
    for k, v in base.items():
        if getattr(args, k, None) is None:
            setattr(args, k, _QUICK[k] if args.quick else v)
    for k in ("warmup", "steps", "call_steps", "twin_steps"):
        n = int(getattr(args, k))
        if n <= 0 or n % LIDAR_EVERY:
            from jaxslam.errors import InputError

            raise InputError(f"--{k.replace('_', '-')}: must be a positive multiple of "
                             f"{LIDAR_EVERY}, got {n}")
    return args


def _progress(msg):
    print(f"[bench fastslam] {msg}", file=sys.stderr, flush=True)


def _mc_runs(args):
    """The Monte Carlo batch sizes M: ``--mc-runs`` with M = 1 (the sequential single run, the
    reference of every M) put first when it is not there; ``args`` is left as it is."""
    Ms = int_list(args.mc_runs, "--mc-runs")
    return Ms if 1 in Ms else [1] + Ms


def _row(case, params, jax_s, ref_name, ref_s, **extra):
    r = {"case": case, "params": params, "jaxslam_s": jax_s, "reference": ref_name,
         "reference_s": ref_s, "speedup": (ref_s / jax_s) if (jax_s and ref_s) else None}
    r.update(extra)
    return r


# ---------------------------------------------------------------------------
# Flight and filter
# ---------------------------------------------------------------------------

def _setup(args, n_frames):
    """Scenario defaults (cfg, prm), one simulated flight (NumPy arrays), landmark ids."""
    import jax
    import jax.numpy as jnp

    from jaxslam.sim.scenarios import fastslam as sc

    opts = {o.name: o.default for o in sc.OPTIONS}
    cfg, prm = sc.make_filter(opts, jnp.float64)
    want = dict(model="dynamics", lidar="world", weights="exact", stage2="paper",
                accel_mode="specific_force", resampling="systematic", regen_noise=True,
                lidar_every=LIDAR_EVERY, dt=DT)
    diff = {k: getattr(cfg, k) for k, v in want.items() if getattr(cfg, k) != v}
    if diff:  # the twin reproduces exactly this configuration
        raise RuntimeError(f"fastslam-helix defaults changed ({diff}); update numpy_fastslam.py")
    setup = sc.truth_setup(float(opts["bias"]), jnp.float64)
    fl = jax.jit(lambda k: sc.fly(setup, k, n_frames, LIDAR_EVERY, cfg.lidar, cfg.accel_mode))(
        prng_key(args.seed))
    fl = jax.tree_util.tree_map(np.asarray, fl)
    ids = np.arange(np.asarray(setup.landmarks).shape[0], dtype=np.int32)
    return cfg, prm, fl, ids


def _per_step_inputs(fl, ids):
    """Flight → per-step arrays: rotor (T, 4), imu (T, 6), z (T, L, 3), mask (T, L) with the
    frame on the last sample of each LiDAR period (as ``fastslam_001.run``)."""
    T = fl.imu.shape[0]
    L = ids.shape[0]
    z = np.zeros((T, L, 3))
    mask = np.zeros((T, L), bool)
    z[LIDAR_EVERY - 1::LIDAR_EVERY] = fl.z
    mask[LIDAR_EVERY - 1::LIDAR_EVERY] = fl.mask
    return fl.rotor, fl.imu, z, mask


def _advance_fn(cfg, prm):
    """jit(advance(state, outbuf, inputs, ids, keys, start, count)): steps start..start+count−1
    of the stacked inputs in one ``lax.fori_loop``; StepOut k written into outbuf[k]."""
    import jax

    from jaxslam.systems import fastslam_001 as fs1

    def advance(state, outbuf, inputs, ids, keys, start, count):
        rotor, imu, z, mask = inputs

        def body(i, carry):
            s, ob = carry
            s, out = fs1.step(s, fs1.Event(rotor[i], imu[i], z[i], ids, mask[i]), cfg, prm,
                              key=keys[i])
            ob = jax.tree_util.tree_map(lambda b, o: b.at[i].set(o), ob, out)
            return s, ob

        return jax.lax.fori_loop(start, start + count, body, (state, outbuf))

    return jax.jit(advance, donate_argnums=(0, 1))


def _log0(x0):
    """A ``fastslam_001.Log`` for ``init`` (which reads only ``x0``)."""
    from jaxslam.systems import fastslam_001 as fs1

    return fs1.Log(x0=x0, rotor_w=None, imu=None, z=None, ids=None, mask=None)


def _outbuf(T, dtype):
    import jax.numpy as jnp

    from jaxslam.systems import fastslam_001 as fs1

    z = lambda *s: jnp.zeros((T,) + s, dtype)  # noqa: E731
    return fs1.StepOut(z(12), z(12), z(12), z(12), z(6), z())


def _copy(tree):
    import jax
    import jax.numpy as jnp

    return jax.block_until_ready(jax.tree_util.tree_map(jnp.copy, tree))


# ---------------------------------------------------------------------------
# Part: step
# ---------------------------------------------------------------------------

def _compile_all(jobs):
    """Run the warm-up (compiling) jobs two at a time; returns {name: (result, wall_s)}."""
    def timed(item):
        name, fn = item
        t0 = time.perf_counter()
        res = fn()
        return name, res, time.perf_counter() - t0

    out = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as ex:
        for name, res, dt in ex.map(timed, jobs):
            out[name] = (res, dt)
            _progress(f"compiled + warmed up {name} in {dt:.1f} s")
    return out


def _step_jobs(args, cfg, prm, inputs_dev, ids_dev, keys_dev, x0, T):
    import jax
    import jax.numpy as jnp

    from jaxslam.systems import fastslam_001 as fs1

    jobs = []
    for N in int_list(args.particles, "--particles"):
        def job(N=N):
            adv = _advance_fn(cfg, prm)
            st = fs1.init(_log0(jnp.asarray(x0)), cfg._replace(n_particles=N), prm,
                          key=prng_key(args.seed, 1))
            ob = _outbuf(T, jnp.float64)
            st, ob = adv(st, ob, inputs_dev, ids_dev, keys_dev, jnp.int32(0),
                         jnp.int32(args.warmup))
            return adv, jax.block_until_ready((st, ob))

        jobs.append((f"step N={N}", job))
    return jobs


class _Clock:
    """Wall and process-CPU time of a block (CPU time counts every thread of the process,
    so it measures the work done whatever the machine's load)."""

    def __enter__(self):
        self.w, self.c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.w
        self.cpu = time.process_time() - self.c


def _jax_loop_once(adv, warm, inputs, ids, keys, start, count):
    import jax
    import jax.numpy as jnp

    s0, c0 = jnp.int32(start), jnp.int32(count)
    st, ob = _copy(warm)
    with _Clock() as c:
        jax.block_until_ready(adv(st, ob, inputs, ids, keys, s0, c0))
    return c.wall / count, c.cpu / count


def _jax_calls_once(adv, warm, inputs, ids, keys, start, count):
    import jax
    import jax.numpy as jnp

    idx = [jnp.int32(start + i) for i in range(count)]
    one = jnp.int32(1)
    st, ob = _copy(warm)
    with _Clock() as c:
        for i in idx:
            st, ob = adv(st, ob, inputs, ids, keys, i, one)
            jax.block_until_ready((st, ob))
    return c.wall / count, c.cpu / count


def _twin_once(tw, ts0, P, inputs, ids, start, count, seed, loop=False):
    rotor, imu, z, mask = inputs
    n = ts0.pose.shape[0]
    rng = np.random.default_rng(seed)
    ts, outs = ts0, []
    fn = tw.step_loop if loop else tw.step
    with _Clock() as c:
        for i in range(start, start + count):
            ts, o = fn(ts, rotor[i], imu[i], z[i], ids, mask[i], tw.draw(rng, n), P)
            outs.append(o)
    return c.wall / count, c.cpu / count


def _subset(ts, n):
    """The first n particles of a twin state, weights renormalised."""
    lw = ts.log_w[:n]
    lw = lw - np.log(np.sum(np.exp(lw - lw.max()))) - lw.max()
    return ts._replace(pose=ts.pose[:n], aux=ts.aux[:n], lm_mean=ts.lm_mean[:n],
                       lm_cov=ts.lm_cov[:n], active=ts.active[:n], ids=ts.ids[:n], log_w=lw)


def _med(pairs):
    """(median wall, median cpu) of a list of (wall, cpu)."""
    a = np.asarray(pairs, float)
    return float(np.median(a[:, 0])), float(np.median(a[:, 1]))


def run_step(args, tw, cfg, prm, compiled, inputs_np, inputs_dev, ids_np, ids_dev, keys_dev,
             results, out):
    P = tw.params_from(prm, cfg.dt, prm.resample_threshold)
    W = args.warmup
    rows = []
    loop_pp = None
    for N in int_list(args.particles, "--particles"):
        adv, warm = compiled[f"step N={N}"][0]
        comp_s = compiled[f"step N={N}"][1]
        ts0 = tw.state_from(warm[0])
        nl = min(args.loop_particles, N)
        m = {"loop": [], "call": [], "twin": [], "py": []}
        _progress(f"step N={N}: {args.repeats} interleaved repeats of jaxslam (loop, calls), "
                  f"twin" + (f", per-particle loop at N={nl}" if loop_pp is None else ""))
        # Repeats interleaved, so that the machine's changing load hits every method alike.
        for r in range(args.repeats):
            m["loop"].append(_jax_loop_once(adv, warm, inputs_dev, ids_dev, keys_dev, W, args.steps))
            m["call"].append(_jax_calls_once(adv, warm, inputs_dev, ids_dev, keys_dev, W,
                                             args.call_steps))
            m["twin"].append(_twin_once(tw, ts0, P, inputs_np, ids_np, W, args.twin_steps,
                                        args.seed + r))
            if loop_pp is None:
                m["py"].append(_twin_once(tw, _subset(ts0, nl), P, inputs_np, ids_np, W,
                                          LIDAR_EVERY, args.seed + r, loop=True))
        (t_loop, c_loop), (t_call, c_call), (t_twin, c_twin) = (_med(m[k]) for k in
                                                                ("loop", "call", "twin"))
        if loop_pp is None:
            w_py, c_py = _med(m["py"])
            loop_pp = {"measured_at_particles": nl, "step_s": w_py, "step_cpu_s": c_py,
                       "per_particle_s": w_py / nl, "per_particle_cpu_s": c_py / nl}
        t_pl = loop_pp["per_particle_s"] * N
        c_pl = loop_pp["per_particle_cpu_s"] * N
        ns = lambda t: t / N * 1e9  # noqa: E731
        row = {"particles": N, "jax_loop_step_s": t_loop, "jax_call_step_s": t_call,
               "twin_step_s": t_twin, "python_loop_step_s": t_pl,
               "jax_loop_per_particle_ns": ns(t_loop), "jax_call_per_particle_ns": ns(t_call),
               "twin_per_particle_ns": ns(t_twin),
               "python_loop_per_particle_ns": loop_pp["per_particle_s"] * 1e9,
               "speedup_vs_twin": t_twin / t_loop, "speedup_vs_python_loop": t_pl / t_loop,
               "call_speedup_vs_twin": t_twin / t_call,
               "cpu": {"jax_loop_per_particle_ns": ns(c_loop),
                       "jax_call_per_particle_ns": ns(c_call),
                       "twin_per_particle_ns": ns(c_twin),
                       "python_loop_per_particle_ns": loop_pp["per_particle_cpu_s"] * 1e9,
                       "speedup_vs_twin": c_twin / c_loop, "speedup_vs_python_loop": c_pl / c_loop},
               "compile_s": comp_s}
        rows.append(row)
        prm_ = {"particles": N, "steps": args.steps}
        results.append(_row(f"step N={N} (jitted loop)", prm_, t_loop, "NumPy twin (vectorised)",
                            t_twin, per_particle_ns=ns(t_loop)))
        results.append(_row(f"step N={N} (one call per step)", {**prm_, "steps": args.call_steps},
                            t_call, "NumPy twin (vectorised)", t_twin, per_particle_ns=ns(t_call)))
        results.append(_row(f"step N={N} (jitted loop) vs per-particle loop", prm_, t_loop,
                            "per-particle Python loop (scaled)", t_pl,
                            scaled_from_particles=loop_pp["measured_at_particles"]))
        _progress(f"step N={N}: per particle jaxslam loop {ns(t_loop):.0f} ns, call "
                  f"{ns(t_call):.0f} ns, twin {ns(t_twin):.0f} ns, python loop "
                  f"{loop_pp['per_particle_s'] * 1e9:.0f} ns per step (wall)")
    out["step"] = {
        "rows": rows, "per_particle_loop": {
            **loop_pp, "note": ("numpy_fastslam.step_loop (the twin's kernels called once per "
                                "particle) timed at 'measured_at_particles' over one LiDAR "
                                "period and scaled linearly to N (python_loop_step_s = "
                                "per_particle_s × N)")},
        "warmup_steps": W, "loop_steps": args.steps, "call_steps": args.call_steps,
        "twin_steps": args.twin_steps,
        "config": {k: v for k, v in cfg._asdict().items()},
        "note": ("wall-clock medians decide the targets; 'cpu' repeats them in process CPU time "
                 "(all threads), which the load of other processes does not inflate"),
    }
    by_n = {r["particles"]: r for r in rows}
    if 2000 in by_n:
        r = by_n[2000]
        out["targets"].append({"name": "jaxslam (jitted loop) vs vectorised NumPy twin at N = 2000",
                               "target": f">= {TARGETS['twin_speedup_at_2000']:g}x",
                               "value": r["speedup_vs_twin"],
                               "value_cpu_time": r["cpu"]["speedup_vs_twin"],
                               "met": bool(r["speedup_vs_twin"] >= TARGETS["twin_speedup_at_2000"])})
        out["targets"].append({"name": "jaxslam (jitted loop) vs per-particle Python loop at N = 2000",
                               "target": f">= {TARGETS['loop_speedup_at_2000']:g}x",
                               "value": r["speedup_vs_python_loop"],
                               "value_cpu_time": r["cpu"]["speedup_vs_python_loop"],
                               "met": bool(r["speedup_vs_python_loop"]
                                           >= TARGETS["loop_speedup_at_2000"])})
    if 500 in by_n and 10000 in by_n:
        a, b = by_n[500], by_n[10000]
        ratio = b["jax_loop_per_particle_ns"] / a["jax_loop_per_particle_ns"]
        out["targets"].append({"name": "time per particle N = 10000 / N = 500 (jitted loop)",
                               "target": f"<= {TARGETS['flat_ratio_max']:g} (roughly flat)",
                               "value": ratio,
                               "value_cpu_time": (b["cpu"]["jax_loop_per_particle_ns"]
                                                  / a["cpu"]["jax_loop_per_particle_ns"]),
                               "met": bool(ratio <= TARGETS["flat_ratio_max"])})


# ---------------------------------------------------------------------------
# Part: Monte Carlo
# ---------------------------------------------------------------------------

def _mc_windows(fl, M, F):
    """M overlapping windows of F frames (run m starts at frame m) as batched run inputs."""
    E = LIDAR_EVERY
    sl = [slice(m * E, (m + F) * E) for m in range(M)]
    return (np.stack([fl.truth[m * E] for m in range(M)]),
            np.stack([fl.rotor[s] for s in sl]), np.stack([fl.imu[s] for s in sl]),
            np.stack([fl.z[m:m + F] for m in range(M)]),
            np.stack([fl.mask[m:m + F] for m in range(M)]))


def _mc_jobs(args, cfg, prm, fl, ids):
    """Programs: the single run (vmap over 1) and the chunk of ``--mc-chunk`` runs."""
    import jax
    import jax.numpy as jnp

    from jaxslam.systems import fastslam_001 as fs1

    N = int(args.mc_particles)
    F = lidar_frames(args.mc_duration, "--mc-duration", cfg.dt, LIDAR_EVERY)
    ids_d = jnp.asarray(ids)
    Ms = _mc_runs(args)
    M_max = max(Ms)

    cfg_n = cfg._replace(n_particles=N)

    def one(key, x0, rw, imu, z, mask):
        log = fs1.Log(x0=x0, rotor_w=rw, imu=imu, z=z, ids=ids_d, mask=mask)
        return fs1.run(log, cfg_n, prm, key=key)

    win = tuple(jnp.asarray(a) for a in _mc_windows(fl, M_max, F))
    keys = jax.random.split(prng_key(args.seed, 7), M_max)
    sizes = sorted({1} | {min(M, int(args.mc_chunk)) for M in Ms})
    jobs = []
    for B in sizes:
        def job(B=B):
            f = jax.jit(jax.vmap(one))
            jax.block_until_ready(f(keys[:B], *(a[:B] for a in win)))
            return f

        jobs.append((f"mc batch={B}", job))
    return jobs, (keys, win), N, F


def run_mc(args, compiled, data, N, F, results, out):
    import jax

    from jaxslam.sim import monte_carlo

    keys, win = data
    single = compiled["mc batch=1"][0]
    rows = []
    for M in _mc_runs(args):
        B = min(M, int(args.mc_chunk))
        f, comp = compiled[f"mc batch={B}"]
        n_chunks = -(-M // B)
        _progress(f"monte carlo M={M} ({n_chunks} vmapped call(s) of {B} runs)")

        def batched():
            for c in range(n_chunks):
                lo, hi = c * B, min((c + 1) * B, M)
                if hi - lo < B:  # pad a last partial chunk by repeating its runs
                    sl = np.r_[np.arange(lo, hi), np.full(B - (hi - lo), hi - 1)]
                    jax.block_until_ready(f(keys[sl], *(a[sl] for a in win)))
                else:
                    jax.block_until_ready(f(keys[lo:hi], *(a[lo:hi] for a in win)))

        n_seq = min(M, int(args.mc_seq_max))
        tv, tsq = [], []
        for _ in range(max(1, min(args.repeats, 2))):
            with _Clock() as c:
                batched()
            tv.append((c.wall, c.cpu))
            with _Clock() as c:
                for m in range(n_seq):
                    jax.block_until_ready(single(keys[m:m + 1], *(a[m:m + 1] for a in win)))
            tsq.append((c.wall / n_seq * M, c.cpu / n_seq * M))
        (t_vmap, c_vmap), (t_seq, c_seq) = _med(tv), _med(tsq)
        # what `jaxslam run fastslam-helix` does on a CPU: the single run called from the
        # runner's threads at once (monte_carlo's "loop" batching), all M runs timed
        threads = monte_carlo.default_threads()
        with _Clock() as c:
            monte_carlo._loop_runs(lambda m: single(keys[m:m + 1], *(a[m:m + 1] for a in win)),
                                   np.arange(M), threads, False, None)
        t_thr = c.wall
        rows.append({"runs": M, "chunk": B, "vmap_s": t_vmap, "vmap_runs_per_s": M / t_vmap,
                     "vmap_compile_s": comp, "sequential_s": t_seq,
                     "sequential_runs_per_s": M / t_seq, "sequential_timed_calls": n_seq,
                     "speedup": t_seq / t_vmap, "speedup_cpu_time": c_seq / c_vmap,
                     "vmap_per_particle_step_ns": t_vmap / (M * N * F * LIDAR_EVERY) * 1e9,
                     "loop_threads": threads, "loop_threads_s": t_thr, "loop_threads_speedup": t_seq / t_thr})
        results.append(_row(f"monte carlo M={M}", {"runs": M, "chunk": B, "particles": N,
                                                   "duration_s": F * LIDAR_EVERY * 0.01},
                            t_vmap, "M sequential calls of the jitted single run", t_seq,
                            runs_per_s=M / t_vmap))
        results.append(_row(f"monte carlo M={M}, runner's loop on {threads} threads",
                            {"runs": M, "threads": threads, "particles": N,
                             "duration_s": F * LIDAR_EVERY * 0.01},
                            t_thr, "M sequential calls of the jitted single run", t_seq,
                            runs_per_s=M / t_thr))
    out["monte_carlo"] = {
        "particles": N, "frames": F, "steps_per_run": F * LIDAR_EVERY,
        "compile_single_s": compiled["mc batch=1"][1], "rows": rows,
        "note": ("each run: fastslam_001.run (the whole filter, one nested lax.scan) over a "
                 f"{F * LIDAR_EVERY * 0.01:g} s window of the flight (run m starts at frame m), "
                 "its own key; vmap = jax.jit(jax.vmap(run)) called on chunks of 'chunk' runs; "
                 "sequential = calls of the batch-of-1 program (a jitted single run), each "
                 "blocked, timed over 'sequential_timed_calls' runs and scaled to M (the runs "
                 "are independent)"),
    }


# ---------------------------------------------------------------------------
# Part: profile (opt-in)
# ---------------------------------------------------------------------------

def _profile_jobs(args, cfg, prm, compiled_state_fn, inputs_np):
    """(name, make) pairs: make() compiles one piece and returns (fn, args)."""
    import jax
    import jax.numpy as jnp

    from jaxslam.filters import ekf
    from jaxslam.filters import fastslam as fs
    from jaxslam.linalg import cholesky_small
    from jaxslam.systems import fastslam_001 as fs1

    rotor, imu, z, mask = inputs_np
    k_lidar = LIDAR_EVERY - 1 + args.warmup  # a LiDAR step after the warm-up
    k_imu = args.warmup  # an IMU-only step
    w, u = jnp.asarray(rotor[k_imu]), jnp.asarray(imu[k_imu])
    zf, mf = jnp.asarray(z[k_lidar]), jnp.asarray(mask[k_lidar])
    ids = jnp.arange(zf.shape[0], dtype=jnp.int32)
    N = int(args.profile_particles)
    R = jnp.diag(prm.lidar_var)
    model = fs1.landmark_model(cfg.lidar)

    def bias_update(st):
        H = jnp.asarray(fs1.H_B, jnp.float64)
        nu = u - st.particles.aux @ H.T
        out = ekf.linear_update_shared(st.particles.aux, st.bias_cov, nu, H,
                                       jnp.diag(prm.imu_var), jnp.ones((6,), bool))
        return out[0], out[4]

    def regen_pos(st, k):
        p = st.particles
        m, P, ok = jax.vmap(lambda x, mu, c, a: fs1.position_posterior(
            x, mu, c, a, zf, ids, mf, R, cfg.lidar, True))(p.pose, p.lm_mean, p.lm_cov, p.active)
        eps = jax.random.normal(k, m.shape, jnp.float64)
        return jnp.where(ok[:, None], m + jnp.einsum("nij,nj->ni", cholesky_small(P), eps), 0.0)

    pieces = [
        ("imu_stage", lambda s, k: fs1.imu_stage(s, w, u, k, cfg, prm)),
        ("lidar_stage", lambda s, k: fs1.lidar_stage(s, zf, ids, mf, k, cfg, prm)[0]),
        ("  proposal: RK4 of eq. 1-4 only", lambda s, k: jax.vmap(
            lambda x: fs1.rk4_step(fs1.rotor.f, x, w, cfg.dt, prm.quad))(s.particles.pose)),
        ("  proposal: one normal(N*12) draw", lambda s, k: jax.random.normal(
            k, (N * 12,), jnp.float64)),
        ("  IMU prediction h^d(x) (eq. 12)", lambda s, k: jax.vmap(
            lambda x: fs1.h_imu(x, w, prm.quad, cfg.accel_mode))(s.particles.pose)),
        ("  bias KF: ekf.linear_update_shared", lambda s, k: bias_update(s)),
        ("  resampling (systematic, forced)", lambda s, k: fs.maybe_resample(
            s.particles, k, None, cfg.resampling).pose),
        ("  step output: _step_out (estimate)", lambda s, k: fs1._step_out(s, 1.0)),
        ("  landmarks: observe_update", lambda s, k: fs.observe_update(
            s.particles, model, zf, ids, mf, R, None, slot_by_id=True)[0].log_w),
        ("  landmarks: position_posterior + draw", regen_pos),
    ]
    jobs = []
    for name, fn in pieces:
        def job(fn=fn):
            st = compiled_state_fn()
            f = jax.jit(fn)
            key = prng_key(args.seed, 3)
            jax.block_until_ready(f(st, key))
            return f, (st, key)

        jobs.append((f"profile {name}", job))
    return jobs


def run_profile(args, tw, cfg, prm, compiled, twin_state, inputs_np, out):
    import jax

    N = int(args.profile_particles)
    reps = max(5, 3 * args.repeats)
    rows = []
    for name in [k for k in compiled if k.startswith("profile ")]:
        f, fa = compiled[name][0]
        ts = []
        for _ in range(reps):
            with _Clock() as c:
                jax.block_until_ready(f(*fa))
            ts.append((c.wall, c.cpu))
        wall, cpu = _med(ts)
        rows.append({"piece": name[len("profile "):], "wall_s": wall, "cpu_s": cpu,
                     "cpu_per_particle_ns": cpu / N * 1e9, "wall_per_particle_ns": wall / N * 1e9,
                     "compile_s": compiled[name][1]})
    P = tw.params_from(prm, cfg.dt, prm.resample_threshold)
    rotor, imu, z, mask = inputs_np
    rng = np.random.default_rng(args.seed)
    k_imu, k_lid = args.warmup, args.warmup + LIDAR_EVERY - 1
    for name, fn in [("twin imu_stage", lambda: tw.imu_stage(twin_state, rotor[k_imu], imu[k_imu],
                                                             tw.draw(rng, N), P)),
                     ("twin lidar_stage", lambda: tw.lidar_stage(twin_state, z[k_lid], np.arange(
                         z.shape[1]), mask[k_lid], tw.draw(rng, N), P))]:
        ts = []
        for _ in range(reps):
            with _Clock() as c:
                fn()
            ts.append((c.wall, c.cpu))
        wall, cpu = _med(ts)
        rows.append({"piece": name, "wall_s": wall, "cpu_s": cpu,
                     "cpu_per_particle_ns": cpu / N * 1e9, "wall_per_particle_ns": wall / N * 1e9})
    out["profile"] = {"particles": N, "repeats": reps, "rows": rows,
                      "note": ("each piece jitted alone on the warmed-up state, median of "
                               "'repeats' calls; indented pieces are parts of the stages above; "
                               "per-particle times are per call (one IMU sample or one "
                               "LiDAR frame of 4 landmarks)")}
    for r in rows:
        _progress(f"profile N={N}: {r['piece']:45s} {r['cpu_per_particle_ns']:8.0f} ns/particle "
                  f"CPU, {r['wall_per_particle_ns']:8.0f} ns wall")


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------

_OPTION_DESTS = ("parts", "quick", "seed", "particles", "warmup", "steps", "call_steps",
                 "twin_steps", "loop_particles", "repeats", "mc_runs", "mc_particles",
                 "mc_duration", "mc_chunk", "mc_seq_max", "profile_particles")


def _print_targets(out):
    print("targets:")
    for t in out["targets"]:
        print(f"  [{'met' if t['met'] else 'MISSED'}] {t['name']}: {t['value']:.3g} "
              f"(target {t['target']})")


def _filter_state(ts, imu_prev):
    """A ``fastslam_001.State`` holding a twin state (counters 0)."""
    import jax.numpy as jnp

    from jaxslam.filters import fastslam as fs
    from jaxslam.systems import fastslam_001 as fs1

    i32 = lambda v: jnp.asarray(v, jnp.int32)  # noqa: E731
    p = fs.Particles(jnp.asarray(ts.pose), jnp.asarray(ts.aux), jnp.asarray(ts.lm_mean),
                     jnp.asarray(ts.lm_cov), jnp.asarray(ts.active), i32(ts.ids),
                     jnp.asarray(ts.log_w), i32(0), i32(0), i32(0), i32(ts.resamples))
    return fs1.State(p, jnp.asarray(ts.bias_cov), i32(ts.k), jnp.asarray(ts.neff_min),
                     jnp.asarray(imu_prev))


def _run_here(args, parts):
    import jax
    import jax.numpy as jnp

    import numpy_fastslam as tw
    from jaxslam.systems import fastslam_001 as fs1

    t_start = time.perf_counter()
    results, out = [], {"targets": []}
    load = {"before": list(os.getloadavg())}
    F_mc = lidar_frames(args.mc_duration, "--mc-duration", DT, LIDAR_EVERY) if "mc" in parts else 0
    M_max = max(_mc_runs(args)) if "mc" in parts else 1
    need_steps = args.warmup + max(args.steps, args.call_steps, args.twin_steps, LIDAR_EVERY)
    n_frames = max(need_steps // LIDAR_EVERY, (M_max - 1) + F_mc if "mc" in parts else 0) + 1
    _progress(f"simulating a {n_frames * LIDAR_EVERY * 0.01:g} s helix flight (scenario "
              "fastslam-helix)")
    t0 = time.perf_counter()
    cfg, prm, fl, ids = _setup(args, n_frames)
    t_flight = time.perf_counter() - t0
    inputs_np = _per_step_inputs(fl, ids)
    T = inputs_np[0].shape[0]
    inputs_dev = tuple(jnp.asarray(a) for a in inputs_np)
    ids_dev = jnp.asarray(ids)
    keys_dev = jax.random.split(prng_key(args.seed, 2), T)

    jobs = []
    if "step" in parts:
        jobs += _step_jobs(args, cfg, prm, inputs_dev, ids_dev, keys_dev, fl.truth[0], T)
    if "mc" in parts:
        mc_jobs, mc_data, N_mc, F = _mc_jobs(args, cfg, prm, fl, ids)
        jobs += mc_jobs
    if "profile" in parts:
        # The profile's warmed-up state comes from the twin (no compilation needed).
        Np = int(args.profile_particles)
        P = tw.params_from(prm, cfg.dt, prm.resample_threshold)
        ts = tw.state_from(fs1.init(_log0(jnp.asarray(fl.truth[0])), cfg._replace(n_particles=Np),
                                    prm, key=prng_key(args.seed, 1)))
        rng = np.random.default_rng(args.seed)
        for i in range(args.warmup):
            ts, _ = tw.step(ts, inputs_np[0][i], inputs_np[1][i], inputs_np[2][i], ids,
                            inputs_np[3][i], tw.draw(rng, Np), P)
        prof_np = ts
        prof_state = _filter_state(ts, inputs_np[1][args.warmup - 1])
        jobs += _profile_jobs(args, cfg, prm, lambda: prof_state, inputs_np)
    _progress(f"compiling {len(jobs)} programs (two at a time)")
    t0 = time.perf_counter()
    compiled = _compile_all(jobs)
    t_compile = time.perf_counter() - t0
    if "step" in parts:
        run_step(args, tw, cfg, prm, compiled, inputs_np, inputs_dev, ids, ids_dev, keys_dev,
                 results, out)
    if "mc" in parts:
        run_mc(args, compiled, mc_data, N_mc, F, results, out)
    if "profile" in parts:
        run_profile(args, tw, cfg, prm, compiled, prof_np, inputs_np, out)
    load["after"] = list(os.getloadavg())
    out["load_average"] = load
    out["timing"] = {"flight_s": t_flight, "compile_all_s": t_compile,
                     "compile_s": {k: v[1] for k, v in compiled.items()},
                     "total_s": time.perf_counter() - t_start}
    out["xla_flags"] = os.environ.get("XLA_FLAGS")
    return results, out


def _spawn(args, parts):
    """Run in a fresh process with OPENBLAS_NUM_THREADS=1 (acts only before NumPy loads it)."""
    import jaxslam

    root = str(pathlib.Path(jaxslam.__file__).resolve().parents[1])
    with tempfile.TemporaryDirectory() as td:
        a_path, o_path = os.path.join(td, "args.json"), os.path.join(td, "out.json")
        with open(a_path, "w") as fh:
            json.dump({k: getattr(args, k) for k in _OPTION_DESTS}, fh)
        env = dict(os.environ)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = "1"
        env["PYTHONPATH"] = os.pathsep.join([root, str(HERE), str(HERE.parent / "tests" / "oracles")] + ([env["PYTHONPATH"]]
                                                                   if env.get("PYTHONPATH") else []))
        _progress("OPENBLAS_NUM_THREADS is not 1 here: running in a fresh process with it set")
        proc = subprocess.run([sys.executable, str(HERE / "bench_fastslam.py"), "--child", a_path, o_path],
                              env=env, stdout=sys.stderr)
        res = None
        if os.path.exists(o_path):
            with open(o_path) as fh:
                res = json.load(fh)
        if res is not None and "input_error" in res:  # the child's bad input: exit 2, its message
            from jaxslam.errors import InputError

            raise InputError(res["input_error"])
        if proc.returncode != 0 or res is None:
            raise subprocess.CalledProcessError(proc.returncode, proc.args)
    return res["results"], res["out"]


def run(args):
    """Run the selected parts; returns the bench JSON dict (see module docstring)."""
    import jax

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)  # standalone use; the CLI has set it already
    from jaxslam.errors import InputError

    args = _fill_defaults(args)
    parts = {p.strip() for p in str(args.parts).split(",") if p.strip()}
    if not parts:
        raise InputError(f"--parts: no part given, got {args.parts!r}; choose from step, mc, profile")
    unknown = parts - {"step", "mc", "profile"}
    if unknown:
        raise InputError(f"--parts: unknown part(s) {sorted(unknown)}; choose from step, mc, "
                         "profile")
    # The lists are read deep inside the run (after the flight is simulated, or in the child
    # process): check them here, before any work.
    if "step" in parts:
        int_list(args.particles, "--particles")
    if "mc" in parts:
        int_list(args.mc_runs, "--mc-runs")
        # the window holds whole LiDAR frames: a value under one frame (0, negative) was silently
        # run as one frame while the JSON's options recorded the value given
        lidar_frames(args.mc_duration, "--mc-duration", DT, LIDAR_EVERY)
    if os.environ.get("OPENBLAS_NUM_THREADS") == "1":
        results, out = _run_here(args, parts)
        out["openblas_pinning"] = "OPENBLAS_NUM_THREADS=1 in this process"
    else:
        results, out = _spawn(args, parts)
        out["openblas_pinning"] = "fresh process with OPENBLAS_NUM_THREADS=1"
    out.update({
        "dtype": "float64", "parts": sorted(parts), "quick": bool(args.quick),
        "options": {k: getattr(args, k) for k in _OPTION_DESTS},
        "notes": [
            "jaxslam_s / reference_s are seconds per filter step (step part) or per batch of M "
            "runs (monte carlo), medians after warm-up; speedup = reference_s / jaxslam_s",
            "a step time is the mean over whole LiDAR periods: 9 IMU-only steps and one "
            "IMU + LiDAR step (4 landmark updates per particle) per 10 steps",
            "'jitted loop': the steps inside one jitted lax.fori_loop (the XLA while loop "
            "lax.scan lowers to; StepOut stacked as a scan would) divided by the step count; "
            "'one call per step': the same program called once per step, blocked each time",
            "the per-particle Python loop is measured at step.per_particle_loop."
            "measured_at_particles and scaled linearly to N",
            "the NumPy twin reproduces fastslam_001.step to ~1e-15 on the same draws "
            "(tests/benchmarks/test_bench_fastslam_twin.py); here it draws its own numbers",
            "timings depend on the machine's load: see load_average (2 cores shared)"],
    })
    _print_targets(out)
    return {"results": results, **out}


def _child_main(a_path, o_path):
    import argparse

    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    with open(a_path) as fh:
        args = argparse.Namespace(**json.load(fh))
    from jaxslam.errors import InputError

    parts = {p.strip() for p in str(args.parts).split(",") if p.strip()}
    try:
        results, out = _run_here(_fill_defaults(args), parts)
    except InputError as e:  # handed to the parent, which raises it (exit 2)
        with open(o_path, "w") as fh:
            json.dump({"input_error": str(e)}, fh)
        sys.exit(2)
    with open(o_path, "w") as fh:
        json.dump({"results": results, "out": out}, fh)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child_main(sys.argv[2], sys.argv[3])
    else:
        sys.exit("run this benchmark through the CLI: python -m jaxslam bench fastslam [options]")
