"""What a figure depends on besides the code: library versions and the CPU's vector ISA.

Every results record (``nimbus-train``'s ``results.json``, the benchmark's store) carries
:func:`software_versions`, so a figure can be traced to the versions that made it and
compared with ``constraints.txt``, the tested versions the README installs.
"""

from __future__ import annotations

import functools
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

#: Distributions whose version can change a synthesised pixel or a trained figure.
_DISTRIBUTIONS = ("torch", "numpy", "opencv-contrib-python-headless", "pycolmap", "scikit-image", "onnxruntime",
                  "colour-science", "scipy", "gsplat")


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


#: The folders whose code makes the figures; a change there marks the commit ``+modified``.
_CODE_FOLDERS = ("nimbus", "weather_synth", "benchmark")


@functools.lru_cache(maxsize=1)
def source_commit() -> str | None:
    """The git commit of the source tree Nimbus runs from, as 12 hex digits; ``+modified`` appended when a
    tracked file of the code (:data:`_CODE_FOLDERS`) differs from it.  None where Nimbus is not run from a
    git checkout (an installed wheel), or git is missing or refuses the folder.

    ``nimbus.__version__`` names a release, not the code between releases; a table assembled from
    cells run at several commits (several sessions, several machines) needs the commit of each.
    """
    return commit_of(Path(__file__).resolve().parent.parent)


def commit_of(root: Path) -> str | None:
    """:func:`source_commit` of the checkout at ``root`` (None when it is not one)."""
    if not (root / ".git").exists():
        return None
    # No optional locks: concurrent benchmark workers must not fight over (or leave) .git/index.lock.
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=20,
                                  env=env, stdin=subprocess.DEVNULL)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    head = git("rev-parse", "--short=12", "HEAD")
    if not head:
        return None
    changed = git("status", "--porcelain", "--untracked-files=no", "--", *_CODE_FOLDERS)
    return head + ("+modified" if changed else "" if changed is not None else "+unknown")


def software_versions() -> dict[str, str]:
    """Python, Nimbus (and its source commit, in a git checkout), the figure-relevant libraries that are
    installed, the machine and its ISA."""
    import nimbus

    found = {"nimbus": nimbus.__version__, "python": platform.python_version(), **_installed(),
             "machine": platform.machine(), "cpu_isa": cpu_isa()}
    commit = source_commit()
    if commit:
        found["nimbus_commit"] = commit
    return found
