"""Review of systems.ekf_slam_3d (params_from_dict, make_estimator) and
sim.scenarios.tracking (controller_from_dict): bad inputs are an InputError naming the key the
user wrote; good inputs are read as NumPy reads them (expectations built here, by hand)."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control import dflqr
from jaxslam.errors import InputError
from jaxslam.sim.scenarios.tracking import controller_from_dict
from jaxslam.systems import ekf_slam_3d as s3


@pytest.mark.parametrize("entry, value, pattern", [
    ("R", "abc", r"^params\.noise\.R: expected numbers"),
    ("R", [[1.0, 2.0]], r"^params\.noise\.R: expected shape \(3, 3\)"),
    ("R", [[1.0, 2.0], [3.0]], r"^params\.noise\.R: expected numbers"),
    ("R", [math.nan, 1.0, 1.0], r"^params\.noise\.R: contains NaN or Inf"),
    ("R", [1.0, -1.0, 1.0], r"^params\.noise\.R: not positive semi-definite"),
    ("Qc", [1.0] * 8, r"^params\.noise\.Qc: expected shape \(9, 9\)"),
    ("Qimu", [[1.0, 0.5, 0, 0, 0, 0]] + [[0.0] * 6] * 5, r"^params\.noise\.Qimu: not symmetric"),
    ("P0", [True] * 9, r"^params\.noise\.P0: expected numbers"),
    ("P0", None, r"^params\.noise\.P0: expected numbers"),
    ("R", 5.0, r"^params\.noise\.R: expected shape"),
])
def test_params_from_dict_bad_entry_names_params_noise_key(entry, value, pattern):
    base = s3.paper_noise("unknown")
    with pytest.raises(InputError, match=pattern):
        s3.params_from_dict({entry: value}, base, jnp.float64)


def test_params_from_dict_not_a_dict_is_an_input_error():
    with pytest.raises(InputError, match=r"^params\.noise: expected a dict"):
        s3.params_from_dict("R", s3.paper_noise("unknown"), jnp.float64)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_params_from_dict_reads_diagonals_and_matrices_like_numpy(dtype):
    base = s3.paper_noise("known", dtype)
    R = [0.01, 0.02, 0.5]
    Qimu = np.diag([1e-4] * 3 + [1e-6] * 3)
    Qimu[0, 1] = Qimu[1, 0] = 1e-5
    out = s3.params_from_dict({"R": R, "Qimu": Qimu.tolist()}, base, dtype)
    np.testing.assert_array_equal(np.asarray(out.R), np.diag(np.asarray(R, np.dtype(dtype))))
    np.testing.assert_array_equal(np.asarray(out.Qimu), Qimu.astype(np.dtype(dtype)))
    assert out.R.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(np.asarray(out.P0), np.diag(np.asarray(s3.TABLE6_P0, np.dtype(dtype))))
    s3.validate_params(out)


def test_make_estimator_checks_params_like_run():
    base = s3.paper_noise("unknown")
    with pytest.raises(InputError, match=r"^params\.R: not positive definite"):
        s3.make_estimator(s3.Config(), base._replace(R=jnp.diag(jnp.array([1.0, -1.0, 1.0]))))
    with pytest.raises(InputError, match=r"^params\.P0: expected shape \(9, 9\)"):
        s3.make_estimator(s3.Config(), base._replace(P0=jnp.eye(8)))
    with pytest.raises(InputError, match=r"^params\.nn_new: need nn_gate <= nn_new"):
        s3.make_estimator(s3.Config(), base._replace(nn_gate=50.0))


def test_make_estimator_takes_a_list_known_map():
    # the known map as a nested list (it raised AttributeError: 'list' has no attribute 'shape')
    est = s3.make_estimator(s3.Config(mode="known", capacity=2), s3.paper_noise("known"),
                            landmarks_true=[[5.0, 0.0, -1.0]])
    import jax

    st = est.init(jax.random.PRNGKey(0), jnp.zeros(12))
    np.testing.assert_array_equal(np.asarray(st.slam.x[9:12]), [5.0, 0.0, -1.0])  # the map, preloaded
    np.testing.assert_array_equal(np.asarray(st.slam.active), [True, False])
    with pytest.raises(InputError, match=r"^config\.capacity"):
        s3.make_estimator(s3.Config(mode="known", capacity=1), s3.paper_noise("known"),
                          landmarks_true=[[5.0, 0.0, -1.0], [6.0, 0.0, -1.0]])


@pytest.mark.parametrize("d, pattern", [
    ({"Q": [1, 1, 1, 1, 1, 1, -1]}, r"^params\.controller\.Q: not positive semi-definite"),
    ({"Q": [[1, 2], [3, 4]]}, r"^params\.controller\.Q: expected shape \(7, 7\)"),
    ({"R": [0, 1, 1, 1]}, r"^params\.controller\.R: not positive definite"),
    ({"kp": [1, 2]}, r"^params\.controller\.kp: expected shape \(3,\)"),
    ({"kd": [-1, 0, 0]}, r"^params\.controller\.kd: must be finite and >= 0"),
    ({"Q": [math.nan] * 7}, r"^params\.controller\.Q: contains NaN or Inf"),
    ({"kp": [True, 1, 1]}, r"^params\.controller\.kp: expected numbers"),
    ({"Q": [True] * 7}, r"^params\.controller\.Q: expected numbers"),
    ("Q", r"^params\.controller: expected a dict"),
])
def test_controller_from_dict_names_the_params_key(d, pattern):
    with pytest.raises(InputError, match=pattern):
        controller_from_dict(d, dflqr.paper000_params())


def test_controller_from_dict_reads_diagonals_like_numpy():
    q = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    out = controller_from_dict({"Q": q, "kp": [1.0, 2.0, 3.0]}, dflqr.paper000_params())
    np.testing.assert_array_equal(np.asarray(out.Q), np.diag(q))
    assert tuple(out.pd.kp) == (1.0, 2.0, 3.0)


def test_cli_singular_controller_R_names_controller_R(tmp_path, capsys):
    from jaxslam import cli

    f = tmp_path / "p.json"
    f.write_text(json.dumps({"controller": {"R": [0, 1, 1, 1]}}))  # PSD (the file check passes), not PD
    assert cli.main(["run", "track-figure8", "--duration", "0.1", "--params", str(f)]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "controller.R" in lines[0] and "Traceback" not in lines[0], lines


def test_tracking_metrics_takes_nested_lists_hand_values():
    from jaxslam.sim.scenarios.tracking import tracking_metrics

    t = [0.0, 1.0, 2.0]
    truth = [[0.5] + [0.0] * 11, [0.05] + [0.0] * 11, [0.0] * 12]
    ref = [[0.0] * 4] * 3
    m = tracking_metrics(t, truth, ref)
    assert float(m["track_pos_rmse_m"]) == pytest.approx(math.sqrt((0.25 + 0.0025) / 3), rel=1e-12)
    assert float(m["settle_time_s"]) == 1.0  # inside 0.1 m from t = 1 s on
    assert float(m["max_tilt_deg"]) == 0.0 and float(m["track_yaw_rmse_deg"]) == 0.0
    with pytest.raises(InputError, match=r"^truth"):
        tracking_metrics(t, [[0.0] * 12, [0.0]], ref)


@pytest.mark.parametrize("field", ["gate", "nn_gate", "nn_new"])
def test_validate_params_refuses_a_boolean_threshold(field):
    # gate=True (meaning "on") was taken as a chi-square gate of 1.0
    with pytest.raises(InputError, match=rf"^params\.{field}: expected a positive finite scalar"):
        s3.validate_params(s3.paper_noise("unknown")._replace(**{field: True}))
    s3.validate_params(s3.paper_noise("unknown")._replace(gate=11.34))  # a number stays accepted
