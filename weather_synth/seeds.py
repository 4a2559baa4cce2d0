"""Reproducible random streams, derived from the scene seed with a stable hash.

Every random quantity of a synthesis run is drawn from a stream named by *what*
it is for, e.g. ``("rain", "000.png")``: the stream's seed is the SHA-256 of the
scene seed and those names.  So

* the same seed gives the same bytes on any machine and any Python (Python's
  ``hash()`` is salted per process and never used);
* a view's rain does not depend on which other views or settings are written, or
  in which order (``H+R`` and ``R`` of one view share one rain layer);
* streams are independent of one another (SHA-256 outputs are uncorrelated).
"""

from __future__ import annotations

import hashlib

import numpy as np


def derive_seed(seed: int, *names: str) -> int:
    """A 64-bit seed for the stream ``names`` of the run seeded with ``seed``.

    Parameters
    ----------
    seed : int
        The run's (scene's) seed, any non-negative integer.
    *names : str
        What the stream is for, most general first (``"rain"``, view name, ...).
    """
    text = "\x1f".join([str(int(seed)), *map(str, names)])
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")


def rng_for(seed: int, *names: str) -> np.random.Generator:
    """A numpy Generator (PCG64) for the stream ``names`` (see :func:`derive_seed`)."""
    return np.random.Generator(np.random.PCG64(derive_seed(seed, *names)))
