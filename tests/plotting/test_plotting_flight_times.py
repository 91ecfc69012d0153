"""The flight plots' time axis ``t`` is checked like their other arrays: numbers only, (T,)."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxslam.errors import InputError  # noqa: E402
from jaxslam.plotting import flight  # noqa: E402


@pytest.mark.parametrize("t", ["1.5", ["0", "0.1", "0.2", "0.3", "0.4"], None])
def test_flight_plots_refuse_times_that_are_not_numbers(t):
    # NumPy parsed "1.5" (and a list of such strings) as floats, so a typo in a file was plotted
    with pytest.raises(InputError, match=r"^t: expected numbers"):
        flight.states_over_time(t, np.zeros((5, 9)), np.zeros((5, 4)))
    with pytest.raises(InputError, match=r"^t: expected numbers"):
        flight.inputs_over_time(t, np.zeros((5, 4)))


def test_flight_plots_keep_the_shape_message_and_accept_numbers():
    with pytest.raises(InputError, match=r"^t: expected shape \(T,\), got \(\)"):
        flight.inputs_over_time(1.5, np.zeros((5, 4)))
    try:
        fig = flight.inputs_over_time([0, 1, 2, 3, 4], np.zeros((5, 4)))  # ints are times too
        assert len(fig.axes) == 2
    finally:
        flight.plt().close("all")
