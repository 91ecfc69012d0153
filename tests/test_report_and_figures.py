"""What the console report and the figures say (issue 22): consistency statistics name their
state block and dimension and explain an OUTSIDE verdict; the figures show the statistics that
matter, only meaningful ±3σ bands, visible 3σ ellipses and a readable landmark summary.

All cheap: report dicts built by hand, synthetic arrays, figures built but not drawn.
"""

import types

import numpy as np
import pytest

from jaxslam.cli.run import format_run_report as _format_run_report
from jaxslam.metrics import STEPS_INSIDE_MIN, consistency_verdict, steps_inside_text
from jaxslam.plotting import flight, slam3d, tuning, uwb
from jaxslam.plotting.flight import plt  # pyplot on the Agg backend


def _report(cons):
    m = {"mean": 0.18, "median": 0.18, "p95": 0.18, "max": 0.18, "per_run": [0.18]}
    return {"scenario": "uwb-circle", "runs": 1, "seed": 0, "dtype": "float64",
            "metrics": {"pos_rmse_m": m}, "consistency": cons, "flags": {},
            "timing": {"compile_s": 1.0, "run_s": 1.0, "runs_per_s": 1.0}}


UWB_CONS = {
    "anees": 3.35, "anees_bounds": [0.05, 7.38], "anees_block": "position (x, y)", "anees_dim": 2,
    "anees_robot": 2.1, "anees_robot_bounds": [3.25, 20.5],
    "anees_robot_block": "robot block (x, y, v_x, v_y, roll, pitch, yaw, 3 body rates)", "anees_robot_dim": 10,
    "nis_mean": 0.248, "nis_bounds": [0.90, 1.10], "nis_block": "UWB ranges and gyro rates, per degree of freedom",
    "nis_dim": 1,
}


def test_console_names_block_dimension_and_explains_outside():
    text = _format_run_report(_report(UWB_CONS))
    lines = {ln.strip().split("[")[1].split("]")[0]: ln for ln in text.splitlines() if "]: " in ln}
    assert set(lines) == {"anees", "anees_robot", "nis_mean"}
    assert "position (x, y), 2 states" in lines["anees"] and lines["anees"].endswith(" ok")
    rob = lines["anees_robot"]
    assert "robot block" in rob and "10 states" in rob
    assert "OUTSIDE, below: conservative (covariance larger than the errors)" in rob
    nis = lines["nis_mean"]
    assert "UWB ranges" in nis and "OUTSIDE, below: innovations smaller than predicted (R or P too large)" in nis
    hi = _format_run_report(_report({**UWB_CONS, "anees": 9.0}))
    assert "OUTSIDE, above: over-confident (errors larger than the covariance)" in hi


def test_console_reads_reports_without_block_entries():
    text = _format_run_report(_report({"anees": 30.0, "anees_bounds": [1.0, 2.0], "nis_mean": None,
                                       "nis_bounds": [0.9, 1.1]}))
    assert "anees 30.0000 in [1.0000, 2.0000] OUTSIDE, above: over-confident" in text
    assert "nis_mean nan in [0.9000, 1.1000] undefined" in text


def test_uwb_consistency_summary_names_both_blocks():
    from jaxslam.sim.scenarios import uwb as S

    rng = np.random.default_rng(0)
    t = np.arange(1.0, 41.0)
    series = {"nees_robot": rng.chisquare(10, (4, 40)), "nees_pos": rng.chisquare(2, (4, 40)),
              "nis": rng.chisquare(6, (4, 40)), "nis_dof": np.full((4, 40), 6.0)}
    cons, _ = S.consistency(series, t, 4)
    c = S.consistency_summary(cons)
    assert (c["anees"], c["anees_dim"]) == (cons["pos"]["anees"], 2)
    assert (c["anees_robot"], c["anees_robot_dim"]) == (cons["robot"]["anees"], 10)
    assert c["anees_bounds"] == cons["pos"]["bounds"] and c["nis_dim"] == 1
    assert "position" in c["anees_block"] and "robot" in c["anees_robot_block"]


def test_console_adds_the_per_step_check_to_a_time_averaged_anees():
    # lineslam-room's stored report: the time average sits inside the per-step bounds while only
    # 6 % of the steps do (docs/results/paper004/lineslam-room.json), so the line must say LOW.
    cons = {"anees": 3.41, "anees_bounds": [2.54, 3.50], "anees_block": "robot pose (x, y, yaw)", "anees_dim": 3,
            "anees_steps_inside": 0.06, "nis_mean": 0.48, "nis_bounds": [0.995, 1.005]}
    text = _format_run_report(_report(cons))
    line = next(ln for ln in text.splitlines() if "[anees]" in ln)
    assert line.endswith("3.4100 (time average) in [2.5400, 3.5000] ok; per step: 6.0 % of steps inside "
                         "(95 % expected): LOW"), line
    assert "steps_inside" not in text  # a companion, not a statistic of its own
    ok = _format_run_report(_report({**cons, "anees_steps_inside": 0.962}))
    assert "per step: 96.2 % of steps inside (95 % expected): ok" in ok
    assert steps_inside_text(STEPS_INSIDE_MIN).endswith(": ok")
    assert steps_inside_text(np.nextafter(STEPS_INSIDE_MIN, 0)).endswith(": LOW")
    assert steps_inside_text(float("nan")) == steps_inside_text(None) == "undefined"
    assert steps_inside_text(0.8996) == "89.9 % of steps inside (95 % expected): LOW"  # never "90.0 %, LOW"


def test_uwb_summary_carries_the_per_step_fraction_of_both_blocks():
    from jaxslam.sim.scenarios import uwb as S

    rng = np.random.default_rng(1)
    t = np.arange(1.0, 201.0)
    # position NEES 0.4x on the first half, 1.6x on the second: the time average (about 2 = n)
    # passes, the steps do not
    pos = rng.chisquare(2, (50, 200)) * np.where(t > 100, 1.6, 0.4)
    series = {"nees_robot": rng.chisquare(10, (50, 200)), "nees_pos": pos,
              "nis": rng.chisquare(6, (50, 200)), "nis_dof": np.full((50, 200), 6.0)}
    cons, per_step = S.consistency(series, t, 50)
    c = S.consistency_summary(cons)
    lo, hi = c["anees_bounds"]
    want = np.mean((np.nanmean(pos, axis=0) >= lo) & (np.nanmean(pos, axis=0) <= hi))
    assert c["anees_steps_inside"] == pytest.approx(want) and want < 0.2
    assert lo <= c["anees"] <= hi
    assert c["anees_robot_steps_inside"] > 0.85  # χ²(10) draws: about 95 % inside
    line = next(ln for ln in _format_run_report(_report(c)).splitlines() if "[anees]" in ln)
    assert f"(time average) in [{lo:.4f}, {hi:.4f}] ok; per step: {100 * want:.1f} % of steps inside (95 % expected): LOW" in line


def test_verdict_words():
    assert consistency_verdict(1.0, (0.5, 2.0)) == "ok"
    assert consistency_verdict(0.1, (0.5, 2.0)).startswith("OUTSIDE, below: conservative")
    assert consistency_verdict(3.0, (0.5, 2.0), "nis").startswith("OUTSIDE, above: innovations larger")
    assert consistency_verdict(3.0, (0.5, 2.0), None) == "OUTSIDE"
    assert consistency_verdict(None, (0.5, 2.0)) == "undefined"


def _tune_report(n_extra=12, consistency=True):
    names = ["att_rmse_deg", "init_landmark_err_m", "init_trilat_err_m", "landmark_rmse_aligned_m",
             "landmark_rmse_m", "landmarks_mapped", "pos_rmse_m", "vel_rmse_mps", "yaw_rmse_deg",
             "nees_pos_mean", "nees_robot_mean", "pos_err_max_m"][:n_extra]
    met = {n: {"mean": 1.0 + i} for i, n in enumerate(names)}
    side = {"metrics": met, "consistency": dict(UWB_CONS) if consistency else None}
    return {"before": side, "after": side, "references": {}, "loss": "mse",
            "history": [{"step": 0, "loss": 2.0}, {"step": 5, "loss": 1.0, "test_loss": 1.5}]}


def test_tune_panels_put_loss_position_and_consistency_first():
    panels, left_out = tuning.choose_panels(_tune_report(), max_panels=8)
    keys = [q["key"] for q in panels]
    assert keys[:5] == ["loss", "pos_rmse_m", "anees", "nis_mean", "anees_robot"]
    assert len(panels) == 8 and len(left_out) == 1 + 12 + 3 - 8 and "pos_rmse_m" not in left_out
    assert panels[0]["values"] == [2.0, 1.0]  # held-out loss is not recorded at step 0: training
    assert panels[2]["bounds"] == (0.05, 7.38) and "position (x, y)" in panels[2]["title"]
    # Without consistency (e.g. the LQR target) the headline still comes second.
    panels, _ = tuning.choose_panels(_tune_report(consistency=False), max_panels=8)
    assert [q["key"] for q in panels][:2] == ["loss", "pos_rmse_m"]


def test_tune_figure_shows_pos_rmse_and_names_what_is_left_out():
    fig = tuning.before_after(_tune_report(), title="t")
    titles = [a.get_title() for a in fig.axes]
    assert any(t.startswith("pos_rmse_m") for t in titles)
    assert any(t.startswith("anees\n") for t in titles)
    note = " ".join(t.get_text() for t in fig.texts)
    assert "showing 8 of 16" in note and "nees_robot_mean" in note
    plt().close(fig)


def test_uwb_error_panels_skip_roll_pitch_of_a_planar_flight():
    panels, notes = uwb.state_panels(np.zeros((10, 3)))
    labels = [q[0] for q in panels]
    assert not any("roll" in lab or "pitch" in lab for lab in labels)
    assert any("heading" in lab for lab in labels) and "x error [m]" in labels
    assert any("roll and pitch not drawn" in n for n in notes)
    att = np.zeros((10, 3))
    att[3:, 0] = 0.1
    panels, notes = uwb.state_panels(att)
    assert any(q[1] == (4, 5) for q in panels) and not notes


def test_uwb_band_omits_what_constrains_nothing():
    t = np.arange(5.0)
    b, note = uwb.band(np.array([30.0, 120.0, 200.0, 900.0, np.nan]), t, limit=180.0, name="yaw")
    assert np.array_equal(np.isnan(b), [False, False, True, True, True])
    assert "yaw: 3σ exceeds ±180°" in note and "first at t = 2 s" in note and "non-finite" in note
    b, note = uwb.band(np.array([0.1, 0.2]), t[:2])
    assert note is None and np.all(np.isfinite(b))


def test_slam3d_magnification_and_landmark_summary():
    assert slam3d.magnification([0.07, 0.08], 40.0) == 10  # 0.025 * 40 / 0.075 = 13.3 -> 10
    assert slam3d.magnification([3.0], 40.0) == 1 and slam3d.magnification([0.0], 40.0) == 1
    lms = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    F = 4
    est = np.zeros((F, 3, 3))
    est[:, 0] = lms[2] + [0.3, 0, 0]  # slot 0 holds landmark 2, slot 1 landmark 0, slot 2 unused
    est[:, 1] = lms[0] + [0.0, 0.1, 0]
    var = np.zeros((F, 3, 3))
    var[1:, 0] = 0.01
    var[:, 1] = 0.01
    fl = types.SimpleNamespace(
        est_frames=types.SimpleNamespace(landmarks=est, lm_var=var),
        est_final=types.SimpleNamespace(slam=types.SimpleNamespace(active=np.array([True, True, False]),
                                                                   ids=np.array([2, 0, -1]))))
    info = slam3d.landmark_errors(fl, lms, types.SimpleNamespace(association="known"))
    assert info["ids"].tolist() == [2, 0]  # sorted by decreasing final error
    np.testing.assert_allclose(info["final_err"], [0.3, 0.1])
    np.testing.assert_allclose(info["final_3sig"], [3 * np.sqrt(0.03)] * 2)
    assert np.isnan(info["err"][0, 0]).all() and np.isfinite(info["err"][1:, 0]).all()  # mapped at frame 1
    nn = slam3d.landmark_errors(fl, lms, types.SimpleNamespace(association="nn"))
    assert nn["ids"].tolist() == [2, 0]


@pytest.mark.parametrize("margins", [{"left": 0.2, "top": 0.7}])
def test_keep_margins_survive_the_default_adjust(margins):
    fig, axs = plt().subplots(1, 2)
    flight.keep_margins(fig, **margins)
    fig.subplots_adjust(left=0.08, top=0.94)  # what jaxslam.plotting.flight.save does
    assert axs[0].get_position().x0 == pytest.approx(0.2)
    assert axs[0].get_position().y1 == pytest.approx(0.7)
    assert fig.get_layout_engine() is None  # drawn once by savefig
    plt().close(fig)


def test_landmark_band_quantiles_match_numpy():
    import warnings

    rng = np.random.default_rng(1)
    x = rng.normal(size=(40, 7, 3))
    x[rng.random(x.shape) < 0.4] = np.nan
    x[0] = np.nan  # a frame before any landmark is mapped
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanquantile(x, [0.05, 0.5, 0.95], axis=1)
    for got, want in zip(slam3d._nanquantiles(x, (0.05, 0.5, 0.95)), ref):
        np.testing.assert_allclose(got, want, equal_nan=True)


def test_param_figure_shows_a_symmetric_matrix_once_and_the_truth_dotted():
    R = np.array([[0.05, 0.02, 0.0], [0.02, 0.04, 0.01], [0.0, 0.01, 0.1]])
    hist = [{"step": s, "params": {"Q": [0.1 * (s + 1), 0.2, 0.3, 0.4], "R": (R * (1 + s)).ravel().tolist()}}
            for s in range(3)]
    report = {"history": hist, "references": {
        "no_params": {"metrics": {}}, "nan": {"params": {"noise": {"Q": [float("nan")] * 4}}}, "odd": None,
        "true": {"params": {"noise": {"Q": np.diag([0.06, 0.08, 0.1, 0.2]).tolist(), "R": R.tolist()}}},
        "other": {"params": {"noise": {"Q": np.eye(4).tolist()}}}}}
    ref = tuning.reference_values(report)
    assert list(ref) == ["true", "other"]  # a reference without finite parameters is no reference
    assert ref["true"]["Q"] == [0.06, 0.08, 0.1, 0.2]  # the history holds Q's diagonal
    assert ref["true"]["R"] == R.ravel().tolist()  # and R whole
    fig = tuning.param_trajectories(hist, ref, title="t")
    q_ax, r_ax = fig.axes
    # Q: 4 entries (four values are not a symmetric 2×2 here); R: the 6 upper-triangle entries
    assert [ln.get_label() for ln in q_ax.get_lines() if not ln.get_label().startswith("_")] == [
        f"Q[{i}]" for i in range(4)]
    labels = [ln.get_label() for ln in r_ax.get_lines() if not ln.get_label().startswith("_")]
    assert labels == ["R[0,0]", "R[0,1]", "R[0,2]", "R[1,1]", "R[1,2]", "R[2,2]"]
    # the first reference only, dotted at the true values, named in the title
    dotted = sorted(round(float(ln.get_ydata()[0]), 6) for ln in q_ax.get_lines() if ln.get_linestyle() == ":")
    assert dotted == [0.06, 0.08, 0.1, 0.2] and "dotted: true" in q_ax.get_title()
    plt().close(fig)
    # a reference with nothing drawable on a log axis (zeros) is not named in the title
    fig = tuning.param_trajectories(hist, {"zeros": {"Q": [0.0] * 4}}, title="t")
    assert "dotted" not in fig.axes[0].get_title()
    assert not [ln for ln in fig.axes[0].get_lines() if ln.get_linestyle() == ":"]
    plt().close(fig)


@pytest.mark.parametrize("scenario", ["ekfslam3d", "lineslam"])
def test_per_step_share_is_recomputed_from_the_series(scenario):
    # An independent oracle for the reports' per-step check: the run-averaged NEES of each step
    # against SciPy's χ²(n·runs)/runs quantiles, counted in NumPy.  NEES 0.5x its dof on the
    # first half and 1.5x on the second: the time average passes, few steps do.
    from scipy.stats import chi2

    from jaxslam.sim.scenarios import ekfslam3d, lineslam

    n, runs, T = (9, 20, 120) if scenario == "ekfslam3d" else (3, 20, 120)
    rng = np.random.default_rng(5)
    t = np.arange(1, T + 1) * 0.1
    nees = rng.chisquare(n, (runs, T)) * np.where(np.arange(T) >= T // 2, 1.5, 0.5)
    nees[3, 7] = np.nan  # a run without a figure at one step: averaged over the others
    series = {"nees": nees, "nis": rng.chisquare(2, (runs, T)), "nis_dof": np.full((runs, T), 2.0),
              "dof": np.full((runs, T), 2.0)}
    if scenario == "ekfslam3d":
        cons, per_step = ekfslam3d.consistency(series, t, runs)
        share = cons["anees_fraction_in_bounds"]
    else:
        cons, per_step = lineslam.consistency(series, runs)
        share = cons["anees_steps_inside"]
    lo, hi = chi2.ppf([0.025, 0.975], n * runs) / runs
    np.testing.assert_allclose(cons["anees_bounds"], [lo, hi], rtol=1e-10)
    avg = np.array([np.mean(nees[~np.isnan(nees[:, k]), k]) for k in range(T)])
    np.testing.assert_allclose(per_step, avg, rtol=1e-12)
    want = np.count_nonzero((avg >= lo) & (avg <= hi)) / T
    assert share == pytest.approx(want, abs=1e-15) and want < 0.2
    assert lo <= cons["anees"] <= hi
    nis_lo, nis_hi = chi2.ppf([0.025, 0.975], 2 * runs * T) / (2 * runs * T)
    assert cons["nis_mean"] == pytest.approx(series["nis"].sum() / (2 * runs * T), rel=1e-12)
    np.testing.assert_allclose(cons["nis_bounds"], [nis_lo, nis_hi], rtol=1e-10)


def test_tune_table_shows_the_per_step_share_beside_the_time_average():
    from jaxslam.cli.tune import format_comparison

    def res(rmse, anees, share, key):
        cons = {"anees": anees, "anees_bounds": [7.04, 11.19], "nis_mean": 1.0, "nis_bounds": [0.9, 1.1]}
        return {"metrics": {"pos_rmse_m": {"mean": rmse}}, "consistency": {**cons, key: share}}

    # the loop / ekfslam3d targets name it anees_fraction_in_bounds, the uwb target anees_steps_inside
    for key in ("anees_fraction_in_bounds", "anees_steps_inside"):
        text = format_comparison(res(0.05, 10.4, 0.52, key), res(0.045, 9.4, 0.8996, key),
                                 {"ref": {"metrics": {"pos_rmse_m": {"mean": 0.046}},
                                          "consistency": {"anees": 9.0, "nis_mean": 1.0}}})
        rows = text.splitlines()
        i = next(k for k, r in enumerate(rows) if r.startswith("anees ["))
        assert rows[i + 1].split() == ["steps", "inside", "(95", "%", "expected,", "90.0", "%", "ok)",
                                       "52.0", "%", "89.9", "%", "-", "-"], rows[i + 1]
    # without a per-step share (figure-8, linear-Gaussian targets have no consistency block; an old report) no row
    old = res(0.05, 10.4, None, "anees_steps_inside")
    assert "steps inside" not in format_comparison(old, old)


def test_nees_figure_titles_give_the_verdict_and_the_per_step_share():
    # The same synthetic series as the per-step test above: a time average inside, few steps inside.
    from jaxslam.sim.scenarios import ekfslam3d
    from jaxslam.sim.scenarios import uwb as U

    rng = np.random.default_rng(5)
    runs, T = 20, 120
    t = np.arange(1, T + 1) * 0.1
    half = np.where(np.arange(T) >= T // 2, 1.5, 0.5)
    nees9 = rng.chisquare(9, (runs, T)) * half
    cons, per_step = ekfslam3d.consistency({"nees": nees9, "nis": rng.chisquare(2, (runs, T)),
                                           "nis_dof": np.full((runs, T), 2.0)}, t, runs)
    fig = slam3d.nees_figure("ekfslam3d-known", t, nees9[0], per_step, cons, runs)
    title = fig.axes[0].get_title().replace("\n", " ")
    assert f"flight average {cons['anees']:.2f} (consistency.anees): ok;" in title, title
    assert f"per step: {steps_inside_text(cons['anees_fraction_in_bounds'])}" in title and "LOW" in title, title
    plt().close(fig)

    series = {"nees_pos": rng.chisquare(2, (runs, T)) * half, "nees_robot": rng.chisquare(10, (runs, T)),
              "nis": rng.chisquare(6, (runs, T)), "nis_dof": np.full((runs, T), 6.0)}
    cons, per_step = U.consistency(series, t, runs)
    fig = uwb.nees_figure("uwb-circle", t, per_step, cons, runs)
    titles = [a.get_title().replace("\n", " ") for a in fig.axes]
    for title, key in zip(titles, ("pos", "robot")):
        c = cons[key]
        assert f"time average {c['anees']:.2f}" in title, title
        assert f"per step: {steps_inside_text(c['fraction_steps_in_bounds'])}" in title, title
    assert "LOW" in titles[0] and "LOW" not in titles[1]  # only the position block was made inconsistent
    plt().close(fig)
