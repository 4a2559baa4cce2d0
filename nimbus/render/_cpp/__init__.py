"""C++ sources of the compiled render kernels (built on first use by :mod:`nimbus.render.composite_cpp`).

A package only so that the sources ship with the wheel as package data.
"""
