"""Monte Carlo split over a group of processes (``jax.distributed``, loopback, gloo): the same
per-run results as one process; usage errors; the block arithmetic."""

import json
import subprocess
import sys

import numpy as np
import pytest

from jaxslam import cli
from jaxslam.errors import InputError
from jaxslam.sim import distributed


def _run(argv):
    return subprocess.run([sys.executable, "-m", "jaxslam", "run", *argv], capture_output=True, text=True,
                          timeout=600)


def test_two_processes_give_the_single_process_runs(tmp_path):
    """5 runs over 2 processes (blocks of 3, the last padded): every per-run metric equals the
    single-process run's (1e-12), the batch statistics too; only process 0 writes."""
    one, two = tmp_path / "one.json", tmp_path / "two.json"
    r1 = _run(["uwb-circle", "--runs", "5", "--json", str(one), "--quiet"])
    assert r1.returncode == 0, r1.stderr
    r2 = _run(["uwb-circle", "--runs", "5", "--json", str(two), "--processes", "2"])
    assert r2.returncode == 0, r2.stderr
    a, b = json.loads(one.read_text()), json.loads(two.read_text())
    assert b["runs"] == a["runs"] == 5 and b["config"]["processes"] == 2 and "processes" not in a["config"]
    assert set(a["metrics"]) == set(b["metrics"])
    for k, v in a["metrics"].items():
        x = np.array(v["per_run"], float)
        y = np.array(b["metrics"][k]["per_run"], float)
        np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-300, err_msg=k)
    np.testing.assert_allclose(b["consistency"]["anees"], a["consistency"]["anees"], rtol=1e-12)
    assert b["flags"] == a["flags"]
    assert r2.stdout.count("wrote ") == 1  # process 0 alone printed and wrote


def test_quiet_group_member_silences_its_stdout_descriptor():
    # --quiet in a group points file descriptor 1 at the null device, so what C++ prints there
    # (gloo's 'Rank 0 is connected ...') goes too; stderr stays
    code = ("import os, sys; from jaxslam.cli.common import silence_stdout; print('before', flush=True); "
            "silence_stdout(); os.write(1, b'c-level'); print('python'); sys.stdout.flush(); "
            "os.write(2, b'still on stderr')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "before\n" and r.stderr == "still on stderr"


@pytest.mark.parametrize("argv, needle", [
    (["--processes", "2", "--num-processes", "2"], "--processes starts its own group"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2"], "needs all of"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "2"], "--process-id"),
    (["--processes", "0"], "--processes"),
])
def test_group_usage_errors_exit_2(capsys, argv, needle):
    assert cli.main(["run", "uwb-circle", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_a_bad_output_path_fails_before_the_group_starts(tmp_path, capsys):
    (tmp_path / "f").write_text("a file, not a folder")
    assert cli.main(["run", "uwb-circle", "--processes", "2", "--json", str(tmp_path / "f" / "x.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--json" in err[0]


def test_an_error_every_process_meets_is_said_once():
    r = _run(["no-such", "--processes", "2"])
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert len(lines) == 1 and "no-such" in lines[0]


def test_process_0_shows_the_group_s_progress():
    from jaxslam.sim.monte_carlo import _GroupProgress

    seen = []

    class P:
        def update(self, n):
            seen.append(n)

    g = _GroupProgress(P(), 2, 5)
    for n in (1, 2, 3):  # process 0's block of 3 runs
        g.update(n)
    assert seen == [2, 4, 5] and g.compiling is None


def test_blocks_cover_the_runs_in_order():
    assert [distributed.block(5, 2, i) for i in range(2)] == [(0, 3), (3, 3)]
    assert [distributed.block(4, 4, i) for i in range(4)] == [(0, 1), (1, 1), (2, 1), (3, 1)]
    assert distributed.block(1, 2, 1) == (1, 1)  # all padding: computed and dropped
    for bad, needle in (("nohost", "--coordinator"), ("h:0", "--coordinator"), ("h:x", "--coordinator")):
        with pytest.raises(InputError, match=needle):
            distributed.initialize(bad, 2, 0)
    with pytest.raises(InputError, match="--process-id"):
        distributed.initialize("127.0.0.1:1234", 2, 2)
