"""Nimbus: 3D scene reconstruction under bad weather (NimbusGS), with weather synthesis and benchmarks.

Importing the library changes nothing in the process's environment; the command-line tools set the
OpenMP wait policy they want (:mod:`nimbus.cli`).
"""

__version__ = "0.1.0"
