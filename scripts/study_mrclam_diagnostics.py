"""Diagnostics of what limits the MRCLAM dataset 6 EKF-SLAM ATE (issue 9).

    python scripts/study_mrclam_diagnostics.py [--data DIR] [--part all|resid|odo|loc|slam]

DIR: the folder holding mrclam6/ (default: $JAXSLAM_DATA_DIR).

Parts (all use ground truth and are *diagnostics*; the protocol of any fitted constant is
printed with it):

* ``resid``: landmark range/bearing residuals against GT pose + surveyed landmarks, as a
  function of a measurement time shift and of the bearing (a bearing-dependent range error
  of the camera: ranges too long at the image centre, too short at the edges).
* ``odo``: odometry against GT motion over 1 s windows, as a function of an odometry time
  shift; speed scale, turn-rate scale and bias per robot and per half.
* ``loc``: localisation on the surveyed landmark map (the EKF with the 15 landmarks preloaded
  with a tiny covariance, no registration) with and without each correction: tells how far
  better sensor/odometry modelling alone can go.
* ``slam``: the EKF-SLAM (known ids and nn) with the chosen preset, ATE over the whole GT span,
  dead reckoning and run time after compile.

Protocol for fitted constants: everything is fitted on the FIRST HALF of robot 1's log
(t < 386 s of its 772 s GT span); robot 1's second half and all of robot 2 are held out.
"""

from __future__ import annotations

import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import runtime  # noqa: E402
from jaxslam.cli.common import ScriptParser, one_line, path_arg  # noqa: E402
from jaxslam.errors import InputError  # noqa: E402

runtime.configure_process()

import numpy as np  # noqa: E402
from jaxslam.data.events import merge_events  # noqa: E402
from jaxslam.data.mrclam import load_mrclam  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, presets, dead_reckoning, evaluate_planar, planar, es, P, _loc_scan
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jaxslam.data import presets
    from jaxslam.data.runners import dead_reckoning, evaluate_planar
    from jaxslam.dynamics import planar
    from jaxslam.filters import ekf_slam as es
    from jaxslam.systems import planar_ekf_slam as P
    _loc_scan = jax.jit(_loc_scan_impl, static_argnames=("config",))


DATA = __import__("os").environ.get("JAXSLAM_DATA_DIR")


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def mad(e):
    return float(np.median(np.abs(e - np.median(e))))


# ---------------------------------------------------------------------------
# Residuals against ground truth
# ---------------------------------------------------------------------------

def predicted(D, t):
    """Range/bearing predicted from GT (interpolated at t) and the surveyed landmarks."""
    lm = D.landmark_positions()
    L = np.array([lm[int(i)] for i in D.meas_id])
    th = np.unwrap(D.gt[:, 2])
    ok = (t >= D.gt_t[0]) & (t <= D.gt_t[-1])
    x = np.interp(t, D.gt_t, D.gt[:, 0])
    y = np.interp(t, D.gt_t, D.gt[:, 1])
    p = np.interp(t, D.gt_t, th)
    r = np.hypot(L[:, 0] - x, L[:, 1] - y)
    b = wrap(np.arctan2(L[:, 1] - y, L[:, 0] - x) - p)
    return ok, r, b


def fit_range_model(D, t_shift, sel_fn):
    """Least squares r_meas / r_true = k0 + k2 β² on the rows selected by sel_fn(D)."""
    ok, r, _ = predicted(D, D.meas_t + t_shift)
    rm, bm = D.meas[:, 0], D.meas[:, 1]
    sel = ok & sel_fn(D) & (np.abs(rm - r) < 0.5)
    A = np.stack([np.ones(sel.sum()), bm[sel] ** 2], 1)
    return np.linalg.lstsq(A, rm[sel] / r[sel], rcond=None)[0]


def first_half(D):
    return D.meas_t < D.gt_t[-1] / 2


def part_resid(Ds):
    print("== measurement residuals vs GT (range m, bearing rad) ==")
    for robot, D in Ds.items():
        rows = []
        for sh in (-0.2, -0.1, -0.06, -0.04, -0.02, 0.0, 0.05, 0.1):
            ok, r, b = predicted(D, D.meas_t + sh)
            er, eb = (D.meas[:, 0] - r)[ok], wrap(D.meas[:, 1] - b)[ok]
            rows.append(f"{sh:+.2f}: r med {np.median(er):+.3f} MAD {mad(er):.3f}, b med {np.median(eb):+.4f} "
                        f"MAD {mad(eb):.4f}")
        print(f"robot {robot} measurement time shift (GT at t_meas + shift):\n   " + "\n   ".join(rows))
        ok, r, b = predicted(D, D.meas_t - 0.04)
        rm, bm = D.meas[:, 0], D.meas[:, 1]
        for lo, hi in ((-.6, -.45), (-.45, -.3), (-.3, -.15), (-.15, 0), (0, .15), (.15, .3), (.3, .45), (.45, .6)):
            m = ok & (bm >= lo) & (bm < hi)
            print(f"   bearing [{lo:+.2f},{hi:+.2f}): n {m.sum():4d}  r_meas/r_true med {np.median(rm[m] / r[m]):.4f}  "
                  f"r error med {np.median((rm - r)[m]):+.3f}  bearing error med {np.median(wrap(bm - b)[m]):+.4f}")
    k = fit_range_model(Ds[1], -0.04, first_half)
    print(f"range model fitted on robot 1 first half: r_meas = r_true·({k[0]:.4f} {k[1]:+.4f} β²)")
    for robot, D in Ds.items():
        kr = fit_range_model(D, -0.04, lambda D_: np.ones(D_.meas_t.shape, bool))
        print(f"   (for reference, fitted on all of robot {robot}: {kr[0]:.4f} {kr[1]:+.4f} β²)")
        ok, r, b = predicted(D, D.meas_t - 0.04)
        rm, bm = D.meas[:, 0], D.meas[:, 1]
        rc = rm / (k[0] + k[1] * bm ** 2)
        for nm, m in (("2nd half", ok & ~first_half(D)), ("all", ok)):
            print(f"   robot {robot} {nm}: raw r error med {np.median((rm - r)[m]):+.3f} MAD {mad((rm - r)[m]):.3f} "
                  f"-> corrected med {np.median((rc - r)[m]):+.3f} MAD {mad((rc - r)[m]):.3f}")
    return k


# ---------------------------------------------------------------------------
# Odometry against ground truth
# ---------------------------------------------------------------------------

def _cumint(t_odo, u, tq):
    dt = np.diff(t_odo)
    c = np.concatenate([[0], np.cumsum(u[:-1] * dt)])
    i = np.clip(np.searchsorted(t_odo, tq, side="right") - 1, 0, len(t_odo) - 1)
    return c[i] + u[i] * (tq - t_odo[i])


def odo_fit(D, shift, lo=None, hi=None, W=1.0):
    """(kv, kw, bw, rms_v, rms_w) of GT arc length / heading change vs odometry over W windows.

    GT motion over [a, b] is compared with the odometry over [a + shift, b + shift]; a best shift
    of −0.2 s means the odometry sample stamped τ describes the motion at τ + 0.2 s.
    """
    th = np.unwrap(D.gt[:, 2])
    t_end = min(D.gt_t[-1], D.odom_t[-1]) - 1
    lo = D.odom_t[0] + 1 if lo is None else lo
    hi = t_end if hi is None else min(hi, t_end)
    a = np.arange(lo, hi - W, W)
    b = a + W
    # chord over the window (a summed GT arc length would add the Vicon jitter: biased upwards)
    dS = np.hypot(np.interp(b, D.gt_t, D.gt[:, 0]) - np.interp(a, D.gt_t, D.gt[:, 0]),
                  np.interp(b, D.gt_t, D.gt[:, 1]) - np.interp(a, D.gt_t, D.gt[:, 1]))
    dT = np.interp(b, D.gt_t, th) - np.interp(a, D.gt_t, th)
    oS = _cumint(D.odom_t, D.odom[:, 0], b + shift) - _cumint(D.odom_t, D.odom[:, 0], a + shift)
    oT = _cumint(D.odom_t, D.odom[:, 1], b + shift) - _cumint(D.odom_t, D.odom[:, 1], a + shift)
    kv = np.sum(dS * oS) / np.sum(oS * oS)
    A = np.stack([oT, np.full_like(oT, W)], 1)
    kw, bw = np.linalg.lstsq(A, dT, rcond=None)[0]
    return kv, kw, bw / W, float(np.sqrt(np.mean((dS - kv * oS) ** 2))), float(np.sqrt(np.mean((dT - A @ [kw, bw]) ** 2)))


def part_odo(Ds):
    print("== odometry vs GT over 1 s windows (GT motion in [a, b] vs odometry in [a+shift, b+shift]) ==")
    for robot, D in Ds.items():
        for sh in (-0.4, -0.3, -0.25, -0.2, -0.15, -0.1, 0.0, 0.1):
            kv, kw, bw, rv, rw = odo_fit(D, sh)
            print(f"robot {robot} shift {sh:+.2f}: speed scale {kv:.4f} (rms {rv:.4f} m) | turn scale {kw:.4f} "
                  f"bias {bw:+.5f} rad/s (rms {rw:.4f} rad)")
        half = D.gt_t[-1] / 2
        best = min((odo_fit(D, sh, None, half)[4], sh) for sh in np.arange(-0.5, 0.21, 0.05))
        print(f"   robot {robot} 1st half: turn residual RMS minimal at shift {best[1]:+.2f} s ({best[0]:.4f} rad)")
        for nm, lo, hi in (("1st half", None, half), ("2nd half", half, None)):
            kv, kw, bw, rv, rw = odo_fit(D, -0.2, lo, hi)
            print(f"   robot {robot} {nm} (shift −0.2): speed {kv:.4f} turn {kw:.4f} bias {bw:+.5f} rad/s")
    kv, kw, bw, _, _ = odo_fit(Ds[1], -0.2, None, Ds[1].gt_t[-1] / 2)
    print(f"odometry calibration fitted on robot 1 first half (shift −0.2 s): ({kv:.4f}, {kw:.4f}, {bw:+.5f})")
    return kv, kw, bw


# ---------------------------------------------------------------------------
# Preparing the event log with corrections
# ---------------------------------------------------------------------------

def prepare(D, odo_shift=0.0, meas_shift=0.0, range_k=None, odo_cal=None, t_end=None):
    """EventLog with odometry stamps + odo_shift, measurement stamps + meas_shift, ranges divided by
    (k0 + k2 β²), odometry (v, ω) → (c0 v, c1 ω + c2).  Returns (log, pose0)."""
    ot = D.odom_t + odo_shift
    u = D.odom.copy()
    if odo_cal is not None:
        u = np.stack([odo_cal[0] * u[:, 0], odo_cal[1] * u[:, 1] + odo_cal[2]], 1)
        u[(D.odom[:, 0] == 0) & (D.odom[:, 1] == 0)] = 0.0  # robot at rest: no bias
    z = D.meas.copy()
    if range_k is not None:
        z[:, 0] = z[:, 0] / (range_k[0] + range_k[1] * z[:, 1] ** 2)
    mt = D.meas_t + meas_shift
    t_end = D.gt_t[-1] if t_end is None else t_end
    log = merge_events(ot, u, mt, z, D.meas_id, K=8, input_mode="rate", t_end=t_end)
    t0 = log.t[0]
    th = np.unwrap(D.gt[:, 2])
    pose0 = np.array([np.interp(t0, D.gt_t, D.gt[:, 0]), np.interp(t0, D.gt_t, D.gt[:, 1]),
                      np.interp(t0, D.gt_t, th)])
    return log, pose0


def evaluate(D, log, pose, dr=None):
    m, _ = evaluate_planar(log.t, np.asarray(pose), D.gt_t, D.gt, dr_pose=None if dr is None else np.asarray(dr))
    return m


def dr_ate(D, log, pose0):
    dr = dead_reckoning(planar.unicycle, jnp.asarray(pose0), jnp.asarray(log.u), jnp.asarray(log.dt))
    return evaluate(D, log, np.asarray(dr))["ate_m"]


# ---------------------------------------------------------------------------
# Localisation on the surveyed map
# ---------------------------------------------------------------------------

def localise(D, log, pose0, params, config):
    """EKF with the 15 surveyed landmarks preloaded (covariance 1e-10 m², no cross terms)."""
    model = P.make_model(config)
    dtype = jnp.float64
    cap = 16
    x0 = jnp.asarray(pose0, dtype)
    P0 = jnp.asarray(params.P0, dtype)
    if config.calibrate:
        x0 = jnp.concatenate([x0, jnp.asarray(params.calib0, dtype)])
        P0 = jax.scipy.linalg.block_diag(P0, params.calib_P0)
    st = es.init(x0, P0, cap, 2)
    n = st.x.shape[0]
    for i, (j, xy) in enumerate(zip(D.landmark_id, D.landmark_xy)):
        st = es.add_landmark(st, model, i, jnp.asarray(xy, dtype), jnp.eye(2, dtype=dtype) * 1e-10,
                             jnp.zeros((2, n), dtype), int(j))
    return _loc_scan(st, jnp.asarray(log.dt), jnp.asarray(log.u), jnp.asarray(np.nan_to_num(log.z)),
                     jnp.asarray(log.ids), jnp.asarray(log.mask), params, config)


def _loc_scan_impl(st0, dt, u, z, ids, mask, params, config):
    model = P.make_model(config)
    f = model.motion
    nr = model.robot_dim
    Q_add = params.Q_floor
    if config.calibrate:
        Q_add = jax.scipy.linalg.block_diag(params.Q_floor, params.calib_Q)

    def body(st, inp):
        dt_k, u_k, z_k, id_k, m_k = inp
        s = st.x[:nr]
        M = planar.step_input_cov(params.M_c, dt_k, "rate")
        Q = planar.input_noise_cov(f, s, u_k, dt_k, M) + Q_add * dt_k
        st = es.predict(st, model, u_k, Q, dt_k)
        slots, mapped = es.associate_known(st, id_k, m_k)

        def upd(st_):
            return es.update(st_, model, z_k, slots, mapped, params.R, None, gate=params.update_gate)[0]

        st = jax.lax.cond(jnp.any(mapped), upd, lambda st_: st_, st)
        return st, st.x[:nr]

    return jax.lax.scan(body, st0, (dt, u, z, ids, mask))[1]


def part_loc(Ds, range_k, odo_cal, base_params=None):
    print("== localisation on the surveyed map (ATE over the whole GT span) ==")
    cfg = presets.mrclam_config()
    for robot, D in Ds.items():
        prm = presets.mrclam_params(robot) if base_params is None else base_params(robot)
        cases = [
            ("raw", {}),
            ("meas shift −0.04", dict(meas_shift=-0.04)),
            ("odo shift +0.2", dict(odo_shift=0.2)),
            ("range model", dict(range_k=range_k)),
            ("odo calib", dict(odo_cal=odo_cal)),
            ("odo shift + range", dict(odo_shift=0.2, range_k=range_k)),
            ("all", dict(odo_shift=0.2, meas_shift=-0.04, range_k=range_k, odo_cal=odo_cal)),
        ]
        for nm, kw in cases:
            log, pose0 = prepare(D, **kw)
            pose = localise(D, log, pose0, prm, cfg)
            print(f"   robot {robot} {nm:20s}: loc ATE {evaluate(D, log, pose)['ate_m']:.4f} m   "
                  f"(DR {dr_ate(D, log, pose0):.3f} m)")


# ---------------------------------------------------------------------------
# SLAM
# ---------------------------------------------------------------------------

def slam(D, log, pose0, params, config):
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), params)
    P.run(P.log_from_events(log, jnp.asarray(pose0)), config, params).pose.block_until_ready()
    t1 = time.perf_counter()
    res = P.run(P.log_from_events(log, jnp.asarray(pose0)), config, params)
    res.pose.block_until_ready()
    t_run = time.perf_counter() - t1
    return res, evaluate(D, log, np.asarray(res.pose)), t_run


def part_slam(Ds):
    print("== EKF-SLAM with the preset (mrclam_log + mrclam_params + mrclam_config), whole GT span ==")
    for robot, D in Ds.items():
        for nm, corr in (("raw log, old preset", False), ("corrected preset", True)):
            if corr:
                log, pose0 = presets.mrclam_log(D)
            else:
                log, pose0 = presets.mrclam_log(D, range_model=None, odometry_delay=0.0)
            prm = presets.mrclam_params(robot, corrected=corr)._replace(update_gate=13.8 if corr else 9.21)
            for assoc, cfgs in (("known", [(presets.mrclam_config(), prm)]),
                                ("nn", [(presets.mrclam_config("nn", capacity=32), prm),
                                        (presets.mrclam_config("nn", capacity=48), prm),
                                        (presets.mrclam_config("nn", capacity=48), prm._replace(new_threshold=60.0))])):
                for cfg, prm_c in cfgs:
                    res, m, tr = slam(D, log, pose0, prm_c, cfg)
                    print(f"   robot {robot} {nm:20s} {assoc:5s} cap {cfg.capacity} new_thr {prm_c.new_threshold}: "
                          f"ATE {m['ate_m']:.4f} m, run {tr:.2f} s after compile, mapped "
                          f"{int(np.sum(np.asarray(res.active)))}, overflow {int(res.overflow)}, "
                          f"gated {int(res.n_gated.sum())}, rejected {int(res.n_rejected.sum())}")
            print(f"   robot {robot} {nm:20s} dead reckoning ATE {dr_ate(D, log, pose0):.3f} m")


def main(argv=None):
    ap = ScriptParser(prog="study_mrclam_diagnostics.py", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=DATA, type=path_arg, help="folder holding mrclam6/ (default: $JAXSLAM_DATA_DIR)")
    ap.add_argument("--part", default="all", choices=("all", "resid", "odo", "loc", "slam"))  # (another ran nothing)
    a = ap.parse_args(argv)
    try:  # a missing or malformed log: one usage line, not a traceback
        Ds = {r: load_mrclam(a.data, r) for r in (1, 2)}
    except InputError as e:
        ap.error(f"--data: {one_line(str(e)) or type(e).__name__}")
    _import_jax()
    range_k = odo_cal = None
    if a.part in ("all", "resid", "loc"):
        range_k = part_resid(Ds)
    if a.part in ("all", "odo", "loc"):
        odo_cal = part_odo(Ds)
    if a.part in ("all", "loc"):
        part_loc(Ds, range_k, odo_cal)
    if a.part in ("all", "slam"):
        part_slam(Ds)


if __name__ == "__main__":
    main()
