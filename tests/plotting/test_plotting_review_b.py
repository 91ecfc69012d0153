"""Review of plotting.uwb, .lines, .dataset, .tuning: a non-finite position band on the UWB
error figure, figures left open when a plot fails, scan_index and name checks, NumPy-scalar
consistency statistics and null reference entries in the tuning figures."""

from types import SimpleNamespace as NS

import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.plotting import dataset, flight, lines, uwb
from jaxslam.plotting import tuning as pt


def _uwb_args(T=6, N=3, x_var_nan_from=None, robot_cov=None):
    truth = np.zeros((T, 10))
    truth[:, 0] = np.arange(T)
    cov = np.tile(np.eye(10) * 0.01, (T, 1, 1))
    if x_var_nan_from is not None:
        cov[x_var_nan_from:, 0, 0] = np.nan  # a diverged run: the x variance undefined
    steps = NS(mean=truth + 0.1, cov=cov, active=np.ones((T, N), bool), landmarks=np.zeros((T, N, 2)),
               lm_cov=np.tile(np.eye(2), (T, N, 1, 1)), nis=np.ones(T), dof=np.ones(T))
    res = NS(steps=steps, smoothed=None,
             startup=NS(robot_pos=np.zeros(2), robot_cov=np.eye(2) if robot_cov is None else robot_cov))
    sim = NS(truth=truth, anchors=np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]))
    setup = NS(ts=np.arange(T, dtype=float), startup_pos=np.zeros((2, 2)))
    cfg = NS(mode="localization", model="m")
    c = {"bounds": [0.5, 2.0], "dof": 2, "anees": 1.0, "fraction_steps_in_bounds": 0.9}
    return (sim, res, {"series": {"pos_err_m": np.full(T, 0.1 * np.sqrt(2))}}, setup, cfg,
            {"pos": np.ones(T), "robot": np.ones(T)}, {"pos": c, "robot": dict(c, dof=10)}, 1)


def test_uwb_errors_figure_of_a_run_with_an_undefined_position_band(tmp_path, monkeypatch):
    # a non-finite x variance (limit None on the x panel) crashed the figure with a TypeError
    texts = {}
    real_save = uwb.save

    def spy(fig, directory, name):
        texts[name] = [t.get_text() for ax in fig.axes for t in ax.texts] + [t.get_text() for t in fig.texts]
        if name.endswith("_errors"):
            x_line = fig.axes[0].lines[0]
            texts["x_err"] = np.asarray(x_line.get_ydata(), float)
        return real_save(fig, directory, name)

    monkeypatch.setattr(uwb, "save", spy)
    paths = uwb.plot_all("u", *_uwb_args(x_var_nan_from=3), tmp_path)
    assert [p.name for p in paths] == ["u_path.png", "u_startup.png", "u_errors.png", "u_nees.png"]
    assert all(p.stat().st_size > 0 for p in paths) and flight.plt().get_fignums() == []
    np.testing.assert_allclose(texts["x_err"], np.full(6, 0.1), atol=1e-12)  # mean − truth, by hand
    err_texts = "\n".join(texts["u_errors"])
    assert "3σ band omitted where undefined (see note)" in err_texts
    assert "x: 3σ undefined (non-finite covariance) at 3 step(s)" in err_texts
    assert "wider than" not in err_texts


def test_uwb_and_dataset_close_the_figure_that_fails(tmp_path):
    with pytest.raises(InputError, match=r"^cov: not positive semi-definite"):
        uwb.plot_all("u", *_uwb_args(robot_cov=-np.eye(2)), tmp_path / "u")
    assert flight.plt().get_fignums() == []
    T = 4
    ev = {"ref_xy": np.c_[np.arange(T, dtype=float), np.zeros(T)],
          "est_xy": np.c_[np.arange(T, dtype=float), np.ones(T)], "ref_label": "ground truth",
          "t": np.arange(T, dtype=float), "frame_note": "n", "lm_xy": np.zeros((2, 2)),
          "lm_cov": np.array([np.eye(2), -np.eye(2)])}
    run = NS(dataset="utias", config={"filter": "ekf", "setting": "s"}, evaluation=ev, metrics={"ate_m": 1.0})
    with pytest.raises(InputError, match=r"^cov: not positive semi-definite"):
        dataset.plot_run(run, tmp_path / "d")
    assert flight.plt().get_fignums() == []


def test_dataset_plot_run_checks_name_before_drawing(tmp_path):
    with pytest.raises(InputError, match=r"^name: expected a plain file name \(no folder part\), got 'a/b'"):
        dataset.plot_run(None, tmp_path, name="a/b")  # (run is never read: name is checked first)
    assert flight.plt().get_fignums() == []


@pytest.mark.parametrize("index, msg", [(5, r"expected an int < 5 \(the number of scans\), got 5"),
                                        (-1, r"expected an int >= 0, got -1"),
                                        (2.5, r"expected an int >= 0, got 2.5"),
                                        (True, r"expected an int >= 0, got True")])
def test_lines_scan_index_is_checked(tmp_path, index, msg):
    T = 5
    setup = NS(ts=np.arange(T, dtype=float), truth=np.zeros((T, 5)),
               walls=np.array([[[0.0, 0.0], [1.0, 0.0]]]))
    log = NS(ranges=np.ones((T, 3)), valid=np.ones((T, 3), bool), tilt=np.zeros((T, 2)))
    res = NS(steps=NS(mean=np.zeros((T, 5)), cov=np.zeros((T, 5, 5))))
    with pytest.raises(InputError, match="^scan_index: " + msg):
        lines.plot_all("n", setup, None, log, res, np.ones(T), (0.5, 2.0), tmp_path, scan_index=index)
    assert flight.plt().get_fignums() == []


def test_tuning_panels_take_numpy_scalar_consistency_statistics():
    side = {"metrics": {"pos_rmse_m": {"mean": 1.0}},
            "consistency": {"anees": np.float32(3.0), "anees_bounds": [1.0, 5.0], "nis_mean": np.int64(2)}}
    panels, left_out = pt.choose_panels({"before": side, "after": side})
    assert [q["key"] for q in panels] == ["pos_rmse_m", "anees", "nis_mean"] and left_out == []
    assert panels[1]["values"] == [3.0, 3.0] and panels[1]["bounds"] == (1.0, 5.0)


def test_param_trajectories_errors_and_null_reference_entries():
    with pytest.raises(InputError, match=r"^history holds no 'params' records$"):
        pt.param_trajectories([{"step": 0, "loss": 1.0}])
    h = [{"step": 0, "params": {"Q": [1.0, 2.0]}}, {"step": 1, "params": {"Q": [1.5, 2.5]}}]
    fig = pt.param_trajectories(h, {"Q": [None, 4.0]})  # JSON null: that entry is not drawn
    dotted = [ln for ln in fig.axes[0].lines if ln.get_linestyle() == ":"]
    assert len(dotted) == 1 and list(dotted[0].get_ydata()) == [4.0, 4.0]
    assert dotted[0].get_color() == "C1"  # Q[1]'s colour
