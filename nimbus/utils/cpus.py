"""The CPU cores this process may run on.

``os.cpu_count()`` counts the machine's cores, not the ones a process is allowed: under ``taskset``,
a batch scheduler's CPU set or a container pinned to some cores, threads sized from it oversubscribe
the cores really available (several workers each believing they own the machine).
"""

from __future__ import annotations

import os


def usable_cpus() -> int:
    """Cores in this process's CPU affinity set where the OS reports one (Linux), else ``os.cpu_count()``.

    At least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS / Windows: no affinity query
        return max(1, os.cpu_count() or 1)
