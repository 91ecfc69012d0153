"""The built-in scenarios' names, descriptions and command-line options, declared without JAX.

Each scenario module (:mod:`~jaxslam.sim.scenarios.tracking`, ``ekfslam3d``, ``uwb``,
``fastslam``, ``attitude``, ``lineslam``) registers its :class:`~.registry.Scenario` with the
name, description and options declared here, and nowhere else.  What only needs these — the
scenario names (``jaxslam run``, ``jaxslam run no-such-name``), ``jaxslam list``, and a
mistyped or out-of-range scenario option (``jaxslam run track-figure8 --bogus``) — is answered
from this module before JAX is imported (importing JAX alone takes 1.2-2.3 s on the 2-core
development machines; such an exit now takes ~0.15 s), and so is a ``--params`` file's top
level (its sections, :func:`jaxslam.paramfile.check_sections`).  A scenario's own checks of its
values' meaning (``--duration -1``) and the values in a ``--params`` file still need the
scenario module.
``tests/sim/test_scenarios_builtin.py`` checks that every module registers exactly what is
declared here.
"""

from __future__ import annotations

import dataclasses

from .option import Option

__all__ = ["Declared", "DECLARED"]


@dataclasses.dataclass(frozen=True)
class Declared:
    """A built-in scenario as the command line sees it before its module is imported.

    Attributes:
      name: what ``jaxslam run NAME`` takes.
      description: the one line of ``jaxslam list``.
      options: its :class:`~.option.Option` tuple (the registered scenario's own).
      module: the module that registers it.
      params_sections: the sections of its ``--params`` file (the keys of its
        ``Scenario.params`` schema), or ``None`` when it takes no file: what
        :func:`jaxslam.paramfile.check_sections` checks a file's top level against.
    """

    name: str
    description: str
    options: tuple
    module: str
    params_sections: tuple | None


# The flights' shortest duration: one sensor frame, 10 steps of 0.01 s (tracking.DT * FRAME_STEPS,
# fastslam.DT * LIDAR_EVERY; the test checks they agree).
_ONE_FRAME_S = 0.1

# jaxslam.sim.monte_carlo caps a vmapped chunk at 256 runs, and at DETAIL_CHUNK = 16 when the
# flights also return the figures' data (--plots); the test checks both numbers against it.
_CHUNK_CAP, _DETAIL_CHUNK_CAP = 256, 16
_CHUNK_HELP = (f"Monte Carlo runs per compiled call (default: all, max {_CHUNK_CAP}; "
               f"max {_DETAIL_CHUNK_CAP} with --plots)")
_CHUNK_HELP_LOOP = (f"Monte Carlo runs per compiled call on a GPU/TPU (default: all, max {_CHUNK_CAP}; "
                    f"max {_DETAIL_CHUNK_CAP} with --plots); on the CPU the runs go one compiled run "
                    "at a time and it has no effect")

_TRACKING = (
    Option("duration", float, 50.0, "flight duration [s]", lower=_ONE_FRAME_S),
    Option("no_feedforward", bool, False,
           "paper's eq. 19 attitude references (p_d = q_d = 0, no torque feedforward) instead of "
           "jaxslam's full flatness feedforward"),
    Option("chunk", int, None, _CHUNK_HELP, lower=1),
)

_EKFSLAM3D = (
    Option("duration", float, 50.0, "flight duration [s]", lower=_ONE_FRAME_S),
    Option("q", str, "imu", "filter noise: 'imu' (Q from Table 5 densities) or 'paper' (Tables 6-7 P0/Q)",
           ("imu", "paper")),
    Option("association", str, "known", "data association: 'known' ids (paper) or 'nn' (ids hidden)",
           ("known", "nn")),
    Option("capacity", int, 64, "landmark slots in the padded map", lower=1),
    Option("landmarks", int, 40, "number of true landmarks (Table 3: 40)", lower=1),
    Option("max_obs", int, 16, "LiDAR measurements processed per frame (extras counted as dropped)", lower=1),
    Option("control_on", str, "estimate", "what the DF-LQR acts on: 'estimate' (paper) or 'truth'",
           ("estimate", "truth")),
    Option("accel", str, "3axis", "IMU input: '3axis' specific force or 'az' (paper eq. 25)",
           ("3axis", "az")),
    Option("altitude", float, 3.0, "figure-8 altitude above the start point [m]; landmarks centred on it"),
    Option("no_feedforward", bool, False, "paper's eq. 19 attitude references instead of the flatness feedforward"),
    Option("chunk", int, None, _CHUNK_HELP_LOOP, lower=1),
)

_UWB = (
    Option("mode", str, "slam", "'slam' (anchors unknown, trilateration start-up) or 'localization' "
           "(known anchors)", ("slam", "localization")),
    Option("model", str, "squared", "UWB observation: 'squared' range (eq. 17, paper) or plain 'range' "
           "(eq. 16)", ("squared", "range")),
    Option("noise", str, "uniform", "simulated noise: 'uniform' (paper: ±0.2 m, ±0.002 rad/s) or "
           "'gaussian' of the same variance", ("uniform", "gaussian")),
    Option("filter", str, "paper", "filter noise: 'paper' (Q eq. 27, R 0.2/0.01) or 'matched' (R from "
           "the simulated variance, scaled with distance; white-noise-acceleration Q)", ("paper", "matched")),
    Option("duration", float, None, "flight after the start-up [s] (default: circle 126, square 160, "
           "rough 150)"),
    Option("dt", float, 1.0, "filter and sensor step [s] (paper: one iteration = 1)"),
    Option("anchors", int, 3, "number of anchors, 3 (paper) to 6; beyond 3 mapped by delayed init"),
    Option("startup_speed", float, 0.15, "speed of the forced straight-line start-up [m/s]"),
    Option("max_range", float, 0.0, "UWB range limit [m] (0: unlimited)", lower=0.0),
    Option("chunk", int, None, _CHUNK_HELP, lower=1),
    Option("smooth", bool, False, "also RTS-smooth each run's robot trajectory (backward pass, the map "
           "held static) and report smoothed_* metrics beside the filter's"),
)

_FASTSLAM = (
    Option("model", str, "dynamics", "proposal: 'dynamics' (paper 001, rotor inputs + bias KF) "
           "or 'kinematics' (IMU-driven FastSLAM baseline)", ("dynamics", "kinematics")),
    Option("bias", float, 0.0005, "IMU bias on every axis [m/s², rad/s] (paper: 0.0005 or 0.005)"),
    Option("particles", int, 500, "number of particles N (paper: 500)", lower=1),
    Option("inertia_mismatch", bool, False,
           "filter uses Ixx = Iyy = 0.0288, Izz = 0.0545 kg m² (+150 %), truth unchanged"),
    Option("weights", str, "exact", "particle weights: 'exact' (innovation covariance) or "
           "'paper' (eq. 26-28 mean approximations)", ("exact", "paper")),
    Option("resampling", str, "systematic", "resampling scheme",
           ("systematic", "stratified", "multinomial", "residual", "soft")),
    Option("resample_threshold", float, 0.5,
           "resample when N_eff < threshold·N; 1 = at every weight update (paper's Step 6)"),
    Option("soft_alpha", float, 0.5, "mixture weight of soft resampling (with --resampling soft)"),
    Option("duration", float, 50.0, "flight duration [s]", lower=_ONE_FRAME_S),
    Option("lidar", str, "world", "LiDAR model: 'world' (eq. 13-15) or 'body' (paper 000)",
           ("world", "body")),
    Option("stage2", str, "paper", "stage 2 (Step 8): 'paper' (position + rates), 'rates', 'none'",
           ("paper", "rates", "none")),
    Option("accel", str, "specific_force", "accelerometer model of truth and filter: "
           "'specific_force' (real IMU) or 'kinematic' (paper eq. 7)",
           ("specific_force", "kinematic")),
    Option("chunk", int, None, _CHUNK_HELP_LOOP, lower=1),
)

# attitude-smc's defaults are jaxslam.control.smc's DURATION_S, DT_S and TAU_MAX_APPB (app. B),
# written out here so that the declaration needs no JAX (the test checks they agree)
_ATTITUDE = (
    Option("perturbation", str, "constant", "app. B perturbation ξ: constant, sinusoidal, random "
           "(bounded) or none", ("constant", "sinusoidal", "random", "none")),
    Option("gains", str, "thesis", "K1, K2: 'thesis' (ch. 3.4), 'prototype' (eq. 6.1) or 'lqr' "
           "(app. B weights)", ("thesis", "prototype", "lqr")),
    Option("duration", float, 25.0, "simulated time [s] (app. B: 25)"),
    Option("dt", float, 1e-3, "integration and control step [s] (app. B: 0.001)"),
    Option("torque", str, "direct", "torque model: 'direct' τ = u (app. B, the code behind Figs "
           "3.2-3.7) or 'exact' τ = J u + ω×Jω (eq. 3.15)", ("direct", "exact")),
    Option("tau_max", float, 0.6 * 0.3, "torque limit per axis [N m] (app. B: 0.18; <= 0: none)"),
    Option("perturbation_scale", float, 1.0, "L1, L2 as a multiple of Theorem 3.1's admissible maxima"),
    Option("switching", str, "tanh", "switching term: 'tanh' (thesis) or 'sign'", ("tanh", "sign")),
    Option("eps", float, 1.0, "tanh smoothing width (1 = the thesis' TANH) [rad, rad/s]"),
)

_LINESLAM = (
    Option("duration", float, 60.0, "flight duration [s] (10 Hz scans; 60 s = two laps)"),
    Option("capacity", int, 16, "line slots of the map", lower=1),
    Option("outlier_prob", float, 0.05, "fraction of laser returns replaced by clutter"),
    Option("tilt_deg", float, 2.0, "roll/pitch amplitude [deg] (known to the filter)"),
    Option("chunk", int, None, _CHUNK_HELP, lower=1),
)

_PKG = "jaxslam.sim.scenarios."

DECLARED: dict[str, Declared] = {d.name: d for d in (
    Declared("track-figure8",
             "Paper 000: DF-LQR tracks the 50 s figure-8 from the origin (true state, no estimator)",
             _TRACKING + (
                 Option("altitude", float, 3.0, "figure-8 altitude above the start point [m]"),
                 Option("ramp", float, 0.0,
                        "take-off blend of the reference from the origin [s]; 0 = the paper's start "
                        "(reference starts on the figure-8, the vehicle at the origin)", lower=0.0),
             ), _PKG + "tracking", ("controller",)),
    Declared("track-helix",
             "Paper 001: DF-LQR tracks the climbing helix from the origin (true state, no estimator)",
             _TRACKING, _PKG + "tracking", ("controller",)),
    Declared("ekfslam3d-unknown",
             "Paper 000: 3D EKF-SLAM (landmarks unknown) with DF-LQR on the estimate, 50 s figure-8",
             _EKFSLAM3D, _PKG + "ekfslam3d", ("noise", "controller")),
    Declared("ekfslam3d-known",
             "Paper 000: EKF localisation against the known 40-landmark map, DF-LQR on the estimate",
             _EKFSLAM3D, _PKG + "ekfslam3d", ("noise", "controller")),
    Declared("uwb-circle",
             "Paper 003 I: range-only UWB EKF-SLAM, circle r 1.5 m, yaw rate 0.2 sin(0.1t), LS start-up",
             _UWB, _PKG + "uwb", ("filter",)),
    Declared("uwb-square",
             "Paper 003 II: range-only UWB EKF-SLAM, 3 m square with sharp corners, staged angular motion",
             _UWB, _PKG + "uwb", ("filter",)),
    Declared("uwb-rough",
             "Paper 003 III: range-only UWB EKF-SLAM, rough path (sudden turns, wiggle, switching rates)",
             _UWB, _PKG + "uwb", ("filter",)),
    Declared("fastslam-helix",
             "Paper 001: dynamics-based two-stage FastSLAM with IMU bias/drift KF on the helix",
             _FASTSLAM, _PKG + "fastslam", None),
    Declared("attitude-smc",
             "Paper 004 ch. 3.4: quaternion sliding-mode attitude control under bounded perturbations",
             _ATTITUDE, _PKG + "attitude", None),
    Declared("lineslam-room",
             "Paper 004: line-feature EKF-SLAM (RANSAC walls, optical flow, gyro) in a 10-wall L-shaped room",
             _LINESLAM, _PKG + "lineslam", ("filter",)),
)}
