"""EKF-SLAM benchmark of paper 000: the Fig. 12 study, JAX vs a NumPy twin, Monte Carlo.

Run with ``python -m jaxslam bench ekfslam [--json PATH] [--plots DIR] [options]``
(float64: the CLI enables x64).  Three parts (``--parts``):

``study``  Fig. 12 of paper 000 — the cost of each EKF-SLAM operation:
   * prediction (``propagate``: Q_d + RK4 + P_rr/P_rl) vs mapped landmarks
     N (capacity = N);
   * update vs k observed mapped landmarks at a fixed map (engine ``update``
     compiled for exactly k measurements);
   * registration vs k observed unmapped landmarks (engine ``register`` for k);
   * one full frame (10 predictions + ``correct`` with max_obs = 16: update of
     the mapped, registration of the unmapped) at 200 mapped landmarks, with the
     default covariance form of ``ekf_slam_3d.Config`` (eq. 43, P − K S Kᵀ) and with
     the factored Joseph form (``Config(joseph=True)``: twice the correction's products),
     each against the twin doing the same form.
   Each JAX operation is jitted in isolation and timed two ways: ``call`` —
   one jitted call per operation with the state donated (what a user who calls
   the step from Python pays, dispatch included), and ``scan`` — the same
   operation repeated inside one ``lax.fori_loop`` and divided (what it costs
   inside the filter's scan).  The reference is the NumPy twin's same
   operation (``numpy_ekfslam3d``), each call on a fresh copy of the same state.

``full``   a whole flight (default 50 s: 5000 IMU steps, 500 LiDAR frames) as ONE
   jitted :func:`jaxslam.systems.ekf_slam_3d.run` scan vs the NumPy twin on the same log, at
   capacities 16, 64, 256, with the default form (eq. 43, P − K S Kᵀ) and the Joseph form
   (``jaxslam-joseph-form``), each timed against the twin doing the same form (the twin's
   ``joseph``); both filters' estimates are compared (max |Δ|).  A second reference:
   the twin doing the same leading-active-block update; each run's FLOP count (per frame
   2 n² m for the mapped state, per step 2 n_r² n) is in the JSON, and the frame case of the
   study reports its floor, its own n²·m product timed.  The repeats of the five methods are
   interleaved; the capacity 256 / 64 time ratio comes from ``--pairs`` alternating calls of
   the two compiled runs (the ratio of two medians taken minutes apart moved by ±0.1 with the
   machine's load).

``mc``     Monte Carlo throughput: ``jax.vmap`` of the closed-loop flight
   (``jaxslam.sim.scenarios.ekfslam3d.build(...)[0]``: simulate with the
   DF-LQR on the estimate + EKF-SLAM + metrics) over M seeded runs, in chunks,
   vs M sequential calls of the jitted single run.  The sequential time is
   measured over min(M, ``--mc-seq-max``) calls and scaled to M (each call is
   independent, so its cost is linear in M); the JSON says so.  Medians of
   min(``--repeats``, 3) interleaved repeats.  A second row
   per M times what ``jaxslam run ekfslam3d-*`` does on a CPU: the runner's
   ``"loop"`` batching (``monte_carlo.run``), the compiled single run called
   from ``monte_carlo.default_threads()`` host threads at once (all M runs
   timed), against the same sequential reference.

OpenBLAS threads: jaxlib's LAPACK kernels (Cholesky, triangular solves) run on
the OpenBLAS that NumPy loads, so its thread count changes BOTH sides (on a busy
2-core machine an unpinned triangular solve with 177 right-hand sides took
~20 ms instead of ~50 µs).  Every part is measured with OpenBLAS on 1 thread —
in this process when ``OPENBLAS_NUM_THREADS=1`` (the ``jaxslam`` command sets
it unless the user chose otherwise) or threadpoolctl is installed, else in a
fresh child process (the variable only acts before NumPy loads OpenBLAS) — and
the full run (jaxslam vs NumPy) is repeated with OpenBLAS's default threads
(a fresh process with the variable unset) for the record.

Medians after warm-up, ``block_until_ready`` on every JAX result.  Every target
is recorded in ``targets`` (met or missed); ``load_average`` records how busy
the machine was.
"""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
from timing import int_list, lidar_frames, prng_key

DESCRIPTION = ("Paper 000 EKF-SLAM: Fig. 12 cost study (predict/update/registration), full 50 s "
               "run as one jitted scan vs a NumPy twin, vmap Monte Carlo throughput")

HERE = pathlib.Path(__file__).resolve().parent
DT = 0.01
LIDAR_EVERY = 10
G = 9.81

# Issue 19's acceptance.
TARGETS = {
    "frame_step_call_s": 2e-3,
    "full_speedup": {16: 10.0, 64: 8.0, 256: 8.0},
    "capacity_ratio_256_64": 1.3,
    "mc_speedup_at_100": 2.0,
}


def _matmul_floor(n, m, reps=200):
    """Median time of the floor's own product: one jitted (n, m) @ (m, n) float64 matmul
    (2·n²·m FLOP), which is the cost of one rank-m covariance correction of an n-state."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.normal(size=(n, m)))
    b = jnp.asarray(rng.normal(size=(m, n)))
    f = jax.jit(lambda a_, b_: a_ @ b_)
    for _ in range(5):
        jax.block_until_ready(f(a, b))
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(a, b))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), 2.0 * n * n * m


def add_arguments(parser):
    """Benchmark options (quick defaults: a few minutes on 2 CPU cores)."""
    parser.add_argument("--parts", default="study,full,mc",
                        help="comma list of parts to run: study, full, mc (default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of logs, states and runs")
    parser.add_argument("--calls", type=int, default=100,
                        help="timed calls per study operation (median; default 100)")
    parser.add_argument("--scan-reps", type=int, default=50,
                        help="repetitions inside one fori_loop for the in-scan cost (default 50)")
    parser.add_argument("--study-maps", default="5,10,20,50,100,200",
                        help="mapped landmarks for the prediction study (capacity = mapped)")
    parser.add_argument("--study-obs", default="1,2,4,8,16",
                        help="observed landmarks for the update / registration study")
    parser.add_argument("--study-map-size", type=int, default=40,
                        help="mapped landmarks during the update / registration study")
    parser.add_argument("--frame-mapped", type=int, default=200,
                        help="mapped landmarks of the full-frame case (capacity +16)")
    parser.add_argument("--capacities", default="16,64,256",
                        help="capacities of the full-run comparison (default 16,64,256)")
    parser.add_argument("--duration", type=float, default=50.0,
                        help="flight duration of the full-run comparison [s] (default 50)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed repeats of each full run, the methods interleaved (median; "
                             "default 5); the mc part uses min(REPEATS, 3)")
    parser.add_argument("--pairs", type=int, default=15,
                        help="alternating calls of the capacity 64 and 256 runs for their time "
                             "ratio (median of each; default 15); used only when --capacities "
                             "includes both 64 and 256, else ignored")
    parser.add_argument("--log", choices=("sim", "synthetic"), default="sim",
                        help="log of the full run: closed-loop simulation of the ekfslam3d "
                             "scenario (default; falls back to synthetic if it fails) or a "
                             "hand-made smooth flight")
    parser.add_argument("--mc-runs", default="1,10,100,1000",
                        help="Monte Carlo batch sizes M (default 1,10,100,1000)")
    parser.add_argument("--mc-duration", type=float, default=2.0,
                        help="flight duration of each Monte Carlo run [s] (default 2, to keep "
                             "M = 1000 within a few minutes; the paper's flight is 50 s)")
    parser.add_argument("--mc-capacity", type=int, default=64, help="capacity of the MC runs")
    parser.add_argument("--mc-chunk", type=int, default=100,
                        help="runs per vmapped call (memory bound; default 100)")
    parser.add_argument("--mc-seq-max", type=int, default=100,
                        help="sequential single-run calls actually timed per M (default 100: the "
                             "target's M = 100 is timed whole, not scaled)")
    parser.add_argument("--plots", metavar="DIR", default=None,
                        help="write bench_ekfslam_fig12.png into DIR (the study part's figure: "
                             "needs study in --parts)")


# ---------------------------------------------------------------------------
# Logs
# ---------------------------------------------------------------------------

def synthetic_log(duration, seed, n_landmarks=40, dt=DT, lidar_every=LIDAR_EVERY, yaw0=-0.5):
    """A smooth hand-made flight and its sensor log (no controller involved).

    Position: a figure-8 of 12 m × 6 m around (0, 0, −5) NED with a 20 s period
    and ±0.5 m of altitude; roll/pitch small sinusoids; yaw turning at
    0.4 rad/s from ``yaw0`` so the ±45° LiDAR sweeps the landmarks (and the
    yaw crosses ±π, exercising the angle wrapping).  The IMU is the exact
    specific force / body rate of that flight (derivatives by ``jacfwd`` in
    time) plus Table 5 white noise at 1/dt; LiDAR frames every ``lidar_every``
    steps from ``jaxslam.sensors.lidar3d`` with Table 4 noise; 40 landmarks of
    Table 3 around the centre.

    Returns a dict of NumPy arrays: truth (T+1, 9), imu (T+1, 6), y (F, L, 3),
    visible (F, L), ids (L,), landmarks (L, 3), s0 (9,) and lidar_every, dt.
    """
    import jax
    import jax.numpy as jnp

    from jaxslam.geometry.euler import dcm_from_euler, euler_rate_matrix
    from jaxslam.sensors import imu as imu_mod
    from jaxslam.sensors import landmarks as lm_mod
    from jaxslam.sensors import lidar3d

    dtype = jnp.float64
    F = lidar_frames(duration, "duration", dt, lidar_every)
    T = F * lidar_every
    center = jnp.array([0.0, 0.0, -5.0], dtype)
    w8 = 2 * math.pi / 20.0

    def pos(t):
        return center + jnp.stack([6 * jnp.sin(w8 * t), 3 * jnp.sin(2 * w8 * t), 0.5 * jnp.sin(w8 * t)])

    def euler(t):
        return jnp.stack([0.08 * jnp.sin(1.3 * t), 0.06 * jnp.cos(0.9 * t), 0.4 * t + yaw0])

    def vel_b(t):
        return dcm_from_euler(euler(t)).T @ jax.jacfwd(pos)(t)

    def state(t):
        return jnp.concatenate([pos(t), vel_b(t), euler(t)])

    def imu_true(t):
        e, v = euler(t), vel_b(t)
        w = jnp.linalg.solve(euler_rate_matrix(e), jax.jacfwd(euler)(t))
        fb = jax.jacfwd(vel_b)(t) - jnp.cross(v, w) - G * dcm_from_euler(e)[2, :]
        return jnp.concatenate([fb, w])

    R = lidar3d.measurement_cov(lidar3d.PAPER000_LIDAR, dtype)
    sa, sg = imu_mod.white_noise_sigma(imu_mod.PAPER000_IMU._replace(rate=1.0 / dt))
    sig = jnp.concatenate([sa, sg]).astype(dtype)

    @jax.jit
    def make(key):
        k_lm, k_imu, k_y = jax.random.split(key, 3)
        lms = lm_mod.generate_landmarks(k_lm, n_landmarks, center=np.asarray(center), dtype=dtype)
        t = jnp.arange(T + 1, dtype=dtype) * dt
        truth = jax.vmap(state)(t)
        imus = jax.vmap(imu_true)(t) + sig * jax.random.normal(k_imu, (T + 1, 6), dtype)

        def frame(tt, k):
            yy, vis = lidar3d.measure_all(pos(tt), euler(tt), lms)
            yy = yy + jnp.sqrt(jnp.diag(R)) * jax.random.normal(k, yy.shape, dtype)
            yy = yy.at[:, 0].set(jnp.mod(yy[:, 0] + jnp.pi, 2 * jnp.pi) - jnp.pi)
            return yy, vis

        y, vis = jax.vmap(frame)(t[lidar_every::lidar_every], jax.random.split(k_y, F))
        return truth, imus, y, vis, lms

    truth, imus, y, vis, lms = (np.array(a) for a in make(prng_key(seed)))
    truth[:, 8] = np.mod(truth[:, 8] + np.pi, 2 * np.pi) - np.pi  # the filter's yaw is wrapped
    return {"truth": truth, "imu": imus, "y": y, "visible": vis,
            "ids": np.arange(n_landmarks, dtype=np.int32), "landmarks": lms,
            "s0": truth[0, :9].copy(), "lidar_every": lidar_every, "dt": dt, "source": "synthetic"}


def sim_log(duration, seed, capacity=64):
    """The log of one closed-loop flight of the ``ekfslam3d-unknown`` scenario (same layout)."""
    import jax
    import jax.numpy as jnp

    from jaxslam.sim.scenarios import ekfslam3d

    opts = _scenario_options(duration, capacity)
    _, flight, _, noise, _ = ekfslam3d.build(opts, "unknown", jnp.float64)
    fl, lms = jax.jit(lambda k: flight(k, noise))(prng_key(seed))
    imu = np.asarray(fl.imu)
    truth = np.asarray(fl.truth)
    # The sample preceding the first prediction is not part of Flight; the first
    # measured sample stands in for it (only the log's timing matters here).
    imu = np.concatenate([imu[:1], imu], axis=0)
    L = lms.shape[0]
    return {"truth": truth[:, :9], "imu": imu, "y": np.asarray(fl.lidar_y),
            "visible": np.asarray(fl.lidar_mask), "ids": np.arange(L, dtype=np.int32),
            "landmarks": np.asarray(lms), "s0": truth[0, :9].copy(), "lidar_every": LIDAR_EVERY,
            "dt": DT, "source": "sim"}


def _scenario_options(duration, capacity):
    """The ``ekfslam3d-unknown`` scenario's own option defaults with duration and capacity set."""
    from jaxslam.sim.scenarios import registry

    opts = {o.name: o.default for o in registry.get("ekfslam3d-unknown").options}
    opts.update(duration=float(duration), capacity=int(capacity))
    return opts


def _filter_noise():
    from jaxslam.sensors import imu as imu_mod
    from jaxslam.systems import ekf_slam_3d as sys3d

    return sys3d.imu_noise(imu_mod.PAPER000_IMU)


# ---------------------------------------------------------------------------
# Timing helpers
# ---------------------------------------------------------------------------

def _median_call(fn, make_input, calls, warmup=3):
    """Median of ``calls`` timings of fn(*make_input()) (input prepared outside the timer)."""
    import jax

    for _ in range(warmup):
        jax.block_until_ready(fn(*make_input()))
    times = []
    for _ in range(calls):
        args = make_input()
        jax.block_until_ready(args)
        t0 = time.perf_counter()
        out = fn(*args)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _median_np(fn, make_input, calls, warmup=3):
    for _ in range(warmup):
        fn(*make_input())
    times = []
    for _ in range(calls):
        args = make_input()
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _row(case, params, jax_s, ref_name, ref_s, **extra):
    r = {"case": case, "params": params, "jaxslam_s": jax_s, "reference": ref_name,
         "reference_s": ref_s, "speedup": (ref_s / jax_s) if (jax_s and ref_s) else None}
    r.update(extra)
    return r


# ---------------------------------------------------------------------------
# Part a: Fig. 12 study
# ---------------------------------------------------------------------------

def _study_state(n_mapped, capacity, seed):
    """A realistic posterior: robot at (0, 0, −5), n_mapped landmarks 6-20 m around it,
    dense positive-definite covariance over the active block (zeros elsewhere)."""
    rng = np.random.default_rng(seed)
    n = 9 + 3 * capacity
    x = np.zeros(n)
    x[:9] = [0.3, -0.2, -5.0, 1.0, 0.5, -0.1, 0.05, -0.03, 0.3]
    d = rng.normal(size=(n_mapped, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x[9:9 + 3 * n_mapped] = (x[:3] + d * rng.uniform(6, 20, size=(n_mapped, 1))).reshape(-1)
    na = 9 + 3 * n_mapped
    B = rng.normal(size=(na, 12)) * 0.03
    P = np.zeros((n, n))
    P[:na, :na] = B @ B.T + np.diag(np.r_[np.full(9, 1e-3), np.full(3 * n_mapped, 4e-3)])
    active = np.zeros(capacity, bool)
    active[:n_mapped] = True
    ids = np.full(capacity, -1, np.int32)
    ids[:n_mapped] = np.arange(n_mapped)
    return x, P, active, ids


def _in_fov_measurements(rng, k):
    return np.stack([rng.uniform(-0.7, 0.7, k), rng.uniform(-0.45, 0.45, k), rng.uniform(5, 20, k)], 1)


def run_study(args, noise, results, out):
    import jax
    import jax.numpy as jnp

    import numpy_ekfslam3d as tw
    from jaxslam.filters import ekf_slam as es
    from jaxslam.systems import ekf_slam_3d as sys3d

    model = sys3d.make_model()
    mparams = (DT, G, "3axis")
    R = noise.R
    calls, reps = args.calls, args.scan_reps
    rng = np.random.default_rng(args.seed)
    a_imu = np.array([0.1, -0.05, -9.7, 0.01, -0.02, 0.1])
    b_imu = np.array([0.12, -0.04, -9.75, 0.012, -0.018, 0.11])

    def slam_state(x, P, active, ids):
        return es.SlamState(jnp.asarray(x), jnp.asarray(P), jnp.asarray(active), jnp.asarray(ids),
                            jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))

    def fresh(st):
        return jax.tree.map(jnp.copy, st)

    def twin_from(x, P, active, ids, cap, joseph=False):  # the twin in the system's form (eq. 43)
        return tw.NumpyEkfSlam3D(noise, x[:9], cap, max_obs=16, dt=DT, g=G,
                                 joseph=joseph).set_state(x, P, active, ids)

    def prop(st, a, b):
        Qd = sys3d.process_noise(st.x[:9], 0.5 * (a + b), noise, DT, G)
        return es.predict(st, model, jnp.concatenate([a, b]), Qd, mparams)

    def looped(op):
        def f(st, *args):
            return jax.lax.fori_loop(0, reps, lambda i, s: op(s, *args), st)
        return jax.jit(f)

    study = {"predict": [], "update": [], "register": [], "frame": None,
             "timing_modes": {"call": "one jitted call per operation, state donated, dispatch included",
                              "scan": f"operation repeated {reps}x in one fori_loop, time / {reps}"}}
    A, Bi = jnp.asarray(a_imu), jnp.asarray(b_imu)

    # -- prediction vs mapped landmarks ------------------------------------
    f_pred = jax.jit(prop, donate_argnums=0)
    f_pred_loop = looped(prop)
    for N in int_list(args.study_maps, "--study-maps"):
        _progress(f"study: prediction, {N} mapped")
        x, P, active, ids = _study_state(N, N, args.seed + N)
        st = slam_state(x, P, active, ids)
        t_call = _median_call(f_pred, lambda: (fresh(st), A, Bi), calls)
        t_scan = _median_call(f_pred_loop, lambda: (st, A, Bi), max(5, calls // 10)) / reps
        twin = twin_from(x, P, active, ids, N)
        t_np = _median_np(lambda t: t.predict(a_imu, b_imu), lambda: (twin.copy(),), calls)
        study["predict"].append({"mapped": N, "capacity": N, "jax_call_s": t_call, "jax_scan_s": t_scan,
                                 "numpy_s": t_np})
        for mode, t in (("call", t_call), ("scan", t_scan)):
            results.append(_row(f"fig12 predict/{mode} N={N}", {"mapped": N, "capacity": N},
                                t, "numpy twin (1 call)", t_np))

    # -- update and registration vs observed -------------------------------
    M0 = args.study_map_size
    x, P, active, ids = _study_state(M0, M0 + 16, args.seed + 1000)
    st = slam_state(x, P, active, ids)
    twin = twin_from(x, P, active, ids, M0 + 16)
    for k in int_list(args.study_obs, "--study-obs"):
        _progress(f"study: update and registration, {k} observed")
        slots = np.sort(rng.choice(M0, size=min(k, M0), replace=False))
        zh, _, _ = tw.observe(x[:9], x[9:9 + 3 * M0].reshape(M0, 3)[slots])
        z = zh + rng.normal(size=zh.shape) * np.sqrt(np.diag(np.asarray(R)))
        kk = len(slots)
        Z, S, Mk = jnp.asarray(z), jnp.asarray(slots, jnp.int32), jnp.ones(kk, bool)

        def upd(s_, z_, sl_, m_):
            return es.update(s_, model, z_, sl_, m_, R, mparams)[0]

        t_call = _median_call(jax.jit(upd, donate_argnums=0), lambda: (fresh(st), Z, S, Mk), calls)
        t_scan = _median_call(looped(upd), lambda: (st, Z, S, Mk), max(5, calls // 10)) / reps
        t_np = _median_np(lambda t: t.update(z, slots), lambda: (twin.copy(),), calls)
        study["update"].append({"observed": kk, "mapped": M0, "capacity": M0 + 16, "jax_call_s": t_call,
                                "jax_scan_s": t_scan, "numpy_s": t_np})
        for mode, t in (("call", t_call), ("scan", t_scan)):
            results.append(_row(f"fig12 update/{mode} k={kk}", {"observed": kk, "mapped": M0,
                                                                "capacity": M0 + 16},
                                t, "numpy twin (1 call)", t_np))

        zr = _in_fov_measurements(rng, k)
        idr = np.arange(1000, 1000 + k)
        Zr, Ir, Mr = jnp.asarray(zr), jnp.asarray(idr, jnp.int32), jnp.ones(k, bool)

        def reg(s_, z_, i_, m_):
            return es.register(s_, model, z_, i_, m_, R, mparams)

        t_call = _median_call(jax.jit(reg, donate_argnums=0), lambda: (fresh(st), Zr, Ir, Mr), calls)
        t_scan = _median_call(looped(reg), lambda: (st, Zr, Ir, Mr), max(5, calls // 10)) / reps
        t_np = _median_np(lambda t: t.register(zr, idr), lambda: (twin.copy(),), calls)
        study["register"].append({"observed": k, "mapped": M0, "capacity": M0 + 16, "jax_call_s": t_call,
                                  "jax_scan_s": t_scan, "numpy_s": t_np})
        for mode, t in (("call", t_call), ("scan", t_scan)):
            results.append(_row(f"fig12 register/{mode} k={k}", {"observed": k, "mapped": M0,
                                                                 "capacity": M0 + 16},
                                t, "numpy twin (1 call)", t_np))

    # -- one full frame at 200 mapped -------------------------------------
    Nf = args.frame_mapped
    _progress(f"study: full frame, {Nf} mapped")
    cap = Nf + 16
    x, P, active, ids = _study_state(Nf, cap, args.seed + 2000)
    cfg = sys3d.Config(mode="unknown", capacity=cap, max_obs=16)
    est = sys3d.make_estimator(cfg, noise)
    e0 = sys3d.State(slam_state(x, P, active, ids), jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
    Ltot = Nf + 16
    imu_a = np.tile(a_imu, (LIDAR_EVERY, 1))
    imu_b = np.tile(b_imu, (LIDAR_EVERY, 1))
    # The frame's data from a generator of its own (not the sweeps' draws, so the figure does
    # not depend on --study-obs): 12 mapped landmarks inside the field of view of the pose after
    # the frame's 10 predictions, observed from that pose (as a real frame is), so they pass the
    # association and the correction runs (rows_matched in the JSON says how many did).
    frng = np.random.default_rng(args.seed + 3000)
    ahead = twin_from(x, P, active, ids, cap)
    for j in range(LIDAR_EVERY):
        ahead.predict(imu_a[j], imu_b[j])
    lm_all = np.concatenate([x[9:9 + 3 * Nf].reshape(Nf, 3), np.zeros((16, 3))])
    z_all, _, _ = tw.observe(ahead.x[:9], lm_all[:Nf])
    in_fov = np.flatnonzero((np.abs(z_all[:, 0]) < 0.7) & (np.abs(z_all[:, 1]) < 0.45))
    sel_mapped = np.sort(frng.choice(in_fov, size=min(12, in_fov.size), replace=False))
    zh = z_all[sel_mapped]
    k_m = len(sel_mapped)
    y = np.zeros((Ltot, 3))
    y[:, 2] = 10.0
    y[sel_mapped] = zh + frng.normal(size=zh.shape) * np.sqrt(np.diag(np.asarray(R)))
    y[Nf:Nf + 4] = _in_fov_measurements(frng, 4)
    vis = np.zeros(Ltot, bool)
    vis[sel_mapped] = True
    vis[Nf:Nf + 4] = True
    idl = np.arange(Ltot, dtype=np.int32)

    def predictions(est, e, ia, ib):
        return jax.lax.scan(lambda c, ab: (est.propagate(c, ab[0], ab[1]), None), e, (ia, ib))[0]

    def frame_of(est):
        def frame(e, ia, ib, y_, id_, v_):
            return est.correct(predictions(est, e, ia, ib), y_, id_, v_)[0]
        return frame

    frame = frame_of(est)
    fa = (jnp.asarray(imu_a), jnp.asarray(imu_b), jnp.asarray(y), jnp.asarray(idl), jnp.asarray(vis))
    # mapped rows the update used
    rows_matched = int(est.correct(predictions(est, fresh(e0), *fa[:2]), *fa[2:])[1].dof) // 3
    t_call = _median_call(jax.jit(frame, donate_argnums=0), lambda: (fresh(e0),) + fa, calls)
    t_scan = _median_call(looped(frame), lambda: (e0,) + fa, max(5, calls // 10)) / reps
    # the same frame with the factored Joseph form (Config.joseph=True)
    frame_jos = frame_of(sys3d.make_estimator(cfg._replace(joseph=True), noise))
    t_call_jos = _median_call(jax.jit(frame_jos, donate_argnums=0), lambda: (fresh(e0),) + fa, calls)
    t_scan_jos = _median_call(looped(frame_jos), lambda: (e0,) + fa, max(5, calls // 10)) / reps
    twin = twin_from(x, P, active, ids, cap)

    def np_frame(t):
        for j in range(LIDAR_EVERY):
            t.predict(imu_a[j], imu_b[j])
        t.correct(y, idl, vis)

    t_np = _median_np(np_frame, lambda: (twin.copy(),), calls)
    twin_j = twin_from(x, P, active, ids, cap, joseph=True)
    t_np_jos = _median_np(np_frame, lambda: (twin_j.copy(),), calls)
    # The floor (issue 19): one n²·m product, n the mapped state, m the mapped rows' scalars.
    n_f, m_f = 9 + 3 * Nf, 3 * k_m
    floor_s, floor_flops = _matmul_floor(n_f, m_f)
    study["frame"] = {"mapped": Nf, "capacity": cap, "observed_mapped": k_m, "observed_new": 4,
                      "rows_matched": rows_matched,
                      "max_obs": 16, "predictions": LIDAR_EVERY, "jax_call_s": t_call, "jax_scan_s": t_scan,
                      "jax_call_joseph_form_s": t_call_jos, "jax_scan_joseph_form_s": t_scan_jos,
                      "numpy_s": t_np, "numpy_joseph_form_s": t_np_jos, "floor": {
                          "what": f"one ({n_f}, {m_f}) @ ({m_f}, {n_f}) float64 product, jitted, median",
                          "flops": floor_flops, "s": floor_s, "gflops": floor_flops / floor_s / 1e9,
                          "fraction_call": floor_s / t_call, "fraction_scan": floor_s / t_scan}}
    fparams = {"mapped": Nf, "capacity": cap, "observed_mapped": k_m, "observed_new": 4,
               "predictions": LIDAR_EVERY, "max_obs": 16}
    for mode, t in (("call", t_call), ("scan", t_scan)):
        results.append(_row(f"frame/{mode} N={Nf}", fparams, t, "numpy twin (1 call)", t_np))
    for mode, t in (("call", t_call_jos), ("scan", t_scan_jos)):
        results.append(_row(f"frame/{mode} N={Nf} Joseph form (joseph=True)", fparams, t,
                            "numpy twin, Joseph form (1 call)", t_np_jos))
    out["study"] = study
    out["targets"].append({"name": f"frame step (10 predicts + update + registration), {Nf} mapped, "
                                   f"one jitted call, default form P − K S Kᵀ (the floor's product: "
                                   f"{floor_s * 1e3:.3g} ms, {floor_s / t_call:.0%} of it)",
                           "target": f"<= {TARGETS['frame_step_call_s'] * 1e3:g} ms",
                           "value_ms": t_call * 1e3, "met": bool(t_call <= TARGETS["frame_step_call_s"])})
    out["targets"].append({"name": f"the same frame with the factored Joseph form "
                                   f"(Config.joseph=True; {floor_s / t_call_jos:.0%} of the floor)",
                           "target": f"<= {TARGETS['frame_step_call_s'] * 1e3:g} ms",
                           "value_ms": t_call_jos * 1e3,
                           "met": bool(t_call_jos <= TARGETS["frame_step_call_s"])})

    if args.plots is not None:
        out["plots"] = [_plot_study(study, args.plots)]


def _plot_study(study, directory):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    panels = (("predict", "mapped", "prediction vs mapped landmarks", "mapped landmarks (capacity)"),
              ("update", "observed", "update vs observed mapped landmarks", "observed mapped landmarks"),
              ("register", "observed", "registration vs observed new landmarks", "observed new landmarks"))
    for ax, (key, xk, title, xl) in zip(axes, panels):
        rows = study[key]
        xs = [r[xk] for r in rows]
        for col, lab, mk in (("jax_call_s", "jaxslam, jitted call", "o-"),
                             ("jax_scan_s", "jaxslam, inside scan", "s-"),
                             ("numpy_s", "NumPy twin", "^--")):
            ax.plot(xs, [r[col] * 1e6 for r in rows], mk, label=lab)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(xl)
        ax.set_ylabel("time per operation [µs]")
        ax.set_yscale("log")
        if key == "predict":
            ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fr = study.get("frame")
    if fr:
        fig.suptitle(f"Paper 000 Fig. 12 study (float64, CPU). Full frame at {fr['mapped']} mapped: "
                     f"jaxslam {fr['jax_call_s'] * 1e3:.3g} ms/call, {fr['jax_scan_s'] * 1e3:.3g} ms in scan; "
                     f"NumPy {fr['numpy_s'] * 1e3:.3g} ms", fontsize=9)
    fig.tight_layout()
    from jaxslam.files import atomic_write

    try:  # atomic: an interrupted run leaves the previous figure, not half a PNG
        path = atomic_write(d / "bench_ekfslam_fig12.png", lambda f: fig.savefig(f, dpi=120, format="png"),
                            mode="wb")
    finally:
        plt.close(fig)
    return str(path)


# ---------------------------------------------------------------------------
# Part b: full run
# ---------------------------------------------------------------------------

#: the full runs' jaxslam rows: name -> ``Config.joseph`` (the default form first)
FORMS = {"jaxslam": False, "jaxslam-joseph-form": True}


def _run_twin(tw, log, noise, cap, active_block=False, joseph=False):
    return tw.run_log(noise, log["s0"], log["imu"], log["y"], log["ids"], log["visible"],
                      log["lidar_every"], capacity=cap, max_obs=16, dt=log["dt"], g=G,
                      active_block=active_block, joseph=joseph)


def _get_log(args):
    log, note = None, None
    if args.log == "sim":
        try:
            log = sim_log(args.duration, args.seed)
        except Exception as e:  # the closed loop needs the controller; say why we fell back
            note = f"closed-loop log failed ({type(e).__name__}: {e}); used the synthetic log"
    if log is None:
        log = synthetic_log(args.duration, args.seed)
    return log, note


def run_full(args, noise, results, out, threads_label):
    """Whole-flight ``ekf_slam_3d.run`` vs the NumPy twin, in this process."""
    import jax
    import jax.numpy as jnp

    import numpy_ekfslam3d as tw
    from jaxslam.systems import ekf_slam_3d as sys3d

    log, log_note = _get_log(args)
    caps = int_list(args.capacities, "--capacities")
    F = log["visible"].shape[0]
    inputs = tuple(jnp.asarray(log[k]) for k in ("s0", "imu", "y", "visible"))
    ids = jnp.asarray(log["ids"])
    rows, kept = [], {}
    for cap in caps:
        _progress(f"full run: capacity {cap} ({threads_label})")
        cfg = sys3d.Config(mode="unknown", capacity=cap, max_obs=16)

        def engine(s0, imu, y, vis, cfg=cfg):
            res = sys3d.run(sys3d.Log(s0=s0, imu=imu, y=y, visible=vis, ids=ids), cfg, noise)
            return res.final.slam.x, res.final.slam.P, res.means, res.frames.n_active, res.frames.dof

        runners = {name: jax.jit(functools.partial(engine, cfg=cfg._replace(joseph=j)))
                   for name, j in FORMS.items()}
        compiled = {}
        for name, fn in runners.items():
            t0 = time.perf_counter()
            compiled[name] = (jax.block_until_ready(fn(*inputs)), time.perf_counter() - t0)
        # Repeats interleaved (both forms, the twin in both forms, the active-block twin), so a change
        # of the machine's load hits every method alike and the speedups compare like with like.
        ts = {name: [] for name in runners}
        tt = {j: [] for j in (False, True)}  # the twin in each covariance form
        ta = []
        _run_twin(tw, log, noise, cap)  # one untimed warm-up call of the twin, as the jitted runs had theirs
        for _ in range(args.repeats):
            for name, fn in runners.items():
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*inputs))
                ts[name].append(time.perf_counter() - t0)
            for j in (False, True):
                t0 = time.perf_counter()
                twin_out = _run_twin(tw, log, noise, cap, joseph=j)
                tt[j].append(time.perf_counter() - t0)
                if not j:
                    flt, means = twin_out
            t0 = time.perf_counter()  # the twin doing the same leading-active-block work
            _run_twin(tw, log, noise, cap, active_block=True)
            ta.append(time.perf_counter() - t0)
        timed = {name: (float(np.median(ts[name])), float(np.min(ts[name])), compiled[name][1], compiled[name][0])
                 for name in runners}
        t_twin = {j: float(np.median(v)) for j, v in tt.items()}
        row = {"capacity": cap, "numpy_s": t_twin[False], "numpy_min_s": float(np.min(tt[False])),
               "numpy_joseph_form_s": t_twin[True],
               "numpy_active_block_s": float(np.median(ta)),
               "mapped_final": int(flt.active.sum()), "overflow": int(flt.overflow)}
        params = {"capacity": cap, "duration_s": args.duration, "imu_steps": F * log["lidar_every"],
                  "frames": F, "max_obs": 16, "mode": "unknown", "log": log["source"],
                  "openblas_threads": threads_label}
        for name, (med, mn, comp, res) in timed.items():
            ref = t_twin[FORMS[name]]  # the twin doing the same form
            agree = {"max_abs_means": float(np.max(np.abs(np.asarray(res[2]) - means))),
                     "max_abs_x": float(np.max(np.abs(np.asarray(res[0]) - flt.x))),
                     "max_abs_P": float(np.max(np.abs(np.asarray(res[1]) - flt.P)))}
            # FLOP floor of the run: per frame one correction of the mapped state (2 n² m),
            # per IMU step the robot rows F P_rl (2 n_r² n) — n = 9 + 3·(mapped landmarks)
            n_act = np.asarray(res[3], float)
            n_st = 9.0 + 3.0 * n_act
            flops = float(np.sum(2.0 * n_st ** 2 * np.asarray(res[4], float))
                          + np.sum(2.0 * 81.0 * n_st) * log["lidar_every"])
            row[name] = {"median_s": med, "min_s": mn, "compile_s": comp, "speedup": ref / med,
                         "speedup_vs_active_block_twin": row["numpy_active_block_s"] / med,
                         "floor_flops": flops, "agreement_with_twin": agree}
            results.append(_row(f"full run cap={cap} {name} [OpenBLAS {threads_label}]", params, med,
                                f"numpy twin{', Joseph form' if FORMS[name] else ''}, OpenBLAS "
                                f"{threads_label}", ref, jaxslam_compile_s=comp,
                                implementation="jaxslam.systems.ekf_slam_3d.run"
                                + (", Config(joseph=True)" if FORMS[name] else ""), agreement=agree))
        rows.append(row)
        kept[cap] = runners["jaxslam"]
    full = {"log": log["source"], "log_note": log_note, "duration_s": args.duration,
            "visible_per_frame_mean": float(log["visible"].sum(1).mean()),
            "openblas_threads": threads_label, "rows": rows}
    if 64 in kept and 256 in kept:
        full["capacity_pairs"] = _paired_times(kept[64], kept[256], inputs, args.pairs)
    return full


def _paired_times(fa, fb, inputs, pairs):
    """Times of ``fa`` and ``fb`` (compiled, warm) called alternately ``pairs`` times on the
    same inputs, and the ratio of their medians.  Alternating calls see the same machine load,
    so the ratio does not move with load drifts between two separate blocks of calls (the
    per-capacity medians above are minutes apart, the NumPy twin's runs between them)."""
    import jax

    ta, tb = [], []
    for _ in range(pairs):
        for f, ts in ((fa, ta), (fb, tb)):
            t0 = time.perf_counter()
            jax.block_until_ready(f(*inputs))
            ts.append(time.perf_counter() - t0)
    return {"what": "capacity 64 and 256 (ekf_slam_3d.run, default form) called alternately",
            "pairs": pairs, "times_64_s": ta, "times_256_s": tb,
            "median_64_s": float(np.median(ta)), "median_256_s": float(np.median(tb)),
            "ratio": float(np.median(tb) / np.median(ta))}


def _full_targets(full, out, duration):
    by_cap = {r["capacity"]: r for r in full["rows"]}
    if "capacity_pairs" in full:
        pairs = full["capacity_pairs"]
        ratio = pairs["ratio"]
        blocks = by_cap[256]["jaxslam"]["median_s"] / by_cap[64]["jaxslam"]["median_s"]
        tgt = TARGETS["capacity_ratio_256_64"]
        out["targets"].append({"name": f"full {duration:g} s run, capacity 256 vs 64 (the same log, "
                                       f"{by_cap[256]['mapped_final']} mapped), time ratio of "
                                       f"{pairs['pairs']} alternating calls ({full['openblas_threads']})",
                               "target": f"<= {tgt:g}x", "value": ratio, "met": bool(ratio <= tgt),
                               "ratio_of_the_separate_medians": blocks})
    for r in full["rows"]:
        tgt = TARGETS["full_speedup"].get(r["capacity"])
        if tgt is None:
            continue
        for name, joseph in FORMS.items():
            sp = r[name]["speedup"]
            what = "ekf_slam_3d.run" + (" (joseph=True)" if joseph else "")
            out["targets"].append({"name": f"full {duration:g} s run, capacity {r['capacity']}, {what} "
                                           f"speedup vs NumPy ({full['openblas_threads']})",
                                   "target": f">= {tgt:g}x", "value": sp, "met": bool(sp >= tgt)})


# ---------------------------------------------------------------------------
# Part c: Monte Carlo throughput
# ---------------------------------------------------------------------------

def run_mc(args, results, out):
    import jax
    import jax.numpy as jnp

    from jaxslam.sim import monte_carlo
    from jaxslam.sim.scenarios import ekfslam3d

    opts = _scenario_options(args.mc_duration, args.mc_capacity)
    one_run = ekfslam3d.build(opts, "unknown", jnp.float64)[0]
    single = jax.jit(one_run)
    batched = {}
    rows = []
    Ms = int_list(args.mc_runs, "--mc-runs")
    keys_all = monte_carlo.keys_for(args.seed, max(Ms))
    _progress("monte carlo: compiling the single run")
    t0 = time.perf_counter()
    jax.block_until_ready(single(keys_all[0]))
    compile_single = time.perf_counter() - t0
    for M in Ms:
        chunk = min(M, args.mc_chunk)
        if chunk not in batched:
            _progress(f"monte carlo: compiling vmap over {chunk} runs")
            f = jax.jit(jax.vmap(one_run))
            t0 = time.perf_counter()
            jax.block_until_ready(f(keys_all[:chunk]))
            batched[chunk] = (f, time.perf_counter() - t0)
        f, comp = batched[chunk]
        _progress(f"monte carlo: M = {M}")
        n_chunks = math.ceil(M / chunk)
        keys = keys_all[:M]
        if n_chunks * chunk > M:
            keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], n_chunks * chunk - M, axis=0)])
        n_seq = min(M, args.mc_seq_max)
        threads = monte_carlo.default_threads()
        monte_carlo.run(one_run, args.seed, min(M, threads), cpu_batching="loop", threads=threads)  # compile
        seq_s, vmap_s, loop_s = [], [], []
        for _ in range(max(1, min(args.repeats, 3))):  # interleaved, so load changes hit all three
            t0 = time.perf_counter()
            for i in range(n_seq):
                jax.block_until_ready(single(keys_all[i]))
            seq_s.append((time.perf_counter() - t0) / n_seq * M)
            t0 = time.perf_counter()
            for c in range(n_chunks):
                jax.block_until_ready(f(keys[c * chunk:(c + 1) * chunk]))
            vmap_s.append(time.perf_counter() - t0)
            loop_s.append(monte_carlo.run(one_run, args.seed, M, cpu_batching="loop", threads=threads).run_s)
        t_seq, t_vmap, t_loop = (float(np.median(v)) for v in (seq_s, vmap_s, loop_s))
        rows.append({"runs": M, "chunk": chunk, "vmap_s": t_vmap, "vmap_runs_per_s": M / t_vmap,
                     "vmap_compile_s": comp, "sequential_s": t_seq, "sequential_runs_per_s": M / t_seq,
                     "sequential_timed_calls": n_seq, "speedup": t_seq / t_vmap, "repeats": len(seq_s)})
        results.append(_row(f"monte carlo M={M}", {"runs": M, "chunk": chunk, "duration_s": args.mc_duration,
                                                   "capacity": args.mc_capacity},
                            t_vmap, "M sequential calls of the jitted single run", t_seq,
                            runs_per_s=M / t_vmap))
        rows[-1].update(loop_threads=threads, loop_threads_s=t_loop, loop_threads_speedup=t_seq / t_loop)
        results.append(_row(f"monte carlo M={M}, runner's loop on {threads} threads",
                            {"runs": M, "threads": threads, "duration_s": args.mc_duration,
                             "capacity": args.mc_capacity},
                            t_loop, "M sequential calls of the jitted single run", t_seq,
                            runs_per_s=M / t_loop))
    out["monte_carlo"] = {"duration_s": args.mc_duration, "capacity": args.mc_capacity,
                          "note": (f"each run: a {args.mc_duration:g} s closed-loop ekfslam3d-unknown "
                                   "flight (DF-LQR on the estimate, EKF-SLAM, metrics) with the "
                                   "scenario's defaults; shorter than the paper's 50 s to keep the "
                                   "benchmark quick (--mc-duration); the sequential time is measured "
                                   "over 'sequential_timed_calls' calls and scaled to M"),
                          "compile_single_s": compile_single, "rows": rows}
    by_m = {r["runs"]: r for r in rows}
    if 100 in by_m:
        sp = by_m[100]["speedup"]
        out["targets"].append({"name": "Monte Carlo vmap speedup at M = 100",
                               "target": f">= {TARGETS['mc_speedup_at_100']:g}x", "value": sp,
                               "met": bool(sp >= TARGETS["mc_speedup_at_100"])})
        sp = by_m[100]["loop_threads_speedup"]
        out["targets"].append({"name": "Monte Carlo speedup at M = 100, the runner's loop on "
                                       f"{by_m[100]['loop_threads']} threads (what jaxslam run does on a CPU)",
                               "target": f">= {TARGETS['mc_speedup_at_100']:g}x", "value": sp,
                               "met": bool(sp >= TARGETS["mc_speedup_at_100"])})
    if 100 in by_m and 1000 in by_m:
        ratio = by_m[1000]["vmap_runs_per_s"] / by_m[100]["vmap_runs_per_s"]
        out["targets"].append({"name": "Monte Carlo runs/s at M = 1000 relative to M = 100",
                               "target": ">= 0.9 (no drop)", "value": ratio, "met": bool(ratio >= 0.9)})


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------

_OPTION_DESTS = ("parts", "seed", "calls", "scan_reps", "study_maps", "study_obs", "study_map_size",
                 "frame_mapped", "capacities", "duration", "repeats", "pairs", "log", "mc_runs", "mc_duration",
                 "mc_capacity", "mc_chunk", "mc_seq_max", "plots")


def _progress(msg):
    print(f"[bench ekfslam] {msg}", file=sys.stderr, flush=True)


def _print_targets(out):
    print("targets:")
    for t in out["targets"]:
        val = t.get("value_ms", t.get("value"))
        unit = " ms" if "value_ms" in t else "x"
        print(f"  [{'met' if t['met'] else 'MISSED'}] {t['name']}: {val:.3g}{unit} (target {t['target']})")


def _run_parts(args, parts, threads_label):
    """All selected parts in this process (OpenBLAS threads as they are here)."""
    noise = _filter_noise()
    results, out = [], {"targets": []}
    load = {"before": list(os.getloadavg())}
    if "study" in parts:
        run_study(args, noise, results, out)
    if "full" in parts:
        full = run_full(args, noise, results, out, threads_label)
        out["full_run"] = full
        _full_targets(full, out, args.duration)
    if "mc" in parts:
        try:
            run_mc(args, results, out)
        except Exception as e:  # closed loop unavailable: record it, keep the other parts
            out["monte_carlo"] = {"error": f"{type(e).__name__}: {e}"}
    load["after"] = list(os.getloadavg())
    out["load_average"] = load
    return results, out


def _spawn(args, parts, threads, label):
    """Run the parts in a fresh process with OPENBLAS_NUM_THREADS=threads (None: unset).

    The variable acts only before NumPy loads OpenBLAS, hence a fresh process.
    Returns (results, out).
    """
    import jaxslam

    root = str(pathlib.Path(jaxslam.__file__).resolve().parents[1])
    with tempfile.TemporaryDirectory() as td:
        a_path, o_path = os.path.join(td, "args.json"), os.path.join(td, "out.json")
        opts = {k: getattr(args, k) for k in _OPTION_DESTS}
        opts.update(parts=",".join(sorted(parts)), _label=label)
        if "study" not in parts:
            opts["plots"] = None  # the figure is the study's (the default-threads rerun is full only)
        with open(a_path, "w") as fh:
            json.dump(opts, fh)
        env = dict(os.environ)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.pop(var, None)
            if threads is not None:
                env[var] = str(threads)
        env["PYTHONPATH"] = os.pathsep.join([root, str(HERE), str(HERE.parent / "tests" / "oracles")] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        _progress(f"running {', '.join(sorted(parts))} in a fresh process ({label})")
        cmd = [sys.executable, str(HERE / "bench_ekfslam.py"), "--child", a_path, o_path]
        proc = subprocess.run(cmd, env=env, stdout=sys.stderr)
        res = None
        if os.path.exists(o_path):
            with open(o_path) as fh:
                res = json.load(fh)
        if isinstance(res, dict) and "input_error" in res:  # the child's bad input: the CLI's exit 2
            from jaxslam.errors import InputError

            raise InputError(res["input_error"])
        if proc.returncode != 0 or res is None:
            raise subprocess.CalledProcessError(proc.returncode, cmd)
    return res["results"], res["out"]


def run(args):
    """Run the selected parts; returns the bench JSON dict (see module docstring).

    OpenBLAS threads: jaxlib's LAPACK kernels (Cholesky, triangular solves) run on
    the same OpenBLAS as NumPy, so its thread count changes both sides.  Every part
    is measured with OpenBLAS on 1 thread (this process when it already is — the
    ``jaxslam`` command pins it unless the user set the variable — or threadpoolctl
    is installed, else a fresh process), and the full run (jaxslam vs NumPy) is
    repeated with OpenBLAS's default threads for the record.
    """
    import jax

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)  # standalone use; the CLI has set it already
    from jaxslam import files
    from jaxslam.errors import InputError

    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    if not parts:
        raise InputError(f"--parts: no part given (got {args.parts!r}); choose from study, full, mc")
    unknown = parts - {"study", "full", "mc"}
    if unknown:
        raise InputError(f"--parts: unknown part(s) {sorted(unknown)}; choose from study, full, mc")
    for flag, text in (("--study-maps", args.study_maps), ("--study-obs", args.study_obs),
                       ("--capacities", args.capacities), ("--mc-runs", args.mc_runs)):
        int_list(text, flag)  # every list checked before anything runs (the mc part records its errors)
    for flag, part, value in (("--duration", "full", args.duration),
                              ("--mc-duration", "mc", args.mc_duration)):
        # at least one LiDAR frame (a negative or zero duration crashed the full run with an
        # internal error, and the mc part recorded the scenario's refusal as its result)
        if part in parts:
            lidar_frames(value, flag, DT, LIDAR_EVERY)
    if args.plots is not None:  # checked (and created) before anything runs, not after the study
        if "study" not in parts:
            raise InputError(f"--plots: the figure is the study part's; add study to --parts "
                             f"(got {args.parts!r}) or drop --plots")
        files.prepare_dir("--plots", args.plots)
    if getattr(args, "_label", None):  # a child started by _spawn
        results, out = _run_parts(args, parts, args._label)
        return {"results": results, **out}
    env_threads = os.environ.get("OPENBLAS_NUM_THREADS")
    try:
        import threadpoolctl
    except ImportError:
        threadpoolctl = None
    pinned = "1 thread"
    if env_threads == "1":
        results, out = _run_parts(args, parts, pinned)
        out["openblas_pinning"] = "OPENBLAS_NUM_THREADS=1 in this process"
        default = ("fresh process, OPENBLAS_NUM_THREADS unset", None)
    elif threadpoolctl is not None:
        with threadpoolctl.threadpool_limits(limits=1, user_api="blas"):
            results, out = _run_parts(args, parts, pinned)
        out["openblas_pinning"] = "threadpoolctl.threadpool_limits(1, 'blas')"
        default = ("this process, OPENBLAS_NUM_THREADS=" + (env_threads or "unset"), "here")
    else:
        results, out = _spawn(args, parts, 1, pinned)
        out["openblas_pinning"] = "fresh process with OPENBLAS_NUM_THREADS=1 (threadpoolctl not installed)"
        default = ("this process, OPENBLAS_NUM_THREADS=" + (env_threads or "unset"), "here")
    if "full" in parts:
        label = f"default threads ({default[0]})"
        if default[1] == "here":
            out["full_run_default_threads"] = run_full(args, _filter_noise(), results, out, label)
        else:
            res_d, out_d = _spawn(args, {"full"}, None, label)
            results += res_d
            out["full_run_default_threads"] = out_d.get("full_run")
    out.update({
        "dtype": "float64", "parts": sorted(parts),
        "notes": ["jaxslam_s / reference_s are medians after warm-up; speedup = reference_s / jaxslam_s",
                  "'call' rows: one jitted call per operation (dispatch included, state donated); "
                  "'scan' rows: the operation repeated inside one fori_loop, per-iteration cost",
                  "the NumPy twin processes only the measurements present; jaxslam's update in the "
                  "filter processes max_obs / 2 or max_obs rows (static shapes, masked; active_only)",
                  "timings depend on the machine's load: see load_average"]})
    _print_targets(out)
    return {"results": results, **out}


def _child_main(a_path, o_path):
    import argparse

    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    from jaxslam.errors import InputError

    with open(a_path) as fh:
        args = argparse.Namespace(**json.load(fh))
    try:
        res = run(args)
    except InputError as e:  # handed to the parent, which raises it (the CLI's exit 2, one line)
        with open(o_path, "w") as fh:
            json.dump({"input_error": str(e)}, fh)
        sys.exit(2)
    with open(o_path, "w") as fh:
        json.dump({"results": res["results"], "out": {k: v for k, v in res.items() if k != "results"}}, fh)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child_main(sys.argv[2], sys.argv[3])
    else:
        sys.exit("run this benchmark through the CLI: python -m jaxslam bench ekfslam [options]")
