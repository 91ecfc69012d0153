"""Development: NN vs NN + pairwise joint check vs JCBB on MRCLAM with ids hidden and on Victoria Park (docs/datasets.md).

    python scripts/study_association_compare.py mrclam fitted|hand [DATA_DIR]
    python scripts/study_association_compare.py vp - [DATA_DIR]

DATA_DIR: the folder holding mrclam6/ and victoria_park/ (default: $JAXSLAM_DATA_DIR).

Prints ATE (at the filter's events), landmarks mapped, rejected rows and run time per robot and
association; ground truth is used only for the printed ATE.
"""
import sys, time, json
from jaxslam import runtime
runtime.configure_process()
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from jaxslam.data import merge_events
from jaxslam.data.mrclam import load_mrclam
from jaxslam.data.runners import evaluate_planar
from jaxslam.data import presets
from jaxslam.systems import planar_ekf_slam as pe
which = sys.argv[1]
DATA = sys.argv[3] if len(sys.argv) > 3 else __import__("os").environ["JAXSLAM_DATA_DIR"]
out = {}
def timed(f):
    r = f(); jax.block_until_ready(r.pose); t = time.time(); r = f(); jax.block_until_ready(r.pose); return r, time.time() - t
if which == "mrclam":
    for r in range(1, 6):
        d = load_mrclam(DATA, r)
        log, pose0 = presets.mrclam_raw_log(d, K=8)
        prm = presets.mrclam_params(r, preset=sys.argv[2])
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
