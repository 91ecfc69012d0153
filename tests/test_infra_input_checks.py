"""Input checks and exactness of the infrastructure modules: Monte Carlo seeds and arguments,
JSON and file writing, metric summaries, the progress bar, process blocks."""

from __future__ import annotations

import io as _io
import math
import os
import warnings

import jax
import numpy as np
import pytest

from jaxslam import files, io
from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim import distributed, monte_carlo

SEEDS = (0, 1, 12345, 2**32 + 5, -1, -(2**40), 2**31, -2**31, 2**63 - 1, -2**63)


def _x64_keys(seed, runs):
    """The keys as ``jax.random.PRNGKey`` makes them with x64 on (what float64 runs always used)."""
    with jax.enable_x64(True):
        base = jax.random.PRNGKey(np.int64(seed))
        return np.asarray(jax.vmap(lambda i: jax.random.fold_in(base, i))(np.arange(runs)))


@pytest.mark.parametrize("x64", [True, False])
def test_keys_for_is_the_x64_key_of_every_seed_whatever_the_setting(x64):
    with jax.enable_x64(x64):
        got = {s: monte_carlo.keys_for(s, 3) for s in SEEDS}
    for s in SEEDS:
        want = _x64_keys(s, 3)
        assert got[s].dtype == want.dtype and np.array_equal(got[s], want), s
    # seeds 2**32 apart (x64 off used to keep 32 bits) have their own keys
    with jax.enable_x64(x64):
        assert not np.array_equal(monte_carlo.keys_for(0, 2), monte_carlo.keys_for(2**32, 2))


@pytest.mark.parametrize("seed", [2**63, 2**64, -2**63 - 1, 1.5, True, "3"])
def test_seed_outside_the_64_bit_range_is_an_input_error(seed):
    with pytest.raises(InputError, match=r"^seed: "):
        monte_carlo.keys_for(seed, 2)
    with pytest.raises(InputError, match=r"^seed: "):
        monte_carlo.run(lambda k: {"a": jax.random.normal(k, ())}, seed, 2)


def _fn(key):
    return {"a": jax.random.normal(key, (3,)).sum()}


def test_run_arguments_cpu_batching_and_an_iterator_of_devices():
    with pytest.raises(InputError, match=r"^cpu_batching: "):
        monte_carlo.run(_fn, 0, 2, cpu_batching="x")
    dev = jax.local_devices()[:1]
    a = monte_carlo.run(_fn, 0, 3, devices=dev)
    b = monte_carlo.run(_fn, 0, 3, devices=iter(dev))  # an iterator is read once
    assert b.runs == 3 and np.array_equal(a.out["a"], b.out["a"])
    with pytest.raises(InputError, match=r"^devices: "):
        monte_carlo.run(_fn, 0, 2, devices=iter([]))


def test_atomic_write_keeps_the_permission_bits_of_the_file_it_replaces(tmp_path):
    p = tmp_path / "keep.json"
    io.write_json(p, {"a": 1})
    os.chmod(p, 0o600)
    io.write_json(p, {"a": 2})
    assert os.stat(p).st_mode & 0o777 == 0o600
    assert '"a": 2' in p.read_text()
    new = tmp_path / "new.txt"
    files.atomic_write(new, lambda f: f.write("x"))
    assert os.stat(new).st_mode & 0o777 == 0o666 & ~files._UMASK


def test_write_json_refuses_keys_that_collide_as_json_strings(tmp_path):
    p = tmp_path / "k.json"
    with pytest.raises(InputError, match=r"^obj: keys 1 and '1' of one mapping are both"):
        io.write_json(p, {1: "int", "1": "str"})
    with pytest.raises(InputError, match=r"^obj: keys True and 'True' of one mapping are both"):
        io.write_json(p, {"x": [0, {True: 1, "True": 2}]})
    assert not p.exists()
    io.write_json(p, {1: "a", 2.5: "b", None: "c"})  # distinct strings: written as before
    assert p.read_text() == '{\n  "1": "a",\n  "2.5": "b",\n  "None": "c"\n}\n'


def test_write_json_under_a_file_says_so_like_prepare_file(tmp_path):
    (tmp_path / "afile").write_text("x")
    target = tmp_path / "afile" / "sub" / "x.json"
    with pytest.raises(InputError) as want:
        files.prepare_file("path", target)
    with pytest.raises(InputError) as got:
        io.write_json(target, {"a": 1})
    # (was a bare "File exists"): write_json's own words, then prepare_file's explanation
    assert str(got.value).startswith("path: cannot write JSON to ")
    assert str(got.value).endswith(str(want.value).removeprefix("path: "))
    assert "is a file, so" in str(got.value)


def test_summary_p95_of_values_with_an_infinity_is_infinite():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = io.summarize_metrics({"a": [1.0, math.inf], "b": [math.inf, math.inf], "c": [-math.inf, 1.0],
                                  "d": [1.0] * 30 + [math.inf]})
    assert s["a"]["p95"] == math.inf and s["a"]["max"] == math.inf
    assert s["b"]["p95"] == math.inf
    assert s["c"]["p95"] == -math.inf
    assert s["d"]["p95"] == 1.0  # the infinity is not among the runs interpolated
    x = np.random.RandomState(0).randn(37)
    assert io.summarize_metrics({"x": x})["x"]["p95"] == float(np.percentile(x, 95))


@pytest.mark.parametrize("total", [-5, 2.7, True, "abc", math.nan, None])
def test_progress_total_must_be_a_count(total):
    with pytest.raises(InputError, match=r"^total: "):
        Progress(total)


def test_progress_update_takes_ints_only():
    p = Progress(np.int64(5), stream=_io.StringIO(), delay_s=0.0)
    assert p.total == 5 and Progress(0).total == 0
    p.update(np.int32(3))
    p.advance(1)
    assert p.n_done == 4
    p.update(-3)  # clipped, as documented
    assert p.n_done == 0
    for bad in ("3", 2.9, True):
        with pytest.raises(InputError, match=r"^n_done: "):
            p.update(bad)
    with pytest.raises(InputError, match=r"^k: "):
        p.advance(1.0)


def test_distributed_counts_follow_the_int_rules():
    with pytest.raises(InputError, match=r"^--num-processes: "):
        distributed.initialize("bad", True, 0)
    with pytest.raises(InputError, match=r"^--process-id: "):
        distributed.initialize("bad", 2, False)
    with pytest.raises(InputError, match=r"^--coordinator: "):  # np.int64 counts pass their checks
        distributed.initialize("bad", np.int64(2), np.int64(1))
    assert distributed.block(np.int64(5), np.int64(2), np.int64(1)) == (3, 3)
    with pytest.raises(InputError, match=r"^num_processes: "):
        distributed.block(10, 0, 0)
    with pytest.raises(InputError, match=r"^runs: "):
        distributed.block(-3, 2, 1)
    with pytest.raises(InputError, match=r"^runs: "):
        distributed.block(2.5, 2, 0)
    with pytest.raises(InputError, match=r"^index: "):
        distributed.block(10, 2, 5)
    with pytest.raises(InputError, match=r"^index: "):
        distributed.block(10, 2, True)
