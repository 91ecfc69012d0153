"""Faults in the line-feature EKF-SLAM of paper 004 and the two-stage FastSLAM of paper 001.

Both run on the same engines as the systems of ``test_faults_systems.py``
(``filters/ekf_slam.py``, ``filters/fastslam.py``), whose masking and flags are checked there;
these checks add each system's own pre-processing (laser scan → RANSAC lines; IMU stage with
the bias/drift KF).  One compiled program per system serves every fault (the set compiles in
about 10 s; it was in the slow set while these programs took 20-60 s to compile).  Expected
outcomes, from the design: for every fault the estimate and its covariance stay finite, no
``non_finite`` / ``not_psd`` is raised, and the position RMSE stays ≤ 2·clean + 0.05 m; a
non-finite sample or row is also flagged ``masked_input``.

* line SLAM (scans 20-29, odometry steps 20-24): NaN and Inf ranges marked valid (masked before
  RANSAC: no return is normal for a laser), a dropout (valid False), an outlier burst (every
  return 0.5 m long), a frozen scan, returns of 10 km marked valid, NaN flow/gyro and Inf flow
  (the odometry row is skipped by the engine, ``masked_input``): 8 kinds.
* FastSLAM 001 (LiDAR frames 5-7, IMU samples 100-104 or 100-109): NaN and Inf LiDAR rows (the
  core and the position regeneration skip them), a LiDAR dropout, an outlier burst (ranges
  0.5 m long), a frozen frame, NaN and Inf IMU samples (skipped: prediction only), a frozen IMU:
  8 kinds.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors

def _rmse(est, truth):
    e = np.asarray(est)[:, :2] - np.asarray(truth)[:, :2]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


@pytest.fixture(scope="module")
def line_slam():
    from jaxslam.sim.scenarios import lineslam as sc
    from jaxslam.systems import line_slam_004 as LS

    setup = sc.make_setup(duration=6.0)
    cfg = LS.Config()
    fp = LS.default_params()
    log = jax.jit(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float64))(jax.random.PRNGKey(3))
    run = LS.run  # jitted itself (config static)
    clean = run(log, cfg, fp, key=jax.random.PRNGKey(5))
    return setup, cfg, fp, log, run, clean


def _line_fault(log, fault):
    """The corrupted log (scans / steps 20-29)."""
    w = slice(20, 30)
    if fault == "nan_ranges":
        return log._replace(ranges=log.ranges.at[w].set(jnp.nan), valid=log.valid.at[w].set(True))
    if fault == "inf_ranges":
        return log._replace(ranges=log.ranges.at[w].set(jnp.inf), valid=log.valid.at[w].set(True))
    if fault == "dropout":
        return log._replace(valid=log.valid.at[w].set(False))
    if fault == "outlier_burst":  # every return 0.5 m long: walls seen too far
        return log._replace(ranges=log.ranges.at[w].add(0.5))
    if fault == "frozen_scan":
        return log._replace(ranges=log.ranges.at[w].set(log.ranges[20]), valid=log.valid.at[w].set(log.valid[20]))
    if fault == "out_of_range":  # returns far beyond the sensor's range, marked valid
        return log._replace(ranges=log.ranges.at[w].set(1e4), valid=log.valid.at[w].set(True))
    if fault == "nan_odometry":
        return log._replace(flow=log.flow.at[20:25].set(jnp.nan), gyro=log.gyro.at[20:25].set(jnp.nan))
    if fault == "inf_odometry":
        return log._replace(flow=log.flow.at[20:25].set(jnp.inf))
    raise AssertionError(fault)


LINE_FAULTS = ("nan_ranges", "inf_ranges", "dropout", "outlier_burst", "frozen_scan", "out_of_range",
               "nan_odometry", "inf_odometry")


@pytest.mark.parametrize("fault", LINE_FAULTS)
def test_line_slam_fault(line_slam, fault):
    """Every fault: estimate and covariance finite, no ``non_finite`` / ``not_psd``, position RMSE
    ≤ 2·clean + 0.05 m; non-finite odometry rows are also flagged ``masked_input``."""
    setup, cfg, fp, log, run, clean = line_slam
    base = _rmse(clean.steps.mean, setup.truth)
    assert not {"masked_input", "non_finite", "not_psd"} & set(errors.decode(int(clean.final.status)))
    res = run(_line_fault(log, fault), cfg, fp, key=jax.random.PRNGKey(5))
    flags = errors.decode(int(res.final.status))
    assert np.all(np.isfinite(np.asarray(res.steps.mean))) and np.all(np.isfinite(np.asarray(res.steps.cov)))
    assert "non_finite" not in flags and "not_psd" not in flags, flags
    if fault.endswith("odometry"):
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
    def go(key, imu, z, mask):
        log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor, imu=imu, z=z, ids=ids, mask=mask)
        return fs1.run(log, cfg, prm, key=key)  # cfg.n_particles = n

    clean = go(jax.random.PRNGKey(3), fl.imu, fl.z, fl.mask)
    return fl, go, clean


def _status(res):
    return int(res.final.particles.status)


def _fs_fault(fl, fault):
    """(imu, z, mask) corrupted: LiDAR frames 5-7 or IMU samples 100-104."""
    imu, z, mask = fl.imu, fl.z, fl.mask
    if fault == "nan_lidar":
        z = z.at[5:8].set(jnp.nan)
    elif fault == "inf_lidar":
        z = z.at[5:8].set(jnp.inf)
    elif fault == "lidar_dropout":
        mask = mask.at[5:8].set(False)
    elif fault == "lidar_outlier_burst":  # ranges 0.5 m long on every pole
        z = z.at[5:8, :, 2].add(0.5)
    elif fault == "lidar_frozen":
        z = z.at[5:8].set(z[5])
    elif fault == "nan_imu":
        imu = imu.at[100:105].set(jnp.nan)
    elif fault == "inf_imu":
        imu = imu.at[100:105].set(jnp.inf)
    elif fault == "imu_frozen":
        imu = imu.at[100:110].set(imu[100])
    else:
        raise AssertionError(fault)
    return imu, z, mask


FS_FAULTS = ("nan_lidar", "inf_lidar", "lidar_dropout", "lidar_outlier_burst", "lidar_frozen", "nan_imu",
             "inf_imu", "imu_frozen")


@pytest.mark.parametrize("fault", FS_FAULTS)
def test_fastslam_001_fault(fastslam_001, fault):
    """Every fault: estimate finite, no ``non_finite``, position RMSE ≤ 2·clean + 0.05 m;
    non-finite samples or rows are also flagged ``masked_input``."""
    fl, go, clean = fastslam_001
    truth = np.asarray(fl.truth)

    def rmse(res):
        est = np.asarray(res.steps.pose_mean)
        return _rmse(est, truth[1:] if len(truth) > len(est) else truth)

    assert "masked_input" not in errors.decode(_status(clean))
    res = go(jax.random.PRNGKey(3), *_fs_fault(fl, fault))
    flags = errors.decode(_status(res))
    assert np.all(np.isfinite(np.asarray(res.steps.pose_mean))), flags
    assert "non_finite" not in flags, flags
    if fault.startswith(("nan", "inf")):
        assert "masked_input" in flags
    assert rmse(res) <= 2 * rmse(clean) + 0.05
