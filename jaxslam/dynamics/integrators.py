"""Fixed-step integration and linearisation of ẋ = f(x, u, *args).

Paper 000 integrates eq. 2 (and eq. 26-29 of the filter) "through the time
step" without naming a scheme; jaxslam uses the classical 4th-order
Runge-Kutta method with the input held constant over the step (zero-order
hold).  Callers that need a first-order hold on u (interpolated IMU samples,
see STYLE.md) pass a function of x that closes over the interpolation.

``rollout`` runs a whole input sequence in one ``lax.scan`` (no Python loop,
one compilation); ``linearize`` returns the continuous-time Jacobians
A = ∂f/∂x, B = ∂f/∂u by ``jax.jacfwd`` (forward mode: n is small).
``rk4_field`` / ``rk4_linearized`` take the vector field as ``field(x, c)``, c the
stage's fraction of the step (an input interpolated over the step closes over c);
``rk4_linearized`` also returns the step's exact Jacobian, by the chain rule through
the four stages from the field's Jacobians (autodiff or the model's own).

All functions are pure and jit/vmap/grad-safe; ``f``'s extra ``*args``
(e.g. parameters) may be traced arrays.  ``dt`` is cast to the dtype of the
state so float32 runs stay float32.  ``check_dt`` is the host-side validator.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..compilation import call_compiled
from ..errors import InputError
from ..linalg import check_int, check_real, small_matmul
from ._checks import as_scalar, real_float

__all__ = ["rk4_step", "rk4_field", "rk4_linearized", "rollout", "linearize", "check_dt"]


def rk4_step(f, x, u, dt, *args):
    """One classical RK4 step of ẋ = f(x, u, *args) with u held over [t, t+dt].

    ``x``: (n,); ``u``: (m,); ``dt``: scalar step, s.  Returns x(t + dt) (n,)
    in the dtype of ``x``.  Local error O(dt⁵), global O(dt⁴).
    """
    return rk4_field(lambda x_, c: f(x_, u, *args), x, dt)


def rk4_field(field, x, dt):
    """One classical RK4 step of ẋ = field(x, c), c ∈ {0, ½, 1} the stage's fraction of the
    step (an input held or interpolated over the step closes over c).

    ``x``: (n,); ``dt``: scalar step, s.  Returns x(t + dt) (n,) in the dtype of ``x`` (an
    integer state is promoted to JAX's default float: ``dt`` cast to an integer dtype was 0).
    """
    x = real_float(x, "x")
    h = as_scalar(dt, x.dtype, "dt")
    k1 = field(x, 0.0)
    k2 = field(x + 0.5 * h * k1, 0.5)
    k3 = field(x + 0.5 * h * k2, 0.5)
    k4 = field(x + h * k3, 1.0)
    return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rk4_linearized(field, x, dt, *, jacobian=None, skip: int = 0):
    """One RK4 step of ẋ = field(x, c) (as :func:`rk4_field`) and its Jacobian F = ∂x(t+dt)/∂x.

    F is the exact derivative of the RK4 map, formed by the chain rule through its stages from
    the field's Jacobians A_i = ∂field/∂x at the four stage points:

        K₁ = A₁,  K₂ = A₂ (I + h/2 K₁),  K₃ = A₃ (I + h/2 K₂),  K₄ = A₄ (I + h K₃),
        F = I + h/6 (K₁ + 2 K₂ + 2 K₃ + K₄).

    ``jacobian(x, c) -> (ẋ, A)``: the field and its Jacobian with respect to ``x[skip:]``
    ((n, n − skip)); None: forward-mode autodiff of ``field``.  ``skip`` (static): the field
    does not depend on ``x[:skip]`` (the positions of a kinematic model), so only the other
    n − skip columns are carried (F's first ``skip`` columns are the identity's).  Equal to
    ``jax.jacfwd`` of :func:`rk4_field` (tests); a model's closed-form ``jacobian`` gives the
    same F with far fewer kernels in its second derivatives (a gradient through a filter
    differentiates F).  Returns ``(x(t + dt) (n,), F (n, n))``.
    """
    x = real_float(x, "x")
    n = x.shape[0]
    skip = check_int(skip, "skip", lower=0)  # 1.5 was truncated to 1
    if not 0 <= skip < n:
        raise InputError(f"skip: expected 0 <= skip < {n} (the state's size), got {skip}")
    h = as_scalar(dt, x.dtype, "dt")
    if jacobian is None:
        def jacobian(y, c):
            def g(q):
                return field(jnp.concatenate([y[:skip], q]), c)
            return g(y[skip:]), jax.jacfwd(g)(y[skip:])
    eye = jnp.eye(n - skip, dtype=x.dtype)
    k1, K1 = jacobian(x, 0.0)
    k2, A2 = jacobian(x + 0.5 * h * k1, 0.5)
    K2 = small_matmul(A2, eye + 0.5 * h * K1[skip:])
    k3, A3 = jacobian(x + 0.5 * h * k2, 0.5)
    K3 = small_matmul(A3, eye + 0.5 * h * K2[skip:])
    k4, A4 = jacobian(x + h * k3, 1.0)
    K4 = small_matmul(A4, eye + h * K3[skip:])
    x_new = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    F = jnp.eye(n, dtype=x.dtype).at[:, skip:].add((h / 6.0) * (K1 + 2.0 * K2 + 2.0 * K3 + K4))
    return x_new, F


def rollout(f, x0, us, dt, *args):
    """Integrate an input sequence with RK4 in one ``lax.scan``.

    ``x0``: (n,) initial state; ``us``: (T, m) inputs, ``us[k]`` held over
    step k; ``dt``: scalar step, s.  Returns xs (T + 1, n) with xs[0] = x0.  Called eagerly it
    is compiled once per ``f`` (:func:`jaxslam.compilation.call_compiled`; uncompiled, each
    call traced and compiled its scan again).
    """
    x0 = real_float(x0, "x0")  # an integer x0 made the scan's carry change dtype (a TypeError)
    check_real(us, "us")
    if np.ndim(us) != 2:  # (f's own check named its argument u)
        raise InputError(f"us: expected shape (T, m) (one input per step), got {np.shape(us)}")
    return call_compiled(("integrators.rollout", f), lambda *a: _rollout(f, *a), (x0, jnp.asarray(us), dt, *args),
                         after="auto")


def _rollout(f, x0, us, dt, *args):
    """:func:`rollout`'s scan."""
    def body(x, u):
        xn = rk4_step(f, x, u, dt, *args)
        return xn, xn

    _, xs = jax.lax.scan(body, x0, us)
    return jnp.concatenate([x0[None], xs], axis=0)


def linearize(f, x, u, *args):
    """Continuous-time Jacobians (A, B) = (∂f/∂x, ∂f/∂u) at (x, u) by jacfwd.

    ``x``: (n,), ``u``: (m,).  Returns A (n, n), B (n, m).  (Paper 000's filter model has
    eq. 28, F = ∂f_s/∂s, in closed form: ``systems.ekf_slam_3d.state_jacobian``.)
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
