"""The optimisation loop: optax Adam with a schedule and gradient clipping, vmapped batches.

``fit(loss_fn, theta0, train, ...)`` minimises the batch mean of a per-run loss
``loss_fn(theta, item)`` over the training runs (``jax.vmap`` over the leading axis of
``train``), one jitted step per iteration (loss, gradient and the candidate update in
one call), with the host deciding whether the update is applied:

* every training run's loss and gradient are computed on their own; a run whose loss or
  gradient is non-finite, or (with ``explode_ratio``) whose loss exceeds ``explode_ratio`` ×
  the batch's lower median — a diverged or exploding flight — is **left out** of that step's
  mean loss and gradient, never averaged in; the record names it (``dropped_runs``) and
  ``FitResult.n_dropped`` counts it;
* when no run is left, a **non-finite loss** (the mean over all runs) stops the optimisation;
  the parameters of the last step whose loss was finite are returned, and
  ``FitResult.stopped`` says why and where;
* otherwise (finite losses, every gradient non-finite or exploding) the step is reported in
  the history and *skipped*: the candidate update is discarded, parameters and optimiser
  state stay as they were.  With the full batch every step sees the same data, so the same
  gradient would recur: after ``max_skips`` consecutive skips the loop stops (last good
  parameters kept; ``max_skips=0``: at the first skip).  With ``batch_size`` < runs each step
  draws a new minibatch (from ``key``) and a skip only loses one step (the loop stops after
  10 × ``max_skips`` consecutive ones).  The last record (``steps``: no update follows) is
  never a skip: a non-finite gradient there shows only in its ``grad_norm`` (NaN).
* a skipped step applies no update, so it does not advance the optimiser's step count nor the
  learning-rate schedule, which is laid out over ``steps`` updates: after skips the cosine
  ends short of its final value (each record's ``lr`` is the one its update applies, read at
  the optimiser's count).
* every ``eval_every`` steps the mean loss on the held-out batch ``test`` is recorded
  (value only, a separately compiled function) — the test-loss curve.
* ``callback(record)`` receives each history record (progress bars, logging).

Decisions (no paper covers tuning):

* Schedule: linear warm-up over ``warmup`` steps (default 5 % of the steps), then cosine
  decay to 5 % of lr (``schedule="cosine"``; :func:`make_optimizer`'s ``final_lr_frac``,
  fixed at its default in :func:`fit`); ``"constant"`` keeps lr.
  Gradient clipping by global norm (``clip``, default 1.0) comes before Adam, which
  matters on the first steps from a far-off start (Table 7 is 10³-10⁷ too large).
* Adam's β2 defaults to 0.9, not optax's 0.999.  The batches are deterministic (the same
  training runs every step) and the gradient shrinks by orders of magnitude on the way from
  a far-off start to the optimum; with β2 = 0.999 the second-moment estimate remembers the
  early, large gradients for ~10³ steps and the late steps shrink ~100×: tuning Table 7's Q
  on EKF-SLAM logs stalled at 2.5× the reachable MSE (measured: 80 steps, β2 = 0.999:
  MSE 0.0095; β2 = 0.9: 0.0077; β2 = 0.9 with a log objective: 0.0047; the IMU-derived Q
  0.0038, 2 logs of 10 s).
* ``log_objective=True`` differentiates log(mean loss) instead of the mean loss (positive
  losses whose optimum is not 0: MSE, closed-loop costs; not the NEES loss, whose optimum
  is 0, nor the NLL, which may be negative): a relative decrease then counts the same at every
  scale, which keeps the steps large when the loss falls by decades.  The history records
  the plain mean loss either way.  A step whose mean loss is ≤ 0 has no log: its update is
  skipped and counted as a non-finite gradient's is (its record says ``nonpositive_loss``;
  the stop message names ``log_objective``), never taken uphill; the one exception is a
  mean loss of exactly 0 with a zero gradient (the optimum of a non-negative loss), whose
  gradient is 0 (not 0/0) and whose step goes on as any zero-gradient step.
* The returned ``theta`` is the last good iterate (not the best training loss seen): the
  training loss is noisy with minibatches, and a held-out evaluation decides anyway.
  ``best_theta`` (lowest training loss seen) is returned as well, among the steps whose loss
  covers the same runs: a step that dropped a run (``dropped_runs``) is compared only with
  steps that dropped the same ones, and one that keeps a strict superset of the current
  best's runs replaces it whatever its loss (a mean over fewer runs is not comparable: the
  rest of a diverged run's batch looks better exactly where that run fails).  With minibatches
  (``batch_size`` < runs) "the same runs" means the same dropped runs only: each step's loss
  is over its own minibatch, so ``best_theta`` compares losses over different runs there and
  is a noisy choice (a step that drew easy runs wins); ``theta`` is the one to use.
* Memory: ``memory`` reports the compiled step's XLA memory analysis (temporary,
  argument and output bytes — what the backward pass holds) and the process's peak
  resident memory (``resource.getrusage``, monotone over the process lifetime).
"""

from __future__ import annotations

import math
import resource
import sys
import time
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import runtime
from ..errors import InputError
from ..linalg import check_int, check_key, check_scalar, is_concrete, reworded

__all__ = ["FitResult", "make_optimizer", "batch_loss", "fit", "memory_report", "peak_rss_mb", "FAST_COMPILE"]

# XLA CPU options that trade run time for compile time (LLVM back-end optimisation off);
# measured by ``jaxslam bench tuning`` (see docs/tuning.md).
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


class FitResult(NamedTuple):
    """Result of :func:`fit`.

    theta: last good parameters (finite loss); best_theta: lowest training loss seen among
      the steps over the same runs (module docstring).
    history: list of records ``{"step", "loss", "grad_norm", "lr", "skipped", "time_s",
      ["dropped_runs"], ["nonpositive_loss"], ["test_loss"], ["params"]}``: record k holds the
      loss at θ_k (mean over the runs kept; before update k); there are ``steps + 1`` records,
      the last one (no update) checks the final iterate.  ``dropped_runs``: training-run
      indices left out.  ``grad_norm``: global norm of the step's gradient, NaN when it is
      non-finite.  ``lr``: the schedule at the optimiser's step count (updates applied so
      far), i.e. the learning rate of this record's update; a skipped step does not advance
      it.  ``nonpositive_loss``: the step was skipped because ``log_objective`` met a mean
      loss ≤ 0.
    stopped: None, or a message saying why the loop stopped early.
    compile_s: compilation time of the training step [s]; step_s: median step time [s].
    memory: see :func:`memory_report`.
    n_skipped: number of skipped updates (non-finite gradient, or a loss ≤ 0 under
      ``log_objective``); the last record, which has no update, is never counted.
    n_dropped: number of (step, run) pairs left out of a step's mean (``dropped_runs``).
    interrupted: a Ctrl-C stopped the loop after at least one step (``stopped`` says when);
      ``theta`` / ``best_theta`` are those reached so far.
    """

    theta: Any
    best_theta: Any
    history: list
    stopped: Optional[str]
    compile_s: float
    step_s: float
    memory: dict
    n_skipped: int
    interrupted: bool = False
    n_dropped: int = 0


def make_optimizer(lr: float, steps: int, schedule: str = "cosine", warmup: Optional[int] = None,
                   clip: Optional[float] = 1.0, final_lr_frac: float = 0.05, b2: float = 0.9):
    """optax chain: clip_by_global_norm(clip) → Adam(schedule, b2).  Returns (tx, schedule_fn)."""
    lr = reworded(lambda: check_scalar(lr, "lr", lower=0, strict=True),
                   f"lr: expected a positive finite number (--lr), got {lr!r}")
    steps = check_int(steps, "steps", lower=1, what="an int (--steps)")
    # < 0: gradient ascent; NaN: NaN lr; a bool is not a fraction
    frac = reworded(lambda: check_scalar(None if isinstance(final_lr_frac, bool) else final_lr_frac,
                                          "final_lr_frac", lower=0),
                     f"final_lr_frac: expected a number in [0, 1] (the final lr as a fraction of lr), "
                     f"got {final_lr_frac!r}", upper=1.0)
    if warmup is not None:
        reworded(lambda: check_int(warmup, "warmup", lower=0), f"warmup: must be an int >= 0 (or None), got {warmup!r}")
    warmup = max(1, int(round(0.05 * steps))) if warmup is None else int(warmup)
    if schedule == "cosine":
        sched = optax.warmup_cosine_decay_schedule(
            init_value=lr * 0.1, peak_value=lr, warmup_steps=max(warmup, 1),
            decay_steps=max(steps, warmup + 1), end_value=lr * frac)
    elif schedule == "constant":
        sched = optax.constant_schedule(lr)
    else:
        raise InputError(f"schedule: expected 'cosine' or 'constant', got {schedule!r}")
    parts = []
    if clip is not None:
        reworded(lambda: check_scalar(clip, "clip", finite=False, lower=0, strict=True), f"clip: must be > 0, got {clip}")
        parts.append(optax.clip_by_global_norm(clip))
    b2 = reworded(lambda: check_scalar(b2, "b2"), f"b2: must be in (0, 1), got {b2!r}")
    if not 0.0 < b2 < 1.0:
        raise InputError(f"b2: must be in (0, 1), got {b2}")
    parts.append(optax.adam(sched, b2=b2))
    return optax.chain(*parts), sched


def batch_loss(loss_fn: Callable, theta, batch, sequential: bool = False):
    """Mean of ``loss_fn(theta, item)`` over the leading axis of ``batch``.

    ``jax.vmap`` by default; ``sequential=True`` uses ``lax.map`` (one item after another),
    for losses whose scans branch per step with ``lax.cond`` (real logs: an update only on
    events with measurements) — under ``vmap`` both branches would run at every step.
    """
    if sequential:
        return jnp.mean(jax.lax.map(lambda item: loss_fn(theta, item), batch))
    return jnp.mean(jax.vmap(loss_fn, in_axes=(None, 0))(theta, batch))


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far [MB] (Linux ru_maxrss is in kB)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1e6 if sys.platform == "darwin" else r / 1e3


def memory_report(compiled) -> dict:
    """XLA memory analysis of a compiled function [MB] plus the process peak RSS."""
    out = {"peak_rss_mb": peak_rss_mb()}
    try:
        ma = compiled.memory_analysis()
    except Exception:  # not every backend reports it
        ma = None
    if ma is not None:
        for k in ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
                  "generated_code_size_in_bytes"):
            v = getattr(ma, k, None)
            if v is not None:
                out[k.replace("_size_in_bytes", "_mb")] = float(v) / 1e6
    return out


def _tree_finite(t):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(t)]))


def _kept_runs(losses, grads, explode_ratio):
    """Per run: loss and gradient finite and, with ``explode_ratio``, the loss at most that
    many times the lower median of the batch's finite losses (positive losses only)."""
    per_run = [jnp.all(jnp.isfinite(a).reshape(a.shape[0], -1), axis=1) for a in jax.tree.leaves(grads)]
    finite = jnp.isfinite(losses)
    keep = finite & jnp.all(jnp.stack(per_run), axis=0) if per_run else finite
    if explode_ratio is not None:
        n_fin = jnp.sum(finite)
        med = jnp.sort(jnp.where(finite, losses, jnp.inf))[jnp.maximum((n_fin - 1) // 2, 0)]
        keep = keep & ~((med > 0) & (losses > explode_ratio * med))
    return keep


def _global_norm(t):
    return jnp.sqrt(sum(jnp.sum(jnp.where(jnp.isfinite(x), x, 0.0) ** 2) for x in jax.tree.leaves(t)))


def _per_run_avals(batch):
    """(structure, [(shape without the runs axis, dtype)]) of a batch: what a trace of the loss sees."""
    return jax.tree.structure(batch), [(tuple(np.shape(x))[1:], jnp.result_type(x)) for x in jax.tree.leaves(batch)]


def _check_test(test, train, loss_fn, theta0, sequential) -> None:
    """InputError unless the held-out batch has one leading axis of runs (≥ 1) shared by its
    arrays and the loss can be evaluated on it: a batch whose items differ from ``train``'s (in
    structure — a target may add per-run weights —, shape or dtype) is traced once, abstractly
    (``jax.eval_shape``), here, so a mismatch is named before the training step compiles,
    not after the last step."""
    leaves = jax.tree.leaves(test)
    if not leaves:
        raise InputError("test: empty batch (no arrays)")
    n = {int(np.shape(x)[0]) if np.ndim(x) else -1 for x in leaves}
    if len(n) != 1 or min(n) < 1:
        raise InputError(f"test: every array needs the same leading axis of runs (≥ 1), got {sorted(n)}")
    if _per_run_avals(test) == _per_run_avals(train):  # the items the step is compiled for
        return
    try:
        jax.eval_shape(lambda th, b: batch_loss(loss_fn, th, b, sequential), theta0, test)
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:
        raise InputError(f"test: the loss cannot be evaluated on this held-out batch (structure "
                         f"{jax.tree.structure(test)}, the training batch's is {jax.tree.structure(train)}): "
                         f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:500]) from None


def fit(loss_fn: Callable, theta0, train, steps: int, lr: float = 0.1, *, test=None,
        eval_every: int = 0, schedule: str = "cosine", warmup: Optional[int] = None,
        clip: Optional[float] = 1.0, batch_size: Optional[int] = None, key=None,
        max_skips: int = 3, callback: Optional[Callable] = None,
        describe: Optional[Callable] = None, b2: float = 0.9,
        log_objective: bool = False, compiler_options: Optional[dict] = None,
        sequential: bool = False, explode_ratio: Optional[float] = None) -> FitResult:
    """Minimise mean_runs ``loss_fn(theta, item)`` with Adam; see the module docstring.

    Args:
      loss_fn: per-run loss (jit/vmap/grad-safe).  theta0: pytree of float arrays.
      train: batch pytree, leading axis = runs.  steps: optimisation steps.
      lr: peak learning rate (Adam step size in θ units: log-variances for log
        parametrisations, so 0.1 ≈ 10 % relative change per step at most).
      test, eval_every: held-out batch and how often its loss is recorded (0: never;
        the final parameters are always evaluated when ``test`` is given).
      schedule, warmup, clip, b2: see :func:`make_optimizer`.
      log_objective: differentiate log(mean loss) (positive losses; module docstring).
      batch_size, key: minibatches of the training runs drawn per step (key required).
      max_skips: the loop stops at the ``max_skips``-th consecutive skipped update (the
        ``10 × max_skips``-th with minibatches); 0 and 1 both stop at the first skip.
      callback: called with each history record.
      describe: ``describe(theta) -> dict`` stored in each record (parameter trajectories).
      sequential: evaluate the batch's items one after another (:func:`batch_loss`).
      explode_ratio: leave out a run whose loss exceeds this many times the batch's lower
        median (positive losses only; None: only non-finite runs are left out).
      compiler_options: passed to XLA when the step is compiled (e.g. :data:`FAST_COMPILE`), over
        the library's CPU options (:func:`jaxslam.runtime.compiler_options`).
    """
    leaves = jax.tree.leaves(train)
    if not leaves:
        raise InputError("train: empty batch")
    if any(np.ndim(x) < 1 for x in leaves):
        raise InputError("train: every array needs a leading axis of runs")
    runs = int(leaves[0].shape[0])
    if runs < 1 or any(int(np.shape(x)[0]) != runs for x in leaves):
        raise InputError(f"train: every array needs the same leading axis of runs (≥ 1), got "
                         f"{sorted({int(np.shape(x)[0]) for x in leaves})}")
    th_leaves = jax.tree.leaves(theta0)
    if not th_leaves:
        raise InputError("theta0: no parameters")
    for x in th_leaves:
        if not jnp.issubdtype(jnp.result_type(x), jnp.floating):
            raise InputError(f"theta0: parameters must be floating-point arrays (a gradient needs "
                             f"them), got dtype {jnp.result_type(x)}")
        if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
            raise InputError("theta0: contains NaN or Inf")
    reworded(lambda: check_int(max_skips, "max_skips", lower=0), f"max_skips: must be an int >= 0, got {max_skips!r}")
    if batch_size is not None:
        batch_size = check_int(batch_size, "batch_size", lower=1)
        if batch_size > runs:
            raise InputError(f"batch_size: must be in [1, {runs}], got {batch_size}")
    if batch_size is not None and batch_size < runs and key is None:
        raise InputError("key: a PRNG key is required for minibatches (batch_size < runs)")
    if key is not None:
        check_key(key, raw_shape=(2,))  # PRNGKey data: the pair of the default (threefry) key
    eval_every = check_int(eval_every, "eval_every", lower=0)
    if test is not None:
        _check_test(test, train, loss_fn, theta0, sequential)
    if explode_ratio is not None:
        explode_ratio = reworded(lambda: check_scalar(explode_ratio, "explode_ratio", lower=1, strict=True),
                                 f"explode_ratio: expected a finite number > 1 or None, got {explode_ratio!r}")
    tx, sched = make_optimizer(lr, steps, schedule, warmup, clip, b2=b2)
    opt_state = tx.init(theta0)
    mini = batch_size is not None and batch_size < runs

    def loss_and_grad(th, batch):
        if sequential:
            # Each item's value and gradient one after another: the reverse pass of one log ends
            # before the next log starts, so memory holds one log's residuals, not the batch's.
            ls, gs = jax.lax.map(lambda item: jax.value_and_grad(loss_fn)(th, item), batch)
        else:
            ls, gs = jax.vmap(jax.value_and_grad(loss_fn), in_axes=(None, 0))(th, batch)
        keep = _kept_runs(ls, gs, explode_ratio)
        n_keep = jnp.sum(keep)
        denom = jnp.maximum(n_keep, 1).astype(ls.dtype)
        # No run left: the plain mean (non-finite if any loss is) decides stop or skip.
        loss = jnp.where(n_keep > 0, jnp.sum(jnp.where(keep, ls, 0.0)) / denom, jnp.mean(ls))
        g = jax.tree.map(lambda a: jnp.sum(jnp.where(keep.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0.0),
                                           axis=0) / denom, gs)
        g = jax.tree.map(lambda a: jnp.where(n_keep > 0, a, jnp.nan), g)
        if log_objective:  # d log(mean L) = d(mean L) / mean L, defined for mean L > 0 only
            pos = loss > 0
            # mean L = 0 with a zero gradient: the optimum of a non-negative loss, gradient 0 (not
            # 0/0); any other mean L <= 0 has no log: NaN, so the step is skipped (module docstring)
            flat = jnp.all(jnp.stack([jnp.all(a == 0) for a in jax.tree.leaves(g)])) & (loss == 0)
            g = jax.tree.map(lambda a: jnp.where(pos, a / loss, jnp.where(flat, 0.0, jnp.nan)), g)
        return loss, g, keep

    def step(theta, opt_state, batch):
        loss, g, keep = loss_and_grad(theta, batch)
        g_ok = _tree_finite(g)
        g_safe = jax.tree.map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
        upd, new_state = tx.update(g_safe, opt_state, theta)
        return loss, g_ok, _global_norm(g), optax.apply_updates(theta, upd), new_state, keep

    def take(idx):
        return jax.tree.map(lambda a: a[idx], train)

    first = take(np.arange(batch_size)) if mini else train
    opts = {**(runtime.compiler_options() or {}), **(compiler_options or {})}
    t0 = time.perf_counter()
    step_c = jax.jit(step).lower(theta0, opt_state, first).compile(compiler_options=opts or None)
    compile_s = time.perf_counter() - t0
    memory = memory_report(step_c)
    test_c = None
    if test is not None:
        test_c = jax.jit(lambda th, b: batch_loss(loss_fn, th, b, sequential), compiler_options=opts or None)

    theta, good, best, best_loss, best_dropped = theta0, theta0, theta0, math.inf, None
    history, stopped, skips, n_skipped, n_dropped, times = [], None, 0, 0, 0, []
    applied = 0  # updates applied so far: the optimiser's step count, which its schedule reads
    limit = max_skips if not mini else 10 * max_skips
    log_skip = False  # the last skip was a loss <= 0 under log_objective
    rng = np.random.default_rng(None if key is None else np.asarray(jax.random.key_data(key)).ravel().tolist())
    # Iterate k = 0..steps: step k evaluates the loss (and gradient) at θ_k and, for k < steps,
    # proposes θ_{k+1}; the last pass only checks that the final iterate has a finite loss.
    interrupted = False
    try:
        for k in range(steps + 1):
            last = k == steps
            idx = np.sort(rng.choice(runs, batch_size, replace=False)) if mini else np.arange(runs)
            batch = take(idx) if mini else train
            ts = time.perf_counter()
            loss, g_ok, gnorm, cand, cand_state, keep = step_c(theta, opt_state, batch)
            loss = float(loss)
            g_ok = bool(g_ok)
            keep = np.asarray(keep)
            times.append(time.perf_counter() - ts)
            # the lr this step's update applies: optax reads the schedule at its own count, which
            # only an applied update advances (equal to k in a run without skips)
            rec = {"step": k, "loss": loss, "grad_norm": float(gnorm) if g_ok else math.nan,
                   "lr": float(sched(applied)), "skipped": False, "time_s": times[-1]}
            dropped = frozenset()
            if keep.any() and not keep.all():  # some runs left out, the rest applied
                rec["dropped_runs"] = [int(i) for i in idx[~keep]]
                n_dropped += int((~keep).sum())
                dropped = frozenset(rec["dropped_runs"])
            if describe is not None:
                rec["params"] = describe(theta)
            if not math.isfinite(loss):
                prev = next((h for h in reversed(history) if h.get("loss") is not None), None)
                stopped = (f"loss became non-finite ({loss}) at step {k}; stopped and kept the "
                           "parameters of the last step with a finite loss"
                           + (f" (step {prev['step']}, loss {prev['loss']:.6g})" if prev else " (the starting point)"))
                rec["skipped"] = True
                history.append(rec)
                if callback is not None:
                    callback(rec)
                break
            good = theta
            # best: only among losses over the same runs; covering more runs takes over
            if best_dropped is None or dropped < best_dropped or (dropped == best_dropped and loss < best_loss):
                best, best_loss, best_dropped = theta, loss, dropped
            if last:
                pass  # the final check: no update to apply or skip
            elif not g_ok:
                rec["skipped"] = True
                skips += 1
                n_skipped += 1
                log_skip = bool(log_objective and loss <= 0)
                if log_skip:
                    rec["nonpositive_loss"] = True
            else:
                theta, opt_state, skips = cand, cand_state, 0
                applied += 1
            if test_c is not None and ((eval_every and k % eval_every == 0) or last):
                rec["test_loss"] = float(test_c(good, test))
            history.append(rec)
            if callback is not None:
                callback(rec)
            if not last and skips > 0 and skips >= limit:
                if log_skip:
                    stopped = (f"log_objective: the mean loss was <= 0 ({loss:.6g}) at step {k} ({skips} consecutive "
                               "skipped steps); log(mean loss) is undefined there, so those updates were skipped, "
                               "never applied; stopped with the last good parameters (log_objective=False fits a "
                               "loss that can be <= 0)")
                else:
                    stopped = (f"gradient non-finite at {skips} consecutive steps (last: step {k}); "
                               "those updates were skipped, never applied; stopped with the last good parameters")
                break
    except KeyboardInterrupt:  # Ctrl-C: keep what is done (the caller writes it, marked)
        if not history:
            raise
        interrupted = True
        # history holds the evaluations at steps 0 … k (step 0: the start)
        stopped = (f"interrupted (Ctrl-C) at step {len(history) - 1} of {steps} ({len(history)} of "
                   f"{steps + 1} evaluations, step 0 the start); kept the parameters reached so far")
    return FitResult(theta=good, best_theta=best, history=history, stopped=stopped, compile_s=compile_s,
                     step_s=float(np.median(times)) if times else math.nan,
                     memory={**memory, "peak_rss_after_mb": peak_rss_mb()}, n_skipped=n_skipped,
                     interrupted=interrupted, n_dropped=n_dropped)
