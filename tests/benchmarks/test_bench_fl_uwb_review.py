"""Review of benchmarks/bench_filters.py, bench_lines.py and bench_uwb.py: ``bench lines
--slam-duration`` checked up front under its own name, ``bench lines --seed`` at the top of the
CLI's range, ``bench uwb`` Monte Carlo compile times per program and repeated ``--runs``, and
help text that says how often the NumPy references are timed."""

import json
import pathlib
import sys

import jax
import numpy as np
import pytest

from jaxslam import cli

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_lines  # noqa: E402


def _bench(capsys, name, *opts):
    rc = cli.main(["bench", name, "--dir", str(BENCH), *opts])
    out = capsys.readouterr()
    return rc, out.err, out.out


# ------------------------------------------------------------------ bench lines --slam-duration


@pytest.mark.parametrize("value", ["0", "-5", "0.05", "0.1"])
@pytest.mark.parametrize("parts", ["slam", "ransac,slam"])
def test_lines_slam_duration_named_and_checked_before_compute(capsys, value, parts):
    # one scan period is 0.1 s: a log needs more than that; the old message named "--duration"
    # (not an option of bench lines) and came only after the ransac part had run
    rc, err, _ = _bench(capsys, "lines", "--parts", parts, "--slam-duration", value,
                        "--scans", "1", "--twin-max", "1", "--repeats", "1", "--slam-runs", "1")
    assert rc == 2, err
    assert "--slam-duration" in err and "internal error" not in err
    assert "simulating" not in err  # nothing ran
    assert len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ bench lines --seed


def test_lines_prng_key_is_the_seed_as_64_bits():
    if str(jax.config.jax_default_prng_impl) != "threefry2x32":
        pytest.skip("hand values are threefry2x32 keys: [high word, low word]")
    # hand-computed two's-complement words of each seed
    cases = {0: [0, 0], 1: [0, 1], 2**40 + 7: [2**8, 7], 2**63 - 1: [0x7FFFFFFF, 0xFFFFFFFF],
             2**63: [0x80000000, 0], 2**63 + 5: [0x80000000, 5]}
    for seed, words in cases.items():
        np.testing.assert_array_equal(np.asarray(bench_lines._prng_key(seed)), np.array(words, np.uint32))


def test_lines_largest_seed_runs(capsys, tmp_path):
    """``--seed 2**63 - 1`` (the CLI accepts [0, 2**63)) used to stop with an internal
    OverflowError (exit 1) at the extraction keys (seed + 1), after the scans were simulated."""
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64")
    out = tmp_path / "lines.json"
    rc, err, _ = _bench(capsys, "lines", "--parts", "ransac", "--scans", "1", "--twin-max", "1",
                        "--repeats", "1", "--seed", str(2**63 - 1), "--json", str(out))
    assert rc == 0, err
    res = json.loads(out.read_text())
    assert res["config"]["seed"] == 2**63 - 1 and res["ransac"]["scans"] == 1


# ------------------------------------------------------------------ help text: reference repeats


@pytest.mark.parametrize("name,text", [("lines", "min(REPEATS, 3)"), ("uwb", "min(REPEATS, 2)"),
                                       ("filters", "max(1, REPEATS // 2)")])
def test_help_says_how_often_the_reference_is_timed(capsys, name, text):
    assert cli.main(["bench", name, "--dir", str(BENCH), "--help"]) == 0
    assert text in " ".join(capsys.readouterr().out.split())


# ------------------------------------------------------------------ bench uwb --runs, mc compile


def _uwb_mc(capsys, tmp_path, runs):
    out = tmp_path / "uwb.json"
    rc, err, _ = _bench(capsys, "uwb", "--parts", "mc", "--runs", runs, "--mc-chunk", "1",
                        "--seq-max", "1", "--repeats", "1", "--json", str(out))
    assert rc == 0, err
    return json.loads(out.read_text()), err


def test_uwb_mc_compile_time_is_the_programs_first_call(capsys, tmp_path):
    """With ``--mc-chunk 1`` both M run the one 1-run program: M = 2 reports its compile time
    (the first call's), not a warm call of it presented as a compile."""
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64")
    res, err = _uwb_mc(capsys, tmp_path, "1,2")
    rows = res["monte_carlo"]["rows"]
    assert [r["runs"] for r in rows] == [1, 2]
    assert [r["chunk"] for r in rows] == [1, 1] and [r["chunks"] for r in rows] == [1, 2]
    assert rows[1]["vmap_compile_s"] == rows[0]["vmap_compile_s"]
    assert err.count("compiling 1 runs") == 1


def test_uwb_repeated_runs_size_is_one_row(capsys, tmp_path):
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64")
    res, _ = _uwb_mc(capsys, tmp_path, "2,2")
    assert [r["runs"] for r in res["monte_carlo"]["rows"]] == [2]
    assert [r["params"]["runs"] for r in res["results"]] == [2]
