"""Status bit flags returned inside jitted state, and host-side decoding.

Inside ``jit`` nothing raises: failures are OR-ed into an ``int32`` status word
carried in the returned state (the optax / diffrax habit).  On the host,
:func:`decode` turns a status word into names and :func:`check` raises.

Input validation at the public Python boundary (before ``jit``) raises
:class:`InputError` with a message that names the offending argument.
"""

from __future__ import annotations

import operator

import numpy as np

__all__ = [
    "OK",
    "CAPACITY_OVERFLOW",
    "NON_FINITE",
    "GATED",
    "DEGENERATE",
    "MASKED_INPUT",
    "NOT_PSD",
    "DIVERGED",
    "NOT_CONVERGED",
    "FLAG_NAMES",
    "InputError",
    "check_int",
    "check_flag",
    "has_bool",
    "check_run_dtype",
    "decode",
    "check",
]

OK = 0
CAPACITY_OVERFLOW = 1 << 0  # a landmark could not be registered: no free slot
NON_FINITE = 1 << 1  # a NaN/Inf appeared in a mean or covariance
GATED = 1 << 2  # at least one measurement was rejected by the Mahalanobis gate
DEGENERATE = 1 << 3  # a degenerate geometry (e.g. collinear trilateration) was met
MASKED_INPUT = 1 << 4  # a non-finite or out-of-range input measurement was masked
NOT_PSD = 1 << 5  # a covariance failed its Cholesky factorisation
DIVERGED = 1 << 6  # the run stopped being consistent: >10 % of known-landmark rows were outliers
NOT_CONVERGED = 1 << 7  # an iterated update/smoother stopped at its iteration limit before converging

FLAG_NAMES = {
    CAPACITY_OVERFLOW: "capacity_overflow",
    NON_FINITE: "non_finite",
    GATED: "gated",
    DEGENERATE: "degenerate",
    MASKED_INPUT: "masked_input",
    NOT_PSD: "not_psd",
    DIVERGED: "diverged",
    NOT_CONVERGED: "not_converged",
}


class InputError(ValueError):
    """Bad input detected at a public boundary (shape, dtype, PSD, range)."""


# The two argument checks the JAX-free layers need (the loaders, the catalogue, the runtime
# settings read before JAX starts); :mod:`jaxslam.linalg` exports them with the others.

def check_int(value, name: str, lower: int = 1, what: str = "an int") -> int:
    """``value`` as an int when it is a Python or NumPy integer ≥ ``lower`` (a bool is not a
    count); else :class:`InputError` naming ``name`` ("expected {what} >= {lower}").  Host-side,
    for sizes and counts."""
    try:  # ints, NumPy integers and 0-d integer arrays; a float, a string or a bool is not a count
        v = None if isinstance(value, (bool, np.bool_)) else operator.index(value)
    except TypeError:
        v = None
    if v is None or v < lower:
        raise InputError(f"{name}: expected {what} >= {lower}, got {value!r}"[:300])
    return int(v)


def check_flag(value, name: str) -> bool:
    """``value`` as a bool when it is ``True`` / ``False`` (NumPy's too), else :class:`InputError`
    naming ``name`` (a string "no" is truthy: a static switch given one silently stayed on)."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name}: expected True or False, got {value!r}"[:300])
    return bool(value)


def has_bool(value) -> bool:
    """True when ``value`` is a boolean, an array of booleans (NumPy's or JAX's, traced too) or a
    (nested) list / tuple holding one: JSON true / false is not a number (NumPy reads it as 1 / 0)."""
    if isinstance(value, (bool, np.bool_)):
        return True
    if isinstance(value, (list, tuple)):
        return any(has_bool(v) for v in value)
    dtype = getattr(value, "dtype", None)
    return dtype is not None and np.dtype(dtype) == np.bool_


_KNOWN = sum(FLAG_NAMES)


def _word(status) -> int:
    """``status`` (a status word, or an array of them: OR-ed together; empty: ``OK``) as an int;
    a non-integer one (a float 2.5 was truncated to ``non_finite``) is an :class:`InputError`."""
    if isinstance(status, (int, np.integer)):
        return int(status)
    a = np.asarray(status)
    if a.size == 0:
        return OK
    if a.dtype.kind not in "iu":
        raise InputError(f"status: expected an integer status word, got dtype {a.dtype}")
    return int(np.bitwise_or.reduce(a.ravel().astype(np.int64)))


def decode(status) -> list[str]:
    """Names of the flags set in a status word (host side); an array of words (a batch of
    runs) is OR-ed first, as :func:`check` does."""
    s = _word(status)
    return [name for bit, name in FLAG_NAMES.items() if s & bit]


def check(status, allow: int = GATED | MASKED_INPUT) -> None:
    """Raise ``RuntimeError`` if a status word (or any of an array of them) has a flag outside
    ``allow``; bits no flag names are reported as ``unknown bits 0x…``."""
    bad = _word(status) & ~allow
    if bad:
        names = decode(bad)
        unknown = bad & ~_KNOWN & 0xFFFFFFFF
        if unknown:
            names.append(f"unknown bits {unknown:#x}")
        raise RuntimeError(f"jaxslam status flags set: {', '.join(names)}")


def check_run_dtype(dtype, where: str = "dtype"):
    """``dtype`` as a NumPy dtype, float32 or float64 (float64 only with JAX's x64 on: it would
    compute in float32 while a report said float64), else an :class:`InputError` naming
    ``where``.  The rule of a scenario's and a dataset's run; JAX is imported only for float64."""
    want = "float32 or float64"
    try:
        dt = None if dtype is None or isinstance(dtype, bool) else np.dtype(dtype)
    except (TypeError, ValueError):
        dt = None
    if dt is None or dt not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise InputError(f"{where}: expected {want}, got {dtype!r}"[:300])
    if dt == np.float64:
        import jax

        if jax.dtypes.canonicalize_dtype(np.float64) != np.float64:
            raise InputError(f"{where}: float64 needs JAX's 64-bit mode, which is off (it would compute "
                             "in float32): call jax.config.update('jax_enable_x64', True) (or set "
                             "JAX_ENABLE_X64=1) before any JAX computation, or pass float32")
    return dt
