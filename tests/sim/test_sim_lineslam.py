"""Scenario ``lineslam-room`` (paper 004 ch. 4): metrics, consistency, plots, bad options.

The full acceptance run (100 vmapped runs of 60 s) is ``scripts/reproduce_paper004.py``;
here a 4-run, 30 s batch (one lap) checks the same statistics with bounds that a broken
filter (wrong sign, lost lines, over-confident covariance) fails.
"""

import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import lineslam, registry

METRICS = ("pos_rmse_m", "yaw_rmse_deg", "line_rho_err_m", "line_theta_err_deg", "lines_mapped", "anees")


def _run(runs=2, plots=False, **opts):
    sc = registry.get("lineslam-room")
    options = {o.name: o.default for o in sc.options}
    options["duration"] = 30.0
    options.update(opts)
    return sc.run(runs=runs, seed=0, dtype=np.dtype(np.float64), options=options, progress=Progress.null(),
                  plots=plots)


@pytest.fixture(scope="module")
def result():
    return _run(plots=True)


def test_map_and_truth_lines():
    walls = lineslam.room_walls()
    assert walls.shape == (10, 2, 2)
    lines = lineslam.true_lines(walls)
    assert lines.shape == (10, 2) and np.all(lines[:, 0] > 0.25)  # 10 distinct lines, none through the origin


def test_metrics_consistency_and_plots(result, tmp_path, monkeypatch):
    r = result
    for k in METRICS:
        assert np.shape(r.metrics[k]) == (2,), k
        assert np.all(np.isfinite(r.metrics[k])), k
    m = r.metrics
    # One lap: every wall seen, none spurious; centimetre pose, sub-degree yaw.
    assert np.all(m["true_lines_found"] >= 9) and np.all(m["lines_spurious"] == 0)
    assert np.all(m["pos_rmse_m"] < 0.15) and np.all(m["yaw_rmse_deg"] < 0.3)
    assert np.all(m["line_rho_err_m"] < 0.05) and np.all(m["line_theta_err_deg"] < 1.5)
    # Pose NEES (3 dof) averaged over runs and time: not over-confident (measured 1-3).
    assert 0.3 < r.consistency["anees"] < 6.0
    assert r.consistency["anees_dim"] == 3 and "pose" in r.consistency["anees_block"]
    assert r.consistency["anees_steps_inside"] == r.extra["consistency_detail"]["fraction_steps_in_bounds"]
    assert 0 <= r.consistency["anees_steps_inside"] <= 1
    assert r.flags["non_finite"] == 0 and r.flags["capacity_overflow"] == 0 and r.flags["diverged_runs"] == 0
    from jaxslam.metrics import steps_inside_text
    from jaxslam.plotting import lines as lplot

    titles, save = {}, lplot.save
    monkeypatch.setattr(lplot, "save", lambda fig, d, name: (titles.setdefault(name, [a.get_title() for a in fig.axes]),
                                                             save(fig, d, name))[1])
    paths = r.plot(tmp_path)
    assert [p.name for p in paths] == [f"lineslam-room_{s}.png" for s in ("scan", "map", "errors", "nees")]
    nees_title = titles["lineslam-room_nees"][0].replace("\n", " ")
    assert f"time average {r.consistency['anees']:.2f}" in nees_title, nees_title
    assert f"per step: {steps_inside_text(r.consistency['anees_steps_inside'])}" in nees_title, nees_title
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_bad_options():
    with pytest.raises(InputError, match="--duration"):
        _run(runs=1, duration=-1.0)
    with pytest.raises(InputError, match="--outlier-prob"):
        _run(runs=1, outlier_prob=1.5)
    with pytest.raises(InputError, match="--capacity"):
        _run(runs=1, capacity=0)
