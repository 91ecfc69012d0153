"""Reproduce paper 000's Sec. 3 figures: EKF-SLAM with DF-LQR, known and unknown landmarks.

Runs ``ekfslam3d-known`` and ``ekfslam3d-unknown`` with both noise settings (``--q imu``, the
Q derived from the IMU densities of Table 5, and ``--q paper``, Tables 6-7) over N seeded
Monte Carlo runs, writes one run JSON per case and a markdown table (``table.md``;
``table_f32.md`` with ``--float32``, beside the ``_f32`` JSONs) beside the paper's single-run
figures.

    python scripts/reproduce_paper000.py --runs 100 --out out/paper000

Every figure comes from the public API (the same code path as ``jaxslam run``).
"""

from __future__ import annotations

from jaxslam import runtime  # noqa: E402

runtime.configure_process()  # OpenBLAS one thread, XLA workaround flags: before NumPy and JAX start

import json
import sys

from jaxslam.cli.common import ScriptParser, path_arg, positive_float, positive_int, seed_int
from jaxslam.files import atomic_write


PAPER = {  # paper 000, Sec. 3 (one run): average RMSE
    "known": {"pos_rmse_m": 0.012, "vel_rmse_mps": 0.03, "att_rmse_deg": 0.17},
    "unknown": {"pos_rmse_m": 0.04, "vel_rmse_mps": 0.04, "att_rmse_deg": 0.34, "landmark_rmse_m": 0.03},
}
SHOW = ["pos_rmse_m", "pos_rmse_axis_m", "vel_rmse_mps", "vel_rmse_axis_mps", "att_rmse_deg",
        "att_rmse_axis_deg", "landmark_rmse_m", "landmark_rmse_axis_m", "pos_rmse_settled_m"]


def main(argv=None):
    ap = ScriptParser(prog="reproduce_paper000.py", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=positive_int, default=100)
    ap.add_argument("--seed", type=seed_int, default=0)
    ap.add_argument("--duration", type=positive_float, default=50.0)
    ap.add_argument("--chunk", type=positive_int, default=25)
    ap.add_argument("--out", default="out/paper000", type=path_arg)
    ap.add_argument("--float32", action="store_true")
    args = ap.parse_args(argv)
    out = ap.output_dir("--out", args.out)  # one usage line (exit 2) for an unusable --out, before any run
    from jaxslam import cli

    rows = []
    for mode in ("unknown", "known"):
        for q in ("imu", "paper"):
            path = out / f"ekfslam3d-{mode}_q-{q}{'_f32' if args.float32 else ''}.json"
            argv_run = ["run", f"ekfslam3d-{mode}", "--runs", str(args.runs), "--seed", str(args.seed),
                        "--q", q, "--duration", str(args.duration), "--chunk", str(args.chunk),
                        "--json", str(path), "--quiet"] + (["--float32"] if args.float32 else [])
            print("jaxslam " + " ".join(argv_run), file=sys.stderr)
            rc = cli.main(argv_run)
            if rc != 0:
                return rc
            res = json.loads(path.read_text())
            rows.append((mode, q, res))
    lines = ["| mode | Q | " + " | ".join(SHOW) + " | ANEES [bounds] | mean NIS [bounds] |",
             "|---" * (len(SHOW) + 4) + "|"]
    for mode, q, res in rows:
        cells = []
        for k in SHOW:
            m = res["metrics"].get(k)
            cells.append("—" if m is None else f"{m['mean']:.4f} (p95 {m['p95']:.4f})")
        c = res["consistency"]
        cells.append(f"{c['anees']:.2f} [{c['anees_bounds'][0]:.2f}, {c['anees_bounds'][1]:.2f}]")
        cells.append(f"{c['nis_mean']:.3f} [{c['nis_bounds'][0]:.3f}, {c['nis_bounds'][1]:.3f}]")
        lines.append(f"| {mode} | {q} | " + " | ".join(cells) + " |")
    for mode, figs in PAPER.items():
        lines.append(f"| {mode} | paper (1 run) | " + " | ".join(
            f"{figs[k]:.3f}" if k in figs else "—" for k in SHOW) + " | — | — |")
    table = "\n".join(lines)
    atomic_write(out / ("table_f32.md" if args.float32 else "table.md"), lambda f: f.write(table + "\n"))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
