"""``jaxslam list``: the scenarios, the benchmarks and the datasets (found in a data folder or not)."""

from __future__ import annotations

import argparse
import os

from jaxslam.errors import InputError

from .bench import find_benchmarks_dir, list_benchmarks
from .common import PROG, Parser, echo, path_arg

__all__ = ["command"]


def command(rest: list[str]) -> int:
    """``jaxslam list``: scenarios, benchmarks and datasets (found or not)."""
    p = Parser(prog=f"{PROG} list", description="List scenarios, benchmarks and datasets.")
    p.add_argument("--dir", metavar="DIR", type=path_arg, help="benchmarks folder (default: see 'jaxslam bench --help')")
    p.add_argument("--data", metavar="DIR", type=path_arg,
                   help="data folder whose datasets to show as found / not found (default: $JAXSLAM_DATA_DIR)")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(rest)
    from jaxslam.data import catalogue

    root = None  # checked first: a bad --data costs no JAX import
    if args.data:
        root = catalogue.data_root(args.data)
    elif os.environ.get(catalogue.DATA_ENV, "").strip():
        try:  # a stale variable does not stop the listing
            root = catalogue.data_root(None)
        except InputError as e:
            root = f"{e}, so found / not found is not shown"

    from jaxslam.sim.scenarios import registry

    # declared, not loaded: the built-in scenarios' modules (and JAX) are not imported to list them
    scenarios = [registry.declared(n) for n in registry.names()]
    echo(f"Scenarios ({PROG} run NAME):")
    if scenarios:
        w = max(len(s.name) for s in scenarios)
        for s in scenarios:
            echo(f"  {s.name.ljust(w)}  {s.description.strip()}")
    else:
        echo("  (none registered)")

    echo()
    try:
        bench_dir = find_benchmarks_dir(args.dir)
    except InputError as e:
        if args.dir:
            raise
        bench_dir, note = None, str(e)
    benches = list_benchmarks(bench_dir) if bench_dir is not None else {}
    echo(f"Benchmarks ({PROG} bench NAME)" + (f", in {bench_dir}:" if bench_dir else ":"))
    if benches:
        w = max(len(n) for n in benches)
        for name, desc in benches.items():
            echo(f"  {name.ljust(w)}  {desc}")
    else:
        echo(f"  (none: {note})" if bench_dir is None else "  (none)")

    echo()
    _list_datasets(root)
    return 0


def _list_datasets(root) -> None:
    """The datasets of ``jaxslam dataset`` and, when a data folder is known, which it holds."""
    from jaxslam.data import catalogue

    if isinstance(root, str):  # the environment's folder is not usable: say so, list the rest
        echo(f"Datasets ({PROG} dataset NAME --data DIR; {root}):")
        w = max(len(d.name) for d in catalogue.DATASETS)
        for d in catalogue.DATASETS:
            echo(f"  {d.name.ljust(w)}  {d.description}")
        return
    where = f"in {root}" if root is not None else f"give --data DIR or set {catalogue.DATA_ENV} to see which are present"
    echo(f"Datasets ({PROG} dataset NAME --data DIR; {where}):")
    w = max(len(d.name) for d in catalogue.DATASETS)
    for d in catalogue.DATASETS:
        state = ""
        if root is not None:
            folder = catalogue.find(d.name, root)
            robots = catalogue.robots_found(d.name, root)
            state = ("  [not found]" if folder is None else
                     f"  [found: {folder}" + (f", --robot {', '.join(map(str, robots))}" if robots else "") + "]")
        echo(f"  {d.name.ljust(w)}  {d.description}{state}")


# ----------------------------------------------------------------------------- run
