"""Reproduce paper 003's simulations: range-only UWB EKF-SLAM and known-anchor localisation.

Runs ``uwb-circle``, ``uwb-square`` and ``uwb-rough`` (Sec. IV-A, B, C) over N seeded,
vmapped Monte Carlo runs in these cases:

* SLAM, paper filter (Q eq. 27, R 0.2/0.01), uniform noise — the paper's setting —
  with the squared range (eq. 17) and the plain range (eq. 16), and with the matched
  filter;
* localisation with known anchors: paper filter (uniform), matched filter with the
  paper's uniform noise and with Gaussian noise of the same variance (both models) —
  the consistency check and the effect of the uniform noise on it.

Writes one run JSON per case to ``--out`` (default ``docs/results/paper003``) and
``table.md`` (``table_f32.md`` and ``_f32`` JSONs with ``--float32``) with the mean and p95 of every metric, the largest position error of
any run, and the ANEES (position, 2 states; robot block, 10 states) against their
95 % bounds with the share of steps inside them.  Every figure comes from the public API
(``jaxslam run``)::

    python scripts/reproduce_paper003.py --runs 100
    python scripts/reproduce_paper003.py --table-only   # table.md from the stored JSONs
"""

from __future__ import annotations

from jaxslam import runtime  # noqa: E402

runtime.configure_process()  # OpenBLAS one thread, XLA workaround flags: before NumPy and JAX start

import json
import pathlib
import sys

from jaxslam.cli.common import ScriptParser, path_arg, positive_int, seed_int
from jaxslam.files import atomic_write

SCENARIOS = ("circle", "square", "rough")  # uwb-<name>
CASES = [  # (mode, model, noise, filter)
    ("slam", "squared", "uniform", "paper"),
    ("slam", "range", "uniform", "paper"),
    ("slam", "squared", "uniform", "matched"),
    ("localization", "squared", "uniform", "paper"),
    ("localization", "range", "gaussian", "matched"),
    ("localization", "squared", "gaussian", "matched"),
    ("localization", "range", "uniform", "matched"),
    ("localization", "squared", "uniform", "matched"),
]
SHOW = ["pos_rmse_m", "pos_rmse_aligned_m", "pos_err_max_m", "vel_rmse_mps", "yaw_rmse_deg", "att_rmse_deg",
        "landmark_rmse_m", "landmark_rmse_aligned_m", "init_landmark_err_m", "init_trilat_err_m",
        "init_pos_err_m", "nees_pos_mean", "nees_robot_mean"]


def _cell(m):
    return "—" if m is None else f"{m['mean']:.3f} / {m['p95']:.3f}"


def main(argv=None):
    ap = ScriptParser(prog="reproduce_paper003.py", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=positive_int, default=100)
    ap.add_argument("--seed", type=seed_int, default=0)
    ap.add_argument("--out", default="docs/results/paper003", type=path_arg)
    ap.add_argument("--plots", default=None, type=path_arg, help="also write the figures of each case here")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--float32", action="store_true")
    ap.add_argument("--table-only", action="store_true",
                    help="rebuild table.md from the JSONs already in --out (no run)")
    args = ap.parse_args(argv)
    scenarios = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    # an empty list would replace table.md with an empty table; an unknown name stopped the script
    # only when its turn came, after the scenarios before it had run
    if not scenarios or set(scenarios) - set(SCENARIOS):
        ap.error(f"--scenarios: expected a comma-separated list of circle, square, rough, got {args.scenarios!r}")
    # one usage line (exit 2) for an unusable folder (an existing file), before any run
    out = ap.output_dir("--out", args.out)
    if args.plots and not args.table_only:
        ap.output_dir("--plots", args.plots)
    from jaxslam import cli

    rows = []
    for sc in scenarios:
        for mode, model, noise, filt in CASES:
            tag = f"uwb-{sc}_{mode}_{model}_{noise}_{filt}{'_f32' if args.float32 else ''}"
            path = out / f"{tag}.json"
            if args.table_only and not path.is_file():
                ap.error(f"--table-only: {path} is missing (run without --table-only first)")
            argv_run = ["run", f"uwb-{sc}", "--runs", str(args.runs), "--seed", str(args.seed), "--mode", mode,
                        "--model", model, "--noise", noise, "--filter", filt, "--json", str(path), "--quiet"]
            if args.plots:
                argv_run += ["--plots", str(pathlib.Path(args.plots) / tag)]
            if args.float32:
                argv_run.append("--float32")
            if not args.table_only:
                print("jaxslam " + " ".join(argv_run), file=sys.stderr, flush=True)
                rc = cli.main(argv_run)
                if rc != 0:
                    return rc
            res = json.loads(path.read_text())
            if args.table_only and (res.get("runs"), res.get("seed")) != (args.runs, args.seed):
                ap.error(f"{path}: holds {res.get('runs')} runs with seed {res.get('seed')}; "
                         f"give --runs {res.get('runs')} --seed {res.get('seed')} to tabulate it")
            rows.append((sc, mode, model, noise, filt, res))

    lines = [f"Paper 003 reproduction: {args.runs} runs per case, seed {args.seed}; cells are mean / p95 "
             "over the runs.  Frames: SLAM in the start-up frame (origin end anchor, +x start→end anchor, "
             "+y towards the trilaterated anchor), localisation in the anchors' frame; *_aligned after the "
             "best-fit 2D rigid transform.  ANEES: per-step average over the runs, averaged over the flight, "
             "with the per-step two-sided 95 % bounds, then the share of steps whose per-step ANEES is inside "
             "them (about 95 % for a consistent filter).", "",
             "| scenario | mode | model | noise | filter | " + " | ".join(SHOW)
             + " | max pos err [m] | ANEES pos [bounds], steps inside | ANEES robot [bounds], steps inside | mean NIS |",
             "|---" * (len(SHOW) + 9) + "|"]
    for sc, mode, model, noise, filt, res in rows:
        m = res["metrics"]
        det = res.get("consistency_detail", {})
        pos, rob = det.get("pos", {}), det.get("robot", {})

        def an(d):
            return (f"{d['anees']:.2f} [{d['bounds'][0]:.2f}, {d['bounds'][1]:.2f}]"
                    f"{'' if d['bounds'][0] <= d['anees'] <= d['bounds'][1] else ' out'}, "
                    f"{100 * d['fraction_steps_in_bounds']:.0f} % of steps") if d else "—"

        lines.append(f"| {sc} | {mode} | {model} | {noise} | {filt} | " + " | ".join(_cell(m.get(k)) for k in SHOW)
                     + f" | {res.get('max_pos_err_m', float('nan')):.3f} | {an(pos)} | {an(rob)} | "
                     f"{res['consistency']['nis_mean']:.2f} |")
    lines += ["", "Uniform vs Gaussian noise (localisation, matched filter): NEES spread relative to χ² "
              "(var/2n; 1 for χ²) and share of NEES above the χ² 95 % quantile (0.05 for χ²):", "",
              "| scenario | model | noise | ANEES pos | var/2n | P(NEES > χ²₉₅) |", "|---|---|---|---|---|---|"]
    for sc, mode, model, noise, filt, res in rows:
        if mode == "localization" and filt == "matched":
            d = res["consistency_detail"]["pos"]
            lines.append(f"| {sc} | {model} | {noise} | {d['anees']:.2f} | {d['nees_var_over_2n']:.2f} | "
                         f"{d['fraction_nees_above_chi2_95']:.3f} |")
    table = "\n".join(lines)
    atomic_write(out / ("table_f32.md" if args.float32 else "table.md"), lambda f: f.write(table + "\n"))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
