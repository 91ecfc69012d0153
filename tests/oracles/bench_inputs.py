"""Small inputs for the benchmarks' helpers (``benchmarks/``), shared by their tests."""

import argparse
import types

import numpy as np


def fastslam_mc_jobs(bench_fastslam, seed: int, M: int = 2, F: int = 1):
    """``bench_fastslam._mc_jobs`` at ``--seed seed`` (Monte Carlo batches of 1 and 2 runs of 0.1 s,
    3 particles) on an all-zero flight of ``M + F`` LiDAR frames: ``(jobs, (keys, ...), N, F)``."""
    import jax.numpy as jnp

    from jaxslam.sim.scenarios import fastslam as sc

    p = argparse.ArgumentParser()
    bench_fastslam.add_arguments(p)
    args = p.parse_args(["--seed", str(seed), "--mc-runs", "1,2", "--mc-duration", "0.1", "--mc-chunk", "2",
                         "--mc-particles", "3"])
    cfg, prm = sc.make_filter({o.name: o.default for o in sc.OPTIONS}, jnp.float64)
    E = bench_fastslam.LIDAR_EVERY
    fl = types.SimpleNamespace(truth=np.zeros(((M + F) * E, 12)), rotor=np.zeros(((M + F) * E, 4)),
                               imu=np.zeros(((M + F) * E, 6)), z=np.zeros((M + F, 4, 3)),
                               mask=np.zeros((M + F, 4), bool))
    return bench_fastslam._mc_jobs(args, cfg, prm, fl, np.arange(4))
