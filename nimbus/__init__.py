"""Nimbus: 3D scene reconstruction under bad weather (NimbusGS), with weather synthesis and benchmarks."""

import os

# OpenMP's default spin-waiting makes torch 10-40x slower on 2 threads when another
# process shares the cores (measured on the 2-core CI machine); passive waiting costs
# little when the machine is idle. Only effective if set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
