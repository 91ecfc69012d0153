"""Ultra-wide-band (UWB) range sensor and the gyro-rate observation of paper 003.

A UWB tag on the drone measures its distance to each anchor (paper 003
Sec. III-A-1); the IMU's gyro measures the body rates (Sec. III-A-2).  The
paper is planar: positions are 2D, in metres, in the filter's map frame.

Observation models (paper 003 eq. 16-20):

* plain range (eq. 16)      d_k  = ‖A_k − T‖,                    T = (x, y)
* squared range (eq. 17)    d_k² = (l_kx − x)² + (l_ky − y)²     (the paper's choice)
* gyro (eq. 19)             Ω = [w_α, w_β, w_θ]                  (identity on the rate states)

Jacobians are never written here: the filter takes them with ``jax.jacfwd``
(eq. 18 and 21 are the hand forms; they serve as oracles in the tests).

Decisions (paper silent):

* The plain range uses :func:`jaxslam.linalg.safe_norm`, so its Jacobian at a
  zero distance is 0 instead of NaN (the drone starts the filter on top of the
  end anchor of the start-up run, where the distance is 0).
* Noise: the paper adds *uniform* noise of maximum deviation 0.2 (ranges) and
  0.002 (gyro rates) (Sec. IV).  :func:`sample_noise` draws it, and also
  Gaussian noise *of the same variance* (σ = a/√3 for half-width a), which is
  what a consistency test against χ² bounds needs.
* A measured squared range is the square of the measured range, (d + δ)²; its
  noise 2dδ + δ² has mean σ² and variance ≈ 4d²σ² + 2σ⁴
  (:func:`squared_range_variance`; the 2σ⁴ term is the Gaussian value, the
  uniform one is 4a⁴/45 — both are negligible beside 4d²σ² except within a few
  centimetres of an anchor).
* A range that is not finite or not positive is not a measurement (a real UWB
  never reports d ≤ 0, and a simulated one with additive noise can near an
  anchor): :func:`valid_ranges` marks it, and the filter masks and counts it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import real_float
from ..errors import InputError
from ..linalg import check_float_dtype, check_numbers, check_real, is_concrete, safe_norm

__all__ = [
    "UwbNoise",
    "PAPER003_NOISE",
    "MODELS",
    "squared_range",
    "plain_range",
    "observe_range",
    "gyro",
    "ranges_to",
    "uniform_variance",
    "squared_range_variance",
    "measurement_variance",
    "sample_noise",
    "valid_ranges",
    "check_model",
]

MODELS = ("squared", "range")


class UwbNoise(NamedTuple):
    """Simulated sensor noise (paper 003 Sec. IV).

    range_half_width: () m, maximum deviation a_r of the range noise (uniform on [−a_r, a_r]).
    gyro_half_width: () rad/s, maximum deviation a_g of each gyro-rate noise.
    The Gaussian alternative has the same variance, σ² = a²/3.
    """

    range_half_width: float = 0.2
    gyro_half_width: float = 0.002


PAPER003_NOISE = UwbNoise()


def check_model(model: str) -> str:
    """Host-side check of an observation-model name ('squared' or 'range')."""
    if model not in MODELS:
        raise InputError(f"model: expected one of {MODELS}, got {model!r}")
    return model


def _pair(p, l):
    """Tag and anchor positions of one shape, (d,) (static check: a transposed (2, 1) anchor
    broadcast against a (2,) tag and gave a wrong range), as real arrays of their common
    floating dtype: integers become JAX's default float (an int32 squared range overflowed:
    40000² + 40000² read −1094967296), complex or non-numbers are an InputError naming the
    argument."""
    ps, ls = np.shape(p), np.shape(l)
    if len(ps) != 1 or ps != ls:
        raise InputError(f"p and l: expected one position each, both of shape (d,), got {tuple(ps)} "
                         f"and {tuple(ls)}")
    p, l = real_float(p, "p"), real_float(l, "l")
    dt = jnp.result_type(p, l)
    return p.astype(dt), l.astype(dt)


def squared_range(p, l):
    """Squared distance d² = (l_x − x)² + (l_y − y)² (paper 003 eq. 17).

    p: (2,) tag position [m]; l: (2,) anchor position [m].  Returns () [m²].
    """
    p, l = _pair(p, l)
    d = l - p
    return jnp.sum(d * d)


def plain_range(p, l):
    """Distance d = ‖l − p‖ (paper 003 eq. 16); Jacobian 0 (not NaN) at d = 0.

    p: (2,) tag position [m]; l: (2,) anchor position [m].  Returns () [m].
    """
    p, l = _pair(p, l)
    return safe_norm(l - p)


def observe_range(p, l, model: str):
    """Eq. 17 (``model="squared"``) or eq. 16 (``"range"``) as a (1,) measurement vector."""
    if model == "squared":
        return squared_range(p, l)[None]
    if model == "range":
        return plain_range(p, l)[None]
    raise InputError(f"model: expected one of {MODELS}, got {model!r}")


def gyro(rates):
    """Gyro observation Ω = [w_α, w_β, w_θ] (paper 003 eq. 19).  rates (3,) rad/s -> (3,)."""
    return rates


def ranges_to(p, anchors):
    """True distances from a tag at p (2,) to anchors (N, 2): (N,) [m] (eq. 16 for each)."""
    if np.ndim(anchors) != 2:
        raise InputError(f"anchors: expected shape (N, d), got {np.shape(anchors)}")
    anchors = real_float(anchors, "anchors")  # a list of anchors failed inside vmap
    return jax.vmap(lambda l: plain_range(p, l))(anchors)


def _check_nonneg(v, name):
    """InputError naming ``name`` when a concrete (not traced) ``v`` holds a negative or NaN entry:
    a negative variance or half-width would give a plausible-looking wrong variance or noise."""
    if is_concrete(v) and not np.all(check_numbers(v, name) >= 0):
        raise InputError(f"{name}: must be >= 0, got {v!r}")


def uniform_variance(half_width):
    """Variance a²/3 of the uniform distribution on [−a, a]."""
    _check_nonneg(half_width, "half_width")
    return half_width * half_width / 3.0


def squared_range_variance(d, range_var):
    """Variance of a squared measured range (d + δ)², δ ~ (0, σ²): 4d²σ² + 2σ⁴ [m⁴].

    d: distance [m] (any shape); range_var: σ² [m²].  First-order in δ plus the
    Gaussian fourth moment; see the module docstring.
    """
    _check_nonneg(range_var, "range_var")
    return 4.0 * d * d * range_var + 2.0 * range_var * range_var


def measurement_variance(d, range_var, model: str):
    """Variance of one UWB measurement of ``model`` at distance d [m]: m⁴ ('squared') or m² ('range')."""
    if model == "squared":
        return squared_range_variance(d, range_var)
    if model == "range":
        # as "squared" does: a negative or NaN variance is refused when known
        _check_nonneg(range_var, "range_var")
        check_real(d, "d")
        dt = jnp.result_type(d)  # an integer distance used to cast the variance to int (0.04 -> 0)
        dt = dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)
        return jnp.broadcast_to(jnp.asarray(range_var, dt), jnp.shape(d))
    raise InputError(f"model: expected one of {MODELS}, got {model!r}")


def sample_noise(key, shape, half_width, dist: str, dtype=None):
    """Zero-mean noise of variance a²/3: uniform on [−a, a] (paper 003 Sec. IV) or Gaussian.

    key: PRNG key; shape: output shape; half_width: a (scalar, traced); dist:
    ``"uniform"`` or ``"gaussian"`` (static).  Returns an array of ``dtype`` (a floating dtype;
    default JAX's default float: float64 was asked for, and truncated with a warning, without
    x64).
    """
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)
    _check_nonneg(half_width, "half_width")
    a = jnp.asarray(half_width, dtype)
    if dist == "uniform":
        return jax.random.uniform(key, shape, dtype, minval=-1.0, maxval=1.0) * a
    if dist == "gaussian":
        return jax.random.normal(key, shape, dtype) * (a / math.sqrt(3.0))
    raise InputError(f"noise: expected 'uniform' or 'gaussian', got {dist!r}")


def valid_ranges(z):
    """Which ranges are measurements: finite and > 0 (any shape, bool)."""
    check_real(z, "z")
    zs = jnp.where(jnp.isfinite(z), z, 0.0)
    return jnp.isfinite(z) & (zs > 0)
