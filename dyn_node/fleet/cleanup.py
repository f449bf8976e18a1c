"""Leave nothing behind from the local Ray a dyn-fleet run starts: its session folder lives in a
temporary directory of its own, removed at exit, and the processes it started (raylet, GCS,
agents, workers) are ended when it shuts down, also after Ctrl-C, instead of lingering until
they notice their parent is gone (45-90 s). Linux /proc only; elsewhere nothing is tracked.
"""
from __future__ import annotations

import os
import shutil
import signal
import tempfile
import time
from pathlib import Path

TEMP_PREFIX = "dyn-fleet-ray-"  # short: Ray's Unix socket paths under it must stay < 108 bytes


def make_temp_dir() -> Path:
    """A fresh directory for Ray's session files (``ray.init(_temp_dir=...)``)."""
    return Path(tempfile.mkdtemp(prefix=TEMP_PREFIX))


def remove_temp_dir(path: Path | None) -> None:
    if path is not None:
        shutil.rmtree(path, ignore_errors=True)


def _stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, start time in clock ticks) of ``pid``, None if gone or unreadable."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = raw[raw.rfind(")") + 2:].split()  # after "pid (comm) "; comm may hold spaces
    try:
        return int(fields[1]), int(fields[19])
    except (IndexError, ValueError):
        return None


def descendants(root: int | None = None) -> list[tuple[int, int]]:
    """(pid, start time) of every live descendant of ``root`` (default: this process)."""
    root = os.getpid() if root is None else root
    children: dict[int, list[tuple[int, int]]] = {}
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return []
    for pid in pids:
        st = _stat(pid)
        if st is not None:
            children.setdefault(st[0], []).append((pid, st[1]))
    out: list[tuple[int, int]] = []
    todo = [root]
    while todo:
        for pid, start in children.get(todo.pop(), []):
            out.append((pid, start))
            todo.append(pid)
    return out


def _alive(pid: int, start: int) -> bool:
    """Still the process we recorded (a reused pid has another start time)."""
    st = _stat(pid)
    if st is None:
        return False
    try:
        with open(f"/proc/{pid}/status") as fh:
            if any(line.startswith("State:") and "Z" in line.split()[1] for line in fh):
                return False  # a zombie has ended; its parent reaps it
    except OSError:
        return False
    return st[1] == start


def end_processes(procs: list[tuple[int, int]], *, grace_s: float = 2.0) -> list[int]:
    """SIGTERM the recorded processes still alive, SIGKILL those alive after ``grace_s``;
    returns the pids that had to be signalled."""
    left = [(p, s) for p, s in procs if _alive(p, s)]
    signalled = [p for p, _s in left]
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid, _s in left:
            try:
                os.kill(pid, sig)
            except OSError:
                pass
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline and any(_alive(p, s) for p, s in left):
            time.sleep(0.05)  # polling /proc: these are not our children after the raylet died
        left = [(p, s) for p, s in left if _alive(p, s)]
    return signalled


def ray_processes(baseline: set[int]) -> list[tuple[int, int]]:
    """This process's descendants started since ``baseline`` (pids) whose command line is
    Ray's (raylet, gcs_server, agents, ``ray::`` workers): what a local Ray left running."""
    out = []
    for pid, start in descendants():
        if pid in baseline:
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b"ray" in cmd:
            out.append((pid, start))
    return out
