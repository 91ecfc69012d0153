"""Development (issue 16): UTIL TWR, known anchors, ranges only -- one white-noise acceleration
density q_acc (shipped) against a horizontal/vertical pair (q_h for x and y, q_v for z), each
learned the same way (Student-t innovation NLL on the first half of the flight, 25 steps of
``jaxslam.tuning.optimize.fit`` at lr 0.1 from the hand-set values, as ``jaxslam tune util-uwb``
fits: the single density reproduces the shipped fit), judged on the held-out second half
(docs/datasets.md, UTIL).  The rule fixed before the run: the pair ships if its held-out NLL
per range beats the single density's; the position RMSE is reported, not read.

    python scripts/study_util_anisotropic.py [DATA_DIR] [--json PATH]
"""
import json
import os

from jaxslam import runtime

runtime.configure_process(cache=False)
from jaxslam.cli.common import ScriptParser, path_arg  # noqa: E402
from jaxslam.errors import InputError  # noqa: E402
from jaxslam.files import prepare_file  # noqa: E402
import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, ur, presets, optimize, window_nll, heldout_nll, util_flight, NU, orig
    import jax
    import jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    from jaxslam.systems import util_range as ur
    from jaxslam.data import presets
    from jaxslam.tuning import optimize
    from jaxslam.tuning.targets import window_nll, heldout_nll
    from jaxslam.tuning.targets.util_uwb import util_flight, NU
    orig = ur.cv_process_noise


DEFAULT_DATA = "../shared/data"  # DATA_DIR when neither it nor $JAXSLAM_DATA_DIR is given


def cv_aniso(dt, q_acc, q_bias, dtype=None):  # q_acc scalar or (3,) per axis
    q = jnp.asarray(q_acc)
    if q.ndim == 0:
        return orig(dt, q_acc, q_bias, dtype)
    dtype = dtype or q.dtype
    Q = orig(dt, jnp.asarray(1.0, dtype), q_bias, dtype)
    s = jnp.sqrt(jnp.concatenate([q, q, jnp.ones((1,), dtype)]).astype(dtype))
    return Q.at[:6, :6].set(Q[:6, :6] * s[:6, None] * s[None, :6])


def parser():
    ap = ScriptParser(prog="study_util_anisotropic.py", description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=os.environ.get("JAXSLAM_DATA_DIR", DEFAULT_DATA), type=path_arg,
                    metavar="DATA_DIR", help=f"the data folder (default: $JAXSLAM_DATA_DIR, else {DEFAULT_DATA})")
    ap.add_argument("--json", default=None, type=path_arg, metavar="PATH", help="write the results here")
    return ap


def main(argv=None):
    ap = parser()
    a = ap.parse_args(argv)
    data, jpath = a.data, a.json
    if not os.path.isdir(data):  # (a MissingDataError traceback after the JAX imports)
        ap.error(f"DATA_DIR: {data!r} (the default when neither DATA_DIR nor $JAXSLAM_DATA_DIR is given) is not "
                 "a folder; give DATA_DIR, the folder holding util_uwb/" if data == DEFAULT_DATA
                 and not os.environ.get("JAXSLAM_DATA_DIR") else f"DATA_DIR: {data!r} is not a folder")
    if jpath:
        try:  # an unusable path (a folder, under a file) before the fits, not after them
            prepare_file("--json", jpath)
        except InputError as e:
            ap.error(str(e))
    _import_jax()
    ur.cv_process_noise = cv_aniso  # (only while the study runs: importing this file patched the library)
    try:
        out = _study(data)
    finally:
        ur.cv_process_noise = orig
    if jpath:
        json.dump(out, open(jpath, "w"), indent=1)


def _study(data):
    log, t, true, air = util_flight(data)
    t_split = float(t[0] + 0.5 * (t[-1] - t[0])); held = t >= t_split
    fit_log, t_fit, _, _ = util_flight(data, t_end=t_split)
    w = jnp.asarray(t_fit < t_split, jnp.float64)
    train = {"log": jax.tree.map(lambda a: a[None], fit_log), "w": w[None]}
    base = presets.util_params(preset="hand")
    cfg = ur.Config(height=False)
    out = {}
    for name in ("shipped_3", "aniso_4"):
        if name == "shipped_3":
            th0 = jnp.log(jnp.asarray([base.sigma_r, base.q_acc, base.q_bias]))
            phys = lambda th: base._replace(sigma_r=jnp.exp(th[0]), q_acc=jnp.exp(th[1]), q_bias=jnp.exp(th[2]), gate=None, nu=NU)
        else:
            th0 = jnp.log(jnp.asarray([base.sigma_r, base.q_acc, base.q_acc, base.q_bias]))
            phys = lambda th: base._replace(sigma_r=jnp.exp(th[0]), q_acc=jnp.exp(jnp.stack([th[1], th[1], th[2]])),
                                            q_bias=jnp.exp(th[3]), gate=None, nu=NU)
        # the fit of `jaxslam tune util-uwb` (optimize.fit with its defaults, the target's batch)
        fit = optimize.fit(lambda t, item: window_nll(ur.run(item["log"], cfg, phys(t["th"])), item["w"]),
                           {"th": th0}, train, steps=25, lr=0.1, sequential=True)
        th, v = fit.theta["th"], fit.history[-1]["loss"]
        res = ur.run(log, cfg, phys(th))
        err = np.linalg.norm(np.asarray(res.pos) - true, axis=1)
        ev = held & air
        out[name] = {"theta_phys": np.exp(np.asarray(th)).tolist(), "train_nll": float(v),
                     "heldout_nll": heldout_nll(res, held), "heldout_pos_rmse_m": float(np.sqrt(np.mean(err[ev]**2))),
                     "heldout_vertical_m": float(np.sqrt(np.mean((np.asarray(res.pos)[ev, 2] - true[ev, 2])**2))),
                     "whole_airborne_rmse_m": float(np.sqrt(np.mean(err[air]**2)))}
        print(name, out[name], flush=True)
    return out


if __name__ == "__main__":
    main()
