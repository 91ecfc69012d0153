"""Output files: checked before any compute, written atomically.

Every command that writes (``--json``, ``--plots``, ``--tum``, ``--params-out``) calls
:func:`prepare_file` / :func:`prepare_dir` on its paths while parsing its arguments, before
JAX is asked to compile anything, so an unusable path costs a second, not the run.  The
writers then go through :func:`atomic_write`: the bytes land in a temporary file in the
target's folder and are renamed over the target, so an interrupted or failed write never
leaves a truncated file (a reader sees the old file or the new one).

Decisions
- "Usable" is tested, not guessed: the folder is created (with its parents) and a
  temporary file is created and removed in it.  Permission bits alone are wrong for root,
  ACLs and read-only mounts.
- The error names the option and says what is wrong in words (``'out/x' is a file, so
  'out/x/run.json' cannot be created``), never a bare ``File exists``.
- A write that fails in the file system (a folder that cannot be made or written, a full
  disk) raises an :class:`InputError` naming the path and the reason, which is also the
  ``OSError`` it came from (``errno``, ``strerror``), so a caller that catches ``OSError`` to
  name its own option still does.
- Standard library only; nothing here is traced.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import stat
import tempfile
from typing import Callable, Optional

from jaxslam.errors import InputError

__all__ = ["prepare_file", "prepare_dir", "distinct_outputs", "atomic_write"]

_UMASK = os.umask(0o022)  # read once at import (os.umask can only be read by setting it)
os.umask(_UMASK)


def _blocking_ancestor(path: pathlib.Path) -> Optional[pathlib.Path]:
    """The first existing ancestor of ``path`` that is not a folder, if any."""
    for parent in reversed(path.parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def _check_no_file_above(flag: str, path: pathlib.Path, target: pathlib.Path) -> None:
    """InputError naming ``flag`` when an existing ancestor of ``path`` is a file (so
    ``target`` cannot be created): the words, not a bare ``File exists``."""
    blocker = _blocking_ancestor(path)
    if blocker is not None:
        raise InputError(f"{flag}: {str(blocker)!r} is a file, so {str(target)!r} cannot be created")


def _probe_folder(flag: str, folder: pathlib.Path, target: pathlib.Path, create: bool = True) -> None:
    """Create ``folder`` (and its parents) and check that a file can be created in it; with
    ``create=False`` nothing is made: the nearest existing folder on its way is probed instead
    (the missing ones would be made there)."""
    _check_no_file_above(flag, folder / "x", target)
    if not create:
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".jaxslam-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        reason = e.strerror or str(e)
        raise InputError(f"{flag}: cannot write into {str(folder)!r} ({reason})") from None


class _WriteError(InputError, OSError):
    """:func:`atomic_write`'s error for a failed write: an :class:`InputError` whose message
    names the target, that is also the ``OSError`` it came from (``errno``, ``strerror``;
    ``filename``: the target), so a caller's ``except OSError`` still handles it."""

    def __init__(self, message, errno=None, strerror=None, filename=None):
        super().__init__(message)
        self.errno, self.strerror, self.filename = errno, strerror, filename

    def __str__(self):  # the message, not OSError's "[Errno n] ..."
        return str(self.args[0])

    def __reduce__(self):  # (OSError's would rebuild it from errno, strerror, filename)
        return type(self), (self.args[0], self.errno, self.strerror, self.filename)


def _write_error(path, err: OSError, name: str = "path") -> _WriteError:
    """The :class:`_WriteError` of ``err``, raised while ``path`` (the argument ``name``) was written."""
    reason = err.strerror or str(err)
    return _WriteError(f"{name}: cannot write {str(path)!r} ({reason})", err.errno, err.strerror, str(path))


def _about_this_file(err: BaseException, *paths) -> bool:
    """Whether ``err`` (raised while the file was written) is a file-system refusal of the file
    being written: an ``OSError`` naming one of ``paths`` or no file (``write`` / ``close`` on a
    full disk).  An ``OSError`` about another file (one the ``write`` function read), a pipe
    whose reader left (``BrokenPipeError``: the CLI's quiet exit) or an error of this module is
    raised as is."""
    if not isinstance(err, OSError) or isinstance(err, (InputError, ConnectionError)):
        return False
    return err.filename is None or str(err.filename) in {str(p) for p in paths}


def _check_path(flag: str, path) -> None:
    """InputError naming ``flag`` unless ``path`` is a str or path-like (None, a number: not a path)."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"{flag}: expected a file or folder path, got {path!r}")


def prepare_file(flag: str, path, create: bool = True) -> pathlib.Path:
    """Check, before compute, that the output file ``path`` of option ``flag`` can be written.

    Creates the parent folders (``create=False``: creates nothing and probes the nearest
    existing folder on the way, for a command that may still stop at its own options; the
    folders are then made by a later call or by :func:`atomic_write`).  Raises
    :class:`InputError` naming ``flag`` when ``path`` is a folder, lies under a file, or its
    folder is not writable (an existing read-only file is replaced by :func:`atomic_write`, so
    only the folder's permission matters).
    """
    _check_path(flag, path)
    p = pathlib.Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise InputError(f"{flag}: {str(path)!r} is not a file name")
    if p.is_dir():
        raise InputError(f"{flag}: {str(p)!r} is a folder; give a file path")
    if _special_file(p) or _std_descriptor(p) is not None:  # /dev/stdout, a FIFO: written into as they are
        return p
    target = _link_target(flag, p) if p.is_symlink() else p  # written there (atomic_write): probe it
    _probe_folder(flag, target.parent, target, create=create)
    return p


def _special_file(p: pathlib.Path) -> bool:
    """``p`` exists (its links followed by the system) and is neither a regular file nor a
    folder: a device, a FIFO, a socket -- ``/dev/stdout`` among them, whose link into
    ``/proc/self/fd`` names a pipe (``pipe:[N]``) that no path resolution can follow."""
    try:
        mode = os.stat(p).st_mode
    except (OSError, ValueError):
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


def _std_descriptor(p: pathlib.Path) -> Optional[int]:
    """1 or 2 when ``p`` is the regular file this process's stdout or stderr writes into
    (``--json /dev/stdout >> log.txt``: ``/dev/stdout`` leads to ``log.txt``), else None."""
    try:
        st = os.stat(p)
    except (OSError, ValueError):
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    for fd in (1, 2):
        try:
            if os.path.samestat(st, os.fstat(fd)):
                return fd
        except OSError:
            pass
    return None


def _write_to_descriptor(fd: int, write: Callable, mode: str) -> None:
    """``write(f)`` into a buffer, then the bytes onto descriptor ``fd`` after what Python holds
    for it (stdout, stderr) is flushed: in order with the command's other output."""
    import io
    import sys

    buf = io.BytesIO() if "b" in mode else io.StringIO()
    write(buf)
    data = buf.getvalue()
    data = data if isinstance(data, bytes) else data.encode("utf-8")
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _link_target(flag: str, p: pathlib.Path) -> pathlib.Path:
    """The file a symbolic link ``p`` names (followed as :func:`atomic_write` follows it), or an
    :class:`InputError` naming ``flag`` for a link that cannot be followed (a loop)."""
    try:
        return p.resolve()
    except (RuntimeError, OSError) as e:  # (a loop: RuntimeError before Python 3.13, OSError after)
        raise InputError(f"{flag}: {str(p)!r} is a symbolic link that cannot be followed ({e})") from None


def prepare_dir(flag: str, path) -> pathlib.Path:
    """Check, before compute, that the output folder ``path`` of option ``flag`` is usable.

    Creates it (with its parents) and checks that files can be created in it; raises
    :class:`InputError` naming ``flag`` otherwise.
    """
    _check_path(flag, path)
    p = pathlib.Path(path)
    if str(path) == "":
        raise InputError(f"{flag}: '' is not a folder name")
    if p.exists() and not p.is_dir():
        raise InputError(f"{flag}: {str(p)!r} exists and is not a folder")
    _probe_folder(flag, p, p)
    return p


def distinct_outputs(*, folders=None, inputs=None, **paths) -> None:
    """No output overwrites another output or an input; else an :class:`InputError` naming the
    option (the later write would replace the earlier's, or the input the command reads).

    ``paths``: the output files (``flag=path``, underscores for dashes, None: not asked for),
    pairwise distinct.  ``folders``: the output folders (``{flag: path}``), none of which may be
    an output file or lie under one (the folder could not be made, or the file not written,
    after the compute).  ``inputs``: the files the command reads (``{flag: path}``), none of
    which may be an output file.
    """
    def key(name, path):
        flag = "--" + name.replace("_", "-")
        return flag, _link_target(flag, pathlib.Path(path))

    seen = {}
    for name, path in paths.items():
        if path is None:
            continue
        flag, k = key(name, path)
        if k in seen:
            raise InputError(f"{flag}: {str(path)!r} is also {seen[k]}'s file; give each output its own path")
        seen[k] = flag
    for name, path in (inputs or {}).items():
        if path is None:
            continue
        flag, k = key(name, path)
        if k in seen:
            raise InputError(f"{seen[k]}: {str(path)!r} is the {flag} file this command reads; writing it "
                             "would replace it, so give the output another path")
    for name, path in (folders or {}).items():
        if path is None:
            continue
        flag, k = key(name, path)
        for f, out in seen.items():
            if k == f or f in k.parents:
                where = "is" if k == f else "lies under"
                raise InputError(f"{flag}: {str(path)!r} {where} {out}'s file {str(f)!r}; give the folder "
                                 "another path")


def atomic_write(path, write: Callable, mode: str = "w", *, name: str = "path") -> pathlib.Path:
    """Write ``path`` atomically: ``write(f)`` fills a temporary file that is renamed over it.

    A replaced file keeps its permission bits (a new one gets ``0666`` less the umask).  A
    symbolic link is followed (its target is replaced, the link kept); an existing path that
    is not a regular file (``/dev/null``, a FIFO, a terminal) is written into directly — a
    rename would replace the device with a file.

    Args:
      path: the target; its folder is created.
      write: called with the open temporary file (text mode with ``mode="w"``, binary with
        ``"wb"``).
      name: what the messages about ``path`` call it (a caller's own argument or option, e.g.
        ``"directory"``); ``"path"`` by default.
    Returns:
      The target path.  On any exception the temporary file is removed and the target is
      left as it was.  The temporary file is synced to the disk (``fsync``) before the
      rename, and the folder after it where the system supports that (POSIX), so a crash
      leaves the old file or the whole new one.
    Raises:
      InputError: ``path`` is a folder or lies under a file, or the file system refused the
        write (the folder cannot be made or written, the disk is full): the message names
        ``path`` (as ``name``) and the reason; the latter is also an ``OSError`` (``errno``,
        ``strerror``).
    """
    if not isinstance(name, str) or not name:
        raise InputError(f"name: expected the name of the path argument, got {name!r}"[:300])
    _check_path(name, path)
    if not callable(write):
        raise InputError(f"write: expected a function write(f) that fills the file, got {type(write).__name__}")
    if mode not in ("w", "wb"):
        raise InputError(f"mode: expected 'w' or 'wb', got {mode!r}")
    path = pathlib.Path(path)
    opts = {"encoding": "utf-8"} if "b" not in mode else {}
    fd = _std_descriptor(path)
    if fd is not None:  # /dev/stdout redirected into a file: written on, not replaced (its content kept)
        try:
            _write_to_descriptor(fd, write, mode)
        except OSError as e:
            raise _write_error(path, e, name) from None
        return path
    try:
        if _special_file(path):  # (opened as named: /dev/stdout on a pipe cannot be resolved)
            is_dir, special = False, True
        else:
            if path.is_symlink():
                path = _link_target(name, path)
            is_dir, special = path.is_dir(), path.exists() and not path.is_file()
    except OSError as e:  # (e.g. a folder on the way that cannot be searched)
        raise _write_error(path, e, name) from None
    if is_dir:
        raise InputError(f"{name}: {str(path)!r} is a folder; give a file path")
    if special:  # (a folder was refused above)
        try:
            with open(path, mode, **opts) as f:
                write(f)
        except OSError as e:
            if not _about_this_file(e, path):
                raise
            raise _write_error(path, e, name) from None
        return path
    try:
        _check_no_file_above(name, path, path)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            keep_mode = stat.S_IMODE(os.stat(path).st_mode) & 0o777  # not setuid/setgid/sticky
        except FileNotFoundError:
            keep_mode = None
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        raise _write_error(path, e, name) from None
    try:
        with os.fdopen(fd, mode, **opts) as f:
            write(f)
            # on the disk before the rename: after a crash the target is the old file or the
            # whole new one (without it, ext4 and others could show a renamed empty file)
            f.flush()
            os.fsync(f.fileno())
        # mkstemp makes 0600: keep the replaced file's permission bits, else give the usual mode
        os.chmod(tmp, keep_mode if keep_mode is not None else 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if _about_this_file(e, tmp, path):
            raise _write_error(path, e, name) from None
        raise
    _fsync_dir(path.parent)
    return path


def _fsync_dir(folder) -> None:
    """Flush ``folder``'s entries (the rename of :func:`atomic_write`) to the disk, where the
    system supports it (POSIX; a folder cannot be opened on Windows, and some file systems
    refuse to sync one): best effort, never an error (the file itself is already synced)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
