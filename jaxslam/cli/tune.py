"""``jaxslam tune SCENARIO --target noise|lqr|loop --loss ...``: gradient tuning from the command line.

    jaxslam tune SCENARIO [--target noise|lqr|loop] [--loss nll|mse|nees|cost] [--steps K]
                 [--train-runs M] [--test-runs M] [--lr LR] [--seed S] [--json PATH]
                 [--plots DIR] [--params-out FILE] [--float32] [--quiet] [target options]

What it does: builds the target (:mod:`jaxslam.tuning.targets`: simulates the training
logs once), runs :func:`jaxslam.tuning.optimize.fit` with a progress line, evaluates the
starting and the tuned parameters (and the target's references, e.g. ``q_imu``) on
held-out seeds of the scenario itself, prints the before/after table and the tuned
parameters, and writes:

* ``--json PATH``: the ``tune`` JSON of docs/cli.md (``scenario, target, loss, before, after,
  params_before, params_after, history``, plus ``references, config, timing, memory,
  stopped, eval_command, eval_note where the target has one, versions``).  Its top level also holds the tuned parameters
  themselves (``"noise"`` or ``"controller"``), so the same file works as
  ``jaxslam run SCENARIO --params PATH``;
* ``--params-out FILE``: only the tuned parameters (the ``--params`` file);
* ``--plots DIR``: loss curves and parameter trajectories (:mod:`jaxslam.plotting.tuning`).

Exit codes as ``jaxslam``: 0 success (also when the optimisation stopped early on a
non-finite loss: the message is printed and recorded, the last good parameters are
evaluated and saved), 2 usage or input error (one line; also no SCENARIO at all), 1 internal
failure, 130 interrupted (the best parameters the finished steps reached are saved, marked
``"interrupted": true``).
x64 is switched on here (before any target module is imported) unless ``--float32``.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time

from jaxslam.errors import InputError

from .common import (Parser, UsageError, compile_timing, finite_float, int_at_least, nonnegative_float, path_arg,
                     positive_float, raise_if_interrupted, seed_int)

__all__ = ["main", "build_parser", "DEFAULTS"]

PROG = "jaxslam tune"

# Per-target defaults (steps, learning rate, training / evaluation durations) chosen from the
# measurements in docs/results/tuning (see docs/tuning.md).
DEFAULTS = {
    "noise": {"steps": 100, "lr": 0.5, "loss": "nll"},
    "lqr": {"steps": 40, "lr": 0.1, "loss": "cost"},
    "loop": {"steps": 30, "lr": 0.1, "loss": "cost"},
}
# Real logs (the protocol of docs/datasets.md): 25 Adam steps at 0.1 on 500 s of each log.
REAL_LOG_DEFAULTS = {"steps": 25, "lr": 0.1, "loss": "nll", "window": 500.0}
# A training run whose (positive) loss exceeds this many times the batch's lower median is an
# exploding flight, left out of that step like a non-finite one (optimize.fit, explode_ratio).
EXPLODE_RATIO = 1e3


def _targets_text():
    from jaxslam.tuning import targets

    return "; ".join(f"{s} --target {t} (--loss {'|'.join(ls)})" for (s, t), ls in targets.available().items())


def _default_robots(scenario: str, key: str) -> str:
    """The default ``key`` ("robots" / "test_robots") of ``scenario`` as the help writes it
    (``targets.DEFAULT_ROBOTS``, the targets' own defaults)."""
    from jaxslam.tuning.targets import DEFAULT_ROBOTS

    return ",".join(map(str, DEFAULT_ROBOTS[scenario][key]))


def _robot_list(text: str) -> tuple:
    if text.strip().lower() == "none":
        return ()
    try:
        out = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated robot numbers such as 1,2,3, got {text!r}")
    if not out:
        raise argparse.ArgumentTypeError(f"expected at least one robot, got {text!r}")
    return out


def _tune_seed(text: str) -> int:
    """argparse type: a training seed S (:func:`seed_int`) with S + 1 (the held-out runs' seed)
    still a PRNG seed: a larger one failed only after the target was built, as ``seed: ...``."""
    value = seed_int(text)
    if value + 1 >= 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63 - 1) (the held-out runs use S+1), got {value}")
    return value


def build_parser(with_targets: bool = True) -> Parser:
    """The argument parser of ``jaxslam tune`` (``with_targets`` lists the targets in the epilog)."""
    p = Parser(
        prog=PROG,
        usage=f"{PROG} SCENARIO [--target noise|lqr|loop] [--loss LOSS] [--steps K] [--train-runs M] "
              f"[--test-runs M] [options]",
        description="Tune filter noise (Q, R) or DF-LQR weights by gradient descent (optax Adam) on "
                    "training runs, then compare the start and the result on held-out runs.",
        epilog=("targets: " + _targets_text()) if with_targets else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scenario", metavar="SCENARIO", help="scenario to tune (see the list below)")
    p.add_argument("--target", choices=("noise", "lqr", "loop"), default=None,
                   help="what to tune: filter 'noise' (Q, optionally R), 'lqr' weights, or 'loop' "
                        "(ekfslam3d-*: LQR weights and/or filter noise through the closed loop with the "
                        "estimator in it; see --tune) (default: 'noise' where the scenario has it, else its "
                        "only target)")
    p.add_argument("--loss", choices=("nll", "mse", "nees", "cost"), default=None,
                   help="nll: innovation negative log-likelihood (no truth needed); mse: squared state "
                        "error vs truth; nees: NEES consistency; cost: closed-loop cost (lqr) "
                        "(default: nll for noise where offered, else the target's first loss; cost for lqr)")
    p.add_argument("--steps", type=int_at_least(1), default=None,
                   help="optimisation steps (default: 100 noise, 40 lqr, 30 loop, 25 real logs)")
    p.add_argument("--train-runs", type=int_at_least(1), default=4, metavar="M", help="training runs (default 4)")
    p.add_argument("--test-runs", type=int_at_least(1), default=8, metavar="M",
                   help="held-out runs for the before/after table (default 8)")
    p.add_argument("--lr", type=positive_float, default=None,
                   help="peak Adam learning rate in log-parameter units (default: 0.5 noise, 0.1 lqr, loop and "
                        "real logs)")
    p.add_argument("--seed", type=_tune_seed, default=0,
                   help="training seed S in [0, 2**63 - 1); held-out runs use seed S+1 (default 0)")
    p.add_argument("--batch-size", type=int_at_least(1), default=None,
                   help="minibatch of training runs (real logs: training logs) per step, at most their number "
                        "(default: all)")
    p.add_argument("--clip", type=positive_float, default=1.0, help="gradient clipping, global norm (default 1)")
    p.add_argument("--b2", type=finite_float, default=0.9,
                   help="Adam's second-moment decay (default 0.9; see jaxslam.tuning.optimize)")
    p.add_argument("--eval-every", type=int_at_least(0), default=10,
                   help="held-out loss every N steps for the loss curve (0: only at the end; default 10)")
    p.add_argument("--duration", type=positive_float, default=None,
                   help="training flight duration [s] (default: 10 noise and loop, 25 lqr)")
    p.add_argument("--eval-duration", type=positive_float, default=50.0,
                   help="held-out evaluation flight duration [s] (default 50, the scenario's)")
    p.add_argument("--cov", choices=("diag", "chol"), default="diag",
                   help="covariance parametrisation: log-diagonal or log-Cholesky (noise; default diag)")
    p.add_argument("--tune-r", action="store_true", help="also tune the measurement covariance R (noise)")
    p.add_argument("--filter", choices=("ekf", "ukf", "cubature"), default=None,
                   help="linear-gaussian: the filter the loss runs through, the EKF (default) or the "
                        "sigma-point filter with unscented or cubature points")
    p.add_argument("--structure", choices=("qc", "imu", "imu_iso"), default=None,
                   help="ekfslam3d noise: tune the 9x9 process-noise density Q_c (Table 7's form; default), "
                        "the 6x6 IMU density Q_imu entering through the filter's G Q_imu G^T (imu), or one "
                        "density per sensor, accelerometer and gyro (imu_iso, Table 5's form); the loop "
                        "target's Q_imu: imu (default) or imu_iso")
    loop = p.add_argument_group("closed loop with the estimator in it (ekfslam3d-* --target loop)")
    loop.add_argument("--tune", choices=("lqr", "noise", "both"), default=None,
                      help="what the loop target tunes: the DF-LQR weights (default), the filter's IMU "
                           "noise density Q_imu, or both jointly")
    loop.add_argument("--w-mse", type=nonnegative_float, default=None, metavar="W",
                      help="weight of the estimator's position MSE in the objective (default 0)")
    loop.add_argument("--w-nees", type=nonnegative_float, default=None, metavar="W",
                      help="weight of the NEES consistency term (log(ANEES/9))^2 (default 0)")
    loop.add_argument("--w-u", type=nonnegative_float, default=None, metavar="W",
                      help="weight of the control effort mean|u~|^2 in the objective (default 0.1)")
    loop.add_argument("--w-tilt", type=nonnegative_float, default=None, metavar="W",
                      help="weight of the soft tilt limit, per rad^2 above --tilt-max (default 10)")
    loop.add_argument("--tilt-max", type=positive_float, default=None, metavar="DEG",
                      help="tilt [deg, below 90] above which the soft limit acts (default 12)")
    loop.add_argument("--compare", metavar="FILE", default=None,
                      help="also evaluate the controller of FILE (a --params file or a 'jaxslam tune "
                           "track-figure8 --target lqr' report) with the estimator in the loop")
    real = p.add_argument_group("real logs (jaxslam tune mrclam | util-uwb | plaza | victoria-park)")
    real.add_argument("--data", metavar="DIR", type=path_arg, default=None,
                      help="dataset folder (the one with mrclam6/, util_uwb/, gtsam/ or victoria_park/, or a "
                           "parent of it; for util-uwb also the flight folder itself; default: $JAXSLAM_DATA_DIR)")
    real.add_argument("--robots", type=_robot_list, default=None, metavar="LIST",
                      help=f"training robots, e.g. 1,2,3,4 (mrclam, default {_default_robots('mrclam', 'robots')}; "
                           f"plaza: sequences, default {_default_robots('plaza', 'robots')})")
    real.add_argument("--test-robots", type=_robot_list, default=None, metavar="LIST",
                      help=f"held-out robots for the before/after table, e.g. 5 (mrclam, default "
                           f"{_default_robots('mrclam', 'test_robots')}; plaza: default "
                           f"{_default_robots('plaza', 'test_robots')}; 'none': no held-out)")
    real.add_argument("--window", type=positive_float, default=None, metavar="S",
                      help="fit on the first S seconds of each training log (mrclam: default 500 s, the "
                           "held-out robots are evaluated whole; util-uwb: the first S seconds of the flight, "
                           "counted from its first range, default half the flight, the rest is held out; "
                           "plaza: default the whole log; victoria-park: default 500 s, the rest is held out)")
    real.add_argument("--anchor-offsets", action="store_true", default=None,
                      help="util-uwb: also learn a range offset per anchor (mean removed)")
    real.add_argument("--odometry-delay", default=None, metavar="S|auto",
                      help="lag of the odometry stamps [s], or 'auto' (default): the delay of 0, 0.05, "
                           "..., 0.4 s with the lowest training NLL at the starting point")
    p.add_argument("--no-checkpoint", action="store_true",
                   help="do not wrap the scan body in jax.checkpoint (more memory, a little faster)")
    p.add_argument("--float32", action="store_true", help="compute in float32 (default float64)")
    p.add_argument("--json", metavar="PATH", help="write the tune JSON (also usable as --params)")
    p.add_argument("--params-out", metavar="FILE", help="write only the tuned parameters (a --params file)")
    p.add_argument("--plots", metavar="DIR", help="write loss-curve and parameter-trajectory PNGs")
    p.add_argument("--quiet", action="store_true", help="no progress and no table on stdout")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _dest(flag: str) -> str:
    """The argparse attribute of an option: ``--eval-duration`` -> ``eval_duration``."""
    return flag[2:].replace("-", "_")


def _not_default(args, flags) -> list:
    """Those of ``flags`` (e.g. ``["--cov", "--seed"]``) whose value in ``args`` is not the parser's
    default (the user gave them), in order: a target that would ignore them refuses them by name."""
    if not flags:
        return []
    defaults = build_parser(with_targets=False)
    return [flag for flag in flags if getattr(args, _dest(flag)) != defaults.get_default(_dest(flag))]


def _fmt(x):
    from jaxslam.io import _fmt_num

    return _fmt_num(float("nan") if x is None else float(x))


def format_comparison(before: dict, after: dict, refs: dict | None = None) -> str:
    """Text table: metric, before, after, change %, and reference columns (means over runs).
    The change is ``-`` where either mean is missing, non-finite or the start's is 0."""
    refs = refs or {}
    header = ["metric (held-out mean)", "before", "after", "change"] + list(refs)
    rows = [header]
    for name in before["metrics"]:
        b = before["metrics"][name]["mean"]
        a = after["metrics"][name]["mean"]
        ch = (f"{100.0 * (a - b) / abs(b):+.1f}%" if _finite(a) and _finite(b) and b != 0
              else "-")  # (a missing or non-finite mean has no change: it printed +nan% or failed)
        rows.append([name, _fmt(b), _fmt(a), ch] + [_fmt(r["metrics"][name]["mean"]) for r in refs.values()])
    cb, ca = before.get("consistency"), after.get("consistency")
    if cb and ca:
        from jaxslam.metrics import STEPS_INSIDE_MIN
        from jaxslam.metrics import percent_text as _pct

        for key in ("anees", "nis_mean"):
            lo, hi = ca.get(f"{key}_bounds", ca.get(f"{key.split('_')[0]}_bounds", [None, None]))
            rows.append([f"{key} [{_fmt(lo)}, {_fmt(hi)}]", _fmt(cb[key]), _fmt(ca[key]), "-"]
                        + [_fmt(r["consistency"][key]) for r in refs.values()])
            if key == "anees" and _steps_inside(ca) is not None:
                # the time average can sit inside its bounds while most steps do not (metrics.steps_inside)
                rows.append([f"  steps inside (95 % expected, {_pct(STEPS_INSIDE_MIN)} ok)", _pct(_steps_inside(cb)),
                             _pct(_steps_inside(ca)), "-"]
                            + [_pct(_steps_inside(r.get("consistency"))) for r in refs.values()])
    w = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = []
    for j, r in enumerate(rows):
        lines.append("  ".join([r[0].ljust(w[0])] + [c.rjust(x) for c, x in zip(r[1:], w[1:])]))
        if j == 0:
            lines.append("  ".join("-" * x for x in w))
    return "\n".join(lines)


def _finite(x) -> bool:
    """``x`` is a finite number (None, NaN and inf are not)."""
    try:
        return x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _steps_inside(cons):
    """The per-step share of a consistency block (its name differs by target), or None."""
    for key in ("anees_steps_inside", "anees_fraction_in_bounds"):
        if cons and cons.get(key) is not None:
            return cons[key]
    return None


def _summ(res):
    from jaxslam import io

    out = {"metrics": io.summarize_metrics(res["metrics"])}
    if res.get("consistency") is not None:
        out["consistency"] = io.to_jsonable(res["consistency"], nonfinite_to_none=False)
    return out


def _plan(args) -> tuple:
    """``(target_name, loss, steps, lr, real, kw)`` of ``args``, checked before JAX or any
    target module is imported (the targets' names and losses are declared,
    ``targets.DECLARED``): every argument error of ``jaxslam tune`` but a bad ``--compare``
    file and a target's own checks.  ``kw`` goes to ``targets.get`` (without its dtype)."""
    from jaxslam.tuning import targets

    avail = targets.available()
    scen_targets = [t for (s, t) in avail if s == args.scenario]
    if not scen_targets:
        names = sorted({s for s, _ in avail})
        raise InputError(f"no tuning target for scenario {args.scenario!r}; tunable scenarios: {', '.join(names)}")
    target_name = args.target or targets.default_target(args.scenario)
    if target_name not in scen_targets:
        raise InputError(f"--target: {args.scenario} offers {', '.join(scen_targets)}; got {target_name!r}")
    if args.filter is not None and args.scenario != "linear-gaussian":
        raise InputError(f"--filter: only the linear-gaussian target takes it, not {args.scenario}")
    if not args.scenario.startswith("ekfslam3d"):
        for flag, used in (("--structure", args.structure is not None), ("--tune-r", args.tune_r)):
            if used:
                raise InputError(f"{flag}: only the ekfslam3d-* noise targets take it, not {args.scenario}")
    if target_name != "loop":
        for flag, used in (("--tune", args.tune), ("--w-mse", args.w_mse), ("--w-nees", args.w_nees),
                           ("--w-u", args.w_u), ("--w-tilt", args.w_tilt), ("--tilt-max", args.tilt_max),
                           ("--compare", args.compare)):
            if used is not None:
                raise InputError(f"{flag}: only the loop target (ekfslam3d-* --target loop) takes it")
    elif args.structure is not None and (args.structure == "qc" or (args.tune or "lqr") == "lqr"):
        raise InputError(f"--structure {args.structure}: the loop target shapes its IMU noise Q_imu "
                         "(imu or imu_iso) and needs --tune noise or both for it")
    elif args.tilt_max is not None and not args.tilt_max < 90:  # before the build: the only line
        raise InputError(f"--tilt-max: expected (0, 90) degrees, got {args.tilt_max}")
    real = args.scenario in targets.REAL_LOG_SCENARIOS
    if not real:  # options a simulation target would ignore: refused by name, like the real logs'
        flights = args.scenario.startswith("ekfslam3d") or args.scenario == "track-figure8"
        takes_cov = (args.scenario.startswith("ekfslam3d") and target_name == "noise") or args.scenario.startswith("uwb-")
        unused = _not_default(args, [flag for flag, ok in (("--duration", flights), ("--eval-duration", flights),
                                                           ("--no-checkpoint", flights), ("--cov", takes_cov)) if not ok])
        if unused:
            raise InputError(f"{unused[0]}: {args.scenario} --target {target_name} does not use it (it would be "
                             "ignored)")
    if not 0 < args.b2 < 1:  # before the build (it used to fail after compiling the step)
        raise InputError(f"--b2: Adam's second-moment decay must be in (0, 1), got {args.b2}")
    if not real and args.batch_size is not None and args.batch_size > args.train_runs:
        raise InputError(f"--batch-size: {args.batch_size} is more than the {args.train_runs} training runs "
                         "(--train-runs)")
    if not real:
        for flag, used in (("--data", args.data), ("--robots", args.robots), ("--test-robots", args.test_robots),
                           ("--window", args.window), ("--odometry-delay", args.odometry_delay),
                           ("--anchor-offsets", args.anchor_offsets)):
            if used is not None:
                raise InputError(f"{flag}: only the real-log targets ({', '.join(targets.REAL_LOG_SCENARIOS)}) "
                                 f"take it, not {args.scenario}")
    else:  # the simulation-only options would be ignored on a real log: refused by name
        # the training logs are known from the options (mrclam, plaza: --robots, by default the target's own,
        # targets.DEFAULT_ROBOTS; util-uwb, victoria-park: one log), so a larger minibatch is refused before the
        # (slow) build, by the option's name (optimize.fit said "batch_size: ..." after it); repeated robots
        # are left to the target's own check
        takes_robots = args.scenario in targets.DEFAULT_ROBOTS
        robots = (None,) if not takes_robots else (
            args.robots if args.robots is not None else targets.DEFAULT_ROBOTS[args.scenario]["robots"])
        n_logs = len(robots) if len(set(robots)) == len(robots) else None
        sim_only = ["--train-runs", "--test-runs", "--duration", "--eval-duration", "--cov", "--no-checkpoint"]
        if args.batch_size is None or (n_logs is not None and args.batch_size == n_logs):
            # it seeds the minibatches of --batch-size (fewer than the training logs), nothing else here
            sim_only.append("--seed")
        unused = _not_default(args, sim_only)
        if unused:
            raise InputError(f"{unused[0]}: the real-log target {args.scenario} does not use it (simulation "
                             "targets only)")
    own = {"--robots": tuple(targets.DEFAULT_ROBOTS), "--test-robots": tuple(targets.DEFAULT_ROBOTS),
           "--odometry-delay": ("mrclam",),
           "--anchor-offsets": ("util-uwb",)}
    for flag, scens in own.items():
        if args.scenario not in scens and getattr(args, _dest(flag)) is not None:
            raise InputError(f"{flag}: only 'jaxslam tune {' | '.join(scens)}' takes it, not {args.scenario}")
    if real and args.batch_size is not None and n_logs is not None and args.batch_size > n_logs:
        src = "--robots" if takes_robots else "one log"
        raise InputError(f"--batch-size: {args.batch_size} is more than the {n_logs} training log"
                         f"{'s' if n_logs != 1 else ''} of {args.scenario} ({src})")
    d = REAL_LOG_DEFAULTS if real else DEFAULTS.get(target_name, DEFAULTS["noise"])
    supported = avail[(args.scenario, target_name)]
    loss = args.loss or (d["loss"] if d["loss"] in supported else supported[0])
    if loss not in supported:  # checked before the (slow) build, so the error is the only line
        raise InputError(f"--loss: {args.scenario} --target {target_name} supports {', '.join(supported)}; "
                         f"got {loss!r}")
    steps = args.steps or d["steps"]
    lr = args.lr or d["lr"]
    kw = dict(train_runs=args.train_runs, test_runs=args.test_runs, seed=args.seed,
              eval_duration=args.eval_duration, checkpoint=not args.no_checkpoint, cov=args.cov,
              tune_r=args.tune_r, structure=args.structure or "qc", filter=args.filter or "ekf")
    if target_name == "loop":
        kw.update(tune=args.tune or "lqr", w_mse=args.w_mse or 0.0, w_nees=args.w_nees or 0.0,
                  compare=args.compare, structure=args.structure or "imu")
        kw.update({k: v for k, v in (("w_u", args.w_u), ("w_tilt", args.w_tilt), ("tilt_max_deg", args.tilt_max))
                   if v is not None})  # the target's defaults otherwise
    if args.duration is not None:
        kw["train_duration"] = args.duration
    if args.scenario in ("util-uwb", "plaza", "victoria-park"):
        from jaxslam.data import catalogue

        kw = dict(data=catalogue.data_root(args.data), t_max=args.window)
        if args.scenario == "util-uwb":
            kw["anchor_offsets"] = bool(args.anchor_offsets)
        else:
            kw.update({k: v for k, v in (("robots", args.robots), ("test_robots", args.test_robots)) if v is not None})
    elif real:  # the folder and the robots checked before the (slow) build says anything
        from jaxslam.data import catalogue

        data = catalogue.data_root(args.data)
        catalogue.check_robots(args.scenario, data, (args.robots or ()) + (args.test_robots or ()),
                               flag="--robots/--test-robots")
        delay = args.odometry_delay or "auto"
        if delay != "auto":
            try:
                delay = float(delay)
            except ValueError:
                raise InputError(f"--odometry-delay: expected seconds or 'auto', got {delay!r}") from None
            if not (math.isfinite(delay) and 0.0 <= delay <= 2.0):
                raise InputError(f"--odometry-delay: expected 0 to 2 s, got {delay:g}")
        kw = dict(data=data, t_max=args.window or REAL_LOG_DEFAULTS["window"], odometry_delay=delay)
        if args.robots is not None:
            kw["robots"] = args.robots
        if args.test_robots is not None:
            kw["test_robots"] = args.test_robots
    return target_name, loss, steps, lr, real, kw


def run_tuning(args, progress_stream=None, plan=None) -> dict:
    """Build, fit, evaluate; returns the tune JSON dict (host-side, JSON-ready).  ``plan``: what
    :func:`_plan` returned for ``args`` (checked again when not given)."""
    target_name, loss, steps, lr, real, kw = _plan(args) if plan is None else plan
    import jax
    import jax.numpy as jnp

    import jaxslam
    from jaxslam.progress import Progress
    from jaxslam.sim import monte_carlo
    from jaxslam.tuning import optimize, targets

    kw = dict(kw, dtype=jnp.float32 if args.float32 else jnp.float64)
    if target_name == "loop" and args.compare is not None:  # read before the (slow) build: a bad
        from jaxslam.control import dflqr  # file is the only line (and needs JAX, x64 set first)
        from jaxslam.tuning.targets import loop as loop_target

        loop_target.controller_file(args.compare, dflqr.paper000_params())
    quiet = args.quiet
    stream = progress_stream or sys.stderr
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError):
        tty = False

    def say(msg):
        if not quiet:
            print(msg, file=stream, flush=True)

    t_all = time.perf_counter()
    say(f"{PROG}: building {args.scenario} --target {target_name} --loss {loss} "
        + ("(real logs)" if real else f"({args.train_runs} training runs, {args.test_runs} held-out)"))
    tg = targets.get(args.scenario, target_name, loss, **kw)
    t_build = time.perf_counter() - t_all

    # On a terminal a redrawn bar shows the loss; on a pipe or file, one line every ~10 % of
    # the steps (and at every skipped update) is the progress.
    bar = Progress(steps + 1, label="tune", enabled=not quiet and tty, stream=stream, delay_s=0.0)
    every = max(1, steps // 10)

    def cb(rec):
        bar.label = f"tune loss {rec['loss']:.5g}"
        bar.update(rec["step"] + 1)
        if rec.get("dropped_runs"):  # said at every such step: a run diverged at these parameters
            msg = (f"  step {rec['step']:4d}: training run(s) {', '.join(map(str, rec['dropped_runs']))} "
                   "non-finite or exploding: left out of this step's loss and gradient")
            if tty:
                bar.note(msg)
            else:
                say(msg)
        if tty or not (rec["step"] % every == 0 or rec["step"] == steps or rec.get("skipped")):
            return
        extra = f"  held-out {rec['test_loss']:.5g}" if rec.get("test_loss") is not None else ""
        flag = "  (gradient non-finite: update skipped)" if rec.get("skipped") else ""
        say(f"  step {rec['step']:4d}  loss {rec['loss']:.6g}  |grad| {rec['grad_norm']:.3g}"
            f"  lr {rec['lr']:.3g}{extra}{flag}")

    say(f"{PROG}: compiling the training step (value and gradient) ...")
    # (the x64-on key of the seed whatever the dtype: with x64 off PRNGKey kept 32 bits)
    key = jnp.asarray(monte_carlo.seed_key(args.seed)) if args.batch_size else None
    try:
        res = optimize.fit(tg.loss_fn, tg.theta0, tg.train, steps, lr, test=tg.test,
                           eval_every=args.eval_every, clip=args.clip, batch_size=args.batch_size,
                           key=key, callback=cb, describe=tg.describe, b2=args.b2,
                           log_objective=tg.log_objective, sequential=tg.sequential,
                           explode_ratio=EXPLODE_RATIO if tg.log_objective else None)
    finally:
        bar.close()
    say(f"{PROG}: compile {res.compile_s:.1f} s, {res.step_s:.3g} s per step")
    if res.interrupted:  # no held-out evaluation: keep the best parameters the finished steps reached
        phys0, phys1 = tg.physical(tg.theta0), tg.physical(res.best_theta)
        params_after = {**_params_file(tg, tg.to_params(phys1)), "interrupted": True}
        report = {
            "scenario": tg.scenario, "target": tg.target, "loss": tg.loss, "interrupted": True,
            "stopped": res.stopped, "steps_done": len(res.history), "steps": steps, "lr": lr,
            "params_before": tg.to_params(phys0), "params_after": params_after,
            "history": res.history, "n_skipped": res.n_skipped, "n_dropped_runs": res.n_dropped,
            "config": {**tg.config, "steps": steps, "lr": lr},
            "timing": {"build_s": t_build, "compile_s": res.compile_s, "step_s": res.step_s,
                       "total_s": time.perf_counter() - t_all},
            "memory": res.memory, "eval_command": tg.eval_command,
            **({"eval_note": tg.eval_note} if tg.eval_note else {}),
            "versions": {"jaxslam": jaxslam.__version__, "jax": jax.__version__},
            **params_after,
        }
        report["stopped"] += " (the saved parameters are those of the lowest training loss)"
        report["_physical_after"] = tg.describe(res.best_theta)
        return report
    if res.stopped:
        print(f"{PROG}: warning: {res.stopped}", file=sys.stderr, flush=True)
    if res.n_dropped:
        steps_hit = sum(1 for h in res.history if h.get("dropped_runs"))
        print(f"{PROG}: warning: {res.n_dropped} training run(s) non-finite or exploding (loss above "
              f"{EXPLODE_RATIO:g}x the batch median) at {steps_hit} step(s), left out of those steps "
              "(history: dropped_runs)", file=sys.stderr, flush=True)
    phys0, phys1 = tg.physical(tg.theta0), tg.physical(res.theta)
    refs = tg.references_for(phys1)
    say(f"{PROG}: evaluating start, tuned{''.join(', ' + k for k in refs)} on "
        + (f"{tg.config.get('evaluated_on')} ..." if real else f"{args.test_runs} held-out runs ..."))
    t0 = time.perf_counter()
    ev = tg.evaluate({"before": phys0, "after": phys1, **refs})
    t_eval = time.perf_counter() - t0
    params_after = _params_file(tg, tg.to_params(phys1))
    report = {
        "scenario": tg.scenario,
        "target": tg.target,
        "loss": tg.loss,
        "before": _summ(ev["before"]),
        "after": _summ(ev["after"]),
        "params_before": tg.to_params(phys0),
        "params_after": params_after,
        "history": res.history,
        "references": {k: {**_summ(ev[k]), "params": tg.to_params(v)} for k, v in refs.items()},
        "stopped": res.stopped,
        "n_skipped": res.n_skipped,
        "n_dropped_runs": res.n_dropped,
        "steps": steps,
        "lr": lr,
        "config": {**tg.config, "steps": steps, "lr": lr, "clip": args.clip, "batch_size": args.batch_size,
                   "eval_every": args.eval_every, "b2": args.b2, "log_objective": tg.log_objective,
                   "optimizer": "adam (optax), warmup + cosine decay, clip_by_global_norm"},
        "timing": {"build_s": t_build, "compile_s": res.compile_s, "step_s": res.step_s,
                   "eval_s": t_eval, "total_s": time.perf_counter() - t_all},
        "memory": res.memory,
        "eval_command": tg.eval_command,
        **({"eval_note": tg.eval_note} if tg.eval_note else {}),
        "versions": {"jaxslam": jaxslam.__version__, "jax": jax.__version__},
        **params_after,
    }
    report["_tables"] = format_comparison(report["before"], report["after"], report["references"])
    report["_physical_after"] = tg.describe(res.theta)
    report["_history_np"] = res.history
    return report


def _params_file(tg, params: dict) -> dict:
    """A ``--params`` file's content: the sections, and the scenario they were tuned for (real-log
    targets name their ``dataset`` themselves), so a file applied elsewhere is refused."""
    return params if "dataset" in params else {"scenario": tg.scenario, **params}


def _print_report(rep, params_file=None, data=None):
    print(f"scenario {rep['scenario']}: tuned {rep['target']} by {rep['loss']} "
          f"({rep['steps']} steps, lr {rep['lr']:g}); held-out evaluation:")
    print()
    print(rep["_tables"])
    print()
    # covariances and weights by their diagonals, sigma_* as standard deviations, and a full
    # matrix (linear-gaussian's R) row by row, as each target's describe() gives them
    print("tuned parameters:")
    for k, v in rep["_physical_after"].items():
        print(f"  {k}: [" + ", ".join(f"{x:.4g}" for x in v) + "]")
    if rep.get("stopped"):
        print(f"stopped early: {rep['stopped']}")
    if rep.get("eval_command"):
        # the file written (--params-out, else the tune JSON, itself a --params file) and the --data
        # folder given; without --data the dataset command reads $JAXSLAM_DATA_DIR as tune did
        cmd = rep["eval_command"]
        if params_file is not None:
            cmd = cmd.replace("TUNED.json", shlex.quote(str(params_file)))
        if data:
            cmd = cmd.replace("--data DIR", f"--data {shlex.quote(str(data))}")
        elif os.environ.get("JAXSLAM_DATA_DIR"):
            cmd = cmd.replace(" --data DIR", "")
        print(f"run the tuned parameters: {cmd}")
        if rep.get("eval_note"):
            print(f"  ({rep['eval_note']})")


def main(argv=None) -> int:
    """Entry point of ``jaxslam tune`` (also callable directly).  Returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if not argv:  # a usage error: one line (it printed the whole help on stdout, exit 2)
            from jaxslam.tuning import targets

            raise UsageError(f"{PROG}: missing SCENARIO (see '{PROG} --help'); tunable scenarios: "
                             f"{', '.join(sorted({s for s, _ in targets.available()}))}")
        if argv[0] in ("-h", "--help"):
            build_parser().print_help()
            return 0
        args = build_parser(with_targets="-h" in argv or "--help" in argv).parse_args(argv)
        from jaxslam import files

        plan = _plan(args)  # the arguments against the declared targets, before any folder is made
        # Every output path checked (and its folder created) before JAX is even imported.
        json_path = files.prepare_file("--json", args.json) if args.json is not None else None
        params_out = files.prepare_file("--params-out", args.params_out) if args.params_out is not None else None
        files.distinct_outputs(json=json_path, params_out=params_out, folders={"plots": args.plots},
                               inputs={"compare": getattr(args, "compare", None)})
        plots = files.prepare_dir("--plots", args.plots) if args.plots is not None else None
        import jax  # x64 before any target module is imported (module constants take its dtype)

        if not args.float32:
            jax.config.update("jax_enable_x64", True)
        from jaxslam import compilation

        with compilation.account() as acct:
            rep = run_tuning(args, plan=plan)
        rep["timing"]["step_compile_s"] = rep["timing"].pop("compile_s")
        rep["timing"].update(compile_timing(acct.result))
    except (InputError, UsageError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(msg if msg.startswith("jaxslam") else f"{PROG}: error: {msg}", file=sys.stderr)
        return 2
    from jaxslam import io

    interrupted = bool(rep.get("interrupted"))
    if not interrupted:
        raise_if_interrupted()  # a Ctrl-C whose exception was dropped: exit 130, nothing written
    if not args.quiet and not interrupted:
        _print_report(rep, params_out if params_out is not None else json_path, getattr(args, "data", None))
    written = []
    clean = {k: v for k, v in rep.items() if not k.startswith("_")}
    if json_path is not None:
        written.append(io.write_json(json_path, clean))
    if params_out is not None:
        written.append(io.write_json(params_out, rep["params_after"]))
    if interrupted:  # what the finished steps reached is saved; no evaluation, no plots
        print(f"{PROG}: {rep['stopped']}; no held-out evaluation"
              + (f"; wrote {', '.join(map(str, written))} (marked \"interrupted\": true)" if written
                 else " (no --json / --params-out: nothing saved)"), file=sys.stderr, flush=True)
        return 130
    if plots is not None:
        import matplotlib

        matplotlib.use("Agg")
        from jaxslam.plotting import tuning as tplot

        written += tplot.plot_all(clean, plots)
    if not args.quiet:
        for w in written:
            print(f"wrote {w}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
