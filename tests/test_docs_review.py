"""Guards of docs/filters.md and docs/cli.md statements (review of 2026-12-07).

Oracles are independent of the code under test: the noise-free truth the doc's snippet
builds its data from, SciPy's chi-square quantiles, a linear Kalman filter written here in
NumPy, and the argparse parsers the commands really use (for the usage lines).
"""

from __future__ import annotations

import pathlib
import re
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

ROOT = pathlib.Path(__file__).resolve().parents[1]
FILTERS_MD = (ROOT / "docs" / "filters.md").read_text()
CLI_MD = (ROOT / "docs" / "cli.md").read_text()


def test_filters_md_snippet_runs_and_recovers_the_noise_free_track():
    """The ```python block of docs/filters.md runs as written in a fresh interpreter (it used to
    name f, h, x0, ... without defining them: NameError).  Its data are noise free, made from
    x_t = 1 + 0.05 t, v = 0.5 (t < T = 50), so every estimate's last mean is the truth."""
    blocks = re.findall(r"```python\n(.*?)```", FILTERS_MD, re.S)
    assert blocks, "docs/filters.md has no python block"
    r = subprocess.run([sys.executable, "-c", blocks[0]], cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    nums = [float(v) for v in re.findall(r"-?\d+\.\d*(?:e[-+]?\d+)?", r.stdout)]
    # sm.means[-1] (2), nll (1), post_u.means[-1] (2), it.means[-1] (2)
    assert len(nums) == 7, r.stdout
    truth = np.array([1.0 + 0.05 * 49, 0.5])
    for means in (nums[0:2], nums[3:5], nums[5:7]):
        np.testing.assert_allclose(means, truth, atol=2e-3)
    assert np.isfinite(nums[2])


@pytest.mark.parametrize("p", [0.5, 0.6, 0.9, 0.95, 0.99, 0.995])
def test_chi2_gate_beyond_its_table_within_documented_accuracy(p):
    """docs/filters.md: beyond the table, chi2_gate gives the Wilson–Hilferty quantile, exact for
    2 dof and, from 3 dof on, within 0.7 % for 0.5 <= p <= 0.995 (the doc said 'p <= 0.99',
    which is false below p = 0.5)."""
    from jaxslam.filters import ekf

    g = ekf.chi2_gate(p, 1)  # a table of 1 dof: every dof >= 2 is beyond it
    assert float(g(2)) == pytest.approx(stats.chi2.ppf(p, 2), rel=1e-12)
    dofs = np.arange(3, 80)
    got = np.array([float(g(int(d))) for d in dofs])
    rel = np.abs(got / stats.chi2.ppf(p, dofs) - 1)
    assert rel.max() <= 0.007, (dofs[rel.argmax()], rel.max())


@pytest.mark.parametrize("p, low", [(0.3, 0.01), (0.05, 0.06), (0.01, 0.3)])
def test_chi2_gate_beyond_its_table_poor_for_small_p_as_documented(p, low):
    """The doc's warning: for small p the approximation is off by more than 1 %, 6 %, 30 %."""
    from jaxslam.filters import ekf

    g = ekf.chi2_gate(p, 1)
    assert abs(float(g(3)) / stats.chi2.ppf(p, 3) - 1) > low


def _numpy_kf(F, H, x0, P0, us, zs, masks, Q, Rs):
    """Linear KF (predict with u_t, then update with z_t), masked components dropped."""
    x, P, out = np.array(x0, float), np.array(P0, float), []
    for t in range(len(zs)):
        x = F @ x + np.array([0.0, us[t, 0]])
        P = F @ P @ F.T + Q
        m = masks[t]
        if m.any():
            Hm, Rm = H[m], Rs[t][np.ix_(m, m)]
            S = Hm @ P @ Hm.T + Rm
            K = P @ Hm.T @ np.linalg.inv(S)
            x = x + K @ (zs[t][m] - Hm @ x)
            P = (np.eye(len(x)) - K @ Hm) @ P
        out.append(x.copy())
    return np.array(out)


def _masked_nan_problem():
    T = 6
    F = np.array([[1.0, 0.1], [0.0, 1.0]])
    H = np.eye(2)
    rng = np.random.default_rng(1)
    us, zs = rng.normal(size=(T, 1)), rng.normal(size=(T, 2))
    masks = np.ones((T, 2), bool)
    masks[2, 1] = False
    R = np.diag([0.3, 0.4])
    Rs = np.stack([R] * T)
    Rs[2, 1, 1] = Rs[2, 0, 1] = Rs[2, 1, 0] = np.nan  # only the masked row/column
    x0, P0, Q = np.array([0.0, 1.0]), np.diag([1.0, 2.0]), np.diag([0.01, 0.02])
    f = lambda x, u: jnp.asarray(F) @ x + jnp.array([0.0, u[0]])  # noqa: E731
    h = lambda x: x  # noqa: E731
    ref = _numpy_kf(F, H, x0, P0, us, zs, masks, Q, Rs)
    return f, h, x0, P0, us, zs, masks, Q, Rs, ref


@pytest.mark.parametrize("name", ["ekf", "ukf", "sqrt_ukf"])
def test_per_step_r_with_nan_on_masked_rows_is_accepted(name):
    """docs/filters.md: 'a per-step R may hold anything, NaN included, on the rows of masked
    measurements' — the run equals a NumPy KF that never reads those rows."""
    from jaxslam.filters import ekf, sqrt_ukf, ukf

    mod = {"ekf": ekf, "ukf": ukf, "sqrt_ukf": sqrt_ukf}[name]
    f, h, x0, P0, us, zs, masks, Q, Rs, ref = _masked_nan_problem()
    post = mod.filter_scan(f, h, x0, P0, us, zs, masks, Q, Rs)
    np.testing.assert_allclose(np.asarray(post.means), ref, atol=1e-10)


def test_sqrt_ekf_per_step_r_with_nan_on_masked_rows_is_accepted():
    # sqrt_ekf checked every row of a concrete per-step R, masked or not (the others did not)
    from jaxslam.filters import sqrt_ekf

    f, h, x0, P0, us, zs, masks, Q, Rs, ref = _masked_nan_problem()
    post = sqrt_ekf.filter_scan(f, h, x0, P0, us, zs, masks, Q, Rs)
    np.testing.assert_allclose(np.asarray(post.means), ref, atol=1e-10)


def _doc_usage(command: str) -> str:
    row = next(line for line in CLI_MD.splitlines() if line.startswith(f"| `jaxslam {command} "))
    return row.split("` |", 1)[0]


def _options(parser) -> set:
    return {s for a in parser._actions for s in a.option_strings
            if s.startswith("--") and s not in ("--help", "--debug")}


def test_cli_md_dataset_usage_lists_every_option():
    """The dataset row's usage line names every option of 'jaxslam dataset' (it lacked --smooth)."""
    from jaxslam.cli import dataset

    usage = _doc_usage("dataset NAME")
    missing = sorted(o for o in _options(dataset._parser()) if o not in usage)
    assert not missing, missing


def test_cli_md_run_usage_lists_every_common_option():
    """The run row's usage line names every common option of 'jaxslam run' (it lacked the
    process-group options --processes, --coordinator, --num-processes, --process-id)."""
    from jaxslam.cli import run

    usage = _doc_usage("run SCENARIO")
    missing = sorted(o for o in _options(run._run_parser()) if o not in usage)
    assert not missing, missing


def test_cli_md_consistency_example_matches_a_uwb_circle_run(tmp_path):
    """docs/cli.md's `consistency` JSON example is what `jaxslam run uwb-circle` (one run, seed 0)
    writes, to the two decimals shown (its steps_inside entries said 0.99 and 0.0: they are 0.90
    and 0.44), and its bounds are the two-sided 95 % chi-square bounds of one run (SciPy)."""
    import json

    m = re.search(r"Example \(`(?:jaxslam run )?uwb-circle`[^)]*\):\s*`(\{.*?\})`", CLI_MD, re.S)
    assert m, "the example is missing"
    doc = json.loads(re.sub(r"\s*\n\s*", " ", m.group(1)))
    out = tmp_path / "run.json"
    r = subprocess.run([sys.executable, "-m", "jaxslam", "run", "uwb-circle", "--runs", "1", "--seed", "0",
                        "--quiet", "--json", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(out.read_text())["consistency"]
    for key, value in doc.items():
        if isinstance(value, str):
            if "..." not in value:
                assert got[key] == value, key
        elif isinstance(value, list):
            np.testing.assert_allclose(got[key], value, atol=0.005 + 1e-12, err_msg=key)
        else:
            assert abs(got[key] - value) <= 0.005 + 1e-12, (key, got[key], value)
    for key, dim in (("anees_bounds", 2), ("anees_robot_bounds", 10)):
        np.testing.assert_allclose(got[key], stats.chi2.ppf([0.025, 0.975], dim), rtol=1e-9)
