"""Tunable targets: what is tuned, on which data, with which loss, evaluated how.

A :class:`Target` bundles the unconstrained parameters θ (a dict of vectors, see
:mod:`jaxslam.tuning.params`), a per-run loss ``loss_fn(θ, item)``, the training batch
(leading axis = runs), a held-out batch for the test-loss curve, and ``evaluate`` — the
held-out before/after comparison on the scenario itself (the same flights ``jaxslam run``
flies).  Factories build targets; :func:`get` looks them up by ``(scenario, target)``.

Built-in targets

* ``("ekfslam3d-unknown", "noise")`` and ``("ekfslam3d-known", "noise")`` — paper 000's
  EKF-SLAM: the process-noise density Q_c of the IMU-driven filter (optionally the LiDAR
  R).  Training data are **recorded logs**: flights are simulated once (DF-LQR on the
  truth, IMU and LiDAR noise drawn), then the loss runs :func:`run_slam_log` — the filter
  alone, open loop, exactly what a user does with a real log — and never differentiates
  the closed loop.  Held-out evaluation flies the full closed-loop scenario (DF-LQR on the
  estimate) on seeds never used in training.
* ``("track-figure8", "lqr")`` — the DF-LQR weights Q̃, R̃ (paper 000 Table 2) by the
  gradient of a closed-loop cost through the differentiable CARE and the simulation scan.
* ``("linear-gaussian", "noise")`` — a 2D constant-velocity model with position
  measurements and known Q, R: the oracle for NLL tuning (the maximum-likelihood estimate
  of Q, R is consistent, so tuning must recover them).

Decisions (no paper covers tuning):

* **ekfslam3d**: the tuned matrix is Q_c (Table 7's form, log-diagonal by default), started
  from Table 7 with Q_imu = 0 — "the paper's filter, re-tuned".  P0 is held at the
  ``--q imu`` value and R at Table 4 (unless ``tune_r``) in training and evaluation:
  the scenario draws each run's initial estimate from P0, so changing P0 would change the
  flights themselves, and the comparison with the ``--q imu`` reference would no longer be
  on equal flights.  The saved ``--params`` file holds P0, Q_c, Q_imu and R, so
  ``jaxslam run ekfslam3d-unknown --params FILE`` reproduces the evaluation whatever ``--q``.
* Training logs are flown with the controller on the truth (a log does not depend on the
  filter being tuned) and may be shorter than the 50 s scenario; the first IMU sample of a
  log is the noise-free reading at the initial hover (what :func:`simulate` uses), and the
  initial estimate is drawn from P0.  Seeds: training runs use ``keys_for(seed, M)``, the
  held-out test runs ``keys_for(seed + 1, M)`` — the seeds of ``jaxslam run --seed seed+1``.
* NLL needs the joint innovation covariance of each frame: the engine's update reports its
  NIS, log det S and degrees of freedom (:class:`jaxslam.filters.ekf_slam.UpdateInfo`), from
  the prior and the estimator's own measurement selection, so nothing is formed twice; the
  NLL target requires known association and no gate (checked), so that the update's
  measurements are the log's.
* **track-figure8**: with the controller on the truth the scenario's flight is deterministic,
  so training and held-out runs differ by a random initial state (hover at a position offset
  of σ = 0.5 m per axis, yaw σ = 0.1 rad; ``start_sigma``); the nominal start (the flight of
  ``jaxslam run track-figure8``) is reported as well.  Cost per run (fixed evaluation
  weights, not the tuned ones): J = mean_t ‖ρ − ρ_d‖² + w_u mean_t ‖ũ‖², ũ the LQR correction
  (m/s², rad/s) recomputed from the flown states, w_u = 0.1 by default.
* ``jax.checkpoint`` wraps the body of the outer (per LiDAR frame) scan, so the backward
  pass stores one carry per frame and recomputes the ten inner steps: memory grows with the
  number of frames, not of IMU steps.
* Hook for more scenarios: :func:`register_target` (``uwb-circle`` is added where
  :mod:`jaxslam.systems.uwb_slam_2d` is available).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..filters import ekf as ekf_mod
from . import losses as L
from . import params as P

__all__ = [
    "Target",
    "SlamLog",
    "SlamRun",
    "register_target",
    "get",
    "available",
    "make_slam_logs",
    "run_slam_log",
    "slam_loss",
    "ekfslam3d_noise",
    "figure8_lqr",
    "linear_gaussian",
    "lg_simulate",
    "lg_run",
    "uwb_noise",
]


STRUCTURES = ("qc", "imu", "imu_iso")  # ekfslam3d noise: what is tuned (see ekfslam3d_noise)


class Target(NamedTuple):
    """A tuning problem (host-side container; see the module docstring).

    scenario, target, loss: names (e.g. ``"ekfslam3d-unknown"``, ``"noise"``, ``"nll"``).
    specs: {name: :class:`~jaxslam.tuning.params.CovSpec`} of the tuned matrices.
    theta0: {name: (p,) array} starting point.
    loss_fn: ``loss_fn(theta, item) -> ()`` per run (jit/vmap/grad-safe).
    train: training batch (pytree, leading axis = runs).
    test: held-out batch of the same form (or None): the test-loss curve.
    physical: ``physical(theta) -> params container`` (e.g. NoiseParams).
    evaluate: ``evaluate({label: physical}) -> {label: {"metrics": {name: (runs,)},
      "consistency": dict | None}}`` on held-out runs of the scenario itself.
    references: {label: physical} extra rows of the evaluation (e.g. ``"q_imu"``).
    to_params: ``to_params(physical) -> dict`` loadable by ``jaxslam run --params``.
    describe: ``describe(theta) -> {name: [floats]}`` physical values tracked in the history.
    config: every setting used (JSON-ready).
    eval_command: the ``jaxslam run`` command that reproduces the held-out "after" row.
    log_objective: optimise log(mean loss) (positive losses; see :func:`~jaxslam.tuning.optimize.fit`).
    sequential: the loss and gradient of each training item run after the other (``lax.map``),
      not vmapped: the compiled step is smaller (one log's program, not a batched one) and, for
      the EKF-SLAM logs, faster per step too (4 logs: compile 19.0 → 14.6 s, step 1.57 → 1.36 s).
    """

    scenario: str
    target: str
    loss: str
    specs: dict
    theta0: dict
    loss_fn: Callable
    train: Any
    test: Any
    physical: Callable
    evaluate: Callable
    references: dict
    to_params: Callable
    describe: Callable
    config: dict
    eval_command: str = ""
    log_objective: bool = False
    sequential: bool = False  # evaluate the training items one after another (lax.map)


_FACTORIES: dict = {}


def register_target(scenario: str, target: str, factory: Callable, losses: tuple) -> None:
    """Make ``factory(loss=..., train_runs=..., test_runs=..., seed=..., dtype=..., **kw) -> Target``
    available as ``jaxslam tune SCENARIO --target TARGET`` with the given ``losses``."""
    _FACTORIES[(scenario, target)] = (factory, tuple(losses))


def available() -> dict:
    """{(scenario, target): losses} of every registered target."""
    _load_optional()
    return {k: v[1] for k, v in sorted(_FACTORIES.items())}


def get(scenario: str, target: str, loss: str, **kw) -> Target:
    """Build the target ``(scenario, target)`` with ``loss``; raises InputError naming the valid ones."""
    _load_optional()
    if (scenario, target) not in _FACTORIES:
        valid = ", ".join(f"{s} --target {t}" for s, t in sorted(_FACTORIES))
        raise InputError(f"no tuning target {target!r} for scenario {scenario!r}; available: {valid}")
    factory, losses = _FACTORIES[(scenario, target)]
    if loss not in losses:
        raise InputError(f"--loss: {scenario} --target {target} supports {', '.join(losses)}; got {loss!r}")
    return factory(loss=loss, **kw)


#: scenarios whose targets learn from real logs (``--data``, ``--robots``, ``--window``)
REAL_LOG_SCENARIOS = ("mrclam",)


def _load_optional():
    """Register targets of systems that may be absent from an installation (UWB, paper 003),
    and the real-log targets (:mod:`jaxslam.tuning.real_logs`)."""
    if ("mrclam", "noise") not in _FACTORIES:
        from . import real_logs  # noqa: F401  (registers mrclam --target noise)
    if ("uwb-circle", "noise") in _FACTORIES:
        return
    try:
        from ..sim.scenarios import uwb as _scen  # noqa: F401
        from ..systems import uwb_slam_2d as _u  # noqa: F401
    except ImportError:
        return
    for sc in ("circle", "square", "rough"):
        register_target(f"uwb-{sc}", "noise", lambda _sc=sc, **kw: uwb_noise(scenario=_sc, **kw), ("mse", "nees"))


def _keys(seed: int, runs: int):
    from ..sim.monte_carlo import keys_for

    return keys_for(int(seed), int(runs))


def _diag_list(M):
    return [float(v) for v in np.diag(np.asarray(M))]


# ===========================================================================
# Paper 000 EKF-SLAM: recorded logs and the open-loop filter
# ===========================================================================

class SlamLog(NamedTuple):
    """A recorded flight (one run; batches add a leading axis).  T = F · lidar_every.

    s0: (9,) initial estimate [ρ m, v_B m/s, Λ rad].
    imu: (T + 1, 6) IMU samples at t = 0, Δt, …, TΔt [m/s², rad/s].
    y: (F, L, 3) LiDAR [α, β, δ] per frame; visible: (F, L) bool; ids: (L,) int32.
    truth: (T + 1, 12) true states (for MSE/NEES only; a real log may hold NaN here).
    landmarks: (L, 3) true landmarks [m] (known-map mode only).
    """

    s0: jax.Array
    imu: jax.Array
    y: jax.Array
    visible: jax.Array
    ids: jax.Array
    truth: jax.Array
    landmarks: jax.Array


class SlamRun(NamedTuple):
    """Outputs of :func:`run_slam_log` (one run).

    means: (T, 9) robot mean after every prediction step (and the frame's update).
    nll_nis, nll_logdet, nll_dof: (F,) NLL terms of each frame's update (zeros unless
      ``with_nll``).
    nees: (F,) robot NEES after each update (NaN unless ``with_nees``).
    nis, dof: (F,) the engine's joint NIS and its degrees of freedom.
    status: () int32 status bits of the final state.
    """

    means: jax.Array
    nll_nis: jax.Array
    nll_logdet: jax.Array
    nll_dof: jax.Array
    nees: jax.Array
    nis: jax.Array
    dof: jax.Array
    status: jax.Array


def _scenario_options(mode: str, **over) -> dict:
    from ..sim.scenarios import registry

    opts = {o.name: o.default for o in registry.get(f"ekfslam3d-{mode}").options}
    opts.update(over)
    return opts


_LOG_MAKERS: dict = {}


def _log_maker(n_landmarks: int, nf: int, dtype, altitude: float):
    """One jitted, vmapped flight recorder per static configuration (compiled once)."""
    from ..dynamics import euler_ned
    from ..sensors import imu as imu_mod
    from ..sensors import landmarks as lm_mod
    from ..sim.scenarios.tracking import FRAME_STEPS, make_setup, paper000_figure8
    from ..sim.simulate import simulate

    k = (n_landmarks, nf, jnp.dtype(dtype).name, float(altitude))
    if k in _LOG_MAKERS:
        return _LOG_MAKERS[k]
    traj = paper000_figure8(altitude, 0.0)
    center = np.asarray(traj.center, float)

    def one(key, sqrtP0):
        k_lm, k_fl, k_e = jax.random.split(key, 3)
        lms = lm_mod.generate_landmarks(k_lm, n_landmarks, center=center, dtype=dtype)
        setup = make_setup(traj, dtype, landmarks=lms)
        fl = simulate(setup, k_fl, nf, FRAME_STEPS, feedforward=True)
        quad = setup.ctrl.quad
        x0 = setup.x0
        imu0 = imu_mod.imu_ideal(x0, euler_ned.f(x0, euler_ned.hover_input(quad, dtype), quad), quad.g)
        s0 = x0[:9] + sqrtP0 @ jax.random.normal(k_e, (9,), dtype)
        return SlamLog(s0=s0, imu=jnp.concatenate([imu0[None].astype(dtype), fl.imu]), y=fl.lidar_y,
                       visible=fl.lidar_mask, ids=jnp.arange(n_landmarks, dtype=jnp.int32),
                       truth=fl.truth, landmarks=lms)

    _LOG_MAKERS[k] = jax.jit(jax.vmap(one, in_axes=(0, None)))
    return _LOG_MAKERS[k]


def make_slam_logs(seed: int, runs: int, duration: float, n_landmarks: int = 40, P0=None,
                   dtype=jnp.float64, altitude: float = 3.0):
    """Simulate ``runs`` flights of the paper-000 figure-8 once and return their logs.

    Flights as in the ``ekfslam3d`` scenarios (40 Table 3 landmarks per run, Table 4/5
    sensors, 100 Hz IMU, 10 Hz LiDAR) with the DF-LQR on the truth.  Run i uses
    ``keys_for(seed, runs)[i]`` split into (landmarks, flight, initial error); the initial
    estimate is the true start plus an error drawn from ``P0`` (9, 9) (default: the
    ``--q imu`` P0).  Returns a :class:`SlamLog` batch (leading axis runs) in ``dtype``.
    """
    from ..sim.scenarios.tracking import FRAME_STEPS
    from ..sim.simulate import n_frames
    from ..systems import ekf_slam_3d as sys3d

    dtype = jnp.dtype(dtype)
    if not (duration >= 0.1 and math.isfinite(duration)):
        raise InputError(f"duration: must be at least 0.1 s, got {duration}")
    if int(runs) < 1:
        raise InputError(f"runs: must be >= 1, got {runs}")
    P0 = np.diag(sys3d.IMU_P0) if P0 is None else np.asarray(P0, float)
    w, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    sqrtP0 = jnp.asarray(V * np.sqrt(np.clip(w, 0, None)), dtype)
    nf = n_frames(duration, 0.01, FRAME_STEPS)
    return _log_maker(int(n_landmarks), nf, dtype, altitude)(_keys(seed, runs), sqrtP0)


def run_slam_log(noise, cfg, log: SlamLog, lidar_every: int = 10, *, with_nll: bool = False,
                 with_nees: bool = False, checkpoint: bool = True) -> SlamRun:
    """Paper 000's EKF-SLAM on one recorded log, open loop, as one nested ``lax.scan``.

    The same estimator as the closed loop (:func:`jaxslam.systems.ekf_slam_3d.make_estimator`,
    paper 000 eq. 24-53) and the same step order as
    :func:`~jaxslam.systems.ekf_slam_3d.filter_log`; differentiable in every leaf of
    ``noise`` (P0 included: the initial state is built without the estimator's random draw).
    Static: ``cfg``, ``lidar_every``, ``with_nll`` (also compute the frames' NLL terms, which
    needs ``cfg.association == "known"`` and ``cfg.gate is None``), ``with_nees`` (NEES
    against ``log.truth``), ``checkpoint`` (``jax.checkpoint`` on the per-frame body).
    """
    from ..filters import ekf_slam as es
    from ..systems import ekf_slam_3d as sys3d

    if with_nll and (cfg.association != "known" or cfg.gate is not None):
        raise InputError("loss 'nll': needs association='known' and gate=None")
    nx = sys3d.NX
    dtype = log.s0.dtype
    F, Lm = log.visible.shape
    est = sys3d.make_estimator(noise, cfg, log.landmarks if cfg.mode == "known" else None)

    st = es.init(log.s0, noise.P0.astype(dtype), cfg.capacity, 3)
    if cfg.mode == "known":
        idx = jnp.arange(Lm)
        st = st._replace(x=st.x.at[nx:nx + 3 * Lm].set(log.landmarks.reshape(-1).astype(dtype)),
                         active=st.active.at[idx].set(True), ids=st.ids.at[idx].set(idx.astype(jnp.int32)))
    z0 = jnp.zeros((), jnp.int32)
    e0 = sys3d.EstState(st, z0, z0)
    ids = log.ids
    imu_prev = log.imu[:-1].reshape(F, lidar_every, 6)
    imu_now = log.imu[1:].reshape(F, lidar_every, 6)
    x_frames = log.truth[lidar_every::lidar_every]
    zero = jnp.zeros((), dtype)

    def frame(e, inp):
        a, b, yf, vf, xt = inp

        def step(e2, ab):
            e2 = est.propagate(e2, ab[0], ab[1])
            return e2, e2.slam.x[:nx]

        e, means = jax.lax.scan(step, e, (a, b))
        e, out = est.correct(e, yf, ids, vf, xt if with_nees else None)
        # The update's own innovation terms (prior of this frame, the estimator's selection).
        terms = (out.nis, out.logdet, out.dof.astype(dtype)) if with_nll else (zero, zero, zero)
        return e, (means, terms, out.nees, out.nis, out.dof)

    body = jax.checkpoint(frame) if checkpoint else frame
    e, (means, terms, nees, nis, dof) = jax.lax.scan(
        body, e0, (imu_prev, imu_now, log.y, log.visible, x_frames))
    return SlamRun(means=means.reshape(-1, nx), nll_nis=terms[0], nll_logdet=terms[1],
                   nll_dof=terms[2], nees=nees, nis=nis, dof=dof, status=e.slam.status)


def slam_loss(run: SlamRun, log: SlamLog, loss: str, weights=None):
    """Per-run loss of a :class:`SlamRun`: ``"nll"``, ``"mse"`` or ``"nees"`` (module losses)."""
    from ..systems import ekf_slam_3d as sys3d

    if loss == "nll":
        return L.innovation_nll(run.nll_nis, run.nll_logdet, run.nll_dof)
    if loss == "mse":
        err = jax.vmap(sys3d.robot_error)(run.means, log.truth[1:])
        return L.mse(err, weights)
    if loss == "nees":
        return L.nees_loss(run.nees, sys3d.NX)
    raise InputError(f"loss: expected 'nll', 'mse' or 'nees', got {loss!r}")


def ekfslam3d_noise(loss: str = "nll", train_runs: int = 4, test_runs: int = 8, seed: int = 0,
                    dtype=jnp.float64, mode: str = "unknown", train_duration: float = 10.0,
                    eval_duration: float = 50.0, capacity: int | None = None, tune_r: bool = False,
                    cov: str = "diag", start: str = "paper", mse_weights=None,
                    checkpoint: bool = True, eval_chunk: int | None = None, structure: str = "qc",
                    **_ignored) -> Target:
    """Target: Q_c (and optionally R) of paper 000's EKF-SLAM, tuned on recorded logs.

    ``structure``: ``"qc"`` tunes the 9×9 process-noise density Q_c directly (Table 7's form,
    Q_imu = 0); ``"imu"`` tunes the 6×6 IMU density Q_imu that enters through the filter's own
    G Q_imu Gᵀ (paper 000 eq. 27 with the IMU as the noise input; Q_c = 0): the structure says
    that position is the integral of velocity and the noise enters through the IMU, leaving 6
    parameters.  With ``start="paper"`` it starts from Table 7's velocity and attitude entries
    (0.01 m²/s³ ×3, then 0.02, 0.2, 0.2 rad²/s) read as accelerometer and gyro densities.
    ``"imu_iso"``: the same with one density per sensor (Table 5's form, 2 parameters: the
    three axes of a sensor share it), started from the means of those Table 7 entries.
    ``start``: ``"paper"`` (Table 6/7, as above) or ``"imu"`` (the IMU-derived Q, projected
    on Q_c's diagonal for ``structure="qc"``).  ``cov``: ``"diag"`` (log-diagonal) or ``"chol"``
    (log-Cholesky, full matrix).  ``capacity``: landmark slots of the training filter
    (default: the number of landmarks, 40, which cannot overflow; estimates do not depend
    on the capacity).  Evaluation: the ``ekfslam3d-{mode}`` scenario, ``eval_duration``
    seconds, ``test_runs`` seeds from ``seed + 1``.  See the module docstring.
    """
    from ..sensors import imu as imu_mod
    from ..sim.scenarios import ekfslam3d as scen
    from ..sim.scenarios.tracking import DT, FRAME_STEPS
    from ..systems import ekf_slam_3d as sys3d

    dtype = jnp.dtype(dtype)
    if mode not in ("unknown", "known"):
        raise InputError(f"mode: expected 'unknown' or 'known', got {mode!r}")
    if cov not in P.KINDS:
        raise InputError(f"--cov: expected one of {P.KINDS}, got {cov!r}")
    if loss not in ("nll", "mse", "nees"):
        raise InputError(f"--loss: expected nll, mse or nees, got {loss!r}")
    if start not in ("paper", "imu"):
        raise InputError(f"start: expected 'paper' or 'imu', got {start!r}")
    if structure not in STRUCTURES:
        raise InputError(f"--structure: expected one of {STRUCTURES}, got {structure!r}")
    if structure == "imu_iso" and cov != "diag":
        raise InputError("--structure imu_iso: two densities (accelerometer, gyro); use --cov diag")
    ref = sys3d.imu_noise(imu_mod.PAPER000_IMU, dtype)
    nda2 = float(imu_mod.PAPER000_IMU.accel_noise_density) ** 2
    ndg2 = float(imu_mod.PAPER000_IMU.gyro_noise_density) ** 2
    Qc_paper = np.asarray(sys3d.paper_noise(mode, dtype).Qc)
    if structure == "qc":
        name, n = "Qc", sys3d.NX
        M0 = Qc_paper if start == "paper" else np.diag([1e-12] * 3 + [nda2] * 3 + [ndg2] * 3)
    elif structure == "imu":
        name, n = "Qimu", 6
        M0 = np.diag(np.diag(Qc_paper)[3:]) if start == "paper" else np.asarray(ref.Qimu)
    else:  # one density per sensor, the form of Table 5: [accelerometer, gyro]
        name, n = "Qimu_sensor", 2
        q7 = np.diag(Qc_paper)
        M0 = np.diag([np.mean(q7[3:6]), np.mean(q7[6:9])] if start == "paper" else [nda2, ndg2])
    specs = {name: P.CovSpec(cov, n)}
    mats = {name: M0}
    if tune_r:
        specs["R"] = P.CovSpec(cov, 3)
        mats["R"] = np.asarray(ref.R)
    theta0 = P.pack(specs, mats, dtype=dtype)
    n_lm = scen.N_LANDMARKS
    cap = n_lm if capacity is None else int(capacity)
    cfg = sys3d.EstimatorConfig(mode=mode, capacity=cap, dt=DT, g=9.81)
    if mode == "known" and cap < n_lm:
        raise InputError(f"capacity: {cap} slots cannot hold the {n_lm} known landmarks")

    def physical(theta):
        m = P.unpack(specs, theta)
        if "Qimu_sensor" in m:
            m["Qimu"] = jnp.diag(jnp.repeat(jnp.diag(m.pop("Qimu_sensor")), 3))
        return sys3d.NoiseParams(P0=ref.P0.astype(dtype), Qc=m.get("Qc", jnp.zeros((sys3d.NX, sys3d.NX), dtype)),
                                 Qimu=m.get("Qimu", jnp.zeros((6, 6), dtype)), R=m.get("R", ref.R.astype(dtype)))

    w = None if mse_weights is None else jnp.asarray(mse_weights, dtype)

    def loss_fn(theta, log):
        run = run_slam_log(physical(theta), cfg, log, FRAME_STEPS, with_nll=loss == "nll",
                           with_nees=loss == "nees", checkpoint=checkpoint)
        return slam_loss(run, log, loss, w)

    train = make_slam_logs(seed, train_runs, train_duration, n_lm, np.asarray(ref.P0), dtype)
    test = make_slam_logs(seed + 1, test_runs, train_duration, n_lm, np.asarray(ref.P0), dtype)

    opts = _scenario_options(mode, duration=float(eval_duration))
    one_run, _, ecfg, _, nf = scen.build(opts, mode, dtype)
    test_seed = seed + 1

    fn = jax.jit(jax.vmap(one_run, in_axes=(0, None)))  # compiled on the first evaluate, then reused

    def evaluate(physicals: dict) -> dict:
        keys = _keys(test_seed, test_runs)
        chunk = test_runs if eval_chunk is None else max(1, min(int(eval_chunk), test_runs))
        t_frames = (np.arange(nf) + 1) * DT * FRAME_STEPS
        res = {}
        for label, noise in physicals.items():
            noise = jax.tree.map(lambda a: jnp.asarray(a, dtype), noise)
            outs = [jax.tree.map(np.asarray, fn(keys[i:i + chunk], noise))
                    for i in range(0, test_runs, chunk)]
            out = jax.tree.map(lambda *a: np.concatenate(a, 0), *outs)
            cons, _ = scen.consistency(out["series"], t_frames, test_runs)
            res[label] = {"metrics": out["metrics"],
                          "consistency": {**{k: cons[k] for k in ("anees", "anees_bounds", "nis_mean",
                                                                  "nis_bounds", "anees_fraction_in_bounds")},
                                          **scen.CONSISTENCY_BLOCKS}}
        return res

    def to_params(noise):
        return {"noise": sys3d.noise_to_dict(noise)}

    def describe(theta):
        m = P.unpack(specs, theta)
        return {k: _diag_list(v) for k, v in m.items()}

    config = {"mode": mode, "train_duration_s": float(train_duration), "eval_duration_s": float(eval_duration),
              "train_seed": int(seed), "test_seed": int(test_seed), "train_runs": int(train_runs),
              "test_runs": int(test_runs), "capacity_train": cap, "cov": cov, "tune_r": bool(tune_r),
              "start": start, "structure": structure, "checkpoint": bool(checkpoint), "dtype": dtype.name,
              "mse_weights": None if mse_weights is None else [float(v) for v in mse_weights],
              "fixed": {"P0": "--q imu P0 (diag 1e-4 x6, (0.1 deg)^2 x3)",
                        **({"Qimu": "0"} if structure == "qc" else {"Qc": "0"}),
                        **({} if tune_r else {"R": "Table 4"})},
              "logs": "simulated once, DF-LQR on the truth; filter run open loop on the logs",
              "evaluation": f"ekfslam3d-{mode} scenario (closed loop, DF-LQR on the estimate), "
                            f"{eval_duration:g} s, seeds keys_for({test_seed}, {test_runs})"}
    cmd = (f"jaxslam run ekfslam3d-{mode} --runs {test_runs} --seed {test_seed}"
           f"{'' if eval_duration == 50.0 else f' --duration {eval_duration:g}'} --params TUNED.json")
    return Target(scenario=f"ekfslam3d-{mode}", target="noise", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={"q_imu": ref}, to_params=to_params, describe=describe, config=config,
                  eval_command=cmd, log_objective=loss == "mse", sequential=True)


for _m in ("unknown", "known"):
    register_target(f"ekfslam3d-{_m}", "noise",
                    lambda _mode=_m, **kw: ekfslam3d_noise(mode=_mode, **kw), ("nll", "mse", "nees"))


# ===========================================================================
# DF-LQR weights on the figure-8 (closed loop through the differentiable CARE)
# ===========================================================================

def _lqr_run(ctrl, x0, key, traj, nf, feedforward, w_u, checkpoint):
    """Closed-loop figure-8 from ``x0``; returns per-run metrics incl. the cost J."""
    from ..control import dflqr
    from ..sim.scenarios.tracking import FRAME_STEPS, make_setup, tracking_metrics
    from ..sim.simulate import simulate

    dtype = x0.dtype
    setup = make_setup(traj, dtype, ctrl=ctrl, x0=x0)
    K = dflqr.gain(ctrl, dtype)
    fl = simulate(setup, key, nf, FRAME_STEPS, K=K, feedforward=feedforward)
    T = fl.u.shape[0]
    t = fl.t[:T]
    refs = jax.vmap(lambda tt: dflqr.reference_at(tt, traj, ctrl, feedforward=feedforward, dtype=dtype))(t)

    def utilde(x, ref):
        _, info = dflqr.control_ref(x, ref, K, ctrl, feedforward=feedforward)
        return info.u_lqr - ref.u_d

    ut = jax.vmap(utilde)(fl.truth[:T], refs)
    e = fl.truth[:, :3] - fl.ref[:, :3]
    track = jnp.mean(jnp.sum(e * e, axis=1))
    effort = jnp.mean(jnp.sum(ut * ut, axis=1))
    m = tracking_metrics(fl.t, fl.truth, fl.ref)
    m = {k: m[k] for k in ("track_pos_rmse_m", "track_pos_rmse_settled_m", "track_yaw_rmse_deg", "max_tilt_deg")}
    m.update(closed_loop_cost=track + jnp.asarray(w_u, dtype) * effort, tracking_ms_m2=track,
             effort_ms=effort)
    return m


def figure8_lqr(loss: str = "cost", train_runs: int = 4, test_runs: int = 8, seed: int = 0,
                dtype=jnp.float64, train_duration: float = 25.0, eval_duration: float = 50.0,
                w_u: float = 0.1, start_sigma: float = 0.5, feedforward: bool = True,
                checkpoint: bool = True, **_ignored) -> Target:
    """Target: DF-LQR weights Q̃ (7), R̃ (4) on ``track-figure8`` (paper 000 eq. 10-13).

    Cost per run J = mean ‖ρ − ρ_d‖² + ``w_u`` · mean ‖ũ‖² (module docstring) through the
    differentiable CARE (:func:`jaxslam.control.lqr.care`) and the closed-loop scan.
    Log-diagonal parametrisation started from Table 2 (R̃ per errata).  Training and test
    runs start from random hover offsets (``start_sigma`` m per axis, yaw σ 0.1 rad); the
    evaluation also reports the nominal start of ``jaxslam run track-figure8``.
    """
    from ..control import dflqr
    from ..dynamics import euler_ned
    from ..sim.scenarios.tracking import FRAME_STEPS, controller_to_dict, paper000_figure8
    from ..sim.simulate import n_frames

    dtype = jnp.dtype(dtype)
    if loss != "cost":
        raise InputError(f"--loss: the lqr target uses the closed-loop cost ('cost'), got {loss!r}")
    base = dflqr.paper000_params()
    specs = {"Q": P.CovSpec("diag", 7), "R": P.CovSpec("diag", 4)}
    theta0 = P.pack(specs, {"Q": np.asarray(base.Q), "R": np.asarray(base.R)}, dtype=dtype)
    traj = paper000_figure8(3.0, 0.0)
    nf_train = n_frames(train_duration, 0.01, FRAME_STEPS)
    nf_eval = n_frames(eval_duration, 0.01, FRAME_STEPS)

    def physical(theta):
        m = P.unpack(specs, theta)
        return base._replace(Q=m["Q"], R=m["R"])

    def starts(s, runs):
        keys = _keys(s, runs)

        def one(k):
            k1, k2, k3 = jax.random.split(k, 3)
            pos = start_sigma * jax.random.normal(k1, (3,), dtype)
            yaw = 0.1 * jax.random.normal(k2, (), dtype)
            return {"x0": euler_ned.hover_state(pos, yaw, dtype=dtype), "key": k3}

        return jax.vmap(one)(keys)

    def loss_fn(theta, item):
        m = _lqr_run(physical(theta), item["x0"], item["key"], traj, nf_train, feedforward, w_u, checkpoint)
        return m["closed_loop_cost"]

    train = starts(seed, train_runs)
    test = starts(seed + 1, test_runs)
    nominal = {"x0": euler_ned.hover_state(dtype=dtype), "key": _keys(seed + 1, 1)[0]}

    @jax.jit
    def _eval(ctrl, items):
        return jax.vmap(lambda it: _lqr_run(ctrl, it["x0"], it["key"], traj, nf_eval, feedforward, w_u,
                                            False))(items)

    def evaluate(physicals):
        res = {}
        for label, ctrl in physicals.items():
            ctrl = ctrl._replace(Q=jnp.asarray(ctrl.Q, dtype), R=jnp.asarray(ctrl.R, dtype))
            out = jax.tree.map(np.asarray, _eval(ctrl, test))
            nom = jax.tree.map(np.asarray, _eval(ctrl, jax.tree.map(lambda a: a[None], nominal)))
            metrics = dict(out)
            metrics.update({f"nominal_{k}": v for k, v in nom.items()
                            if k in ("closed_loop_cost", "track_pos_rmse_m", "track_pos_rmse_settled_m")})
            res[label] = {"metrics": metrics, "consistency": None}
        return res

    def describe(theta):
        return {k: _diag_list(v) for k, v in P.unpack(specs, theta).items()}

    config = {"train_duration_s": float(train_duration), "eval_duration_s": float(eval_duration),
              "train_seed": int(seed), "test_seed": int(seed + 1), "train_runs": int(train_runs),
              "test_runs": int(test_runs), "w_u": float(w_u), "start_sigma_m": float(start_sigma),
              "start_yaw_sigma_rad": 0.1, "feedforward": bool(feedforward), "checkpoint": bool(checkpoint),
              "dtype": dtype.name,
              "cost": "mean_t |rho - rho_d|^2 + w_u mean_t |u_tilde|^2 (u_tilde: LQR correction)",
              "evaluation": f"closed loop {eval_duration:g} s from held-out random starts "
                            f"(keys_for({seed + 1}, {test_runs})) and from the nominal start"}
    return Target(scenario="track-figure8", target="lqr", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={}, to_params=lambda c: {"controller": {k: v for k, v in controller_to_dict(c).items()
                                                                     if k in ("Q", "R")}},
                  describe=describe, config=config,
                  eval_command="jaxslam run track-figure8 --params TUNED.json  (nominal start)",
                  log_objective=True)


register_target("track-figure8", "lqr", figure8_lqr, ("cost",))


# ===========================================================================
# Linear-Gaussian oracle
# ===========================================================================

def _lg_model(dt):
    A = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    return A, np.eye(4)


# Chosen so every entry is identified from the innovations with good precision: position and
# velocity are both measured (a position fix and a Doppler velocity), and each process-noise
# entry is comparable to the measurement noise of the same channel, so neither swamps the other
# (with position-only measurements the position process noise is nearly confounded with R and
# 10⁴ samples pin it to no better than ±100 %).
LG_DT = 1.0
LG_Q_TRUE = (0.06, 0.08, 0.1, 0.2)  # diag Q of the oracle [m², m², (m/s)², (m/s)²] per step
LG_R_TRUE = ((0.05, 0.02, 0.0, 0.0),  # full R: correlated position noise [m²], velocity [(m/s)²]
             (0.02, 0.04, 0.0, 0.0),
             (0.0, 0.0, 0.1, 0.0),
             (0.0, 0.0, 0.0, 0.15))


def lg_simulate(key, T: int, Q, R, dt: float = LG_DT, dtype=jnp.float64):
    """Simulate the oracle x' = A x + w, z = x + v (w ~ N(0, Q), v ~ N(0, R)); T steps.

    x = [p_x, p_y, v_x, v_y]: 2D constant velocity with step ``dt``; the position and the
    velocity are measured.  Returns ``{"z": (T, 4), "x": (T, 4)}`` (state after each step;
    x_0 = 0).
    """
    A, H = (jnp.asarray(a, dtype) for a in _lg_model(dt))
    Lq = jnp.linalg.cholesky(jnp.asarray(Q, dtype))
    Lr = jnp.linalg.cholesky(jnp.asarray(R, dtype))
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (T, 4), dtype) @ Lq.T
    v = jax.random.normal(kv, (T, 4), dtype) @ Lr.T

    def step(x, wv):
        x = A @ x + wv[0]
        return x, (H @ x + wv[1], x)

    _, (z, x) = jax.lax.scan(step, jnp.zeros(4, dtype), (w, v))
    return {"z": z, "x": x}


def lg_run(Q, R, z, dt: float = LG_DT, P0=None):
    """Kalman filter of the oracle over z (T, 4) with :mod:`jaxslam.filters.ekf`.

    Returns (means (T, 4), nis (T,), logdet (T,), dof (T,), nees-ready covs (T, 4, 4)).
    """
    dtype = z.dtype
    A, H = (jnp.asarray(a, dtype) for a in _lg_model(dt))
    P0 = jnp.eye(4, dtype=dtype) if P0 is None else P0

    def step(g, zk):
        g = ekf_mod.predict(g, lambda x, u: A @ x, None, Q)
        g, info = ekf_mod.update(g, zk, lambda x: H @ x, R)
        nis, logdet, dof = L.nll_terms(info.innovation, info.S)
        return g, (g.mean, nis, logdet, dof, g.cov)

    _, out = jax.lax.scan(step, ekf_mod.Gaussian(jnp.zeros(4, dtype), P0), z)
    return out


def linear_gaussian(loss: str = "nll", train_runs: int = 4, test_runs: int = 4, seed: int = 0,
                    dtype=jnp.float64, T: int = 2000, q0_scale: float = 4.0, r0_scale: float = 0.25,
                    **_ignored) -> Target:
    """Oracle target: diag Q (log-diagonal) and full R (log-Cholesky) of a 2D constant-velocity
    Kalman filter measuring position and velocity, with known truth (:data:`LG_Q_TRUE`, :data:`LG_R_TRUE`), started at
    ``q0_scale``·Q and ``r0_scale``·diag(R) (a diagonal first guess).  Losses nll / mse / nees on the filtered state."""
    dtype = jnp.dtype(dtype)
    if loss not in ("nll", "mse", "nees"):
        raise InputError(f"--loss: expected nll, mse or nees, got {loss!r}")
    Qt, Rt = np.diag(LG_Q_TRUE), np.asarray(LG_R_TRUE)
    specs = {"Q": P.CovSpec("diag", 4), "R": P.CovSpec("chol", 4)}
    # A user's first guess has no correlation: the start is diagonal (wrong scale, wrong shape).
    theta0 = P.pack(specs, {"Q": q0_scale * Qt, "R": r0_scale * np.diag(np.diag(Rt))}, dtype=dtype)

    def physical(theta):
        return P.unpack(specs, theta)

    def data(s, runs):
        return jax.jit(jax.vmap(lambda k: lg_simulate(k, T, Qt, Rt, dtype=dtype)))(_keys(s, runs))

    def loss_fn(theta, item):
        m = physical(theta)
        means, nis, logdet, dof, covs = lg_run(m["Q"], m["R"], item["z"])
        if loss == "nll":
            return L.innovation_nll(nis, logdet, dof)
        err = means - item["x"]
        if loss == "mse":
            return L.mse(err)
        nees = jax.vmap(lambda e, C: e @ jnp.linalg.solve(C, e))(err, covs)
        return L.nees_loss(nees, 4)

    train, test = data(seed, train_runs), data(seed + 1, test_runs)

    def evaluate(physicals):
        res = {}
        for label, m in physicals.items():
            def per(item, m=m):
                means, nis, logdet, dof, covs = lg_run(jnp.asarray(m["Q"], dtype), jnp.asarray(m["R"], dtype),
                                                       item["z"])
                err = means - item["x"]
                return {"nll": L.innovation_nll(nis, logdet, dof),
                        "pos_rmse_m": jnp.sqrt(jnp.mean(jnp.sum(err[:, :2] ** 2, 1))),
                        "vel_rmse_mps": jnp.sqrt(jnp.mean(jnp.sum(err[:, 2:] ** 2, 1)))}
            res[label] = {"metrics": jax.tree.map(np.asarray, jax.jit(jax.vmap(per))(test)),
                          "consistency": None}
        return res

    def describe(theta):
        m = physical(theta)
        return {"Q": _diag_list(m["Q"]), "R": [float(v) for v in np.asarray(m["R"]).ravel()]}

    config = {"T": int(T), "train_runs": int(train_runs), "test_runs": int(test_runs), "seed": int(seed),
              "Q_true": list(LG_Q_TRUE), "R_true": [list(r) for r in LG_R_TRUE],
              "q0_scale": float(q0_scale), "r0_scale": float(r0_scale), "dtype": dtype.name}
    return Target(scenario="linear-gaussian", target="noise", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={"true": {"Q": Qt, "R": Rt}},
                  to_params=lambda m: {"noise": {k: np.asarray(v).tolist() for k, v in m.items()}},
                  describe=describe, config=config, log_objective=loss == "mse")


register_target("linear-gaussian", "noise", linear_gaussian, ("nll", "mse", "nees"))


# ===========================================================================
# Paper 003 UWB range-only EKF-SLAM (registered when jaxslam.systems.uwb_slam_2d exists)
# ===========================================================================

def uwb_noise(loss: str = "mse", train_runs: int = 4, test_runs: int = 8, seed: int = 0,
              dtype=jnp.float64, scenario: str = "circle", mode: str = "slam", cov: str = "diag",
              **_ignored) -> Target:
    """Target: the process noise Q (10, 10) of paper 003's UWB EKF-SLAM (eq. 27, "fine tuned").

    Started from the paper's Q (log-diagonal; ``cov="chol"`` for a full matrix), R, P0 and the
    start-up as the ``paper`` filter of the ``uwb-{scenario}`` scenario.  The flights are
    open loop (a prescribed path), so the training items are simulated logs and the loss runs
    :func:`jaxslam.systems.uwb_slam_2d.run` on them.  Losses: ``mse`` (mean squared position
    error in the scenario's comparison frame, m²) and ``nees`` (position NEES).  The engine
    reports no log det S for this system's two-stage update, so the NLL is not offered here.
    Held-out evaluation: the scenario's own runs on seeds from ``seed + 1``.
    """
    from ..sim.scenarios import registry
    from ..sim.scenarios import uwb as scen
    from ..systems import uwb_slam_2d as U

    dtype = jnp.dtype(dtype)
    if loss not in ("mse", "nees"):
        raise InputError(f"--loss: uwb targets support mse, nees; got {loss!r}")
    opts = {o.name: o.default for o in registry.get(f"uwb-{scenario}").options}
    opts["mode"] = mode
    one_run, _, cfg, fp0, setup = scen.build(scenario, opts, dtype)
    specs = {"Q": P.CovSpec(cov, U.NR)}
    theta0 = P.pack(specs, {"Q": np.asarray(fp0.Q)}, dtype=dtype)

    def physical(theta):
        return fp0._replace(Q=P.cov_from_theta(specs["Q"], theta["Q"]))

    sim_batch = jax.jit(jax.vmap(lambda k: scen.simulate(k, setup, dtype)))
    train = sim_batch(_keys(seed, train_runs))
    test = sim_batch(_keys(seed + 1, test_runs))

    def loss_fn(theta, sim):
        res = U.run(sim.log, cfg, physical(theta))
        ev = scen.evaluate(sim, res, cfg)
        if loss == "mse":
            return ev["metrics"]["pos_rmse_m"] ** 2
        nees = ev["series"]["nees_pos"]
        ok = jnp.isfinite(nees)
        return L.nees_loss(jnp.where(ok, nees, 0.0), 2, ok)

    fn = jax.jit(jax.vmap(one_run, in_axes=(0, None)))

    def evaluate(physicals):
        res = {}
        keys = _keys(seed + 1, test_runs)
        for label, fp in physicals.items():
            fp = jax.tree.map(lambda a: jnp.asarray(a, dtype), fp)
            out = jax.tree.map(np.asarray, fn(keys, fp))
            cons, _ = scen.consistency(out["series"], setup.ts, test_runs)
            res[label] = {"metrics": out["metrics"],
                          "consistency": scen.consistency_summary(cons)}
        return res

    def to_params(fp):
        return {"filter": {"Q": np.asarray(fp.Q, float).tolist()}}

    def describe(theta):
        return {"Q": _diag_list(P.unpack(specs, theta)["Q"])}

    config = {"scenario": f"uwb-{scenario}", "mode": mode, "train_runs": int(train_runs),
              "test_runs": int(test_runs), "train_seed": int(seed), "test_seed": int(seed + 1), "cov": cov,
              "dtype": dtype.name, "start": "paper 003 eq. 27 Q (filter 'paper'), R and P0 fixed",
              "evaluation": f"uwb-{scenario} scenario, seeds keys_for({seed + 1}, {test_runs})"}
    return Target(scenario=f"uwb-{scenario}", target="noise", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={}, to_params=to_params, describe=describe, config=config,
                  eval_command=f"jaxslam run uwb-{scenario} --mode {mode} --runs {test_runs} --seed {seed + 1} "
                               f"--params TUNED.json", log_objective=loss == "mse")
