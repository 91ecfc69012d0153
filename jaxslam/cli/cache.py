"""``jaxslam cache info|clear``: the persistent XLA compilation cache (:mod:`jaxslam.compilation`)."""

from __future__ import annotations

import argparse

from .common import PROG, Parser, echo, path_arg

__all__ = ["command"]


def command(rest: list[str]) -> int:
    """``jaxslam cache info|clear``."""
    from jaxslam import compilation

    p = Parser(prog=f"{PROG} cache",
                description="The persistent XLA compilation cache every jaxslam command uses "
                            f"(folder: ${compilation.CACHE_DIR_ENV}, else $XDG_CACHE_HOME/jaxslam/xla, "
                            f"else ~/.cache/jaxslam/xla; {compilation.CACHE_ENV}=0 switches it off).")
    p.add_argument("action", choices=("info", "clear"), help="info: folder, entries, size; clear: delete the cache's own entries (other files in the folder are left alone)")
    p.add_argument("--dir", metavar="DIR", type=path_arg, help="the cache folder (default: as above)")
    p.add_argument("--json", action="store_true", help="print the information as JSON")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(rest)
    if args.action == "info":
        info = compilation.cache_info(args.dir)
    else:
        info = compilation.clear_cache(args.dir)
        info = {**info, "removed_entries": info.pop("entries"), "removed_bytes": info.pop("bytes")}
    if args.json:
        import json

        echo(json.dumps(info, indent=2))
        return 0
    state = ("on" if info["usable"] else f"on but unusable: {info['reason']}; commands run uncached") \
        if info["enabled"] else f"off ({compilation.CACHE_ENV}=0)"
    if args.action == "info":
        echo(f"compilation cache: {info['dir']} ({state})")
        echo(f"  {info['entries']} entries, {info['bytes'] / 2**20:.1f} MiB"
             + ("" if info["exists"] else " (folder not created yet)"))
        if info["other"]:
            echo(f"  {info['other']} other entries in the folder (not this cache's; never removed)")
    else:
        echo(f"cleared {info['dir']}: {info['removed_entries']} entries, "
             f"{info['removed_bytes'] / 2**20:.1f} MiB removed"
             + (f"; {info['other']} other entries left in place (not this cache's)" if info["other"] else ""))
    return 0
