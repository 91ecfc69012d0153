"""Review of jaxslam.geometry.quaternion and the built-in scenarios' option declarations:
each test compares against an independent expectation (NumPy, hand-computed values, the
Monte Carlo runner's observed behaviour)."""

import numpy as np
import pytest

from jaxslam.geometry import quaternion as qu


def _np_log(q):
    """Shortest rotation vector of a quaternion, in float64 NumPy."""
    q = np.asarray(q, np.float64)
    q = q * (1.0 if q[0] >= 0 else -1.0)
    n = np.linalg.norm(q[1:])
    return 2.0 * np.arctan2(n, q[0]) / n * q[1:]


@pytest.mark.parametrize("dtype, scale", [(np.float32, 1e-40), (np.float32, 3e-45),
                                          (np.float64, 1e-310)])
def test_subnormal_quaternion_is_normalised_not_nan(dtype, scale):
    # a finite non-zero q whose entries are all subnormal: XLA flushes them to zero, so the
    # power-of-two rescaling could not help and qnormalize / qlog returned NaN
    q = (np.array([1.0, 2.0, 3.0, 4.0]) * scale).astype(dtype)
    assert np.abs(q).max() > 0 and np.abs(q).max() < np.finfo(dtype).tiny
    q64 = np.ldexp(q.astype(np.float64), 600)  # the subnormal entries' exact values, times 2^600
    ref = q64 / np.linalg.norm(q64)
    out = np.asarray(qu.qnormalize(q))
    assert out.dtype == dtype
    tol = 2e-7 if dtype == np.float32 else 1e-15
    np.testing.assert_allclose(out.astype(np.float64), ref, atol=tol)
    lg = np.asarray(qu.qlog(q))
    assert lg.dtype == dtype
    np.testing.assert_allclose(lg.astype(np.float64), _np_log(q64), atol=10 * tol)


def test_subnormal_quaternion_in_a_batch_leaves_the_other_rows_bit_identical():
    q = np.array([[1e-40, -2e-40, 0.0, 3e-40], [0.5, 0.5, 0.5, 0.5], [0.1, 0.2, 0.3, 0.9]],
                 np.float32)
    out = np.asarray(qu.qnormalize(q))
    q64 = q.astype(np.float64)
    np.testing.assert_allclose(out.astype(np.float64), q64 / np.linalg.norm(q64, axis=1, keepdims=True),
                               atol=2e-7)
    np.testing.assert_array_equal(out[1:], np.asarray(qu.qnormalize(q[1:])))
    lg = np.asarray(qu.qlog(q))
    for i in range(3):
        np.testing.assert_allclose(lg[i].astype(np.float64), _np_log(q64[i]), atol=2e-6)
    # a zero quaternion is still refused, a NaN one still NaN
    from jaxslam.errors import InputError
    with pytest.raises(InputError, match="zero quaternion"):
        qu.qnormalize(np.zeros(4, np.float32))
    assert np.isnan(np.asarray(qu.qnormalize(np.array([np.nan, 0, 0, 0], np.float32)))).all()


def test_chunk_help_states_the_runners_caps():
    # the help said "max 256" only; with --plots (a "detail" output) the runner caps a vmapped
    # chunk at 16 runs.  Observe both caps on the runner itself.
    import jax

    from jaxslam.sim import monte_carlo
    from jaxslam.sim.scenarios.builtin import DECLARED

    def fn(key):
        x = jax.random.normal(key, ())
        return {"x": x, "detail": {"y": x}}

    def fn_plain(key):
        return {"x": jax.random.normal(key, ())}

    cap_detail = monte_carlo.run(fn, 0, 40, chunk=300, detail=True, cpu_batching="vmap").chunk
    cap_plain = monte_carlo.run(fn_plain, 0, 300, chunk=1000, cpu_batching="vmap").chunk
    assert (cap_plain, cap_detail) == (256, 16)  # the numbers the help must state
    helps = [o.help for d in DECLARED.values() for o in d.options if o.name == "chunk"]
    assert len(helps) == len(DECLARED) - 1  # attitude-smc runs no Monte Carlo chunks
    for h in helps:
        assert f"max {cap_plain}" in h and f"max {cap_detail} with --plots" in h, h


@pytest.mark.parametrize("call, msg", [
    (lambda: qu.qmul(np.ones((2, 4)), np.ones((3, 4))),
     r"^qmul: p and q batch shapes \(2,\) and \(3,\) do not broadcast$"),
    (lambda: qu.qrotate(np.ones((2, 4)), np.ones((3, 3))),
     r"^qrotate: q and v batch shapes \(2,\) and \(3,\) do not broadcast$"),
])
def test_batch_shapes_that_do_not_broadcast_are_named(call, msg):
    # they were a bare TypeError / ValueError from inside the arithmetic
    from jaxslam.errors import InputError
    with pytest.raises(InputError, match=msg):
        call()


def test_batch_shapes_that_broadcast_still_broadcast():
    # hand-built: rotations by 90° about z (q = [c, 0, 0, s], c = s = √½) and the identity
    c = np.sqrt(0.5)
    q = np.array([[[c, 0, 0, c]], [[1.0, 0, 0, 0]]])  # (2, 1, 4)
    v = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # (3, 3)
    out = np.asarray(qu.qrotate(q, v))
    assert out.shape == (2, 3, 3)
    np.testing.assert_allclose(out[0], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(out[1], v, atol=0)
    m = np.asarray(qu.qmul(q, np.array([c, 0, 0, c])))  # (2, 1, 4): 180° about z, then 90°
    np.testing.assert_allclose(m[:, 0], [[0, 0, 0, 1.0], [c, 0, 0, c]], atol=1e-15)
