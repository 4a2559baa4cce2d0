"""This process's resident-memory peak: read it, and reset it where the kernel allows.

On Linux the peak is ``VmHWM`` of ``/proc/self/status``, the resident-set high-water mark of
this process's own address space.  ``ru_maxrss`` (``getrusage``) is used only where there is
no ``/proc``: it also keeps the peak of the address space the process replaced when it
started, which for a process spawned from a big parent (``fork`` + ``exec``) is the parent's
resident size, and no call resets it.  Writing ``5`` to ``/proc/self/clear_refs`` resets
``VmHWM`` to the current resident size (Linux >= 4.0, proc(5)); a process that runs several
jobs in turn (the benchmark's workers) does that before each one.
"""

from __future__ import annotations

import resource
from pathlib import Path

STATUS = Path("/proc/self/status")
CLEAR_REFS = Path("/proc/self/clear_refs")
#: Written to ``clear_refs``, resets the resident-set high-water mark (proc(5)).
RESET_HIGH_WATER_MARK = "5"


def status_kb(field: str) -> int | None:
    """A ``kB`` field of ``/proc/self/status`` (``VmHWM``, ``VmRSS``), None where there is none."""
    try:
        with open(STATUS) as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB: ``VmHWM`` where there is one, else ``ru_maxrss``."""
    kb = status_kb("VmHWM")
    if kb is None:
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0


def reset_peak_rss() -> bool:
    """Reset :func:`peak_rss_mb` to the current resident size; whether it was (checked, not assumed)."""
    try:
        CLEAR_REFS.write_text(RESET_HIGH_WATER_MARK)
    except OSError:
        return False
    peak, now = status_kb("VmHWM"), status_kb("VmRSS")
    # Pages touched between the two reads may raise the mark a little above the first reading.
    return peak is not None and now is not None and peak <= now + 1024
