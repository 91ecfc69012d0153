"""A callable gate (``ekf.chi2_gate``) in the SLAM engines: ``ekf_slam.update`` used its
threshold as a number (``d2 > callable``: a bare TypeError) and now calls it with d_z, as
FastSLAM's updates do; a gate built for fewer components than d_z is refused in both (its
table would be clipped to the smaller χ²)."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

from jaxslam.errors import InputError
from jaxslam.filters import ekf_slam as es
from jaxslam.filters.ekf import chi2_gate

from test_filters_ekf_slam import MODEL, R


def _mapped():
    st = es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 4, 2)
    return es.register(st, MODEL, jnp.array([[5.0, 0.2]]), jnp.array([7]), jnp.array([True]), jnp.asarray(R))


@pytest.mark.parametrize("off, gated", [(2.0, True), (0.0, False)])
def test_ekf_slam_update_takes_a_callable_gate_as_its_threshold(off, gated):
    st = _mapped()
    z = jnp.array([[5.0 + off, 0.2]])
    st_c, info_c = es.update(st, MODEL, z, jnp.array([0]), jnp.array([True]), jnp.asarray(R),
                             gate=chi2_gate(0.99, 2))
    # the same update with the number: the 0.99 quantile of χ² with 2 dof (SciPy)
    st_n, info_n = es.update(st, MODEL, z, jnp.array([0]), jnp.array([True]), jnp.asarray(R),
                             gate=float(chi2.ppf(0.99, 2)))
    assert bool(info_c.gated[0]) is gated and bool(info_n.gated[0]) is gated
    np.testing.assert_array_equal(np.asarray(st_c.x), np.asarray(st_n.x))
    np.testing.assert_array_equal(np.asarray(st_c.P), np.asarray(st_n.P))


def test_a_gate_built_for_fewer_components_than_d_z_is_refused():
    st = _mapped()
    with pytest.raises(InputError, match=r"^gate: built for at most 1 valid components"):
        es.update(st, MODEL, jnp.array([[5.0, 0.2]]), jnp.array([0]), jnp.array([True]), jnp.asarray(R),
                  gate=chi2_gate(0.99, 1))


def test_fastslam_refuses_a_gate_built_for_fewer_components_than_d_z():
    from jaxslam.filters import fastslam as fs

    from test_filters_fastslam import MODEL as FS_MODEL, R_NP

    p = fs.init(jnp.zeros(3), 2, 4, 2)
    z = np.array([[1.0, 0.1]])
    with pytest.raises(InputError, match=r"^gate: built for at most 1 valid components"):
        fs.observe_update(p, FS_MODEL, z, np.array([0]), np.array([True]), R_NP, None, gate=chi2_gate(0.99, 1))
