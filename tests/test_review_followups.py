"""Follow-ups of a review of the day's fixes: what the fixes made too strict or stale.

Each test failed on the commit before these follow-ups (the review's repros)."""
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.data import catalogue
from jaxslam.data import runners as R


def test_configure_process_sets_openblas_threads_before_numpy_loads():
    # The cache flag's check imported jaxslam.errors (and NumPy with it) before
    # OPENBLAS_NUM_THREADS was set: NumPy's OpenBLAS started with its default threads.
    code = ("import sys; from jaxslam import runtime; assert 'numpy' not in sys.modules; "
            "runtime.configure_process(cache=False); print('numpy' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_dead_reckoning_sees_what_a_users_motion_reads_and_keeps_nothing_for_it():
    scale = {"k": 1.0}

    def motion(s, u, dt):  # reads mutable state: a jit keyed on the function served a stale program
        return s + scale["k"] * u[0] * dt

    u, dt = np.ones((3, 2)), np.ones(3)
    first = np.asarray(R.dead_reckoning(motion, np.zeros(3), u, dt))[-1]
    scale["k"] = 2.0
    second = np.asarray(R.dead_reckoning(motion, np.zeros(3), u, dt))[-1]
    np.testing.assert_array_equal(first, [3.0, 3.0, 3.0])  # hand values: 3 steps of 1·1·1
    np.testing.assert_array_equal(second, [6.0, 6.0, 6.0])
    n0 = R._dead_reckoning_jit._cache_size()
    for _ in range(3):  # fresh lambdas each call: one program each was kept before
        R.dead_reckoning(lambda s, u, dt: s + u[0] * dt, np.zeros(3), u, dt)
    assert R._dead_reckoning_jit._cache_size() == n0


def test_catalogue_finds_a_twice_nested_util_flight(tmp_path):
    # twr_obs_log1/twr_obs_log1/groundtruth.csv: load_util resolves it (resolve_dataset_dir's
    # subfolder rule), so the catalogue must find the dataset too
    flight = tmp_path / "util_uwb" / "twr_obs_log1" / "twr_obs_log1"
    flight.mkdir(parents=True)
    (flight / "groundtruth.csv").write_text("t\n")
    assert catalogue.find("util-uwb", tmp_path) == tmp_path / "util_uwb"
    empty = tmp_path / "other" / "util_uwb" / "twr_obs_log1" / "sub"
    empty.mkdir(parents=True)  # a subfolder without groundtruth.csv is still not a flight
    assert catalogue.find("util-uwb", tmp_path / "other") is None


def test_nees_loss_ignores_a_negative_value_the_mask_leaves_out():
    from jaxslam.errors import InputError
    from jaxslam.tuning import losses

    # hand value: mean of the counted steps 2, 2 is n = 2 -> (log 1)² = 0
    assert float(losses.nees_loss(jnp.array([2.0, 2.0, -1.0]), 2, mask=jnp.array([1, 1, 0]))) == 0.0
    with pytest.raises(InputError, match=r"^nees: expected values >= 0"):
        losses.nees_loss(jnp.array([2.0, 2.0, -1.0]), 2, mask=jnp.array([1, 0, 1]))


def test_imu_shape_prefix_takes_a_numpy_vector():
    import jax

    from jaxslam.sensors import imu

    spec = imu.PAPER001_IMU()
    a = imu.sample_white_noise(jax.random.PRNGKey(0), spec, np.array([3]))
    b = imu.sample_white_noise(jax.random.PRNGKey(0), spec, (3,))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_monitor_takes_a_round_off_negative_d2():
    from jaxslam.filters import consistency as C
    from jaxslam.filters import ekf_slam as es

    m = es.SlamModel(2, 2, 2, lambda s, u, p=None: s + u, lambda s, l, p=None: l - s,
                     lambda s, z, p=None: s + z)
    st = es.preload(es.init(jnp.zeros(2), 0.1 * jnp.eye(2), 3, 2), m, jnp.array([[1.0, 0.0], [0.0, 1.0]]),
                    jnp.stack([0.1 * jnp.eye(2)] * 2), ids=jnp.array([0, 1]))
    _OK = C.MonitorParams(alpha=0.1, threshold=1.5, max_factor=4.0, outlier_gate=9.21)
    mon = C.init(jnp.float64)
    # d² = −1e-17 (round-off of a d² near 0) and 2 over 2 rows of 2 dof: r = 2 / 4 = 0.5,
    # m = 0.9·1 + 0.1·0.5 = 0.95 (hand values), no inflation
    mon2, _ = C.observe(mon, st, m, jnp.array([-1e-17, 2.0]), jnp.array([True, True]), _OK)
    assert float(mon2.mean) == pytest.approx(0.95, abs=1e-12) and int(mon2.inflations) == 0


def test_planar_params_round_trip_keeps_a_threshold_off_against_a_base_with_it_on():
    # params_to_dict left an off (None) threshold out; read against a base with it on, the
    # file switched it back on (the run then gated at the base's value)
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as pe

    base = presets.mrclam_params()
    on = base._replace(update_gate=9.21)
    off = base._replace(update_gate=None)
    d = pe.params_to_dict(off)
    assert "update_gate" in d and d["update_gate"] is None
    assert pe.params_from_dict(d, on).update_gate is None
    assert pe.params_from_dict(pe.params_to_dict(on), off).update_gate == pytest.approx(9.21)


@pytest.mark.parametrize("which", ["ekf", "ukf"])
def test_filter_scan_names_an_empty_measurement(which):
    # zs of shape (T, 0) ended in a bare "cannot reshape array of size 0" from the R check
    import importlib

    from jaxslam.errors import InputError

    mod = importlib.import_module(f"jaxslam.filters.{which}")
    with pytest.raises(InputError, match=r"^zs: expected at least one measurement component, got shape \(3, 0\)"):
        mod.filter_scan(lambda x, u: x, lambda x: x[:0], np.zeros(2), np.eye(2), np.zeros((3, 1)),
                        np.zeros((3, 0)), None, np.eye(2), np.zeros((0, 0)))


def test_plaza_eval_command_names_every_evaluated_sequence():
    # as the MRCLAM target's: the dataset command takes one --robot, so one command per
    # evaluated sequence joined by && (it named the first sequence only)
    import pathlib

    from jaxslam.tuning.targets import plaza as PT

    data = pathlib.Path(__file__).resolve().parent / "data"
    tg = PT.plaza_noise(data=data, robots=(1, 2), test_robots=())  # nothing held out: both evaluated
    assert tg.eval_command == ("jaxslam dataset plaza --data DIR --robot 1 --params TUNED.json && "
                               "jaxslam dataset plaza --data DIR --robot 2 --params TUNED.json")
