"""Weather synthesis: turn clean multi-view scenes into haze / rain / snow benchmarks.

Imports only :mod:`nimbus.data` (the shared scene model) from the rest of Nimbus.
"""
