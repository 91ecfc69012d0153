"""Development: UTIL ranges with the vertical channel driven by the IMU (oracle-scored study).

    python scripts/study_util_imu_vertical.py [key=value ...]   (data from $JAXSLAM_DATA_DIR or ../shared/data)

keys: imu (1: the IMU drives p_z, v_z; 0: the shipped constant-velocity model), qh (horizontal
white-acceleration density, the shipped fit's 0.139 m²/s³), qz (vertical acceleration noise
density [m²/s³]), qg (roll/pitch walk [rad²/s]), qba (vertical accelerometer bias walk), qb
(common range bias walk), sab (prior σ of per-anchor range offsets as 4th map coordinates; 0: none),
sr, nu (Student-t ranges), ds (IMU samples averaged per input, 1 kHz log).

Model: robot [p (3), v (3), roll, pitch, b_az, b]; roll and pitch integrated from the gyro (their
kinematics do not involve yaw, started from the accelerometer at rest), the vertical acceleration
(R f)_z − b_az − g from the accelerometer; horizontal constant velocity as shipped.  The values
were explored against the motion-capture truth (a study; nothing shipped is chosen with it).
Measured on 2026-12-06 (docs/datasets.md, UTIL): imu=0 0.209 m; imu=1 qz=0.01 0.201 m, qz=0.001
0.192 m; with per-anchor offset states (sab=0.2) 0.35 m — the offsets settle while the drone
stands before take-off, where they trade with the position, and end far from the truth's.
"""
import argparse
import os
import time

# an entry point: OpenBLAS reads this when NumPy loads, which jaxslam.cli.common's package does
# (a user's own setting is kept)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from jaxslam.cli.common import ScriptParser, nonnegative_float, positive_float, positive_int

DEFAULT_DATA = "../shared/data"  # when $JAXSLAM_DATA_DIR is not set (a checkout beside the shared data)

#: key -> (type, default) of the ``key=value`` settings (the docstring's keys)
KEYS = {"imu": (lambda t: int(_choice(t, ("0", "1"))), 1), "qh": (nonnegative_float, 0.139),
        "qz": (nonnegative_float, 0.01), "qg": (nonnegative_float, 1e-4), "qba": (nonnegative_float, 1e-4),
        "qb": (nonnegative_float, 3.4e-5), "sab": (nonnegative_float, 0.0), "sr": (positive_float, 0.0592),
        "nu": (positive_float, 5.0), "ds": (positive_int, 5)}


def _choice(text, allowed):
    if text not in allowed:
        raise argparse.ArgumentTypeError(f"expected {' or '.join(allowed)}, got {text!r}")
    return text


def _setting(text: str):
    """argparse type: ``key=value`` with a known key, the value read by the key's type:
    ``(key, text value, value)``.  (An unknown key -- a typo -- was ignored, the default run.)"""
    key, eq, raw = text.partition("=")
    if not eq:
        raise argparse.ArgumentTypeError(f"expected key=value, got {text!r}")
    if key not in KEYS:
        raise argparse.ArgumentTypeError(f"unknown key {key!r} in {text!r}; the keys: {', '.join(KEYS)}")
    try:
        return key, raw, KEYS[key][0](raw)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{key}: {e}") from None


def parser():
    ap = ScriptParser(prog="study_util_imu_vertical.py", description=__doc__.splitlines()[0])
    ap.add_argument("settings", nargs="*", type=_setting, metavar="key=value",
                    help=f"settings (keys: {', '.join(KEYS)}; see the docstring)")
    return ap


def parse(argv=None):
    """``({key: text value} as given, {key: value} with every default)``; a usage error exits 2."""
    ap = parser()
    given = ap.parse_args(argv).settings
    keys = [k for k, _, _ in given]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:  # (the last one won, silently)
        ap.error(f"key=value: {', '.join(dup)} given more than once")
    values = {k: default for k, (_, default) in KEYS.items()}
    values.update({k: v for k, _, v in given})
    return {k: raw for k, raw, _ in given}, values


def main(argv=None):
    args, v = parse(argv)
    DATA = os.environ.get("JAXSLAM_DATA_DIR") or DEFAULT_DATA
    if not os.path.isdir(DATA):  # (a MissingDataError traceback after the JAX imports)
        parser().error(f"$JAXSLAM_DATA_DIR: {DATA!r} is not a folder" if DATA != DEFAULT_DATA else
                       f"$JAXSLAM_DATA_DIR: not set, and the default data folder {DATA!r} is not a folder; set "
                       "$JAXSLAM_DATA_DIR to the folder holding util_uwb/")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import numpy as np, jax, jax.numpy as jnp  # noqa: E401
    jax.config.update("jax_enable_x64", True)
    from jaxslam.data.util_uwb import load_util
    from jaxslam.data.events import merge_events
    from jaxslam.filters import ekf_slam as es
    from jaxslam.filters import trilateration as tri
    from jaxslam.linalg import safe_norm

    q_h, q_z, q_g, q_ba, q_b = v["qh"], v["qz"], v["qg"], v["qba"], v["qb"]
    sig_ab, sigma_r, nu, ds, imu_on = v["sab"], v["sr"], v["nu"], v["ds"], v["imu"]
    G = 9.81
    d = load_util(os.path.join(DATA, "util_uwb") if os.path.isdir(os.path.join(DATA, "util_uwb")) else DATA)
    # IMU block means (ds samples)
    n = (d.imu_t.shape[0] // ds) * ds
    it = d.imu_t[:n].reshape(-1, ds)[:, -1]
    U = np.concatenate([d.acc[:n].reshape(-1, ds, 3).mean(1), d.gyro[:n].reshape(-1, ds, 3).mean(1)], 1)
    f0 = d.acc[d.imu_t < 1.0].mean(0)
    phi0 = np.arctan2(f0[1], f0[2]); th0 = np.arctan2(-f0[0], np.hypot(f0[1], f0[2]))
    log = merge_events(it, U, d.twr_t, d.twr_range.reshape(-1, 1), meas_ids=d.twr_anchor, K=1, input_mode="rate")
    NR = 10  # p3 v3 phi theta b_az b
    def motion(s, u, dt):
        p, v, phi, th, baz, b = s[0:3], s[3:6], s[6], s[7], s[8], s[9]
        f, w = u[0:3], u[3:6]
        az = (-jnp.sin(th) * f[0] + jnp.sin(phi) * jnp.cos(th) * f[1] + jnp.cos(phi) * jnp.cos(th) * f[2]) - baz - G
        az = az * imu_on
        a = jnp.stack([0.0 * az, 0.0 * az, az])
        dphi = w[0] + jnp.tan(th) * (jnp.sin(phi) * w[1] + jnp.cos(phi) * w[2])
        dth = jnp.cos(phi) * w[1] - jnp.sin(phi) * w[2]
        return jnp.concatenate([p + v * dt + 0.5 * a * dt**2, v + a * dt, jnp.stack([phi + dphi * dt, th + dth * dt, baz, b])])
    def Qd(dt):
        dt = jnp.asarray(dt, jnp.float64)
        Q = jnp.zeros((NR, NR))
        for k, q in ((0, q_h), (1, q_h), (2, q_z)):
            Q = Q.at[k, k].set(q * dt**3 / 3).at[k, 3 + k].set(q * dt**2 / 2).at[3 + k, k].set(q * dt**2 / 2).at[3 + k, 3 + k].set(q * dt)
        return Q.at[6, 6].set(q_g * dt).at[7, 7].set(q_g * dt).at[8, 8].set(q_ba * dt).at[9, 9].set(q_b * dt)
    def obs(s, l, params=None):
        return jnp.reshape(safe_norm(s[:3] - l[:3]) + s[9] + l[3], (1,))
    M = es.SlamModel(robot_dim=NR, lm_dim=4, meas_dim=1, motion=lambda s, u, pp: s, observe=obs)
    aid = jnp.asarray(d.anchor_id, jnp.int32); N = aid.shape[0]; anchors = jnp.asarray(d.anchor_p)
    # init: trilateration of first 16 ranges
    z0, ids0 = jnp.asarray(d.twr_range[:16]), jnp.asarray(d.twr_anchor[:16])
    eq = ids0[:, None] == aid[None, :]
    fix = tri.trilaterate(anchors[jnp.argmax(eq, axis=1)], z0, mask=jnp.any(eq, axis=1))
    s0 = jnp.concatenate([fix.position, jnp.zeros(3), jnp.asarray([phi0, th0, 0.0, 0.0])])
    p0 = jnp.asarray([0.3] * 3 + [0.1] * 3 + [0.02, 0.02, 0.3, 0.5])
    st = es.init(s0, jnp.diag(p0 * p0), N, 4)
    L = jnp.concatenate([anchors, jnp.zeros((N, 1))], 1)
    x = st.x.at[NR:NR + 4 * N].set(L.reshape(-1))
    Pd = jnp.diagonal(st.P).at[NR:NR + 4 * N].set(jnp.tile(jnp.asarray([0, 0, 0, sig_ab**2]), N))
    st = st._replace(x=x, P=jnp.diag(Pd), active=st.active.at[:N].set(True), ids=st.ids.at[:N].set(aid))
    Rm = jnp.reshape(sigma_r**2, (1, 1))
    @jax.jit
    def run(st, dt, u, z, ids, mask):
        def step(st, inp):
            dt_k, u_k, z_k, id_k, m_k = inp
            st = es.predict(st, M._replace(motion=lambda s, uu, pp: motion(s, u_k, dt_k)), None, Qd(dt_k))
            slots, mapped = es.associate_known(st, id_k, m_k)
            st, info = es.update(st, M, z_k, slots, mapped, Rm, robust=nu)
            return st, (st.x[:3], st.x[6:10])
        return jax.lax.scan(step, st, (dt, u, z, ids, mask))
    t0 = time.time()
    stf, (pos, aux) = run(st, jnp.asarray(log.dt), jnp.asarray(log.u), jnp.asarray(log.z), jnp.asarray(log.ids), jnp.asarray(log.mask))
    pos = np.asarray(pos); tt = np.asarray(log.t)
    tag = d.tag_positions()
    rng_ev = np.any(np.asarray(log.mask), axis=1)
    true = np.stack([np.interp(tt, d.gt_t, tag[:, j]) for j in range(3)], 1)
    sel = rng_ev & (true[:, 2] > 0.3) & (tt > d.gt_t[0]) & (tt < d.gt_t[-1])
    e = pos[sel] - true[sel]
    mid = 33.08
    h1 = tt[sel] < mid
    rm = lambda a: float(np.sqrt(np.mean(np.sum(a**2, 1))))
    off = np.asarray(stf.x[NR:NR + 4 * N]).reshape(N, 4)[:, 3]
    print(f"{args} rmse {rm(e):.4f} vert {np.sqrt(np.mean(e[:,2]**2)):.4f} horiz {rm(e[:, :2]):.4f} | 1st half {rm(e[h1]):.4f} 2nd half {rm(e[~h1]):.4f} | b {float(stf.x[9]):.3f} baz {float(stf.x[8]):.3f} off {np.round(off - off.mean(), 3)} nonfinite {int(np.sum(~np.isfinite(pos)))} t {time.time()-t0:.1f}s")


if __name__ == "__main__":
    main()
