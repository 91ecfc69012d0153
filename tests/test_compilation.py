"""jaxslam.compilation: the persistent cache (folders, bad folders, corrupt entries), stored
programs, the compile account, and ``jaxslam cache``.

The end-to-end checks run the ``jaxslam`` command in fresh processes (a cache is per process)
on a short flight, so each costs one small compile.
"""

import json
import os
import pathlib
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli, compilation
from jaxslam.errors import InputError

# A short scenario: one program of a few seconds' compile.
RUN = ["run", "track-helix", "--runs", "1", "--duration", "0.5", "--quiet"]


def _cli(args, cache, tmp_path, extra_env=None):
    env = {**os.environ, compilation.CACHE_DIR_ENV: str(cache), **(extra_env or {})}
    env.pop(compilation.CACHE_ENV, None)
    js = tmp_path / "out.json"
    p = subprocess.run([sys.executable, "-m", "jaxslam", *args, "--json", str(js)], capture_output=True,
                       text=True, env=env, timeout=600)
    return p, (json.loads(js.read_text()) if p.returncode == 0 else None)


@pytest.fixture
def keep_cache():
    """Tests that switch this process's cache off get the suite's cache back afterwards."""
    before = compilation.enabled_dir()
    yield
    if before is not None:
        compilation._enabled_dir = None
        compilation.enable_cache(before)


def test_cache_folder_precedence_and_switch(keep_cache, monkeypatch, tmp_path):
    monkeypatch.delenv(compilation.CACHE_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compilation.cache_dir() == tmp_path / "xdg" / "jaxslam" / "xla"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compilation.cache_dir() == tmp_path / "home" / ".cache" / "jaxslam" / "xla"
    monkeypatch.setenv(compilation.CACHE_DIR_ENV, str(tmp_path / "mine"))
    assert compilation.cache_dir() == tmp_path / "mine"
    assert compilation.cache_dir(tmp_path / "arg") == tmp_path / "arg"
    for off in ("0", "off", "False", "no"):
        monkeypatch.setenv(compilation.CACHE_ENV, off)
        assert compilation.enable_cache(tmp_path / "never") is None
    assert not (tmp_path / "never").exists()


def test_unwritable_folder_warns_once_and_runs_uncached(tmp_path, keep_cache, monkeypatch):
    monkeypatch.delenv(compilation.CACHE_ENV, raising=False)  # the suite run uncached sets it (JAXSLAM_TEST_NO_CACHE)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert compilation.enable_cache(blocker / "cache") is None
        assert compilation.enable_cache(blocker / "cache") is None
    assert len([x for x in w if issubclass(x.category, compilation.CacheWarning)]) == 1
    # The command runs, uncached, with one warning line.
    p, rep = _cli(RUN, blocker / "cache", tmp_path)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if "cannot be written" in ln]
    assert len(lines) == 1, p.stderr
    # one line in all (no file:line header, no source line), said as a warning
    assert lines[0].startswith("jaxslam: warning: compilation cache folder"), p.stderr
    assert not [ln for ln in p.stderr.splitlines() if "CacheWarning" in ln or "enable_cache" in ln], p.stderr
    assert rep["timing"]["cache"]["dir"] is None and rep["timing"]["cache"]["hits"] == 0


def test_a_cache_path_whose_home_cannot_be_found_warns_and_runs_uncached(keep_cache, monkeypatch, capsys):
    # '~nosuchuser' raised RuntimeError from expanduser: every command, --version included,
    # ended in a traceback
    monkeypatch.delenv(compilation.CACHE_ENV, raising=False)
    bad = "~no_such_user_of_jaxslam/x"
    with pytest.raises(InputError, match=r"cannot expand '~no_such_user_of_jaxslam/x' \(from the path given\)"):
        compilation.cache_dir(bad)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert compilation.enable_cache(bad) is None
    assert [str(x.message) for x in w if issubclass(x.category, compilation.CacheWarning)]
    monkeypatch.setenv(compilation.CACHE_DIR_ENV, bad)
    with pytest.raises(InputError, match=r"\$JAXSLAM_CACHE_DIR"):
        compilation.cache_dir()
    monkeypatch.delenv(compilation.CACHE_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", "~no_such_user_of_jaxslam")
    with pytest.raises(InputError, match=r"\$XDG_CACHE_HOME"):
        compilation.cache_dir()
    monkeypatch.setenv(compilation.CACHE_DIR_ENV, bad)
    assert cli.main(["cache", "info"]) == 2  # an exit-2 error naming the variable, no traceback
    err = capsys.readouterr().err
    assert "JAXSLAM_CACHE_DIR" in err and "Traceback" not in err


def test_cache_info_says_when_the_folder_cannot_be_used(tmp_path, keep_cache, monkeypatch, capsys):
    # 'cache info' printed '(on)' right after the warning that the folder cannot be written
    monkeypatch.delenv(compilation.CACHE_ENV, raising=False)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    info = compilation.cache_info(blocker / "cache")
    assert info["enabled"] and not info["usable"] and "is not a folder" in info["reason"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", compilation.CacheWarning)
        assert compilation.enable_cache(blocker / "cache") is None
    assert compilation.cache_info(blocker / "cache")["usable"] is False
    assert compilation.cache_info(tmp_path / "fine")["usable"] is True
    assert cli.main(["cache", "info", "--dir", str(blocker / "cache")]) == 0
    assert "on but unusable" in capsys.readouterr().out


def test_second_call_is_served_and_corrupt_entries_are_ignored(tmp_path):
    cache = tmp_path / "cache"
    p1, cold = _cli(RUN, cache, tmp_path)
    assert p1.returncode == 0, p1.stderr
    assert cold["timing"]["cache"]["misses"] > 0 and cold["timing"]["cache"]["hits"] == 0
    programs = list((cache / "programs").glob("*.jaxprog"))
    assert programs, "the scenario's traced program is stored"
    p2, warm = _cli(RUN, cache, tmp_path)
    assert p2.returncode == 0, p2.stderr
    t = warm["timing"]
    assert t["cache"]["misses"] == 0 and t["cache"]["hits"] == t["programs"] > 0
    assert t["trace_s"] < 0.5 * cold["timing"]["trace_s"]  # the stored program was not traced again
    assert warm["metrics"] == cold["metrics"]
    # Corrupt every entry: truncated programs, garbage XLA executables.  Never a crash.
    for f in cache.rglob("*"):
        if f.is_file():
            data = f.read_bytes()
            f.write_bytes(data[: len(data) // 3] if f.suffix == ".jaxprog" else b"garbage" * 10)
    p3, again = _cli(RUN, cache, tmp_path)
    assert p3.returncode == 0, p3.stderr
    assert again["metrics"] == cold["metrics"]
    assert "could not be used" in p3.stderr  # the stored program, rebuilt


def test_cache_command_info_and_clear(tmp_path, capsys):
    d = tmp_path / "c"
    (d / "programs").mkdir(parents=True)
    (d / ("jit_x-" + "ab" * 32 + "-cache")).write_bytes(b"1" * 1000)  # JAX's <name>-<sha256>-cache
    (d / "programs" / "p.jaxprog").write_bytes(b"2" * 24)
    assert cli.main(["cache", "info", "--dir", str(d), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["entries"] == 2 and info["bytes"] == 1024 and info["dir"] == str(d)
    assert cli.main(["cache", "clear", "--dir", str(d)]) == 0
    assert "2 entries" in capsys.readouterr().out and not any(d.rglob("*"))
    assert cli.main(["cache", "wipe"]) == 2


def test_compile_program_stores_memoises_and_rebuilds(tmp_path, monkeypatch):
    monkeypatch.setattr(compilation, "_enabled_dir", tmp_path)
    compilation.clear_programs()
    traces = []

    def fn(x, p):
        traces.append(1)
        return {"y": jnp.sin(x) * p["a"], "n": jnp.sum(x)}

    args = (jnp.arange(3.0), {"a": 2.0})
    c1 = compilation.compile_program(fn, args, key={"k": 1})
    out = c1(*args)
    np.testing.assert_allclose(out["y"], np.sin(np.arange(3.0)) * 2.0)
    assert len(traces) == 1 and len(list((tmp_path / "programs").glob("*.jaxprog"))) == 1
    # Same key in this process: no trace; new numbers run through the same program.
    c2 = compilation.compile_program(fn, (jnp.arange(3.0) + 1, {"a": 3.0}), key={"k": 1})
    assert c2 is c1 and len(traces) == 1
    np.testing.assert_allclose(c2(jnp.arange(3.0) + 1, {"a": 3.0})["y"], np.sin(np.arange(3.0) + 1) * 3.0)
    # A new process (memo cleared) loads the stored program without tracing fn.
    compilation.clear_programs()
    c3 = compilation.compile_program(fn, args, key={"k": 1})
    assert len(traces) == 1
    np.testing.assert_allclose(c3(*args)["y"], out["y"])
    # Another key, another shape: traced again.
    compilation.compile_program(fn, args, key={"k": 2})
    compilation.compile_program(fn, (jnp.arange(4.0), {"a": 2.0}), key={"k": 1})
    assert len(traces) == 3
    with pytest.raises(TypeError, match="structure"):
        c3(jnp.arange(3.0), 2.0)
    compilation.clear_programs()


def test_keys_holding_arrays_that_differ_get_different_programs(tmp_path, monkeypatch):
    # the key was written with repr: arrays over 1000 elements elided, others rounded to 8
    # digits, so a second key served the first key's program (a closed-over weight ignored)
    monkeypatch.setattr(compilation, "_enabled_dir", None)
    compilation.clear_programs()
    w1 = np.zeros(2000)
    w2 = w1.copy()
    w2[1000] = 5.0
    x = jnp.float32(0)
    assert float(compilation.compile_program(lambda v: v + jnp.asarray(w1).sum(), (x,), key={"w": w1})(x)) == 0.0
    assert float(compilation.compile_program(lambda v: v + jnp.asarray(w2).sum(), (x,), key={"w": w2})(x)) == 5.0
    digest = compilation._program_digest
    a = np.array([0.1])
    assert digest({"w": a}, (x,), None) != digest({"w": a + 1e-12}, (x,), None)
    assert digest({"w": np.float32(0.1)}, (x,), None) != digest({"w": np.float64(0.1)}, (x,), None)
    assert digest({"w": a}, (x,), None) == digest({"w": a.copy()}, (x,), None)  # equal keys still meet
    compilation.clear_programs()


def test_a_function_edited_under_the_same_key_gets_its_own_program(tmp_path, monkeypatch):
    # The digest held the key but not fn: another function under one key got the first one's
    # program, from memory and from disk (a user's edited scenario kept its old program).
    monkeypatch.setattr(compilation, "_enabled_dir", tmp_path)
    compilation.clear_programs()
    x = jnp.ones(3)
    np.testing.assert_array_equal(compilation.compile_program(lambda v: v + 1.0, (x,), key={"s": "mine"})(x), 2.0)
    np.testing.assert_array_equal(compilation.compile_program(lambda v: v * 10.0, (x,), key={"s": "mine"})(x), 10.0)
    compilation.clear_programs()  # a new process: from disk
    np.testing.assert_array_equal(compilation.compile_program(lambda v: v * 10.0, (x,), key={"s": "mine"})(x), 10.0)
    np.testing.assert_array_equal(compilation.compile_program(lambda v: v - 1.0, (x,), key={"s": "mine"})(x), 0.0)
    # a function the closure holds counts too
    inner_a, inner_b = (lambda v: v * 3.0), (lambda v: v * 4.0)
    assert compilation._code_digest(lambda v: inner_a(v)) != compilation._code_digest(lambda v: inner_b(v))
    assert len(list((tmp_path / "programs").glob("*.jaxprog"))) == 3
    # written readable to others, as JAX's own entries (0666 less the umask), not 0600
    umask = os.umask(0)
    os.umask(umask)
    for f in (tmp_path / "programs").glob("*.jaxprog"):
        assert f.stat().st_mode & 0o777 == 0o666 & ~umask
    compilation.clear_programs()


def test_the_random_bits_setting_is_part_of_a_stored_program_s_key():
    # jax_threefry_partitionable changes the draws a traced program makes; a program stored
    # under the other setting was served
    x = jnp.float32(0)
    before = compilation._program_digest({"k": 1}, (x,), None)
    flag = jax.config.jax_threefry_partitionable
    try:
        jax.config.update("jax_threefry_partitionable", not flag)
        assert compilation._program_digest({"k": 1}, (x,), None) != before
    finally:
        jax.config.update("jax_threefry_partitionable", flag)
    assert compilation._program_digest({"k": 1}, (x,), None) == before


def test_account_splits_trace_lower_compile():
    with compilation.account() as acc:
        jax.jit(lambda x: jnp.cos(x) * 3.0 + 1.0).lower(jnp.ones(7)).compile()
    a = acc.result
    assert a.programs >= 1 and a.trace_s > 0 and a.lower_s > 0 and a.compile_s > 0
    assert abs(a.total_s - (a.trace_s + a.lower_s + a.compile_s)) < 1e-12
    assert set(a.as_dict()) >= {"trace_s", "lower_s", "compile_s", "total_s", "cache_hits", "cache_misses"}


_SUITE_CACHE_CHOSEN = bool(os.environ.get("JAXSLAM_TEST_CACHE_DIR")) or os.environ.get("JAXSLAM_TEST_NO_CACHE") == "1"


@pytest.mark.skipif(_SUITE_CACHE_CHOSEN, reason="the suite's cache folder was chosen (or switched off) by the user")
def test_the_suites_cache_folder_is_inside_the_checkout():
    # The suite's own folder is test-local (conftest), never the user's XDG cache.
    here = pathlib.Path(__file__).resolve().parents[1]
    assert here in pathlib.Path(os.environ[compilation.CACHE_DIR_ENV]).resolve().parents


@pytest.mark.skipif(os.environ.get("JAXSLAM_TEST_NO_CACHE") == "1", reason="the suite runs uncached")
def test_the_suites_cache_is_on_after_the_tests_that_switch_it_off():
    assert compilation.enabled_dir() is not None and jax.config.jax_compilation_cache_dir


def test_clear_removes_only_the_caches_own_files(tmp_path):
    # a cache folder pointed at a folder of other files (a mistyped --dir) must not lose them
    folder = tmp_path / "mixed"
    (folder / "sub").mkdir(parents=True)
    (folder / "programs").mkdir()
    h = "0123abcd" * 8
    (folder / "xla_gpu_per_fusion_autotune_cache_dir").mkdir()  # XLA's GPU autotuning, in JAX's folder
    mine = [folder / f"jit_f-{h}-cache", folder / f"jit_f-{h}-atime", folder / "programs" / "ab12.jaxprog",
            folder / "xla_gpu_per_fusion_autotune_cache_dir" / "k.textproto"]
    theirs = [folder / "thesis.tex", folder / "sub" / "notes.txt", folder / "programs" / "readme.md",
              folder / "cache", folder / "my-notes-cache"]
    for p in mine + theirs:
        p.write_text("x")
    info = compilation.cache_info(folder)
    # thesis.tex, sub, cache, my-notes-cache, programs/readme.md
    assert info["entries"] == 4 and info["other"] == 5, info
    removed = compilation.clear_cache(folder)
    assert removed["entries"] == 4
    assert not any(p.exists() for p in mine)
    assert all(p.exists() for p in theirs)
    with pytest.raises(InputError, match="is not a folder"):
        compilation.cache_info(folder / "thesis.tex")
