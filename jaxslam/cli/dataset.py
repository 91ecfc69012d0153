"""``jaxslam dataset NAME --data DIR ...``: run a system on a real log, print and save its figures.

Prints ATE / RPE / map error (with dead reckoning beside), the measurement
counts (used, gated, rejected, registered) and the run time after
compilation; writes the ``dataset`` JSON of docs/cli.md (``--json``), the
figures (``--plots``) and the estimated trajectory in TUM format (``--tum``,
for ``evo``).  Exit code 2 with a one-line message on a usage or input error
(missing folder, malformed file with its line number, a --json or --tum path that is one of
the dataset's own files), 1 on an internal failure.
"""

from __future__ import annotations

import argparse
import sys

from jaxslam.errors import InputError

from .common import Parser, compile_timing, path_arg, positive_int, raise_if_interrupted, seed_int

__all__ = ["main"]

_EPILOG = """\
datasets (see docs/datasets.md for downloads, formats and measured figures):
  mrclam         UTIAS MRCLAM (dataset 6 as shipped): unicycle odometry, range-bearing to
                 15 barcoded landmarks, Vicon ground truth; --robot 1..5, --ids known|hidden,
                 --calibrated (camera range model + odometry delay from robot 1's first half)
  victoria-park  ACFR Victoria Park: Ackermann car, laser tree detections, unknown
                 association (Mahalanobis gate), GPS as reference
  util-uwb       UTIL UWB TWR flight: constant-velocity range-only EKF with a range-bias
                 state; --anchors known|unknown, --tof adds the laser height
  plaza          CMU Plaza 1/2 (gtsam files): odometry + range-only SLAM with unknown
                 beacons and a range-bias state; --robot selects Plaza 1 or 2;
                 --anchors known localises against the surveyed beacons instead

DIR is the dataset's folder or a parent holding it (e.g. the folder with mrclam6/,
victoria_park/, util_uwb/ and gtsam/, or the one with an unpacked MRCLAM_Dataset9/: a
single subfolder holding the files is found; for util-uwb also the flight folder itself,
util_uwb/twr_obs_log1); without --data, $JAXSLAM_DATA_DIR names it.
'jaxslam list' shows which datasets that folder holds.

Ctrl-C: the log is filtered by one compiled scan, so an interrupted run has nothing
finished to keep; it exits 130 and writes no file (an existing --json is left as it was)."""


def _params_help() -> str:
    """The keys a dataset ``--params`` file may set (built only for ``--help``)."""
    import textwrap

    from jaxslam.data.presets import PLAZA_NOISE_KEYS, UTIL_NOISE_KEYS
    from jaxslam.systems.planar_ekf_slam import Params

    return ("\n\n--params FILE (mrclam or victoria-park, EKF): {\"dataset\": \"mrclam\", \"noise\": {...}, \"log\": {...}}\n"
            "as 'jaxslam tune mrclam|victoria-park' writes it (victoria-park: no \"log\"); noise keys (each optional, absent: the preset's value;\n"
            "shapes as in planar_ekf_slam.Params; the thresholds gate ... prune_min_obs are scalars, null: off):\n"
            + textwrap.fill(", ".join(Params._fields), 84, initial_indent="  ", subsequent_indent="  ")
            + "\nlog keys (optional): odometry_delay (s, the odometry stamps' lag the noise was fitted with;\n"
              "  absent: 0, the stamps as logged)"
            + "\n\n--params FILE (util-uwb): {\"dataset\": \"util-uwb\", \"noise\": {...}} as 'jaxslam tune util-uwb'\n"
              "writes it; noise keys (each optional, absent: the shipped fit's value; null switches nu, gate or\n"
              "anchor_offset off, and makes outlier_gate the model's own 99 % quantile):\n"
            + textwrap.fill(", ".join(UTIL_NOISE_KEYS), 84, initial_indent="  ", subsequent_indent="  ")
            + "\n\n--params FILE (plaza): {\"dataset\": \"plaza\", \"noise\": {...}} as 'jaxslam tune plaza' writes it;\n"
              "noise keys (each optional, absent: the preset's value):\n"
            + textwrap.fill(", ".join(PLAZA_NOISE_KEYS), 84, initial_indent="  ", subsequent_indent="  "))


def _parser(help_params: bool = False):
    p = Parser(prog="jaxslam dataset", usage="jaxslam dataset NAME --data DIR [options]",
                description="Run EKF-SLAM or FastSLAM on a real dataset and evaluate it.",
                epilog=_EPILOG + (_params_help() if help_params else ""),
                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", metavar="NAME", choices=("mrclam", "victoria-park", "util-uwb", "plaza"),
                   help="mrclam | victoria-park | util-uwb | plaza")
    p.add_argument("--data", metavar="DIR", type=path_arg, default=None,
                   help="folder holding the dataset files, or a parent of it (default: $JAXSLAM_DATA_DIR)")
    p.add_argument("--robot", type=positive_int, default=1, metavar="N",
                   help="MRCLAM robot number, or Plaza sequence 1|2 (default: 1)")
    p.add_argument("--filter", choices=("ekf", "fastslam"), default="ekf",
                   help="EKF-SLAM or FastSLAM (the dataset's setting: FastSLAM 2.0 for mrclam known ids "
                        "and victoria-park, 1.0 for mrclam ids hidden; default: ekf)")
    p.add_argument("--ids", choices=("known", "hidden"), default="known",
                   help="MRCLAM: use the barcode ids, or hide them and associate by "
                        "Mahalanobis distance (EKF: capacity 64, tentative landmarks not matched "
                        "4 times within 2 s pruned; default: known)")
    p.add_argument("--calibrated", action="store_true",
                   help="mrclam: correct the camera's bearing-dependent range error and the 0.2 s "
                        "odometry delay (fitted on the first half of robot 1) and use the matching "
                        "tight noise")
    p.add_argument("--anchors", choices=("known", "unknown"), default=None,
                   help="util-uwb: surveyed anchors (default) or SLAM after a start-up window; "
                        "plaza: unknown beacons, SLAM (default) or surveyed beacons (localisation)")
    p.add_argument("--tof", action="store_true",
                   help="util-uwb: also use the downward laser height (the run is then not range-only)")
    p.add_argument("--particles", type=positive_int, default=None, metavar="N",
                   help="FastSLAM particle count (default: the dataset's setting)")
    p.add_argument("--seed", type=seed_int, default=0, metavar="S", help="FastSLAM PRNG seed (default: 0)")
    p.add_argument("--smooth", action="store_true",
                   help="also smooth the EKF run (RTS backward pass over the robot trajectory, the map "
                        "held static) and report its figures beside the filter's as smoothed_* "
                        "(mrclam with --filter ekf, util-uwb, plaza)")
    p.add_argument("--float32", action="store_true",
                   help="compute in float32 (default: float64, jax_enable_x64 switched on)")
    p.add_argument("--params", metavar="FILE",
                   help="noise for the EKF from a 'jaxslam tune NAME' file (--json or --params-out); "
                        "the EKF of mrclam and victoria-park, util-uwb, plaza; a file for another dataset or with unknown "
                        "keys is an error")
    p.add_argument("--json", metavar="PATH", help="write the dataset JSON here")
    p.add_argument("--plots", metavar="DIR", help="write the path/map and error figures into DIR")
    p.add_argument("--tum", metavar="PATH", help="write the estimated trajectory in TUM format (evo)")
    p.add_argument("--quiet", action="store_true", help="print nothing on stdout")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


_DATA_SUFFIXES = (".dat", ".txt", ".csv", ".gz")
_TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"  # what metrics.write_tum writes first


def _not_a_data_file(name, data, **outputs) -> None:
    """No output file (``flag=path``) replaces one of the dataset's own files: an existing
    ``.dat`` / ``.txt`` / ``.csv`` / ``.gz`` file inside its folder (for a UTIL flight folder, also
    the anchors file the loader reads beside it), unless it is a TUM file an earlier ``--tum`` wrote (else an :class:`InputError` naming the option, before the run:
    the JSON or TUM file replaced the log it was computed from)."""
    import pathlib

    from jaxslam.data import catalogue

    folder = catalogue.find(name, data)
    if folder is None:
        return
    folder = folder.resolve()
    extra = set()  # files the loader reads from outside the folder
    if name == "util-uwb" and catalogue.util_flight(folder):
        # a flight folder named itself: the loader reads the anchors file beside it
        from jaxslam.data.util_uwb import ANCHORS_FILE

        if not (folder / ANCHORS_FILE).is_file():
            extra.add((folder.parent / ANCHORS_FILE).resolve())
    for flag, path in outputs.items():
        if path is None:
            continue
        try:
            target = pathlib.Path(path).resolve()
            inside = target.is_file() and (target in extra or (target.is_relative_to(folder)
                                                               and target.suffix.lower() in _DATA_SUFFIXES))
            if inside:
                with open(target, "rb") as f:
                    inside = not f.readline().decode("utf-8", "replace").startswith(_TUM_HEADER)
        except (OSError, RuntimeError):
            continue  # (an unreadable or looping path: prepare_file and the write say so)
        if inside:
            where = target.parent if target in extra else folder
            raise InputError(f"--{flag}: {str(path)!r} is a file of the {name} dataset in {str(where)!r}, which "
                             "this command reads; writing it would replace it, so give the output another path")


def main(argv) -> int:
    from jaxslam import files, paramfile
    from jaxslam.data import catalogue

    args = _parser(help_params="-h" in argv or "--help" in argv).parse_args(argv)
    # Inputs, then outputs, checked before anything is parsed or compiled.
    data = catalogue.data_root(args.data)
    params = paramfile.load(args.params) if args.params else None
    catalogue.check_options(args.name, dict(robot=args.robot, filter=args.filter, ids=args.ids,
                                            anchors=args.anchors, tof=args.tof, calibrated=args.calibrated,
                                            particles=args.particles, seed=args.seed, params=params,
                                            smooth=args.smooth))
    catalogue.check_robot(args.name, data, args.robot)
    json_path = files.prepare_file("--json", args.json) if args.json is not None else None
    tum_path = files.prepare_file("--tum", args.tum) if args.tum is not None else None
    files.distinct_outputs(json=json_path, tum=tum_path, folders={"plots": args.plots},
                           inputs={"params": args.params})
    _not_a_data_file(args.name, data, json=json_path, tum=tum_path)
    plots = files.prepare_dir("--plots", args.plots) if args.plots is not None else None
    if params is not None:
        paramfile.check_dataset_sections(params, args.name)  # its top level, still without JAX

    import jax
    import numpy as np

    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    from jaxslam import compilation, io
    from jaxslam.data import runners

    dtype = np.dtype(np.float32 if args.float32 else np.float64)
    if params is not None:
        runners.dataset_params(params, args.name)  # keys checked before the log is read
        runners.dataset_log_options(params, args.name)
    try:
        with compilation.account() as acct:
            run = runners.run_dataset(args.name, data, robot=args.robot, filter=args.filter, ids=args.ids,
                                      anchors=args.anchors, tof=args.tof, calibrated=args.calibrated,
                                      particles=args.particles, seed=args.seed, dtype=dtype,
                                      smooth=args.smooth,
                                      **({"params": params} if params is not None else {}))
        raise_if_interrupted()  # a Ctrl-C whose exception was dropped (cli.common)
    except KeyboardInterrupt:
        print("jaxslam dataset: interrupted before the run finished: nothing to keep, no file written"
              + (f" ({str(json_path)!r} left as it was)" if json_path is not None and json_path.exists() else ""),
              file=sys.stderr, flush=True)
        return 130
    doc = runners.to_json(run)
    if "compile_s" in doc["timing"]:
        doc["timing"]["main_program_compile_s"] = doc["timing"].pop("compile_s")
    doc["timing"].update(compile_timing(acct.result))
    if "diverged" in str(run.counts.get("status_flags", "")).split(","):
        frac = run.metrics.get("outlier_fraction_mapped")
        print(f"jaxslam dataset: warning: the run DIVERGED ({'' if frac is None else f'{100 * frac:.0f} % of '}"
              "the sightings of mapped landmarks were outliers, > 10 %): its estimate is not trustworthy",
              file=sys.stderr, flush=True)
    if "capacity_overflow" in str(run.counts.get("status_flags", "")).split(","):
        print(f"jaxslam dataset: warning: CAPACITY_OVERFLOW: {run.counts.get('overflow', 0)} sightings of new "
              "landmarks found no free slot and were not mapped", file=sys.stderr, flush=True)
    if not args.quiet:
        out = sys.stdout
        print(f"{run.dataset} ({run.config['filter']}, {run.config['dtype']}): {run.config['setting']}", file=out)
        for k, v in run.metrics.items():
            print(f"  {k:28s} {_fmt(v)}", file=out)
        print("  counts: " + ", ".join(f"{k} {v}" for k, v in run.counts.items()), file=out)
        print("  timing: " + ", ".join(f"{k} {v:.2f}" for k, v in doc["timing"].items()
                                       if isinstance(v, float)), file=out)
        for note in run.notes:
            print(f"  note: {note}", file=out)
    if json_path is not None:
        io.write_json(json_path, doc)
        if not args.quiet:
            print(f"wrote {json_path}")
    if tum_path is not None:
        from jaxslam.metrics import write_tum

        t, pos, yaw = run.trajectory
        try:
            path = write_tum(tum_path, t, pos, yaw=yaw)
        except OSError as e:
            raise InputError(f"--tum: cannot write {str(tum_path)!r}: {e.strerror or e}") from None
        if not args.quiet:
            print(f"wrote {path}")
    if plots is not None:
        from jaxslam.plotting.dataset import plot_run

        for path in plot_run(run, plots):
            if not args.quiet:
                print(f"wrote {path}")
    return 0
