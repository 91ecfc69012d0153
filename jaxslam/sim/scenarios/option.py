"""A scenario's command-line option (``jaxslam run NAME --option VALUE``).

Its own module so that the registry (:mod:`~jaxslam.sim.scenarios.registry`) and the
built-in scenarios' declarations (:mod:`~jaxslam.sim.scenarios.builtin`) both use it and
neither imports the other at module level.  Re-exported as ``registry.Option``.
"""

from __future__ import annotations

import dataclasses

__all__ = ["Option"]


@dataclasses.dataclass(frozen=True)
class Option:
    """A scenario-specific command-line option (e.g. ``--duration``, ``--capacity``).

    Attributes:
      name: Python identifier; ``"duration"`` -> ``--duration``, ``"noise_scale"``
        -> ``--noise-scale``.  The key in the ``options`` dict passed to ``run``.
      type: one of ``float``, ``int``, ``str``, ``bool`` (``bool`` is a flag).
      default: value used when the option is not given; state units in ``help``.
      help: one line for ``jaxslam run SCENARIO --help``, with units.
      choices: allowed values, or ``None`` for any value of ``type``.
      lower: smallest allowed value of an ``int`` or ``float`` option, or ``None``
        (:func:`~jaxslam.sim.scenarios.registry.check_options`, so ``Scenario.run`` and the
        command line, refuse less).
    """

    name: str
    type: type
    default: object
    help: str
    choices: tuple | None = None
    lower: int | None = None

    @property
    def flag(self) -> str:
        """The primary command-line spelling, e.g. ``--noise-scale``."""
        return "--" + self.name.replace("_", "-")
