"""Development: the FastSLAM step (paper 001, bench fastslam's program) compiled with XLA's
CPU fusion emitters off (the library's CPU option) and on, timed alternately in one process.

    python scripts/study_fastslam_fusion_emitters.py [N]   (default N = 2000 particles)

Measured on 2026-12-06 (2 cores, a slower machine than the benchmark JSON's, N = 2000, medians
of 7 alternating repeats of 60 steps): emitters off 3973 ns per particle and step (CPU 6297),
on 3502 ns (CPU 5393), −12 %; compile 10.4 → 11.7 s; states equal to 3e-18.  Not adopted
(docs/papers.md, FastSLAM benchmark).
"""
import os
import sys
import time
import types

# an entry point: OpenBLAS reads this when NumPy loads, which jaxslam.cli.common's package does
# (a user's own setting is kept)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from jaxslam.cli.common import ScriptParser, positive_int


def parser():
    ap = ScriptParser(prog="study_fastslam_fusion_emitters.py", description=__doc__.splitlines()[0])
    ap.add_argument("N", nargs="?", type=positive_int, default=2000, help="particles (default 2000)")
    return ap


def main(argv=None):
    N = parser().parse_args(argv).N  # (before JAX: its flags below are read when it starts)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ["XLA_FLAGS"] = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
    import numpy as np, jax, jax.numpy as jnp  # noqa: E401
    jax.config.update("jax_enable_x64", True)
    ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sys.path.insert(0, os.path.join(ROOT, "benchmarks")); sys.path.insert(0, os.path.join(ROOT, "tests", "oracles"))  # noqa: E702
    import bench_fastslam as b
    from jaxslam.systems import fastslam_001 as fs1
    args = types.SimpleNamespace(seed=0)
    cfg, prm, fl, ids = b._setup(args, 10)
    inp = tuple(jnp.asarray(a) for a in b._per_step_inputs(fl, ids)); T = inp[0].shape[0]
    ids_d = jnp.asarray(ids); keys = jax.random.split(jax.random.PRNGKey(2), T)
    st = fs1.init(b._log0(jnp.asarray(fl.truth[0])), cfg._replace(n_particles=N), prm, key=jax.random.PRNGKey(1))
    ob = b._outbuf(T, jnp.float64)
    adv = b._advance_fn(cfg, prm)
    low = adv.lower(st, ob, inp, ids_d, keys, jnp.int32(0), jnp.int32(20))
    progs = {}
    for name, opt in [("emit_off", {"xla_cpu_use_fusion_emitters": False}), ("emit_on", {"xla_cpu_use_fusion_emitters": True})]:
        t0 = time.perf_counter(); progs[name] = low.compile(compiler_options=opt); print(name, "compile", round(time.perf_counter()-t0, 1), flush=True)
    warm = {}
    for name, p in progs.items():
        s, o = p(*b._copy((st, ob)), inp, ids_d, keys, jnp.int32(0), jnp.int32(20)); warm[name] = jax.block_until_ready((s, o))
    res = {k: [] for k in progs}
    for rep in range(7):
        for name, p in progs.items():
            s, o = b._copy(warm[name])
            w, c = time.perf_counter(), time.process_time()
            jax.block_until_ready(p(s, o, inp, ids_d, keys, jnp.int32(20), jnp.int32(60)))
            res[name].append(((time.perf_counter()-w)/60/N*1e9, (time.process_time()-c)/60/N*1e9))
    for k, v in res.items():
        a = np.array(v); print(k, "ns/particle/step wall med", np.median(a[:,0]).round(0), "cpu med", np.median(a[:,1]).round(0), "all wall", a[:,0].round(0))
    # agreement
    a = jax.tree.leaves(warm["emit_off"]); c = jax.tree.leaves(warm["emit_on"])
    print("max diff", max(float(jnp.max(jnp.abs(x.astype(float)-y.astype(float)))) for x, y in zip(a, c)))


if __name__ == "__main__":
    main()
