"""Plotting tests: files only (the Agg backend, set before pyplot loads), and no figure left open
between tests (each test checks what it opened)."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402

from jaxslam.plotting import flight  # noqa: E402


@pytest.fixture(autouse=True)
def _no_figures_left():
    flight.plt().close("all")
    yield
    flight.plt().close("all")
