"""Simulation: the closed-loop flight (:mod:`jaxslam.sim.simulate`), vmapped Monte Carlo
(:mod:`jaxslam.sim.monte_carlo`) and the scenarios behind ``jaxslam run``
(:mod:`jaxslam.sim.scenarios`).
"""
