"""Your own model on jaxslam's generic filters: 2D bearing-only SLAM with a prior map.

None of the four papers: a planar robot (unicycle) sees the *bearings* of a few landmarks whose
positions are known only roughly (a survey good to ±0.5 m).  A bearing does not fix a landmark,
so the map is not registered from one sighting: it starts from the survey as a prior, preloaded
with its covariance, and the filter refines robot and map together.

The script:

1. defines the model (motion, bearing, angle residual) in a few lines: a ``SlamModel``;
2. runs it through the generic EKF-SLAM runner (``jaxslam.filters.ekf_slam.run``) and, with the
   map held exact, through the generic EKF (``jaxslam.filters.ekf.filter_scan``): the two give
   the same robot track, as they must;
3. vmaps simulation + filter over 100 seeds and checks the robot NEES against its χ² bounds;
4. tunes the bearing noise σ_b by gradient (optax Adam on the innovation log-likelihood of 20
   training runs, scored on 20 held-out runs; 8 and 8 with ``--quick``), from a start 4× too large.

Run it:  python examples/bearing_only_slam.py [--quick] [--plot FILE.png]
(``--quick``: fewer steps, tuning iterations and tuning runs; the tests run it that way.)
The ``--plot`` path is checked before anything is computed: one that cannot be written (its
folder lies under a file, or cannot be made or written) is an ``InputError`` naming ``plot``
(from the command line: one line naming ``--plot``, exit code 2).
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxslam.errors import InputError
from jaxslam.files import prepare_file
from jaxslam.filters import ekf
from jaxslam.filters import ekf_slam as es
from jaxslam.linalg import wrap_angle
from jaxslam.stats import anees_bounds, nees

# --- 1. The model: state s = (x, y, θ) [m, m, rad], input u = (v, ω), landmark l = (x, y) ------
DT = 0.1  # s


def motion(s, u, params=None):
    """Unicycle over one step of DT."""
    return jnp.stack([s[0] + DT * u[0] * jnp.cos(s[2]), s[1] + DT * u[0] * jnp.sin(s[2]), s[2] + DT * u[1]])


def bearing(s, l, params=None):
    """Bearing of landmark l from the robot, relative to its heading [rad]."""
    return wrap_angle(jnp.arctan2(l[1] - s[1], l[0] - s[0]) - s[2])[None]


MODEL = es.SlamModel(robot_dim=3, lm_dim=2, meas_dim=1, motion=motion, observe=bearing,
                     residual=lambda z, zh: wrap_angle(z - zh))

# --- The world (truth) ----------------------------------------------------------------------
LANDMARKS = jnp.array([[6.0, 0.0], [3.0, 5.5], [-3.0, 5.5], [-6.0, 0.0], [-3.0, -5.5], [3.0, -5.5]])
Q_TRUE = jnp.diag(jnp.array([0.02, 0.02, 0.01]) ** 2)  # process noise per step
SIGMA_B = 0.05  # rad, true bearing noise
SIGMA_MAP = 0.5  # m, survey σ per axis
P0 = jnp.diag(jnp.array([0.05, 0.05, 0.02]) ** 2)


def simulate(key, T):
    """A noisy circle of radius ~3 m: inputs, bearings (70 % of rows present) and the survey."""
    k1, k2, k3, k4, k5 = jax.random.split(key, 5)
    u = jnp.tile(jnp.array([1.0, 1.0 / 3.0]), (T, 1))
    w = jax.random.multivariate_normal(k1, jnp.zeros(3), Q_TRUE, (T,))
    s0 = jnp.array([0.0, -3.0, 0.0])

    def step(s, w_t):
        s = motion(s, u[0]) + w_t
        return s, s

    _, truth = jax.lax.scan(step, s0, w)
    zb = jax.vmap(lambda s: jax.vmap(lambda l: bearing(s, l))(LANDMARKS))(truth)  # (T, N, 1)
    z = wrap_angle(zb + SIGMA_B * jax.random.normal(k2, zb.shape))
    mask = jax.random.uniform(k3, z.shape[:2]) < 0.7
    survey = LANDMARKS + SIGMA_MAP * jax.random.normal(k4, LANDMARKS.shape)
    start = s0 + jax.random.multivariate_normal(k5, jnp.zeros(3), P0)
    ids = jnp.broadcast_to(jnp.arange(LANDMARKS.shape[0]), mask.shape)
    return start, es.SlamLog(u=u, z=z, ids=ids, mask=mask), survey, truth


# --- 2. The two generic runners ---------------------------------------------------------------
def slam(start, log, survey, sigma_b, map_sigma=SIGMA_MAP):
    """EKF-SLAM with the survey preloaded as the map's prior (map_sigma 0: held exact)."""
    N = survey.shape[0]
    st = es.preload(es.init(start, P0, N, 2), MODEL, survey, covs=jnp.broadcast_to(map_sigma**2 * jnp.eye(2), (N, 2, 2)))
    return es.run(MODEL, st, log, Q_TRUE, jnp.reshape(sigma_b**2, (1, 1)))


def localise(start, log, landmarks, sigma_b):
    """The generic EKF with the landmarks as constants: one bearing per landmark per step."""
    h = lambda s: jax.vmap(lambda l: bearing(s, l)[0])(landmarks)  # noqa: E731
    N = landmarks.shape[0]
    return ekf.filter_scan(motion, h, start, P0, log.u, log.z[..., 0], log.mask, Q_TRUE,
                           sigma_b**2 * jnp.eye(N), residual=lambda z, zh: wrap_angle(z - zh))


def main(quick: bool = False, plot: str | None = None) -> dict:
    if plot:
        prepare_file("plot", plot)  # an unusable path fails now, not after the whole run
    T = 150 if quick else 600
    runs, n_train, iters = 100, (8 if quick else 20), (80 if quick else 150)
    keys = jax.random.split(jax.random.PRNGKey(0), runs + 2 * n_train)
    mc_keys, train_keys, test_keys = keys[:runs], keys[runs:runs + n_train], keys[runs + n_train:]
    t0 = time.perf_counter()

    # One run: SLAM vs the generic EKF with the map held exact (same robot track).
    start, log, survey, truth = simulate(keys[0], T)
    exact = jax.jit(lambda: slam(start, log, LANDMARKS, SIGMA_B, 0.0).robot)()
    loc = jax.jit(lambda: localise(start, log, LANDMARKS, SIGMA_B).means)()
    agree = float(jnp.max(jnp.abs(exact - loc)))
    print(f"EKF-SLAM runner with the exact map vs the generic EKF: max |Δ robot| = {agree:.1e}")

    # 3. Monte Carlo: 100 seeds, simulation and filter vmapped as one program.
    @jax.jit
    def mc(keys):
        def one(key):
            start, log, survey, truth = simulate(key, T)
            out = slam(start, log, survey, SIGMA_B)
            e = out.robot - truth
            e = e.at[:, 2].set(wrap_angle(e[:, 2]))
            s_err = jnp.sqrt(jnp.mean(jnp.sum(e[:, :2] ** 2, 1)))
            m_err = jnp.sqrt(jnp.mean(jnp.sum((es.landmarks(out.final, MODEL) - LANDMARKS) ** 2, 1)))
            P_end = out.final.P[:3, :3]
            return s_err, m_err, nees(e[-1], P_end), jnp.sqrt(jnp.mean(jnp.sum((survey - LANDMARKS) ** 2, 1)))

        return jax.vmap(one)(keys)

    pos_rmse, map_rmse, nees_end, survey_rmse = (np.asarray(a) for a in mc(mc_keys))
    lo, hi = anees_bounds(3, runs)
    anees = float(nees_end.mean())
    print(f"{runs} runs × {T} steps: robot RMSE {pos_rmse.mean():.3f} m; map RMSE {map_rmse.mean():.3f} m "
          f"(survey {survey_rmse.mean():.3f} m); final ANEES {anees:.2f} in [{lo:.2f}, {hi:.2f}]: "
          f"{'yes' if lo <= anees <= hi else 'NO'}")

    # 4. Tune σ_b by gradient of the innovation likelihood (train on n_train runs, score as many others).
    data_train = jax.vmap(lambda k: simulate(k, T))(train_keys)
    data_test = jax.vmap(lambda k: simulate(k, T))(test_keys)

    def nll(log_sigma, data):
        start, log, survey, _ = data
        ll = jax.vmap(lambda a, b, c: slam(a, b, c, jnp.exp(log_sigma)).log_likelihood.sum())(start, log, survey)
        return -jnp.mean(ll) / T

    opt = optax.adam(optax.cosine_decay_schedule(0.1, iters))
    # a strongly typed scalar: a Python float would make a weakly typed array, and the first call
    # of `update` (weak) and the later ones (strong, from optax) would compile two programs
    theta = jnp.log(jnp.full((), 4 * SIGMA_B, dtype=jnp.result_type(float)))
    state = opt.init(theta)

    @jax.jit
    def update(theta, state):
        v, g = jax.value_and_grad(nll)(theta, data_train)
        upd, state = opt.update(g, state)
        return optax.apply_updates(theta, upd), state, v

    test_nll = jax.jit(nll)
    before = float(test_nll(theta, data_test))
    for _ in range(iters):
        theta, state, _ = update(theta, state)
    sigma_fit = float(jnp.exp(theta))
    after = float(test_nll(theta, data_test))
    truth_nll = float(test_nll(jnp.log(jnp.full((), SIGMA_B, dtype=theta.dtype)), data_test))
    print(f"σ_b tuned from {4 * SIGMA_B:.3f} to {sigma_fit:.4f} rad (truth {SIGMA_B}) in {iters} Adam steps; "
          f"held-out NLL per step {before:.3f} → {after:.3f} (at the truth {truth_nll:.3f})")
    print(f"total {time.perf_counter() - t0:.1f} s")

    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        out = jax.jit(lambda: slam(start, log, survey, SIGMA_B))()
        fig, ax = plt.subplots(figsize=(5, 5))
        ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1, label="truth")
        ax.plot(out.robot[:, 0], out.robot[:, 1], "C0-", lw=1, label="EKF-SLAM")
        ax.plot(LANDMARKS[:, 0], LANDMARKS[:, 1], "k*", ms=10, label="landmarks")
        ax.plot(survey[:, 0], survey[:, 1], "C3x", label="survey (prior)")
        L = es.landmarks(out.final, MODEL)
        ax.plot(L[:, 0], L[:, 1], "C0o", mfc="none", label="estimated map")
        ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=8)
        ax.set_title("bearing-only SLAM with a prior map (one run)")
        fig.savefig(plot, dpi=120, bbox_inches="tight")
        print(f"wrote {plot}")
    return {"agree": agree, "anees": anees, "anees_bounds": (lo, hi), "pos_rmse": float(pos_rmse.mean()),
            "map_rmse": float(map_rmse.mean()), "survey_rmse": float(survey_rmse.mean()),
            "sigma_fit": sigma_fit, "nll_before": before, "nll_after": after, "nll_truth": truth_nll}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps, tuning iterations and tuning runs")
    ap.add_argument("--plot", default=None, help="write a figure of one run to this PNG")
    a = ap.parse_args()
    if a.plot:
        try:
            prepare_file("--plot", a.plot)
        except InputError as e:
            print(f"bearing_only_slam.py: error: {e}", file=sys.stderr)
            raise SystemExit(2) from None
    jax.config.update("jax_enable_x64", True)  # the script's choice (the library never sets it)
    main(a.quick, a.plot)
