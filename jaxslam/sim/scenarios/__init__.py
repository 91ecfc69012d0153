"""Built-in scenarios.

The registry (registry.py) imports the modules named in ``BUILTIN_MODULES``
lazily, on the first ``get()``/``all_scenarios()``, so ``jaxslam --help`` stays fast and a
broken scenario module cannot break the registry import itself; their names, descriptions and
options are declared in builtin.py (``names()`` and ``declared()`` import no module).
"""

BUILTIN_MODULES = (
    "jaxslam.sim.scenarios.tracking",
    "jaxslam.sim.scenarios.ekfslam3d",
    "jaxslam.sim.scenarios.uwb",
    "jaxslam.sim.scenarios.fastslam",
    "jaxslam.sim.scenarios.attitude",
    "jaxslam.sim.scenarios.lineslam",
)
