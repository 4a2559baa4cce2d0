"""Command-line tools that live in the ``nimbus`` package (``nimbus-train``, ``nimbus-view``).

Importing this package (every Nimbus command does, first: ``nimbus-synth`` and ``nimbus-bench`` too) sets how
torch's OpenMP threads wait between parallel sections, unless the user set it (:func:`openmp_environment`):

- ``OMP_WAIT_POLICY=PASSIVE``: OpenMP's default spin-waiting (GNU libgomp: 300,000 spins, a few milliseconds) makes
  torch 10-40x slower on 2 threads when another process shares the cores (measured on the 2-core CI machine);
- ``GOMP_SPINCOUNT=1000`` (:data:`SPIN_COUNT`) beside it when the machine is idle as the command starts (other
  processes used less than :data:`IDLE_CORES` of a core over a tenth of a second): a thread then spins about ten
  microseconds before it sleeps, which covers the gap between the many small parallel sections of a training step
  (NimbusGS opens about 190 a step, 3DGS about 40), each of which otherwise pays for waking a sleeping thread.
  Idle, that made a small NimbusGS cell 5 % faster; with a busy process beside it, its steps were 5 % slower, hence
  the test.  The load average would not do: it still counts the install or the command run just before.
  docs/performance.md ("How idle threads wait") has the measurements.

It only takes effect before torch is loaded, hence here and not in ``main()``; the library itself (``import nimbus``)
leaves the environment alone.
"""

import os
import time
from collections.abc import Callable

#: libgomp's spins before a waiting thread sleeps (libgomp's estimate: about 100 spins a microsecond).
SPIN_COUNT = 1000
#: Cores' worth of CPU time other processes may use while a command starts for the machine to count as idle.
IDLE_CORES = 0.5
#: Seconds over which that is measured.
IDLE_WINDOW = 0.1


def openmp_environment(environ, busy_cores: Callable[[], float | None]) -> dict[str, str]:
    """The OpenMP variables a command adds to ``environ``: none when the user set ``OMP_WAIT_POLICY`` (it
    chooses the waiting), else ``OMP_WAIT_POLICY=PASSIVE``, and the short spin (``GOMP_SPINCOUNT``) beside
    it unless the user set a spin count or ``busy_cores()`` (called only then; None = unknown) says other
    processes keep at least :data:`IDLE_CORES` of a core busy."""
    if "OMP_WAIT_POLICY" in environ:
        return {}
    add = {"OMP_WAIT_POLICY": "PASSIVE"}
    if "GOMP_SPINCOUNT" not in environ:
        busy = busy_cores()
        if busy is not None and busy < IDLE_CORES:
            add["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    return add


def other_processes_busy_cores(window: float = IDLE_WINDOW) -> float | None:
    """Cores' worth of CPU time that processes other than this one used over the next ``window`` seconds
    (Linux ``/proc``; None where it cannot be read)."""
    def busy_ticks() -> int:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:9]]  # user nice system idle iowait irq softirq steal
        return sum(ticks) - ticks[3] - ticks[4]

    def own_ticks() -> int:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime, stime

    try:
        hz = os.sysconf("SC_CLK_TCK")
        b0, o0 = busy_ticks(), own_ticks()
        time.sleep(window)
        b1, o1 = busy_ticks(), own_ticks()
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return max(0, (b1 - b0) - (o1 - o0)) / hz / window


os.environ.update(openmp_environment(os.environ, other_processes_busy_cores))
