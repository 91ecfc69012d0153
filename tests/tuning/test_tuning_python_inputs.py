"""The tuning package's Python API on awkward inputs: the optimisation loop's bookkeeping (log
objective at a loss <= 0, skips, best parameters, recorded lr, held-out batch), the losses'
masks, the parametrisations' dicts and dtypes, the targets' shared options, robot lists and fit
windows, the --params file's numbers and the LAPACK thread pin.  Oracles: closed forms, NumPy."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import paramfile, runtime
from jaxslam.errors import InputError
from jaxslam.tuning import losses as L
from jaxslam.tuning import optimize as O
from jaxslam.tuning import params as P
from jaxslam.tuning import targets as T
from jaxslam.tuning.targets import linear_gaussian as LG
from jaxslam.tuning.targets import util_uwb as UT

DATA = "tests/data"


def _quad(th, item):
    return jnp.sum((th["a"] - item) ** 2)


@jax.custom_jvp
def _nan_grad(x):
    return x


_nan_grad.defjvp(lambda p, t: (p[0], jnp.nan * t[0]))  # finite value, NaN derivative


# ---------------------------------------------------------------------------- optimize.fit

def test_log_objective_never_climbs_a_negative_loss_and_names_log_objective():
    """Item 1: the mean loss ≤ 0 has no log: the old g / loss flipped the gradient's sign and the
    fit climbed (-7.5 → +1.3); now each such update is skipped, counted and the stop names it."""
    def neg(th, it):
        return jnp.sum((th["a"] - it) ** 2) - 10.0

    items = jnp.array([[1.0], [2.0]])
    res = O.fit(neg, {"a": jnp.zeros(1)}, items, 20, 0.1, log_objective=True, schedule="constant")
    losses = [h["loss"] for h in res.history]
    assert losses[0] == pytest.approx(-7.5)  # (1 + 4) / 2 - 10
    assert max(losses) <= losses[0] and float(res.theta["a"][0]) == 0.0  # never moved uphill
    assert res.n_skipped == 3 and all(h["skipped"] and h.get("nonpositive_loss") for h in res.history)
    assert res.stopped.startswith("log_objective: the mean loss was <= 0")


def test_log_objective_at_a_zero_loss_with_zero_gradient_is_no_non_finite_gradient():
    """Item 1: at the optimum of a non-negative loss (0, zero gradient) the log objective's
    gradient is 0, not 0/0: nothing is skipped, the norm recorded is 0."""
    res = O.fit(_quad, {"a": jnp.ones(1)}, jnp.ones((2, 1)), 4, 0.1, log_objective=True)
    assert res.stopped is None and res.n_skipped == 0
    assert [h["grad_norm"] for h in res.history] == [0.0] * 5 and not any(h["skipped"] for h in res.history)
    assert float(res.theta["a"][0]) == 1.0 and all(h["loss"] == 0.0 for h in res.history)


def test_max_skips_zero_runs_every_step_when_nothing_is_skipped():
    """Item 2: max_skips=0 stopped after step 0 ("non-finite at 0 consecutive steps")."""
    res = O.fit(_quad, {"a": jnp.zeros(1)}, jnp.ones((2, 1)), 5, 0.1, max_skips=0)
    assert res.stopped is None and len(res.history) == 6 and float(res.theta["a"][0]) > 0.0
    # and it stops at the first skip (0 tolerated)
    res = O.fit(lambda th, it: jnp.sqrt(jnp.abs(th["a"][0])) + 0.0 * it, {"a": jnp.zeros(1)}, jnp.zeros(2), 5,
                0.1, max_skips=0)
    assert len(res.history) == 1 and res.n_skipped == 1 and "never applied" in res.stopped


@pytest.mark.parametrize("max_skips, n", [(0, 1), (1, 1), (2, 2), (3, 3)])
def test_max_skips_stops_at_that_many_consecutive_skips(max_skips, n):
    """The count the docstring states (fixed to match the code, on which
    test_non_finite_gradient_is_skipped_never_applied and docs/tuning.md's "after 3
    consecutive skips" rely): the loop stops at the max_skips-th skip, 0 and 1 at the first."""
    res = O.fit(lambda th, it: jnp.sqrt(jnp.abs(th["a"][0])) + 0.0 * it, {"a": jnp.zeros(1)}, jnp.zeros(2), 8,
                0.1, max_skips=max_skips)
    assert res.n_skipped == n == len(res.history) and f"non-finite at {n} consecutive steps" in res.stopped


def test_best_theta_compares_only_losses_over_the_same_runs():
    """Item 3: run 1 diverges (NaN) for a >= 0.5; once it is dropped the mean of run 0 alone is
    lower, and best_theta landed where the full batch's loss is NaN.  Oracle: the lowest loss
    among the records that kept both runs."""
    def lf(th, item):
        a = th["a"][0]
        run1 = jnp.where(a < 0.5, (a - 1.0) ** 2 + 1.0, jnp.nan)
        return jnp.where(item[0] > 0, run1, (a - 1.0) ** 2)

    train = jnp.array([[0.0], [1.0]])
    res = O.fit(lf, {"a": jnp.zeros(1)}, train, 15, 0.2, schedule="constant",
                describe=lambda th: float(th["a"][0]))
    assert any(h.get("dropped_runs") == [1] for h in res.history)  # the situation is reached
    full = [h for h in res.history if not h.get("dropped_runs")]
    want = min(full, key=lambda h: h["loss"])["params"]
    best = float(res.best_theta["a"][0])
    assert best == want and best < 0.5
    assert np.isfinite(float(O.batch_loss(lf, res.best_theta, train)))


def test_recorded_lr_is_the_one_applied_after_skipped_steps():
    """Item 4: a skipped step does not advance optax's count; the record said sched(k) (step 6:
    0.861 recorded, 0.964 applied).  Oracle: with a constant gradient of 1 (and no clipping)
    Adam's step is exactly lr / (1 + eps), so each applied update moves θ by its record's lr."""
    def lf(th, item):
        return jax.lax.cond(item[0] > 0, lambda a: _nan_grad(a), lambda a: a, th["a"][0])

    res = O.fit(lf, {"a": jnp.zeros(1)}, jnp.array([[1.0], [0.0]]), 12, 1.0, batch_size=1,
                key=jax.random.PRNGKey(3), clip=None, warmup=4, sequential=True,
                describe=lambda th: float(th["a"][0]))
    h = res.history
    assert res.n_skipped > 0  # the minibatches hit the NaN-gradient run
    _, sched = O.make_optimizer(1.0, 12, warmup=4)
    applied = 0
    for k in range(len(h) - 1):
        step = h[k]["params"] - h[k + 1]["params"]
        assert h[k]["lr"] == pytest.approx(float(sched(applied)), rel=1e-12)
        if h[k]["skipped"]:
            assert step == 0.0
        else:
            assert step == pytest.approx(h[k]["lr"], rel=1e-6)
            applied += 1
    # without skips the record is the schedule at the step index, as before
    r = O.fit(_quad, {"a": jnp.zeros(1)}, jnp.ones((2, 1)), 6, 0.5)
    _, s6 = O.make_optimizer(0.5, 6)
    assert [x["lr"] for x in r.history] == [float(s6(k)) for k in range(7)]


def test_a_held_out_batch_of_wrong_shapes_is_refused_before_the_steps():
    """Item 13: same structure, other item shapes: a bare TypeError at the final evaluation after
    all steps (eval_every=0); now an InputError naming test before compiling."""
    calls = []

    def lf(th, it):
        calls.append(1)
        return jnp.sum((th["a"] - it) ** 2)

    with pytest.raises(InputError, match=r"^test: the loss cannot be evaluated"):
        O.fit(lf, {"a": jnp.zeros(2)}, jnp.ones((2, 2)), 3, 0.1, test=jnp.ones((2, 3)))
    # another number of held-out runs with the same items is fine
    res = O.fit(_quad, {"a": jnp.zeros(2)}, jnp.ones((2, 2)), 2, 0.1, test=jnp.ones((3, 2)))
    assert res.history[-1]["test_loss"] == pytest.approx(float(_quad(res.theta, jnp.ones(2))), rel=1e-12)


def test_final_check_is_never_a_skip_and_a_non_finite_gradient_has_a_nan_norm():
    """Minor: the last record (no update follows) was counted in n_skipped; the norm of a
    non-finite gradient was reported 0.0 (its NaN entries zeroed)."""
    def lf(th, it):  # finite gradient at a = 0, NaN gradient once a > 0.5 (the first step lands at 1)
        return jax.lax.cond(th["a"][0] > 0.5, _nan_grad, lambda a: (a - 3.0) ** 2, th["a"][0]) + 0.0 * it[0]

    res = O.fit(lf, {"a": jnp.zeros(1)}, jnp.zeros((2, 1)), 1, 1.0, schedule="constant")
    assert res.n_skipped == 0 and res.stopped is None and len(res.history) == 2
    assert not res.history[-1]["skipped"] and math.isnan(res.history[-1]["grad_norm"])
    skip = O.fit(lambda th, it: jnp.sqrt(jnp.abs(th["a"][0])) + 0.0 * it, {"a": jnp.zeros(1)}, jnp.zeros(2), 5, 0.1)
    assert all(math.isnan(h["grad_norm"]) for h in skip.history)


# ---------------------------------------------------------------------------- losses

def test_mse_mask_keeps_a_masked_out_nan_out_of_value_and_gradient():
    """Item 5: the mask was multiplied in (NaN · 0 = NaN).  Oracle: NumPy on the kept rows."""
    err = jnp.array([[1.0, 0.0], [jnp.nan, 0.0], [1.0, 2.0]])
    mask = jnp.array([True, False, True])
    e = np.asarray(err)[[0, 2]]
    assert float(L.mse(err, mask=mask)) == pytest.approx(np.mean(np.sum(e ** 2, 1)), rel=1e-15)
    g = np.asarray(jax.grad(lambda x: L.mse(x, mask=mask))(err))
    np.testing.assert_allclose(g, 2.0 * np.where(np.asarray(mask)[:, None], np.asarray(err), 0.0) / 2, rtol=1e-15)


def test_masks_must_be_bool_or_zero_one_integers():
    """Item 6: nees_loss counted a mask [2, 0, 1] as 3 steps (0.164 for a consistent series)."""
    for bad in (jnp.array([2, 0, 1]), jnp.array([1.0, 0.0, 0.5]), jnp.array([1.0, 0.0, 1.0])):
        with pytest.raises(InputError, match="^mask: expected a bool mask"):
            L.nees_loss(jnp.array([2.0, 2.0, 2.0]), 2, bad)
        with pytest.raises(InputError, match="^mask: expected a bool mask"):
            L.mse(jnp.ones((3, 2)), mask=bad)
    for ok in (jnp.array([1, 0, 1]), [True, False, True]):
        assert float(L.nees_loss(jnp.array([2.0, 9.0, 2.0]), 2, ok)) == 0.0
        assert float(L.mse(jnp.array([[1.0], [5.0], [3.0]]), mask=ok)) == pytest.approx(5.0)


def test_mse_refuses_a_one_dimensional_error():
    """Item 7: L.mse(jnp.ones(4)) returned the sum 4.0 (one step of 4 components)."""
    with pytest.raises(InputError, match=r"^err: expected a non-empty \(T, n\)"):
        L.mse(jnp.ones(4))
    assert float(L.mse(jnp.ones((4, 1)))) == 1.0


# ---------------------------------------------------------------------------- params

def test_chol_floor_shifts_every_matrix_by_floor_i_as_documented():
    """Item 8 (documentation): with a floor the log-Cholesky form always factors M + floor·I (a
    PD M too); the log-diagonal form raises only the entries below the floor."""
    M = np.array([[4.0, 1.0], [1.0, 3.0]])
    th = P.theta_from_cov(P.CovSpec("chol", 2), M, floor=1.0)
    np.testing.assert_allclose(np.asarray(P.cov_from_theta(P.CovSpec("chol", 2), th)), M + np.eye(2), rtol=1e-14)
    th = P.theta_from_cov(P.CovSpec("diag", 2), np.diag([0.5, 3.0]), floor=1.0)
    np.testing.assert_allclose(np.exp(np.asarray(th)), [1.0, 3.0], rtol=1e-15)
    for doc in (P.log_chol_from_cov.__doc__, P.__doc__):
        assert "always" in doc or "a positive-definite one included" in doc


def test_pack_and_unpack_name_bad_dicts_dtypes_and_floors():
    """Item 16: lists gave bare TypeError/AttributeError, extra or misspelt names were ignored,
    an integer dtype truncated θ (log 3 → 1), a bogus one was a bare TypeError, floor=inf gave θ inf."""
    specs = {"Q": P.CovSpec("diag", 2)}
    cases = [
        (lambda: P.pack(specs, [np.eye(2)]), r"^mats: expected a dict"),
        (lambda: P.pack(specs, {"Q": np.eye(2)}, floors=[1.0]), r"^floors: expected a dict"),
        (lambda: P.pack(specs, {"Q": np.eye(2), "R": np.eye(2)}), r"^mats: unknown name\(s\) \['R'\]"),
        (lambda: P.pack(specs, {"Q": np.eye(2)}, floors={"q": 1e-3}), r"^floors: unknown name\(s\) \['q'\]"),
        (lambda: P.unpack(specs, [jnp.zeros(2)]), r"^thetas: expected a dict"),
        (lambda: P.unpack(specs, {"Q": jnp.zeros(2), "R": jnp.zeros(2)}), r"^thetas: unknown name\(s\) \['R'\]"),
        (lambda: P.log_diag_from_cov(np.diag([3.0, 1.0]), dtype=jnp.int32), r"^dtype: expected a floating dtype"),
        (lambda: P.log_diag_from_cov(np.eye(2), dtype="bogus"), r"^dtype: expected a floating dtype"),
        (lambda: P.log_chol_from_cov(np.eye(2), dtype=np.int64), r"^dtype: expected a floating dtype"),
        (lambda: P.pack(specs, {"Q": np.eye(2)}, dtype=jnp.int32), r"^dtype: expected a floating dtype"),
        (lambda: P.log_diag_from_cov(np.eye(2), floor=math.inf), r"^floor: must be > 0"),
        (lambda: P.log_chol_from_cov(np.eye(2), floor=math.inf), r"^floor: must be > 0"),
    ]
    for call, msg in cases:
        with pytest.raises(InputError, match=msg):
            call()
    th = P.pack(specs, {"Q": np.diag([3.0, 1.0])}, floors={"Q": 1e-3}, dtype=jnp.float32)
    assert th["Q"].dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(th["Q"]), np.log([3.0, 1.0]), rtol=1e-6)


# ---------------------------------------------------------------------------- targets

def test_get_refuses_a_shared_option_the_target_would_ignore():
    """Item 9: linear-gaussian built with tune_r=True, structure="imu", ... (still tuning R its
    own way); mrclam ignored seed and train_runs.  The CLI's default values stay accepted."""
    with pytest.raises(InputError, match=r"^checkpoint: tuning target linear-gaussian --target noise does not use "
                                         r"checkpoint, eval_duration, structure, tune_r"):
        T.get("linear-gaussian", "noise", "nll", T=20, cov="diag", tune_r=True, structure="imu",
              eval_duration=1.0, checkpoint=False)
    with pytest.raises(InputError, match=r"^seed: tuning target mrclam does not use seed, train_runs"):
        T.get("mrclam", "noise", "nll", data=DATA, robots=(1,), test_robots=(2,), t_max=10.0,
              odometry_delay=0.0, seed=7, train_runs=3)
    # what `jaxslam tune linear-gaussian` passes when no flag is given builds
    tg = T.get("linear-gaussian", "noise", "nll", train_runs=1, test_runs=1, seed=0, dtype=jnp.float64, T=20,
               eval_duration=50.0, checkpoint=True, cov="diag", tune_r=False, structure="qc", filter="ekf")
    assert tg.config["T"] == 20


def test_get_names_a_scenario_that_is_not_a_string():
    """Item 19: a list was a bare "unhashable type" TypeError."""
    with pytest.raises(InputError, match=r"^scenario: expected a name"):
        T.get(["x"], "noise", "nll")
    with pytest.raises(InputError, match=r"^loss: expected a name"):
        T.get("linear-gaussian", "noise", None)


@pytest.mark.parametrize("robots, msg", [
    ((1, 1), r"^robots: robot\(s\) \[1\] listed more than once"),
    ("12", r"^robots: expected a list of robot numbers"),
    ((1.7,), r"^robots: expected robot numbers"),
    ((), r"^robots: give at least one robot"),
])
def test_robot_lists_must_be_distinct_whole_numbers(robots, msg):
    """Item 10: (1, 1) trained on robot 1 twice, "12" read as robots 1 and 2, 1.7 as robot 1,
    () a bare max() of an empty sequence."""
    from jaxslam.tuning.targets import mrclam, plaza

    with pytest.raises(InputError, match=msg):
        mrclam.mrclam_noise(data=DATA, robots=robots, test_robots=(5,))
    if robots != ():  # plaza names its own empty training list (existing message)
        with pytest.raises(InputError, match=msg):
            plaza.plaza_noise(data=DATA, robots=robots, test_robots=())
    with pytest.raises(InputError, match=r"^test_robots: robot\(s\) \[2\] listed more than once"):
        plaza.plaza_noise(data=DATA, robots=(1,), test_robots=[2, 2])


def test_robot_lists_take_any_iterable_of_robot_numbers():
    """A range or a generator of robots worked before this session's list/tuple check refused it."""
    from collections import OrderedDict

    from jaxslam.tuning.targets import _check_robots

    for value in (range(1, 5), (r for r in (1, 2, 3, 4)), np.arange(1, 5), [1, 2, 3, np.int64(4)],
                  iter([1, 2, 3, 4])):
        assert _check_robots(value, "robots", "--robots", allow_empty=False) == (1, 2, 3, 4)
    assert _check_robots(range(0), "test_robots", "--test-robots", allow_empty=True) == ()
    for bad in ("12", b"12", {1: 1}, OrderedDict([(1, 2)]), 3, None, np.int64(2), np.array(2)):
        with pytest.raises(InputError, match=r"^robots: expected a list of robot numbers \(--robots\)"):
            _check_robots(bad, "robots", "--robots", allow_empty=False)
    with pytest.raises(InputError, match=r"^robots: robot\(s\) \[2\] listed more than once"):
        _check_robots((r for r in (2, 1, 2)), "robots", "--robots", allow_empty=False)
    with pytest.raises(InputError, match=r"^robots: expected robot numbers \(--robots\): ints >= 1, got 0"):
        _check_robots(range(3), "robots", "--robots", allow_empty=False)


def test_mrclam_fit_window_counts_the_odometry_delay():
    """The log starts at the first odometry stamp + odometry_delay (presets.mrclam_log): the
    excerpt's odometry starts 0.5 s into its ground truth, so with a 0.25 s delay a 0.6 s window
    holds no step (it surfaced as merge_events' "reversed window" of t_start and t_end)."""
    from jaxslam.tuning.targets import mrclam

    with pytest.raises(InputError, match=r"^--window: robot 1's odometry \(stamps \+ 0\.25 s delay\) starts "
                                         r"0\.75 s into its ground truth, so a 0\.6 s fit window holds no step; "
                                         r"give --window above 0\.75$"):
        mrclam.mrclam_logs(DATA, [1], np.float64, t_max=0.6, odometry_delay=0.25)
    batch, raw = mrclam.mrclam_logs(DATA, [1], np.float64, t_max=0.8, odometry_delay=0.25)
    (log, d), = raw
    assert log.t[0] == pytest.approx(d.odom_t[0] + 0.25) and d.odom_t[0] + 0.25 < log.t[-1] <= d.gt_t[0] + 0.8
    assert batch.dt.shape[1] == log.t.size > 1
    with pytest.raises(InputError, match=r"^odometry_delay: expected a finite scalar"):
        mrclam.mrclam_logs(DATA, [1], np.float64, t_max=0.8, odometry_delay="x")


@pytest.mark.parametrize("t_max", ["10", math.nan, -1.0, True])
def test_real_log_fit_window_is_a_positive_number_of_seconds(t_max):
    """Item 18: mrclam's t_max "10" was a bare TypeError, NaN an error naming t_end."""
    from jaxslam.tuning.targets import mrclam

    with pytest.raises(InputError, match=r"^t_max: expected the fit window in seconds"):
        mrclam.mrclam_noise(data=DATA, robots=(1,), test_robots=(), t_max=t_max)


def test_util_uwb_window_counts_seconds_from_the_first_range():
    """Item 11: t_max was an absolute time (the excerpt starts at t = 20.0 s: t_max=0.5 left 0
    ranges to fit), unlike --window's "first S seconds" and the other targets."""
    tg = UT.util_noise(data=DATA, t_max=0.5)
    t0, split = tg.config["fit_window_s"]
    assert t0 == pytest.approx(20.007191) and split == pytest.approx(t0 + 0.5, abs=1e-12)
    assert tg.config["n_fit_ranges"] == 42 and tg.config["n_held_out_ranges"] == 42


def test_util_uwb_window_is_described_as_the_first_seconds_of_the_flight():
    """docs/cli.md described util-uwb's --window as "the ranges before S seconds" (an absolute
    time); it is the first S seconds of the flight, counted from its first range, as the CLI's
    help says."""
    import pathlib
    import re

    from jaxslam.cli import tune as cli_tune

    row = next(line for line in pathlib.Path("docs/cli.md").read_text().splitlines()
               if line.startswith("| `jaxslam tune util-uwb"))
    assert "before S seconds" not in row and "the first S seconds of the flight" in row
    assert "counted from its first range" in row
    act = next(a for a in cli_tune.build_parser()._actions if "--window" in a.option_strings)
    text = re.sub(r"\s+", " ", act.help)
    assert "util-uwb: the first S seconds of the flight, counted from its first range" in text


def test_linear_gaussian_float32_log_is_the_float64_log_rounded():
    """Item 12: drawn in float32, the noise was unrelated to float64's (measurements differed by
    up to 1.0 from one seed); now one stream, cast."""
    key = jax.random.PRNGKey(0)
    Q, R = np.diag(LG.LG_Q_TRUE), np.asarray(LG.LG_R_TRUE)
    d64 = LG.lg_simulate(key, 200, Q, R, dtype=jnp.float64)
    d32 = LG.lg_simulate(key, 200, Q, R, dtype=jnp.float32)
    for k in ("z", "x"):
        assert d32[k].dtype == jnp.float32
        np.testing.assert_array_equal(np.asarray(d32[k]), np.asarray(d64[k]).astype(np.float32))


def test_ekfslam3d_noise_refuses_bad_capacity_and_ignored_mse_weights_before_simulating():
    """Item 14: capacity=0 built (the error came when traced, naming config.capacity); mse_weights
    with another loss was ignored; a scalar weight was a TypeError after the simulation."""
    kw = dict(train_runs=1, test_runs=1, train_duration=0.1, eval_duration=0.1)
    with pytest.raises(InputError, match=r"^capacity: expected a number of landmark slots"):
        T.get("ekfslam3d-unknown", "noise", "nll", capacity=0, **kw)
    with pytest.raises(InputError, match=r"^mse_weights: only the mse loss reads them"):
        T.get("ekfslam3d-unknown", "noise", "nll", mse_weights=2.0, **kw)
    for bad in (np.ones(3), -1.0, "2"):
        with pytest.raises(InputError, match=r"^mse_weights: expected"):
            T.get("ekfslam3d-unknown", "noise", "mse", mse_weights=bad, **kw)


# ---------------------------------------------------------------------------- paramfile, runtime

def test_paramfile_refuses_huge_integers_and_booleans_as_numbers():
    """Item 15: 10**400 was a bare OverflowError; [true, false] for a vector was accepted and
    returned as booleans."""
    schema = {"filter": {"r": 1.0, "q": [1.0, 2.0]}}
    with pytest.raises(InputError, match=r"^--params: filter.r: holds a number too large"):
        paramfile.check({"filter": {"r": 10 ** 400}}, schema, target="x")
    for bad in ([True, False], [1.0, True]):
        with pytest.raises(InputError, match=r"^--params: filter.q: expected numbers"):
            paramfile.check({"filter": {"q": bad}}, schema, target="x")
    assert paramfile.check({"filter": {"q": [3, 4.5]}}, schema, target="x") == {"filter": {"q": [3, 4.5]}}


@pytest.mark.parametrize("n", [0, -3, 2.7, True, "2"])
def test_pin_lapack_threads_refuses_a_count_it_would_not_apply(n):
    """Item 17: 0 set the pool to all cores and returned 0; -3 and 2.7 were returned as if applied."""
    before = runtime.lapack_threads()
    with pytest.raises(InputError, match=r"^n: expected an int >= 1"):
        runtime.pin_lapack_threads(n)
    assert runtime.lapack_threads() == before
