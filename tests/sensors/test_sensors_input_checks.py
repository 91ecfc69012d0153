"""Bad input to the sensor models and the line features: an early InputError naming the argument
(shapes are static, so they are checked under jit too), never a plausible wrong reading.

Each case was found by calling the function as a careless user would; the expected values are
written by hand."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.features import lines as L
from jaxslam.linalg import safe_norm
from jaxslam.sensors import imu, lidar3d as l3, range_bearing2d as rb2, uwb


def test_safe_norm_keeps_nan_and_inf_and_its_zero_gradient():
    """``NaN > 0`` is false: the norm of a NaN vector used to be 0 (a plausible reading)."""
    assert np.isnan(float(safe_norm(jnp.array([np.nan, 0.0, 0.0]))))
    assert float(safe_norm(jnp.array([np.inf, 1.0]))) == np.inf
    assert float(safe_norm(jnp.array([3.0, 4.0]))) == 5.0
    np.testing.assert_array_equal(np.asarray(jax.grad(safe_norm)(jnp.zeros(3))), np.zeros(3))


def test_a_nan_point_is_no_visible_lidar_return():
    y, vis = l3.measure_all(jnp.array([np.nan, 0.0, 0.0]), jnp.zeros(3),
                            jnp.array([[5.0, 1.0, 0.5], [50.0, -3.0, 2.0]]))
    assert not bool(jnp.any(vis)) and bool(jnp.all(jnp.isnan(y[:, 2])))  # was y = 0, visible
    assert bool(jnp.isnan(l3.spherical_from_cartesian(jnp.array([np.nan, 1.0, 2.0]))[2]))


@pytest.mark.parametrize("call, needle", [
    (lambda: rb2.observe(jnp.array([1.0, 2.0]), jnp.array([3.0, 4.0])), r"^s: expected shape \(3\+,\)"),
    (lambda: rb2.observe(jnp.zeros(3), jnp.array([[3.0], [4.0]])), r"^l: expected shape \(2\+,\)"),
    (lambda: rb2.inverse(jnp.zeros(3), jnp.array([5.0])), r"^z: expected shape \(2,\)"),
    (lambda: rb2.residual(jnp.array([1.0, 2.0, 3.0]), jnp.array([1.0, 2.0])), r"^z: expected shape \(2,\)"),
    (lambda: l3.cartesian_from_spherical(jnp.array([0.1, 0.2])), r"^y: expected shape \(\.\.\., 3\)"),
    (lambda: l3.spherical_from_cartesian(jnp.array([1.0, 2.0])), r"^c: expected shape \(\.\.\., 3\)"),
    (lambda: uwb.squared_range(jnp.zeros(2), jnp.array([[3.0], [4.0]])), "^p and l: "),
    (lambda: uwb.plain_range(jnp.zeros(2), jnp.zeros(3)), "^p and l: "),
    (lambda: l3.measurement_cov(l3.LidarSpec(sigma_range=-0.1)), "^spec.sigma_range: must be >= 0"),
    (lambda: l3.sample_noise(jax.random.PRNGKey(0), l3.LidarSpec(sigma_az=float("nan"))), "^spec.sigma_az: must be finite"),
    (lambda: imu.white_noise_sigma(imu.ImuSpec(accel_noise_density=-1.0)), "^spec.accel_noise_density: invalid"),
    (lambda: imu.drift_transition(imu.ImuSpec(drift_tau=-5.0, drift_density=0.1), 0.01), "^spec.drift_tau: invalid"),
    (lambda: imu.drift_transition(imu.ImuSpec(drift_tau=5.0, drift_density=0.1), -0.01), "^dt: expected a step >= 0"),
    (lambda: imu.bias_drift_rollout(jax.random.PRNGKey(0), imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)),
                                    imu.ImuSpec(drift_tau=5.0), 0.01, 2.7), "^n_steps: expected an int"),
    (lambda: imu.check_imu_spec(imu.PAPER000_IMU._replace(rate="100")), "^spec.rate: expected numbers"),
    (lambda: l3.check_lidar_spec(l3.PAPER000_LIDAR._replace(sigma_range="0.1")), "^spec.sigma_range: expected numbers"),
    (lambda: imu.corrupt(jnp.zeros((6, 5)), imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)), jnp.zeros((6, 5))),
     r"^ideal: expected shape \(\.\.\., 6\)"),  # a transposed (6, T) log
    (lambda: imu.corrupt(jnp.zeros((5, 6)), imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)), jnp.zeros((4, 6))),
     r"^white: shape \(4, 6\) does not broadcast"),
    (lambda: imu.corrupt(jnp.zeros((5, 6)), (jnp.zeros(6), jnp.zeros(6)), jnp.zeros((5, 6))),
     "^state: expected a BiasDriftState"),
    (lambda: uwb.squared_range_variance(2.0, -0.01), "^range_var: must be >= 0"),
    (lambda: uwb.uniform_variance(-0.3), "^half_width: must be >= 0"),
    (lambda: uwb.sample_noise(jax.random.PRNGKey(0), (3,), -0.3, "uniform"), "^half_width: must be >= 0"),
], ids=["rb2-pose", "rb2-landmark", "rb2-inverse", "rb2-residual", "lidar-cart", "lidar-sph", "uwb-transposed",
        "uwb-dims", "lidar-cov-sigma", "lidar-noise-nan", "imu-density", "imu-tau", "imu-dt", "imu-steps",
        "imu-spec-str", "lidar-spec-str", "corrupt-transposed", "corrupt-white", "corrupt-state", "uwb-var-neg",
        "uwb-halfwidth-neg", "uwb-noise-neg"])
def test_sensor_functions_name_a_bad_argument(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_sensor_shape_checks_hold_under_jit_and_good_calls_are_unchanged():
    with pytest.raises(InputError, match="^s: "):
        jax.jit(rb2.observe)(jnp.zeros(2), jnp.ones(2))
    z = rb2.observe(jnp.array([0.0, 0.0, 0.0]), jnp.array([3.0, 4.0]))
    np.testing.assert_allclose(np.asarray(z), [5.0, np.arctan2(4.0, 3.0)], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(rb2.inverse(jnp.zeros(3), z)), [3.0, 4.0], rtol=1e-6)
    assert float(uwb.squared_range(jnp.zeros(2), jnp.array([3.0, 4.0]))) == 25.0


XS = jnp.linspace(0.0, 2.0, 30)
PTS = jnp.stack([XS, jnp.ones_like(XS)], 1)  # the line y = 1: ρ = 1, θ = π/2


@pytest.mark.parametrize("call, needle", [
    (lambda: L.fit_line(PTS, jnp.ones(1)), r"^weights: expected shape \(30,\)"),  # broadcast before
    (lambda: L.fit_line(PTS, -jnp.ones(30)), "^weights: must be >= 0"),
    (lambda: L.fit_line(jnp.pad(PTS, ((0, 0), (0, 1))), jnp.ones(30)), r"^points: expected shape \(N, 2\)"),
    (lambda: L.fit_line_cov(PTS, jnp.ones(30), -0.02), "^sigma: expected a point noise σ > 0"),
    (lambda: L.fit_line_cov(PTS, jnp.ones(30), jnp.array([0.02, 0.03])), "^sigma: expected a scalar"),
    (lambda: L.largest_run(jnp.ones(5, bool), -1), "^max_gap: expected an int >= 0"),
    (lambda: L.trim_run(jnp.ones(5, bool), 1.5), "^k: expected an int >= 0"),
    (lambda: L.check_ransac_config(L.DEFAULT_RANSAC._replace(stop_on_fail="no")), "^cfg.stop_on_fail"),
    (lambda: L.check_ransac_config(L.DEFAULT_RANSAC._replace(threshold=True)), "^cfg.threshold"),
    (lambda: L.check_ransac_config(L.DEFAULT_RANSAC._replace(trim_ends=1.5)), "^cfg.trim_ends"),
    (lambda: L.check_ransac_config(L.DEFAULT_RANSAC._replace(max_gap=-2)), "^cfg.max_gap"),
    (lambda: L.match_predicted(PTS, jnp.ones(30, bool), jnp.array([1.0]), jnp.array([1.5]),
                               jnp.array([True]), gate=-1.0), "^gate: expected a distance > 0"),
    (lambda: L.extract_lines(jax.random.PRNGKey(0), jnp.zeros((0, 2)), jnp.zeros(0, bool)),
     "^points: expected at least one point"),
    (lambda: L.match_predicted(jnp.zeros((0, 2)), jnp.zeros(0, bool), jnp.array([1.0]), jnp.array([1.5]),
                               jnp.array([True])), "^points: expected at least one point"),
], ids=["weights-len", "weights-neg", "points-3d", "sigma-neg", "sigma-vec", "gap", "trim", "stop",
        "thr-bool", "trim-frac", "gap-neg", "match-gate", "extract-empty", "match-empty"])
def test_line_features_name_a_bad_argument(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_line_fit_of_good_input_is_unchanged():
    rho, theta = L.fit_line(PTS, jnp.ones(30))
    assert float(rho) == pytest.approx(1.0, abs=1e-6) and float(theta) == pytest.approx(np.pi / 2, abs=1e-6)
    rho_i, _ = L.fit_line(PTS.astype(jnp.int32), jnp.ones(30))  # integer points are promoted
    assert np.isfinite(float(rho_i))


def test_more_small_functions_name_a_bad_argument():
    from jaxslam.filters import ekf, sqrt_ekf
    from jaxslam.sensors import landmarks, laser2d
    from jaxslam.sim import simulate
    from jaxslam.sim.scenarios import registry

    spec = laser2d.URG04LX
    with pytest.raises(InputError, match=rf"^valid: expected shape \({spec.n_beams},\)"):
        laser2d.scan_points(jnp.ones(spec.n_beams), jnp.array([True]), spec)  # all beams valid before
    with pytest.raises(InputError, match="^dtype: beam angles need a floating dtype"):
        laser2d.beam_angles(spec, jnp.int32)
    for args, needle in (((-10.0, 0.01, 10), "^duration: expected a positive"), ((10.0, 0.0, 10), "^dt: "),
                         ((0.01, 0.01, 10), "^duration: 0.01 s holds no LiDAR frame"),
                         ((1.0, 0.01, 2.5), "^lidar_every: expected an int")):
        with pytest.raises(InputError, match=needle):
            simulate.n_frames(*args)
    assert simulate.n_frames(1.0, 0.01, 10) == 10
    with pytest.raises(InputError, match="^g: expected an"):
        sqrt_ekf.from_gaussian(ekf.Gaussian(jnp.zeros(2), jnp.eye(3)))
    with pytest.raises(InputError, match="^center: must be finite"):
        landmarks.generate_landmarks(jax.random.PRNGKey(0), 2, center=(0.0, float("nan"), 0.0))
    with pytest.raises(InputError, match="^name: expected a scenario name"):
        registry.get(["uwb-circle"])
    for change, needle in (({"sigma_near": -0.01}, "^spec.sigma_near: expected a non-negative"),
                           ({"range_max": 0.01}, "^spec.range_max: must exceed spec.range_min"),
                           ({"angle_step": float("nan")}, "^spec.angle_step: expected a finite")):
        with pytest.raises(InputError, match=needle):
            laser2d.range_sigma(jnp.ones(3), spec._replace(**change))
    np.testing.assert_allclose(np.asarray(laser2d.range_sigma(jnp.array([0.5, 2.0]), spec)), [0.01, 0.02])
    from jaxslam.dynamics import params as quad_params
    with pytest.raises(InputError, match="^params.mass: expected numbers"):
        quad_params.validate_params(quad_params.PAPER000._replace(mass="1.2"))


def test_review_2026_12_07_sensor_dtypes_fov_spec_and_outlier_probability():
    """A review reproduced: an integer dtype made an all-zero R (lidar3d, range_bearing3d) or a bare
    JAX error (sample_noise); uwb's default dtype was float64 (truncated with a warning without
    x64); an inverted FOV spec hid every landmark; laser2d.scan took outlier_prob 2.0, -1, NaN."""
    from jaxslam.sensors import laser2d, range_bearing3d as rb3

    for fn in (lambda: l3.measurement_cov(dtype=jnp.int32), lambda: rb3.measurement_cov(dtype=jnp.int32),
               lambda: l3.sample_noise(jax.random.PRNGKey(0), dtype=jnp.int32),
               lambda: rb3.sample_noise(jax.random.PRNGKey(0), dtype=jnp.int32),
               lambda: uwb.sample_noise(jax.random.PRNGKey(0), (3,), 0.1, "uniform", jnp.int32)):
        with pytest.raises(InputError, match=r"^dtype: expected a floating dtype"):
            fn()
    assert uwb.sample_noise(jax.random.PRNGKey(0), (3,), 0.1, "uniform").dtype == jnp.result_type(float)
    bad = l3.PAPER000_LIDAR._replace(az_min=1.0, az_max=-1.0)
    with pytest.raises(InputError, match=r"az_min"):
        l3.in_fov(np.array([0.0, 0.0, 5.0]), bad)
    assert bool(l3.in_fov(np.array([0.0, 0.0, 5.0])))
    room = laser2d.walls_from_polygon([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
    args = (jax.random.PRNGKey(0), jnp.array([1.0, 1.0, 0.0]), jnp.asarray(room), jnp.ones(len(room), bool),
            laser2d.URG04LX)
    for q in (2.0, -1.0, float("nan"), "0.1"):
        with pytest.raises(InputError, match=r"^outlier_prob: expected a probability in \[0, 1\]"):
            laser2d.scan(*args, outlier_prob=q)
    r, v, _ = laser2d.scan(*args, outlier_prob=0.5)
    assert np.isfinite(np.asarray(r)[np.asarray(v)]).all()
