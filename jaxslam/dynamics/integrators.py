"""Fixed-step integration and linearisation of ẋ = f(x, u, *args).

Paper 000 integrates eq. 2 (and eq. 26-29 of the filter) "through the time
step" without naming a scheme; jaxslam uses the classical 4th-order
Runge-Kutta method with the input held constant over the step (zero-order
hold).  Callers that need a first-order hold on u (interpolated IMU samples,
see STYLE.md) pass a function of x that closes over the interpolation.

``rollout`` runs a whole input sequence in one ``lax.scan`` (no Python loop,
one compilation); ``linearize`` returns the continuous-time Jacobians
A = ∂f/∂x, B = ∂f/∂u by ``jax.jacfwd`` (forward mode: n is small).

All functions are pure and jit/vmap/grad-safe; ``f``'s extra ``*args``
(e.g. parameters) may be traced arrays.  ``dt`` is cast to the dtype of the
state so float32 runs stay float32.  ``check_dt`` is the host-side validator.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError

__all__ = ["rk4_step", "rollout", "linearize", "check_dt"]


def rk4_step(f, x, u, dt, *args):
    """One classical RK4 step of ẋ = f(x, u, *args) with u held over [t, t+dt].

    ``x``: (n,); ``u``: (m,); ``dt``: scalar step, s.  Returns x(t + dt) (n,)
    in the dtype of ``x``.  Local error O(dt⁵), global O(dt⁴).
    """
    x = jnp.asarray(x)
    h = jnp.asarray(dt, dtype=x.dtype)
    k1 = f(x, u, *args)
    k2 = f(x + 0.5 * h * k1, u, *args)
    k3 = f(x + 0.5 * h * k2, u, *args)
    k4 = f(x + h * k3, u, *args)
    return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rollout(f, x0, us, dt, *args):
    """Integrate an input sequence with RK4 in one ``lax.scan``.

    ``x0``: (n,) initial state; ``us``: (T, m) inputs, ``us[k]`` held over
    step k; ``dt``: scalar step, s.  Returns xs (T + 1, n) with xs[0] = x0.
    """
    x0 = jnp.asarray(x0)

    def body(x, u):
        xn = rk4_step(f, x, u, dt, *args)
        return xn, xn

    _, xs = jax.lax.scan(body, x0, jnp.asarray(us))
    return jnp.concatenate([x0[None], xs], axis=0)


def linearize(f, x, u, *args):
    """Continuous-time Jacobians (A, B) = (∂f/∂x, ∂f/∂u) at (x, u) by jacfwd.

    ``x``: (n,), ``u``: (m,).  Returns A (n, n), B (n, m).  Paper 000 eq. 28
    (F = ∂f_s/∂s) uses this on the filter model.
    """
    return jax.jacfwd(f, argnums=(0, 1))(x, u, *args)


def check_dt(dt, name="dt"):
    """Host-side check that ``dt`` is a finite positive scalar; returns it.

    Raises :class:`~jaxslam.errors.InputError` naming ``name``.
    """
    a = np.asarray(dt)
    if a.shape != ():
        raise InputError(f"{name}: expected a scalar, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"{name}: expected a real number, got dtype {a.dtype}")
    if not np.isfinite(a) or a <= 0:
        raise InputError(f"{name}: must be a finite positive time step, got {a.item()}")
    return dt
