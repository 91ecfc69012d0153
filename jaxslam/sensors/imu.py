"""Inertial measurement unit: ideal readings, white noise, constant bias and Gauss-Markov drift.

Paper 000 (EKF-SLAM + DF-LQR), eq. 25 and Table 5; paper 001 (modified FastSLAM), eq. 5-12.

Frames and state: NED inertial frame N (n̂3 points down, gravity is +g n̂3), body frame B
(b̂3 down), 12-state ``x = [ρ_N (3), v_B (3), Λ = (φ, θ, ψ) (3), ω_B (3)]`` of paper 000
eq. 2 and its time derivative ``xdot`` (same layout).  ``C_NB`` is the 3-2-1 direction cosine
matrix of paper 000 eq. 1 (``jaxslam.geometry.euler.dcm_from_euler``).  IMU readings are
ordered ``[accel (3) m/s², gyro (3) rad/s]`` in the body frame.

Decisions where the papers are silent or wrong (also in docs/papers.md):

* **Accelerometer = specific force.**  Paper 000 eq. 25 feeds only a_z = −f_T/m; paper 001
  eq. 7 uses the kinematic acceleration R_bᵂᵀ a_w without gravity.  A real accelerometer
  measures the specific force f_B = C_NBᵀ(a_N − g n̂3).  For paper 000's rigid, drag-free
  model f_B = [0, 0, −f_T/m], so the 3-axis form contains eq. 25 (its third component) and
  stays right when drag or other body forces act.  :func:`kinematic_accel` keeps paper 001's
  form (``mode="kinematic"``) for reproduction.
* **Inertial acceleration from the state.**  With ρ̇ = C_NB v_B (eq. 2),
  a_N = ρ̈ = C_NB (v̇_B + ω_B × v_B).  Hence f_B = v̇_B + ω_B × v_B − g C_NBᵀ n̂3; the last
  term is the third row of C_NB, so no matrix product is needed.
* **Discrete white noise.**  Table 5 gives noise densities ND.  A sample that averages white
  noise of two-sided density ND² over one sample interval 1/rate has σ = ND·√rate; that is the
  σ used here (:func:`white_noise_sigma`).  Table 5's "300 µg/rtHz²" is read as 300 µg/√Hz
  with 1 g = 9.81 m/s².
* **Bias + drift (paper 001 eq. 5-10).**  Per axis, offset = b0 + b1 where b0 is constant
  (ḃ0 = 0) and b1 is a first-order Gauss-Markov process ḃ1 = −b1/τ + w, with w white of
  spectral density ``drift_density``² (units of the reading per s per √Hz).  jaxslam
  propagates it with the exact discretisation
  b1[k+1] = e^{−Δt/τ} b1[k] + w_k, Var w_k = σ_w² τ/2 (1 − e^{−2Δt/τ}),
  which is exact for any Δt and gives the stationary variance σ_w² τ/2 and autocorrelation
  σ_w² τ/2 · e^{−|lag|/τ}.  τ = ∞ gives a random walk (Var w_k = σ_w² Δt).  Paper 001 eq. 11
  uses the Euler form a = 1 − T/τ, Q = T² σ_b1²; it is available as
  ``drift_transition(..., method="euler")`` with σ_b1² = σ_w²/T (so Q = σ_w² T).
* **Paper 001 values.**  Paper 001 gives only the constant biases (0.0005 or 0.005 on every
  axis, m/s² and rad/s) and T = 0.01 s.  It gives neither white-noise levels nor τ nor the
  drift noise.  :func:`PAPER001_IMU` takes rate 100 Hz (T = 0.01 s), paper 000's Table 5
  noise densities, τ = 100 s and a drift whose stationary standard deviation is 10 % of the
  bias (σ_w = 0.1·bias·√(2/τ)); all are keyword arguments.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import as_scalar, check_last_dim, real_float
from ..compilation import call_compiled
from ..errors import InputError
from ..geometry.euler import dcm_from_euler
from ..linalg import check_float_dtype, check_int, check_key, check_numbers, check_real, check_scalar, is_concrete, list_array

__all__ = [
    "G_IMU",
    "ImuSpec",
    "PAPER000_IMU",
    "PAPER001_IMU",
    "check_imu_spec",
    "specific_force",
    "kinematic_accel",
    "imu_ideal",
    "white_noise_sigma",
    "white_noise_cov",
    "sample_white_noise",
    "BiasDriftState",
    "drift_stationary_sigma",
    "drift_transition",
    "bias_drift_init",
    "bias_drift_step",
    "bias_drift_rollout",
    "corrupt",
]

G_IMU = 9.81
"""Gravity [m/s²] used only to convert Table 5's µg density into m/s²."""

_MODES = ("specific_force", "kinematic")


class ImuSpec(NamedTuple):
    """IMU noise, bias and drift parameters (paper 000 Table 5; paper 001 eq. 5-10).

    Every field may be a Python float or an array (so ``grad`` w.r.t. them works).
    Bias and drift fields broadcast to (6,) = [accel x, y, z, gyro x, y, z].
    """

    accel_noise_density: Any = 300e-6 * G_IMU
    """Accelerometer white-noise density ND_a [m/s²/√Hz]; scalar or (3,). Table 5: 300 µg/√Hz."""
    gyro_noise_density: Any = math.radians(0.01)
    """Gyroscope white-noise density ND_g [rad/s/√Hz]; scalar or (3,). Table 5: 0.01 °/s/√Hz."""
    rate: Any = 10.0
    """Sampling rate [Hz]. Table 5: 10 Hz."""
    bias: Any = 0.0
    """Constant offset b0 (eq. 5, 9) [m/s² ×3, rad/s ×3]; scalar or (6,)."""
    bias_sigma: Any = 0.0
    """Std of a random turn-on part of b0 drawn by :func:`bias_drift_init`; scalar or (6,)."""
    drift_tau: Any = math.inf
    """Gauss-Markov time constant τ of b1 (eq. 8, 10) [s]; scalar or (6,); ∞ = random walk."""
    drift_density: Any = 0.0
    """Spectral density σ_w of the drift driving noise (eq. 8, 10) [unit/s/√Hz]; scalar or (6,)."""


PAPER000_IMU = ImuSpec()
"""Paper 000 Table 5: 300 µg/√Hz, 0.01 °/s/√Hz, 10 Hz; no bias or drift."""


def PAPER001_IMU(bias: float = 0.0005, *, rate: float = 100.0, drift_tau: float = 100.0,
                 drift_fraction: float = 0.1,
                 accel_noise_density: float = 300e-6 * G_IMU,
                 gyro_noise_density: float = math.radians(0.01)) -> ImuSpec:
    """IMU preset of paper 001 (Sec. IV-B: bias 0.0005 or 0.005 m/s² and rad/s on every axis).

    Paper 001 gives only ``bias`` and T = 0.01 s (``rate`` = 100 Hz).  The rest are jaxslam
    choices (module docstring): paper 000's noise densities, τ = ``drift_tau`` [s], and a
    drift with stationary standard deviation ``drift_fraction``·|bias|.

    Returns an :class:`ImuSpec`.  Raises :class:`~jaxslam.errors.InputError` on a non-finite
    bias or non-positive rate, τ, or a negative fraction, and on a bool argument.
    """
    for name, v in (("bias", bias), ("rate", rate), ("drift_tau", drift_tau), ("drift_fraction", drift_fraction),
                    ("accel_noise_density", accel_noise_density), ("gyro_noise_density", gyro_noise_density)):
        check_real(v, name, allow_bool=False)  # True was read as 1
    bias = check_scalar(bias, "bias")
    rate = check_scalar(rate, "rate", lower=0, strict=True)
    drift_tau = check_scalar(drift_tau, "drift_tau", finite=False, lower=0, strict=True)
    drift_fraction = check_scalar(drift_fraction, "drift_fraction", lower=0)
    accel_noise_density = check_scalar(accel_noise_density, "accel_noise_density", lower=0)
    gyro_noise_density = check_scalar(gyro_noise_density, "gyro_noise_density", lower=0)
    drift_sigma = drift_fraction * abs(bias)
    density = drift_sigma * math.sqrt(2.0 / drift_tau) if math.isfinite(drift_tau) else 0.0
    return ImuSpec(accel_noise_density=float(accel_noise_density),
                   gyro_noise_density=float(gyro_noise_density), rate=float(rate),
                   bias=bias, bias_sigma=0.0, drift_tau=float(drift_tau),
                   drift_density=density)


def check_imu_spec(spec: ImuSpec, name: str = "spec") -> ImuSpec:
    """Host-side validation of an :class:`ImuSpec` (call before jit).

    Raises :class:`~jaxslam.errors.InputError` naming the field when a density, σ or τ is
    negative / non-positive, the rate is not positive, or a field does not broadcast to its
    shape ((3,) for densities, (6,) for bias/drift fields), or is a bool (``rate=True`` was
    read as 1 Hz).
    """
    if not isinstance(spec, ImuSpec):
        raise InputError(f"{name}: expected an ImuSpec, got {type(spec).__name__}")
    rules = {
        "accel_noise_density": ((3,), "nonneg"),
        "gyro_noise_density": ((3,), "nonneg"),
        "rate": ((), "pos"),
        "bias": ((6,), "finite"),
        "bias_sigma": ((6,), "nonneg"),
        "drift_tau": ((6,), "pos_or_inf"),
        "drift_density": ((6,), "nonneg"),
    }
    for field, (shape, rule) in rules.items():
        check_real(getattr(spec, field), f"{name}.{field}", allow_bool=False)
        val = check_numbers(getattr(spec, field), f"{name}.{field}")
        try:
            np.broadcast_to(val, shape)
        except ValueError:
            raise InputError(f"{name}.{field}: shape {val.shape} does not broadcast to {shape}")
        if rule == "pos_or_inf":
            ok = np.all(val > 0) and not np.any(np.isnan(val))
        elif rule == "pos":
            ok = np.all(val > 0) and np.all(np.isfinite(val))
        elif rule == "nonneg":
            ok = np.all(val >= 0) and np.all(np.isfinite(val))
        else:
            ok = np.all(np.isfinite(val))
        if not ok:
            raise InputError(f"{name}.{field}: invalid value {val} (rule: {rule})")
    return spec


# ---------------------------------------------------------------------------
# Ideal readings
# ---------------------------------------------------------------------------

def _check_x_xdot(x, xdot):
    """``x`` and ``xdot`` as real floating (12,) arrays: an integer state becomes JAX's default
    float (it used to cast g to int: 9.81 read as 9), a complex one is refused, a list is
    converted; a float dtype is kept."""
    return real_float(x, "x", (12,)), real_float(xdot, "xdot", (12,))


def kinematic_accel(x, xdot):
    """Body-frame kinematic acceleration a_B = C_NBᵀ a_N, without gravity (paper 001 eq. 7).

    Args:
      x: (12,) state [ρ_N m, v_B m/s, Λ rad, ω_B rad/s] (paper 000 eq. 2).
      xdot: (12,) its time derivative; only v̇_B = xdot[3:6] is read.

    Returns:
      (3,) a_B = v̇_B + ω_B × v_B [m/s²] (equal to C_NBᵀ ρ̈_N because ρ̇ = C_NB v_B).
      Zero in hover: paper 001's accelerometer form, kept for reproduction.
    """
    x, xdot = _check_x_xdot(x, xdot)
    v = x[3:6]
    w = x[9:12]
    return xdot[3:6] + jnp.cross(w, v)


def specific_force(x, xdot, g):
    """Body-frame specific force f_B = C_NBᵀ(a_N − g n̂3) (paper 000 eq. 2, 25; NED).

    Args:
      x: (12,) state [ρ_N m, v_B m/s, Λ = (φ, θ, ψ) rad, ω_B rad/s] (paper 000 eq. 2).
      xdot: (12,) its time derivative; v̇_B = xdot[3:6] is read.
      g: gravity [m/s²] (scalar), acting along +n̂3 (down).

    Returns:
      (3,) f_B [m/s²].  Hover gives [0, 0, −g]; under eq. 2 without drag it equals
      [0, 0, −f_T/m], whose third entry is eq. 25's ã_z.

    Raises :class:`~jaxslam.errors.InputError` when ``g`` is not one real number (a (3,) gravity
    vector was applied elementwise to the third row of C_NB) or, when known, not finite.
    """
    x, xdot = _check_x_xdot(x, xdot)
    a_b = kinematic_accel(x, xdot)
    C = dcm_from_euler(x[6:9])
    g = _gravity(g, a_b.dtype)
    # C_NBᵀ n̂3 is the third row of C_NB.
    return a_b - g * C[2, :]


def _gravity(g, dtype):
    """Scalar gravity ``g`` as an array of ``dtype`` (:func:`~jaxslam.dynamics._checks.as_scalar`:
    one real number); a concrete non-finite value is an InputError naming ``g``."""
    if np.ndim(g) != 0:
        raise InputError(f"g: expected a scalar gravity [m/s²] along +n3, got shape {np.shape(g)}")
    out = as_scalar(g, dtype, "g")
    if is_concrete(g) and not np.isfinite(np.asarray(g, float)):  # (the value as given: no device copy back)
        raise InputError(f"g: expected a finite gravity [m/s²], got {g!r}")
    return out


def imu_ideal(x, xdot, g, mode: str = "specific_force"):
    """Noise-free IMU reading [accel (3), gyro (3)] in the body frame.

    Paper 000 eq. 25 (3-axis form, see module docstring); paper 001 eq. 5, 7, 9 without the
    bias, drift and noise terms.

    Args:
      x: (12,) state (paper 000 eq. 2).  xdot: (12,) its time derivative.
      g: gravity [m/s²] along +n̂3.
      mode: ``"specific_force"`` (default, real accelerometer) or ``"kinematic"``
        (paper 001 eq. 7, no gravity).  Static (Python) argument.

    Returns:
      (6,) [accel m/s², ω_B rad/s].
    """
    if mode not in _MODES:
        raise InputError(f"mode: expected one of {_MODES}, got {mode!r}")
    x, xdot = _check_x_xdot(x, xdot)
    if mode == "specific_force":
        acc = specific_force(x, xdot, g)
    else:
        acc = kinematic_accel(x, xdot)
    return jnp.concatenate([acc, x[9:12].astype(acc.dtype)])


# ---------------------------------------------------------------------------
# White noise
# ---------------------------------------------------------------------------

def _spec(spec: ImuSpec) -> ImuSpec:
    """``spec`` checked by :func:`check_imu_spec` when its fields are concrete (a negative density
    gave a negative σ, a negative τ an unstable drift); traced fields (a tuned density) pass."""
    if not isinstance(spec, ImuSpec) or is_concrete(tuple(spec)):
        check_imu_spec(spec)
    return spec


def white_noise_sigma(spec: ImuSpec):
    """Discrete white-noise standard deviations σ = ND·√rate (paper 000 Table 5).

    Returns:
      (sigma_accel [m/s²], sigma_gyro [rad/s]), each broadcast to (3,).
      σ = ND·√rate is the std of white noise of two-sided density ND² averaged over one sample
      interval 1/rate (module docstring).
    """
    spec = _spec(spec)
    root_rate = jnp.sqrt(jnp.asarray(spec.rate))
    sa = jnp.broadcast_to(jnp.asarray(spec.accel_noise_density) * root_rate, (3,))
    sg = jnp.broadcast_to(jnp.asarray(spec.gyro_noise_density) * root_rate, (3,))
    return sa, sg


def _sigma6(spec: ImuSpec, dtype):
    sa, sg = white_noise_sigma(spec)
    return jnp.concatenate([sa, sg]).astype(dtype)


def _default_dtype(dtype):
    """``dtype`` (default: JAX's default float); a non-floating one is an InputError naming
    ``dtype`` (an int32 covariance of σ² ≈ 1e-5 read as all zeros)."""
    return jnp.result_type(float) if dtype is None else check_float_dtype(dtype)


def _shape_prefix(shape_prefix) -> tuple:
    """``shape_prefix`` as a tuple of ints >= 0; anything else is an :class:`InputError` naming
    ``shape_prefix`` (a 2.7 used to be truncated to 2, a -1 failed inside XLA)."""
    if not (isinstance(shape_prefix, (tuple, list))
            or (isinstance(shape_prefix, np.ndarray) and shape_prefix.ndim == 1)):  # np.array([3]) too
        raise InputError(f"shape_prefix: expected a tuple of ints, got {shape_prefix!r}"[:300])
    return tuple(check_int(d, "shape_prefix", lower=0, what="ints") for d in shape_prefix)


def _std_normal(key, shape, dtype):
    """N(0, 1) of ``shape`` drawn flat and reshaped.

    With the default (threefry, partitionable) keys, XLA on CPU compiled a direct
    ``normal(key, (N, 6))`` 3-7× slower than a flat draw of the same size (measured 4.2 s vs
    1.2 s for 6·10⁵ samples); the samples have the same distribution either way.
    """
    shape = tuple(int(d) for d in shape)
    size = int(np.prod(shape, dtype=np.int64)) if shape else 1
    return jax.random.normal(key, (size,), dtype).reshape(shape)


def white_noise_cov(spec: ImuSpec, dtype=None):
    """(6, 6) covariance diag(σ_a², σ_a², σ_a², σ_g², σ_g², σ_g²) of one IMU sample.

    The R^I of paper 001 eq. 12 and R_η of paper 000 eq. 25 (3-axis accel form).
    """
    s = _sigma6(spec, _default_dtype(dtype))
    return jnp.diag(s * s)


def sample_white_noise(key, spec: ImuSpec, shape_prefix=(), dtype=None):
    """Draw IMU white noise v^I (paper 001 eq. 12; paper 000 eq. 25 η).

    Args:
      key: PRNG key.  spec: :class:`ImuSpec`.
      shape_prefix: leading shape (static tuple of ints >= 0), e.g. ``(T,)`` for a whole run.
      dtype: floating dtype (default: JAX's default float).

    Returns:
      (*shape_prefix, 6) zero-mean Gaussian, std :func:`white_noise_sigma` per axis.
    """
    check_key(key)  # an int seed was JAX's bare "invalid PRNG key data" TypeError
    dtype = _default_dtype(dtype)
    shape = _shape_prefix(shape_prefix) + (6,)
    return _std_normal(key, shape, dtype) * _sigma6(spec, dtype)


# ---------------------------------------------------------------------------
# Bias + drift (paper 001 eq. 5-12)
# ---------------------------------------------------------------------------

class BiasDriftState(NamedTuple):
    """Current sensor offset of paper 001 eq. 5, 9 (order [accel (3), gyro (3)])."""

    bias: Any
    """(6,) constant offset b0 = [b0a, b0ω] [m/s², rad/s]."""
    drift: Any
    """(6,) Gauss-Markov drift b1 = [b1a, b1ω] [m/s², rad/s]."""


def _b6(v, dtype):
    return jnp.broadcast_to(jnp.asarray(v, dtype=dtype), (6,))


def drift_stationary_sigma(spec: ImuSpec, dtype=None):
    """(6,) stationary std of b1: σ_w·√(τ/2) (paper 001 eq. 8, 10); ∞ where τ = ∞ and σ_w > 0."""
    spec = _spec(spec)  # a negative τ gave NaN, which bias_drift_init read as no drift
    dtype = _default_dtype(dtype)
    tau = _b6(spec.drift_tau, dtype)
    dens = _b6(spec.drift_density, dtype)
    return jnp.where(dens > 0, dens * jnp.sqrt(tau / 2), jnp.zeros_like(dens))


def drift_transition(spec: ImuSpec, dt, method: str = "exact", dtype=None):
    """Per-axis discrete drift model b1[k+1] = a·b1[k] + w_k, Var w_k = q (paper 001 eq. 11).

    Args:
      spec: :class:`ImuSpec`.  dt: step [s], one finite real number >= 0.
      method: ``"exact"`` (default): a = e^{−Δt/τ}, q = σ_w² τ/2 (1 − e^{−2Δt/τ}), exact for
        any Δt (→ random walk a = 1, q = σ_w² Δt as τ → ∞).  ``"euler"``: paper 001 eq. 11,
        a = 1 − Δt/τ, q = σ_w² Δt (= T² σ_b1² with σ_b1² = σ_w²/T).  Static argument.
      dtype: output dtype (default: that of ``dt`` if it is a floating array, else JAX's
        default float).

    Returns:
      (a (6,), q (6,)): the diagonal drift blocks of A^b and Q^b of eq. 11 (the constant-bias
      blocks are 1 and 0).
    """
    if method not in ("exact", "euler"):
        raise InputError(f"method: expected 'exact' or 'euler', got {method!r}")
    a, q, _ = _drift(spec, dt, method, dtype)
    return a, q


def _drift(spec: ImuSpec, dt, method: str, dtype):
    """:func:`drift_transition`'s ``(a, q)`` and the driving-noise std ``√q``.

    ``√q`` is ``jnp.sqrt(q)`` wherever q > 0; where q = 0 (no drift noise: σ_w = 0, the
    default) it is |σ_w|·√(Δt·ratio), the same value, whose derivative in σ_w is finite
    (``sqrt``'s is infinite at 0, so ``grad`` w.r.t. ``drift_density`` at 0 was NaN).
    """
    spec = _spec(spec)
    check_real(dt, "dt", allow_bool=False)  # True was read as a 1 s step
    kind = np.dtype(dt.dtype).kind if hasattr(dt, "dtype") else None
    bad = np.ndim(dt) != 0 or (kind is not None and kind not in "iuf") or (
        kind is None and not isinstance(dt, numbers.Real))  # a string "0.01" was parsed
    # NaN included; an infinite step gave q = ∞·0 = NaN
    if bad or (is_concrete(dt) and not 0 <= float(np.asarray(dt)) < math.inf):
        raise InputError(f"dt: expected a step >= 0 [s] (a scalar), got {dt!r}")
    if dtype is None:
        dtype = dt.dtype if (hasattr(dt, "dtype") and jnp.issubdtype(dt.dtype, jnp.floating)) \
            else _default_dtype(None)
    else:
        dtype = _default_dtype(dtype)  # an int dtype truncated dt, τ and σ_w
    dt = jnp.asarray(dt, dtype=dtype)
    tau = _b6(spec.drift_tau, dtype)
    dens = _b6(spec.drift_density, dtype)
    x = dt / tau  # 0 where τ = ∞
    if method == "euler":
        q = dens * dens * dt
        ratio = jnp.ones_like(x)
        a = 1.0 - x
    else:
        a = jnp.exp(-x)
        # (1 − e^{−2x})/(2x) → 1 as x → 0; expm1 keeps it accurate for Δt ≪ τ.
        two_x = 2.0 * x
        safe = jnp.where(two_x > 0, two_x, 1.0)
        ratio = jnp.where(two_x > 0, -jnp.expm1(-safe) / safe, 1.0)
        q = dens * dens * dt * ratio
    pos = q > 0
    root = jnp.where(pos, jnp.sqrt(jnp.where(pos, q, 1.0)), jnp.abs(dens) * jnp.sqrt(dt * ratio))
    return a, q, root


def _drift_state(state) -> BiasDriftState:
    """``state`` with real floating (..., 6) fields (a list or an int state is converted; a
    complex or a (5,) one is an InputError naming the field)."""
    if not isinstance(state, BiasDriftState):
        raise InputError(f"state: expected a BiasDriftState, got {type(state).__name__}")
    bias = check_last_dim(real_float(state.bias, "state.bias"), 6, "state.bias")
    drift = check_last_dim(real_float(state.drift, "state.drift"), 6, "state.drift")
    return BiasDriftState(bias=bias, drift=drift)


def bias_drift_init(key, spec: ImuSpec, dtype=None, stationary: bool = True, shape_prefix=()):
    """Initial offset state (paper 001 eq. 5, 9).

    b0 = ``spec.bias`` + ``spec.bias_sigma``·N(0, 1) (turn-on bias; deterministic when
    bias_sigma = 0, as in paper 001).  b1 ~ N(0, σ_ss²) from the stationary distribution when
    ``stationary`` and τ is finite, else 0.

    Args:
      key: PRNG key.  spec: :class:`ImuSpec`.  dtype: float dtype (default JAX's default).
      stationary: draw b1 from its stationary law (static).
      shape_prefix: static leading shape (tuple of ints >= 0), e.g. ``(runs,)`` for independent Monte Carlo runs.

    Returns a :class:`BiasDriftState` of (*shape_prefix, 6) arrays of ``dtype``.
    """
    spec = _spec(spec)  # a NaN bias or a (7,) one passed (or failed with a bare broadcast error)
    check_key(key)
    dtype = _default_dtype(dtype)
    shape = _shape_prefix(shape_prefix) + (6,)
    kb, kd = jax.random.split(key)
    bias = _b6(spec.bias, dtype) + _b6(spec.bias_sigma, dtype) * _std_normal(kb, shape, dtype)
    if stationary:
        sig = drift_stationary_sigma(spec, dtype)
        sig = jnp.where(jnp.isfinite(sig), sig, jnp.zeros_like(sig))
        drift = sig * _std_normal(kd, shape, dtype)
    else:
        drift = jnp.zeros(shape, dtype)
    return BiasDriftState(bias=bias, drift=drift)


def bias_drift_step(key, state: BiasDriftState, spec: ImuSpec, dt):
    """Advance the offset by Δt with the exact Gauss-Markov discretisation (paper 001 eq. 8, 10).

    b0 is constant; b1[k+1] = e^{−Δt/τ} b1[k] + √q ξ, ξ ~ N(0, I) (:func:`drift_transition`).

    Args:
      key: PRNG key.  state: :class:`BiasDriftState` with (..., 6) fields.
      spec: :class:`ImuSpec`.  dt: step [s].

    Returns the new :class:`BiasDriftState` (same shape and dtype as ``state.drift``).
    """
    check_key(key)
    state = _drift_state(state)
    dtype = state.drift.dtype
    a, _, sq = _drift(spec, dt, "exact", dtype)
    drift = a * state.drift + sq * _std_normal(key, state.drift.shape, dtype)
    return BiasDriftState(bias=state.bias, drift=drift)


def bias_drift_rollout(key, state: BiasDriftState, spec: ImuSpec, dt, n_steps: int):
    """Offset sequence for ``n_steps`` IMU samples in one ``lax.scan`` (paper 001 eq. 8-11).

    Same law as iterating :func:`bias_drift_step` (exact discretisation), with all driving
    noise drawn up front from ``key``.

    Args:
      key: PRNG key.  state: :class:`BiasDriftState` with (..., 6) fields (a leading batch
        shape runs independent chains).  spec: :class:`ImuSpec`.  dt: step [s].
      n_steps: number of samples (static, >= 1).

    Returns a :class:`BiasDriftState` of (n_steps, ..., 6) arrays whose row k is the offset
    at sample k; row 0 is ``state`` itself.  Called eagerly it is compiled once per
    ``n_steps`` (:func:`jaxslam.compilation.call_compiled`; uncompiled, each call traced and
    compiled its scan again: 40 ms a call, the program kept).
    """
    n_steps = check_int(n_steps, "n_steps")  # 2.7 used to run 2 steps
    check_key(key)
    state = _drift_state(state)
    a, _, sq = _drift(spec, dt, "exact", state.drift.dtype)
    return call_compiled(("imu.bias_drift_rollout", n_steps),
                         lambda key, state, a, sq: _drift_rollout(key, state, a, sq, n_steps), (key, state, a, sq),
                         after="auto")


def _drift_rollout(key, state: BiasDriftState, a, sq, n_steps: int) -> BiasDriftState:
    """:func:`bias_drift_rollout`'s draws and scan, with the step's factors ``a``, ``sq``."""
    dtype = state.drift.dtype
    xi = _std_normal(key, (n_steps - 1,) + tuple(state.drift.shape), dtype)

    def body(d, x):
        d = a * d + sq * x
        return d, d

    _, rest = jax.lax.scan(body, state.drift, xi)
    drift = jnp.concatenate([state.drift[None], rest], axis=0)
    bias = jnp.broadcast_to(state.bias, drift.shape)
    return BiasDriftState(bias=bias, drift=drift)


def corrupt(ideal, state: BiasDriftState, white):
    """Measured IMU reading z^I = ideal + b0 + b1 + v (paper 001 eq. 5, 9, 12).

    Args:
      ideal: (..., 6) :func:`imu_ideal` output.  state: :class:`BiasDriftState` with fields
        broadcastable to ``ideal``.  white: (..., 6) :func:`sample_white_noise` output.
      Lists are read as arrays.

    Returns (..., 6).
    """
    if not isinstance(state, BiasDriftState):
        raise InputError(f"state: expected a BiasDriftState, got {type(state).__name__}")
    # lists become arrays (four 6-lists used to be concatenated into a 24-list)
    ideal, white = list_array(ideal, "ideal"), list_array(white, "white")
    state = BiasDriftState(bias=list_array(state.bias, "state.bias"), drift=list_array(state.drift, "state.drift"))
    for name, v in (("ideal", ideal), ("state.bias", state.bias), ("state.drift", state.drift), ("white", white)):
        check_real(v, name)  # a complex reading kept its imaginary part
    if np.shape(ideal)[-1:] != (6,):
        raise InputError(f"ideal: expected shape (..., 6), got {np.shape(ideal)}")
    for name, v in (("state.bias", state.bias), ("state.drift", state.drift), ("white", white)):
        try:
            ok = np.broadcast_shapes(np.shape(v), np.shape(ideal)) == np.shape(ideal)
        except ValueError:
            ok = False
        if not ok:
            raise InputError(f"{name}: shape {np.shape(v)} does not broadcast to ideal's {np.shape(ideal)}")
    return ideal + state.bias + state.drift + white
