"""Speed and measurement scripts, one per thing measured; each runs as ``python -m tools.speed.<name>`` from a checkout."""

import os


def openmp_wait() -> str:
    """How torch's OpenMP threads wait in this process, for a measurement's header: the two variables the
    commands set (``nimbus.cli``), or ``unset``."""
    return ", ".join(f"{k}={os.environ.get(k, 'unset')}" for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"))


def load_average() -> str:
    """The 1, 5 and 15 minute load averages for a measurement's header (``n/a`` where the OS has none)."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"
