"""Who a driver process is, and whether it still runs: what the ledger records about each driver.

A process is named by its host (for people), its *machine* (the kernel's boot id and PID namespace on
Linux: two processes with the same machine see the same PIDs), its PID and its start time (the
kernel's clock ticks since boot, so a reused PID is not mistaken for the original process).

`process_alive` answers at once for a process on this machine (the PID exists, is not a zombie and
started when recorded) and answers ``None`` for one elsewhere: there, only the heartbeat the driver
renews in the ledger (and the expiry of its leases) can tell.
"""

from __future__ import annotations

import functools
import os
import socket
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ProcessIdentity:
    host: str
    """Host name, for people."""
    machine: str
    """Equal for two processes that share a kernel and a PID namespace (PIDs comparable)."""
    pid: int
    start: str
    """The process's start time in clock ticks since boot ('' where the platform does not say)."""


@functools.lru_cache(maxsize=1)
def this_machine() -> str:
    """The boot id and PID namespace of this process (Linux), else the host name."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        namespace = os.readlink("/proc/self/ns/pid")
    except OSError:
        return socket.gethostname()
    return f"{boot}/{namespace}"


def process_start(pid: int) -> str | None:
    """The start time of a live process ('' where /proc is missing; None if it is gone or a zombie)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return None if Path("/proc/self/stat").exists() else ""
    except OSError:
        return ""
    fields = stat[stat.rindex(")") + 2 :].split()  # from field 3 (state) on
    if fields[0] in ("Z", "X"):
        return None
    return fields[19]


def process_identity(pid: int | None = None) -> ProcessIdentity:
    """This process (or another process of this machine, by PID)."""
    pid = os.getpid() if pid is None else pid
    return ProcessIdentity(host=socket.gethostname(), machine=this_machine(), pid=pid, start=process_start(pid) or "")


def process_alive(process: ProcessIdentity) -> bool | None:
    """True or False for a process of this machine; None for one elsewhere (the caller must go by its
    heartbeat)."""
    if process.machine != this_machine():
        return None
    try:
        os.kill(process.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists, under another user
    start = process_start(process.pid)
    if start is None:
        return False
    return not (process.start and start and start != process.start)
