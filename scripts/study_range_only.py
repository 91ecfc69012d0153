"""Dev/evaluation script: range-only UTIL TWR (known / unknown anchors) and CMU Plaza 1/2.

Usage: python scripts/study_range_only.py [util|plaza|all] [--f32] [--data DIR]
Prints the figures reported for issue 9 (RMSE, ATE, anchor/beacon errors, bias, counts):
UTIL range-only and range + ToF height (known / unknown anchors), Plaza SLAM and
localisation with the surveyed (TL) beacons.
Reads the data with the jaxslam.data loaders (DIR default: $JAXSLAM_DATA_DIR).
"""

import time

from jaxslam import runtime

runtime.configure_process()
from jaxslam.cli.common import ScriptParser, path_arg  # noqa: E402
from jaxslam import errors  # noqa: E402
# (the loaders do not load JAX)
from jaxslam.data import load_plaza as _load_plaza  # noqa: E402
from jaxslam.data import load_util as _load_util  # noqa: E402
from jaxslam.data import tag_positions  # noqa: E402

import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read (--help
    and a usage error exit before JAX loads), and by util()/plaza() (for callers from outside main)."""
    global jax, jnp, metrics, pr, ur
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxslam import metrics
    from jaxslam.systems import plaza_range as pr
    from jaxslam.systems import util_range as ur


DATA = None  # the data folder (main: --data, else $JAXSLAM_DATA_DIR)


def load_util():
    """(TWR rows (t, anchor, range), GT times, GT tag positions, anchor ids, anchors) via the loader."""
    d = _load_util(DATA)
    u = np.stack([d.twr_t, d.twr_anchor, d.twr_range], 1)
    return u, d.gt_t, tag_positions(d.gt_p, d.gt_q, d.tag_offset), np.asarray(d.anchor_id), d.anchor_p


def load_tof():
    d = _load_util(DATA)
    return d.tof_t, d.tof


def err_report(log_t, est, true, mask_air):
    """Airborne RMSE (3D, vertical) over the log's range events."""
    e = est - true
    a = mask_air
    return (float(np.sqrt(np.mean(np.sum(e[a] ** 2, axis=1)))), float(np.sqrt(np.mean(e[a, 2] ** 2))),
            float(np.sqrt(np.mean(np.sum(e[a, :2] ** 2, axis=1)))))


def interp(tq, t, X):
    return np.stack([np.interp(tq, t, X[:, i]) for i in range(X.shape[1])], axis=1)


def block(res):
    return jax.tree_util.tree_map(lambda a: a.block_until_ready() if hasattr(a, "block_until_ready") else a, res)


def timed(f):
    t0 = time.perf_counter()
    r = block(f())
    t1 = time.perf_counter()
    r = block(f())
    t2 = time.perf_counter()
    return r, t1 - t0, t2 - t1


def util(dtype, gate=9.0, params=None, t_w=30.0):
    """params: default ur.PARAMS."""
    _import_jax()
    params = ur.PARAMS if params is None else params
    u, gt_t, tag, aid, anchors = load_util()
    log = ur.util_events(u[:, 0], u[:, 1], u[:, 2])
    res, tc, tr = timed(lambda: ur.run(ur.log_from_events(log, aid, anchors=anchors, dtype=dtype), ur.Config(), params._replace(gate=gate)))
    true = interp(log.t, gt_t, tag)
    est = np.asarray(res.pos, np.float64)
    err = np.linalg.norm(est - true, axis=1)
    air = (log.t >= 9.6) & (log.t <= 59.0)
    print(f"UTIL known anchors [{np.dtype(dtype).name}]: RMSE airborne {np.sqrt(np.mean(err[air]**2)):.3f} m, "
          f"whole {np.sqrt(np.mean(err**2)):.3f} m, bias {float(res.bias_final):+.3f} ± "
          f"{float(res.bias_sigma):.3f} m, used {int(res.n_used)} gated {int(res.n_gated)} "
          f"status {errors.decode(res.status)}; compile+run {tc:.2f} s, run {tr:.3f} s")
    late = air & (log.t > t_w)
    print(f"   known anchors over t > {t_w} s airborne (the SLAM interval): {np.sqrt(np.mean(err[late]**2)):.3f} m")
    nis = np.asarray(res.nis)[np.asarray(res.dof) > 0]
    print(f"   mean NIS {nis.mean():.2f} (dof 1); err p95 {np.percentile(err[air], 95):.3f}")
    tof_t, tof = load_tof()
    rmse, rz, rxy = err_report(log.t, est, true, air)
    print(f"   range-only airborne: RMSE {rmse:.3f} m, vertical {rz:.3f} m, horizontal {rxy:.3f} m")
    logh = ur.util_events(u[:, 0], u[:, 1], u[:, 2], tof_t=tof_t, tof=tof)
    resh, tc, tr = timed(lambda: ur.run(ur.log_from_events(logh, aid, anchors=anchors, dtype=dtype), ur.Config(), params._replace(gate=gate)))
    isr = (np.asarray(logh.ids)[:, 0] != ur.HEIGHT_ID)  # evaluate at the range events
    th = logh.t[isr]
    esth = np.asarray(resh.pos, np.float64)[isr]
    trueh = interp(th, gt_t, tag)
    airh = (th >= 9.6) & (th <= 59.0)
    rmse, rz, rxy = err_report(th, esth, trueh, airh)
    print(f"UTIL known anchors + ToF height: airborne RMSE {rmse:.3f} m, vertical {rz:.3f} m, horizontal "
          f"{rxy:.3f} m; K {logh.stats['K']}; ranges used {int(resh.n_used)} gated {int(resh.n_gated)}; "
          f"height used {int(resh.n_height_used)} gated {int(resh.n_height_gated)}; bias "
          f"{float(resh.bias_final):+.3f} ± {float(resh.bias_sigma):.3f} m; status {errors.decode(resh.status)}; "
          f"compile+run {tc:.2f} s, run {tr:.3f} s")
    # unknown anchors: start-up on the mocap window [0, t_w], then SLAM without mocap
    tag_at = interp(u[:, 0], gt_t, tag)
    i_w = np.searchsorted(gt_t, t_w)
    v0 = (tag[i_w + 20] - tag[i_w - 20]) / (gt_t[i_w + 20] - gt_t[i_w - 20])
    su = ur.startup(jnp.asarray(u[:, 0], dtype), u[:, 1].astype(int), jnp.asarray(u[:, 2], dtype),
                         jnp.asarray(tag_at, dtype), aid, t_w, v0=jnp.asarray(v0, dtype))
    a_err0 = np.linalg.norm(np.asarray(su.anchors) - anchors, axis=1)
    print(f"UTIL start-up window [0, {t_w}] s: anchors err mean {a_err0.mean():.3f} max {a_err0.max():.3f} m, "
          f"bias {float(su.bias):+.3f} m, used {int(su.n_used)} rejected {int(su.n_rejected)} rms {float(su.rms):.3f}")
    log2 = ur.util_events(u[:, 0], u[:, 1], u[:, 2], t_start=t_w + 1e-9)
    res2, tc, tr = timed(lambda: ur.run(ur.log_from_events(log2, aid, startup=su, dtype=dtype), ur.Config(), params._replace(gate=gate)))
    true2 = interp(log2.t, gt_t, tag)
    est2 = np.asarray(res2.pos, np.float64)
    err2 = np.linalg.norm(est2 - true2, axis=1)
    air2 = (log2.t >= 9.6) & (log2.t <= 59.0)
    A = np.asarray(res2.landmarks, np.float64)[: len(aid)]
    raw = np.linalg.norm(A - anchors, axis=1)
    R, t, _ = metrics.umeyama(jnp.asarray(A), jnp.asarray(anchors))
    Aal = A @ np.asarray(R).T + np.asarray(t)
    al = np.linalg.norm(Aal - anchors, axis=1)
    ate = float(metrics.ate(jnp.asarray(est2), jnp.asarray(true2)))
    print(f"UTIL unknown anchors (t > {t_w} s): pos RMSE raw airborne {np.sqrt(np.mean(err2[air2]**2)):.3f} "
          f"all {np.sqrt(np.mean(err2**2)):.3f} m, ATE(rigid) {ate:.3f} m; anchor err raw mean {raw.mean():.3f} "
          f"max {raw.max():.3f}, aligned mean {al.mean():.3f} max {al.max():.3f} m; bias "
          f"{float(res2.bias_final):+.3f} ± {float(res2.bias_sigma):.3f}; used {int(res2.n_used)} gated "
          f"{int(res2.n_gated)} status {errors.decode(res2.status)}; run {tr:.3f} s")
    rmse, rz, rxy = err_report(log2.t, est2, true2, air2)
    print(f"   range-only (unknown anchors) airborne: RMSE {rmse:.3f}, vertical {rz:.3f}, horizontal {rxy:.3f} m")
    logh2 = ur.util_events(u[:, 0], u[:, 1], u[:, 2], t_start=t_w + 1e-9, tof_t=tof_t, tof=tof)
    resh2, tc, tr = timed(lambda: ur.run(ur.log_from_events(logh2, aid, startup=su, dtype=dtype), ur.Config(), params._replace(gate=gate)))
    isr = (np.asarray(logh2.ids)[:, 0] != ur.HEIGHT_ID)
    th = logh2.t[isr]
    esth = np.asarray(resh2.pos, np.float64)[isr]
    trueh = interp(th, gt_t, tag)
    airh = (th >= 9.6) & (th <= 59.0)
    rmse, rz, rxy = err_report(th, esth, trueh, airh)
    A = np.asarray(resh2.landmarks, np.float64)[: len(aid)]
    raw = np.linalg.norm(A - anchors, axis=1)
    print(f"UTIL unknown anchors + ToF height (t > {t_w} s): airborne RMSE {rmse:.3f}, vertical {rz:.3f}, "
          f"horizontal {rxy:.3f} m; anchor err raw mean {raw.mean():.3f} max {raw.max():.3f} m; bias "
          f"{float(resh2.bias_final):+.3f} ± {float(resh2.bias_sigma):.3f}; ranges used {int(resh2.n_used)} "
          f"gated {int(resh2.n_gated)}; height used {int(resh2.n_height_used)} gated "
          f"{int(resh2.n_height_gated)}; status {errors.decode(resh2.status)}; run {tr:.3f} s")
    return res, res2


def load_plaza(which):
    """(DR rows, TD rows, GT rows, TL rows) via the loader (TD sorted by time)."""
    d = _load_plaza(DATA, which)
    DR = np.column_stack([d.dr_t, d.dr])
    TD = np.column_stack([d.td_t, d.td_sender, d.td_node, d.td_range])
    GT = np.column_stack([d.gt_t, d.gt])
    TL = np.column_stack([d.node_id, d.node_xy])
    return DR, TD, GT, TL


def plaza(which, dtype, params=None, known=False, **kw):
    """params: default pr.PARAMS."""
    _import_jax()
    params = pr.PARAMS if params is None else params
    DR, TD, GT, TL = load_plaza(which)
    log = pr.plaza_events(DR[:, 0], DR[:, 1:3], TD[:, 0], TD[:, 2], TD[:, 3])
    pose0 = GT[0, 1:4].copy()
    if which == 2:
        pose0[2] += np.pi
    ids = np.array([0, 1, 5, 6])
    if known:
        xy = np.stack([TL[TL[:, 0] == i, 1:3][0] for i in ids])
    rlog = pr.log_from_events(log, pose0, ids, beacons=xy if known else None, dtype=dtype)
    res, tc, tr = timed(lambda: pr.run(rlog, pr.Config(**kw), params))
    est = np.asarray(res.pos, np.float64)
    # ground truth at the event times (inside GT's span)
    inside = (log.t >= GT[0, 0]) & (log.t <= GT[-1, 0])
    true = interp(log.t[inside], GT[:, 0], GT[:, 1:3])
    est = est[inside]
    ate = float(metrics.ate(jnp.asarray(est), jnp.asarray(true)))
    raw = float(np.sqrt(np.mean(np.sum((est - true) ** 2, axis=1))))
    R, t, _ = metrics.umeyama(jnp.asarray(est), jnp.asarray(true))
    # dead reckoning (same composition, from the same start)
    x, y, th = pose0
    dr = [(x, y)]
    for dd, dth in DR[:, 1:3]:
        x += dd * np.cos(th)
        y += dd * np.sin(th)
        th += dth
        dr.append((x, y))
    dr = np.asarray(dr)
    drt = np.concatenate([[GT[0, 0]], DR[:, 0]])
    gt_dr = interp(drt, GT[:, 0], GT[:, 1:3])
    dr_rms = float(np.sqrt(np.mean(np.sum((dr - gt_dr) ** 2, axis=1))))
    dr_ate = float(metrics.ate(jnp.asarray(dr), jnp.asarray(gt_dr)))
    B = np.asarray(res.landmarks, np.float64)
    bid = np.asarray(res.landmark_ids)
    act = np.asarray(res.active)
    tl = {int(r[0]): r[1:3] for r in TL}
    rows = [(int(i), B[k]) for k, i in enumerate(bid) if act[k]]
    berr_raw = {i: float(np.linalg.norm(b - tl[i])) for i, b in rows}
    # beacon errors after the trajectory alignment, and after aligning the beacons themselves
    berr_traj = {i: float(np.linalg.norm(np.asarray(R) @ b + np.asarray(t) - tl[i])) for i, b in rows}
    if len(rows) >= 2:
        Bs = np.stack([b for _, b in rows])
        Ts = np.stack([tl[i] for i, _ in rows])
        R2, t2, _ = metrics.umeyama(jnp.asarray(Bs), jnp.asarray(Ts))
        berr_self = {i: float(np.linalg.norm(np.asarray(R2) @ b + np.asarray(t2) - tl[i])) for i, b in rows}
    else:
        berr_self = {}
    fmt = lambda d: ", ".join(f"{k}:{v:.2f}" for k, v in d.items())  # noqa: E731
    # measured − true range (GT interpolated at the range time, surveyed TL beacons)
    gxy = interp(TD[:, 0], GT[:, 0], GT[:, 1:3])
    tlxy = np.stack([TL[TL[:, 0] == n, 1:3][0] for n in TD[:, 2]])
    rerr = TD[:, 3] - np.linalg.norm(gxy - tlxy, axis=1)
    mode = "localisation, surveyed beacons" if known else "SLAM"
    print(f"Plaza {which} ({mode}): median(measured − true range) {np.median(rerr):+.2f} m; "
          f"bias track: mean over last half {np.mean(np.asarray(res.bias)[len(log.t) // 2:]):+.2f} m")
    print(f"Plaza {which} [{np.dtype(dtype).name}]: ATE(rigid) {ate:.2f} m, raw RMS {raw:.2f} m; DR raw RMS "
          f"{dr_rms:.2f} m, DR ATE {dr_ate:.2f} m; bias {float(res.bias_final):+.2f} ± {float(res.bias_sigma):.2f} m; "
          f"used {int(res.n_used)} gated {int(res.n_gated)} unmapped-buffered {int(res.n_unmapped)} "
          f"registered {int(res.n_registered)}; status {errors.decode(res.status)}; compile+run {tc:.1f} s, run {tr:.2f} s")
    print(f"   beacon err raw {{{fmt(berr_raw)}}}; after traj. alignment {{{fmt(berr_traj)}}}; "
          f"after beacon alignment {{{fmt(berr_self)}}}")
    return res


def parser():
    ap = ScriptParser(prog="study_range_only.py", description=__doc__.splitlines()[0])
    ap.add_argument("what", nargs="?", choices=("util", "plaza", "all"), default="all",
                    help="UTIL TWR, CMU Plaza 1/2, or both (default all)")
    ap.add_argument("--f32", action="store_true", help="float32 (default float64)")
    ap.add_argument("--data", default=None, type=path_arg, metavar="DIR",
                    help="the data folder (default: $JAXSLAM_DATA_DIR)")
    return ap


def main(argv=None):
    global DATA
    ap = parser()
    a = ap.parse_args(argv)
    DATA = ap.data_root(a.data)
    _import_jax()
    what = a.what
    dtype = jnp.float32 if a.f32 else jnp.float64
    if what in ("util", "all"):
        util(dtype)
    if what in ("plaza", "all"):
        plaza(1, dtype)
        plaza(2, dtype)
        plaza(1, dtype, known=True)
        plaza(2, dtype, known=True)


if __name__ == "__main__":
    main()
