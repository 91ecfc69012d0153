"""Review of plotting/{flight,slam3d,attitude,fastslam}.py: the attitude state-error figure wraps
the roll error (−179° against 179° is 2°, it was drawn as 358°), the FastSLAM particle-cloud
titles give the flight's own times (0.01 s steps were assumed), bad ``frames`` and missing
particles are InputErrors before any figure opens, one NaN in the true IMU offsets no longer
breaks the bias figure's limits, and trajectory_3d names a landmark argument without a length.
Every expectation is computed by hand here."""

import types

import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.plotting import attitude, fastslam, flight


def _q_roll(deg):
    a = np.radians(deg)
    return np.array([np.cos(a / 2), np.sin(a / 2), 0.0, 0.0])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_attitude_state_error_wraps_the_roll_error(tmp_path, monkeypatch, dtype):
    from jaxslam.control.smc import Rollout

    T = 4
    xa = np.zeros((T + 1, 7), dtype)
    xa[:, :4] = _q_roll(-179.0)  # roll −179°, desired +179°: 2° apart across ±180°
    ro = Rollout(xa=xa, x_err=np.full((T, 6), 1e-3, dtype), tau=np.zeros((T, 3), dtype), xa_final=xa[-1],
                 norms=np.zeros((T, 3), dtype))
    figs = []
    monkeypatch.setattr(attitude, "save", lambda fig, d, n: (figs.append(fig), tmp_path / f"{n}.png")[1])
    attitude.plot_all("a", 0.01, ro, _q_roll(179.0), tmp_path)
    roll_line, pitch_line, yaw_line = figs[1].axes[0].lines[:3]
    np.testing.assert_allclose(roll_line.get_ydata(), 10 * np.log10(2.0), atol=1e-3)  # 3.01 dB, not 25.5
    np.testing.assert_array_equal(pitch_line.get_ydata(), -120.0)  # exact zeros stay on the floor
    np.testing.assert_array_equal(yaw_line.get_ydata(), -120.0)


def _fastslam_inputs(F=3, N=5, every=10, dt=0.02):
    T = F * every
    t = np.arange(T + 1) * dt
    truth = np.zeros((T + 1, 12))
    truth[:, 0] = np.arange(T + 1)
    fr = types.SimpleNamespace(particles=np.random.default_rng(0).random((F, N, 3)),
                               log_w=np.log(np.full((F, N), 1.0 / N)), map_mean=np.zeros((F, 4, 3)),
                               map_var=np.full((F, 4, 3), 1e-3), neff=np.full(F, float(N)))
    steps = types.SimpleNamespace(bias_mean=np.zeros((T, 12)), offset_var=np.zeros((T, 6)))
    fl = types.SimpleNamespace(t=t, truth=truth, offset=np.zeros((T, 12)))
    return fl, types.SimpleNamespace(frames=fr, steps=steps), np.zeros((4, 3))


def test_fastslam_cloud_titles_give_the_flights_own_times():
    fl, res, lms = _fastslam_inputs(dt=0.02)  # frame f at sample (f + 1)·10: t = 0.2, 0.4, 0.6 s
    fig = fastslam.particle_clouds(fl, res, lms, frames=[0, 1, 2])
    assert [a.get_title() for a in fig.axes[:3]] == ["t = 0.2 s", "t = 0.4 s", "t = 0.6 s"]


@pytest.mark.parametrize("frames, msg", [
    ([-1], r"^frames: expected frame indices, ints >= 0, got -1"),
    ([0, 3], r"^frames: expected indices in \[0, 3\)"),
    ([], r"^frames: expected indices in \[0, 3\)"),
    ([0.5], r"^frames: expected frame indices"),
    (2, r"^frames: expected a list of frame indices, got 2"),
])
def test_fastslam_cloud_refuses_bad_frames_before_drawing(frames, msg):
    fl, res, lms = _fastslam_inputs()
    with pytest.raises(InputError, match=msg):
        fastslam.particle_clouds(fl, res, lms, frames=frames)
    assert flight.plt().get_fignums() == []


def test_fastslam_cloud_without_particles_is_an_input_error_keeping_its_text():
    fl, res, lms = _fastslam_inputs()
    res.frames.particles = None
    with pytest.raises(InputError, match=r"^particle positions were not saved \(Config\.save_particles=False\)$"):
        fastslam.particle_clouds(fl, res, lms)
    assert flight.plt().get_fignums() == []


def test_fastslam_bias_limits_ignore_a_nan_true_offset():
    fl, res, lms = _fastslam_inputs()
    fl.offset[:, 0] = 0.01
    fl.offset[-1, 0] = np.nan
    fig = fastslam.bias(fl, res)
    np.testing.assert_allclose(fig.axes[0].get_ylim(), (-0.05, 0.05))  # ±5 · max |finite offset|
    np.testing.assert_allclose(fig.axes[1].get_ylim(), (-1e-4, 1e-4))  # all zero: the 1e-4 floor


@pytest.mark.parametrize("kw, msg", [({"landmarks": 5}, r"^landmarks: expected shape \(T, 3\+\), got \(\)"),
                                     ({"est_landmarks": 2.0}, r"^est_landmarks: expected shape")])
def test_trajectory_3d_names_landmarks_without_a_length(kw, msg):
    with pytest.raises(InputError, match=msg):
        flight.trajectory_3d(np.zeros((3, 3)), np.zeros((3, 3)), **kw)
    fig = flight.trajectory_3d(np.zeros((3, 3)), np.zeros((3, 3)), landmarks=[], est_landmarks=np.zeros((0, 3)))
    assert len(fig.axes[0].collections) == 0  # empty: nothing scattered, as before


@pytest.mark.parametrize("args, msg", [(("x", 10.0), r"^sig3: expected numbers, got 'x'$"),
                                       (([1.0], "10"), r"^span: expected numbers, got '10'$"),
                                       (([1.0], None), r"^span: expected numbers, got None$"),
                                       (([1.0], [10.0, 20.0]), r"^span: expected a scalar, got shape \(2,\)$")])
def test_magnification_names_sig3_and_span(args, msg):
    from jaxslam.plotting import slam3d

    with pytest.raises(InputError, match=msg):
        slam3d.magnification(*args)
    # by hand: median 3σ 0.01 at 2.5 % of 40 m wants ×100; of 10 m ×25 → 20; inf / 0 span → 1
    assert slam3d.magnification([0.01, np.nan, 0.0, 0.01], 40.0) == 100
    assert slam3d.magnification(np.float32([0.01]), np.float32(10.0)) == 20
    assert slam3d.magnification([0.01], np.inf) == 1 and slam3d.magnification([0.01], 0.0) == 1
