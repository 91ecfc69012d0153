"""Scenario ``attitude-smc`` (paper 004 ch. 3.4): runs, metrics, plots."""

import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import attitude, registry

METRICS = ("att_err_rms_deg", "att_err_final_deg", "rate_err_rms_dps", "max_torque", "settle_time_s")


def _run(runs=2, dtype=np.float64, plots=False, **opts):
    options = {o.name: o.default for o in attitude.OPTIONS}
    options["duration"] = 4.0
    options.update(opts)
    return attitude.SCENARIO.run(runs=runs, seed=0, dtype=np.dtype(dtype), options=options,
                                 progress=Progress.null(), plots=plots)


@pytest.fixture(scope="module")
def random_run():
    return _run(perturbation="random", plots=True)


def test_registered():
    assert registry.get("attitude-smc") is attitude.SCENARIO


def test_scenario_runs_and_reports_metrics(random_run, tmp_path):
    r = random_run
    assert set(r.metrics) == set(METRICS)
    for k in METRICS:
        assert np.shape(r.metrics[k]) == (2,), k
        assert np.all(np.isfinite(r.metrics[k])), k
    assert r.consistency is None
    assert r.flags["non_finite"] == 0
    # random perturbations differ per run
    assert r.metrics["att_err_final_deg"][0] != r.metrics["att_err_final_deg"][1]
    # starts ~83° away, settles in ~3 s (measured 2.9-3.0 s); mean over 3-4 s ≈ 0.6°
    assert np.all(r.metrics["settle_time_s"] < 3.5)
    assert np.all(r.metrics["att_err_final_deg"] < 1.0)
    assert np.all(r.metrics["max_torque"] <= 0.18 + 1e-12)
    assert r.config["gain_matrices"]["K1"][0][0] == 100.0 and r.config["theorem31"]["holds"] == 1.0
    paths = r.plot(tmp_path)
    assert len(paths) == 3
    for p in paths:
        assert p.exists() and p.stat().st_size > 10_000 and p.suffix == ".png"


def test_constant_perturbation_runs_identical_and_never_settles_below_1deg():
    r = _run(perturbation="constant", gains="lqr", torque="exact")
    m = r.metrics
    np.testing.assert_array_equal(m["att_err_rms_deg"][0], m["att_err_rms_deg"][1])
    # the exact law leaves a ξ/K1 offset (1.86° at 25 s; 1.50° mean over 3-4 s, still
    # creeping up) under the constant ξ, so ‖θ_e‖ never stays below 1°
    assert np.all(np.isnan(m["settle_time_s"]))
    assert np.all((m["att_err_final_deg"] > 1.2) & (m["att_err_final_deg"] < 2.5))


def test_bad_options_are_input_errors():
    with pytest.raises(InputError, match="--duration"):
        _run(runs=1, duration=-1.0)
    with pytest.raises(InputError, match="--dt"):
        _run(runs=1, dt=10.0)
    with pytest.raises(InputError, match="perturbation"):
        _run(runs=1, perturbation="gaussian")
