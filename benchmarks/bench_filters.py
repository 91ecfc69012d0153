"""Filter family benchmark: EKF, UKF (unscented, cubature), iterated EKF, RTS and fixed-lag
smoothing, and the iterated smoother, in one run on one model.

Run with ``python -m jaxslam bench filters [--json benchmarks/results/filters.json] [options]``.

Model: a 4-state constant-velocity target seen by range and bearing from a beacon
(``T`` steps, default 1000; the same model as ``tests/filters/test_smoother.py``), float64.
Each case is one jitted whole run (``lax.scan``), timed as the median of ``--repeats``
calls after a warm-up call, ``block_until_ready`` on the outputs; compile time is reported
apart.  Ratios are against the EKF run (``filter_scan``) in the same process:
``rts_pass`` is the backward pass alone over a saved run, ``ekf+rts`` (``ukf+rts``) the run that saves
what the smoother needs plus the pass.  The issue's target: RTS pass ≤ 2× the filter's run.
``numpy_ekf`` is a plain NumPy loop of the same EKF (hand Jacobians) as the outside reference.
``eager_calls``: five of the runs called without the caller's ``jit`` — first call, repeated
call, and the repeated call with the kept program bypassed (what every eager call cost before
``jaxslam.compilation.call_compiled``) — and a Python loop of ``--loop-steps`` (default 50)
eager ``predict`` + ``update`` steps (EKF, UKF, their square-root forms, and the EKF-SLAM
engine's ``predict`` + ``update`` with the beacon as the one landmark of an 8-slot map), and of
a fifth as many ``fastslam.step`` calls (100 particles, the beacon registered at its first
sighting; a fifth, since uncompiled each call took ~1 s and kept its compiled programs: ~280
memory mappings a step, so a few hundred steps reached the system's 65530 and XLA failed with
"Cannot allocate memory"); times are per loop.  Each case starts from empty in-memory caches
(``jax.clear_caches`` and jaxslam's ``compilation.clear_programs``: whatever this process had
compiled is compiled again on its next call).

Which reference a row's ``reference_s`` / ``speedup`` is against: every row's ``reference`` says
it, and ``speedup_vs`` names it in one word — ``"ekf"`` (jaxslam's own EKF run: the speedup is
EKF time / case time, so a slower case reads < 1×) for every case but ``numpy_ekf_loop``,
whose ``"numpy"`` row is the only comparison with NumPy (NumPy loop time / EKF time).  The
NumPy loop gets one untimed warm-up call too; it and the bypassed (uncompiled) eager calls are
timed over max(1, ``--repeats`` // 2) calls, every other case over ``--repeats``.
"""

from __future__ import annotations

import os
import time

import numpy as np
from timing import median_s

DESCRIPTION = ("Filter family on one model: EKF / UKF / cubature / iterated EKF steps, RTS, "
               "fixed-lag and iterated smoothers, against the EKF run and a NumPy EKF loop")

TARGETS = {"rts_pass_vs_filter_max": 2.0}


def add_arguments(parser):
    parser.add_argument("--steps", type=int, default=1000, help="time steps T (default 1000)")
    parser.add_argument("--repeats", type=int, default=7,
                        help="timed repeats (median; default 7; the NumPy loop and the uncompiled eager "
                             "calls use max(1, REPEATS // 2))")
    parser.add_argument("--lag", type=int, default=20, help="fixed-lag smoother lag (default 20)")
    parser.add_argument("--iters", type=int, default=5, help="iterated smoother iterations (default 5)")
    parser.add_argument("--eager", choices=("both", "off", "none"), default="both",
                        help="eager-call measurements: with the persistent cache as this process has it "
                             "and off (both, default), off only, or none")
    parser.add_argument("--loop-steps", type=int, default=50,
                        help="steps of the eager step loops: the EKF, UKF and EKF-SLAM loops run this "
                             "many (at most --steps), the FastSLAM loop a fifth of it, at least 1 "
                             "(default 50)")


DT = 0.1
F = np.array([[1, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1]], float)
G = np.array([[0.5 * DT**2, 0], [0, 0.5 * DT**2], [DT, 0], [0, DT]], float)
Q = 0.05 * G @ G.T + 1e-6 * np.eye(4)
R = np.diag([0.05**2, 0.02**2])
P0 = np.diag([1.0, 1.0, 0.5, 0.5])
X0 = np.array([0.0, 0.0, 1.0, -0.5])
BEACON = np.array([10.0, 8.0])


def _simulate(T, seed=0):
    rng = np.random.default_rng(seed)
    us = rng.normal(0, 0.5, (T, 2))
    x = X0.copy()
    zs = []
    for t in range(T):
        x = F @ x + G @ us[t] + rng.multivariate_normal(np.zeros(4), Q)
        d = x[:2] - BEACON
        zs.append([np.hypot(*d), np.arctan2(d[1], d[0])] + rng.normal(0, [0.05, 0.02]))
    return us, np.array(zs)


def _numpy_ekf(us, zs):
    x, P = X0.copy(), P0.copy()
    out = np.empty((len(zs), 4))
    for t in range(len(zs)):
        x = F @ x + G @ us[t]
        P = F @ P @ F.T + Q
        d = x[:2] - BEACON
        r2 = d @ d
        r = np.sqrt(r2)
        H = np.array([[d[0] / r, d[1] / r, 0, 0], [-d[1] / r2, d[0] / r2, 0, 0]])
        nu = zs[t] - np.array([r, np.arctan2(d[1], d[0])])
        nu[1] = (nu[1] + np.pi) % (2 * np.pi) - np.pi
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ nu
        A = np.eye(4) - K @ H
        P = A @ P @ A.T + K @ R @ K.T
        out[t] = x
    return out


def _eager_calls(cases, repeats, which="both"):
    """The same runs called eagerly (no jit of the caller's): the first call (trace + compile),
    a repeated call (the program :func:`jaxslam.compilation.call_compiled` kept) and, as the
    same-process reference, a repeated call with that program bypassed — the uncompiled scan
    that every eager call paid before (JAX re-traces and re-compiles a scan it is handed
    afresh).  Twice: with the persistent compilation cache as this process has it (the CLI
    switches it on: the uncompiled call then loads its scan from disk) and with it off (a
    script that imports the library without ``configure_process``).

    Each case's first call starts from empty in-memory caches, as in a fresh process: JAX's
    own in-memory caches (traces, lowerings, executables, the one-operation programs of eager
    code) must be emptied with ``jax.clear_caches``, which also empties the caller's: JAX has
    no way to set them aside, and without it a first call would reuse what the cases before it
    (or the other pass over the cache modes) compiled, so its time would depend on their
    order; jaxslam's kept programs are emptied too (:func:`jaxslam.compilation.clear_programs`).
    What that costs the caller: its jitted functions and kept runs trace and compile again on
    their next call (the same results); ``lower().compile()`` executables it holds are kept."""
    from unittest import mock

    import jax

    from jaxslam import compilation

    rows = []
    folder = compilation.enabled_dir()
    modes = ([True] if folder is not None and which == "both" else []) + ([False] if which != "none" else [])
    if not modes or not cases:
        return rows
    try:
        for cache_on in modes:
            if not cache_on:
                compilation.disable_cache()
            for name, fn in cases.items():
                compilation.clear_programs()
                jax.clear_caches()
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                first = time.perf_counter() - t0
                rep = median_s(lambda: jax.block_until_ready(fn()), repeats)
                with mock.patch.object(compilation, "at_top_level", lambda: False):
                    jax.block_until_ready(fn())
                    unc = median_s(lambda: jax.block_until_ready(fn()), max(1, repeats // 2))
                rows.append({"case": name, "persistent_cache": cache_on, "first_call_s": first, "repeat_s": rep,
                             "repeat_uncompiled_s": unc, "speedup": unc / rep,
                             "reference": "the same eager call with the kept program bypassed"})
    finally:
        if folder is not None:
            compilation.enable_cache(folder)
    return rows


def run(args):
    import jax
    import jax.numpy as jnp

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)
    from jaxslam.errors import InputError
    from jaxslam.filters import ekf, ekf_slam, fastslam, gaussian, smoother, sqrt_ekf, sqrt_ukf, ukf

    if args.steps < 2:
        raise InputError(f"--steps: must be >= 2, got {args.steps}")
    if args.repeats < 1:
        raise InputError(f"--repeats: must be >= 1, got {args.repeats}")
    loop_steps = getattr(args, "loop_steps", 50)
    if loop_steps < 1:
        raise InputError(f"--loop-steps: must be >= 1, got {loop_steps}")
    T = int(args.steps)
    n_loop, n_fs = min(loop_steps, T), max(1, min(loop_steps, T) // 5)
    us_np, zs_np = _simulate(T)
    us, zs = jnp.asarray(us_np), jnp.asarray(zs_np)
    Fj, Gj, Bj = jnp.asarray(F), jnp.asarray(G), jnp.asarray(BEACON)

    def f(x, u):
        return Fj @ x + Gj @ u

    def h(x):
        d = x[:2] - Bj
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    res = ekf.angle_residual([False, True])
    load = {"before": list(os.getloadavg())}

    cases = {
        "ekf": lambda: ekf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res).means,
        "iterated_ekf_3": lambda: ekf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res,
                                                  num_iter=3).means,
        "ukf": lambda: ukf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res).means,
        "cubature": lambda: ukf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res,
                                            points=ukf.cubature()).means,
        "ekf_saving_for_smoother": lambda: ekf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res,
                                                           save_smoother=True),
        "ekf+rts": lambda: smoother.rts(ekf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res,
                                                        save_smoother=True), save_cov=False).means,
        "ukf+rts": lambda: smoother.rts(ukf.filter_scan(f, h, X0, P0, us, zs, None, Q, R, residual=res,
                                                        save_smoother=True), save_cov=False).means,
        f"fixed_lag_{args.lag}": lambda: smoother.fixed_lag(ekf.make_filter(f, h, residual=res), X0, P0, us,
                                                            zs, None, Q, R, lag=args.lag).means,
        f"iterated_smoother_{args.iters}": lambda: smoother.iterated(
            f, h, X0, P0, us, zs, None, Q, R, residual=res, num_iter=args.iters).means,
    }
    results, times = [], {}
    saved = None
    for name, fn in cases.items():
        jf = jax.jit(fn)
        t0 = time.perf_counter()
        out = jax.block_until_ready(jf())
        comp = time.perf_counter() - t0
        if name == "ekf_saving_for_smoother":
            saved = out
        times[name] = median_s(lambda: jax.block_until_ready(jf()), args.repeats)
        results.append({"case": name, "params": {"T": T}, "jaxslam_s": times[name],
                        "compile_s": comp})
    rts_pass = jax.jit(lambda p: smoother.rts(p, save_cov=False).means)
    jax.block_until_ready(rts_pass(saved))
    times["rts_pass"] = median_s(lambda: jax.block_until_ready(rts_pass(saved)), args.repeats)
    results.append({"case": "rts_pass", "params": {"T": T, "what": "backward pass over a saved run"},
                    "jaxslam_s": times["rts_pass"]})
    def step_loop(mod):  # the filterpy-style loop: one eager predict and update per step
        if mod in (sqrt_ekf, sqrt_ukf):
            st = sqrt_ekf.SqrtGaussian(jnp.asarray(X0), jnp.asarray(np.linalg.cholesky(P0)))
        else:
            st = gaussian.Gaussian(jnp.asarray(X0), jnp.asarray(P0))
        for t in range(n_loop):
            st = mod.predict(st, f, us[t], Q)
            st, _ = mod.update(st, zs[t], h, R, residual=res)
        return st.mean

    # the same loop on the EKF-SLAM engine: the beacon as the one landmark of an 8-slot map,
    # preloaded at its position with a small covariance
    def h_lm(x, lm, p=None):  # h with the beacon as a landmark of the map
        d = x[:2] - lm
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    slam_model = ekf_slam.SlamModel(robot_dim=4, lm_dim=2, meas_dim=2, motion=lambda s, u, p=None: f(s, u),
                                    observe=h_lm, residual=res)

    def slam_step_loop():
        st = ekf_slam.init(jnp.asarray(X0), jnp.asarray(P0), 8, 2)
        st = ekf_slam.preload(st, slam_model, Bj[None], 1e-4 * jnp.eye(2)[None], ids=jnp.zeros(1, jnp.int32))
        one, seen = jnp.zeros(1, jnp.int32), jnp.ones(1, bool)
        for t in range(n_loop):
            st = ekf_slam.predict(st, slam_model, us[t], Q)
            st, _ = ekf_slam.update(st, slam_model, zs[t][None], one, seen, R)
        return st.x

    # and on the FastSLAM core: 100 particles, the target's position drawn around the motion
    # model, the beacon registered from its first sighting (slot 0)
    def sample(pose, aux, key, u):
        return f(pose, u) + jnp.concatenate([0.05 * jax.random.normal(key, (2,), pose.dtype), jnp.zeros(2)]), aux

    fmodel = fastslam.LandmarkModel(2, 2, h_lm, lambda x, z, p=None: x[:2] - z[0] * jnp.stack(
        [jnp.cos(z[1]), jnp.sin(z[1])]), residual=res)

    def fastslam_step_loop():  # a fifth: uncompiled, each step took ~1 s and kept its programs
        p = fastslam.init(jnp.asarray(X0), 100, 8, 2)
        key = jax.random.PRNGKey(0)
        zero = jnp.zeros(1, jnp.int32)
        for t in range(n_fs):
            key, k = jax.random.split(key)
            p, _ = fastslam.step(p, k, sample, (us[t],), fmodel, zs[t][None], zero, jnp.ones(1, bool), R,
                                 slot_by_id=True)
        return p.pose

    eager_cases = {k: cases[k] for k in ("ekf", "ukf", "ekf+rts", f"fixed_lag_{args.lag}",
                                         f"iterated_smoother_{args.iters}")}
    eager_cases[f"ekf_step_loop_{n_loop}"] = lambda: step_loop(ekf)
    eager_cases[f"ukf_step_loop_{n_loop}"] = lambda: step_loop(ukf)
    eager_cases[f"sqrt_ekf_step_loop_{n_loop}"] = lambda: step_loop(sqrt_ekf)
    eager_cases[f"sqrt_ukf_step_loop_{n_loop}"] = lambda: step_loop(sqrt_ukf)
    eager_cases[f"ekf_slam_step_loop_{n_loop}"] = slam_step_loop
    eager_cases[f"fastslam_step_loop_{n_fs}"] = fastslam_step_loop
    eager = _eager_calls(eager_cases, args.repeats, getattr(args, "eager", "both"))
    np_means = _numpy_ekf(us_np, zs_np)  # the untimed warm-up call, as every JAX case has one
    t_np = median_s(lambda: _numpy_ekf(us_np, zs_np), max(1, args.repeats // 2))
    ekf_means = np.asarray(jax.jit(cases["ekf"])())
    agree = float(np.max(np.abs(ekf_means - np_means)))
    base = times["ekf"]
    for r in results:
        r["reference"] = "jaxslam ekf.filter_scan (same process; not NumPy)"
        r["reference_s"] = base
        r["speedup"] = base / r["jaxslam_s"]
        r["speedup_vs"] = "ekf"
        r["ratio_to_ekf"] = r["jaxslam_s"] / base
        r["us_per_step"] = 1e6 * r["jaxslam_s"] / T
    results.append({"case": "numpy_ekf_loop", "params": {"T": T}, "jaxslam_s": base,
                    "reference": "NumPy loop, hand Jacobians", "reference_s": t_np,
                    "speedup": t_np / base, "speedup_vs": "numpy", "max_abs_diff_means": agree})
    ratio = times["rts_pass"] / base
    load["after"] = list(os.getloadavg())
    return {"results": results, "eager_calls": eager, "load_average": load,
            "targets": [{"name": "rts_pass_vs_filter", "value": ratio, "target_max": 2.0,
                         "met": ratio <= 2.0}]}
