"""Processes a test started, read from ``/proc`` (Linux)."""

import os
import signal


def group_pids(pgid):
    """The processes of process group ``pgid`` still alive (zombies are not)."""
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            pids.append(int(d))
    return pids


def finish(proc, timeout=30):
    """``(stdout, stderr, left)`` of ``proc`` (started in its own process group) once it ends
    within ``timeout`` s; the processes of its group still alive then (``left``) are killed,
    as ``proc`` is if it has not ended."""
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        left = group_pids(proc.pid)
        if proc.poll() is None or left:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return out, err, left
