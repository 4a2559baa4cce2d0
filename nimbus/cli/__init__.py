"""Command-line tools that live in the ``nimbus`` package (``nimbus-train``, ``nimbus-view``).

Importing this package (every Nimbus command does, first: ``nimbus-synth`` and ``nimbus-bench`` too) sets how
torch's OpenMP threads wait between parallel sections, unless the user set it (:func:`openmp_environment`):

- ``OMP_WAIT_POLICY=PASSIVE``: OpenMP's default spin-waiting (GNU libgomp: 300,000 spins, a few milliseconds) makes
  torch 10-40x slower on 2 threads when another process shares the cores (measured on the 2-core CI machine);
- ``GOMP_SPINCOUNT=1000`` (:data:`SPIN_COUNT`) beside it when the machine is idle as the command starts (1-minute
  load average below :data:`IDLE_LOAD`): a thread then spins about ten microseconds before it sleeps, which covers
  the gap between the many small parallel sections of a training step (NimbusGS opens about 190 a step, 3DGS about
  40), each of which otherwise pays for waking a sleeping thread.  Idle, that made a small NimbusGS cell 5 % faster;
  with a busy process beside it, its steps were 5 % slower, hence the load test.  docs/performance.md ("How idle
  threads wait") has the measurements.

It only takes effect before torch is loaded, hence here and not in ``main()``; the library itself (``import nimbus``)
leaves the environment alone.
"""

import os

#: libgomp's spins before a waiting thread sleeps (libgomp's estimate: about 100 spins a microsecond).
SPIN_COUNT = 1000
#: The 1-minute load average below which a command treats the machine as idle and lets threads spin briefly.
IDLE_LOAD = 0.5


def openmp_environment(environ, load: float | None) -> dict[str, str]:
    """The OpenMP variables a command adds to ``environ``: none the user set (``OMP_WAIT_POLICY`` or
    ``GOMP_SPINCOUNT`` chooses the waiting), ``OMP_WAIT_POLICY=PASSIVE`` otherwise, and the short spin
    (``GOMP_SPINCOUNT``) beside it when ``load`` (the 1-minute load average; None = unknown) says the
    machine is idle."""
    if "OMP_WAIT_POLICY" in environ:
        return {}
    add = {"OMP_WAIT_POLICY": "PASSIVE"}
    if "GOMP_SPINCOUNT" not in environ and load is not None and load < IDLE_LOAD:
        add["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    return add


def _load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # not every platform has one
        return None


os.environ.update(openmp_environment(os.environ, _load_average()))
