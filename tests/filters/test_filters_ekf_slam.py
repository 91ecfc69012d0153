"""Generic EKF-SLAM engine against an independent dense NumPy EKF-SLAM.

The oracle below grows its state vector landmark by landmark (the textbook
form of paper 000 eq. 21-53) with hand-derived Jacobians of a 2D unicycle /
range-bearing model, and uses the plain (dense) Joseph form.  The engine uses
autodiff Jacobians, padded slots and gathered columns; both must agree.
"""

import functools

import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxslam import errors
from jaxslam.filters import ekf_slam as es
from jaxslam.linalg import wrap_angle

DT = 0.1


def motion(s, u, p):
    x, y, th = s
    v, w = u
    return jnp.stack([x + DT * v * jnp.cos(th), y + DT * v * jnp.sin(th), th + DT * w])


def observe(s, l, p):
    d = l - s[:2]
    return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0]) - s[2]])


def inverse(s, z, p):
    r, b = z
    return s[:2] + r * jnp.stack([jnp.cos(s[2] + b), jnp.sin(s[2] + b)])


def residual(z, zh):
    d = z - zh
    return d.at[1].set(wrap_angle(d[1]))


MODEL = es.SlamModel(3, 2, 2, motion, observe, inverse, residual)


# ---------------------------------------------------------------- NumPy oracle
class DenseSlam:
    def __init__(self, s0, P0):
        self.x = np.array(s0, float)
        self.P = np.array(P0, float)
        self.ids = []

    def predict(self, u, Q):
        x, y, th = self.x[:3]
        v, w = u
        F = np.array([[1, 0, -DT * v * np.sin(th)], [0, 1, DT * v * np.cos(th)], [0, 0, 1]])
        self.x[:3] = [x + DT * v * np.cos(th), y + DT * v * np.sin(th), th + DT * w]
        n = len(self.x)
        Fb = np.eye(n)
        Fb[:3, :3] = F
        Qb = np.zeros((n, n))
        Qb[:3, :3] = Q
        self.P = Fb @ self.P @ Fb.T + Qb

    @staticmethod
    def h_jac(s, l):
        dx, dy = l[0] - s[0], l[1] - s[1]
        q = dx * dx + dy * dy
        r = np.sqrt(q)
        zh = np.array([r, np.arctan2(dy, dx) - s[2]])
        Hs = np.array([[-dx / r, -dy / r, 0], [dy / q, -dx / q, -1]])
        Hl = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
        return zh, Hs, Hl

    def update(self, zs, ids, R):
        rows, nus = [], []
        n = len(self.x)
        for z, i in zip(zs, ids):
            j = self.ids.index(i)
            zh, Hs, Hl = self.h_jac(self.x[:3], self.x[3 + 2 * j: 5 + 2 * j])
            H = np.zeros((2, n))
            H[:, :3] = Hs
            H[:, 3 + 2 * j: 5 + 2 * j] = Hl
            nu = z - zh
            nu[1] = (nu[1] + np.pi) % (2 * np.pi) - np.pi
            rows.append(H)
            nus.append(nu)
        if not rows:
            self.last_logdet, self.last_dof = 0.0, 0
            return 0.0
        H = np.vstack(rows)
        nu = np.concatenate(nus)
        Rb = np.kron(np.eye(len(zs)), R)
        S = H @ self.P @ H.T + Rb
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ nu
        A = np.eye(n) - K @ H
        self.P = A @ self.P @ A.T + K @ Rb @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self.last_logdet, self.last_dof = float(np.linalg.slogdet(S)[1]), len(nu)
        return float(nu @ np.linalg.solve(S, nu))

    def register(self, z, i, R):
        s = self.x[:3]
        r, b = z
        a = s[2] + b
        l = s[:2] + r * np.array([np.cos(a), np.sin(a)])
        Gs = np.array([[1, 0, -r * np.sin(a)], [0, 1, r * np.cos(a)]])
        Gz = np.array([[np.cos(a), -r * np.sin(a)], [np.sin(a), r * np.cos(a)]])
        n = len(self.x)
        Pll = Gs @ self.P[:3, :3] @ Gs.T + Gz @ R @ Gz.T
        Plx = Gs @ self.P[:3, :]
        P = np.zeros((n + 2, n + 2))
        P[:n, :n] = self.P
        P[n:, :n] = Plx
        P[:n, n:] = Plx.T
        P[n:, n:] = Pll
        self.P = P
        self.x = np.concatenate([self.x, l])
        self.ids.append(i)


# ------------------------------------------------------------------ scenario
def _motion_np(s, u):
    """``motion`` in NumPy (the simulation needs no JAX dispatch per step)."""
    x, y, th = s
    v, w = u
    return np.array([x + DT * v * np.cos(th), y + DT * v * np.sin(th), th + DT * w])


def make_log(seed=0, T=60, n_lm=12, K=6):
    rng = np.random.default_rng(seed)
    lms = rng.uniform(-8, 8, size=(n_lm, 2))
    s = np.array([0.0, 0.0, 0.0])
    us, zs, ids, masks = [], [], [], []
    for t in range(T):
        u = np.array([1.0, 0.3 * np.sin(0.1 * t)])
        s = _motion_np(s, u)
        d = lms - s[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        order = np.argsort(r)[:K]
        z = np.stack([r[order], np.arctan2(d[order, 1], d[order, 0]) - s[2]], -1)
        z += rng.normal(size=z.shape) * [0.05, 0.01]
        z[:, 1] = (z[:, 1] + np.pi) % (2 * np.pi) - np.pi
        m = rng.uniform(size=K) < 0.8
        us.append(u)
        zs.append(z)
        ids.append(order)
        masks.append(m)
    return np.array(us), np.array(zs), np.array(ids, np.int32), np.array(masks)


Q = np.diag([0.01, 0.01, 0.001])
R = np.diag([0.05**2, 0.01**2])


def engine_step(st, u, z, ids, m, active_only=False):
    st = es.predict(st, MODEL, u, jnp.asarray(Q))
    slots, mapped = es.associate_known(st, ids, m)
    st, info = es.update(st, MODEL, z, slots, mapped, jnp.asarray(R), active_only=active_only)
    st = es.register(st, MODEL, z, ids, m & ~mapped, jnp.asarray(R))
    return st, info


@functools.partial(jax.jit, static_argnames="active_only")
def engine_run(st, us, zs, ids, masks, active_only=False):
    def body(st, inp):
        st, info = engine_step(st, *inp, active_only=active_only)
        return st, info.nis

    return jax.lax.scan(body, st, (us, zs, ids, masks))


def oracle_run(us, zs, ids, masks):
    o = DenseSlam(np.zeros(3), np.diag([1e-4, 1e-4, 1e-5]))
    nis, ll, track = [], [], []
    for u, z, i, m in zip(us, zs, ids, masks):
        o.predict(u, Q)
        mapped = [k for k in range(len(i)) if m[k] and i[k] in o.ids]
        new = [k for k in range(len(i)) if m[k] and i[k] not in o.ids]
        nis.append(o.update(z[mapped], i[mapped], R))
        ll.append(-0.5 * (nis[-1] + o.last_logdet + o.last_dof * np.log(2 * np.pi)))
        for k in new:
            o.register(z[k], i[k], R)
        track.append(o.x[:3].copy())
    o.ll, o.track = np.array(ll), np.array(track)
    return o, np.array(nis)


def engine_landmarks(st):
    act = np.asarray(st.active)
    ids = np.asarray(st.ids)[act]
    L = np.asarray(es.landmarks(st, MODEL))[act]
    return dict(zip(ids.tolist(), L))


@pytest.mark.parametrize("cap,active_only,K", [(16, False, 6), (16, True, 6), (100, True, 6),
                                               (100, True, 12)])
def test_engine_matches_dense_numpy_oracle(cap, active_only, K):
    # capacity 100 with the active-block update: n = 203 spans four 64-tiles (the last one
    # clamped) while the map fills only the first of them, and the gain runs on the 50-slot
    # block; with K = 12 rows (24 scalars) the valid rows are compacted into 6 or 12
    us, zs, ids, masks = make_log(K=K, n_lm=max(12, 2 * K))
    st0 = es.init(jnp.zeros(3), jnp.diag(jnp.array([1e-4, 1e-4, 1e-5])), cap, 2)
    st, nis = engine_run(st0, us, zs, ids, masks, active_only=active_only)
    o, nis_o = oracle_run(us, zs, ids, masks)
    np.testing.assert_allclose(np.asarray(st.x[:3]), o.x[:3], atol=1e-10)
    np.testing.assert_allclose(np.asarray(nis), nis_o, rtol=1e-8, atol=1e-10)
    L = engine_landmarks(st)
    assert sorted(L) == sorted(o.ids)
    for j, i in enumerate(o.ids):
        np.testing.assert_allclose(L[i], o.x[3 + 2 * j: 5 + 2 * j], atol=1e-10)
    # full covariance: map engine slots to oracle order
    act_slots = [int(np.flatnonzero((np.asarray(st.ids) == i) & np.asarray(st.active))[0]) for i in o.ids]
    idx = np.concatenate([np.arange(3)] + [3 + 2 * s + np.arange(2) for s in act_slots])
    np.testing.assert_allclose(np.asarray(st.P)[np.ix_(idx, idx)], o.P, atol=1e-10)
    assert int(st.status) == 0 and int(st.overflow) == 0


def test_capacity_padding_and_slot_permutation_change_nothing():
    us, zs, ids, masks = make_log(seed=3)
    P0 = jnp.diag(jnp.array([1e-4, 1e-4, 1e-5]))
    st16, _ = engine_run(es.init(jnp.zeros(3), P0, 16, 2), us, zs, ids, masks)
    st64, _ = engine_run(es.init(jnp.zeros(3), P0, 64, 2), us, zs, ids, masks)
    a, b = engine_landmarks(st16), engine_landmarks(st64)
    assert sorted(a) == sorted(b)
    for i in a:
        np.testing.assert_allclose(a[i], b[i], atol=1e-12)
    np.testing.assert_allclose(np.asarray(st16.x[:3]), np.asarray(st64.x[:3]), atol=1e-12)

    # Permute the slots half-way and continue: the final estimates must not change.
    h = len(us) // 2
    sa, _ = engine_run(es.init(jnp.zeros(3), P0, 16, 2), us[:h], zs[:h], ids[:h], masks[:h])
    perm = np.random.default_rng(1).permutation(16)
    idx = np.concatenate([np.arange(3)] + [3 + 2 * p + np.arange(2) for p in perm])
    x, P, act, lid = (np.asarray(a) for a in (sa.x, sa.P, sa.active, sa.ids))  # permuted on the host
    sp = sa._replace(x=jnp.asarray(x[idx]), P=jnp.asarray(P[np.ix_(idx, idx)]), active=jnp.asarray(act[perm]),
                     ids=jnp.asarray(lid[perm]))
    ea, _ = engine_run(sa, us[h:], zs[h:], ids[h:], masks[h:])
    ep, _ = engine_run(sp, us[h:], zs[h:], ids[h:], masks[h:])
    np.testing.assert_allclose(np.asarray(ea.x[:3]), np.asarray(ep.x[:3]), atol=1e-12)
    la, lp = engine_landmarks(ea), engine_landmarks(ep)
    for i in la:
        np.testing.assert_allclose(la[i], lp[i], atol=1e-12)
    # The active-block update on the permuted map (active slots spread up to the last one,
    # with free slots between them) equals the whole-state update.
    eb, _ = engine_run(sp, us[h:], zs[h:], ids[h:], masks[h:], active_only=True)
    np.testing.assert_allclose(np.asarray(eb.x), np.asarray(ep.x), atol=1e-12)
    np.testing.assert_allclose(np.asarray(eb.P), np.asarray(ep.P), atol=1e-12)


def test_capacity_overflow_is_flagged_and_counted():
    us, zs, ids, masks = make_log(seed=2)
    st, _ = engine_run(es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 4, 2), us, zs, ids, masks)
    assert int(st.active.sum()) == 4
    assert int(st.overflow) > 0
    assert "capacity_overflow" in errors.decode(st.status)
    assert np.all(np.isfinite(np.asarray(st.P)))


def test_register_on_a_full_map_only_counts_and_equals_the_whole_registration():
    # A full map takes the short branch (nothing written, candidates counted); it must give
    # what the whole registration gives there, field by field — also under vmap with a batch
    # in which one run still has a free slot (that batch runs the whole registration).
    z = jnp.array([[5.0, 0.2], [4.0, -0.3], [jnp.nan, 0.1], [3.0, 1.0]])
    mask = jnp.array([True, True, True, False])

    @jax.jit
    def case(z, mask):
        st = es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 2, 2)
        st = es.register(st, MODEL, z[:2], jnp.array([7, 8]), jnp.array([True, True]), jnp.asarray(R))
        return (st, es.register(st, MODEL, z, jnp.arange(4), mask, jnp.asarray(R)),
                es._register(st, MODEL, z, jnp.arange(4), mask, jnp.asarray(R), None))

    full, short, whole = case(z, mask)
    assert bool(full.active.all()) and int(short.overflow) == 2 and int(full.overflow) == 0
    assert errors.decode(short.status) == errors.decode(whole.status)
    assert {"capacity_overflow", "masked_input"} <= set(errors.decode(short.status))
    for a, b in zip(jax.tree.leaves(short), jax.tree.leaves(whole)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # batched: run 0 full, run 1 with its second slot free
    free = full._replace(active=full.active.at[1].set(False))
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), full, free)
    reg = jax.jit(jax.vmap(lambda st: es.register(st, MODEL, z, jnp.arange(4), mask, jnp.asarray(R))))
    out = reg(both)
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda a: a[0], out)), jax.tree.leaves(short)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert bool(out.active[1].all()) and int(out.overflow[1]) == 1


def test_nan_measurements_are_masked_and_flagged():
    us, zs, ids, masks = make_log(seed=4)
    zs_bad = zs.copy()
    zs_bad[10:, 0, :] = np.nan  # the nearest landmark's measurement turns NaN
    st0 = es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 16, 2)
    st, nis = engine_run(st0, us, zs_bad, ids, masks)
    assert np.all(np.isfinite(np.asarray(st.x))) and np.all(np.isfinite(np.asarray(nis)))
    assert "masked_input" in errors.decode(st.status)
    # Same as dropping them through the mask.
    m2 = masks.copy()
    m2[10:, 0] = False
    st2, _ = engine_run(st0, us, zs, ids, m2)
    np.testing.assert_allclose(np.asarray(st.x), np.asarray(st2.x), atol=1e-12)


def test_gate_rejects_outlier():
    @jax.jit  # one program instead of one eager dispatch (and compile) per primitive
    def case(z0, zbad):
        st = es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 4, 2)
        st = es.register(st, MODEL, z0, jnp.array([7]), jnp.array([True]), jnp.asarray(R))
        st2, info = es.update(st, MODEL, zbad, jnp.array([0]), jnp.array([True]), jnp.asarray(R),
                              gate=9.21)
        return st, st2, info

    z0 = jnp.array([[5.0, 0.2]])
    zbad = jnp.array([[7.0, 0.2]])  # 2 m off: hundreds of sigmas
    st, st2, info = case(z0, zbad)
    assert bool(info.gated[0]) and not bool(info.used[0])
    np.testing.assert_array_equal(np.asarray(st2.x), np.asarray(st.x))
    assert "gated" in errors.decode(st2.status)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_nearest_neighbour_association_recovers_ids(dtype):
    @jax.jit  # one program instead of one eager dispatch (and compile) per primitive
    def case(lms, new_l):
        st = es.init(jnp.zeros(3, dtype), jnp.eye(3, dtype=dtype) * 1e-4, 8, 2)
        z = jax.vmap(lambda l: observe(jnp.zeros(3, dtype), l, None))(lms)
        st = es.register(st, MODEL, z, jnp.arange(4), jnp.ones(4, bool), jnp.asarray(R, dtype))
        # observe landmarks 2, 0, and an unseen one far away
        zq = jax.vmap(lambda l: observe(jnp.zeros(3, dtype), l, None))(
            jnp.concatenate([lms[jnp.array([2, 0])], new_l])
        )
        zq = zq + jnp.array([[0.01, 0.002], [-0.02, 0.001], [0.0, 0.0]], dtype)
        return st, es.associate_nn(st, MODEL, zq, jnp.ones(3, bool), jnp.asarray(R, dtype))

    lms = jnp.array([[4.0, 0.0], [0.0, 4.0], [-4.0, 1.0], [3.0, 3.5]], dtype)
    st, (slots, matched, new, d2) = case(lms, jnp.array([[-6.0, -6.0]], dtype))
    assert st.x.dtype == dtype
    assert np.asarray(st.ids)[np.asarray(slots)[:2]].tolist() == [2, 0]
    assert np.asarray(matched).tolist() == [True, True, False]
    assert np.asarray(new).tolist() == [False, False, True]


def test_predict_cost_independent_of_map_block():
    """Prediction must leave the landmark-landmark block bit-for-bit untouched."""
    # T = 30: the same engine_run program as the half-logs of the slot-permutation test
    us, zs, ids, masks = make_log(seed=5, T=30)
    st, _ = engine_run(es.init(jnp.zeros(3), jnp.eye(3) * 1e-4, 16, 2), us, zs, ids, masks)
    st2 = jax.jit(lambda st, u: es.predict(st, MODEL, u, jnp.asarray(Q)))(st, jnp.array([1.0, 0.1]))
    np.testing.assert_array_equal(np.asarray(st2.P[3:, 3:]), np.asarray(st.P[3:, 3:]))
    assert es.robot_cov(st2, MODEL).shape == (3, 3)


# ---------------------------------------------------------------- robot-only update
def test_update_robot_matches_dense_joseph_and_masks():
    """update_robot (paper 004's flow/gyro rows) equals a dense Joseph update of the robot rows."""
    obs = lambda s, p: jnp.stack([s[0] + s[1] ** 2, jnp.sin(s[2])])  # noqa: E731
    z = jnp.array([0.5, 0.2])
    R = np.array([[0.04, 0.01], [0.01, 0.09]])

    @jax.jit  # the three updates in one program (eager dispatch compiled every primitive)
    def case(z, z_nan, R):
        st = es.init(jnp.array([0.3, -0.2, 0.4]), jnp.diag(jnp.array([0.2, 0.3, 0.05])), 4, 2)
        st = es.register(st, MODEL, jnp.array([[2.0, 0.3], [3.0, -0.5]]), jnp.array([0, 1]),
                         jnp.array([True, True]), jnp.asarray(np.diag([0.1, 0.2])))
        both = jnp.array([True, True])
        e0 = es.init(jnp.zeros(3), jnp.eye(3), 2, 2)
        return (st, es.update_robot(st, MODEL, obs, z, both, R),
                es.update_robot(st, MODEL, obs, z_nan, both, R),
                es.update_robot(e0, MODEL, obs, z, True, R))

    st, (new, info), (one, info1), (e1, _) = case(z, jnp.array([0.5, jnp.nan]), jnp.asarray(R))
    x, P = np.asarray(st.x), np.asarray(st.P)
    s = x[:3]
    H = np.zeros((2, x.size))
    H[0, :3] = [1.0, 2 * s[1], 0.0]
    H[1, :3] = [0.0, 0.0, np.cos(s[2])]
    nu = np.asarray(z) - np.array([s[0] + s[1] ** 2, np.sin(s[2])])
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(x.size) - K @ H
    np.testing.assert_allclose(np.asarray(new.x), x + K @ nu, atol=1e-12)
    np.testing.assert_allclose(np.asarray(new.P), IKH @ P @ IKH.T + K @ R @ K.T, atol=1e-12)
    np.testing.assert_allclose(float(info.nis), nu @ np.linalg.solve(S, nu), rtol=1e-10)
    # One row masked (or NaN): the same as the update with the other row alone.
    H1, R1 = H[:1], R[:1, :1]
    K1 = np.linalg.solve(H1 @ P @ H1.T + R1, H1 @ P).T
    np.testing.assert_allclose(np.asarray(one.x), x + K1 @ nu[:1], atol=1e-12)
    assert int(info1.dof) == 1 and int(one.status) & errors.MASKED_INPUT
    # Works on an empty map and keeps P symmetric PSD.
    assert np.all(np.linalg.eigvalsh(np.asarray(e1.P)) > -1e-12)


# ---------------------------------------------------------------- batched registration
def _register_sequential(state, model, z, lm_ids, mask, R, params=None):
    """The engine's former sequential registration (one add_landmark per candidate): oracle."""
    nr = model.robot_dim
    dtype = state.x.dtype
    K = z.shape[0]
    R = jnp.broadcast_to(jnp.asarray(R, dtype), (K,) + (model.meas_dim, model.meas_dim))

    def body(st, inp):
        zk, idk, mk, Rk = inp
        finite = jnp.all(jnp.isfinite(zk))
        zk = jnp.where(finite, zk, 0.0).astype(dtype)
        free = ~st.active
        has_free = jnp.any(free)
        slot = jnp.argmax(free)
        s = st.x[:nr]
        l = model.inverse(s, zk, params)
        Gs, Gz = jax.jacfwd(model.inverse, argnums=(0, 1))(s, zk, params)
        Pss = st.P[:nr, :nr]
        Pll = 0.5 * ((Gs @ Pss @ Gs.T + Gz @ Rk @ Gz.T) + (Gs @ Pss @ Gs.T + Gz @ Rk @ Gz.T).T)
        Plx = Gs @ st.P[:nr, :]
        good = mk & finite & has_free & jnp.all(jnp.isfinite(l)) & jnp.all(jnp.isfinite(Pll))
        st = es.add_landmark(st, model, slot, l, Pll, Plx, idk, ok=good)
        over = mk & finite & ~has_free
        st = st._replace(
            overflow=st.overflow + over.astype(jnp.int32),
            status=st.status
            | jnp.where(over, jnp.int32(errors.CAPACITY_OVERFLOW), 0)
            | jnp.where(mk & ~finite, jnp.int32(errors.MASKED_INPUT), 0),
        )
        return st, None

    state, _ = jax.lax.scan(body, state, (z, lm_ids.astype(jnp.int32), mask, R))
    return state


def _random_state(rng, cap, n_active):
    """A random consistent posterior: robot + n_active landmarks in random slots, P SPD on them."""
    nr, dl = 3, 2
    n = nr + cap * dl
    slots = rng.choice(cap, size=n_active, replace=False)
    act = np.zeros(cap, bool)
    act[slots] = True
    use = np.concatenate([np.arange(nr)] + [nr + dl * s + np.arange(dl) for s in np.sort(slots)])
    A = rng.normal(size=(use.size, use.size)) * 0.1
    P = np.zeros((n, n))
    P[np.ix_(use, use)] = A @ A.T + 0.01 * np.eye(use.size)
    x = np.zeros(n)
    x[use] = rng.normal(size=use.size) * 3.0
    ids = np.where(act, np.arange(cap) + 100, -1).astype(np.int32)
    return es.SlamState(x=jnp.asarray(x), P=jnp.asarray(P), active=jnp.asarray(act), ids=jnp.asarray(ids),
                        status=jnp.zeros((), jnp.int32), overflow=jnp.zeros((), jnp.int32))


@pytest.mark.parametrize("cap,n_active,K", [(12, 4, 5), (8, 6, 5), (6, 6, 3), (10, 0, 6)])
def test_batched_register_equals_sequential(cap, n_active, K):
    """Joint registration == the former sequential one (float64, 1e-12), incl. overflow/masks."""
    rng = np.random.default_rng(cap * 100 + n_active * 10 + K)
    # both registrations in one compiled program
    reg = jax.jit(lambda st, z, i, m, R: (es.register(st, MODEL, z, i, m, R),
                                          _register_sequential(st, MODEL, z, i, m, R)))
    for trial in range(4):
        st = _random_state(rng, cap, n_active)
        z = np.stack([rng.uniform(1, 20, K), rng.uniform(-np.pi, np.pi, K)], 1)
        m = rng.uniform(size=K) < 0.8
        if trial >= 2:
            z[rng.integers(K)] = np.nan  # a non-finite candidate (masked or not)
            z[rng.integers(K), 1] = np.inf
        Rk = np.stack([np.diag(rng.uniform(0.01, 0.2, 2)) for _ in range(K)])
        ids = np.arange(K, dtype=np.int32) + 7
        args = (st, jnp.asarray(z), jnp.asarray(ids), jnp.asarray(m), jnp.asarray(Rk))
        b, s = reg(*args)
        np.testing.assert_allclose(np.asarray(b.x), np.asarray(s.x), atol=1e-12, rtol=0)
        np.testing.assert_allclose(np.asarray(b.P), np.asarray(s.P), atol=1e-12, rtol=0)
        np.testing.assert_array_equal(np.asarray(b.active), np.asarray(s.active))
        np.testing.assert_array_equal(np.asarray(b.ids), np.asarray(s.ids))
        assert int(b.overflow) == int(s.overflow) and int(b.status) == int(s.status)
        np.testing.assert_array_equal(np.asarray(b.P), np.asarray(b.P).T)
    # the overflow cases really overflow
    if cap - n_active < K:
        assert int(b.overflow) > 0 or not np.any(m)


# ---------------------------------------------------------------- NaN hazard of unused rows
def test_masked_rows_and_inactive_slots_never_poison_robot_at_origin():
    """Robot exactly at the origin, inactive slots at 0: atan2'(0, 0) and √'(0) are NaN/inf.

    The engine evaluates the observation also for masked rows and inactive slots; their
    values, Jacobians and derivatives must not leak (update, associate_nn, register; value
    and jvp here, grad in the slow test below).
    """
    R_ = jnp.asarray(R)
    st0 = es.init(jnp.zeros(3), jnp.diag(jnp.array([1e-4, 1e-4, 1e-5])), 4, 2)
    z_reg = jnp.array([[5.0, 0.3], [4.0, -0.2]])
    z = jnp.array([[5.01, 0.301], [7.0, 1.0], [jnp.nan, 0.0]])
    slots = jnp.array([0, 3, 2])  # slot 3 and 2 inactive (mean 0 = robot position)
    mask = jnp.array([True, True, False])

    def step(x0, r_scale):
        st = st0._replace(x=st0.x.at[:3].set(x0))
        st = es.register(st, MODEL, z_reg, jnp.array([0, 1]), jnp.array([True, False]), R_ * r_scale)
        sl, matched, new, d2 = es.associate_nn(st, MODEL, z, mask, R_ * r_scale)
        st, info = es.update(st, MODEL, z, slots, mask, R_ * r_scale)
        return st, d2, info

    def loss_and_value(x0):
        out = step(x0, 1.0)
        return _loss_of(*out), out

    # One compiled program: the jvp's primal pass is the value checked first.
    x0 = jnp.zeros(3)
    _, t, (st, d2, info) = jax.jit(lambda a, ta: jax.jvp(loss_and_value, (a,), (ta,), has_aux=True))(
        x0, jnp.array([1.0, -0.5, 0.2]))
    assert np.all(np.isfinite(np.asarray(st.x))) and np.all(np.isfinite(np.asarray(st.P)))
    assert bool(np.isfinite(np.asarray(d2)[0])) and int(info.dof) == 2
    assert np.asarray(info.used).tolist() == [True, False, False]
    assert np.isfinite(float(t))


def _loss_of(st, d2, info):
    return jnp.sum(st.x) + jnp.sum(st.P) + info.nis + d2[0]


def _origin_loss(step, x0, r_scale):
    return _loss_of(*step(x0, r_scale))


@pytest.mark.slow
def test_masked_rows_and_inactive_slots_never_poison_the_gradient():
    """The reverse-mode half of the test above (its compile dominates; jvp runs by default)."""
    R_ = jnp.asarray(R)
    st0 = es.init(jnp.zeros(3), jnp.diag(jnp.array([1e-4, 1e-4, 1e-5])), 4, 2)
    z_reg = jnp.array([[5.0, 0.3], [4.0, -0.2]])
    z = jnp.array([[5.01, 0.301], [7.0, 1.0], [jnp.nan, 0.0]])

    def step(x0, r_scale):
        st = st0._replace(x=st0.x.at[:3].set(x0))
        st = es.register(st, MODEL, z_reg, jnp.array([0, 1]), jnp.array([True, False]), R_ * r_scale)
        _, _, _, d2 = es.associate_nn(st, MODEL, z, jnp.array([True, True, False]), R_ * r_scale)
        st, info = es.update(st, MODEL, z, jnp.array([0, 3, 2]), jnp.array([True, True, False]),
                             R_ * r_scale)
        return st, d2, info

    g = jax.jit(jax.grad(lambda a, r: _origin_loss(step, a, r), argnums=(0, 1)))(jnp.zeros(3), 1.0)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in g), g


@pytest.mark.parametrize("num_iter", [1, 4])
def test_iterated_update_equals_generic_iterated_ekf(num_iter):
    """The engine's iterated update = the generic iterated EKF on the whole state vector."""
    from jaxslam.filters import ekf

    rng = np.random.default_rng(5)
    cap = 6
    st = _random_state(rng, cap, 4)
    act = np.flatnonzero(np.asarray(st.active))
    slots = np.array([act[0], act[2], act[3]], np.int32)
    mask = np.array([True, False, True])
    x = np.asarray(st.x)
    # measurements far from the prediction, so that re-linearising matters
    z = np.stack([np.asarray(observe(jnp.asarray(x[:3]), jnp.asarray(x[3 + 2 * k:5 + 2 * k]), None))
                  for k in slots]) + np.array([[0.8, 0.3], [9.0, 9.0], [-0.6, -0.25]])
    R = np.diag([0.05**2, 0.03**2])
    # jitted: one program each, not one per operation
    post, info = jax.jit(lambda st, z: es.update(st, MODEL, z, jnp.asarray(slots), jnp.asarray(mask), R,
                                                 num_iter=num_iter))(st, jnp.asarray(z))
    use = slots[mask]

    def h_full(v):
        return jnp.concatenate([observe(v[:3], v[3 + 2 * k:5 + 2 * k], None) for k in use])

    res = ekf.angle_residual([False, True] * len(use))
    g, ginfo = jax.jit(lambda m, c: ekf.update(ekf.Gaussian(m, c), z[mask].reshape(-1), h_full,
                                               np.kron(np.eye(len(use)), R), residual=res,
                                               num_iter=num_iter))(st.x, st.P)
    np.testing.assert_allclose(np.asarray(post.x), np.asarray(g.mean), atol=1e-10)
    np.testing.assert_allclose(np.asarray(post.P), np.asarray(g.cov), atol=1e-10)
    np.testing.assert_allclose(float(info.nis), float(ginfo.nis), rtol=1e-10)
    conv = bool(int(post.status) & errors.NOT_CONVERGED)
    assert conv == bool(int(ginfo.status) & errors.NOT_CONVERGED)


def test_smooth_robot_equals_full_state_rts():
    """Map static: the engine's robot-only RTS pass = the generic RTS smoother on [s; map]."""
    from jaxslam.filters import ekf, smoother

    n_lm, K, T = 5, 3, 40
    us, zs, ids, masks = make_log(seed=3, T=T, n_lm=n_lm, K=K)
    rng = np.random.default_rng(4)
    lm0 = np.random.default_rng(3).uniform(-8, 8, size=(n_lm, 2)) + rng.normal(0, 0.5, (n_lm, 2))
    cap = n_lm + 2  # two free slots: they must change nothing
    x0 = np.concatenate([np.zeros(3), lm0.reshape(-1), np.zeros(4)])
    P0 = np.zeros((3 + 2 * cap,) * 2)
    P0[:3, :3] = np.diag([1e-2, 1e-2, 1e-3])
    P0[3:3 + 2 * n_lm, 3:3 + 2 * n_lm] = 0.25 * np.eye(2 * n_lm)
    st0 = es.SlamState(x=jnp.asarray(x0), P=jnp.asarray(P0),
                       active=jnp.asarray(np.arange(cap) < n_lm),
                       ids=jnp.asarray(np.where(np.arange(cap) < n_lm, np.arange(cap), -1), jnp.int32),
                       status=jnp.zeros((), jnp.int32), overflow=jnp.zeros((), jnp.int32))

    def body(st, inp):
        u, z, i, m = inp
        st = es.predict(st, MODEL, u, jnp.asarray(Q))
        slots, mapped = es.associate_known(st, i, m)
        st, _ = es.update(st, MODEL, z, slots, mapped, jnp.asarray(R))
        return st, (es.smoother_terms(st, MODEL), st.x[:3])

    final, (terms, filt) = jax.lax.scan(body, st0, (us, zs, ids, masks))
    Qs = jnp.broadcast_to(jnp.asarray(Q), (T, 3, 3))

    def diff(a, b):
        d = a - b
        return d.at[2].set(wrap_angle(d[2]))

    rs, st = es.smooth_robot(MODEL, terms, us, Qs, final, difference=diff)
    assert not np.any(np.asarray(st))

    # oracle: the generic EKF + RTS on the dense state (landmarks n_lm, no free slots)
    n = 3 + 2 * n_lm

    def f_full(x, u):
        return jnp.concatenate([motion(x[:3], u, None), x[3:]])

    def h_full(x, c):
        L = x[3:].reshape(n_lm, 2)[c]
        return jax.vmap(lambda l: observe(x[:3], l, None))(L).reshape(-1)

    Qf = np.zeros((n, n))
    Qf[:3, :3] = Q
    res = ekf.angle_residual([False, True] * K)
    mk = np.repeat(masks, 2, axis=1)
    post = ekf.filter_scan(f_full, h_full, x0[:n], P0[:n, :n], us, zs.reshape(T, -1), mk, Qf,
                           np.kron(np.eye(K), R), residual=res, h_inputs=jnp.asarray(ids),
                           save_smoother=True)
    np.testing.assert_allclose(np.asarray(filt), np.asarray(post.means[:, :3]), atol=1e-10)
    sm = smoother.rts(post, difference=lambda a, b: diff(a, b))
    np.testing.assert_allclose(np.asarray(rs), np.asarray(sm.means[:, :3]), atol=1e-9)
    # the smoothed map is the final filtered map at every step
    np.testing.assert_allclose(np.asarray(sm.means[:, 3:]),
                               np.broadcast_to(np.asarray(final.x[3:n]), (T, n - 3)), atol=1e-9)
    assert np.max(np.abs(np.asarray(rs) - np.asarray(filt))) > 1e-3  # smoothing did something


def test_smoother_terms_flag_a_map_block_that_does_not_factor():
    """An indefinite map block (e.g. float32 round-off): W = 0 for that step, and the flag
    reaches smooth_robot's status instead of vanishing."""
    cap = 2
    P = np.eye(3 + 2 * cap) * 0.1
    P[3:, 3:] = np.array([[1.0, 0, 2.0, 0], [0, 1.0, 0, 2.0], [2.0, 0, 1.0, 0], [0, 2.0, 0, 1.0]])
    P[0, 3] = P[3, 0] = 0.05
    good = np.eye(3 + 2 * cap) * 0.1
    good[0, 3] = good[3, 0] = 0.05

    def state(P):
        return es.SlamState(x=jnp.zeros(3 + 2 * cap), P=jnp.asarray(P), active=jnp.ones(cap, bool),
                            ids=jnp.arange(cap, dtype=jnp.int32), status=jnp.zeros((), jnp.int32),
                            overflow=jnp.zeros((), jnp.int32))

    bad_t, good_t = es.smoother_terms(state(P), MODEL), es.smoother_terms(state(good), MODEL)
    assert int(bad_t.status) == errors.NOT_PSD and not np.any(np.asarray(bad_t.W))
    assert int(good_t.status) == 0 and np.asarray(good_t.W)[0, 0] == pytest.approx(0.5)
    terms = jax.tree.map(lambda a, b, c: jnp.stack([a, b, c]), good_t, bad_t, good_t)
    us = jnp.zeros((3,) + np.shape(make_log(seed=0, T=1, n_lm=1, K=1)[0])[1:])
    _, st = es.smooth_robot(MODEL, terms, us, jnp.broadcast_to(jnp.asarray(Q), (3, 3, 3)), state(good))
    assert [int(v) & errors.NOT_PSD for v in np.asarray(st)] == [0, errors.NOT_PSD, 0]


# ------------------------------------------------------- the whole-sequence runner (es.run)
P0_RUN = np.diag([1e-4, 1e-4, 1e-5])


def test_run_matches_dense_numpy_oracle():
    """``ekf_slam.run`` (predict, associate by id, update, register) = the dense oracle, step by
    step: robot track, NIS, innovation log-likelihood, map; per-step and function-valued Q give
    the same run as the constant matrix."""
    us, zs, ids, masks = make_log(seed=5)
    T = len(us)
    log = es.SlamLog(u=jnp.asarray(us), z=jnp.asarray(zs), ids=jnp.asarray(ids), mask=jnp.asarray(masks))
    st0 = es.init(jnp.zeros(3), jnp.asarray(P0_RUN), 16, 2)
    run = jax.jit(es.run, static_argnames=("model", "association", "register_new", "save_cov", "save_map"))
    out = run(MODEL, st0, log, jnp.asarray(Q), jnp.asarray(R), save_cov=True)
    o, nis_o = oracle_run(us, zs, ids, masks)
    np.testing.assert_allclose(np.asarray(out.robot), o.track, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.nis), nis_o, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.log_likelihood), o.ll, rtol=1e-9, atol=1e-9)
    L = engine_landmarks(out.final)
    assert sorted(L) == sorted(o.ids)
    for j, i in enumerate(o.ids):
        np.testing.assert_allclose(L[i], o.x[3 + 2 * j: 5 + 2 * j], atol=1e-10)
    assert int(np.sum(out.n_new)) == len(o.ids) and out.robot_cov.shape == (T, 3, 3)
    per_step = run(MODEL, st0, log, jnp.broadcast_to(jnp.asarray(Q), (T, 3, 3)), jnp.asarray(R))
    as_fn = es.run(MODEL, st0, log, lambda s, u, p: jnp.asarray(Q), jnp.asarray(R))
    for other in (per_step, as_fn):
        np.testing.assert_allclose(np.asarray(other.robot), np.asarray(out.robot), atol=1e-13)


def test_run_bad_inputs_name_the_argument():
    from jaxslam.errors import InputError

    us, zs, ids, masks = make_log(seed=5, T=5)
    log = es.SlamLog(u=us, z=zs, ids=ids, mask=masks)
    st0 = es.init(jnp.zeros(3), jnp.asarray(P0_RUN), 16, 2)
    cases = [
        (dict(log=log._replace(z=zs[..., 0])), "^log.z: expected shape"),
        (dict(log=log._replace(ids=ids[:, :2])), "^log.ids: expected shape"),
        (dict(log=log._replace(mask=masks[:3])), "^log.mask: expected shape"),
        (dict(log=log._replace(u=us[:4])), "^log.u: every leaf needs a leading axis of 5"),
        (dict(Q=np.eye(2)), "^Q: expected shape"),
        (dict(Q=-np.eye(3)), "^Q"),
        (dict(R=np.zeros((2, 2))), "^R"),
        (dict(R=np.broadcast_to(R, (4, 2, 2))), "^R: expected shape"),
        (dict(association="ml"), "^association"),
        (dict(state=st0._replace(x=st0.x[:10])), "^state"),
    ]
    for over, pat in cases:
        kw = dict(model=MODEL, state=st0, log=log, Q=Q, R=R)
        kw.update(over)
        with pytest.raises(InputError, match=pat):
            es.run(**kw)


# ------------------------------------------------------------ active-block update

@pytest.mark.parametrize("form", ["joseph", "standard"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("n,hi", [(10, 4), (57, 57), (130, 64), (130, 65), (203, 203), (203, 150), (203, 0)])
def test_tiled_corrections_match_numpy(n, hi, dtype, form):
    """Tiles (64, the last clamped) of sym_rank_update against P − ½ (U Vᵀ + V Uᵀ) and of
    sym_outer_update against P − U Uᵀ in NumPy: equal where the rows are live, untouched beyond
    ``hi``, symmetric to the bit."""
    rng = np.random.default_rng(n + hi)
    A = rng.normal(size=(n, n))
    P = A @ A.T
    U, V = rng.normal(size=(n, 5)), rng.normal(size=(n, 5))
    U[hi:], V[hi:] = 0.0, 0.0
    P[hi:, hi:] = rng.normal(size=(n - hi, n - hi))  # garbage beyond hi: must stay as it is
    P[hi:, hi:] = P[hi:, hi:] + P[hi:, hi:].T
    if form == "joseph":
        want = P - 0.5 * (U @ V.T + V @ U.T)
        out = jax.jit(es.sym_rank_update)(*(jnp.asarray(a, dtype) for a in (P, U, V)), hi)
    else:
        want = P - U @ U.T
        out = jax.jit(es.sym_outer_update)(jnp.asarray(P, dtype), jnp.asarray(U, dtype), hi)
    out = np.asarray(out)
    assert out.dtype == dtype
    tol = 1e-12 if dtype == np.float64 else 2e-4
    np.testing.assert_allclose(out, want, atol=tol * max(1.0, np.abs(want).max()))
    np.testing.assert_array_equal(out, out.T)
    np.testing.assert_array_equal(out[hi:, hi:], P[hi:, hi:].astype(dtype))


def test_tiled_corrections_derivatives_and_vmap():
    """JVPs of sym_rank_update and sym_outer_update equal their closed-form linear maps; reverse
    mode and vmap (batched ``hi``: every run gets the batch's largest) and nested vmap (the
    batching rule at both levels) agree with the dense formulas."""
    rng = np.random.default_rng(0)
    n, r = 90, 3
    A = rng.normal(size=(n, n))
    P, U, V = A @ A.T, rng.normal(size=(n, r)), rng.normal(size=(n, r))
    dP, dU, dV = rng.normal(size=(n, n)), rng.normal(size=(n, r)), rng.normal(size=(n, r))
    dP = dP + dP.T
    _, t = jax.jvp(lambda P_, U_, V_: es.sym_rank_update(P_, U_, V_, n), (P, U, V), (dP, dU, dV))
    np.testing.assert_allclose(t, dP - 0.5 * (dU @ V.T + U @ dV.T + dV @ U.T + V @ dU.T), atol=1e-12)
    _, t = jax.jvp(lambda P_, U_: es.sym_outer_update(P_, U_, n), (P, U), (dP, dU))
    np.testing.assert_allclose(t, dP - dU @ U.T - U @ dU.T, atol=1e-12)
    W = rng.normal(size=(n, n))
    g = jax.grad(lambda U_: jnp.sum(W * es.sym_rank_update(P, U_, V, n)))(U)
    np.testing.assert_allclose(g, -0.5 * (W @ V + W.T @ V), atol=1e-12)
    g = jax.grad(lambda U_: jnp.sum(W * es.sym_outer_update(P, U_, n)))(U)
    np.testing.assert_allclose(g, -(W + W.T) @ U, atol=1e-12)
    # the dense forms of the full-state update (active_only=False): same values, tangents and
    # gradients (they are written as T + Tᵀ so that reverse mode needs two products, not four)
    np.testing.assert_allclose(es._sym_rank_update_dense(P, U, V), P - 0.5 * (U @ V.T + V @ U.T), atol=1e-12)
    np.testing.assert_allclose(es._sym_outer_update_dense(P, U), P - U @ U.T, atol=1e-12)
    _, t = jax.jvp(es._sym_rank_update_dense, (P, U, V), (dP, dU, dV))
    np.testing.assert_allclose(t, dP - 0.5 * (dU @ V.T + U @ dV.T + dV @ U.T + V @ dU.T), atol=1e-12)
    _, t = jax.jvp(es._sym_outer_update_dense, (P, U), (dP, dU))
    np.testing.assert_allclose(t, dP - dU @ U.T - U @ dU.T, atol=1e-12)
    g = jax.grad(lambda U_, V_: jnp.sum(W * es._sym_rank_update_dense(P, U_, V_)), (0, 1))(U, V)
    np.testing.assert_allclose(g[0], -0.5 * (W @ V + W.T @ V), atol=1e-12)
    np.testing.assert_allclose(g[1], -0.5 * (W.T @ U + W @ U), atol=1e-12)
    g = jax.grad(lambda U_: jnp.sum(W * es._sym_outer_update_dense(P, U_)))(U)
    np.testing.assert_allclose(g, -(W + W.T) @ U, atol=1e-12)
    his = np.array([40, 90, 0])
    Us, Vs = np.stack([U] * 3), np.stack([V] * 3)
    for k, h in enumerate(his):
        Us[k, h:], Vs[k, h:] = 0.0, 0.0
    out = jax.jit(jax.vmap(es.sym_rank_update, in_axes=(None, 0, 0, 0)))(P, Us, Vs, his)
    outer = jax.jit(jax.vmap(es.sym_outer_update, in_axes=(None, 0, 0)))(P, Us, his)
    nested = jax.jit(jax.vmap(jax.vmap(es.sym_outer_update, in_axes=(None, 0, 0)), in_axes=(None, 0, 0)))(
        P, np.stack([Us, Us[::-1]]), np.stack([his, his[::-1]]))
    for k in range(3):
        np.testing.assert_allclose(out[k], P - 0.5 * (Us[k] @ Vs[k].T + Vs[k] @ Us[k].T), atol=1e-12)
        np.testing.assert_allclose(outer[k], P - Us[k] @ Us[k].T, atol=1e-12)
        np.testing.assert_allclose(nested[1, k], P - Us[2 - k] @ Us[2 - k].T, atol=1e-12)


# the dense correction (whole state) and the tiled one (active block; plain updates of it also
# in tests/benchmarks/test_bench_twin.py against the NumPy twin)
@pytest.mark.parametrize("kw,active_only", [({}, False), ({"robust": 4.0}, True), ({"num_iter": 3}, True)],
                         ids=["plain-whole", "robust-active_only", "iterated-active_only"])
def test_standard_form_update_equals_joseph(kw, active_only):
    """joseph=False (P − K S Kᵀ) gives the Joseph form's estimates: the same x to rounding and P
    to 1e-12 (they differ in exact arithmetic only through K's optimality), exactly symmetric."""
    cap, K = 100, 12
    st = _holey_state(5, cap=cap)
    act = np.flatnonzero(np.asarray(st.active))[:K]
    slots = jnp.asarray(act, jnp.int32)
    lm = np.asarray(es.landmarks(st, MODEL))[act]
    z = jax.vmap(lambda l: observe(st.x[:3], l, None))(jnp.asarray(lm))
    z = z + jnp.asarray(np.random.default_rng(2).normal(size=z.shape) * np.array([0.05, 0.01]))
    mask = jnp.ones(len(act), bool)
    # _update_jit (below): the Joseph form (the default) is then the program of the same case of
    # test_active_only_update_equals_whole_state_update (the same shapes: 12 rows, capacity 100),
    # compiled once for both tests
    kw = tuple(sorted(kw.items()))
    a, ia = _update_jit(st, z, slots, mask, active_only, kw)
    b, ib = _update_jit(st, z, slots, mask, active_only, tuple(sorted(kw + (("joseph", False),))))
    np.testing.assert_allclose(np.asarray(b.x), np.asarray(a.x), atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.P), np.asarray(a.P), atol=1e-12)
    assert np.abs(np.asarray(b.P) - np.asarray(st.P)).max() > 1e-4  # the update did move P
    np.testing.assert_array_equal(np.asarray(b.P), np.asarray(b.P).T)
    np.testing.assert_allclose(float(ib.nis), float(ia.nis), rtol=1e-10)
    assert int(a.status) == int(b.status)


def _holey_state(seed, cap=24, spread=False):
    """A map with free slots between active ones (a pruned landmark); ``spread``: the slots
    permuted so that active ones sit up to the last slot."""
    us, zs, ids, masks = make_log(seed=seed, n_lm=16, K=12)
    st, _ = engine_run(es.init(jnp.zeros(3), jnp.diag(jnp.array([1e-4, 1e-4, 1e-5])), cap, 2),
                       us, zs, ids, masks)
    act = np.asarray(st.active)
    drop = int(np.flatnonzero(act)[1])
    keep = np.ones(st.x.shape[0], bool)
    keep[3 + 2 * drop: 5 + 2 * drop] = False
    st = st._replace(x=jnp.where(keep, st.x, 0.0), P=jnp.where(keep[:, None] & keep[None, :], st.P, 0.0),
                     active=st.active.at[drop].set(False), ids=st.ids.at[drop].set(-1))
    if spread:
        perm = np.random.default_rng(seed).permutation(cap)
        perm = np.concatenate([perm[perm >= cap - 4], perm[perm < cap - 4]])  # an active slot near the end
        idx = np.concatenate([np.arange(3)] + [3 + 2 * p + np.arange(2) for p in perm])
        x, P, act_, lid = (np.asarray(a) for a in (st.x, st.P, st.active, st.ids))
        inv = np.argsort(perm)
        idx_inv = np.concatenate([np.arange(3)] + [3 + 2 * p + np.arange(2) for p in inv])
        st = st._replace(x=jnp.asarray(x[idx_inv]), P=jnp.asarray(P[np.ix_(idx_inv, idx_inv)]),
                         active=jnp.asarray(act_[inv]), ids=jnp.asarray(lid[inv]))
        del idx
    return st


@functools.partial(jax.jit, static_argnums=(4, 5))
def _update_jit(st, z, slots, mask, active_only, kw):
    """es.update jitted once for the cases below (kw: its (name, value) pairs): one program per
    kw and mode, shared by the cases, instead of one per operation."""
    return es.update(st, MODEL, z, slots, mask, jnp.asarray(R), active_only=active_only, **dict(kw))


@pytest.mark.parametrize("spread", [False, True], ids=["leading", "spread"])
@pytest.mark.parametrize("kw,n_rows", [({}, 7), ({}, 3), ({"gate": 5.99}, 7), ({"robust": 4.0}, 7),
                                       ({"num_iter": 3}, 7)],
                         ids=["plain", "few-rows", "gate", "robust", "iterated"])
def test_active_only_update_equals_whole_state_update(kw, n_rows, spread):
    # capacity 100: gain blocks of 50 / 100 slots (spread: the active slots reach the end);
    # 12 rows of 2 scalars: the valid ones compacted into 6 (few-rows) or 12
    cap, K = 100, 12
    st = _holey_state(5, cap=cap, spread=spread)
    act = np.flatnonzero(np.asarray(st.active))
    free = np.flatnonzero(~np.asarray(st.active))
    # rows: n_rows + 1 active slots (one masked), two free slots, the rest free too; shuffled
    rows = np.concatenate([act[:n_rows + 1], free[:K - n_rows - 1]])
    rows = rows[np.random.default_rng(1).permutation(K)]
    slots = jnp.asarray(rows, jnp.int32)
    rng = np.random.default_rng(2)
    lm = np.asarray(es.landmarks(st, MODEL))[rows]
    z = jax.vmap(lambda l: observe(st.x[:3], l, None))(jnp.asarray(lm))
    z = z + jnp.asarray(rng.normal(size=(K, 2)) * np.array([0.05, 0.01]))
    first = int(np.flatnonzero(np.isin(rows, act))[0])
    z = z.at[first].set(z[first] + jnp.array([1.0, 0.0]))  # an outlier for the gate / robust weights
    masked = int(np.flatnonzero(np.isin(rows, act))[1])
    mask = jnp.ones(K, bool).at[masked].set(False)
    assert int(np.sum(np.isin(rows, act))) - 1 == n_rows
    kw = tuple(sorted(kw.items()))
    a, ia = _update_jit(st, z, slots, mask, False, kw)
    b, ib = _update_jit(st, z, slots, mask, True, kw)
    np.testing.assert_allclose(np.asarray(b.x), np.asarray(a.x), atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.P), np.asarray(a.P), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(b.P), np.asarray(b.P).T)
    for f in ("nis", "logdet", "dof", "used", "gated", "d2"):
        np.testing.assert_allclose(np.asarray(getattr(ib, f)), np.asarray(getattr(ia, f)), atol=1e-10)
    assert int(a.status) == int(b.status)


def test_active_only_update_derivatives_and_vmap():
    """grad, jacfwd and vmap (two runs with different maps; and vmap of grad) of the
    active-block update equal the whole-state update's."""
    sts = [_holey_state(5), _holey_state(6)]
    S = jax.tree.map(lambda a, b: jnp.stack([a, b]), *sts)
    slots = jnp.arange(6, dtype=jnp.int32)
    z = jnp.tile(jnp.array([[3.0, 0.1]]), (6, 1))

    def loss(logr, st, active_only):
        Rm = jnp.diag(jnp.exp(logr))
        out, info = es.update(st, MODEL, z, slots, jnp.ones(6, bool), Rm, active_only=active_only,
                              gate=50.0)
        return jnp.sum(out.P ** 2) + jnp.sum(out.x) + info.nis

    lr = jnp.log(jnp.array([0.05**2, 0.01**2]))
    for d in (jax.grad, jax.jacfwd):  # jitted: one program each, not one per operation
        dj = jax.jit(d(loss), static_argnums=2)
        np.testing.assert_allclose(dj(lr, sts[0], True), dj(lr, sts[0], False), rtol=1e-10)
    vg = jax.jit(jax.vmap(jax.grad(loss), in_axes=(None, 0, None)), static_argnums=2)
    np.testing.assert_allclose(vg(lr, S, True), vg(lr, S, False), rtol=1e-10)
    vP = jax.jit(jax.vmap(lambda st, ao: es.update(st, MODEL, z, slots, jnp.ones(6, bool), jnp.asarray(R),
                                                   active_only=ao)[0].P, in_axes=(0, None)), static_argnums=1)
    np.testing.assert_allclose(vP(S, True), vP(S, False), atol=1e-12)


# jitted once for both cases below: one program each, shared by the cases, not one per operation
_assoc_jit = jax.jit(lambda st, z, mask, ao: es.associate_nn(st, MODEL, z, mask, jnp.asarray(R), active_only=ao),
                     static_argnums=3)
_vassoc_jit = jax.jit(jax.vmap(_assoc_jit, in_axes=(0, 0, None, None)), static_argnums=3)
_marginal_d2_jit = jax.jit(lambda st, z, mask, ao: es.marginal_d2(st, MODEL, z, mask, jnp.asarray(R), active_only=ao),
                           static_argnums=3)


@pytest.mark.parametrize("spread", [False, True], ids=["leading", "spread"])
def test_active_only_association_equals_the_whole_table(spread):
    """Nearest-neighbour association on the leading block of slots (capacity 100: blocks of 32,
    50, 100) equals the whole table's, alone and vmapped over two maps of different fill: the
    same slots, matches and new rows, d² to rounding (another XLA program: 1 ulp measured)."""
    sts = [_holey_state(5, cap=100, spread=spread), _holey_state(6, cap=100, spread=spread)]
    K = 8
    rng = np.random.default_rng(3)

    def rows_of(st):
        act = np.flatnonzero(np.asarray(st.active))[:K - 2]
        lm = np.asarray(es.landmarks(st, MODEL))[act]
        z = jax.vmap(lambda l: observe(st.x[:3], l, None))(jnp.asarray(lm))
        z = z + jnp.asarray(rng.normal(size=z.shape) * np.array([0.05, 0.01]))
        return jnp.concatenate([z, jnp.array([[40.0, 1.0], [25.0, -1.2]])])  # two far: new

    zs = [rows_of(st) for st in sts]
    mask = jnp.ones(K, bool).at[2].set(False)
    for st, z in zip(sts, zs):
        a = _assoc_jit(st, z, mask, False)
        b = _assoc_jit(st, z, mask, True)
        for x, y in zip(a[:3], b[:3]):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        np.testing.assert_allclose(np.asarray(b[3]), np.asarray(a[3]), rtol=1e-12)
        assert bool(np.asarray(a[2])[-1])  # the far rows are new landmarks
    S = jax.tree.map(lambda a, b: jnp.stack([a, b]), *sts)
    Z = jnp.stack(zs)
    va, vb = _vassoc_jit(S, Z, mask, False), _vassoc_jit(S, Z, mask, True)
    for x, y in zip(va[:3], vb[:3]):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_allclose(np.asarray(vb[3]), np.asarray(va[3]), rtol=1e-12)
    d2a, _ = _marginal_d2_jit(sts[0], zs[0], mask, False)
    d2b, (zh, _, _, _) = _marginal_d2_jit(sts[0], zs[0], mask, True)
    np.testing.assert_allclose(np.asarray(d2b), np.asarray(d2a), rtol=1e-12)  # inf where inf
    assert zh.shape == (100, 2)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("n,hi", [(9, 9), (57, 57), (57, 20), (203, 203), (203, 140), (203, 3)])
def test_robot_cross_update_matches_numpy(n, hi, dtype):
    """Strips (64 wide, the last clamped) against F P_rl in NumPy: the robot rows and columns
    up to ``hi`` moved, the rest untouched, symmetric to the bit."""
    nr = 3
    rng = np.random.default_rng(n + hi)
    A = rng.normal(size=(n, n))
    P = A @ A.T
    P[:nr, hi:], P[hi:, :nr] = 0.0, 0.0
    F = rng.normal(size=(nr, nr))
    want = P.copy()
    want[:nr, nr:] = F @ P[:nr, nr:]
    want[nr:, :nr] = want[:nr, nr:].T
    out = np.asarray(jax.jit(es.robot_cross_update)(jnp.asarray(P, dtype), jnp.asarray(F, dtype), hi))
    tol = 1e-12 if dtype == np.float64 else 1e-4
    np.testing.assert_allclose(out, want, atol=tol * np.abs(want).max())
    np.testing.assert_array_equal(out, out.T)
    np.testing.assert_array_equal(out[nr:, nr:], P[nr:, nr:].astype(dtype))


def test_robot_cross_update_derivatives_and_vmap():
    rng = np.random.default_rng(3)
    n, nr = 150, 3
    A = rng.normal(size=(n, n))
    P, F = A @ A.T, rng.normal(size=(nr, nr))
    dP, dF = rng.normal(size=(n, n)), rng.normal(size=(nr, nr))
    dP = dP + dP.T
    _, t = jax.jvp(lambda P_, F_: es.robot_cross_update(P_, F_, n), (P, F), (dP, dF))
    want = dP.copy()
    want[:nr, nr:] = dF @ P[:nr, nr:] + F @ dP[:nr, nr:]
    want[nr:, :nr] = want[:nr, nr:].T
    np.testing.assert_allclose(t, want, atol=1e-12)
    W = rng.normal(size=(n, n))
    g = jax.grad(lambda F_: jnp.sum(W * es.robot_cross_update(P, F_, n)))(F)
    np.testing.assert_allclose(g, (W[:nr, nr:] + W[nr:, :nr].T) @ P[nr:, :nr], atol=1e-10)
    his = np.array([60, 150, 3])
    Ps = np.stack([P] * 3)
    for k, h in enumerate(his):
        Ps[k, :nr, h:], Ps[k, h:, :nr] = 0.0, 0.0
    out = jax.jit(jax.vmap(es.robot_cross_update, in_axes=(0, None, 0)))(Ps, F, his)
    for k in range(3):
        want = Ps[k].copy()
        want[:nr, nr:] = F @ Ps[k][:nr, nr:]
        want[nr:, :nr] = want[:nr, nr:].T
        np.testing.assert_allclose(out[k], want, atol=1e-10)


def test_active_only_predict_equals_whole_state_predict():
    st = _holey_state(5, cap=100)
    u, Qm = jnp.array([1.0, 0.3]), jnp.asarray(Q)
    pred = jax.jit(lambda st, u, ao: es.predict(st, MODEL, u, Qm, active_only=ao),
                   static_argnums=2)  # one program each, not one per operation
    a = pred(st, u, False)
    b = pred(st, u, True)
    np.testing.assert_allclose(np.asarray(b.x), np.asarray(a.x), atol=0)
    np.testing.assert_allclose(np.asarray(b.P), np.asarray(a.P), atol=1e-14)
    np.testing.assert_array_equal(np.asarray(b.P), np.asarray(b.P).T)
    # a non-finite prediction is rejected block-wise in both
    bad = jnp.array([jnp.nan, 0.0])
    a, b = pred(st, bad, False), pred(st, bad, True)
    np.testing.assert_array_equal(np.asarray(b.P), np.asarray(st.P))
    assert int(a.status) == int(b.status) != 0
