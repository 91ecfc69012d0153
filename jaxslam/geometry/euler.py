"""3-2-1 (yaw-pitch-roll) Euler angles in the NED convention of paper 000.

Paper 000, Sec. 2.1, eq. 1 and 3.  Frames: N is the inertial North-East-Down
frame, B the body frame (b̂1 forward, b̂2 right arm, b̂3 down).  The attitude is
Λ = [φ, θ, ψ] (roll, pitch, yaw, radians) and

    C_NB = C3(ψ) C2(θ) C1(φ)                                   (eq. 1)

maps body components to NED components (v_N = C_NB v_B).  The elementary
matrices are exactly the ones eq. 1 prints (active rotations about the x, y
and z axes).  Paper 001 eq. 6 (R_b^w) is the same product; its (1,3) entry is
misprinted there ("CψSθCφ + SψCφ" must read "CψSθCφ + SψSφ", as its own eq. 3
uses), so jaxslam uses this one function for both papers.

Decisions (the paper is silent):

* ``euler_from_dcm`` returns φ ∈ (−π, π], θ ∈ [−π/2, π/2], ψ ∈ (−π, π].
  θ comes from atan2(−C₃₁, ‖(C₃₂, C₃₃)‖) (accurate at every pitch, unlike
  asin), φ from atan2(C₃₂, C₃₃), and ψ is then solved from the matrix
  C_NB C1(φ)ᵀ = C3(ψ) C2(θ), whose second column is [−sin ψ, cos ψ, 0] with
  O(1) entries.  Because ψ is solved *given* the φ already chosen, the pair
  (φ, ψ) always reproduces C_NB even near gimbal lock, where φ and ψ are
  individually ill-conditioned (only ψ − φ at θ = +90° and ψ + φ at θ = −90°
  are defined).
* Gimbal lock: when cos θ is below machine epsilon of the dtype (θ = ±90° to
  working precision) φ and ψ are not separable; jaxslam returns **φ = 0** and
  puts the whole rotation about the vertical into ψ (yaw carries the heading,
  the usual navigation convention).
* ``euler_rate_matrix`` is D of eq. 3 (Λ̇ = D ω).  Paper 000 eq. 18 misprints
  the ψ̇ row; D of eq. 3 is right (see the errata in docs/papers.md).  Paper 001
  eq. 2 prints θ̇ = cos(θ) q − sin(φ) r; the correct (and eq. 3) form is
  θ̇ = cos(φ) q − sin(φ) r.  D is singular at cos θ = 0; no guard is added
  (a filter near ±90° pitch must not use Euler angles).

All functions accept leading batch dimensions (``euler`` of shape (..., 3),
matrices (..., 3, 3)), are jit/vmap/grad-safe and follow the input dtype.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import check_numbers, check_real, float_array, is_concrete, to_jax

__all__ = [
    "C1",
    "C2",
    "C3",
    "dcm_from_euler",
    "euler_from_dcm",
    "euler_rate_matrix",
    "euler_rates",
    "rotate_jacobian",
    "unrotate_jacobian",
]


def _as_real_array(x, label: str):
    """``x`` as a JAX array of real numbers: a complex dtype (static, refused under ``jit`` too:
    the result came back complex, or a cast dropped the imaginary part with only a warning) or a
    concrete non-number (a string, None: a bare JAX ``TypeError`` before) is an
    :class:`~jaxslam.errors.InputError` naming ``label``.  The dtype is kept."""
    check_real(x, label)
    if not isinstance(x, (jax.Array, np.ndarray)) and is_concrete(x):
        check_numbers(x, label)
    return to_jax(x)


def _last_axis(x, n, name: str, fn: str | None = None):
    """``x`` as a real array whose trailing axes have the sizes ``n`` (an int: the last axis; a
    tuple: e.g. (3, 3) for matrices), checked statically (free under ``jit``); else
    :class:`~jaxslam.errors.InputError` naming ``fn``'s argument (a (3,) quaternion used to
    be read as q0..q2 with q3 taken from a wrapped index, and return a plausible answer; a
    complex array came back complex)."""
    x = _as_real_array(x, name if fn is None else f"{fn}: {name}")
    dims = (n,) if isinstance(n, int) else tuple(n)
    if x.ndim < len(dims) or tuple(x.shape[x.ndim - len(dims):]) != dims:
        raise InputError(f"{'' if fn is None else fn + ': '}{name}{':' if fn is None else ''} expected shape "
                         f"(..., {', '.join(map(str, dims))}), got {tuple(x.shape)}")
    return x


def _matrix33(C, name: str, fn: str):
    """``C`` as an array of (..., 3, 3) matrices, else InputError naming ``fn``'s argument."""
    return _last_axis(C, (3, 3), name, fn)


def _inexact(x, name: str = "x"):
    """``x`` promoted to JAX's default float dtype when it holds integers (or bools): the angle
    functions need an inexact dtype (``finfo``, trig); float inputs keep their dtype
    (:func:`jaxslam.linalg.float_array`)."""
    return float_array(x, name)


def _exact_shape(x, shape: tuple, name: str, fn: str):
    """``x`` as an array of exactly ``shape`` (e.g. a single 3-vector (3,)), else InputError
    naming ``fn``'s argument (a complex one too)."""
    x = _as_real_array(x, f"{fn}: {name}")
    if x.shape != shape:
        raise InputError(f"{fn}: {name} expected shape {shape}, got {tuple(x.shape)}")
    return x


def _jacobian_args(euler, v, C, vname: str, fn: str):
    euler, v = _exact_shape(euler, (3,), "euler", fn), _exact_shape(v, (3,), vname, fn)
    if C is not None:
        C = _exact_shape(C, (3, 3), "C", fn)
    return euler, v, C


def _mat(rows):
    """Stack a nested 3×3 list of (...) arrays into (..., 3, 3)."""
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def C1(phi):
    """Elementary rotation about x̂ (roll), paper 000 eq. 1.

    ``phi``: (...) radians.  Returns (..., 3, 3)
    [[1, 0, 0], [0, cφ, −sφ], [0, sφ, cφ]].
    """
    phi = _as_real_array(phi, "C1: phi")
    c, s = jnp.cos(phi), jnp.sin(phi)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return _mat([[o, z, z], [z, c, -s], [z, s, c]])


def C2(theta):
    """Elementary rotation about ŷ (pitch), paper 000 eq. 1.

    ``theta``: (...) radians.  Returns (..., 3, 3)
    [[cθ, 0, sθ], [0, 1, 0], [−sθ, 0, cθ]].
    """
    theta = _as_real_array(theta, "C2: theta")
    c, s = jnp.cos(theta), jnp.sin(theta)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return _mat([[c, z, s], [z, o, z], [-s, z, c]])


def C3(psi):
    """Elementary rotation about ẑ (yaw), paper 000 eq. 1.

    ``psi``: (...) radians.  Returns (..., 3, 3)
    [[cψ, −sψ, 0], [sψ, cψ, 0], [0, 0, 1]].
    """
    psi = _as_real_array(psi, "C3: psi")
    c, s = jnp.cos(psi), jnp.sin(psi)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return _mat([[c, -s, z], [s, c, z], [z, z, o]])


def _dcm_coef():
    import numpy as np
    # C_NB[i, j] = sum_t prod_k factor[t, k, i, j], factor = a cos + b sin + c of angle k
    K = np.zeros((2, 3, 3, 3, 3))
    c, s_, o = 0, 1, 2
    terms = {  # (i, j): [(psi, theta, phi) factors for each term], ('-s' = minus sine)
        (0, 0): [("c", "c", "1")], (0, 1): [("c", "s", "s"), ("-s", "1", "c")],
        (0, 2): [("c", "s", "c"), ("s", "1", "s")],
        (1, 0): [("s", "c", "1")], (1, 1): [("s", "s", "s"), ("c", "1", "c")],
        (1, 2): [("s", "s", "c"), ("-c", "1", "s")],
        (2, 0): [("1", "-s", "1")], (2, 1): [("1", "c", "s")], (2, 2): [("1", "c", "c")],
    }
    code = {"c": (c, 1.0), "s": (s_, 1.0), "-s": (s_, -1.0), "-c": (c, -1.0), "1": (o, 1.0)}
    for (i, j), ts in terms.items():
        for t, (fp, ft, ff) in enumerate(ts):
            for k, f in ((2, fp), (1, ft), (0, ff)):
                m, v = code[f]
                K[t, k, m, i, j] = v
    return K


_DCM_COEF = _dcm_coef()


def dcm_from_euler(euler):
    """Body-to-NED direction cosine matrix C_NB = C3(ψ) C2(θ) C1(φ).

    Paper 000, eq. 1 (also paper 001 eq. 6 with its (1,3) misprint fixed).
    ``euler``: (..., 3) = [φ, θ, ψ] in radians.  Returns (..., 3, 3) with
    v_N = C_NB @ v_B.
    """
    euler = _last_axis(euler, 3, "euler", "dcm_from_euler")
    ang = euler[..., :3]
    # Each factor of each entry's terms is a cos + b sin + c of one angle; elementwise on
    # (..., term, angle, 3, 3) arrays: a few wide operations in place of ~35 scalar ones, which
    # under nested autodiff (Jacobians inside a differentiated flight) multiplied the program.
    c = jnp.cos(ang)[..., None, :, None, None]
    s = jnp.sin(ang)[..., None, :, None, None]
    K = _DCM_COEF.astype(c.dtype)
    F = c * K[:, :, 0] + s * K[:, :, 1] + K[:, :, 2]
    P = F[..., 2, :, :] * F[..., 1, :, :] * F[..., 0, :, :]  # ψ factor · θ factor · φ factor
    return P[..., 0, :, :] + P[..., 1, :, :]


def euler_from_dcm(C):
    """3-2-1 Euler angles [φ, θ, ψ] of a body-to-NED DCM (inverse of eq. 1).

    ``C``: (..., 3, 3) rotation matrix C_NB.  Returns (..., 3) radians with
    φ, ψ ∈ (−π, π], θ ∈ [−π/2, π/2].  Stable at every pitch: the returned
    angles always reproduce ``C`` through :func:`dcm_from_euler` to working
    precision.  At gimbal lock (cos θ < eps of the dtype) φ and ψ are not
    separable and φ = 0 is returned (the rotation about the vertical goes
    into ψ).  Gradients are finite everywhere (double-``where`` guards).
    """
    C = _inexact(_matrix33(C, "C", "euler_from_dcm"), "C")
    eps = jnp.finfo(C.dtype).eps
    c21, c22 = C[..., 2, 1], C[..., 2, 2]
    n2 = c21 * c21 + c22 * c22  # cos²θ
    locked = n2 < eps * eps
    safe_n2 = jnp.where(locked, 1.0, n2)
    cos_t = jnp.where(locked, 0.0, jnp.sqrt(safe_n2))
    theta = jnp.arctan2(-C[..., 2, 0], cos_t)
    phi = jnp.where(
        locked, 0.0, jnp.arctan2(jnp.where(locked, 0.0, c21), jnp.where(locked, 1.0, c22))
    )
    cf, sf = jnp.cos(phi), jnp.sin(phi)
    # Second column of C C1(φ)ᵀ = C3(ψ) C2(θ) is [−sin ψ, cos ψ, 0].
    m01 = cf * C[..., 0, 1] - sf * C[..., 0, 2]
    m11 = cf * C[..., 1, 1] - sf * C[..., 1, 2]
    psi = jnp.arctan2(-m01, m11)
    # arctan2(−0, −1) is −π: the documented range is (−π, π]
    phi = jnp.where(phi <= -jnp.pi, jnp.asarray(jnp.pi, phi.dtype), phi)
    psi = jnp.where(psi <= -jnp.pi, jnp.asarray(jnp.pi, psi.dtype), psi)
    return jnp.stack([phi, theta, psi], axis=-1)


def euler_rate_matrix(euler):
    """D of paper 000 eq. 3: Λ̇ = D(φ, θ) ω_B.

    ``euler``: (..., 3) = [φ, θ, ψ] radians (ψ unused).  Returns (..., 3, 3)

        D = [[1, sφ tθ, cφ tθ],
             [0, cφ,    −sφ  ],
             [0, sφ/cθ, cφ/cθ]]

    (eq. 3 written with 1/cos θ factored out).  Singular at θ = ±90°.
    """
    euler = _last_axis(euler, 3, "euler", "euler_rate_matrix")
    c, s = jnp.cos(euler[..., :2]), jnp.sin(euler[..., :2])  # one kernel each (see dcm_from_euler)
    cf, ct = c[..., 0], c[..., 1]
    sf = s[..., 0]
    tt = jnp.tan(euler[..., 1])
    o, z = jnp.ones_like(cf), jnp.zeros_like(cf)
    return _mat([[o, sf * tt, cf * tt], [z, cf, -sf], [z, sf / ct, cf / ct]])


def euler_rates(euler, omega):
    """Euler angle rates Λ̇ = D(Λ) ω, paper 000 eq. 2-3 (third block row).

    ``euler``: (..., 3) [φ, θ, ψ] radians; ``omega``: (..., 3) body angular
    velocity [p, q, r] in rad/s (body axes).  Returns (..., 3) rad/s.
    """
    D = euler_rate_matrix(euler)
    return jnp.einsum("...ij,...j->...i", D, _last_axis(omega, 3, "omega", "euler_rates"))


def rotate_jacobian(euler, v, C=None):
    """∂(C_NB v)/∂(φ, θ, ψ) (3, 3) in closed form, for one ``euler`` (3,) and ``v`` (3,).

    C = C₃(ψ) C₂(θ) C₁(φ), so ∂C/∂φ = C [e₁]×, ∂C/∂θ = C [a]× with a = C₁(φ)ᵀ e₂ = [0, cφ, −sφ],
    ∂C/∂ψ = [e₃]× C; the columns are C (e₁ × v), C (a × v), e₃ × C v.  ``C``: the DCM if the
    caller has it (else formed here).  Equal to ``jax.jacfwd`` (tests).
    """
    euler, v, C = _jacobian_args(euler, v, C, "v", "rotate_jacobian")
    C = dcm_from_euler(euler) if C is None else C
    sf, cf = jnp.sin(euler[0]), jnp.cos(euler[0])
    z = jnp.zeros_like(sf)
    Cv = jnp.sum(C * v, axis=-1)
    e1_v = jnp.stack([z, -v[2], v[1]])
    a_v = jnp.stack([cf * v[2] + sf * v[1], -sf * v[0], -cf * v[0]])
    return jnp.concatenate([jnp.sum(C[:, None, :] * jnp.stack([e1_v, a_v])[None], axis=-1),
                            jnp.stack([-Cv[1], Cv[0], z])[:, None]], axis=1)


def unrotate_jacobian(euler, d, C=None):
    """∂(C_NBᵀ d)/∂(φ, θ, ψ) (3, 3) in closed form: with c = Cᵀ d the columns are c × e₁,
    c × a and Cᵀ (d × e₃) (a as in :func:`rotate_jacobian`).  Equal to ``jax.jacfwd`` (tests)."""
    euler, d, C = _jacobian_args(euler, d, C, "d", "unrotate_jacobian")
    C = dcm_from_euler(euler) if C is None else C
    sf, cf = jnp.sin(euler[0]), jnp.cos(euler[0])
    z = jnp.zeros_like(sf)
    c = jnp.sum(C * d[:, None], axis=0)
    return jnp.stack([jnp.stack([z, c[2], -c[1]]),
                      jnp.stack([-c[1] * sf - c[2] * cf, c[0] * sf, c[0] * cf]),
                      jnp.sum(C * jnp.stack([d[1], -d[0], z])[:, None], axis=0)], axis=1)
