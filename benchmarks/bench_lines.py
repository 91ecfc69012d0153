"""RANSAC line extraction (paper 004, Algorithm 1, eq. 4.1): time per scan, JAX vs a NumPy twin.

Run with ``python -m jaxslam bench lines [--json benchmarks/results/lines.json] [options]``
(float64: the CLI enables x64 and pins OpenBLAS to one thread unless the user set
``OPENBLAS_NUM_THREADS``; the JSON records the setting).

Parts (``--parts``, default ``ransac,slam``):

``ransac``  ``--scans`` simulated URG-04LX scans (682 beams, ``jaxslam.sensors.laser2d.scan``)
   of a 5 m × 3.5 m room with a 1 m × 0.6 m box in it, random poses, 30 % clutter outliers
   (``--outlier-prob``); lines extracted with the default ``RansacConfig`` (n_hyp = 459 of
   eq. 4.1, 8 rounds).  Timed: the jitted single-scan ``extract_lines`` called once per scan
   (``jax.jit(..., static_argnames="cfg")``), the jitted ``vmap`` over all scans (one call;
   per-scan time = call / scans), and the NumPy twin (``numpy_lines.extract_lines``, vectorised
   over hypotheses, stops at the first failed round) looped over min(scans, ``--twin-max``)
   scans.  Medians over ``--repeats`` after a warm-up call (the twin: over min(``--repeats``, 3)),
   ``block_until_ready`` on every JAX result.  Target: single jitted ≥ 5× faster than the twin per scan.  Agreement: for every
   line with ≥ ``--agree-min`` inliers found by either implementation, the other finds one
   within 2 cm / 0.5° (different RNGs, so the small clutter lines may differ); and the share
   of true walls (≥ 20 true points) each recovers within 2 cm / 0.5°.

``slam``    the line-feature EKF-SLAM of paper 004 Alg. 2 (``lineslam-room`` filter, prior-guided
   matching + RANSAC for new lines + EKF, on ``--slam-duration`` s logs simulated beforehand):
   runs/second of ``jax.jit(jax.vmap(run))`` over M logs vs M sequential calls of the jitted
   single-log ``run`` (timed on min(M, ``--slam-seq-max``) logs and scaled), for every M in
   ``--slam-runs``.  ``--slam-duration`` must exceed one scan period (0.1 s); it is checked
   before any part runs.

``--seed`` takes any seed the CLI accepts, [0, 2**63): the keys derived from it (seed + 1)
are ``timing.prng_key``'s, ``jax.random.PRNGKey`` of seed + 1's 64 bits (two's complement), so
2**63 - 1 + 1 wraps to -2**63 instead of overflowing; every smaller seed keeps its key.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from timing import int_list, median_s, prng_key

DESCRIPTION = ("Paper 004 RANSAC line extraction (Alg. 1, eq. 4.1): per-scan time of jitted single and "
               "vmapped extraction vs a NumPy twin; line-feature SLAM runs/s vmapped vs sequential")

TARGETS = {"single_vs_twin": 5.0}
PARTS = ("ransac", "slam")


def add_arguments(parser):
    """Benchmark options (defaults: well under a minute on 2 CPU cores)."""
    parser.add_argument("--parts", default="ransac,slam", help="comma list: ransac, slam (default both)")
    parser.add_argument("--scans", type=int, default=64, help="simulated scans (default 64)")
    parser.add_argument("--twin-max", type=int, default=32, help="scans the NumPy twin times (default 32)")
    parser.add_argument("--outlier-prob", type=float, default=0.3)
    parser.add_argument("--agree-min", type=int, default=40,
                        help="lines with at least this many inliers must agree (default 40)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed repeats (median; default 5; the NumPy twin uses min(REPEATS, 3))")
    parser.add_argument("--slam-runs", default="1,10,100", help="slam: batch sizes M (default 1,10,100)")
    parser.add_argument("--slam-duration", type=float, default=20.0,
                        help="slam: simulated flight per log [s], > 0.1 (10 Hz scans; default 20)")
    parser.add_argument("--slam-seq-max", type=int, default=10,
                        help="slam: sequential runs actually timed per M (default 10)")


_prng_key = prng_key  # the shared helper (timing.py); the name tests/benchmarks call


def _progress(msg):
    print(f"[bench lines] {msg}", file=sys.stderr, flush=True)


ROOM = [[0.0, 0.0], [5.0, 0.0], [5.0, 3.5], [0.0, 3.5]]
BOX = [[3.2, 2.2], [4.2, 2.2], [4.2, 2.8], [3.2, 2.8]]


def room_scans(seed, n, outlier_prob, dtype=None):
    """``n`` simulated scans of the benchmark room: (points (n, N, 2), valid, wall, true lines)."""
    import jax
    import jax.numpy as jnp

    from jaxslam.features import lines as F
    from jaxslam.sensors import laser2d as L

    dtype = dtype or jnp.float64
    walls_np = np.concatenate([L.walls_from_polygon(ROOM), L.walls_from_polygon(BOX)])
    walls = jnp.asarray(walls_np, dtype)
    wmask = jnp.ones(walls.shape[0], bool)
    rng = np.random.default_rng(seed)
    poses = np.column_stack([rng.uniform(0.6, 2.8, n), rng.uniform(0.6, 2.9, n), rng.uniform(-np.pi, np.pi, n)])
    keys = jax.random.split(prng_key(seed), n)
    spec = L.URG04LX

    def one(k, pose):
        r, v, w = L.scan(k, pose, walls, wmask, spec, outlier_prob=outlier_prob)
        p, m = L.scan_points(r, v, spec)
        return p, m, w

    pts, valid, wall = jax.jit(jax.vmap(one))(keys, jnp.asarray(poses, dtype))
    # True lines in each sensor frame.
    a, b = walls_np[:, 0], walls_np[:, 1]
    true = np.zeros((n, walls_np.shape[0], 2))
    for i, (x, y, yaw) in enumerate(poses):
        c, s = np.cos(yaw), np.sin(yaw)
        Rt = np.array([[c, s], [-s, c]])
        for j in range(walls_np.shape[0]):
            rho, th = F.line_through(Rt @ (a[j] - [x, y]), Rt @ (b[j] - [x, y]))
            true[i, j] = float(rho), float(th)
    return pts, valid, wall, true


def _close(r1, t1, r2, t2, tol_rho=0.02, tol_th=np.radians(0.5)):
    dth = np.abs((t1 - t2 + np.pi) % (2 * np.pi) - np.pi)
    return (np.abs(r1 - r2) <= tol_rho) & (dth <= tol_th)


def _ransac_part(args, out, results):
    import jax
    import numpy_lines as tw

    from jaxslam.features import lines as F

    cfg = F.DEFAULT_RANSAC
    S = args.scans
    _progress(f"simulating {S} scans")
    pts, valid, wall, true = room_scans(args.seed, S, args.outlier_prob)
    pts, valid = jax.block_until_ready((pts, valid))
    keys = jax.random.split(prng_key(args.seed, 1), S)
    single = jax.jit(F.extract_lines, static_argnames="cfg")
    batched = jax.jit(jax.vmap(lambda k, p, v: F.extract_lines(k, p, v, cfg)))

    t0 = time.perf_counter()
    jax.block_until_ready(single(keys[0], pts[0], valid[0], cfg))
    compile_single = time.perf_counter() - t0
    t0 = time.perf_counter()
    res_b = jax.block_until_ready(batched(keys, pts, valid))
    compile_batch = time.perf_counter() - t0

    _progress("timing jitted single-scan extraction")
    scans = [(keys[i], pts[i], valid[i]) for i in range(S)]
    t_single = median_s(lambda: [jax.block_until_ready(single(k, p, v, cfg)) for k, p, v in scans],
                       args.repeats) / S
    _progress("timing vmapped batch")
    t_batch = median_s(lambda: jax.block_until_ready(batched(keys, pts, valid)), args.repeats) / S
    _progress("timing NumPy twin")
    n_tw = min(S, args.twin_max)
    P_np, V_np = np.asarray(pts), np.asarray(valid)
    rng = np.random.default_rng(args.seed + 2)
    kw = dict(n_hyp=cfg.n_hyp, max_lines=cfg.max_lines, threshold=cfg.threshold, min_inliers=cfg.min_inliers)
    tw.extract_lines(np.random.default_rng(args.seed + 4), P_np[0], V_np[0], **kw)  # untimed warm-up call
    t_twin = median_s(lambda: [tw.extract_lines(rng, P_np[i], V_np[i], **kw) for i in range(n_tw)],
                     max(1, min(args.repeats, 3))) / n_tw

    # Agreement on the twin-timed scans, and recovery of the true walls by each.
    rng = np.random.default_rng(args.seed + 3)
    lines_b = jax.tree.map(np.asarray, res_b[0])
    agree_scans, n_major, wall_rec = 0, 0, {"jax": [0, 0], "numpy": [0, 0]}
    W = np.asarray(wall)
    for i in range(n_tw):
        tl, _ = tw.extract_lines(rng, P_np[i], V_np[i], **kw)
        jr, jt = lines_b.rho[i][lines_b.valid[i]], lines_b.theta[i][lines_b.valid[i]]
        jn = lines_b.n_inliers[i][lines_b.valid[i]]
        nr = np.array([t[0] for t in tl]); nt = np.array([t[1] for t in tl]); nn = np.array([t[2] for t in tl])
        ok = True
        for r, t, n in zip(jr, jt, jn):
            if n >= args.agree_min:
                n_major += 1
                ok &= bool(np.any(_close(r, t, nr, nt))) if nr.size else False
        for r, t, n in zip(nr, nt, nn):
            if n >= args.agree_min:
                n_major += 1
                ok &= bool(np.any(_close(r, t, jr, jt))) if jr.size else False
        agree_scans += ok
        counts = np.bincount(W[i][W[i] >= 0], minlength=true.shape[1])
        for j in np.flatnonzero(counts >= cfg.min_inliers):
            for name, (rr, tt) in (("jax", (jr, jt)), ("numpy", (nr, nt))):
                wall_rec[name][1] += 1
                wall_rec[name][0] += bool(rr.size and np.any(_close(true[i, j, 0], true[i, j, 1], rr, tt)))

    speed = t_twin / t_single
    out["ransac"] = {
        "scans": S, "twin_timed": n_tw, "beams": int(pts.shape[1]), "config": cfg._asdict(),
        "outlier_prob": args.outlier_prob,
        "compile_single_s": compile_single, "compile_batch_s": compile_batch,
        "single_per_scan_s": t_single, "batch_per_scan_s": t_batch, "twin_per_scan_s": t_twin,
        "speedup_single_vs_twin": speed, "speedup_batch_vs_twin": t_twin / t_batch,
        "agreement": {"scans_all_major_lines_agree": agree_scans, "scans_compared": n_tw,
                      "major_lines_compared": n_major, "min_inliers_for_major": args.agree_min},
        "true_wall_recovery": {k: {"recovered": v[0], "walls": v[1], "rate": v[0] / max(v[1], 1)}
                               for k, v in wall_rec.items()},
    }
    case = f"ransac room scan ({pts.shape[1]} beams, {args.outlier_prob:.0%} outliers, n_hyp={cfg.n_hyp})"
    ref = "NumPy twin (numpy_lines.extract_lines) per scan"
    results.append({"case": f"{case}, jitted single scan", "params": {"scans": S}, "jaxslam_s": t_single,
                    "reference": ref, "reference_s": t_twin, "speedup": speed})
    results.append({"case": f"{case}, vmapped batch (per scan)", "params": {"scans": S}, "jaxslam_s": t_batch,
                    "reference": ref, "reference_s": t_twin, "speedup": t_twin / t_batch})
    out["targets"].append({"name": "ransac: jitted single scan vs NumPy twin", "target": f">= {TARGETS['single_vs_twin']:g}x",
                           "value": speed, "met": bool(speed >= TARGETS["single_vs_twin"])})


def _slam_part(args, out, results):
    """Line-feature EKF-SLAM (paper 004 Alg. 2): runs/second, jitted vmap over M logs vs M sequential
    calls of the jitted single-log filter (the logs are simulated beforehand and not timed)."""
    import jax
    import jax.numpy as jnp

    from jaxslam.sim.scenarios import lineslam as sc
    from jaxslam.systems import line_slam_004 as LS

    opts = {"duration": args.slam_duration, "capacity": 16, "outlier_prob": 0.05, "tilt_deg": 2.0,
            "chunk": None}
    _, _, cfg, fp, setup = sc.build(opts, jnp.float64)
    Ms = sorted(set(int_list(args.slam_runs, "--slam-runs")))
    M_max = Ms[-1]
    keys = jax.random.split(prng_key(args.seed), M_max)
    sim = jax.jit(jax.vmap(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float64)))
    logs = jax.block_until_ready(sim(keys))
    fkeys = jax.random.split(prng_key(args.seed, 1), M_max)
    single = jax.jit(lambda k, log: LS.run(log, cfg, fp, key=k))
    batch = jax.jit(jax.vmap(lambda k, log: LS.run(log, cfg, fp, key=k)))
    first = jax.tree.map(lambda a: a[0], logs)
    t0 = time.perf_counter()
    jax.block_until_ready(single(fkeys[0], first))
    compile_single = time.perf_counter() - t0
    rows = []
    for M in Ms:
        sub = jax.tree.map(lambda a: a[:M], logs)
        t0 = time.perf_counter()
        jax.block_until_ready(batch(fkeys[:M], sub))
        compile_b = time.perf_counter() - t0
        t_b = median_s(lambda: jax.block_until_ready(batch(fkeys[:M], sub)), args.repeats)
        n_seq = min(M, args.slam_seq_max)

        def seq():
            for i in range(n_seq):
                jax.block_until_ready(single(fkeys[i], jax.tree.map(lambda a: a[i], sub)))

        t_s = median_s(seq, args.repeats) * M / n_seq
        _progress(f"slam M={M}: vmap {t_b:.3f} s, sequential {t_s:.3f} s ({n_seq} timed, scaled)")
        rows.append({"runs": M, "vmap_s": t_b, "sequential_s": t_s, "sequential_timed_runs": n_seq,
                     "vmap_runs_per_s": M / t_b, "sequential_runs_per_s": M / t_s,
                     "speedup_vmap_vs_sequential": t_s / t_b, "compile_vmap_s": compile_b})
        results.append({"case": f"lineslam-room filter, {setup.ts.shape[0]} scans, vmap over {M} logs",
                        "params": {"runs": M, "steps": int(setup.ts.shape[0])}, "jaxslam_s": t_b,
                        "reference": f"{M} sequential calls of the jitted single-log filter",
                        "reference_s": t_s, "speedup": t_s / t_b})
    out["slam"] = {"steps": int(setup.ts.shape[0]), "duration_s": args.slam_duration,
                   "compile_single_s": compile_single, "batches": rows,
                   "note": "filter only (RANSAC matching + EKF); logs simulated beforehand; sequential "
                           "time measured on min(M, --slam-seq-max) logs and scaled to M"}


def run(args):
    """Run the selected parts; returns the bench JSON dict (see the module docstring)."""
    import jax

    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)  # standalone use; the CLI has set it already
    from jaxslam.errors import InputError

    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not parts:
        raise InputError(f"--parts: no part given (got {args.parts!r}); choose from {', '.join(PARTS)}")
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise InputError(f"--parts: unknown part(s) {unknown}; choose from {', '.join(PARTS)}")
    if args.scans < 1 or args.twin_max < 1 or args.repeats < 1:
        raise InputError("--scans, --twin-max and --repeats must be positive")
    if not 0.0 <= args.outlier_prob < 1.0:
        raise InputError(f"--outlier-prob: expected a probability in [0, 1), got {args.outlier_prob}")
    int_list(args.slam_runs, "--slam-runs")  # checked before anything runs, not after the ransac part
    if "slam" in parts:  # lineslam's own check named "--duration" (no option here), after the ransac part
        d = float(args.slam_duration)
        if not (np.isfinite(d) and d > 0.1):
            raise InputError(f"--slam-duration: must be a finite number > 0.1 (one scan period), got {d:g}")
    load = {"before": list(os.getloadavg())}
    results, out = [], {"targets": []}
    if "ransac" in parts:
        _ransac_part(args, out, results)
    if "slam" in parts:
        _slam_part(args, out, results)
    load["after"] = list(os.getloadavg())
    out["load_average"] = load
    out["config"] = {"parts": parts, "seed": args.seed, "repeats": args.repeats, "dtype": "float64",
                     "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS")}
    out["notes"] = ["medians after a warm-up call; speedup = reference_s / jaxslam_s",
                    "JAX runs all max_lines rounds with static shapes (rounds after the first failure are "
                    "skipped by lax.cond in the single-scan path, masked under vmap); the twin breaks out",
                    "timings depend on the machine's load: see load_average"]
    print("targets:")
    for t in out["targets"]:
        print(f"  [{'met' if t['met'] else 'MISSED'}] {t['name']}: {t['value']:.3g}x (target {t['target']})")
    return {"results": results, **out}


if __name__ == "__main__":
    sys.exit("run this benchmark through the CLI: python -m jaxslam bench lines [options]")
