"""The benchmark (``nimbus-bench``): cells, grid and store, scoring of any method's renders, tables and reports.

Research and developer scripts (threshold derivation, speed measurements, the GPU check) are not part of it: they
live in the checkout's top-level ``tools/`` (``python -m tools.NAME``), which is not installed."""
