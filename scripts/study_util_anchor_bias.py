"""Development: per-anchor UWB range bias as a 4th landmark coordinate (UTIL, known anchors, ranges only).

    python scripts/study_util_anchor_bias.py SIGMA_AB NU|none GATE|none [SIGMA_R] [DATA_DIR]

SIGMA_AB: prior σ of each anchor's own bias (0: the shipped common-bias filter, 0.222 m);
NU: Student-t update; GATE: χ²(1) gate.  Prints the airborne position RMSE and the biases.
Measured (docs/datasets.md): per-anchor biases make it worse (0.23-0.34 m): with a
constant-velocity tag they absorb position error instead of the non-line-of-sight offsets.
"""
from jaxslam import runtime

# an entry point: OpenBLAS pinned, the XLA workaround flags, the compilation cache, before NumPy
# loads (the other scripts do the same; this one did not)
runtime.configure_process()
from jaxslam.cli.common import ScriptParser, nonnegative_float, path_arg, positive_float  # noqa: E402

import numpy as np  # noqa: E402


def _import_jax():
    """JAX and the modules that load it, imported by main once the arguments are read: --help
    and a usage error exit before JAX loads."""
    global jax, jnp, ur, _cast_params, es, tri, load_util, tag_positions, safe_norm
    import jax
    import jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    from jaxslam.systems import util_range as ur
    from jaxslam.systems.biased_range import _cast_params
    from jaxslam.filters import ekf_slam as es
    from jaxslam.filters import trilateration as tri
    from jaxslam.data.util_uwb import load_util, tag_positions
    from jaxslam.linalg import safe_norm


def _or_none(parse):
    """argparse type: ``none``, or a value read by ``parse`` (one of the CLI's types)."""
    return lambda text: None if text == "none" else parse(text)


def parser():
    ap = ScriptParser(prog="study_util_anchor_bias.py", description=__doc__.splitlines()[0])
    ap.add_argument("sig_ab", type=nonnegative_float, metavar="SIGMA_AB",
                    help="prior sigma [m] of each anchor's own bias (0: the shipped common-bias filter)")
    ap.add_argument("nu", type=_or_none(positive_float), metavar="NU|none", help="Student-t update (none: Gaussian)")
    ap.add_argument("gate", type=_or_none(positive_float), metavar="GATE|none", help="chi2(1) gate (none: no gate)")
    ap.add_argument("sigma_r", nargs="?", type=positive_float, default=0.2, metavar="SIGMA_R",
                    help="range noise sigma [m] (default 0.2)")
    ap.add_argument("data", nargs="?", default=None, type=path_arg, metavar="DATA_DIR",
                    help="the data folder (default: $JAXSLAM_DATA_DIR)")
    return ap


def main(argv=None):
    ap = parser()
    a = ap.parse_args(argv)
    sig_ab, nu, gate, sigma_r = a.sig_ab, a.nu, a.gate, a.sigma_r
    DATA = ap.data_root(a.data, flag="DATA_DIR")
    _import_jax()

    def obs4(s, l, params=None):
        return jnp.reshape(safe_norm(s[:3] - l[:3]) + s[-1] + l[3], (1,))
    M4 = es.SlamModel(robot_dim=7, lm_dim=4, meas_dim=1, motion=None, observe=obs4)
    d = load_util(DATA, "twr_obs_log1")
    tag = tag_positions(d.gt_p, d.gt_q, d.tag_offset)
    log = ur.util_events(d.twr_t, d.twr_anchor, d.twr_range)
    aid = jnp.asarray(d.anchor_id, jnp.int32); N = aid.shape[0]
    anchors = jnp.asarray(d.anchor_p)
    p = _cast_params(ur.PARAMS._replace(sigma_r=sigma_r), jnp.float64)
    rl = ur.log_from_events(log, aid, anchors=anchors, dtype=jnp.float64)
    dt, z, ids, mask = rl.dt, rl.z, rl.ids, rl.mask
    nf = 16
    z0, ids0 = z[:nf, 0, 0], ids[:nf, 0]
    eq = ids0[:, None] == aid[None, :]
    fix = tri.trilaterate(anchors[jnp.argmax(eq, axis=1)], z0, mask=jnp.any(eq, axis=1))
    s0 = jnp.concatenate([fix.position, jnp.zeros(4)])
    p0 = jnp.asarray([p.p0_pos] * 3 + [p.p0_vel] * 3 + [p.p0_bias])
    st = es.init(s0, jnp.diag(p0 * p0), N, 4)
    L = jnp.concatenate([anchors, jnp.zeros((N, 1))], 1)
    x = st.x.at[7:7 + 4 * N].set(L.reshape(-1))
    Pd = jnp.diagonal(st.P).at[7:7 + 4 * N].set(jnp.tile(jnp.asarray([0, 0, 0, sig_ab**2]), N))
    st = st._replace(x=x, P=jnp.diag(Pd), active=st.active.at[:N].set(True), ids=st.ids.at[:N].set(aid))
    @jax.jit
    def run(st):
        def step(st, inp):
            dt_k, z_k, id_k, m_k = inp
            Q = ur.cv_process_noise(dt_k, p.q_acc, p.q_bias, st.x.dtype)
            st = es.predict(st, M4._replace(motion=lambda s, u, pp: ur.cv_motion(s, u, dt_k)), None, Q)
            slots, mapped = es.associate_known(st, id_k, m_k)
            st, info = es.update(st, M4, z_k, slots, mapped, jnp.reshape(p.sigma_r**2, (1, 1)), gate=gate, robust=nu)
            return st, st.x[:3]
        return jax.lax.scan(step, st, (dt, z, ids, mask))
    stf, pos = run(st)
    t = np.asarray(log.t); pos = np.asarray(pos)
    true = np.stack([np.interp(t, d.gt_t, tag[:, j]) for j in range(3)], 1)
    rng_ev = np.any(np.asarray(log.mask) & (np.asarray(log.ids) >= 0), axis=1)
    err = np.linalg.norm(pos - true, axis=1)[rng_ev]; air = true[rng_ev][:, 2] > 0.3
    ab = np.asarray(stf.x[7:7 + 4 * N]).reshape(N, 4)[:, 3]
    print(f"sig_ab {sig_ab} nu {nu} gate {gate} sr {sigma_r}: rmse {np.sqrt(np.mean(err[air]**2)):.4f}  common b {float(stf.x[6]):.3f}  per-anchor {np.round(ab,3)}")


if __name__ == "__main__":
    main()
