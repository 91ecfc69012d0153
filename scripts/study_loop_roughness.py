"""Development (issue 21): is the pathwise gradient of the estimator's error through the closed
loop predictive?  Line searches from the start θ₀ (Table 2's weights, the ``--q imu`` filter) of
the joint loop target (``--tune both``) on 16 training flights of 25 s, ``--seed 2`` (flights
``keys_for(2, 16)``; neither the validation nor the held-out set of the shipped run).

Two per-flight quantities, each read from targets that fly the same flights:

* ``mse``: the estimator's position MSE mean_t ‖ρ̂ − ρ‖², as the difference of two targets
  (``w_mse = 1`` and ``w_mse = 0``, effort, tilt and NEES weights 0; the tracking term cancels);
* ``J``: the shipped joint objective (``--w-nees 10 --w-mse 300``, effort 0.1, tilt 10 above 12°).

Part ``line``: for each, its batch-mean gradient g at θ₀, then the batch mean at θ₀ − s·g/‖g‖
for s in ``STEPS`` (log-parameter units), against the first-order prediction −s‖g‖; also the
largest per-flight rise.  A gradient is predictive at step s when the mean falls by about s‖g‖.

Part ``probe``: J per flight at θ₀ + h·d, d a fixed random unit direction, h in ``PROBE``:
the median and largest relative change.  Linear in h where the flight is smooth; a change far
above the median's line is a jump (a discrete event of the flight moved: a landmark entering or
leaving the field of view, a sighting's slot, an association).  Also whether two evaluations at
θ₀ agree bit for bit.

    python scripts/study_loop_roughness.py [unknown|known ...] [--parts line,probe] [--out FILE]

``--out`` is updated in place: parts already there and not rerun are kept.
"""
import json
import pathlib
import time

from jaxslam import runtime
from jaxslam.cli.common import ScriptParser, path_arg
from jaxslam.errors import InputError
from jaxslam.files import prepare_file

runtime.configure_process(cache=False)
import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, get
    import jax
    import jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    from jaxslam.tuning.targets import get


STEPS = (0.001, 0.003, 0.01, 0.03, 0.1)
PROBE = (1e-12, 1e-9, 1e-6, 1e-3, 1e-2)
COMMON = dict(tune="both", train_runs=16, test_runs=1, train_duration=25.0, eval_duration=1.0, seed=2)
SHIPPED = dict(w_nees=10.0, w_mse=300.0)


def per_flight(tg):
    return jax.jit(lambda th: jax.lax.map(lambda it: tg.loss_fn(th, it), tg.train))


def mean_grad(tg):
    return jax.jit(jax.grad(lambda th: jnp.mean(jax.lax.map(lambda it: tg.loss_fn(th, it), tg.train))))


def norm(g):
    return float(jnp.sqrt(sum(jnp.sum(x * x) for x in g.values())))


def line(fn, theta0, g, start):
    gn, rows = norm(g), []
    for s in STEPS:
        th = {k: theta0[k] - s * g[k] / gn for k in g}
        v = np.asarray(fn(th))
        rows.append({"step": s, "mean": float(v.mean()), "change": float(v.mean() - start.mean()),
                     "predicted_change": -s * gn, "largest_flight_rise": float(np.max(v - start))})
    return {"grad_norm": gn, "start_mean": float(start.mean()), "line": rows}


def probe(mode):
    t0 = time.time()
    tg = get(f"ekfslam3d-{mode}", "loop", "cost", **COMMON, **SHIPPED)
    f = per_flight(tg)
    rng = np.random.default_rng(0)
    d = {k: rng.standard_normal(v.shape) for k, v in tg.theta0.items()}
    n = float(np.sqrt(sum(np.sum(x * x) for x in d.values())))
    j0, j0b = np.asarray(f(tg.theta0)), np.asarray(f(tg.theta0))
    rows = []
    for h in PROBE:
        j = np.asarray(f({k: tg.theta0[k] + h * d[k] / n for k in d}))
        r = np.abs(j - j0) / np.abs(j0)
        rows.append({"h": h, "median_rel_change": float(np.median(r)), "max_rel_change": float(np.max(r)),
                     "flights_over_100x_median": int(np.sum(r > 100 * np.median(r)))})
    return {"repeat_bitwise_equal": bool(np.array_equal(j0, j0b)), "rows": rows, "seconds": time.time() - t0}


def study(mode):
    t0 = time.time()
    name = f"ekfslam3d-{mode}"
    zero = dict(w_u=0.0, w_tilt=0.0, w_nees=0.0)
    with_mse = get(name, "loop", "cost", **COMMON, **zero, w_mse=1.0)
    without = get(name, "loop", "cost", **COMMON, **zero, w_mse=0.0)
    shipped = get(name, "loop", "cost", **COMMON, **SHIPPED)
    th0 = shipped.theta0
    f1, f0, fj = per_flight(with_mse), per_flight(without), per_flight(shipped)

    def mse(th):
        return np.asarray(f1(th)) - np.asarray(f0(th))

    g_mse = jax.tree.map(lambda a, b: a - b, mean_grad(with_mse)(th0), mean_grad(without)(th0))
    g_j = mean_grad(shipped)(th0)
    out = {"mse": line(mse, th0, g_mse, mse(th0)), "J": line(fj, th0, g_j, np.asarray(fj(th0)))}
    out["mse"]["start_per_flight"] = [float(x) for x in mse(th0)]
    out["seconds"] = time.time() - t0
    return out


MODES = ("unknown", "known")
PARTS = ("line", "probe")


def main(argv=None):
    ap = ScriptParser(prog="study_loop_roughness.py", description=__doc__.splitlines()[0])
    ap.add_argument("modes", nargs="*", default=list(MODES), help=f"some of {', '.join(MODES)} (default both)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {', '.join(PARTS)}")
    ap.add_argument("--out", default="docs/results/tuning/loop_roughness.json", type=path_arg)
    a = ap.parse_args(argv)
    unknown = [m for m in a.modes if m not in MODES]
    if unknown:
        ap.error(f"modes: unknown {', '.join(map(repr, unknown))}; expected some of {', '.join(MODES)}")
    parts = [s.strip() for s in a.parts.split(",") if s.strip()]
    if not parts or set(parts) - set(PARTS):  # (an unknown part ran nothing and rewrote --out)
        ap.error(f"--parts: expected a comma-separated subset of {', '.join(PARTS)}, got {a.parts!r}")
    p = pathlib.Path(a.out)
    try:  # --out is updated in place: readable and writable before the study, not after it
        prepare_file("--out", p)
        res = json.loads(p.read_text()) if p.exists() else {}
    except InputError as e:
        ap.error(str(e))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        ap.error(f"--out: cannot update {str(p)!r}: {getattr(e, 'strerror', None) or e}"[:300])
    if not isinstance(res, dict):
        ap.error(f"--out: {str(p)!r} holds no JSON object to update")
    _import_jax()
    res.update({"purpose": __doc__.split("\n\n")[0], "setting": {**COMMON, "shipped_objective": SHIPPED},
                "steps": list(STEPS), "probe_steps": list(PROBE)})
    res.setdefault("modes", {})
    for m in a.modes:
        res["modes"].setdefault(m, {})
        if "line" in parts:
            res["modes"][m].update(study(m))
            for q in ("mse", "J"):
                r = res["modes"][m][q]
                print(m, q, f"|g| {r['grad_norm']:.4g} start {r['start_mean']:.5g}", flush=True)
                for row in r["line"]:
                    print(f"   s {row['step']:<6g} change {row['change']:+.4g}  predicted "
                          f"{row['predicted_change']:+.4g}  largest flight rise {row['largest_flight_rise']:+.4g}",
                          flush=True)
        if "probe" in parts:
            res["modes"][m]["probe"] = pr = probe(m)
            print(m, "probe; repeat bitwise equal:", pr["repeat_bitwise_equal"], flush=True)
            for row in pr["rows"]:
                print(f"   h {row['h']:<6g} median {row['median_rel_change']:.3g}  max {row['max_rel_change']:.3g}"
                      f"  flights > 100x median {row['flights_over_100x_median']}", flush=True)
    p.write_text(json.dumps(res, indent=1) + "\n")
    print("wrote", p)


if __name__ == "__main__":
    main()
