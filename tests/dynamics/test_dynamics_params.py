"""Parameter containers, presets and validation."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.dynamics import (
    PAPER000,
    PAPER001,
    PAPER001_MISMATCH,
    QuadParams,
    RotorQuadParams,
    as_arrays,
    validate_params,
)
from jaxslam.errors import InputError


def test_presets_hold_paper_values_as_python_numbers():
    assert PAPER000 == QuadParams(1.56, (0.1147, 0.0576, 0.1712), 9.81)
    assert (PAPER001.mass, PAPER001.inertia) == (1.477, (0.01152, 0.01152, 0.0218))
    assert (PAPER001_MISMATCH.mass, PAPER001_MISMATCH.inertia) == (1.477, (0.0288, 0.0288, 0.0545))
    # 150 % increase, as the paper states (within its rounding).
    np.testing.assert_allclose(np.array(PAPER001_MISMATCH.inertia) / PAPER001.inertia, 2.5, rtol=0.01)
    for p in (PAPER000, PAPER001, PAPER001_MISMATCH):
        assert all(isinstance(v, (float, tuple)) for v in p)
        validate_params(p)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_as_arrays(dtype):
    p = as_arrays(PAPER001, dtype)
    assert isinstance(p, RotorQuadParams)
    assert all(v.dtype == dtype for v in p)
    assert p.inertia.shape == (3,)
    np.testing.assert_allclose(np.asarray(p.inertia), PAPER001.inertia, rtol=1e-7)
    validate_params(p)


@pytest.mark.parametrize(
    "params, field",
    [
        (QuadParams(0.0, (1.0, 1.0, 1.0)), "mass"),
        (QuadParams(-1.0, (1.0, 1.0, 1.0)), "mass"),
        (QuadParams(1.0, (1.0, 0.0, 1.0)), "inertia"),
        (QuadParams(1.0, (1.0, 1.0)), "inertia"),
        (QuadParams(1.0, ((1.0, 1.0, 1.0),)), "inertia"),
        (QuadParams(1.0, (1.0, 1.0, 1.0), -9.81), "g"),
        (QuadParams(np.nan, (1.0, 1.0, 1.0)), "mass"),
        (QuadParams((1.0, 2.0), (1.0, 1.0, 1.0)), "mass"),
        (PAPER001._replace(arm_length=0.0), "arm_length"),
        (PAPER001._replace(k_thrust=-1.0), "k_thrust"),
        (PAPER001._replace(k_drag=0.0), "k_drag"),
        (PAPER001._replace(rotor_inertia=-1e-5), "rotor_inertia"),
    ],
)
def test_validate_params_names_field(params, field):
    with pytest.raises(InputError, match=rf"^params\.{field}:"):
        validate_params(params)


def test_validate_params_rejects_other_types():
    with pytest.raises(InputError, match="^params:"):
        validate_params({"mass": 1.0})
    assert validate_params(PAPER001._replace(rotor_inertia=0.0)).rotor_inertia == 0.0
