"""Dev/evaluation: 2D range-bearing EKF-SLAM on MRCLAM dataset 6 and Victoria Park (issue 9).

Prints ATE (SE(2)-aligned), dead-reckoning ATE, run time after compile and counts.

    .venv/bin/python scripts/dev_planar_ekf.py [--data /work/shared/data] [--only mrclam|vp]
        [--f32] [--tune]

Until the loaders (jaxslam.data.mrclam / victoria_park) exist the files are parsed
here with np.loadtxt, following the data README §1/§2 (barcode → subject via
Barcodes.dat, robots 1–5 and unknown barcodes dropped; Victoria Park bearing − π/2).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import runtime  # noqa: E402

runtime.configure_process()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxslam import metrics  # noqa: E402
from jaxslam.data.events import merge_events  # noqa: E402
from jaxslam.systems import planar_ekf_slam as P  # noqa: E402


# ---------------------------------------------------------------------------
# Loading (temporary; the loaders module replaces this)
# ---------------------------------------------------------------------------

def load_mrclam(root, robot):
    d = pathlib.Path(root) / "mrclam6"
    try:  # the shared loader, once it exists
        from jaxslam.data.mrclam import load_mrclam as _lm  # noqa: F401
    except Exception:
        pass
    odo = np.loadtxt(d / f"Robot{robot}_Odometry.dat", comments="#")
    gt = np.loadtxt(d / f"Robot{robot}_Groundtruth.dat", comments="#")
    meas = np.loadtxt(d / f"Robot{robot}_Measurement.dat", comments="#")
    bc = np.loadtxt(d / "Barcodes.dat", comments="#").astype(int)
    lm = np.loadtxt(d / "Landmark_Groundtruth.dat", comments="#")
    b2s = {b: s for s, b in bc}
    subj = np.array([b2s.get(int(b), -1) for b in meas[:, 1]])
    keep = subj >= 6
    info = {"robot_rows": int(np.sum((subj >= 1) & (subj <= 5))), "unknown_rows": int(np.sum(subj < 0)),
            "landmark_rows": int(np.sum(keep))}
    return dict(odo=odo, gt=gt, mt=meas[keep, 0], z=meas[keep][:, 2:4], ids=subj[keep], lm=lm, info=info)


def load_vp(root):
    d = pathlib.Path(root) / "victoria_park"
    inp = np.loadtxt(d / "inputs.dat")
    meas = np.loadtxt(d / "measurements.dat")
    gps = np.loadtxt(d / "gps.dat")
    z = np.stack([meas[:, 1], meas[:, 2] - np.pi / 2], axis=1)
    return dict(inp=inp, mt=meas[:, 0], z=z, gps=gps)


# ---------------------------------------------------------------------------
# Evaluation helpers
# ---------------------------------------------------------------------------

def interp_pose_xy(t_est, xy, t_q):
    return np.stack([np.interp(t_q, t_est, xy[:, 0]), np.interp(t_q, t_est, xy[:, 1])], axis=1)


def ate_at(t_est, xy_est, t_ref, xy_ref):
    """SE(2)-aligned ATE of the estimate interpolated at the reference times inside its span."""
    inside = (t_ref >= t_est[0]) & (t_ref <= t_est[-1])
    e = interp_pose_xy(t_est, xy_est, t_ref[inside])
    return float(metrics.ate(e, xy_ref[inside], align="rigid")), int(inside.sum())


def timed(fn, *a, **k):
    t0 = time.perf_counter()
    r = fn(*a, **k)
    jax.block_until_ready(r)
    t1 = time.perf_counter()
    r = fn(*a, **k)
    jax.block_until_ready(r)
    return r, t1 - t0, time.perf_counter() - t1


def counts(res):
    return {k: int(np.sum(np.asarray(getattr(res, k)))) for k in
            ("n_meas", "n_limited", "n_dropped", "n_used", "n_gated", "n_rejected", "n_registered")} | {
        "mapped": int(np.sum(np.asarray(res.active))), "overflow": int(res.overflow), "status": int(res.status)}


def nis_summary(res):
    d = np.asarray(res.dof)
    n = np.asarray(res.nis)
    return float(n.sum() / max(d.sum(), 1))


# ---------------------------------------------------------------------------
# MRCLAM
# ---------------------------------------------------------------------------

def mrclam(root, robot, dtype, association="known", params=None, t_end=None, verbose=True, config=None):
    D = load_mrclam(root, robot)
    odo, gt = D["odo"], D["gt"]
    t_stop = gt[-1, 0] if t_end is None else t_end
    log = merge_events(odo[:, 0], odo[:, 1:3], D["mt"], D["z"], D["ids"], K=8, input_mode="rate",
                       t_end=t_stop)
    t0 = log.t[0]
    # start pose: ground truth interpolated at the first event (robot at rest before odometry)
    pose0 = np.array([np.interp(t0, gt[:, 0], gt[:, 1]), np.interp(t0, gt[:, 0], gt[:, 2]),
                      np.interp(t0, gt[:, 0], np.unwrap(gt[:, 3]))])
    cfg = config if config is not None else P.mrclam_config(association=association)
    prm = params if params is not None else P.mrclam_params(robot)
    prm = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), prm)
    res, t_first, t_second = timed(P.run, log, jnp.asarray(pose0, dtype), cfg, prm)
    xy = np.asarray(res.pose[:, :2], np.float64)
    ate, n = ate_at(log.t, xy, gt[:, 0], gt[:, 1:3])
    out = {"ate": ate, "n_gt": n, "t_first": t_first, "t_run": t_second, "events": log.stats["n_events"],
           "counts": counts(res), "mean_nis_per_dof": nis_summary(res), "log": log.stats}
    # landmark map error (known ids, after the trajectory-free comparison in the GT frame)
    if association == "known":
        act = np.asarray(res.active)
        ids = np.asarray(res.ids)[act]
        L = np.asarray(res.landmarks)[act]
        lm = {int(s): (x, y) for s, x, y in D["lm"][:, :3]}
        err = np.array([np.hypot(L[i, 0] - lm[int(j)][0], L[i, 1] - lm[int(j)][1]) for i, j in enumerate(ids)])
        out["map_rmse"] = float(np.sqrt(np.mean(err**2)))
    if verbose:
        print(f"MRCLAM robot {robot} [{association}, {jnp.dtype(dtype).name}]: ATE {ate:.4f} m over {n} GT "
              f"samples; run {t_second:.2f} s after compile (first call {t_first:.1f} s); "
              f"{log.stats['n_events']} events; counts {out['counts']}; mean NIS/dof "
              f"{out['mean_nis_per_dof']:.2f}" + (f"; map RMSE {out['map_rmse']:.3f} m" if "map_rmse" in out else ""))
    return out, res, log


def mrclam_dr(root, robot):
    """Dead reckoning (exact arc) from the first GT pose, SE(2)-aligned ATE at GT times."""
    D = load_mrclam(root, robot)
    odo, gt = D["odo"], D["gt"]
    log = merge_events(odo[:, 0], odo[:, 1:3], np.zeros(0), np.zeros((0, 2)), K=1, t_end=gt[-1, 0])
    t0 = log.t[0]
    s = np.array([np.interp(t0, gt[:, 0], gt[:, 1]), np.interp(t0, gt[:, 0], gt[:, 2]),
                  np.interp(t0, gt[:, 0], np.unwrap(gt[:, 3]))])
    from jaxslam.dynamics import planar

    def body(s, inp):
        dt, u = inp
        s = planar.unicycle(s, u, dt)
        return s, s

    _, traj = jax.lax.scan(body, jnp.asarray(s), (jnp.asarray(log.dt), jnp.asarray(log.u)))
    ate, n = ate_at(log.t, np.asarray(traj[:, :2]), gt[:, 0], gt[:, 1:3])
    return ate


# ---------------------------------------------------------------------------
# Victoria Park
# ---------------------------------------------------------------------------

def victoria(root, dtype, params=None, config=None, t_end=None, verbose=True):
    D = load_vp(root)
    inp = D["inp"]
    log = merge_events(inp[:, 0], inp[:, 1:3], D["mt"], D["z"], None, K=18, input_mode="rate", t_end=t_end)
    cfg = config if config is not None else P.victoria_park_config()
    prm = params if params is not None else P.victoria_park_params()
    prm = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), prm)
    res, t_first, t_second = timed(P.run, log, jnp.zeros(3, dtype), cfg, prm)
    gps = D["gps"]
    xy = np.asarray(res.pose[:, :2], np.float64)
    ate, n = ate_at(log.t, xy, gps[:, 0], gps[:, 1:3])
    out = {"ate": ate, "n_gps": n, "t_first": t_first, "t_run": t_second, "counts": counts(res),
           "events": log.stats["n_events"], "mean_nis_per_dof": nis_summary(res)}
    if verbose:
        print(f"Victoria Park [{jnp.dtype(dtype).name}, cap {cfg.capacity}, K {cfg.K}, r<= {cfg.range_max}]: "
              f"ATE vs GPS {ate:.3f} m over {n} fixes; run {t_second:.2f} s after compile (first call "
              f"{t_first:.1f} s); {log.stats['n_events']} events; counts {out['counts']}; mean NIS/dof "
              f"{out['mean_nis_per_dof']:.2f}")
    return out, res, log


def victoria_dr(root):
    D = load_vp(root)
    inp = D["inp"]
    log = merge_events(inp[:, 0], inp[:, 1:3], np.zeros(0), np.zeros((0, 2)), K=1)
    from jaxslam.dynamics import planar

    def body(s, inp_):
        dt, u = inp_
        s = planar.ackermann(s, u, dt)
        return s, s

    _, traj = jax.lax.scan(body, jnp.zeros(3), (jnp.asarray(log.dt), jnp.asarray(log.u)))
    gps = D["gps"]
    return ate_at(log.t, np.asarray(traj[:, :2]), gps[:, 0], gps[:, 1:3])[0]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/work/shared/data")
    ap.add_argument("--only", default="all")
    ap.add_argument("--f32", action="store_true")
    a = ap.parse_args()
    dtype = jnp.float32 if a.f32 else jnp.float64
    if a.only in ("all", "mrclam"):
        for robot in (1, 2):
            print(f"MRCLAM robot {robot}: dead-reckoning ATE (SE(2)-aligned) {mrclam_dr(a.data, robot):.3f} m")
            mrclam(a.data, robot, dtype, "known")
            mrclam(a.data, robot, dtype, "nn")
    if a.only in ("all", "vp"):
        print(f"Victoria Park: dead-reckoning ATE vs GPS (SE(2)-aligned) {victoria_dr(a.data):.2f} m")
        victoria(a.data, dtype)


if __name__ == "__main__":
    main()
