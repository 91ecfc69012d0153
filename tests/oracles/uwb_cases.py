"""Shared, compiled-once UWB test cases (imported by the UWB system and scenario tests).

Compilation dominates these tests, so each filter configuration is jitted once per
process and the true path is passed as data: one compiled ``run`` serves every
scenario of the same length and every noise draw.
"""

import functools

import jax
import jax.numpy as jnp

from jaxslam.sim.scenarios import uwb as S
from jaxslam.systems import uwb_slam_2d as U

DURATION = 40.0  # s of flight after the start-up in the shared cases


def opts(**kw):
    o = dict(mode="slam", model="squared", noise="uniform", filter="paper", duration=DURATION, dt=1.0,
             anchors=3, startup_speed=0.15, max_range=0.0, chunk=None)
    o.update(kw)
    return o


def case(mode="slam", model="squared", filt="paper", anchors=3, duration=DURATION):
    """(cfg, fp, setup, run(log, fp, anchors), simulate(key, truth, dist)) for one filter configuration."""
    return _case(mode, model, filt, int(anchors), float(duration))


@functools.lru_cache(maxsize=None)
def _case(mode, model, filt, anchors, duration):
    _, _, cfg, fp, setup = S.build("circle", opts(mode=mode, model=model, filter=filt, anchors=anchors,
                                                  duration=duration), jnp.float64)
    run = jax.jit(lambda log, fp, anchors: U.run(log._replace(anchors=anchors) if cfg.mode == "localization"
                                                 else log, cfg, fp))
    sims = {d: jax.jit(lambda k, truth, d=d: S.simulate(k, setup._replace(truth=truth, dist=d), jnp.float64))
            for d in ("uniform", "gaussian")}

    def simulate(key, truth=None, dist="uniform"):
        return sims[dist](key, jnp.asarray(setup.truth if truth is None else truth))

    return cfg, fp, setup, run, simulate


@functools.lru_cache(maxsize=None)
def truth(scenario, duration=DURATION):
    """(T, 10) true planar states of a scenario."""
    return S.make_setup(scenario, duration=duration).truth
