"""Compiled CPU kernels: C++ sources, the one loader that builds them, and their Python bindings.

- ``csrc/``: the sources; ``common.h`` holds what they share (inline and per-ISA clone
  macros, vector types, the float32 exp polynomial and sigmoid).
- :mod:`~nimbus.kernels.extension`: builds, caches and loads a library once per process
  (build folders, ``NIMBUS_EXT_DIR``, ``NIMBUS_DISABLE_CPP``, stale build locks).
- :mod:`~nimbus.kernels.raster`: the rasterizer's library (``composite.cpp`` +
  ``project.cpp``), used by the "cpp" backend; its instruction-set clones (``NIMBUS_CPU_ISA``).
- :mod:`~nimbus.kernels.march`: NimbusGS's library: its ray march through the extinction grid
  (``march.cpp``), the network airlight's fused MLP (``airlight.cpp``, bound in
  :mod:`~nimbus.kernels.airlight`) and the particulate layer's view-consistency check
  (``consistency.cpp``, bound in :mod:`~nimbus.kernels.consistency`).
- :mod:`~nimbus.kernels.train_step`: the training step's loss (L1 + SSIM) with its gradient, and
  the gradients' finiteness check, alone or fused with GGS's per-row scaling (``train_step.cpp``).

Each library builds on first use and is independent of the others: one failing to build
leaves the others usable, and each falls back to its torch path.
"""
