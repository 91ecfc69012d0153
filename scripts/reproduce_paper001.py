"""Reproduce paper 001's Sec. IV-B comparisons: dynamics- vs kinematics-based FastSLAM.

For each IMU bias level (0.0005 and 0.005 m/s² / rad/s on every axis) the script simulates R
seeded flights of ``fastslam-helix`` once (vmapped) and runs every filter configuration on the
*same* flights (paired comparison):

* ``kinematics``           — IMU-driven FastSLAM 1.0 without calibration (the paper's baseline);
* ``dynamics``             — paper 001's two-stage filter (rotor-input dynamics, bias KF,
  stage 2 regenerating position and rates), exact Rao-Blackwellised weights;
* ``dynamics_paperw``      — the same with the paper's mean-approximation weights (eq. 26-28);
* ``dynamics_stage1``      — stage 1 only (no Step 8 regeneration), exact weights;
* ``dynamics_mismatch``    — ``dynamics`` with the filter's inertia +150 % (truth unchanged);
* ``dynamics_stage1_mismatch`` — ``dynamics_stage1`` with the mismatch.

Writes ``OUT/bias<b>_<config>.json`` (``bias<b>_<config>_f32.json`` with ``--float32``, so a
float32 run never replaces the float64 results; run-JSON layout: config, metrics with mean /
median / p95 / max / per_run, flags, timing) and ``OUT/table.md`` (``table_f32.md``).

    python scripts/reproduce_paper001.py --runs 20 --particles 200 --duration 20 \
        --out docs/results/paper001

``--measure`` times one run of one configuration and exits (choose N and duration with it);
``--table-only`` rebuilds ``table.md`` from the JSON files already in ``--out`` (the float32
ones with ``--float32``).  A malformed option (``--biases``, a count below 1, a duration not
above 0) exits with code 2 and one line, before anything is computed.
Every figure comes from the public API (:mod:`jaxslam.sim.scenarios.fastslam`,
:mod:`jaxslam.systems.fastslam_001`).
"""

from __future__ import annotations

from jaxslam import runtime  # noqa: E402

runtime.configure_process()  # OpenBLAS one thread, XLA workaround flags: before NumPy and JAX start

import json
import pathlib
import sys
import time

import numpy as np

from jaxslam.cli.common import ScriptParser, path_arg, positive_float, positive_int, seed_int
from jaxslam.files import atomic_write

CONFIGS = {
    "kinematics": dict(model="kinematics"),
    "dynamics": dict(model="dynamics"),
    "dynamics_paperw": dict(model="dynamics", weights="paper"),
    "dynamics_stage1": dict(model="dynamics", stage2="none"),
    "dynamics_mismatch": dict(model="dynamics", inertia_mismatch=True),
    "dynamics_stage1_mismatch": dict(model="dynamics", stage2="none", inertia_mismatch=True),
}
SHOW = ["pos_rmse_m", "att_rmse_deg", "vel_rmse_mps", "landmark_rmse_m", "accel_bias_err_frac",
        "gyro_bias_err_frac", "neff_min", "resamples"]


def _json_name(bias, name, float32=False):
    return f"bias{bias:g}_{name}{'_f32' if float32 else ''}.json"


def _table_name(float32=False):
    return "table_f32.md" if float32 else "table.md"


def _options(sc, bias, particles, duration, extra):
    opts = {o.name: o.default for o in sc.OPTIONS}
    opts.update(bias=float(bias), particles=int(particles), duration=float(duration))
    opts.update(extra)
    return opts


def main(argv=None):
    ap = ScriptParser(prog="reproduce_paper001.py", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=positive_int, default=20)
    ap.add_argument("--seed", type=seed_int, default=0)
    ap.add_argument("--particles", type=positive_int, default=200)
    ap.add_argument("--duration", type=positive_float, default=20.0)
    ap.add_argument("--biases", default="0.0005,0.005")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--chunk", type=positive_int, default=None, help="runs per compiled call (default all)")
    ap.add_argument("--out", default="docs/results/paper001", type=path_arg, metavar="DIR",
                    help="the results folder: a run writes its JSONs and table here, --table-only reads "
                         "them from it (default: docs/results/paper001)")
    ap.add_argument("--float32", action="store_true")
    ap.add_argument("--measure", action="store_true", help="time one run of 'dynamics' and exit")
    ap.add_argument("--table-only", action="store_true",
                    help="run nothing: rebuild DIR/table.md (table_f32.md with --float32) from the result "
                         "JSONs of --biases x --configs an earlier run wrote in the --out folder DIR")
    args = ap.parse_args(argv)
    try:
        biases = [float(b) for b in args.biases.split(",")]
    except ValueError:
        biases = []
    if not biases or not all(np.isfinite(b) and b >= 0 for b in biases):
        ap.error(f"--biases: expected comma-separated finite numbers >= 0, got {args.biases!r}")
    names = [c for c in args.configs.split(",") if c]
    for c in names:
        if c not in CONFIGS:
            ap.error(f"--configs: unknown configuration {c!r}; choose from {sorted(CONFIGS)}")
    if args.table_only:
        out = pathlib.Path(args.out)
        if not out.is_dir():  # ("no result JSON in FILE" said of a file, as if it were a folder)
            ap.error(f"--table-only: --out {str(out)!r} is not a folder (--table-only reads the result JSONs "
                     "of an earlier run from the --out folder and writes the table there)")
        rows = rows_from_dir(out, biases, names, args.float32)
        if not rows:
            ap.error(f"--table-only: no result JSON of --biases {args.biases} x --configs {','.join(names)} in "
                     f"the --out folder {str(out)!r} (bias<b>_<config>{'_f32' if args.float32 else ''}.json)")
        r0 = rows[0][2]

        def setting(r):
            return r["runs"], r["config"]["particles"], r["config"]["duration"], r["dtype"]

        for bias, name, r in rows[1:]:  # one header describes every row
            if setting(r) != setting(r0):
                ap.error(f"--table-only: {_json_name(bias, name, args.float32)} holds (runs, particles, duration, "
                         f"dtype) {setting(r)}, {_json_name(rows[0][0], rows[0][1], args.float32)} {setting(r0)}; "
                         "rerun one of them or tabulate them apart (--configs, --biases)")
        table = make_table(rows, biases, names, r0["runs"], r0["config"]["particles"],
                           r0["config"]["duration"], r0["dtype"] == "float32")
        atomic_write(out / _table_name(args.float32), lambda f: f.write(table + "\n"))
        print(table)
        return 0

    out = ap.output_dir("--out", args.out)  # one usage line (exit 2) for an unusable --out, before JAX and any run
    import jax
    import jax.numpy as jnp

    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    from jaxslam import metrics as mx
    from jaxslam.sim import monte_carlo
    from jaxslam.sim.scenarios import fastslam as sc
    from jaxslam.systems import fastslam_001 as fs1

    dtype = jnp.float32 if args.float32 else jnp.float64

    if args.measure:
        opts = _options(sc, biases[0], args.particles, args.duration, CONFIGS["dynamics"])
        one_run, *_ = sc.build(opts, dtype)
        f = jax.jit(one_run)
        t0 = time.perf_counter()
        jax.block_until_ready(f(jax.random.PRNGKey(0)))
        t1 = time.perf_counter()
        jax.block_until_ready(f(jax.random.PRNGKey(1)))
        t2 = time.perf_counter()
        print(f"N={args.particles} duration={args.duration}s: compile+first {t1 - t0:.1f} s, "
              f"one run {t2 - t1:.2f} s")
        return 0

    rows = []
    for bias in biases:
        # One set of flights per bias level, shared by every configuration (paired runs).
        opts0 = _options(sc, bias, args.particles, args.duration, {})
        _, _, _, _, nf, setup = sc.build(opts0, dtype)
        keys = monte_carlo.keys_for(args.seed, args.runs)
        k_truth = jax.vmap(lambda k: jax.random.split(k)[0])(keys)
        k_filt = jax.vmap(lambda k: jax.random.split(k)[1])(keys)
        t0 = time.perf_counter()
        flights = jax.jit(jax.vmap(lambda k: sc.fly(setup, k, nf, sc.LIDAR_EVERY)))(k_truth)
        flights = jax.block_until_ready(flights)
        truth_s = time.perf_counter() - t0
        print(f"bias {bias}: {args.runs} flights simulated in {truth_s:.1f} s", file=sys.stderr)
        ids = jnp.arange(setup.landmarks.shape[0], dtype=jnp.int32)
        for name in names:
            opts = _options(sc, bias, args.particles, args.duration, CONFIGS[name])
            cfg, prm = sc.make_filter(opts, dtype)

            def one(k, fl, cfg=cfg, prm=prm):
                log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor, imu=fl.imu, z=fl.z, ids=ids,
                              mask=fl.mask)
                res = fs1.run(log, cfg, prm, key=k)  # cfg.n_particles = args.particles
                return sc.evaluate(fl, res, setup.landmarks, bias)

            batched = jax.jit(jax.vmap(one))
            chunk = args.chunk or args.runs
            t0 = time.perf_counter()
            compiled = batched.lower(k_filt[:chunk], jax.tree_util.tree_map(
                lambda a: a[:chunk], flights)).compile()
            compile_s = time.perf_counter() - t0
            outs = []
            t0 = time.perf_counter()
            for c0 in range(0, args.runs, chunk):
                sl = slice(c0, min(c0 + chunk, args.runs))
                kk = k_filt[sl]
                ff = jax.tree_util.tree_map(lambda a: a[sl], flights)
                pad = chunk - kk.shape[0]
                if pad:
                    kk = jnp.concatenate([kk, jnp.repeat(kk[-1:], pad, 0)])
                    ff = jax.tree_util.tree_map(lambda a: jnp.concatenate(
                        [a, jnp.repeat(a[-1:], pad, 0)]), ff)
                res = jax.block_until_ready(compiled(kk, ff))
                outs.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:chunk - pad], res))
            run_s = time.perf_counter() - t0
            m, c = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)
            report = {
                "scenario": "fastslam-helix",
                "runs": args.runs,
                "seed": args.seed,
                "dtype": "float32" if args.float32 else "float64",
                "config": {"name": name, **{k: v for k, v in opts.items() if k != "chunk"},
                           "filter": cfg._asdict(),
                           "bias_prior_sigma": sc.bias_prior_sigma(bias)},
                "metrics": {k: mx.summarize(v) for k, v in m.items()},
                "flags": {"capacity_overflow": int(np.sum(c["overflow"])),
                          "non_finite": int(np.sum(c["non_finite"])),
                          "weight_underflow": int(np.sum(c["underflow"]))},
                "timing": {"compile_s": compile_s, "run_s": run_s,
                           "runs_per_s": args.runs / run_s, "truth_s": truth_s},
                "versions": {"jax": jax.__version__},
            }
            path = out / _json_name(bias, name, args.float32)
            atomic_write(path, lambda f, report=report: f.write(json.dumps(report, indent=1)))
            print(f"  {name}: compile {compile_s:.0f} s, run {run_s:.0f} s; pos "
                  f"{report['metrics']['pos_rmse_m']['mean']:.4f} m", file=sys.stderr)
            rows.append((bias, name, report))

    table = make_table(rows, biases, names, args.runs, args.particles, args.duration,
                       args.float32)
    atomic_write(out / _table_name(args.float32), lambda f: f.write(table + "\n"))
    print(table)
    return 0


def make_table(rows, biases, names, runs, particles, duration, float32=False):
    """Markdown table and paired ratios of (bias, name, report) rows."""
    lines = [f"Paper 001 reproduction: {runs} runs per row, N = {particles} particles "
             f"(paper: 500), {duration:g} s of the helix (T = 0.01 s, LiDAR 10 Hz), "
             f"{'float32' if float32 else 'float64'}; mean (median) over runs.", "",
             "| bias | filter | " + " | ".join(SHOW) + " |", "|---" * (len(SHOW) + 2) + "|"]
    for bias, name, rep in rows:
        cells = [f"{rep['metrics'][k]['mean']:.4g} ({rep['metrics'][k]['median']:.4g})"
                 for k in SHOW]
        lines.append(f"| {bias:g} | {name} | " + " | ".join(cells) + " |")
    lines += ["", "Ratios of mean position RMSE (paired runs):", ""]
    by = {(b, n): r for b, n, r in rows}
    for bias in biases:
        kin = by.get((bias, "kinematics"))
        for name in names:
            if name == "kinematics" or kin is None or (bias, name) not in by:
                continue
            d = np.asarray(by[(bias, name)]["metrics"]["pos_rmse_m"]["per_run"])
            k = np.asarray(kin["metrics"]["pos_rmse_m"]["per_run"])
            lines.append(f"- bias {bias:g}: {name} / kinematics = {d.mean() / k.mean():.3f} "
                         f"(runs where {name} is lower: {int(np.sum(d < k))}/{len(d)})")
        base = by.get((bias, "dynamics"))
        for name in ("dynamics_mismatch", "dynamics_paperw"):
            if base is not None and (bias, name) in by:
                d = by[(bias, name)]["metrics"]["pos_rmse_m"]["mean"]
                lines.append(f"- bias {bias:g}: {name} / dynamics = "
                             f"{d / base['metrics']['pos_rmse_m']['mean']:.3f}")
        s1 = by.get((bias, "dynamics_stage1"))
        if s1 is not None and (bias, "dynamics_stage1_mismatch") in by:
            d = by[(bias, "dynamics_stage1_mismatch")]["metrics"]["pos_rmse_m"]["mean"]
            lines.append(f"- bias {bias:g}: dynamics_stage1_mismatch / dynamics_stage1 = "
                         f"{d / s1['metrics']['pos_rmse_m']['mean']:.3f}")
    return "\n".join(lines)


def rows_from_dir(out, biases, names, float32=False):
    """(bias, name, report) rows from the JSON files an earlier run wrote in ``out`` (the
    ``_f32`` ones with ``float32``)."""
    rows = []
    for bias in biases:
        for name in names:
            path = pathlib.Path(out) / _json_name(bias, name, float32)
            if path.exists():
                rows.append((bias, name, json.loads(path.read_text())))
    return rows


if __name__ == "__main__":
    sys.exit(main())
