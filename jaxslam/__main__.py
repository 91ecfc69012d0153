"""``python -m jaxslam``: the same as the ``jaxslam`` console script.

A Ctrl-C before :func:`jaxslam.cli.main` handles it -- while the command's modules import (about
0.3 s: NumPy), or while ``main`` sets up the process outside its own handler -- ends with the
command's one line and exit code (``jaxslam: interrupted``, 130), not a traceback: the processes
that ``jaxslam run ... --processes P`` starts are ``python -m jaxslam``, and a Ctrl-C on the
terminal reaches them while they start.
"""

import sys

try:
    from jaxslam.cli import main

    code = main()
except KeyboardInterrupt:
    print("jaxslam: interrupted", file=sys.stderr, flush=True)  # as jaxslam.cli.main says it
    code = 130

raise SystemExit(code)
