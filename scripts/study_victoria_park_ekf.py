"""Dev/evaluation: Victoria Park EKF-SLAM (issue 9): ATE vs GPS, counts, run time.

    python scripts/study_victoria_park_ekf.py  (the data folder: $JAXSLAM_DATA_DIR)

ATE: SE(2)-aligned, estimate interpolated at GPS times; ``ate_raw`` uses every fix,
``ate_all``/``ate_first`` (t < 500 s)/``ate_rest`` (t ≥ 500 s) drop the GPS fixes that are
> 15 m/s away from both neighbours (2 fixes: 270.7 s and 1223.3 s, a 141 m jump).

The helpers (``make_log``, ``ate``, ``run``) serve investigations in an interpreter: call
``load()`` first (importing this file no longer reads the data).
"""
import sys, time, json
import pathlib
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from jaxslam import runtime
runtime.configure_process()
from jaxslam.cli.common import ScriptParser, one_line  # noqa: E402
from jaxslam.data import catalogue  # noqa: E402
from jaxslam.errors import InputError  # noqa: E402
import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read (--help
    and a usage error exit before JAX loads), and by load()/run() (the helper investigations)."""
    global jax, jnp, metrics, load_victoria_park, merge_events, presets, P
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jaxslam import metrics
    from jaxslam.data import load_victoria_park, merge_events
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as P


D = GPS_OK = None  # the data and its usable GPS fixes, set by load() (main, or a helper investigation's first call)


def load(data=None):
    """Read Victoria Park from ``data`` (default: $JAXSLAM_DATA_DIR) into ``D`` and ``GPS_OK``."""
    global D, GPS_OK
    root = str(catalogue.data_root(data, flag="$JAXSLAM_DATA_DIR"))  # (an unset variable: before JAX loads)
    _import_jax()
    D = load_victoria_park(root)
    _d = np.linalg.norm(np.diff(D.gps, axis=0), axis=1) / np.maximum(np.diff(D.gps_t), 1e-3)
    _vin = np.concatenate([[0.0], _d]); _vout = np.concatenate([_d, [0.0]])  # noqa: E702
    GPS_OK = ~((_vin > 15.0) & (_vout > 15.0))  # a fix >15 m/s away from both neighbours (car max 6.6 m/s)
    print("GPS outliers dropped:", int((~GPS_OK).sum()), D.gps_t[~GPS_OK])


def make_log(t_end=None, min_diam=None, max_diam=None):
    keep = np.ones(len(D.det_t), bool)
    if min_diam is not None: keep &= D.det_diameter >= min_diam
    if max_diam is not None: keep &= D.det_diameter <= max_diam
    return merge_events(D.input_t, D.inputs, D.det_t[keep], D.det[keep], K=None, input_mode="rate", t_end=t_end)

def ate(t_est, xy, t0=None, t1=None, clean=True):
    g_t, g = D.gps_t, D.gps
    m = (g_t >= t_est[0]) & (g_t <= t_est[-1])
    if clean: m &= GPS_OK
    if t0 is not None: m &= g_t >= t0
    if t1 is not None: m &= g_t < t1
    e = np.stack([np.interp(g_t[m], t_est, xy[:, 0]), np.interp(g_t[m], t_est, xy[:, 1])], 1)
    return float(metrics.ate(e, g[m], align="rigid")), int(m.sum())

def run(cfg, prm, log, dtype=None, time_it=True, quiet=False):
    """dtype: default float32."""
    _import_jax()
    dtype = jnp.float32 if dtype is None else dtype
    prm = jax.tree_util.tree_map(lambda a: None if a is None else jnp.asarray(a, dtype), prm)
    p0 = jnp.zeros(3, dtype)
    t0 = time.perf_counter(); r = P.run(P.log_from_events(log, p0), cfg, prm); jax.block_until_ready(r); t1 = time.perf_counter()
    trun = None
    if time_it:
        r = P.run(P.log_from_events(log, p0), cfg, prm); jax.block_until_ready(r); trun = time.perf_counter() - t1
    xy = np.asarray(r.pose[:, :2], np.float64)
    out = dict(ate_raw=ate(log.t, xy, clean=False)[0], ate_all=ate(log.t, xy)[0], ate_first=ate(log.t, xy, t1=500.0)[0],
               ate_rest=ate(log.t, xy, t0=500.0)[0] if log.t[-1] > 600 else None,
               first_s=round(t1 - t0, 1), run_s=None if trun is None else round(trun, 2),
               mapped=int(np.sum(np.asarray(r.active))), overflow=int(r.overflow), status=int(r.status),
               finite=bool(np.all(np.isfinite(xy))))
    for k in ("n_meas", "n_limited", "n_dropped", "n_used", "n_gated", "n_rejected", "n_registered", "n_pruned"):
        v = getattr(r, k, None)
        if v is not None: out[k] = int(np.sum(np.asarray(v)))
    if not quiet: print(json.dumps(out), flush=True)
    return out, r


def parser():
    return ScriptParser(prog="study_victoria_park_ekf.py", description=__doc__.splitlines()[0],
                        epilog="The data folder: $JAXSLAM_DATA_DIR.")


def main(argv=None):
    ap = parser()
    ap.parse_args(argv)  # (no arguments: anything given was ignored)
    try:  # an unset $JAXSLAM_DATA_DIR was a KeyError traceback, at import
        load()  # (imports JAX)
    except InputError as e:
        ap.error(one_line(str(e)))
    log = make_log()
    run(presets.victoria_park_config(), presets.victoria_park_params(), log, jnp.float32)


if __name__ == "__main__":
    main()
