"""The examples/ folder runs in the default suite: each example is imported from its file and its
``main(quick=True)`` is called; the figures it returns are checked against what the model
implies (not against numbers the example computed about itself)."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def _load(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_example_is_run_here():
    assert sorted(p.stem for p in EXAMPLES.glob("*.py")) == ["bearing_only_slam"]


def test_bearing_only_slam(tmp_path):
    ex = _load("bearing_only_slam")
    out = ex.main(quick=True, plot=str(tmp_path / "run.png"))
    # The generic EKF-SLAM runner with the map frozen and the generic EKF are one filter.
    assert out["agree"] < 1e-9
    # 100 seeds: the robot's NEES is χ²(3)-consistent (bounds from the χ² quantiles).
    lo, hi = out["anees_bounds"]
    assert lo <= out["anees"] <= hi
    # The map improves on its survey prior.
    assert out["map_rmse"] < out["survey_rmse"]
    # Gradient tuning recovers the simulated bearing noise (0.05 rad) from a 4× start,
    # and the held-out innovation NLL falls.
    assert out["sigma_fit"] == pytest.approx(0.05, abs=0.005)
    assert out["nll_after"] < out["nll_before"]
    assert (tmp_path / "run.png").stat().st_size > 0
