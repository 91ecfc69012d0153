"""Reproduce the real-data figures of docs/datasets.md (issue 9) through ``jaxslam dataset``.

Runs every case below with the public CLI, writes one ``dataset`` JSON per case to
``--out`` (default ``docs/results/datasets``), the figures to ``--plots`` when given, and
``table.md`` with the headline figures of every case::

    python scripts/reproduce_datasets.py --data ../shared/data --plots docs/results/datasets/plots

The full datasets are not in the repository (see docs/datasets.md for downloads).  Usage
errors (``--data`` not a folder, ``--only`` naming no known case) exit 2 with one line before
any case runs; the exit code is 1 when a case failed (its row says so in ``table.md``).  Every
path under ``--data`` in the JSONs is written ``$DATA`` (a relative ``--data`` too), and one under
the home folder (the XLA cache's) ``~/``.
"""

from __future__ import annotations

from jaxslam import runtime  # noqa: E402

runtime.configure_process()  # OpenBLAS one thread, XLA workaround flags: before NumPy and JAX start

import json
import pathlib
import subprocess
import sys

from jaxslam.cli.common import ScriptParser, path_arg

# (case name, CLI arguments after "jaxslam dataset")
CASES = [
    ("mrclam_r1_ekf", ["mrclam", "--robot", "1"]),
    ("mrclam_r2_ekf", ["mrclam", "--robot", "2"]),
    ("mrclam_r3_ekf", ["mrclam", "--robot", "3"]),
    ("mrclam_r4_ekf", ["mrclam", "--robot", "4"]),
    ("mrclam_r5_ekf", ["mrclam", "--robot", "5"]),
    ("mrclam_r1_ekf_calibrated", ["mrclam", "--robot", "1", "--calibrated"]),
    ("mrclam_r2_ekf_calibrated", ["mrclam", "--robot", "2", "--calibrated"]),
    ("mrclam_r1_ekf_hidden", ["mrclam", "--robot", "1", "--ids", "hidden"]),
    ("mrclam_r2_ekf_hidden", ["mrclam", "--robot", "2", "--ids", "hidden"]),
    ("mrclam_r3_ekf_hidden", ["mrclam", "--robot", "3", "--ids", "hidden"]),
    ("mrclam_r4_ekf_hidden", ["mrclam", "--robot", "4", "--ids", "hidden"]),
    ("mrclam_r5_ekf_hidden", ["mrclam", "--robot", "5", "--ids", "hidden"]),
    ("mrclam_r1_fastslam", ["mrclam", "--robot", "1", "--filter", "fastslam"]),
    ("mrclam_r2_fastslam", ["mrclam", "--robot", "2", "--filter", "fastslam"]),
    ("mrclam_r3_fastslam", ["mrclam", "--robot", "3", "--filter", "fastslam"]),
    ("mrclam_r4_fastslam", ["mrclam", "--robot", "4", "--filter", "fastslam"]),
    ("mrclam_r5_fastslam", ["mrclam", "--robot", "5", "--filter", "fastslam"]),
    ("victoria_park_ekf", ["victoria-park", "--float32"]),
    ("victoria_park_fastslam", ["victoria-park", "--filter", "fastslam"]),
    ("util_known", ["util-uwb"]),
    ("util_known_tof", ["util-uwb", "--tof"]),
    ("util_unknown", ["util-uwb", "--anchors", "unknown"]),
    ("util_unknown_tof", ["util-uwb", "--anchors", "unknown", "--tof"]),
    ("plaza1_slam", ["plaza", "--robot", "1"]),
    ("plaza2_slam", ["plaza", "--robot", "2"]),
    ("plaza1_surveyed", ["plaza", "--robot", "1", "--anchors", "known"]),
    ("plaza2_surveyed", ["plaza", "--robot", "2", "--anchors", "known"]),
    # --smooth: the filter's figures and the RTS smoother's (smoothed_*) from one run
    ("mrclam_r1_ekf_smooth", ["mrclam", "--robot", "1", "--smooth"]),
    ("mrclam_r2_ekf_smooth", ["mrclam", "--robot", "2", "--smooth"]),
    ("mrclam_r3_ekf_smooth", ["mrclam", "--robot", "3", "--smooth"]),
    ("mrclam_r4_ekf_smooth", ["mrclam", "--robot", "4", "--smooth"]),
    ("mrclam_r5_ekf_smooth", ["mrclam", "--robot", "5", "--smooth"]),
    ("util_known_smooth", ["util-uwb", "--smooth"]),
    ("util_unknown_smooth", ["util-uwb", "--anchors", "unknown", "--smooth"]),
    ("plaza1_slam_smooth", ["plaza", "--robot", "1", "--smooth"]),
    ("plaza2_slam_smooth", ["plaza", "--robot", "2", "--smooth"]),
]

SHOW = ["ate_m", "smoothed_ate_m", "pos_rmse_m", "smoothed_pos_rmse_m", "dead_reckoning_ate_m", "rpe_m",
        "map_err_m", "range_bias_m"]


def _data_as_placeholder(js: pathlib.Path, root: str) -> None:
    """Rewrite ``js`` with every occurrence of the folder ``root`` as ``$DATA`` and then of the
    home folder as ``~`` (the compilation cache's folder), atomically."""
    from jaxslam import files

    text = js.read_text(encoding="utf-8")
    subs = [(root, "$DATA")]
    home = str(pathlib.Path.home())
    if home not in ("", "/"):
        subs.append((home + "/", "~/"))
    for folder, placeholder in subs:
        for form in (json.dumps(folder)[1:-1], json.dumps(folder, ensure_ascii=False)[1:-1]):  # as JSON writes it
            text = text.replace(form, placeholder)
    files.atomic_write(js, lambda f: f.write(text))


def _cell(v):
    return "—" if v is None else f"{v:.3g}"


def main(argv=None):
    ap = ScriptParser(prog="reproduce_datasets.py", description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=path_arg,
                    help="folder holding mrclam6/, victoria_park/, util_uwb/, gtsam/")
    ap.add_argument("--out", default="docs/results/datasets", type=path_arg)
    ap.add_argument("--plots", default=None, type=path_arg, help="also write each case's figures here")
    ap.add_argument("--only", default=None, help="comma-separated case names (default: all)")
    args = ap.parse_args(argv)
    data = pathlib.Path(args.data)
    if not data.is_dir():
        ap.error(f"--data: {args.data!r} is not a folder")
    only = None
    if args.only is not None:
        only = {n.strip() for n in args.only.split(",") if n.strip()}
        unknown = sorted(only - {name for name, _ in CASES})
        if not only or unknown:
            ap.error(f"--only: unknown case(s) {', '.join(unknown) or repr(args.only)} "
                     f"(the case names are the CASES of this script, e.g. {CASES[0][0]})")
    # the data folder as "$DATA": the shipped results name no folder of the machine they ran on
    # (the CLI gets the absolute folder, so that a relative --data is replaced too)
    root = str(data.resolve())
    # one usage line (exit 2) for an unusable folder (an existing file), before any case runs
    out = ap.output_dir("--out", args.out)
    if args.plots:
        ap.output_dir("--plots", args.plots)
    rows = []
    for name, cli_args in CASES:
        if only and name not in only:
            continue
        js = out / f"{name}.json"
        cmd = [sys.executable, "-m", "jaxslam", "dataset", *cli_args, "--data", root, "--json", str(js),
               "--quiet"]
        if args.plots:
            cmd += ["--plots", str(pathlib.Path(args.plots) / name)]
        print("$ jaxslam dataset " + " ".join(cli_args), flush=True)
        r = subprocess.run(cmd)
        if r.returncode != 0:
            print(f"  failed with exit code {r.returncode}", flush=True)
            rows.append((name, cli_args, None))
            continue
        _data_as_placeholder(js, root)
        rows.append((name, cli_args, json.loads(js.read_text(encoding="utf-8"))))
    # The table covers every case with a JSON in --out (cases not rerun keep their last figures).
    done = {name for name, _, _ in rows}
    for name, cli_args in CASES:
        js = out / f"{name}.json"
        if name not in done and js.exists():
            rows.append((name, cli_args, json.loads(js.read_text(encoding="utf-8"))))
    order = {name: i for i, (name, _) in enumerate(CASES)}
    rows.sort(key=lambda r: order[r[0]])
    lines = ["| case | command | " + " | ".join(SHOW) + " | used / gated / rejected | run_s |",
             "|---" * (len(SHOW) + 4) + "|"]
    for name, cli_args, doc in rows:
        if doc is None:
            lines.append(f"| {name} | `{' '.join(cli_args)}` | failed |" + " |" * (len(SHOW) + 1))
            continue
        m, c = doc["metrics"], doc["counts"]
        lines.append(f"| {name} | `{' '.join(cli_args)}` | " + " | ".join(_cell(m.get(k)) for k in SHOW)
                     + f" | {c['used']} / {c['gated']} / {c['rejected']} | {doc['timing']['run_s']:.2f} |")
    from jaxslam import files

    table = "\n".join(lines) + "\n"
    files.atomic_write(out / "table.md", lambda f: f.write(table))
    print("\n".join(lines))
    return 1 if any(doc is None for _, _, doc in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
