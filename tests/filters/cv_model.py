"""The 2D constant-velocity model shared by the filter tests (test_smoother, test_ukf,
test_sqrt_ukf): state [x, y, vx, vy], acceleration input, position measured."""

import jax.numpy as jnp
import numpy as np

DT = 0.1
F_CV = np.array([[1, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1]], float)
G_CV = np.array([[0.5 * DT**2, 0], [0, 0.5 * DT**2], [DT, 0], [0, DT]], float)
H_CV = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
Q_CV = 0.05 * G_CV @ G_CV.T + 1e-6 * np.eye(4)
R_CV = np.array([[0.04, 0.01], [0.01, 0.09]])
P0_CV = np.diag([1.0, 1.0, 0.5, 0.5])
X0_CV = np.array([0.0, 0.0, 1.0, -0.5])


def f_cv(x, u):
    return jnp.asarray(F_CV, x.dtype) @ x + jnp.asarray(G_CV, x.dtype) @ u


def h_pos(x):
    return x[:2]
