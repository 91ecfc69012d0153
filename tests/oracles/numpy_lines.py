"""NumPy twin of jaxslam.features.lines.extract_lines (paper 004, Algorithm 1, eq. 4.1).

The reference of ``jaxslam bench lines``: the same algorithm written the way a competent NumPy
user would, vectorised over the hypotheses of a round (one ``(n_hyp, N)`` residual array), a
Python loop over rounds that stops at the first failed round (Algorithm 1's break), and its own
RNG (``numpy.random.Generator``) with the same sampling semantics: two distinct ranks among the
remaining points (``integers(0, K)`` and ``integers(0, K − 1)`` shifted past the first), mapped
to indices by ``searchsorted`` on the cumulative mask; support counted with the implicit line
through the two points, ``(a x + b y + c)² ≤ thr² (a² + b²)``; ties → first; least-squares refit
on the best inliers, rescue within ``thr``, final refit on both.  Total least squares via the
closed-form principal axis of the 2×2 scatter matrix.  None of the package's code.

``extract_lines(rng, points, valid, n_hyp, max_lines, threshold, min_inliers)`` returns a list of
``(rho, theta, n_inliers, inlier_mask)`` for the lines found and the remaining mask.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_line", "extract_lines"]


def fit_line(P, m):
    """TLS line (ρ ≥ 0, θ ∈ (−π, π]) of the points P[m]."""
    Q = P[m]
    c = Q.mean(axis=0)
    D = Q - c
    sxx, syy, sxy = D[:, 0] @ D[:, 0], D[:, 1] @ D[:, 1], D[:, 0] @ D[:, 1]
    th = 0.5 * np.arctan2(2 * sxy, sxx - syy) + 0.5 * np.pi
    rho = c[0] * np.cos(th) + c[1] * np.sin(th)
    if rho < 0:
        rho, th = -rho, th + np.pi
    th = np.pi - (np.pi - th) % (2 * np.pi)
    return rho, th


def extract_lines(rng, points, valid, n_hyp=459, max_lines=8, threshold=0.05, min_inliers=20):
    P = np.asarray(points, dtype=np.float64)
    remaining = np.asarray(valid, bool) & np.all(np.isfinite(P), axis=1)
    P = np.where(remaining[:, None], P, 0.0)
    x, y = P[:, 0], P[:, 1]
    thr2 = threshold * threshold
    out = []
    for _ in range(max_lines):
        cum = np.cumsum(remaining)
        K = int(cum[-1])
        if K < 2:
            break
        r1 = rng.integers(0, K, n_hyp)
        r2 = rng.integers(0, K - 1, n_hyp)
        r2 += r2 >= r1
        i1 = np.searchsorted(cum, r1 + 1, side="left")
        i2 = np.searchsorted(cum, r2 + 1, side="left")
        p1, p2 = P[i1], P[i2]
        a = p1[:, 1] - p2[:, 1]
        b = p2[:, 0] - p1[:, 0]
        c = -(a * p1[:, 0] + b * p1[:, 1])
        lim = thr2 * (a * a + b * b)
        R = np.multiply.outer(a, x)
        R += np.multiply.outer(b, y)
        R += c[:, None]
        R *= R
        S = (R <= lim[:, None]) & remaining
        counts = S.sum(axis=1)
        counts[lim <= 0] = 0
        best = int(np.argmax(counts))
        if counts[best] < min_inliers:
            break
        best_in = S[best]
        rho1, th1 = fit_line(P, best_in)
        rescued = remaining & (np.abs(x * np.cos(th1) + y * np.sin(th1) - rho1) <= threshold)
        final = best_in | rescued
        rho, th = fit_line(P, final)
        out.append((rho, th, int(final.sum()), final))
        remaining = remaining & ~final
    return out, remaining
