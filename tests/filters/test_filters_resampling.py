"""Tests of jaxslam.filters.resampling.

Oracles: SciPy softmax and chi-square quantiles, a loop-based NumPy systematic
resampler (the textbook two-pointer algorithm), closed forms (uniform and
one-hot ESS), Monte Carlo means at fixed seeds, and finite differences.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy import special, stats

from jaxslam.errors import InputError
from jaxslam.filters import resampling as rs

N = 16
M_DRAWS = 4000
SEED = 1234


def _weights(seed=0, n=N, zero=(3,)):
    rng = np.random.default_rng(seed)
    w = rng.gamma(0.7, size=n)
    w[list(zero)] = 0.0
    return w / w.sum()


def _logw(w, dtype=np.float64):
    with np.errstate(divide="ignore"):
        return np.log(w).astype(dtype)


@functools.lru_cache(maxsize=None)
def _all_draws():
    """Ancestors (M, N) of M seeded draws for every scheme, in one compilation.

    The extra entry "biased" is systematic resampling of tempered weights
    w^1.1 (for the power check of the chi-square test).
    """
    w = _weights()
    wt = w**1.1 / np.sum(w**1.1)
    names = sorted(rs.SCHEMES)

    def draw(k, lw, lwt):
        out = {s: rs.SCHEMES[s](k, lw) for s in names}
        out["biased"] = rs.systematic(k, lwt)
        return out

    fn = jax.jit(jax.vmap(draw, in_axes=(0, None, None)))
    keys = jax.random.split(jax.random.PRNGKey(SEED), M_DRAWS)
    return {s: np.asarray(v) for s, v in fn(keys, jnp.asarray(_logw(w)),
                                            jnp.asarray(_logw(wt))).items()}


def _draws(scheme, tempered=False):
    """(indices (M, N), offspring counts (M, N)) of a scheme."""
    idx = _all_draws()["biased" if tempered else scheme]
    counts = np.stack([np.bincount(r, minlength=N) for r in idx])
    return idx, counts


def _pearson(counts, w):
    """X² = Σ (O − E)² / E over nonzero-weight particles, E = M N w."""
    nz = w > 0
    O = counts.sum(axis=0)[nz]
    E = M_DRAWS * N * w[nz]
    x2 = float(np.sum((O - E) ** 2 / E))
    return x2, int(nz.sum() - 1)


# ---------------------------------------------------------------------------
# normalize / ess
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normalize_matches_softmax(dtype):
    rng = np.random.default_rng(1)
    lw = (rng.normal(size=50) * 5).astype(dtype)
    out, ok = rs.normalize(jnp.asarray(lw))
    assert out.dtype == dtype and bool(ok)
    tol = 1e-6 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(np.exp(np.asarray(out)), special.softmax(lw.astype(np.float64)),
                               rtol=tol * 10, atol=tol)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normalize_recovers_from_underflow(dtype):
    # exp(-1e4) is 0 in both dtypes; log-sum-exp cancels the offset exactly.
    assert np.exp(np.asarray(-1e4, dtype)) == 0
    out, ok = rs.normalize(jnp.full((8,), -1e4, dtype))
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(out), -np.log(8.0), rtol=1e-6)
    offs = np.array([0.0, -1.0, 2.0, 0.5], dtype)
    out, ok = rs.normalize(jnp.asarray(offs - 1e4))
    np.testing.assert_allclose(np.exp(np.asarray(out)), special.softmax(offs.astype(float)),
                               rtol=1e-5)


def test_normalize_flags_all_neg_inf_and_nan():
    normalize = jax.jit(rs.normalize)
    for bad in (np.full(4, -np.inf), np.full(4, np.nan), np.array([np.nan, -np.inf] * 2)):
        out, ok = normalize(jnp.asarray(bad))
        assert not bool(ok)
        np.testing.assert_allclose(np.asarray(out), -np.log(bad.size), rtol=1e-15)
    # A single NaN among finite entries is treated as -inf (weight 0).
    out, ok = normalize(jnp.asarray([0.0, np.nan, np.log(3.0), -np.inf]))
    assert bool(ok)
    np.testing.assert_allclose(np.exp(np.asarray(out)), [0.25, 0.0, 0.75, 0.0], atol=1e-15)


def test_normalize_grad_safe_when_degenerate():
    g = jax.jit(jax.grad(lambda x: jnp.sum(rs.normalize(x)[0])))(jnp.full((4,), -jnp.inf))
    assert np.all(np.isfinite(np.asarray(g)))
    check_grads(jax.jit(lambda x: rs.normalize(x)[0]), (jnp.array([0.3, -1.0, 2.0]),),
                order=1, modes=["rev"])


def test_ess_closed_forms():
    ess = jax.jit(rs.ess)
    assert float(ess(jnp.zeros(10))) == pytest.approx(10.0, rel=1e-14)
    assert float(ess(jnp.asarray([0.0] + [-jnp.inf] * 9))) == pytest.approx(1.0, rel=1e-14)
    w = _weights(5)
    assert float(ess(jnp.asarray(_logw(w) + 7.0))) == pytest.approx(1.0 / np.sum(w**2),
                                                                       rel=1e-12)


# ---------------------------------------------------------------------------
# Schemes
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("scheme", sorted(rs.SCHEMES))
def test_offspring_counts_chi_square(scheme):
    """Mean offspring counts equal N·w: Pearson X² below χ²₀.₉₉₉(df).

    For multinomial resampling the summed counts are exactly
    Multinomial(M·N, w), so X² ~ χ²(df); the other schemes have a smaller
    variance than multinomial, so the same threshold is conservative for
    variance but still sensitive to bias (see the power check below).
    """
    w = _weights()
    idx, counts = _draws(scheme)
    assert idx.dtype == np.int32 and idx.shape == (M_DRAWS, N)
    assert np.all(counts.sum(axis=1) == N)
    assert np.all(counts[:, 3] == 0), "a zero-weight particle was selected"
    x2, df = _pearson(counts, w)
    thr = stats.chi2.ppf(0.999, df)
    assert x2 < thr, f"{scheme}: X²={x2:.1f} >= {thr:.1f} (df={df})"
    # Per particle, the mean count is within 5 binomial standard errors.
    se = np.sqrt(N * w * (1 - w) / M_DRAWS)
    assert np.all(np.abs(counts.mean(axis=0) - N * w) <= 5 * se + 1e-12)
    assert np.all(np.diff(idx, axis=1) >= 0), "indices not sorted"


def test_chi_square_has_power():
    """The same statistic rejects a sampler biased towards heavy particles."""
    w = _weights()
    _, counts = _draws("systematic", tempered=True)
    x2, df = _pearson(counts, w)
    assert x2 > stats.chi2.ppf(0.999, df)


def _np_systematic(w, U, n):
    """Two-pointer systematic resampling (independent NumPy reference)."""
    pos = (np.arange(n) + U) / n
    c = np.cumsum(w)
    c[-1] = 1.0
    out = np.empty(n, np.int64)
    i = j = 0
    while i < n:
        if pos[i] < c[j]:
            out[i] = j
            i += 1
        else:
            j += 1
    return out


def test_systematic_matches_numpy_index_by_index():
    fn = jax.jit(rs.systematic, static_argnums=2)
    cases = [_weights(0), _weights(1, zero=(0, 5, 15)), _weights(2, n=40, zero=(39,)),
             np.eye(1, N, 7)[0]]
    for w in cases:
        for s in range(25):
            key = jax.random.PRNGKey(100 + s)
            U = float(jax.random.uniform(key, (), jnp.float64))
            for n in (len(w), 9):
                got = np.asarray(fn(key, jnp.asarray(_logw(w)), n))
                np.testing.assert_array_equal(got, _np_systematic(w, U, n))


def test_residual_keeps_floor_copies():
    _, counts = _draws("residual")
    assert np.all(counts >= np.floor(N * _weights())[None, :])
    w = _weights(3, n=12, zero=(2,))
    fn = jax.jit(jax.vmap(rs.residual, in_axes=(0, None)))
    idx = np.asarray(fn(jax.random.split(jax.random.PRNGKey(3), 200), jnp.asarray(_logw(w))))
    c = np.stack([np.bincount(r, minlength=12) for r in idx])
    assert np.all(c >= np.floor(12 * w)[None, :]) and np.all(c.sum(1) == 12)
    # Uniform weights: every particle exactly once, no randomness left.
    u = np.asarray(jax.jit(rs.residual)(jax.random.PRNGKey(0), jnp.zeros(10)))
    np.testing.assert_array_equal(u, np.arange(10))


@pytest.mark.parametrize("scheme", sorted(rs.SCHEMES))
def test_schemes_float32_and_n(scheme):
    w = _weights(4)
    lw = jnp.asarray(_logw(w, np.float32))
    idx = jax.jit(rs.resample, static_argnums=(2, 3))(jax.random.PRNGKey(0), lw, scheme, 7)
    assert idx.shape == (7,) and idx.dtype == jnp.int32
    assert np.all(w[np.asarray(idx)] > 0)


def test_bad_inputs():
    with pytest.raises(InputError, match="scheme"):
        rs.resample(jax.random.PRNGKey(0), jnp.zeros(3), "bogus")
    with pytest.raises(InputError, match="n"):
        rs.systematic(jax.random.PRNGKey(0), jnp.zeros(3), 0)


# ---------------------------------------------------------------------------
# Soft resampling
# ---------------------------------------------------------------------------

def test_soft_weights_match_formula():
    w = _weights(6)
    lw = jnp.asarray(_logw(w) + 3.0)  # unnormalised input
    soft = jax.jit(rs.soft)
    for alpha in (0.0, 0.3, 1.0):
        idx, new = soft(jax.random.PRNGKey(7), lw, alpha)
        idx = np.asarray(idx)
        q = alpha * w + (1 - alpha) / N
        ref = w[idx] / q[idx]
        ref = ref / ref.sum()
        np.testing.assert_allclose(np.exp(np.asarray(new)), ref, rtol=1e-12, atol=1e-15)
        if alpha == 1.0:
            np.testing.assert_allclose(np.asarray(new), -np.log(N), rtol=1e-14)
        if alpha > 0:
            assert np.all(w[idx] > 0)


def test_soft_is_properly_weighted():
    """E[Σ_j w'_j 1(a_j = i)] = w_i for α = 0.5 (Monte Carlo, 5 standard errors)."""
    w = _weights(8)
    fn = jax.jit(jax.vmap(lambda k, lw: rs.soft(k, lw, 0.5), in_axes=(0, None)))
    idx, new = fn(jax.random.split(jax.random.PRNGKey(11), M_DRAWS), jnp.asarray(_logw(w)))
    idx, wn = np.asarray(idx), np.exp(np.asarray(new))
    mass = np.zeros((M_DRAWS, N))
    np.add.at(mass, (np.arange(M_DRAWS)[:, None], idx), wn)
    se = mass.std(axis=0) / np.sqrt(M_DRAWS)
    assert np.all(np.abs(mass.mean(axis=0) - w) <= 5 * se + 1e-12)


def test_soft_gradient_matches_finite_differences():
    """Pathwise gradient at a fixed key equals central differences (indices fixed)."""
    lw0 = jnp.asarray(_logw(_weights(9, zero=())))
    key = jax.random.PRNGKey(2)
    f_vec = jnp.asarray(np.random.default_rng(0).normal(size=N))

    def loss(lw, a):
        return jnp.sum(jnp.exp(rs.soft(key, lw, a)[1]) * f_vec)

    batch = jax.jit(jax.vmap(loss))
    grad_j = jax.jit(jax.grad(loss, argnums=(0, 1)))
    g_lw, g_a = grad_j(lw0, 0.4)
    eps = 1e-6
    E = eps * np.eye(N)
    lws = np.concatenate([lw0 + E, lw0 - E, [lw0, lw0]])
    alphas = np.concatenate([np.full(2 * N, 0.4), [0.4 + eps, 0.4 - eps]])
    v = np.asarray(batch(jnp.asarray(lws), jnp.asarray(alphas)))
    fd_lw = (v[:N] - v[N:2 * N]) / (2 * eps)
    fd_a = (v[-2] - v[-1]) / (2 * eps)
    np.testing.assert_allclose(np.asarray(g_lw), fd_lw, rtol=1e-6, atol=1e-8)
    assert float(g_a) == pytest.approx(float(fd_a), rel=1e-6, abs=1e-8)
    assert np.any(np.asarray(g_lw) != 0)
    # α = 1: uniform new weights, hence no gradient through them.
    g1, _ = grad_j(lw0, 1.0)
    np.testing.assert_allclose(np.asarray(g1), 0.0, atol=1e-12)


def test_a_draw_rounded_to_one_never_picks_a_zero_weight_particle():
    """float32: (i + U)/n with i = n - 1 rounds to 1 for U near 1 (and a ratio of exponential
    sums can equal 1), and a cumulative sum can round below 1 before trailing zero weights.
    Such draws were clipped onto the last particle, weight 0 or not (a review found 2-8 calls in
    150 with n = 2^20 drawing a zero-weight particle).  The inverse CDF must hold them at the
    last particle with weight."""
    for w, want in (([1.0, 0.0], 0), ([0.3, 0.7, 0.0, 0.0], 1), ([0.2, 0.0, 0.8], 2)):
        lw = jnp.log(jnp.asarray(w, jnp.float32))
        u = jnp.asarray([0.0, 0.5, np.nextafter(np.float32(1), np.float32(0)), 1.0], jnp.float32)
        idx = np.asarray(rs._invert(lw, u))
        assert idx[-1] == want and idx[-2] == want, (w, idx)
        assert all(w[i] > 0 for i in idx), (w, idx)
    assert np.float32((2**20 - 1 + np.float32(0.99)) / np.float32(2**20)) == 1.0  # the rounding itself
