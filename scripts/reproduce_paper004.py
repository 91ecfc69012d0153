"""Reproduce paper 004's simulations: sliding-mode attitude control and line-feature EKF-SLAM.

* ``attitude-smc`` (ch. 3.4, app. B): the thesis gains (ch. 3.4) and the prototype gains
  (eq. 6.1) under the constant, sinusoidal and random perturbations of app. B, with app. B's
  torque model (τ = u, the code behind Figs. 3.2-3.7) and with eq. 3.15's (τ = J u + ω×Jω);
  ``--att-runs`` runs each (the random perturbation differs per run).
* ``lineslam-room`` (ch. 4, Algorithm 2): ``--runs`` vmapped Monte Carlo runs (default 100).

Writes one run JSON per case to ``--out`` (default ``docs/results/paper004``) and
``table.md`` with the mean and p95 of every metric.  ``--parts`` (``attitude``, ``lineslam``
or both) picks what is run; ``table.md`` still holds a part that was not run when its JSONs
are already in ``--out`` with the same runs and seed (so ``--parts attitude`` followed by
``--parts lineslam`` leaves both in the table).  Every figure comes from the public
CLI (``jaxslam run``)::

    python scripts/reproduce_paper004.py --runs 100 --plots docs/results/paper004/plots
    python scripts/reproduce_paper004.py --table-only   # table.md from the stored JSONs
"""

from __future__ import annotations

from jaxslam import runtime  # noqa: E402

runtime.configure_process()  # OpenBLAS one thread, XLA workaround flags: before NumPy and JAX start

import json
import pathlib
import sys

from jaxslam.cli.common import ScriptParser, path_arg, positive_int, seed_int
from jaxslam.files import atomic_write

ATT_CASES = [(g, t, p) for g in ("thesis", "prototype") for t in ("direct", "exact")
             for p in ("constant", "sinusoidal", "random")]
ATT_SHOW = ["att_err_rms_deg", "att_err_final_deg", "rate_err_rms_dps", "max_torque", "settle_time_s"]
LS_SHOW = ["pos_rmse_m", "max_pos_err_m", "yaw_rmse_deg", "line_rho_err_m", "line_theta_err_deg",
           "lines_mapped", "lines_spurious", "true_lines_found", "anees"]


def _num(v, fmt=".4g"):
    return "NaN" if v is None else f"{v:{fmt}}"  # JSON writes NaN (e.g. never settled) as null


def _cell(m):
    return "—" if m is None else f"{_num(m['mean'])} / {_num(m['p95'])}"


PARTS = ("attitude", "lineslam")


def _tags(args):
    """(part, scenario, tag, runs) of every case, in table order."""
    return ([("attitude", "attitude-smc", f"attitude-smc_{g}_{t}_{p}", args.att_runs) for g, t, p in ATT_CASES]
            + [("lineslam", "lineslam-room", "lineslam-room", args.runs)])


def main(argv=None):
    ap = ScriptParser(prog="reproduce_paper004.py", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=positive_int, default=100, help="lineslam-room Monte Carlo runs (default 100)")
    ap.add_argument("--att-runs", type=positive_int, default=4, help="attitude-smc runs per case (default 4)")
    ap.add_argument("--seed", type=seed_int, default=0)
    ap.add_argument("--out", default="docs/results/paper004", type=path_arg)
    ap.add_argument("--plots", default=None, type=path_arg, help="also write the figures of each case here")
    ap.add_argument("--parts", default="attitude,lineslam",
                    help="comma-separated parts to run: attitude, lineslam (default both)")
    ap.add_argument("--table-only", action="store_true",
                    help="rebuild table.md from the JSONs already in --out (no run)")
    args = ap.parse_args(argv)
    from jaxslam import cli

    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    if not parts or parts - set(PARTS):
        ap.error(f"--parts: expected a comma-separated subset of {', '.join(PARTS)}, got {args.parts!r}")
    # one usage line (exit 2) for an unusable folder (an existing file), before any run
    out = ap.output_dir("--out", args.out)
    if args.plots and not args.table_only:
        ap.output_dir("--plots", args.plots)

    def stored(part):
        """A part that is not run is tabulated when every JSON of it is in --out, same runs and seed."""
        for p, _, tag, runs in _tags(args):
            path = out / f"{tag}.json"
            if p != part:
                continue
            try:
                res = json.loads(path.read_text())
            except (OSError, ValueError):
                return False
            if (res.get("runs"), res.get("seed")) != (runs, args.seed):
                return False
        return True

    shown = [p for p in PARTS if p in parts or stored(p)]

    def run(scenario, tag, extra, runs, part):
        path = out / f"{tag}.json"
        argv_run = ["run", scenario, "--runs", str(runs), "--seed", str(args.seed), "--json", str(path),
                    "--quiet", *extra]
        if args.plots:
            argv_run += ["--plots", str(pathlib.Path(args.plots) / tag)]
        if not args.table_only and part in parts:
            print("jaxslam " + " ".join(argv_run), file=sys.stderr, flush=True)
            rc = cli.main(argv_run)
            if rc != 0:
                raise SystemExit(rc)
        elif not path.is_file():
            ap.error(f"--table-only: {path} is missing (run without --table-only first)")
        res = json.loads(path.read_text())
        if (res.get("runs"), res.get("seed")) != (runs, args.seed):
            ap.error(f"{path}: holds {res.get('runs')} runs with seed {res.get('seed')}, not {runs} with "
                     f"seed {args.seed}; give the matching --runs/--att-runs and --seed")
        return res

    lines = [f"Paper 004 reproduction, seed {args.seed}; cells are mean / p95 over the runs.", ""]
    if "attitude" in shown:
        lines += [f"attitude-smc: 25 s at 1 ms, τ_max 0.18 N m, tanh ε = 1, perturbation bound at Theorem "
                  f"3.1's admissible L1, L2; {args.att_runs} runs per case (constant and sinusoidal runs are "
                  "identical).", "",
                  "| gains | torque | perturbation | " + " | ".join(ATT_SHOW) + " |", "|---" * (len(ATT_SHOW) + 3) + "|"]
        for g, t, p in ATT_CASES:
            res = run("attitude-smc", f"attitude-smc_{g}_{t}_{p}",
                      ["--gains", g, "--torque", t, "--perturbation", p], args.att_runs, "attitude")
            m = res["metrics"]
            lines.append(f"| {g} | {t} | {p} | " + " | ".join(_cell(m.get(k)) for k in ATT_SHOW) + " |")
        lines.append("")
    if "lineslam" in shown:
        res = run("lineslam-room", "lineslam-room", [], args.runs, "lineslam")
        m, c = res["metrics"], res["consistency"]
        lo, hi = c["anees_bounds"]
        lines += [f"lineslam-room: {args.runs} runs of 60 s (600 scans); ANEES = pose NEES (3 dof) averaged "
                  "over runs and time, bounds for the per-step average over the runs.", "",
                  "| metric | mean | median | p95 | max |", "|---|---|---|---|---|"]
        for k in LS_SHOW:
            s = m[k]
            lines.append(f"| {k} | {_num(s['mean'])} | {_num(s['median'])} | {_num(s['p95'])} | {_num(s['max'])} |")
        inside = c.get("anees_steps_inside", res.get("consistency_detail", {}).get("fraction_steps_in_bounds"))
        inside = "undefined" if inside is None else f"{100 * inside:.1f} %"
        lines += ["", f"ANEES over runs {c['anees']:.3f} in [{lo:.3f}, {hi:.3f}]"
                  f"{'' if lo <= c['anees'] <= hi else ' (outside)'} as a time average; per step inside at "
                  f"{inside} of the steps (a consistent filter: about 95 %); mean NIS {c['nis_mean']:.3f} "
                  f"(bounds [{c['nis_bounds'][0]:.3f}, {c['nis_bounds'][1]:.3f}]); flags {res['flags']}; "
                  f"timing {res['timing']}"]
    table = "\n".join(lines)
    atomic_write(out / "table.md", lambda f: f.write(table + "\n"))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
