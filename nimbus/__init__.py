"""Nimbus: 3D scene reconstruction under bad weather (NimbusGS), with weather synthesis and benchmarks."""

__version__ = "0.1.0"
