"""``python -m jaxslam``: the same as the ``jaxslam`` console script."""

from jaxslam.cli import main

raise SystemExit(main())
