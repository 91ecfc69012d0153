"""Faults in the two systems whose whole-flight programs take 20-60 s to compile (slow set).

The line-feature EKF-SLAM of paper 004 and the two-stage FastSLAM of paper 001 run on the same
engines as the systems of ``test_faults_systems.py`` (``filters/ekf_slam.py``,
``filters/fastslam.py``), whose masking and flags the default suite covers; these checks add
each system's own pre-processing (laser scan → RANSAC lines; IMU stage with the bias/drift KF).
Expected outcomes, from the design:

===========================  ==============================================================
line SLAM, NaN ranges        invalid returns are masked before RANSAC (no return is normal
(scans 20-29, valid True)    for a laser): estimate finite, position RMSE ≤ 2·clean + 0.05 m
line SLAM, NaN flow/gyro     the odometry row is non-finite: the engine skips it and flags
(steps 20-24)                ``masked_input``; estimate finite, RMSE ≤ 2·clean + 0.05 m
FastSLAM 001, NaN LiDAR      the core skips non-finite rows and flags ``masked_input``;
(frames 5-7)                 estimate finite, RMSE ≤ 2·clean + 0.05 m
FastSLAM 001, NaN IMU        the sample is skipped (dynamics model: prediction without the
(steps 100-104)              measurement) and flagged ``masked_input``; estimate finite,
                             RMSE ≤ 2·clean + 0.05 m
===========================  ==============================================================
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors

pytestmark = pytest.mark.slow


def _rmse(est, truth):
    e = np.asarray(est)[:, :2] - np.asarray(truth)[:, :2]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


@pytest.fixture(scope="module")
def line_slam():
    from jaxslam.sim.scenarios import lineslam as sc
    from jaxslam.systems import line_slam_004 as LS

    setup = sc.make_setup(duration=6.0)
    cfg = LS.LineSlamConfig()
    fp = LS.default_params()
    log = jax.jit(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float64))(jax.random.PRNGKey(3))
    run = jax.jit(LS.run, static_argnums=2)
    clean = run(jax.random.PRNGKey(5), log, cfg, fp)
    return setup, cfg, fp, log, run, clean


@pytest.mark.parametrize("fault", ["nan_ranges", "nan_odometry"])
def test_line_slam_fault(line_slam, fault):
    setup, cfg, fp, log, run, clean = line_slam
    base = _rmse(clean.steps.mean, setup.truth)
    assert not {"masked_input", "non_finite", "not_psd"} & set(errors.decode(int(clean.final.status)))
    if fault == "nan_ranges":
        bad = log._replace(ranges=log.ranges.at[20:30].set(jnp.nan), valid=log.valid.at[20:30].set(True))
    else:
        bad = log._replace(flow=log.flow.at[20:25].set(jnp.nan), gyro=log.gyro.at[20:25].set(jnp.nan))
    res = run(jax.random.PRNGKey(5), bad, cfg, fp)
    flags = errors.decode(int(res.final.status))
    assert np.all(np.isfinite(np.asarray(res.steps.mean))) and np.all(np.isfinite(np.asarray(res.steps.cov)))
    assert "non_finite" not in flags and "not_psd" not in flags
    if fault == "nan_odometry":
        assert "masked_input" in flags
    assert _rmse(res.steps.mean, setup.truth) <= 2 * base + 0.05


@pytest.fixture(scope="module")
def fastslam_001():
    from jaxslam.sim.scenarios import fastslam as sc
    from jaxslam.systems import fastslam_001 as fs1

    n, dur = 40, 2.0
    opts = {o.name: o.default for o in sc.OPTIONS}
    opts.update(particles=n, duration=dur, bias=0.005)
    setup = sc.truth_setup(0.005, jnp.float64)
    nf = int(round(dur / (sc.DT * sc.LIDAR_EVERY)))
    fl = jax.jit(lambda k: sc.fly(setup, k, nf))(jax.random.PRNGKey(11))
    cfg, prm = sc.make_filter(opts, jnp.float64)
    ids = jnp.arange(4, dtype=jnp.int32)

    @jax.jit
    def go(key, imu, z):
        return fs1.run(key, fl.truth[0], fl.rotor, imu, z, ids, fl.mask, n, cfg, prm)

    clean = go(jax.random.PRNGKey(3), fl.imu, fl.z)
    return fl, go, clean


def _status(res):
    return int(res.final.particles.status)


@pytest.mark.parametrize("fault", ["nan_lidar", "nan_imu"])
def test_fastslam_001_fault(fastslam_001, fault):
    fl, go, clean = fastslam_001
    truth = np.asarray(fl.truth)
    base = _rmse(clean.steps.pose_mean, truth[1:] if len(truth) > len(clean.steps.pose_mean) else truth)
    assert "masked_input" not in errors.decode(_status(clean))
    imu, z = fl.imu, fl.z
    if fault == "nan_lidar":
        z = z.at[5:8].set(jnp.nan)
    else:
        imu = imu.at[100:105].set(jnp.nan)
    res = go(jax.random.PRNGKey(3), imu, z)
    flags = errors.decode(_status(res))
    est = np.asarray(res.steps.pose_mean)
    assert np.all(np.isfinite(est)), flags
    assert "masked_input" in flags and "non_finite" not in flags, flags
    assert _rmse(est, truth[1:] if len(truth) > len(est) else truth) <= 2 * base + 0.05
