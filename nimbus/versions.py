"""What a figure depends on besides the code: library versions and the CPU's vector ISA.

Every results record (``nimbus-train``'s ``results.json``, the benchmark's store) carries
:func:`software_versions`, so a figure can be traced to the versions that made it and
compared with ``constraints.txt``, the tested versions the README installs.
"""

from __future__ import annotations

import functools
import platform
from importlib import metadata

#: Distributions whose version can change a synthesised pixel or a trained figure.
_DISTRIBUTIONS = ("torch", "numpy", "opencv-contrib-python-headless", "pycolmap", "scikit-image", "onnxruntime",
                  "colour-science", "scipy")


def cpu_isa() -> str:
    """The widest x86 vector ISA the libraries may dispatch to here: ``avx512``, ``avx2`` or ``generic``.

    Read from torch's own dispatch (``ATEN_CPU_CAPABILITY`` lowers it), which is what the
    figures depend on; ``unknown`` off x86 or if torch cannot tell.
    """
    try:
        import torch

        cap = torch.backends.cpu.get_cpu_capability().lower()
    except Exception:  # an old torch, or no torch at all
        return "unknown"
    return {"avx512": "avx512", "avx2": "avx2", "default": "generic", "no avx": "generic"}.get(cap, cap)


@functools.lru_cache(maxsize=1)
def _installed() -> dict[str, str]:
    found = {}
    for dist in _DISTRIBUTIONS:
        try:
            found[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return found


def software_versions() -> dict[str, str]:
    """Python, Nimbus, the figure-relevant libraries that are installed, the machine and its ISA."""
    import nimbus

    return {"nimbus": nimbus.__version__, "python": platform.python_version(), **_installed(),
            "machine": platform.machine(), "cpu_isa": cpu_isa()}
