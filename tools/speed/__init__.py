"""Speed and measurement scripts, one per thing measured; each runs as ``python -m tools.speed.<name>`` from a checkout."""

import os


def openmp_wait() -> str:
    """How torch's OpenMP threads wait in this process, for a measurement's header: the two variables the
    commands set (``nimbus.cli``), or ``unset``."""
    return ", ".join(f"{k}={os.environ.get(k, 'unset')}" for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"))
