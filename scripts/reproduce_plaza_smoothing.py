"""Plaza 1/2 smoothed with the package's generic iterated smoother (issue 20): the figures of
docs/datasets.md "Smoothing Plaza".

    python scripts/reproduce_plaza_smoothing.py --data DIR [--robot 1 2] [--iters 30] [--start rts|ekf] [--damping L] [--json PATH]

``DIR`` holds ``gtsam/PlazaN_*.txt`` (docs/datasets.md).  Three estimates per log, all on
jaxslam's Plaza model (``systems.plaza_range``, ``PARAMS`` unchanged):

1. the EKF (``plaza_range.run``, beacons unknown, delayed initialisation);
2. its map-static RTS smoother (``plaza_range.Config(smooth=True)``, what ``jaxslam dataset plaza
   --smooth`` reports);
3. the MAP of the whole log by ``jaxslam.filters.smoother.iterated`` (Gauss–Newton) with Huber
   IRLS weights (k = 1.345, the 95 %-efficiency constant) on the state
   [x, y, θ, b, l_1 .. l_4] (12), every beacon in the state from t = 0.

Protocol — ground truth is used only to score finished estimates:
* start pose GT₀ (Plaza 2: heading + π), as the filter;
* beacon prior: mean = the EKF's final beacons, σ = 1000 m per axis (diffuse: the ranges decide);
  bias prior as the filter (0 ± 5 m);
* starting trajectory: the RTS smoother's (``--start rts``; from the EKF's own estimates plain
  Gauss–Newton did not converge on Plaza 2 in 40 iterations, its last step still 42 σ, and a
  fixed damping λ = 1 or 10 had not converged after 40 either — judged by the step size, not by
  ground truth); the process noise of each odometry increment is the filter's
  ``odo_process_noise`` evaluated on the EKF's trajectory (fixed over the iterations);
* every range of a listed beacon is used (the ranges the filter buffered before a beacon's
  initialisation too); σ_r = 1.2 m as the filter.
Nothing here was chosen by looking at a ground-truth error.

Per log, ``iterated_huber`` also holds ``converged`` (no ``not_converged`` flag: the last step
was below the tolerance) and ``status``, the names of every flag the smoother set on any step
(``[]`` when none: a ``not_psd`` factorisation failure or a ``non_finite`` value is named there
and on the printed line).

Usage errors (a robot other than 1 or 2, ``--iters`` < 1, ``--damping`` not > 0, missing data
files, a ``--json`` that is a folder, lies under a file or cannot be written) exit 2 with one line before any compute; ``--json`` is
written atomically once every log is done.  A log on which the EKF never initialised a beacon
(a short excerpt) stops with one line naming the beacons, exit code 1.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

from jaxslam import runtime

runtime.configure_process()

import numpy as np  # noqa: E402

from jaxslam import errors  # noqa: E402
from jaxslam.cli.common import ScriptParser, path_arg, positive_float, positive_int  # noqa: E402
from jaxslam.data.plaza import load_plaza  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read and the
    logs loaded (--help, a usage error and missing data exit before JAX loads), and by
    smooth_log (for callers from outside main)."""
    global jax, jnp, evaluate_planar, smoother, wrap_angle, map_error, pr
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxslam.data.runners import evaluate_planar
    from jaxslam.filters import smoother
    from jaxslam.linalg import wrap_angle
    from jaxslam.metrics import map_error
    from jaxslam.systems import plaza_range as pr


NB = 4
N = 4 + 2 * NB


def f_batch(x, u):
    """(ODO) on the pose, bias and beacons unchanged (``pr.odo_motion`` on the first 4)."""
    return jnp.concatenate([pr.odo_motion(x[:4], u), x[4:]])


def h_batch(x, slots):
    """(R1) for each of the event's K rows: ‖p − l_slot‖ + b."""
    L = x[4:].reshape(NB, 2)[slots]
    return jax.vmap(lambda lm: pr.range_observe(x[:4], lm)[0])(L)


def difference(a, b):
    d = a - b
    return d.at[2].set(wrap_angle(d[2]))


def status_fields(status):
    """``converged`` (no ``not_converged`` flag) and ``status``: the names of every flag the
    smoother set on any step (``jaxslam.errors.FLAG_NAMES``; ``[]`` when none), so that a failed
    factorisation (``not_psd``) or a NaN (``non_finite``) is reported, not only the iteration limit."""
    names = errors.decode(np.asarray(status))
    return {"converged": "not_converged" not in names, "status": names}


def smooth_log(d, iters, damping, start_from):
    _import_jax()
    log = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
    pose0 = np.asarray(d.start_pose(), np.float64)
    bid = np.asarray(d.node_id)
    t0 = time.perf_counter()
    res = pr.run(pr.log_from_events(log, pose0, bid), pr.Config(smooth=True))
    jax.block_until_ready(res.smoothed)
    t_ekf = time.perf_counter() - t0
    p = pr.PARAMS
    act = np.asarray(res.active)
    lm = np.asarray(res.landmarks)
    ids = np.asarray(res.landmark_ids)
    missing = [int(b) for b in bid if not np.any((ids == b) & act)]
    if missing:  # the beacon prior's mean is the EKF's final estimate: there is none
        from jaxslam.errors import InputError

        raise InputError(f"Plaza {d.which}: the EKF never initialised beacon(s) {', '.join(map(str, missing))} "
                         f"(too few ranges in this log): the smoother's beacon prior has no mean")
    beacons = np.stack([lm[(ids == b) & act][0] for b in bid])
    # inputs, measurements, masks (rows of listed beacons with a finite range)
    u = np.asarray(log.u, np.float64)
    z = np.asarray(log.z, np.float64)[..., 0]
    eq = np.asarray(log.ids)[..., None] == bid[None, None, :]
    slots = np.argmax(eq, -1).astype(np.int32)
    mask = np.asarray(log.mask) & eq.any(-1) & np.isfinite(z)
    z = np.where(mask, z, 0.0)
    est = np.concatenate([np.asarray(res.pos), np.asarray(res.heading)[:, None],
                          np.asarray(res.bias)[:, None]], 1)
    prev = np.concatenate([np.concatenate([pose0, [p.bias0]])[None], est[:-1]], 0)
    dt = np.asarray(log.dt, np.float64)
    Qr = np.asarray(jax.vmap(lambda s, uu, dd: pr.odo_process_noise(s, uu, dd, p))(
        jnp.asarray(prev), jnp.asarray(u), jnp.asarray(dt)))
    Q = np.zeros((len(u), N, N))
    Q[:, :4, :4] = Qr
    x0 = np.concatenate([pose0, [p.bias0], beacons.reshape(-1)])
    P0 = np.diag([p.p0_pos**2, p.p0_pos**2, p.p0_th**2, p.sigma_bias0**2] + [1000.0**2] * (2 * NB))
    start = np.asarray(res.smoothed, np.float64) if start_from == "rts" else est
    init = np.concatenate([start, np.tile(beacons.reshape(-1), (len(u), 1))], 1)
    R = np.eye(z.shape[1]) * p.sigma_r**2
    run = jax.jit(lambda: smoother.iterated(
        f_batch, h_batch, x0, P0, jnp.asarray(u), jnp.asarray(z), jnp.asarray(mask), jnp.asarray(Q), R,
        num_iter=iters, init=jnp.asarray(init), h_inputs=jnp.asarray(slots), difference=difference,
        robust=smoother.huber_weight(1.345), damping=damping))
    t0 = time.perf_counter()
    sm = jax.block_until_ready(run())
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sm = jax.block_until_ready(run())
    t_it = time.perf_counter() - t0
    gt = np.asarray(d.gt, np.float64).copy()
    gt[:, 2] += d.heading_offset
    out = {}
    for name, traj, bea in (("ekf", est[:, :3], beacons),
                            ("rts", np.asarray(res.smoothed)[:, :3], beacons),
                            ("iterated_huber", np.asarray(sm.means)[:, :3],
                             np.asarray(sm.means)[-1, 4:].reshape(NB, 2))):
        m, ev = evaluate_planar(log.t, traj, d.gt_t, gt)
        R_, tr = ev["transform"]
        me = map_error(bea, bid, d.node_xy, bid, transform=(R_, tr))
        out[name] = {"ate_m": m["ate_m"], "map_err_m": me.rmse}
    out["iterated_huber"].update(
        iterations=iters, last_step_sigma=float(sm.step_sizes[-1]),
        **status_fields(sm.status),
        bias_m=float(np.asarray(sm.means)[-1, 3]),
        first_call_s=t_first, run_s=t_it)
    out["ekf"]["run_s"] = t_ekf
    out["ranges_used"] = int(mask.sum())
    out["events"] = int(len(u))
    return out


def main(argv=None):
    ap = ScriptParser(prog="reproduce_plaza_smoothing.py", description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=path_arg, help="data root holding gtsam/")
    ap.add_argument("--robot", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--iters", type=positive_int, default=30)
    ap.add_argument("--damping", type=positive_float, default=None,
                    help="Levenberg-Marquardt damping λ of the iterated smoother (default: none)")
    ap.add_argument("--start", choices=("rts", "ekf"), default="rts",
                    help="starting trajectory of the iterations (default: the RTS smoother's)")
    ap.add_argument("--json", default=None, type=path_arg)
    a = ap.parse_args(argv)
    bad = [r for r in a.robot if r not in (1, 2)]
    if bad or len(set(a.robot)) != len(a.robot):
        ap.error(f"--robot: expected 1 and/or 2 (Plaza 1, Plaza 2), each once, got {' '.join(map(str, a.robot))}")
    if a.json is not None and pathlib.Path(a.json).is_dir():
        ap.error(f"--json: {a.json!r} is not a file path")
    if a.json is not None:  # under a file, a folder not writable: said now, not after the compute
        ap.output_file("--json", a.json, create=False)
    root = pathlib.Path(a.data)
    root = root / "gtsam" if (root / "gtsam").is_dir() else root
    from jaxslam.errors import InputError

    try:  # every log read before any compute: a missing file is said at once
        logs = {r: load_plaza(root, r) for r in a.robot}
    except InputError as e:
        ap.error(f"--data: {str(e).splitlines()[0] if str(e) else type(e).__name__}")
    _import_jax()
    res = {}
    for r in a.robot:
        try:
            res[f"plaza{r}"] = o = smooth_log(logs[r], a.iters, a.damping, a.start)
        except InputError as e:  # (a beacon the EKF never initialised)
            print(f"reproduce_plaza_smoothing.py: error: --robot {r}: {e}", file=sys.stderr)
            return 1
        print(f"Plaza {r}: " + "  ".join(
            f"{k} ATE {o[k]['ate_m']:.3f} m (beacons {o[k]['map_err_m']:.2f} m)"
            for k in ("ekf", "rts", "iterated_huber"))
            + f"  | iterated: last step {o['iterated_huber']['last_step_sigma']:.2e} σ, "
              f"converged {o['iterated_huber']['converged']}, "
              f"flags {' '.join(o['iterated_huber']['status']) or 'none'}, bias {o['iterated_huber']['bias_m']:+.2f} m, "
              f"{o['iterated_huber']['run_s']:.1f} s")
    if a.json:
        from jaxslam import files

        text = json.dumps(res, indent=1)
        files.atomic_write(pathlib.Path(a.json), lambda f: f.write(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
