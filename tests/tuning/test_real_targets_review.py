"""Review of the real-log and UWB tuning targets (mrclam, plaza, victoria_park, uwb).

Oracles: the preset's own numbers (NumPy), hand-counted event partitions of the log, and the
error messages the project's input rule asks for (InputError naming the argument).
"""

import math
import pathlib

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.data import presets
from jaxslam.errors import InputError
from jaxslam.tuning.targets import mrclam as RL
from jaxslam.tuning.targets import plaza as PT
from jaxslam.tuning.targets import uwb as UW
from jaxslam.tuning.targets import victoria_park as VP

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_planar_theta0_is_in_the_params_dtype_and_round_trips(dtype):
    base = presets.mrclam_params(1, dtype=dtype, preset="hand")
    th = RL.planar_theta0(base)
    assert {k: v.dtype for k, v in th.items()} == {k: jnp.dtype(dtype) for k in th}  # float64 for a float32 preset
    M, R, F = (np.diag(np.asarray(a, np.float64)) for a in (base.M_c, base.R, base.Q_floor))
    want = np.log(np.sqrt(np.concatenate([M, R])))
    np.testing.assert_allclose(np.asarray(th["log_sigma"], np.float64), want, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(th["log_floor"], np.float64), np.log([F[0], F[2]]), rtol=1e-6)
    p = RL.planar_physical(th, base)
    for name in ("M_c", "R", "Q_floor"):
        np.testing.assert_allclose(np.asarray(getattr(p, name), np.float64),
                                   np.asarray(getattr(base, name), np.float64), rtol=1e-5)


@pytest.mark.parametrize("field, value, msg", [
    ("range_model", (1.2, 0.1), r"^params\.range_model: expected \(1, k2\)"),  # k0 was dropped silently
    ("Q_floor", np.diag([1e-3, 2e-3, 1e-4]), r"^params\.Q_floor: expected diag\(q_xy, q_xy, q_phi\)"),
    ("M_c", np.array([[1e-4, 1e-5], [1e-5, 4e-4]]), r"^params\.M_c: expected a diagonal matrix"),
    ("R", np.diag([0.0, 1e-3]), r"^params\.R: expected a diagonal matrix of positive"),
])
def test_planar_theta0_refuses_what_theta_cannot_hold(field, value, msg):
    base = presets.mrclam_params(1, preset="hand")
    with pytest.raises(InputError, match=msg):
        RL.planar_theta0(base._replace(**{field: jnp.asarray(value)}))


def test_mrclam_logs_refuses_no_robots_a_short_t_and_a_bad_window():
    with pytest.raises(InputError, match=r"^robots: expected at least one robot"):
        RL.mrclam_logs(DATA, [], np.float64)  # was max() of an empty sequence
    n = RL.mrclam_logs(DATA, [1], np.float64, t_max=5.0)[0].dt.shape[1]
    with pytest.raises(InputError, match=rf"^T: expected an int >= {n} "):
        RL.mrclam_logs(DATA, [1], np.float64, t_max=5.0, T=3)  # was "negative dimensions"
    assert RL.mrclam_logs(DATA, [1], np.float64, t_max=5.0, T=n + 2)[0].dt.shape == (1, n + 2)
    for bad in ("5", -1.0, math.nan):  # a TypeError, a message about odometry, one naming t_end
        with pytest.raises(InputError, match=r"^t_max: expected the fit window in seconds"):
            RL.mrclam_logs(DATA, [1], np.float64, t_max=bad)


def test_select_odometry_delay_refuses_an_empty_grid():
    base = presets.mrclam_params(1, preset="hand")
    with pytest.raises(InputError, match=r"^grid: expected at least one odometry delay"):
        RL.select_odometry_delay(DATA, [1], base, RL.mrclam_train_config(), t_max=5.0, grid=())


def test_mrclam_noise_refuses_a_boolean_odometry_delay(monkeypatch):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)
    with pytest.raises(InputError, match=r"^--odometry-delay: expected seconds or 'auto', got True$"):
        RL.mrclam_noise(data=DATA, robots=(1,), test_robots=(), t_max=2.0, odometry_delay=True)  # was a 1 s delay


@pytest.mark.parametrize("t_max", ["5", -1.0, math.nan, 0.0])
def test_plaza_logs_checks_the_window(t_max):
    with pytest.raises(InputError, match=r"^t_max: expected the fit window in seconds"):
        PT.plaza_logs(DATA, [2], t_max=t_max)


def test_victoria_park_fit_and_held_out_events_partition_the_log(monkeypatch):
    """An event exactly at the split was in the fit window and held out too."""
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)
    whole, _ = VP._logs(DATA, 5.0)
    t = np.asarray(whole.t, np.float64)
    k = int(np.searchsorted(t, t[0] + 6.0))
    t_max = float(t[k] - t[0])
    assert t[0] + t_max == t[k]  # the split falls exactly on event k
    tg = VP.victoria_park_noise(data=DATA, t_max=t_max)
    n_fit = tg.train["log"].dt.shape[1]
    n_held = int(np.sum(np.asarray(tg.test["w"])))
    assert n_held == t.size - k  # events k, k+1, ... (t >= split)
    assert n_fit == k  # events 0 .. k-1 (t < split), as the module docstring says
    assert n_fit + n_held == tg.test["log"].dt.shape[1] == t.size


def test_uwb_noise_names_a_bad_cov():
    with pytest.raises(InputError, match=r"^cov: expected 'diag' or 'chol', got 'full'"):
        UW.uwb_noise(cov="full", train_runs=1, test_runs=1)  # named "kind", after building the scenario
