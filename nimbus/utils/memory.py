"""This process's resident-memory peak, and the memory a run's sizes are checked against before allocation.

Peak
----

On Linux the peak is ``VmHWM`` of ``/proc/self/status``, the resident-set high-water mark of
this process's own address space.  ``ru_maxrss`` (``getrusage``) is used only where there is
no ``/proc``: it also keeps the peak of the address space the process replaced when it
started, which for a process spawned from a big parent (``fork`` + ``exec``) is the parent's
resident size, and no call resets it.  Writing ``5`` to ``/proc/self/clear_refs`` resets
``VmHWM`` to the current resident size (Linux >= 4.0, proc(5)); a process that runs several
jobs in turn (the benchmark's workers) does that before each one.

Sizes
-----
A size-like setting (``ray_samples``, ``grid_resolution``, a tile size, a frame height) is checked before
anything is allocated (:func:`check_sizes`): its :class:`SizeCost` says about how many bytes a value
needs, from per-unit figures measured beside the code that allocates them, and a value whose estimate
exceeds :func:`memory_limit` (the device's memory, or :data:`MEMORY_LIMIT_ENV`) is refused with the
estimate, the limit and the largest value that fits, instead of crashing in the allocator or running for
hours.  The estimates are of the order of magnitude; they refuse what cannot fit, not what is slow.
"""

from __future__ import annotations

import dataclasses
import os
import resource
from pathlib import Path
from typing import Callable, Iterable

from nimbus.errors import NimbusError

STATUS = Path("/proc/self/status")
CLEAR_REFS = Path("/proc/self/clear_refs")
#: Written to ``clear_refs``, resets the resident-set high-water mark (proc(5)).
RESET_HIGH_WATER_MARK = "5"


def status_kb(field: str, path: Path | None = None) -> int | None:
    """A ``kB`` field of ``/proc/self/status`` (``VmHWM``, ``VmRSS``), or of ``path`` in that format
    (``/proc/meminfo``), None where there is none."""
    try:
        with open(path or STATUS) as f:
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


#: Environment variable: the memory, in GiB, run sizes are checked against instead of the device's.
MEMORY_LIMIT_ENV = "NIMBUS_MEMORY_LIMIT_GIB"
GIB = 2**30
#: cgroup files holding a container's memory limit (v2, then v1); "max" or a huge value: no limit.
CGROUP_LIMITS = (Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"))


def memory_limit(device=None) -> tuple[int, str]:
    """``(bytes, where that figure comes from)``: what one run may plan to allocate on ``device``.

    :data:`MEMORY_LIMIT_ENV` when set; else a CUDA device's total memory; else this machine's physical
    memory, or its container's (cgroup) limit when that is lower.
    """
    raw = os.environ.get(MEMORY_LIMIT_ENV, "").strip()
    if raw:
        try:
            gib = float(raw)
        except ValueError:
            gib = float("nan")
        if not gib > 0 or gib == float("inf"):
            raise NimbusError(f"{MEMORY_LIMIT_ENV}={raw!r} must be a positive number of GiB; fix or unset it")
        return int(gib * GIB), MEMORY_LIMIT_ENV
    if device is not None and getattr(device, "type", str(device)) == "cuda":
        import torch

        return int(torch.cuda.get_device_properties(device).total_memory), f"the memory of {device}"
    limit, source = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "this machine's memory"
    for path in CGROUP_LIMITS:
        try:
            value = int(path.read_text().strip())
        except (OSError, ValueError):
            continue
        if value < limit:
            limit, source = value, "this container's memory limit"
    return limit, source


MEMINFO = Path("/proc/meminfo")


def available_memory() -> int:
    """Bytes that new processes may take now: :func:`memory_limit` (the machine's, its container's or
    :data:`MEMORY_LIMIT_ENV`), lowered to Linux's ``MemAvailable`` estimate where ``/proc`` has one."""
    limit, _ = memory_limit()
    kb = status_kb("MemAvailable", MEMINFO)
    return limit if kb is None else min(limit, kb * 1024)


@dataclasses.dataclass(frozen=True)
class SizeCost:
    """What one size-like setting would allocate.

    Attributes
    ----------
    setting : str
        How the user gives it (``ray_samples``, ``--render-height``).
    value : int
        The value asked for.
    need : callable
        ``need(v)``: about how many bytes value ``v`` needs (non-decreasing in ``v``).
    what : callable
        ``what(v)``: what those bytes are for, e.g. ``"one view's march at 640x480"``.
    """

    setting: str
    value: int
    need: Callable[[int], float]
    what: Callable[[int], str]


def largest_fitting(need: Callable[[int], float], limit: float, hi: int) -> int:
    """The largest ``v`` in ``0..hi`` with ``need(v) <= limit`` (``need`` non-decreasing; 0 if none)."""
    lo = 0
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if need(mid) <= limit:
            lo = mid
        else:
            hi = mid - 1
    return lo


def check_sizes(costs: Iterable[SizeCost], device=None) -> None:
    """Refuse the first setting whose estimate exceeds :func:`memory_limit`, with one :class:`NimbusError` line:
    ``ray_samples=N needs about X GiB for one view's march at WxH; the limit is Y GiB (...); use at most K``."""
    limit, source = memory_limit(device)
    for c in costs:
        need = c.need(c.value)
        if need <= limit:
            continue
        fits = largest_fitting(c.need, limit, c.value)
        advice = f"use at most {fits}" if fits >= 1 else "no value fits: lower the other sizes"
        raise NimbusError(f"{c.setting}={c.value} needs about {_gib(need)} for {c.what(c.value)}; the limit is "
                          f"{_gib(limit)} ({source}); {advice}")


def _gib(n: float) -> str:
    g = n / GIB
    return f"{g:,.0f} GiB" if g >= 100 else f"{g:.3g} GiB"
