"""Development: NN vs NN + pairwise joint check vs JCBB on MRCLAM with ids hidden and on Victoria Park (docs/datasets.md).

    python scripts/study_association_compare.py mrclam fitted|hand [DATA_DIR]
    python scripts/study_association_compare.py vp - [DATA_DIR]      (or vp alone)

DATA_DIR: the folder holding mrclam6/ and victoria_park/ (default: $JAXSLAM_DATA_DIR).

Prints ATE (at the filter's events), landmarks mapped, rejected rows and run time per robot and
association; ground truth is used only for the printed ATE.
"""
import json
import time

from jaxslam import runtime

runtime.configure_process()
from jaxslam.cli.common import ScriptParser, path_arg  # noqa: E402
import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, merge_events, load_mrclam, evaluate_planar, presets, pe
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from jaxslam.data import merge_events
    from jaxslam.data.mrclam import load_mrclam
    from jaxslam.data.runners import evaluate_planar
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as pe


PRESETS = ("fitted", "hand")  # presets.mrclam_params(preset=...)


def parser():
    ap = ScriptParser(prog="study_association_compare.py", description=__doc__.splitlines()[0])
    ap.add_argument("which", choices=("mrclam", "vp"), help="MRCLAM robots 1-5 (ids hidden) or Victoria Park")
    ap.add_argument("preset", nargs="?", default=None,
                    help="mrclam: the noise preset, fitted or hand; vp: '-' (it has one preset)")
    ap.add_argument("data", nargs="?", default=None, type=path_arg, metavar="DATA_DIR",
                    help="the folder holding mrclam6/ and victoria_park/ (default: $JAXSLAM_DATA_DIR)")
    return ap


def parse(argv=None):
    """The checked arguments (a usage error exits 2 with one line, before any data is read)."""
    ap = parser()
    a = ap.parse_args(argv)
    if a.which == "mrclam" and a.preset not in PRESETS:  # (a missing one was an IndexError, a typo a traceback)
        ap.error(f"preset: mrclam needs one of {', '.join(PRESETS)}, got {a.preset!r}")
    if a.which == "vp" and a.preset not in (None, "-"):  # (anything there was ignored)
        ap.error(f"preset: vp has one preset, give '-' (or nothing), got {a.preset!r}")
    a.data = ap.data_root(a.data, flag="DATA_DIR")
    return a


def timed(f):
    r = f(); jax.block_until_ready(r.pose); t = time.time(); r = f(); jax.block_until_ready(r.pose); return r, time.time() - t  # noqa: E702


def main(argv=None):
    a = parse(argv)
    _import_jax()
    which, DATA = a.which, a.data
    out = {}
    if which == "mrclam":
        for r in range(1, 6):
            d = load_mrclam(DATA, r)
            log, pose0 = presets.mrclam_raw_log(d, K=8)
            prm = presets.mrclam_params(r, preset=a.preset)
            for name, kw in (("nn", {}), ("nn+joint", {"joint_gate": 0.99}), ("jcbb", {"association": "jcbb"})):
                cfg = presets.mrclam_config(association="nn", capacity=32)._replace(**kw)  # the table's capacity
                res, rt = timed(lambda: pe.run(pe.log_from_events(log, jnp.asarray(pose0)), cfg, prm))
                m, _ = evaluate_planar(log.t, np.asarray(res.pose), d.gt_t, d.gt)
                print(f"mrclam r{r} {name:9s} ATE {m['ate_m']:.3f} m  landmarks {int(np.sum(res.active))}  rejected {int(np.sum(res.n_rejected))}  run {rt:.2f} s", flush=True)
                out[f"r{r}_{name}"] = {"ate_m": m["ate_m"], "landmarks": int(np.sum(res.active)), "run_s": rt}
    else:
        from jaxslam.data.victoria_park import load_victoria_park
        d = load_victoria_park(DATA)
        log = merge_events(d.input_t, d.inputs, d.det_t, d.det, K=None, input_mode="rate")
        prm = presets.victoria_park_params(dtype=jnp.float32)
        for name, kw in (("nn", {}), ("nn+joint", {"joint_gate": 0.99}), ("jcbb", {"association": "jcbb"})):
            cfg = presets.victoria_park_config()._replace(**kw)
            prm32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), prm)
            res, rt = timed(lambda: pe.run(pe.log_from_events(log, jnp.zeros(3, jnp.float32)), cfg, prm32))
            m, _ = evaluate_planar(log.t, np.asarray(res.pose, np.float64), d.gps_t, d.gps, at_ref_times=True)
            print(f"vp {name:9s} ATE {m['ate_m']:.3f} m landmarks {int(np.sum(res.active))} status {int(res.status)} run {rt:.2f} s", flush=True)
            out[name] = {"ate_m": m["ate_m"], "landmarks": int(np.sum(res.active)), "run_s": rt, "status": int(res.status)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
