"""Dev/evaluation: 2D range-bearing FastSLAM 1.0 on MRCLAM dataset 6 and Victoria Park (issue 9).

Prints SE(2)-aligned ATE, run time after compile (second call, block_until_ready), counts.

    python scripts/study_planar_fastslam.py [--data DIR] [--only mrclam|vp]
        [--particles 100] [--seeds 5] [--vp-particles 50] [--vp-capacity 512] [--vp-t-end T]
        [--f32]

Noise values and their sources:
* MRCLAM R: σ = 1.4826·MAD of the landmark residuals against ground truth (data README §5):
  robot 1 range 0.053 m → 0.0786 m, bearing 0.0074 rad → 0.0110 rad; robot 2 0.121 m →
  0.179 m, 0.0062 rad → 0.0092 rad.
* MRCLAM input-noise density and pose floor: the EKF counterpart's preset
  (``jaxslam.data.presets.mrclam_params``: σ_v 0.03 m/s·√s, σ_ω 0.05 rad/s·√s, floor 1e-4 per s,
  tuned there on the first 300 s of robot 1), unchanged.
* Victoria Park: the EKF counterpart's preset (``jaxslam.data.presets.victoria_park_params``:
  σ_v 0.7 m/s·√s, σ_α 0.06 rad·√s, σ_r 1.0 m, σ_β 1.5°, range 5–40 m; RFS-SLAM's cfg for
  reference: R = 75·diag(0.025 m², 2.5e-5 rad²)), unchanged unless a flag says otherwise.
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import runtime  # noqa: E402
from jaxslam.cli.common import (ScriptParser, finite_float, nonnegative_float, path_arg, positive_float,  # noqa: E402
                                positive_int)

runtime.configure_process()

import numpy as np  # noqa: E402
from jaxslam.data.events import merge_events  # noqa: E402
from jaxslam.data.mrclam import load_mrclam  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, metrics, load_victoria_park, PF
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jaxslam import metrics
    from jaxslam.data.victoria_park import load_victoria_park
    from jaxslam.systems import planar_fastslam as PF


MAD = 1.4826
MRCLAM_SIGMA = {1: (0.053 * MAD, 0.0074 * MAD), 2: (0.121 * MAD, 0.0062 * MAD)}


def ate_at(t_est, xy_est, t_ref, xy_ref):
    inside = (t_ref >= t_est[0]) & (t_ref <= t_est[-1])
    e = np.stack([np.interp(t_ref[inside], t_est, xy_est[:, 0]),
                  np.interp(t_ref[inside], t_est, xy_est[:, 1])], axis=1)
    return float(metrics.ate(e, xy_ref[inside], align="rigid")), int(inside.sum())


def timed(fn, *a):
    t0 = time.perf_counter()
    r = jax.block_until_ready(fn(*a))
    t1 = time.perf_counter()
    r = jax.block_until_ready(fn(*a))
    return r, t1 - t0, time.perf_counter() - t1


def mrclam_log(root, robot):
    D = load_mrclam(root, robot)
    ids = D.meas_id.astype(np.int32) - 6  # subjects 6–20 → 0..14 (slot j)
    t_stop = D.gt_t[-1]
    K = int(np.max(np.unique(D.meas_t, return_counts=True)[1]))
    log = merge_events(D.odom_t, D.odom, D.meas_t, D.meas, ids, K=K, input_mode="rate", t_end=t_stop)
    t0 = log.t[0]
    th = np.unwrap(D.gt[:, 2])
    pose0 = np.array([np.interp(t0, D.gt_t, D.gt[:, 0]), np.interp(t0, D.gt_t, D.gt[:, 1]),
                      np.interp(t0, D.gt_t, th)])
    pose0[2] = (pose0[2] + np.pi) % (2 * np.pi) - np.pi
    return D, log, pose0, K


def mrclam(root, robot, n_particles, seeds, dtype, floor=1e-4, sv=0.03, sw=0.05):
    D, log, pose0, K = mrclam_log(root, robot)
    sr, sb = MRCLAM_SIGMA[robot]
    cfg = PF.Config(motion="unicycle", n_particles=n_particles, capacity=15, K=K, association="known")
    prm = PF.default_params(sigma_r=sr, sigma_b=sb, sigma_v=sv, sigma_w=sw, floor=(floor,) * 3,
                            pose0_sigma=(1e-3, 1e-3, 1e-3), dtype=dtype)
    lm = {int(s): xy for s, xy in zip(D.landmark_id, D.landmark_xy)}
    ates, ates_best, maps, times = [], [], [], []
    first = None
    for s in seeds:
        key = jax.random.PRNGKey(s)
        if first is None:
            res, first, t_run = timed(PF.run, key, log, jnp.asarray(pose0, dtype), cfg, prm)
        else:
            t1 = time.perf_counter()
            res = jax.block_until_ready(PF.run(key, log, jnp.asarray(pose0, dtype), cfg, prm))
            t_run = time.perf_counter() - t1
        times.append(t_run)
        a, n = ate_at(log.t, np.asarray(res.pose_mean[:, :2], np.float64), D.gt_t, D.gt[:, :2])
        ab, _ = ate_at(log.t, np.asarray(res.pose_best[:, :2], np.float64), D.gt_t, D.gt[:, :2])
        act = np.asarray(res.map.active)
        M = np.asarray(res.map.mean)[act]
        ids = np.asarray(res.map.ids)[act] + 6
        err = np.array([np.hypot(*(M[i] - lm[int(j)])) for i, j in enumerate(ids)])
        ates.append(a); ates_best.append(ab); maps.append(float(np.sqrt(np.mean(err ** 2))))
        print(f"  robot {robot} seed {s}: ATE mean-pose {a:.4f} m, best-particle {ab:.4f} m, "
              f"map RMSE (no alignment) {maps[-1]:.3f} m, mapped {int(act.sum())}, used {float(res.used):.0f}, "
              f"resamples {int(res.resamples)}, min Neff {float(jnp.min(res.neff)):.1f}, "
              f"status {int(res.status)}, run {t_run:.2f} s", flush=True)
    print(f"MRCLAM robot {robot} [N={n_particles}, {jnp.dtype(dtype).name}, {len(seeds)} seeds, "
          f"{log.stats['n_events']} events, K={K}, GT samples {n}]: median ATE {np.median(ates):.4f} m "
          f"(min {min(ates):.4f}, max {max(ates):.4f}); best-particle median {np.median(ates_best):.4f} m; "
          f"median map RMSE {np.median(maps):.3f} m; run {np.median(times):.2f} s after compile "
          f"(first call {first:.1f} s)", flush=True)
    return ates


def vp_log(root, range_min=5.0, range_max=40.0, t_end=None):
    D = load_victoria_park(root)
    r = D.det[:, 0]
    keep = (r >= range_min) & (r <= range_max)
    mt, Z = D.det_t[keep], D.det[keep]
    K = int(np.max(np.unique(mt, return_counts=True)[1]))
    log = merge_events(D.input_t, D.inputs, mt, Z, None, K=K, input_mode="rate", t_end=t_end)
    return D, log, K, int(keep.sum())


def victoria(root, n_particles, capacity, seeds, dtype, t_end=None, sv=0.7, sa=0.06,
             sr=1.0, sb=math.radians(1.5), log_p_new=0.0, new_thr=13.8, gate=9.21, range_max=40.0):
    D, log, K, n_det = vp_log(root, range_max=range_max, t_end=t_end)
    cfg = PF.Config(motion="ackermann", n_particles=n_particles, capacity=capacity, K=K,
                    association="ml")
    prm = PF.default_params(sigma_r=sr, sigma_b=sb, sigma_v=sv, sigma_w=sa, floor=(0.0, 0.0, 0.0),
                            pose0_sigma=(1e-3, 1e-3, 1e-3), log_p_new=log_p_new,
                            dtype=dtype)._replace(gate=gate, new_threshold=new_thr)
    first = None
    for s in seeds:
        key = jax.random.PRNGKey(s)
        if first is None:
            res, first, t_run = timed(PF.run, key, log, jnp.zeros(3, dtype), cfg, prm)
        else:
            t1 = time.perf_counter()
            res = jax.block_until_ready(PF.run(key, log, jnp.zeros(3, dtype), cfg, prm))
            t_run = time.perf_counter() - t1
        a, n = ate_at(log.t, np.asarray(res.pose_mean[:, :2], np.float64), D.gps_t, D.gps)
        ab, _ = ate_at(log.t, np.asarray(res.pose_best[:, :2], np.float64), D.gps_t, D.gps)
        act = np.asarray(res.map.active)
        nobs = np.asarray(res.n_obs)[act]
        print(f"Victoria Park [N={n_particles}, cap {capacity}, K={K}, r 5–{range_max} m ({n_det} detections), "
              f"{jnp.dtype(dtype).name}, seed {s}, t_end {t_end}]: ATE vs GPS mean-pose {a:.2f} m, "
              f"best-particle {ab:.2f} m over {n} fixes; mapped {int(act.sum())} "
              f"(≥2 obs {int((nobs >= 2).sum())}, ≥5 obs {int((nobs >= 5).sum())}); used {float(res.used):.0f}, "
              f"registered {float(res.registered):.0f}, ambiguous {float(res.gated):.0f}, overflow "
              f"{int(res.overflow)}, resamples {int(res.resamples)}, status {int(res.status)}; "
              f"{log.stats['n_events']} events; run {t_run:.1f} s after compile (first call {first:.1f} s)",
              flush=True)


def _robots(text):
    """argparse type: comma-separated MRCLAM robot numbers, each 1-5."""
    robots = [positive_int(s.strip()) for s in text.split(",")]
    if any(r > 5 for r in robots):
        raise argparse.ArgumentTypeError(f"expected robot numbers 1-5, got {text!r}")
    return robots


def main(argv=None):
    ap = ScriptParser(prog="study_planar_fastslam.py", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=__import__("os").environ.get("JAXSLAM_DATA_DIR"), type=path_arg,
                    help="folder holding mrclam6/ and victoria_park/ (default: $JAXSLAM_DATA_DIR)")
    ap.add_argument("--only", choices=["mrclam", "vp"], default=None)
    ap.add_argument("--particles", type=positive_int, default=100)
    ap.add_argument("--seeds", type=positive_int, default=5, help="number of seeds (0, 1, ...)")
    ap.add_argument("--robots", type=_robots, default="1,2")
    ap.add_argument("--floor", type=nonnegative_float, default=1e-4)
    ap.add_argument("--vp-particles", type=positive_int, default=50)
    ap.add_argument("--vp-capacity", type=positive_int, default=512)
    ap.add_argument("--vp-seeds", type=positive_int, default=1, help="number of seeds (0, 1, ...)")
    ap.add_argument("--vp-t-end", type=positive_float, default=None)
    ap.add_argument("--vp-sv", type=positive_float, default=0.7)
    ap.add_argument("--vp-sa", type=positive_float, default=0.06)
    ap.add_argument("--vp-range-max", type=positive_float, default=40.0)
    ap.add_argument("--vp-log-p-new", type=finite_float, default=0.0)
    ap.add_argument("--f32", action="store_true")
    a = ap.parse_args(argv)
    _import_jax()
    dtype = jnp.float32 if a.f32 else jnp.float64
    if a.only in (None, "mrclam"):
        for r in a.robots:
            mrclam(a.data, r, a.particles, list(range(a.seeds)), dtype, floor=a.floor)
    if a.only in (None, "vp"):
        victoria(a.data, a.vp_particles, a.vp_capacity, list(range(a.vp_seeds)), dtype,
                 t_end=a.vp_t_end, sv=a.vp_sv, sa=a.vp_sa, range_max=a.vp_range_max,
                 log_p_new=a.vp_log_p_new)


if __name__ == "__main__":
    main()
