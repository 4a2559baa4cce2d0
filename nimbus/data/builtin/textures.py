"""World-space procedural textures for the built-in scenes.

Every texture is a pure function of a surface point's world coordinates (and an
integer seed), so a surface looks the same from every camera: the built-in
scenes are multi-view consistent by construction.  Inputs are float arrays of
shape (N, D) (D = 2 for planar coordinates, 3 for solid textures); outputs are
float32 arrays of shape (N,) in [0, 1] unless stated otherwise.

Noise values come from seeded lookup tables (numpy's PCG64 generator) and
discrete patterns from a uint32 integer hash, so results are bit-identical
across runs.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

# Per-axis odd multipliers for the lattice hash (large primes, as in spatial hashing).
_AXIS_PRIMES = (np.uint32(73856093), np.uint32(19349663), np.uint32(83492791))


def _mix32(h: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array (the murmur3 finaliser)."""
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> np.uint32(13))
    h = h * np.uint32(0xC2B2AE35)
    return h ^ (h >> np.uint32(16))


def _seed_hash(seed: int) -> np.uint32:
    """Hashed seed (computed on a 1-element array: numpy warns on uint32 scalar overflow)."""
    return _mix32(np.array([seed & 0xFFFFFFFF], np.uint32) + np.uint32(0x9E3779B9))[0]


def hash01(cells: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice cell.

    Parameters
    ----------
    cells : ndarray, shape (N, D), integer
        Lattice coordinates (D <= 3).
    seed : int
        Selects an independent random field.

    Returns
    -------
    ndarray, shape (N,), float32 in [0, 1)
    """
    cells = np.asarray(cells)
    h = np.full(cells.shape[0], _seed_hash(seed), dtype=np.uint32)
    for axis in range(cells.shape[1]):
        h = h ^ (cells[:, axis].astype(np.int64).astype(np.uint32) * _AXIS_PRIMES[axis])
        h = _mix32(h)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


# Lattice sizes (cells per period) of the value tables: a 2D texture repeats every 256 cells,
# a 3D one every 32 (tables of 256 KiB and 128 KiB, so lookups stay in cache).  With the
# octaves and materials on independent tables the repetition is not visible.
_PERIOD = {2: 256, 3: 32}


@lru_cache(maxsize=512)
def _lattice(seed: int, dim: int) -> np.ndarray:
    """The random value table of one noise field, flat, length PERIOD ** dim, as complex64 pairs.

    Entry ``i`` holds the lattice values at ``i`` (real part) and at its neighbour one step
    along the last axis (imaginary part), so one gather fetches both ends of an edge.
    """
    size = _PERIOD[dim]
    rng = np.random.default_rng([seed & 0xFFFFFFFF, dim, 7])
    values = rng.random((size,) * dim, dtype=np.float32)
    pairs = np.stack([values, np.roll(values, -1, axis=-1)], axis=-1).reshape(-1, 2)
    table = np.ascontiguousarray(pairs).view(np.complex64).reshape(-1)
    table.setflags(write=False)
    return table


def value_noise(x: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth lattice value noise in 2 or 3 dimensions (unit cell size).

    Random values at integer lattice points (from a seeded table, periodic with 256
    cells in 2D and 32 in 3D) are blended with smoothstep-weighted (C1) multilinear
    interpolation.

    Parameters
    ----------
    x : ndarray, shape (N, D), D in {2, 3}
        Coordinates in lattice units (multiply world coordinates by a frequency first).
    seed : int

    Returns
    -------
    ndarray, shape (N,), float32 in [0, 1]
    """
    x = np.asarray(x, dtype=np.float32)
    n, dim = x.shape
    if dim not in _PERIOD:
        raise ValueError(f"value_noise supports 2 or 3 dimensions, got {dim}")
    if n == 0:
        return np.zeros(0, np.float32)
    table = _lattice(seed, dim)
    size = _PERIOD[dim]
    mask = size - 1
    # Per axis: the lattice index of the cell's low corner and the smoothstep weight.
    idx, wts = [], []
    for a in range(dim):
        xa = x[:, a]
        cell = np.floor(xa)
        f = xa - cell
        wts.append(f * f * (3.0 - 2.0 * f))
        idx.append(cell.astype(np.int32) & mask)

    def edge(*lead: np.ndarray) -> np.ndarray:
        """Values along the last axis between the corners at ``lead`` indices, blended by its weight."""
        flat = idx[-1]
        for k, i in enumerate(lead):
            flat = flat + i * np.int32(size ** (dim - 1 - k))
        pair = np.take(table, flat)
        lo = pair.real
        return lo + wts[-1] * (pair.imag - lo)

    if dim == 2:
        x0 = idx[0]
        x1 = (x0 + 1) & mask
        a, b = edge(x0), edge(x1)
        return (a + wts[0] * (b - a)).astype(np.float32)
    x0, y0 = idx[0], idx[1]
    x1, y1 = (x0 + 1) & mask, (y0 + 1) & mask
    a = edge(x0, y0)
    a = a + wts[1] * (edge(x0, y1) - a)
    b = edge(x1, y0)
    b = b + wts[1] * (edge(x1, y1) - b)
    return (a + wts[0] * (b - a)).astype(np.float32)


def fbm(x: np.ndarray, octaves: int = 4, seed: int = 0, lacunarity: float = 2.0, gain: float = 0.5) -> np.ndarray:
    """Fractal (fBm) sum of value-noise octaves, normalised to [0, 1].

    Parameters
    ----------
    x : ndarray, shape (N, D)
        Coordinates in units of the coarsest octave's cells.
    octaves : int
        Number of octaves; each is ``lacunarity`` times finer and ``gain`` times weaker.
    seed : int
        Each octave uses ``seed + octave`` so octaves are uncorrelated.

    Returns
    -------
    ndarray, shape (N,), float32 in [0, 1]
    """
    x = np.asarray(x, dtype=np.float32)
    total = np.zeros(x.shape[0], np.float32)
    amp, norm, freq = 1.0, 0.0, 1.0
    for o in range(octaves):
        # Offsetting each octave hides the lattice alignment at the origin.
        total += np.float32(amp) * value_noise(x * np.float32(freq) + np.float32(17.31 * o), seed + 1013 * o)
        norm += amp
        amp *= gain
        freq *= lacunarity
    return total / np.float32(norm)


def checker(x: np.ndarray) -> np.ndarray:
    """Checkerboard parity (0 or 1, float32) of unit cells; x has shape (N, D)."""
    cells = np.floor(np.asarray(x, dtype=np.float32)).astype(np.int64)
    return (cells.sum(axis=1) & 1).astype(np.float32)


def bricks(u: np.ndarray, v: np.ndarray, brick_w: float, brick_h: float, mortar: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Running-bond brick pattern on a 2D surface parameterisation.

    Parameters
    ----------
    u, v : ndarray, shape (N,)
        Surface coordinates in metres (u along the rows, v across them).
    brick_w, brick_h : float
        Brick size in metres (including the mortar joint).
    mortar : float
        Joint width in metres.

    Returns
    -------
    is_brick : ndarray, shape (N,), float32
        1 on a brick face, 0 on mortar.
    brick_id : ndarray, shape (N, 2), int64
        Integer id of the brick (column, row), for per-brick colour variation.
    """
    row = np.floor(v / brick_h)
    uu = u / brick_w + 0.5 * (row.astype(np.int64) & 1)  # every other row shifted by half a brick
    col = np.floor(uu)
    fu = (uu - col) * brick_w
    fv = (v / brick_h - row) * brick_h
    half = 0.5 * mortar
    is_brick = ((fu > half) & (fu < brick_w - half) & (fv > half) & (fv < brick_h - half)).astype(np.float32)
    return is_brick, np.stack([col, row], axis=1).astype(np.int64)


def spots(x: np.ndarray, seed: int, density: float = 0.6, radius: tuple[float, float] = (0.12, 0.28),
          softness: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Scattered round spots (flowers, pebbles, stains): at most one per unit cell of a 2D lattice.

    Blob-like, high-contrast features of a known size are what SIFT detects best, so the
    built-in scenes sprinkle them on otherwise smooth surfaces.

    Parameters
    ----------
    x : ndarray, shape (N, 2)
        Coordinates in cell units.
    seed : int
    density : float
        Probability that a cell holds a spot, in [0, 1].
    radius : (float, float)
        Range of spot radii in cell units (at most 0.3, so a spot stays inside its cell).
    softness : float
        Width of the spot's soft edge as a fraction of its radius (anti-aliasing).

    Returns
    -------
    coverage : ndarray, shape (N,), float32 in [0, 1]
        1 inside a spot, 0 outside, smooth across the edge.
    cell : ndarray, shape (N, 2), int64
        The cell id, for per-spot colour (``hash01(cell, ...)``).
    """
    x = np.asarray(x, dtype=np.float32)
    cell = np.floor(x).astype(np.int64)
    f = x - cell
    r = np.float32(radius[0]) + np.float32(radius[1] - radius[0]) * hash01(cell, seed + 2)
    cx = 0.3 + 0.4 * hash01(cell, seed)
    cy = 0.3 + 0.4 * hash01(cell, seed + 1)
    dist = np.sqrt((f[:, 0] - cx) ** 2 + (f[:, 1] - cy) ** 2)
    edge = np.clip((r - dist) / (softness * r), 0.0, 1.0)
    present = (hash01(cell, seed + 3) < density).astype(np.float32)
    return (edge * present).astype(np.float32), cell


def mix(a, b, t: np.ndarray) -> np.ndarray:
    """Per-point linear blend of two colours: ``a`` and ``b`` are (3,) or (N, 3), ``t`` is (N,) or a scalar."""
    t = np.asarray(t, dtype=np.float32)
    t = t[:, None] if t.ndim == 1 else t
    return (np.asarray(a, np.float32) * (1.0 - t) + np.asarray(b, np.float32) * t).astype(np.float32)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 (x <= edge0) to 1 (x >= edge1), float32."""
    t = np.clip((np.asarray(x, np.float32) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return (t * t * (3.0 - 2.0 * t)).astype(np.float32)
