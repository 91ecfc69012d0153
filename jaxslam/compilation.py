"""Compile time: the persistent XLA compilation cache and an account of where compile time goes.

Compilation is what a user of a jitted library waits for first (the main job compiled 21 s
for 2.6 s of running before this module existed).  Two tools:

* **The persistent cache** (JAX's ``jax_compilation_cache_dir``): a compiled program is
  written to disk and a later process that builds the same program loads it instead of
  compiling again.  :func:`enable_cache` switches it on; every entry point (the ``jaxslam``
  command, the scripts, the notebook, the tests) calls it through
  :func:`jaxslam.runtime.configure_process`.  The library never enables it on import.

  Folder, first that applies: the ``path`` argument; ``$JAXSLAM_CACHE_DIR``;
  ``$XDG_CACHE_HOME/jaxslam/xla``; ``~/.cache/jaxslam/xla`` (the XDG base-directory
  convention).  ``JAXSLAM_CACHE=0`` (or ``off``, ``false``, ``no``) disables it.
  Every program is kept, however fast it compiled (JAX's default keeps only those over
  1 s, which on this project dropped 4046 of 4251 programs of the test suite), so a
  second call of a runner pays tracing and lowering only.

  Bad input never stops a run: a folder that cannot be created or written warns once
  (``CacheWarning``) and the process runs uncached; a corrupt or truncated entry is
  reported by JAX as a warning and compiled again (tested).

* **An account** (:class:`CompileAccount`, :func:`account`): JAX reports the seconds it
  spends tracing (Python → jaxpr), lowering (jaxpr → StableHLO) and compiling (XLA backend),
  and every persistent-cache hit and miss, through :mod:`jax.monitoring`.  A listener
  installed once sums them; ``with account() as acc:`` gives the totals of a block.
  The CLI reports them in its timing JSON; ``jaxslam bench compile`` tabulates them for
  every public runner.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import pathlib
import re
import shutil
import sys
import tempfile
import threading
import warnings

from .errors import InputError

__all__ = [
    "CacheWarning",
    "CompileAccount",
    "account",
    "cache_dir",
    "disable_cache",
    "enabled_dir",
    "enable_cache",
    "cache_info",
    "clear_cache",
    "compile_program",
    "clear_programs",
    "call_compiled",
    "kept_programs",
    "split_arrays",
    "at_top_level",
    "CACHE_ENV",
    "CACHE_DIR_ENV",
]

CACHE_ENV = "JAXSLAM_CACHE"  # "0" / "off" / "false" / "no": no persistent cache
CACHE_DIR_ENV = "JAXSLAM_CACHE_DIR"  # the cache folder
_OFF = ("0", "off", "false", "no")


class CacheWarning(RuntimeWarning):
    """The persistent compilation cache cannot be used; the process runs uncached."""


def cache_disabled() -> bool:
    """True when ``$JAXSLAM_CACHE`` switches the persistent cache off."""
    return os.environ.get(CACHE_ENV, "").strip().lower() in _OFF


def cache_dir(path=None) -> pathlib.Path:
    """The cache folder (see the module docstring for the order of precedence).

    Raises:
      InputError: a ``~`` that cannot be expanded (an unknown user, no home folder), naming
        where the path came from.
    """
    def expand(p, source):
        try:
            return pathlib.Path(p).expanduser() if source != "home" else pathlib.Path.home() / ".cache"
        except (RuntimeError, KeyError, OSError) as e:
            raise InputError(f"compilation cache folder: cannot expand {str(p)!r} (from {source}): {str(e).rstrip('.')}") from None

    if path is not None:
        return expand(path, "the path given")
    env = os.environ.get(CACHE_DIR_ENV, "").strip()
    if env:
        return expand(env, f"${CACHE_DIR_ENV}")
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = expand(xdg, "$XDG_CACHE_HOME") if xdg else expand("~", "home")
    return base / "jaxslam" / "xla"


_warned: set = set()
_unusable: dict = {}  # folder -> why this process could not use it (cache_info reports it)
_enabled_dir: pathlib.Path | None = None


def _warn_once(key: str, message: str) -> None:
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(message, CacheWarning, stacklevel=3)


def _writable(folder: pathlib.Path) -> str | None:
    """None if ``folder`` can be created and written, else the reason."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        return e.strerror or str(e)
    return None


def enable_cache(path=None) -> pathlib.Path | None:
    """Switch JAX's persistent compilation cache on in ``cache_dir(path)``.

    Returns the folder, or None when the cache is disabled (``$JAXSLAM_CACHE``) or the
    folder cannot be written (one :class:`CacheWarning` per folder, then uncached).
    Call it before the first compilation; later calls with the same folder are no-ops.
    """
    global _enabled_dir
    if cache_disabled():
        disable_cache()
        return None
    try:
        folder = cache_dir(path)
    except InputError as e:  # bad input never stops a run: one warning, then uncached
        _warn_once(str(e), f"jaxslam: {e}; running without the persistent cache (set {CACHE_DIR_ENV} "
                           f"to another folder, or {CACHE_ENV}=0 to silence this)")
        disable_cache()
        return None
    if _enabled_dir is not None and folder == _enabled_dir:
        return folder
    reason = _writable(folder)
    if reason is not None:
        _unusable[str(folder)] = reason
        _warn_once(str(folder), f"jaxslam: compilation cache folder {str(folder)!r} cannot be written "
                                f"({reason}); running without the persistent cache (set "
                                f"{CACHE_DIR_ENV} to another folder, or {CACHE_ENV}=0 to silence this)")
        disable_cache()
        return None
    settings = {
        "jax_compilation_cache_dir": str(folder),
        # Keep every program: most of this project's programs compile in well under JAX's 1 s
        # default, and a hit costs a file read (tens of µs to a few ms).
        "jax_persistent_cache_min_compile_time_secs": 0.0,
        "jax_persistent_cache_min_entry_size_bytes": -1,
    }
    if "jax" in sys.modules:
        import jax

        for name, value in settings.items():
            jax.config.update(name, value)
        try:  # JAX decides once, at its first compilation, whether a cache is in use
            from jax._src import compilation_cache as _cc

            _cc.reset_cache()
        except Exception:  # private API moved: the setting then applies from the next process
            pass
    else:  # before JAX is imported (the CLI at start-up): JAX reads these when it loads
        for name, value in settings.items():
            os.environ[name.upper()] = str(value)
    _enabled_dir = folder
    return folder


def disable_cache() -> None:
    """No persistent cache in this process (nor one inherited from a parent's environment): for
    measuring cold compile times in a process that enabled it (``jaxslam bench tuning``)."""
    global _enabled_dir
    _enabled_dir = None
    os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)
    if "jax" in sys.modules:
        import jax

        if jax.config.jax_compilation_cache_dir is not None:
            jax.config.update("jax_compilation_cache_dir", None)
            try:
                from jax._src import compilation_cache as _cc

                _cc.reset_cache()
            except Exception:  # private API moved
                pass


def enabled_dir() -> pathlib.Path | None:
    """The folder :func:`enable_cache` switched on in this process, or None."""
    return _enabled_dir


_JAX_ENTRY = re.compile(r"-[0-9a-f]{64}-(cache|atime)$")  # <module>-<sha256>-cache / -atime
# what JAX/XLA may also keep in the folder (GPU autotuning and kernel caches, the LRU lock)
_JAX_EXTRAS = ("xla_gpu_per_fusion_autotune_cache_dir", "xla_gpu_kernel_cache_file", ".lockfile")


def _cache_files(folder: pathlib.Path):
    """The entries of ``folder`` that this cache wrote: JAX's entries (``<name>-<sha256>-cache``
    and their ``-atime`` stamps), XLA's GPU autotune / kernel caches and JAX's lock file,
    leftover ``.probe-`` files, and the exported programs in ``programs/`` (``*.jaxprog`` and
    their ``.tmp-`` leftovers).  Nothing else is counted or removed, so a cache folder pointed
    at a folder of other files never loses them."""
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if p.is_symlink():
            continue
        if p.name in _JAX_EXTRAS or (p.is_file() and (_JAX_ENTRY.search(p.name) or p.name.startswith(".probe-"))):
            yield p
    prog = folder / _PROGRAMS
    if prog.is_dir() and not prog.is_symlink():
        for p in prog.iterdir():
            if p.is_file() and not p.is_symlink() and (p.suffix == ".jaxprog" or p.name.startswith(".tmp-")):
                yield p


def cache_info(path=None) -> dict:
    """``{"dir", "enabled", "usable", "reason", "exists", "entries", "bytes", "other"}`` of the
    cache folder (no JAX import).  ``enabled``: not switched off by ``$JAXSLAM_CACHE``;
    ``usable``: this process did not fail to write it (:func:`enable_cache`'s warning) and its
    nearest existing folder is writable, else ``reason`` says why; ``other``: entries of the
    folder that are not this cache's (never counted or removed)."""
    folder = cache_dir(path)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"cache folder {folder}: exists and is not a folder")
    entries = 0
    size = 0
    ours = set()
    for p in _cache_files(folder):
        ours.add(p)
        if not p.name.startswith(".probe-"):
            entries += 1
            try:
                size += p.stat().st_size
            except OSError:
                pass
    other = 0
    if folder.is_dir():
        other = sum(1 for p in folder.iterdir() if p not in ours and p.name != _PROGRAMS)
        prog = folder / _PROGRAMS
        if prog.is_dir() and not prog.is_symlink():
            other += sum(1 for p in prog.iterdir() if p not in ours)
    reason = _unusable.get(str(folder))
    if reason is None:  # without creating anything: the nearest existing folder on the way
        near = folder
        while not near.exists() and near != near.parent:
            near = near.parent
        if not near.is_dir():
            reason = f"{str(near)!r} is not a folder"
        elif not os.access(near, os.W_OK | os.X_OK):
            reason = f"{str(near)!r} is not writable"
    return {"dir": str(folder), "enabled": not cache_disabled(), "usable": reason is None, "reason": reason,
            "exists": folder.is_dir(), "entries": entries, "bytes": size, "other": other}


def clear_cache(path=None) -> dict:
    """Delete the cache's own files (:func:`cache_info` says which; anything else in the folder
    is left where it is and counted in ``other``); returns :func:`cache_info` of what was
    removed."""
    info = cache_info(path)
    folder = pathlib.Path(info["dir"])
    for p in list(_cache_files(folder)):
        try:
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink()
        except OSError:
            pass
    prog = folder / _PROGRAMS
    if prog.is_dir() and not prog.is_symlink():
        try:
            prog.rmdir()  # only when nothing else is in it
        except OSError:
            pass
    return info


# ---------------------------------------------------------------------------------- account

_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_COMPILE = "/jax/core/compile/backend_compile_duration"
_HIT = "/jax/compilation_cache/cache_hits"
_MISS = "/jax/compilation_cache/cache_misses"


@dataclasses.dataclass
class CompileAccount:
    """Seconds JAX spent tracing, lowering and compiling, and persistent-cache hits/misses.

    ``compile_s`` is XLA backend time, which includes loading a program from the cache
    (``cache_hits`` > 0: the cache served).  ``total_s`` = trace + lower + compile.
    ``programs`` counts backend compilations (or cache loads).
    """

    trace_s: float = 0.0
    lower_s: float = 0.0
    compile_s: float = 0.0
    programs: int = 0
    cache_hits: int = 0
    cache_misses: int = 0

    @property
    def total_s(self) -> float:
        return self.trace_s + self.lower_s + self.compile_s

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["total_s"] = self.total_s
        return d

    def __sub__(self, other: "CompileAccount") -> "CompileAccount":
        return CompileAccount(**{f.name: getattr(self, f.name) - getattr(other, f.name)
                                 for f in dataclasses.fields(self)})


_totals = CompileAccount()
_lock = threading.Lock()
_installed = False


def _on_duration(event: str, duration: float, **_kw) -> None:
    with _lock:
        if event == _TRACE:
            _totals.trace_s += duration
        elif event == _LOWER:
            _totals.lower_s += duration
        elif event == _COMPILE:
            _totals.compile_s += duration
            _totals.programs += 1


def _on_event(event: str, **_kw) -> None:
    with _lock:
        if event == _HIT:
            _totals.cache_hits += 1
        elif event == _MISS:
            _totals.cache_misses += 1


def _install() -> None:
    global _installed
    if _installed:
        return
    import jax.monitoring as mon

    mon.register_event_duration_secs_listener(_on_duration)
    mon.register_event_listener(_on_event)
    _installed = True


def totals() -> CompileAccount:
    """A copy of the process totals since the listener was installed."""
    _install()
    with _lock:
        return dataclasses.replace(_totals)


class _Block:
    def __init__(self):
        self._start = None
        self.result = CompileAccount()

    def __enter__(self) -> "_Block":
        self._start = totals()
        return self

    def __exit__(self, *exc) -> None:
        self.result = totals() - self._start


def account() -> contextlib.AbstractContextManager:
    """``with account() as acc: ...`` then ``acc.result`` is the :class:`CompileAccount`
    of the block."""
    return _Block()


# ---------------------------------------------------------------------------------- programs

_PROGRAMS = "programs"  # sub-folder of the cache folder holding exported (traced) programs
_source_digest: dict = {}


def _package_digest() -> str:
    """sha256 of every source file of the installed jaxslam package (any edit changes it)."""
    if "d" not in _source_digest:
        import hashlib

        root = pathlib.Path(__file__).resolve().parent
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _source_digest["d"] = h.hexdigest()
    return _source_digest["d"]


def _code_digest(fn, depth: int = 3) -> str:
    """sha256 of ``fn``'s own code (its code object with the nested ones: a lambda's body, a
    nested function) and of the code of the functions its closure holds, ``depth`` levels
    down; '' for a callable without code (a C function, a ``functools.partial`` of one)."""
    import hashlib
    import types

    h = hashlib.sha256()
    seen = set()

    def code_text(code) -> str:  # the same in every process (marshal's bytes are not)
        consts = []
        for c in code.co_consts:
            if isinstance(c, types.CodeType):
                consts.append(code_text(c))
            elif isinstance(c, frozenset):
                consts.append(repr(sorted(map(repr, c))))
            else:
                consts.append(repr(c))
        return repr((code.co_name, code.co_code.hex(), code.co_names, code.co_varnames, code.co_freevars,
                     consts))

    def visit(f, d):
        f = getattr(f, "func", f)  # functools.partial
        code = getattr(f, "__code__", None)
        if code is None or id(code) in seen:
            return
        seen.add(id(code))
        h.update(code_text(code).encode())
        if d > 0:
            for cell in getattr(f, "__closure__", None) or ():
                try:
                    v = cell.cell_contents
                except ValueError:  # an empty cell
                    continue
                if callable(v):
                    visit(v, d - 1)

    try:
        visit(fn, depth)
    except Exception:  # noqa: BLE001 - an object marshal cannot write: the key alone decides
        return ""
    return h.hexdigest()


def _program_digest(key, args, compiler_options, fn=None) -> str:
    import hashlib
    import json

    import jax
    import jaxlib

    avals = [(tuple(a.shape), str(a.dtype), bool(a.weak_type)) for a in jax.tree.leaves(_specs(args))]
    devices = jax.local_devices()
    material = {
        "key": key,
        "avals": avals,
        "args_tree": str(jax.tree.structure(args)),
        "compiler_options": compiler_options,
        "source": _package_digest(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "x64": bool(jax.config.jax_enable_x64),
        "matmul_precision": str(jax.config.jax_default_matmul_precision),
        # settings that change the traced program itself (random draws, type promotion)
        "threefry_partitionable": str(getattr(jax.config, "jax_threefry_partitionable", None)),
        "prng_impl": str(getattr(jax.config, "jax_default_prng_impl", None)),
        "dtype_promotion": str(getattr(jax.config, "jax_numpy_dtype_promotion", None)),
        "code": _code_digest(fn) if fn is not None else "",
        "platform": devices[0].platform,
        "device_kind": devices[0].device_kind,
    }
    text = json.dumps(material, sort_keys=True, default=_key_default)
    return hashlib.sha256(text.encode()).hexdigest()[:40]


def _key_default(obj):
    """JSON stand-in for what ``json`` cannot write in a program key: an array (or NumPy
    scalar) by its dtype, shape and a digest of its bytes — its ``repr`` rounds to 8 digits
    and elides arrays over 1000 elements, so two different keys shared a program — anything
    else by its ``repr``."""
    import hashlib

    import numpy as np

    if hasattr(obj, "__array__") or isinstance(obj, np.generic):
        a = np.asarray(obj)
        if a.dtype != object:
            return {"array": str(a.dtype), "shape": list(a.shape),
                    "sha256": hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()}
    return repr(obj)


def _specs(args):
    """ShapeDtypeStructs of ``args``' leaves (Python scalars stay weakly typed, as under jit)."""
    import jax
    import numpy as np

    def spec(a):
        if isinstance(a, (bool, int, float, complex)):
            return jax.ShapeDtypeStruct((), jax.dtypes.result_type(a), weak_type=True)
        weak = bool(getattr(a, "weak_type", False))
        return jax.ShapeDtypeStruct(np.shape(a), jax.dtypes.result_type(a), weak_type=weak)

    return jax.tree.map(spec, args)


def _export_available() -> bool:
    try:
        import flatbuffers  # noqa: F401  (jax.export's serialisation needs it)
    except ImportError:
        return False
    return True


def compile_program(fn, args, *, key=None, compiler_options=None):
    """Compile ``fn(*args)`` once and return ``compiled(*args) -> fn's output pytree``.

    With a ``key`` and the persistent cache on, the *traced* program is kept too (jax.export,
    StableHLO, in ``<cache folder>/programs``), so a later process skips tracing and lowering
    — on the main job those took 3-4 s, more than loading the compiled program.  ``key``
    (JSON-able; NumPy arrays and scalars in it are keyed by their exact bytes, anything else
    that JSON cannot write by its ``repr``) must name everything ``fn`` closes over that is not
    an argument: a scenario's name, options, parameters, dtype.  The stored program is further keyed by the argument
    shapes and dtypes, the compiler options, a digest of jaxslam's source files and of ``fn``'s
    own code (with the functions its closure holds, three levels down; not the functions it
    reaches through globals — name those in the key), the JAX and jaxlib versions, x64, the
    settings that change a traced program (``jax_threefry_partitionable``, the PRNG
    implementation, dtype promotion) and the device kind, so an edit of the code or an upgrade
    never serves a stale program.  A stored program that cannot be read is ignored and replaced
    (never a crash).  The compiled program is also kept in this process (the 32 most recent),
    so a second call with the same key — new numbers in the arguments — neither traces nor
    compiles.  Without a key (or without the ``flatbuffers`` package that ``jax.export``
    serialises with) this is ``jax.jit(fn).lower(*args).compile()``.
    """
    import jax

    jitted = jax.jit(fn, compiler_options=compiler_options)
    if key is None:
        return jitted.lower(*args).compile()
    digest = _program_digest(key, args, compiler_options, fn)
    if digest in _memo:  # the same program again in this process: no trace at all
        return _memo[digest]
    compiled = _compile_keyed(fn, jitted, args, digest, compiler_options)
    if len(_memo) >= _MEMO_MAX:
        _memo.pop(next(iter(_memo)))
    _memo[digest] = compiled
    return compiled


_memo: dict = {}
_MEMO_MAX = 32


def clear_programs() -> None:
    """Forget the programs :func:`compile_program` and :func:`call_compiled` keep in this
    process (the disk copies stay)."""
    _memo.clear()
    with _eager_lock:
        _eager.clear()
        _served.clear()
        _site_recent.clear()
        _site_second.clear()


def kept_programs() -> dict:
    """``{site: count}``: how many keys of each call site (a key's first element, e.g.
    ``"ekf.update"``) hold a compiled program that :func:`call_compiled` keeps now.  A site
    missing here runs its eager calls uncompiled (op by op, or re-traced) — a way to check that
    a loop of eager calls runs kept programs."""
    with _eager_lock:
        sites = [_site(k) for k, v in _eager.items() if not isinstance(v, int) and v is not _EAGER_ONLY]
    return dict(collections.Counter(sites))


def _compile_keyed(fn, jitted, args, digest, compiler_options):
    import jax

    folder = _enabled_dir
    if folder is None or not _export_available() or len(jax.local_devices()) != 1:
        return jitted.lower(*args).compile()
    import pickle

    from jax import export

    leaves, in_tree = jax.tree.flatten(args)
    path = folder / _PROGRAMS / f"{digest}.jaxprog"
    if path.is_file():
        try:
            blob = pickle.loads(path.read_bytes())
            exp = export.deserialize(bytearray(blob["exported"]))
            tree = pickle.loads(blob["out_tree"])
            compiled = jax.jit(exp.call, compiler_options=compiler_options).lower(*leaves).compile()
            return _Flat(compiled, in_tree, tree)
        except Exception as e:  # noqa: BLE001 - a bad entry must never stop a run
            _warn_once(f"prog:{path}", f"jaxslam: stored program {path.name} could not be used "
                                       f"({type(e).__name__}); compiling it again")
    holder = {}

    def flat(*lv):  # flat in, flat out: the stored program holds no Python types
        out = fn(*jax.tree.unflatten(in_tree, lv))
        out_leaves, holder["tree"] = jax.tree.flatten(out)
        return out_leaves

    try:
        exp = export.export(jax.jit(flat, compiler_options=compiler_options))(*_specs(leaves))
        data = pickle.dumps({"exported": bytes(exp.serialize()), "out_tree": pickle.dumps(holder["tree"])})
    except Exception:  # noqa: BLE001 - not exportable (e.g. a host callback): plain compile
        return jitted.lower(*args).compile()
    compiled = jax.jit(exp.call, compiler_options=compiler_options).lower(*leaves).compile()
    try:  # atomically, readable as JAX's own entries are (0666 less the umask: a shared folder)
        from .files import atomic_write

        atomic_write(path, lambda f: f.write(data), mode="wb")
    except OSError as e:
        _warn_once(f"progw:{folder}", f"jaxslam: cannot store a program in {str(path.parent)!r} "
                                      f"({e.strerror or e}); later calls will trace it again")
    return _Flat(compiled, in_tree, holder["tree"])


class _Flat:
    """A compiled flat-in, flat-out program called with, and returning, the original pytrees."""

    def __init__(self, compiled, in_tree, out_tree):
        self._compiled = compiled
        self._in_tree = in_tree
        self._out_tree = out_tree

    def __call__(self, *args):
        import jax

        leaves, tree = jax.tree.flatten(args)
        if tree != self._in_tree:
            raise TypeError(f"compiled program: arguments of structure {tree}, expected {self._in_tree}")
        return jax.tree.unflatten(self._out_tree, self._compiled(*leaves))


# ---------------------------------------------------------------------------
# Eager calls of a whole run: one compiled program per model, reused
# ---------------------------------------------------------------------------

_EAGER_MAX = 64  # keys (models × options × sites): a loop over the engine, FastSLAM and filter steps holds ~20
_eager: dict = {}
_eager_lock = threading.Lock()
# after="auto": calls served by each kept program, and per site (a key's first element) the
# keys it compiled last and whether it has fallen back to compiling on a key's second call
_served: dict = {}
_site_recent: dict = {}
_site_second: set = set()


def _site(key):
    """A key's call site: its first element, descending through nested tuples (the key of a
    call with options is ``(key, options' key)``)."""
    while isinstance(key, tuple) and key:
        key = key[0]
    return key


def _threshold(key, after) -> int:
    """The eager call of ``key`` at which it compiles: ``after``, or for ``"auto"`` 1 until the
    two keys its site compiled last each served a single call, 2 from then on.  (With the lock
    held.)"""
    if after != "auto":
        return after
    site = _site(key)
    recent = _site_recent.get(site, ())
    if len(recent) == 2 and all(_served.get(k, 0) == 1 for k in recent):
        _site_second.add(site)
    return 2 if site in _site_second else 1


def at_top_level() -> bool:
    """True when no JAX transformation (``jit``, ``grad``, ``vmap``, a ``scan`` body) is tracing
    the caller, i.e. the arrays a function receives are concrete.  Reads JAX's trace state
    (not public API); on a JAX without it, False (the caller then stays eager: correct,
    only slower)."""
    try:
        from jax._src import core
        return bool(core.trace_state_clean())
    except Exception:  # noqa: BLE001 - an unknown JAX: never fail, just do not compile
        return False


def call_compiled(key, fn, args, options=None, *, after=1):
    """``fn(*args)``, or ``fn(options, *args)``; called eagerly, through a program compiled once
    per ``key``.

    A whole run (a ``lax.scan`` over a log) called outside any transformation re-traces and
    re-compiles its scan on every call: 0.43-0.56 s for a two-state EKF over 200 steps on
    this project's machine, where the compiled program takes 1.5 ms.  Here the ``after``-th
    eager call with a given ``key`` compiles ``jax.jit(fn)`` and later calls with the same key
    and argument shapes and dtypes run the compiled program; the calls before it run ``fn``
    as it is.  ``after=1`` suits a run, whose uncompiled call compiles its scan anyway;
    ``after=2`` a single step, which runs op by op in a few ms uncompiled: a model made anew
    for every call (a lambda written inside the caller's loop) is then never compiled in
    vain.  ``after="auto"`` suits a step whose uncompiled first call is slow (the EKF-SLAM
    engine's: ~5 s op by op against ~0.8 s to compile the step): a key compiles on its first
    call, until its site (the key's first element, e.g. ``"ekf_slam.update"``) has compiled two
    keys in a row whose programs served one call each (a model made anew for every call); from
    then on the site compiles on a key's second call, as ``after=2``, until one of its kept
    programs serves a second call (the models are kept after all): then on first sight again.
    (A loop that calls one site with three or more keys before it reuses any — e.g. three
    option sets of one update — looks the same at its third key, which compiles at its second
    call; the reuse that follows puts the site back.)
    ``key`` (hashable) must name everything ``fn`` closes over that is not in ``args``
    (the model's functions, static options): a later call with an equal key runs the *first*
    compiled ``fn``, retraced when the shapes differ, so ``fn`` takes every size from its
    arguments, never from its closure.  The 64 most recent keys are kept (their programs with
    them).

    ``options`` (a pytree, or None: not passed): the arrays and numbers in it are arguments of
    the compiled program (a new value never recompiles), the rest — its structure, callables,
    strings, bools — joins the key (:func:`split_arrays`).

    Called under a transformation (the caller's own ``jit``, ``grad``, ``vmap``), with an
    unhashable key, or with a key whose compiled call raised a ``TypeError``, ``IndexError`` or
    ``OverflowError`` (a user's model branching in Python on an argument, slicing with it or
    indexing with a boolean mask: JAX's concretization errors; an argument JAX cannot take),
    ``fn`` runs as it always did, uncompiled — and so
    raises the caller's own error, if it was one.
    """
    if options is not None:
        if not at_top_level():
            return fn(options, *args)
        arrays, rebuild, okey = split_arrays(options)
        return call_compiled((key, okey), lambda arrs, *a: fn(rebuild(*arrs), *a), (arrays, *args),
                             after=after)
    if not at_top_level():
        return fn(*args)
    try:
        hash(key)
    except TypeError:
        return fn(*args)
    import jax

    with _eager_lock:
        entry = _eager.pop(key, 0)
        if isinstance(entry, int):  # calls so far, none compiled
            if entry + 1 >= _threshold(key, after):
                entry = jax.jit(fn)
                if after == "auto":
                    _site_recent.setdefault(_site(key), []).append(key)
                    del _site_recent[_site(key)][:-2]
            else:
                entry += 1
        _eager[key] = entry  # most recent last
        while len(_eager) > _EAGER_MAX:
            oldest = next(iter(_eager))
            del _eager[oldest]
            _served.pop(oldest, None)
        if after == "auto" and not isinstance(entry, int) and entry is not _EAGER_ONLY:
            _served[key] = _served.get(key, 0) + 1
            if _served[key] == 2:  # a kept model reused: the site's models are not made anew
                _site_second.discard(_site(key))
    if isinstance(entry, int) or entry is _EAGER_ONLY:
        return fn(*args)
    try:
        return entry(*args)
    except (TypeError, IndexError, OverflowError):
        # JAX's concretization errors (TypeErrors; IndexErrors for a slice bound or a boolean
        # mask that is an argument), an argument JAX cannot take (a string
        # array, an int beyond int32 without x64): the uncompiled call, which raises the
        # same error again if it was the caller's own
        with _eager_lock:
            _eager[key] = _EAGER_ONLY
        return fn(*args)


_EAGER_ONLY = object()  # a key whose fn needs concrete closure values: always eager


def split_arrays(tree):
    """``(arrays, rebuild, key)``: the array and number leaves of ``tree`` (the arguments of a
    compiled program: a new value never recompiles), ``rebuild(*arrays)`` putting them back, and
    a hashable ``key`` of the rest (the structure and the other leaves by type and value:
    callables, strings, bools, None stay static, as in an uncompiled call).  An unhashable leaf
    makes ``key`` unhashable, and the call uncompiled."""
    import jax
    import numpy as np

    leaves, treedef = jax.tree_util.tree_flatten(tree)
    is_array = tuple(isinstance(v, (jax.Array, np.ndarray, np.generic, int, float, complex))
                     and not isinstance(v, bool) for v in leaves)
    static = tuple(None if a else (type(v), v) for v, a in zip(leaves, is_array))
    arrays = tuple(v for v, a in zip(leaves, is_array) if a)

    def rebuild(*arrs):
        it = iter(arrs)
        return jax.tree_util.tree_unflatten(
            treedef, [next(it) if a else st[1] for st, a in zip(static, is_array)])

    return arrays, rebuild, (treedef, is_array, static)
