"""JCBB (jaxslam.filters.association) against an exhaustive search written here in NumPy.

The oracle enumerates every hypothesis of a scan — each measurement paired with one mapped
landmark or with nothing, no landmark twice — with hand-derived range-bearing Jacobians,
keeps those whose pairings are individually (marginal d² < gate) and jointly (joint NIS <
χ²(2m) quantile) compatible, and chooses the most pairings, then the smallest joint NIS.
With a budget larger than the search tree JCBB must return the same pairing.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.filters import association as A
from jaxslam.filters import ekf_slam as es
from jaxslam.metrics import chi2_ppf_np
from jaxslam.sensors import range_bearing2d as rb

MODEL = es.SlamModel(robot_dim=3, lm_dim=2, meas_dim=2, motion=None, observe=rb.observe,
                     inverse=rb.inverse, residual=rb.residual)
GATE = chi2_ppf_np(0.99, 2)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _h_np(s, l):
    dx, dy = l[0] - s[0], l[1] - s[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    zh = np.array([r, _wrap(np.arctan2(dy, dx) - s[2])])
    Hs = np.array([[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]])
    Hl = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
    return zh, Hs, Hl


def _exhaustive(x, P, cap, z, R, thr):
    K = z.shape[0]
    s = x[:3]
    pred = [_h_np(s, x[3 + 2 * j:5 + 2 * j]) for j in range(cap)]

    def block(i, j):
        zh, Hs, Hl = pred[j]
        H = np.zeros((2, x.size))
        H[:, :3] = Hs
        H[:, 3 + 2 * j:5 + 2 * j] = Hl
        nu = z[i] - zh
        nu[1] = _wrap(nu[1])
        return H, nu

    ind = np.zeros((K, cap), bool)
    for i in range(K):
        for j in range(cap):
            H, nu = block(i, j)
            ind[i, j] = nu @ np.linalg.solve(H @ P @ H.T + R, nu) < GATE
    best, best_m, best_nis = [-1] * K, 0, 0.0
    for hyp in itertools.product(*[[-1] + list(range(cap))] * K):
        pairs = [(i, j) for i, j in enumerate(hyp) if j >= 0]
        js = [j for _, j in pairs]
        if len(set(js)) < len(js) or any(not ind[i, j] for i, j in pairs):
            continue
        m = len(pairs)
        if m == 0:
            continue
        Hs_, nus = zip(*[block(i, j) for i, j in pairs])
        H, nu = np.vstack(Hs_), np.concatenate(nus)
        S = H @ P @ H.T + np.kron(np.eye(m), R)
        nis = float(nu @ np.linalg.solve(S, nu))
        if nis > thr[m - 1]:
            continue
        if m > best_m or (m == best_m and nis < best_nis):
            best, best_m, best_nis = list(hyp), m, nis
    return np.array(best), best_m, best_nis


def _case(seed, cap=4, K=3, clutter=1, spread=3.0):
    rng = np.random.default_rng(seed)
    L = rng.uniform(-spread, spread, (cap, 2))
    L[0] = L[1] + rng.normal(size=2) * 0.3  # two close landmarks: ambiguous individually
    s = np.array([rng.normal() * 0.2, rng.normal() * 0.2, rng.normal() * 0.3])
    x = np.concatenate([s, L.ravel()])
    n = x.size
    G = rng.normal(size=(n, n)) * 0.04
    P = G @ G.T + np.diag([0.01, 0.01, 0.002] + [0.005] * (n - 3))
    R = np.diag([0.08 ** 2, 0.03 ** 2])
    # measurements of the true (x, L) drawn from the prior, plus clutter
    xt = x + np.linalg.cholesky(P) @ rng.normal(size=n)
    seen = rng.choice(cap, K - clutter, replace=False)
    z = [np.asarray(_h_np(xt[:3], xt[3 + 2 * j:5 + 2 * j])[0]) + rng.normal(size=2) * [0.08, 0.03]
         for j in seen]
    for _ in range(clutter):
        z.append(np.array([rng.uniform(1, 6), rng.uniform(-np.pi, np.pi)]))
    z = np.array(z)[rng.permutation(K)]
    return x, P, z, R


@pytest.mark.parametrize("seed,cap,K,clutter,spread", [(s, 4, 3, 1, 3.0) for s in range(8)]
                         + [(s, 5, 4, c, 1.5) for s in range(8) for c in (0, 2)])
def test_jcbb_equals_exhaustive_search(seed, cap, K, clutter, spread):
    # the second group: crowded maps (landmarks within 1.5 m), several pairings ambiguous
    x, P, z, R = _case(seed, cap, K, clutter, spread)
    thr = np.array([chi2_ppf_np(0.99, 2 * m) for m in range(1, K + 1)])
    want, want_m, want_nis = _exhaustive(x, P, cap, z, R, thr)
    st = es.SlamState(x=jnp.asarray(x), P=jnp.asarray(P), active=jnp.ones(cap, bool),
                      ids=jnp.arange(cap, dtype=jnp.int32), status=jnp.int32(0), overflow=jnp.int32(0))
    res = _run(st, jnp.asarray(z), jnp.asarray(R), jnp.asarray(thr), cap)
    assert not bool(res.exhausted)
    assert int(res.n_paired) == want_m
    np.testing.assert_array_equal(np.asarray(res.slots), want)
    if want_m:
        np.testing.assert_allclose(float(res.nis), want_nis, rtol=1e-9)


def _jcbb(st, z, R, thr, n_cand):
    return A.jcbb(st, MODEL, z, jnp.ones(z.shape[0], bool), R, gate=GATE, thresholds=thr,
                  n_cand=n_cand, budget=2000)


_run = jax.jit(_jcbb, static_argnums=4)


def test_budget_bounds_the_search_and_is_reported():
    cap, K = 4, 3
    x, P, z, R = _case(3, cap, K)
    st = es.SlamState(x=jnp.asarray(x), P=jnp.asarray(P), active=jnp.ones(cap, bool),
                      ids=jnp.arange(cap, dtype=jnp.int32), status=jnp.int32(0), overflow=jnp.int32(0))
    thr = jnp.asarray([chi2_ppf_np(0.99, 2 * m) for m in range(1, K + 1)])
    small = A.jcbb(st, MODEL, jnp.asarray(z), jnp.ones(K, bool), jnp.asarray(R), gate=GATE,
                   thresholds=thr, n_cand=4, budget=3)
    assert int(small.nodes) == 3 and bool(small.exhausted)


def test_masked_rows_and_unmapped_slots_are_never_paired():
    cap, K = 4, 3
    x, P, z, R = _case(5, cap, K, clutter=0)
    active = jnp.asarray([True, False, True, True])
    st = es.SlamState(x=jnp.asarray(x), P=jnp.asarray(P), active=active,
                      ids=jnp.arange(cap, dtype=jnp.int32), status=jnp.int32(0), overflow=jnp.int32(0))
    thr = jnp.asarray([chi2_ppf_np(0.99, 2 * m) for m in range(1, K + 1)])
    mask = jnp.asarray([True, False, True])
    def search(zz):
        return A.jcbb(st, MODEL, zz, mask, jnp.asarray(R), gate=GATE, thresholds=thr, n_cand=3, budget=200)

    res = jax.jit(search)(jnp.asarray(z))  # jitted: one program, not one per operation
    slots = np.asarray(res.slots)
    assert slots[1] == -1 and not np.any(slots == 1)
    zero = jax.jit(jax.vmap(lambda zz: search(zz).n_paired))(jnp.stack([jnp.asarray(z)] * 2))
    assert zero.shape == (2,)  # vmappable
