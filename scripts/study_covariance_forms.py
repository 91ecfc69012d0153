"""Development (issue 19): the paper-000 EKF-SLAM's covariance over 10⁵ IMU steps, Joseph form
against the standard form P − K S Kᵀ, float64 and float32 (docs/papers.md, "Eq. 43").

    python scripts/study_covariance_forms.py [--steps 100000] [--seeds 0,1] [--json PATH]
                                             [--r-scale 1,1e-4]

Flies the ``ekfslam3d-unknown`` closed loop (DF-LQR on the estimate, the scenario's defaults:
``--q imu``, capacity 64) for ``--steps`` control steps with each covariance form and dtype, and
reports per flight: the filter's status flags (NOT_PSD: an innovation covariance whose Cholesky
failed; NON_FINITE), the final covariance's asymmetry (max |P − Pᵀ|) and smallest eigenvalue
relative to its largest (over the robot block and the mapped landmarks), the position RMSE and
the per-frame NEES mean.  ``--r-scale`` shrinks the filter's LiDAR R below the simulated noise
(an over-confident filter, the hard case for either form); 1 is the scenario as it is.
Truth is read only for the printed errors.
"""
import json
import time

from jaxslam import runtime

runtime.configure_process(cache=False)
from jaxslam.cli.common import ScriptParser, path_arg, positive_float, positive_int, seed_int  # noqa: E402

import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, errors, dflqr, imu_mod, lm_mod, registry, DT, FRAME_STEPS, make_setup, paper000_figure8
    global controls, simulate, sys3d
    import jax
    import jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    from jaxslam import errors
    from jaxslam.control import dflqr
    from jaxslam.sensors import imu as imu_mod
    from jaxslam.sensors import landmarks as lm_mod
    from jaxslam.sim.scenarios import registry
    from jaxslam.sim.scenarios.tracking import DT, FRAME_STEPS, make_setup, paper000_figure8
    from jaxslam.sim.simulate import controls, simulate
    from jaxslam.systems import ekf_slam_3d as sys3d


def _list_of(parse):
    """argparse type: comma-separated values, each read by ``parse`` (one of the CLI's types)."""
    return lambda text: [parse(s.strip()) for s in text.split(",")]


def main(argv=None):
    ap = ScriptParser(prog="study_covariance_forms.py", description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=positive_int, default=100_000)
    ap.add_argument("--seeds", type=_list_of(seed_int), default="0,1")
    ap.add_argument("--r-scale", type=_list_of(positive_float), default="1,1e-4")
    ap.add_argument("--json", type=path_arg)
    a = ap.parse_args(argv)
    if a.json:
        ap.output_file("--json", a.json)  # an unusable path (a folder, under a file) before the flights
    _import_jax()  # (FRAME_STEPS is the tracking scenario's, a module that loads JAX)
    if a.steps < FRAME_STEPS:  # (fewer flew no frame at all)
        ap.error(f"--steps: expected at least {FRAME_STEPS} (one frame), got {a.steps}")
    opts = {o.name: o.default for o in registry.get("ekfslam3d-unknown").options}
    nf = a.steps // FRAME_STEPS
    out = {"steps": nf * FRAME_STEPS, "duration_s": nf * FRAME_STEPS * DT, "capacity": int(opts["capacity"]),
           "scenario": "ekfslam3d-unknown defaults (--q imu), DF-LQR on the estimate", "flights": []}
    for dtype in (jnp.float64, jnp.float32):
        base = dflqr.paper000_params()
        traj = paper000_figure8(float(opts["altitude"]), 0.0)
        K, refs = controls(make_setup(traj, dtype, ctrl=base), nf * FRAME_STEPS, True,
                           compiler_options=runtime.compiler_options())
        noise0 = sys3d.imu_noise(imu_mod.PAPER000_IMU, dtype)
        for r_scale in a.r_scale:
            noise = noise0._replace(R=noise0.R * jnp.asarray(r_scale, dtype))
            for joseph in (True, False):
                cfg = sys3d.Config(mode="unknown", association=opts["association"], capacity=int(opts["capacity"]),
                                   max_obs=int(opts["max_obs"]), accel_mode=opts["accel"], dt=DT,
                                   g=float(base.quad.g), save_map=False, joseph=joseph)

                @jax.jit
                def fly(key, cfg=cfg, noise=noise, dtype=dtype):
                    k_lm, k_fl = jax.random.split(key)
                    lms = lm_mod.generate_landmarks(k_lm, int(opts["landmarks"]),
                                                    center=np.asarray(traj.center, float), dtype=dtype)
                    setup = make_setup(traj, dtype, landmarks=lms, ctrl=base)
                    est = sys3d.make_estimator(cfg, noise, landmarks_true=lms)
                    fl = simulate(setup, k_fl, nf, FRAME_STEPS, estimator=est, control_on="estimate", K=K, refs=refs)
                    st = fl.est_final.slam
                    used = jnp.concatenate([jnp.ones((sys3d.NX,), bool), jnp.repeat(st.active, 3)])
                    Pu = jnp.where(used[:, None] & used[None, :], st.P, 0.0) + jnp.diag(jnp.where(used, 0.0, 1.0))
                    lam = jnp.linalg.eigvalsh(Pu.astype(jnp.float64))
                    e = fl.est_steps.mean[:, :3] - fl.truth[1:, :3]
                    return {"status": st.status, "asym": jnp.max(jnp.abs(st.P - st.P.T)),
                            "lam_min_rel": lam[0] / lam[-1], "mapped": jnp.sum(st.active),
                            "pos_rmse_m": jnp.sqrt(jnp.mean(jnp.sum(e ** 2, -1))),
                            "nees_mean": jnp.mean(fl.est_frames.nees)}

                for seed in a.seeds:
                    t0 = time.perf_counter()
                    r = jax.tree.map(lambda v: np.asarray(v).item(), fly(jax.random.PRNGKey(seed)))
                    r.update(dtype=jnp.dtype(dtype).name, r_scale=r_scale, joseph=joseph, seed=seed,
                             flags=errors.decode(int(r["status"])),
                             wall_s=round(time.perf_counter() - t0, 1))
                    out["flights"].append(r)
                    print(json.dumps(r), flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
