"""Closed-loop flight benchmark: jaxslam's jitted simulate scan vs a plain NumPy loop.

Run with ``python -m jaxslam bench sim [--json PATH] [options]`` (float64: the CLI enables
x64).  The flight is the ``track-figure8`` scenario of paper 000: the DF-LQR with jaxslam's
flatness feedforward flies the 10 m × 5 m figure-8 on the true state from rest at the
origin, RK4 of eq. 2 at dt = 0.01 s, an IMU sample (specific force + gyro + white noise) every
step, no landmarks.

jaxslam: ``jax.jit`` of :func:`jaxslam.sim.simulate.simulate` (one nested ``lax.scan``; the
LQR gain is solved inside the call, as the scenario does).  Reference: :mod:`numpy_flight`,
a Python ``for`` loop over steps of the same model (closed-form trajectory derivatives, jet
arithmetic for the feedforward, SciPy CARE for the gain once per run), run in the same
process on the same inputs.

Cases (``case`` in the JSON):

``single``  one flight of ``--duration`` s (default 50 s = 5000 steps), rounded to whole LiDAR
   frames of 0.1 s: ``params.duration_s`` is the time flown (``steps`` × ``dt_s``),
   ``params.duration_asked_s`` the option as given.  The IMU noise of
   the NumPy loop is exactly jaxslam's: :func:`imu_standard_normals` reproduces the keys
   ``simulate`` splits, so both produce the same flight; the JSON records the largest
   difference of the truth and IMU arrays (``max_abs_diff_truth``, ``max_abs_diff_imu``).
``batch-M`` ``jax.vmap`` of the jitted flight over M runs vs the NumPy loop × M.  Each run
   starts from its own initial state (position offsets uniform in ±``--x0-spread`` m, yaw
   in ±0.2 rad) and its own key.  Why the offsets: with the controller on the true state
   the IMU noise never feeds back, so a vmap over keys alone leaves the state carry
   unbatched (JAX batches only what depends on the mapped input) and would integrate the
   dynamics once for all M runs.  The NumPy time is measured on the first
   min(M, ``--numpy-batch-max``) runs (same x0, same normals as jaxslam's runs) and scaled
   to M (runs are independent, so the cost is linear in M); the JSON says how many.

What each side's time contains: jaxslam — the LQR gain (CARE inside the call), the IMU noise
draws from the key, the flight and its outputs (truth, ref, u, IMU).  NumPy — the gain (SciPy
CARE), the flight and the same outputs; its standard normals are drawn by JAX before the
timer starts (drawing 6·T normals in NumPy would add < 1 ms).

``--profile`` adds a ``profile`` block: the per-step cost of each part of the scan body timed
alone (:func:`profile_parts`), which shows where the single-run time goes.

Timing: ``lower().compile()`` is timed apart (``compile_s``); each timed call is followed by
``block_until_ready``; the figures are medians of ``--repeats`` calls after one warm-up call
(NumPy: ``--numpy-repeats``).  ``--openblas-check`` also times the NumPy loop in a fresh
process with ``OPENBLAS_NUM_THREADS=1`` (it must be set before NumPy loads OpenBLAS): the single
case's own call of ``numpy_flight.simulate`` on its own inputs (handed over by pickle), so the
child flies the timed flight bit for bit (``reference_openblas1.same_flight_as_timed``); the loop
is scalar-heavy (3×3 and 4×7 products), so threads matter little, and the JSON records both.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
from timing import int_list, lidar_frames, prng_key

from jaxslam.cli.common import nonnegative_float, positive_float
from jaxslam.errors import InputError

import numpy_flight

DESCRIPTION = ("Closed-loop DF-LQR flight (track-figure8, 50 s): jitted simulate scan vs a "
               "plain NumPy loop of the same model, single run and vmapped batches")

HERE = pathlib.Path(__file__).resolve().parent
LIDAR_EVERY = 10
TARGET_SINGLE_SPEEDUP = 30.0
MAX_DURATION_S = 3600.0  # 360 000 steps: ~40 s of NumPy loop per run; far above the 50 s default
MAX_RUN_SECONDS = 50_000.0  # M x duration of a batch case: 10x the default 100 x 50 s (~3 GB)


def _duration(text: str) -> float:
    """argparse type of ``--duration``: a float in [0.1, MAX_DURATION_S] s (one LiDAR period at
    least; the upper bound keeps a typo such as 1e12 from running for ever).  :func:`run` checks
    ``args.duration`` with it too (a namespace made without the parser)."""
    import argparse

    if isinstance(text, bool):  # float(True) is 1.0 s
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}")
    value = positive_float(text)
    lo = LIDAR_EVERY * 0.01
    if not lo <= value <= MAX_DURATION_S:
        raise argparse.ArgumentTypeError(f"must be in [{lo:g}, {MAX_DURATION_S:g}] s, got {text}")
    return value


def add_arguments(parser):
    """Benchmark options (defaults take a few minutes on 2 CPU cores)."""
    parser.add_argument("--duration", type=_duration, default=50.0,
                        help=f"flight duration [s], in [{LIDAR_EVERY * 0.01:g}, {MAX_DURATION_S:g}] "
                             f"(default 50 = 5000 steps); a batch case also needs M x DURATION <= "
                             f"{MAX_RUN_SECONDS:g} (the flights of a batch are held in memory at once)")
    parser.add_argument("--batches", default="10,100",
                        help="comma list of vmapped batch sizes M ('' for none; default 10,100)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed jaxslam calls per case (median; default 5)")
    parser.add_argument("--numpy-repeats", type=int, default=3,
                        help="timed NumPy runs of the single case (median; default 3)")
    parser.add_argument("--numpy-batch-max", type=int, default=3,
                        help="NumPy runs actually timed per batch case, scaled to M (default 3)")
    parser.add_argument("--x0-spread", type=nonnegative_float, default=0.5,
                        help="half width of the initial position offsets of batch runs [m]")
    parser.add_argument("--seed", type=int, default=0, help="seed of keys and offsets")
    parser.add_argument("--no-feedforward", action="store_true",
                        help="paper's eq. 19 attitude references (no flatness feedforward)")
    parser.add_argument("--openblas-check", action="store_true",
                        help="also time the NumPy loop in a subprocess with OPENBLAS_NUM_THREADS=1")
    parser.add_argument("--profile", action="store_true",
                        help="also time the parts of the scan body (control, RK4 + IMU, per-step "
                             "noise draws) and of the NumPy step, each alone (adds ~1 min)")


# ---------------------------------------------------------------------------
# JAX side
# ---------------------------------------------------------------------------

def make_setup(dtype=None):
    """The ``track-figure8`` flight setup (paper 000 quadcopter, figure-8, no landmarks)."""
    import jax.numpy as jnp
    from jaxslam.sim.scenarios import tracking

    dtype = jnp.float64 if dtype is None else dtype
    return tracking.make_setup(tracking.paper000_figure8(), dtype)


def jax_runner(setup, n_frame, lidar_every=LIDAR_EVERY, feedforward=True):
    """``fn(key, x0) -> Flight``: :func:`simulate` of ``setup`` from ``x0`` (not yet jitted)."""
    from jaxslam.sim.simulate import simulate

    def fn(key, x0):
        return simulate(setup._replace(x0=x0), key, n_frame, lidar_every,
                        feedforward=feedforward)

    return fn


def imu_standard_normals(key, n_frame, lidar_every=LIDAR_EVERY, dtype=None):
    """(T, 6) standard normals that :func:`simulate` draws for the IMU from ``key``.

    Mirrors its key schedule: ``k_imu, k_lidar, k_est = split(key, 3)`` and
    ``normal(k_imu, (T·6,))`` reshaped to (T, 6).  Row k multiplies the IMU σ of step k.
    """
    import jax
    import jax.numpy as jnp

    dtype = jnp.float64 if dtype is None else dtype
    k_imu, _, _ = jax.random.split(key, 3)
    T = n_frame * lidar_every
    return jax.random.normal(k_imu, (T * 6,), dtype).reshape(T, 6)


def numpy_inputs(setup):
    """The twin's trajectory, controller, IMU σ (6,) and dt from a jaxslam ``FlightSetup``."""
    from jaxslam.sensors import imu as imu_mod

    traj = numpy_flight.Figure8Params.from_container(setup.traj)
    ctrl = numpy_flight.ControllerNp.from_params(setup.ctrl)
    sa, sg = imu_mod.white_noise_sigma(setup.imu)
    sigma = np.concatenate([np.asarray(sa, np.float64), np.asarray(sg, np.float64)])
    return traj, ctrl, sigma, float(setup.dt)


def batch_initial_states(seed, runs, spread, dtype=None):
    """(runs, 12) hover states at offsets uniform in ±spread m (x, y, z) and yaw ±0.2 rad."""
    rng = np.random.default_rng(seed)
    x0 = np.zeros((runs, 12))
    x0[:, 0:3] = rng.uniform(-spread, spread, (runs, 3))
    x0[:, 8] = rng.uniform(-0.2, 0.2, runs)
    return x0


# ---------------------------------------------------------------------------
# Timing helpers
# ---------------------------------------------------------------------------

def _time_jax(compiled, args, repeats):
    import jax

    jax.block_until_ready(compiled(*args))  # warm-up
    times = []
    out = None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times, out


def _time_numpy(fn, repeats):
    fn_out = fn()  # warm-up (and the result used for the agreement check)
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times, fn_out


# The pinned-OpenBLAS child: it calls the oracle's ``simulate`` explicitly on the inputs the
# parent pickled (those of the timed single case), warms it up on min(steps, 50) steps (as
# ``numpy_flight._main``, which it replaces here, does), times ``repeats`` flights and prints
# one JSON line, with a digest of its flight's truth and IMU (:func:`flight_digest`).
_PINNED_CHILD = """
import hashlib, json, os, pickle, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import numpy_flight
a = pickle.load(sys.stdin.buffer)
def fly(n):
    return numpy_flight.simulate(a["traj"], a["ctrl"], a["x0"], a["dt"], n, a["sigma"], a["noise"],
                                 feedforward_on=a["feedforward"])
fly(min(a["n_steps"], 50))
times = []
for _ in range(a["repeats"]):
    t0 = time.perf_counter()
    out = fly(a["n_steps"])
    times.append(time.perf_counter() - t0)
h = hashlib.sha256()
for k in ("truth", "imu"):
    h.update(np.ascontiguousarray(out[k], np.float64).tobytes())
print(json.dumps({"times_s": times, "median_s": float(np.median(times)),
                  "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                  "steps": a["n_steps"], "feedforward": a["feedforward"],
                  "flight_sha256": h.hexdigest()}))
"""


def flight_digest(flight) -> str:
    """SHA-256 of a NumPy flight's ``truth`` and ``imu`` arrays (float64 bytes, in that order):
    what the pinned child reports, to compare with the in-process flight."""
    import hashlib

    h = hashlib.sha256()
    for k in ("truth", "imu"):
        h.update(np.ascontiguousarray(flight[k], np.float64).tobytes())
    return h.hexdigest()


def _openblas1_numpy(traj, ctrl, x0, dt, n_steps, sigma, noise, repeats, feedforward=True):
    """The NumPy loop timed in a fresh process with OPENBLAS_NUM_THREADS=1 (it must be set
    before NumPy loads OpenBLAS): ``numpy_flight.simulate(traj, ctrl, x0, dt, n_steps, sigma,
    noise, feedforward_on=feedforward)`` — the timed single case's own call, its inputs handed
    over by pickle — after one warm-up flight of min(n_steps, 50) steps, ``repeats`` times.
    Returns the child's JSON (``times_s``, ``median_s``, ``openblas_num_threads``, ``steps``,
    ``feedforward``, ``flight_sha256``), or ``{"error": [last line of its stderr]}``."""
    import pickle

    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    payload = pickle.dumps({"traj": traj, "ctrl": ctrl, "x0": np.asarray(x0, np.float64),
                            "dt": float(dt), "n_steps": int(n_steps),
                            "sigma": np.asarray(sigma, np.float64),
                            "noise": np.asarray(noise, np.float64),
                            "repeats": max(1, int(repeats)), "feedforward": bool(feedforward)})
    oracle_dir = str(pathlib.Path(numpy_flight.__file__).resolve().parent)
    res = subprocess.run([sys.executable, "-c", _PINNED_CHILD, oracle_dir], input=payload,
                         env=env, capture_output=True, timeout=3600)
    if res.returncode != 0:
        return {"error": res.stderr.decode(errors="replace").strip().splitlines()[-1:]}
    return json.loads(res.stdout.decode().strip().splitlines()[-1])


def profile_parts(setup, n_steps, feedforward=True, repeats=5):
    """Per-step cost [µs] of the parts of simulate's scan body, each in its own jitted scan.

    ``control``: :func:`jaxslam.control.dflqr.control` alone (the state carry is nudged by
    the thrust so XLA cannot hoist it); ``reference``: the open-loop part of it
    (``flatness.reference`` + ``flatness.feedforward``) alone; ``rk4_imu``: one RK4 step of
    eq. 2 plus the IMU sample at a fixed input; ``noise``: simulate's per-step key split and
    ``normal(key, (6,))`` draws; ``reference_vmapped``: the open-loop part for all steps in one
    ``vmap`` (what precomputing it outside the scan would cost).  NumPy: the twin's
    ``control``, ``rk4_step`` and ``imu_ideal`` per call (min of 3 × 500 calls).
    """
    import timeit

    import jax
    import jax.numpy as jnp
    from jaxslam.control import dflqr, flatness
    from jaxslam.dynamics import euler_ned
    from jaxslam.dynamics.integrators import rk4_step
    from jaxslam.sensors import imu as imu_mod

    quad = setup.ctrl.quad
    dt = float(setup.dt)
    K = dflqr.gain(setup.ctrl)
    x0 = setup.x0
    ts = jnp.arange(n_steps, dtype=x0.dtype) * dt
    u_hover = euler_ned.hover_input(quad, x0.dtype) * 1.0001

    def f(x, u):
        return euler_ned.f(x, u, quad)

    def open_loop(t):
        r_d, u_d = flatness.reference(setup.traj, t, quad.g)
        if not feedforward:
            return r_d, u_d
        x_ff, u_ff = flatness.feedforward(setup.traj, t, quad)
        return r_d, u_d, x_ff[9:12], u_ff[1:4]

    def s_control(x0, ts):
        def body(x, t):
            u, _ = dflqr.control(x, t, setup.traj, K, setup.ctrl, feedforward=feedforward)
            return x + 1e-12 * u[0], u
        return jax.lax.scan(body, x0, ts)

    def s_reference(x0, ts):
        def body(x, t):
            out = open_loop(t + 1e-12 * x[0])
            return x + 1e-12 * out[0][0], out
        return jax.lax.scan(body, x0, ts)

    def s_rk4_imu(x0, ts):
        def body(x, t):
            xn = rk4_step(f, x, u_hover, dt)
            return xn, (xn, imu_mod.imu_ideal(xn, f(xn, u_hover), quad.g))
        return jax.lax.scan(body, x0, ts)

    def s_noise(key):
        n_frame = n_steps // LIDAR_EVERY

        def frame(c, kf):
            k_steps, _ = jax.random.split(kf)
            keys = jax.random.split(k_steps, LIDAR_EVERY)
            return c, jax.lax.scan(lambda c2, k: (c2, jax.random.normal(k, (6,), x0.dtype)),
                                   c, keys)[1]
        return jax.lax.scan(frame, jnp.zeros((), x0.dtype), jax.random.split(key, n_frame))

    def v_reference(ts):
        return jax.vmap(open_loop)(ts)

    out = {}
    cases = {"control": (s_control, (x0, ts)), "reference": (s_reference, (x0, ts)),
             "rk4_imu": (s_rk4_imu, (x0, ts)), "noise": (s_noise, (jax.random.PRNGKey(0),)),
             "reference_vmapped": (v_reference, (ts,))}
    for name, (fn, a) in cases.items():
        compiled = jax.jit(fn).lower(*a).compile()
        med, _, _ = _time_jax(compiled, a, repeats)
        out[f"jax_{name}_us_per_step"] = 1e6 * med / n_steps
    traj_np, ctrl_np, _, _ = numpy_inputs(setup)
    K_np = numpy_flight.lqr_gain(ctrl_np.Q, ctrl_np.R)
    x = np.asarray(x0, np.float64).copy()
    x[8] = 0.7
    u = np.asarray(u_hover, np.float64)
    np_cases = {
        "control": lambda: numpy_flight.control(x, 3.3, traj_np, K_np, ctrl_np, feedforward),
        "rk4": lambda: numpy_flight.rk4_step(x, u, dt, ctrl_np.quad),
        "imu": lambda: numpy_flight.imu_ideal(x, numpy_flight.f(x, u, ctrl_np.quad), quad.g),
    }
    for name, fn in np_cases.items():
        out[f"numpy_{name}_us_per_call"] = 1e6 * min(timeit.repeat(fn, number=500, repeat=3)) / 500
    return out


def _load():
    try:
        return list(os.getloadavg())
    except OSError:
        return None


# ---------------------------------------------------------------------------
# Benchmark
# ---------------------------------------------------------------------------

def run(args) -> dict:
    """Run the cases of the module docstring; return the bench JSON (dict)."""
    import argparse

    import jax
    import jax.numpy as jnp
    from jaxslam import io

    if not jax.config.jax_enable_x64:
        raise RuntimeError("bench sim needs float64 (run it through 'python -m jaxslam bench')")
    try:  # the option's declared bounds, also for a namespace the parser did not make
        duration = _duration(args.duration)
    except argparse.ArgumentTypeError as e:
        raise InputError(f"--duration: {e}") from None
    batches = int_list(args.batches, "--batches", allow_empty=True)  # "": no vmapped batches
    if batches and max(batches) * duration > MAX_RUN_SECONDS:
        raise InputError(f"--batches: M x --duration must be <= {MAX_RUN_SECONDS:g} run-seconds "
                         f"(all M flights are held in memory), got {max(batches)} x {duration:g}")
    setup = make_setup(jnp.float64)
    dt = float(setup.dt)
    n_frame = lidar_frames(duration, "--duration", dt, LIDAR_EVERY)
    n_steps = n_frame * LIDAR_EVERY
    flown = round(n_steps * dt, 9)  # what ran: whole LiDAR frames (0.14 s flies 0.1 s)
    ff = not args.no_feedforward
    traj_np, ctrl_np, sigma, _ = numpy_inputs(setup)
    fn = jax_runner(setup, n_frame, LIDAR_EVERY, ff)
    base_key = prng_key(args.seed)
    load_before = _load()
    results = []

    # --- single run ------------------------------------------------------------------
    key = jax.random.fold_in(base_key, 0)
    x0 = setup.x0
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(key, x0).compile()
    compile_s = time.perf_counter() - t0
    jax_s, jax_times, flight = _time_jax(compiled, (key, x0), args.repeats)
    noise = np.asarray(imu_standard_normals(key, n_frame, LIDAR_EVERY, jnp.float64))
    x0_np = np.asarray(x0, np.float64)
    np_s, np_times, ref = _time_numpy(
        lambda: numpy_flight.simulate(traj_np, ctrl_np, x0_np, dt, n_steps, sigma, noise, ff),
        args.numpy_repeats)
    single = {
        "case": "single",
        "params": {"runs": 1, "steps": n_steps, "duration_s": flown,
                   "duration_asked_s": duration, "dt_s": dt,
                   "feedforward": ff, "dtype": "float64", "repeats": args.repeats,
                   "numpy_repeats": args.numpy_repeats},
        "jaxslam_s": jax_s,
        "reference": "numpy loop",
        "reference_s": np_s,
        "speedup": np_s / jax_s,
        "steps_per_s_jax": n_steps / jax_s,
        "steps_per_s_numpy": n_steps / np_s,
        "compile_s": compile_s,
        "jaxslam_times_s": jax_times,
        "reference_times_s": np_times,
        "us_per_step_jax": 1e6 * jax_s / n_steps,
        "us_per_step_numpy": 1e6 * np_s / n_steps,
        "max_abs_diff_truth": float(np.max(np.abs(np.asarray(flight.truth) - ref["truth"]))),
        "max_abs_diff_imu": float(np.max(np.abs(np.asarray(flight.imu) - ref["imu"]))),
        "target_speedup": TARGET_SINGLE_SPEEDUP,
        "target_met": bool(np_s / jax_s >= TARGET_SINGLE_SPEEDUP),
    }
    if args.openblas_check:
        pinned = _openblas1_numpy(traj_np, ctrl_np, x0_np, dt, n_steps, sigma, noise,
                                  args.numpy_repeats, ff)
        if "flight_sha256" in pinned:  # it flew the timed case's flight, bit for bit
            pinned["same_flight_as_timed"] = pinned["flight_sha256"] == flight_digest(ref)
        single["reference_openblas1"] = pinned
    results.append(single)

    # --- vmapped batches -------------------------------------------------------------
    for M in batches:
        if M < 1:
            continue
        keys = jax.vmap(lambda i: jax.random.fold_in(base_key, i))(jnp.arange(M))
        x0s_np = batch_initial_states(args.seed, M, args.x0_spread)
        x0s = jnp.asarray(x0s_np)
        t0 = time.perf_counter()
        compiled_b = jax.jit(jax.vmap(fn)).lower(keys, x0s).compile()
        compile_b = time.perf_counter() - t0
        jb_s, jb_times, flights = _time_jax(compiled_b, (keys, x0s), args.repeats)
        n_timed = max(1, min(M, args.numpy_batch_max))
        # Standard normals for the timed NumPy runs (values only matter for agreement,
        # which the single case checks; the cost is the same).
        noises = [np.asarray(imu_standard_normals(keys[i], n_frame, LIDAR_EVERY, jnp.float64))
                  for i in range(n_timed)]
        refs = []
        t0 = time.perf_counter()
        for i in range(n_timed):
            refs.append(numpy_flight.simulate(traj_np, ctrl_np, x0s_np[i], dt, n_steps, sigma,
                                              noises[i], ff))
        per_run = (time.perf_counter() - t0) / n_timed
        truth_b = np.asarray(flights.truth)
        diff_b = max(float(np.max(np.abs(truth_b[i] - refs[i]["truth"]))) for i in range(n_timed))
        nb_s = per_run * M
        results.append({
            "case": f"batch-{M}",
            "params": {"runs": M, "steps": n_steps, "duration_s": flown,
                       "duration_asked_s": duration, "dt_s": dt,
                       "feedforward": ff, "dtype": "float64", "repeats": args.repeats,
                       "x0_spread_m": args.x0_spread, "numpy_runs_timed": n_timed},
            "jaxslam_s": jb_s,
            "reference": "numpy loop",
            "reference_s": nb_s,
            "reference_scaled_from_runs": n_timed,
            "speedup": nb_s / jb_s,
            "steps_per_s_jax": M * n_steps / jb_s,
            "steps_per_s_numpy": M * n_steps / nb_s,
            "compile_s": compile_b,
            "jaxslam_times_s": jb_times,
            "vmap_gain_vs_single": (M * jax_s) / jb_s,
            "max_abs_diff_truth": diff_b,
        })

    profile = profile_parts(setup, n_steps, ff, args.repeats) if args.profile else None

    machine = io.machine_info()
    machine["load_avg_before"] = load_before
    machine["load_avg_after"] = _load()
    machine["x64"] = True
    return {
        "benchmark": "sim",
        "machine": machine,
        "notes": ("NumPy loop in the same process; OPENBLAS_NUM_THREADS as recorded in machine "
                  "(the loop's matrix products are 3×3 and 4×7, so BLAS threads barely "
                  "matter; --openblas-check times a pinned fresh process). IMU noise: the "
                  "single case feeds the NumPy loop the exact normals simulate draws from its "
                  "key. Batch NumPy times are scaled from numpy_runs_timed runs."),
        "results": results,
        **({"profile": profile} if profile is not None else {}),
    }
