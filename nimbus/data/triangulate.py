"""Sparse points for a posed capture that has none: COLMAP triangulation with the poses held fixed, cached by content.

A transforms.json export (instant-ngp, nerfstudio, Blender) or a COLMAP model with an empty
``points3D`` knows every camera but no point.  3DGS needs starting points, and the poses are all a
triangulation needs, so :func:`triangulate_posed` runs the last half of COLMAP (pycolmap, on the CPU):

1. The views' images are copied (PNG / JPEG as they are, other formats re-encoded as PNG) into a
   private temporary folder; the scene folder is never written to.
2. A COLMAP database gets one ``PINHOLE`` camera per distinct intrinsics and every image with its
   known camera, so feature extraction keeps the known intrinsics instead of guessing them.
3. SIFT features (at most ``max_image_size`` px, ``max_num_features`` per image); matching with
   geometric verification: every pair up to :attr:`TriangulationConfig.exhaustive_max_views` views,
   beyond that each view with its :attr:`TriangulationConfig.neighbours` nearest views by pose
   (:func:`pose_neighbour_pairs`), since a few hundred views make tens of thousands of pairs.
4. ``pycolmap.triangulate_points`` (COLMAP's ``point_triangulator``): tracks are triangulated and
   refined by bundle adjustment with every pose and intrinsic held constant.  COLMAP's own filters
   apply (reprojection error below 4 px, triangulation angle above 1.5 degrees); points seen by two
   views only are kept (``ignore_two_view_tracks`` off), as with known poses their position is as
   well determined as their angle allows.

Cache
    ``<cache>/<key>.npz`` with ``<cache>`` = ``$NIMBUS_CACHE/triangulated`` (default
    ``~/.cache/nimbus/triangulated``, :func:`nimbus.utils.fs.cache_root`) and ``<key>`` the SHA-256
    of :data:`TRIANGULATION_VERSION`, the pycolmap version, the settings, and per view its
    intrinsics, its world-to-camera pose and the bytes of its image (the file's, or the in-memory
    array's).  Changed photos, poses or settings make a new entry; a second call reads the entry.
    The file is written atomically, so concurrent runs are safe; it is a few bytes per point.

On the built-in garden scene at the ``small`` size (35 training views, 240 x 180 px) this gives
about 2,500 points in 10 to 20 s on one thread, at a median 0.5 % of the true depth (where the views
see them); at the ``tiny`` size (64 x 48 px) SIFT finds about 40 features per view and no pair has
enough matches, so nothing is triangulated.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from nimbus.data.images import encode_png
from nimbus.data.scene import View
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes, cache_root

#: Bump when the same views would give different points (invalidates every cache entry).
TRIANGULATION_VERSION = 1
#: Sub-folder of the Nimbus cache folder that holds triangulated points.
CACHE_SUBDIR = "triangulated"
MIN_TRIANGULATED_POINTS = 500
"""Fewer triangulated points than this are not enough to start 3DGS from (the trainer then starts from
random points, :mod:`nimbus.train.init_points`).  A few hundred points sit on the few most textured
surfaces and leave most of the scene without a Gaussian for densification to grow from, while random
points fill the volume the cameras look at.  The threshold itself is a judgement; what was measured
(docs/data.md, "Posed scenes without points"): on the built-in ``small`` scenes, 2,456 triangulated points
(garden) and 1,436 (street) trained 3.6 and 4.8 dB better than 10,000 random points (``tiny`` preset)."""

MIN_TRIANGULATION_SIDE_PX = 96
"""Views whose images have a shorter side below this are not triangulated (:func:`triangulation_skip_reason`):
SIFT finds about 40 features in a 64 x 48 image (the built-in ``tiny`` size), no pair of views reaches
COLMAP's 15 inlier matches, and nothing is triangulated.  The ``small`` size (240 x 180) triangulates well."""

#: Image files handed to COLMAP as they are; anything else is re-encoded as PNG.
_COPIED_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class TriangulationConfig:
    """Settings of :func:`triangulate_posed` (all but ``num_threads`` are part of the cache key).

    Attributes
    ----------
    max_image_size : int
        Longest side, in pixels, images are reduced to for feature extraction (as in
        :class:`nimbus.data.sfm.SfmConfig`; the points are in the scene's units whatever it is).
    max_num_features : int
        SIFT features kept per image (COLMAP's default).
    exhaustive_max_views : int
        Up to this many views every pair is matched (default 60: 1,770 pairs); beyond it each view
        is matched with its ``neighbours`` nearest views by pose.
    neighbours : int
        Views each view is matched with beyond ``exhaustive_max_views`` (default 20).
    num_threads : int
        Threads for extraction, matching and triangulation; 1 (default) makes the result the same on
        every run, -1 uses every core.
    seed : int
        Seed of COLMAP's random number generator (RANSAC in the verification).
    """

    max_image_size: int = 1600
    max_num_features: int = 8192
    exhaustive_max_views: int = 60
    neighbours: int = 20
    num_threads: int = 1
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_image_size < 64 or self.max_num_features < 64:
            raise NimbusError("max_image_size and max_num_features must be >= 64")
        if self.exhaustive_max_views < 2 or self.neighbours < 1:
            raise NimbusError("exhaustive_max_views must be >= 2 and neighbours >= 1")
        if self.num_threads == 0 or self.num_threads < -1:
            raise NimbusError(f"num_threads must be -1 (all cores) or positive, got {self.num_threads}")


class Triangulation(NamedTuple):
    """What :func:`triangulate_posed` returns.

    Attributes
    ----------
    points : ndarray, shape (N, 3), float64
        World coordinates, the scene's units.
    colors : ndarray, shape (N, 3), uint8
    errors : ndarray, shape (N,), float64
        Mean reprojection error of each point, pixels.
    track_lengths : ndarray, shape (N,), int64
        Views observing each point.
    info : dict
        ``views``, ``pairs`` (matched), ``verified_pairs`` (with at least COLMAP's ``min_num_matches``
        inlier matches), ``points``, ``mean_reprojection_error_px``,
        ``mean_track_length``, ``seconds`` (of the run that made the entry), ``key``, ``cache``
        (the entry's path, or None), ``reused`` (read from the cache).
    """

    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    track_lengths: np.ndarray
    info: dict


def default_cache_dir() -> Path:
    """``$NIMBUS_CACHE/triangulated`` (default ``~/.cache/nimbus/triangulated``)."""
    return cache_root() / CACHE_SUBDIR


def _image_bytes(view: View) -> tuple[bytes, str]:
    """The bytes handed to COLMAP for ``view`` and their file suffix."""
    if view.image is None and view.image_path is not None and view.image_path.suffix.lower() in _COPIED_SUFFIXES:
        try:
            return Path(view.image_path).read_bytes(), view.image_path.suffix.lower()
        except OSError as e:
            raise NimbusError(f"image {view.image_path} cannot be read ({e.strerror}); check the scene's "
                              "files") from None
    return encode_png(view.load_image()), ".png"


def triangulation_skip_reason(views: Sequence[View]) -> str | None:
    """Why ``views`` cannot be triangulated usefully (fewer than two, or images too small), or None."""
    if len(views) < 2:
        return f"{len(views)} posed view(s) cannot be triangulated (at least two are needed)"
    side = min(min(v.camera.width, v.camera.height) for v in views)
    if side < MIN_TRIANGULATION_SIDE_PX:
        return f"images with a shorter side of {side} px (< {MIN_TRIANGULATION_SIDE_PX}) are too small to triangulate"
    return None


def triangulation_key(views: Sequence[View], config: TriangulationConfig) -> str:
    """SHA-256 over the version, pycolmap's version, ``config`` and each view's camera, pose and image bytes.

    ``num_threads`` is left out: it changes run-to-run noise, not what the points are, so an entry made
    with every core (``nimbus-synth sfm --known-poses --threads -1``) serves the trainer too.
    """
    import pycolmap

    settings = {k: v for k, v in asdict(config).items() if k != "num_threads"}
    h = hashlib.sha256(json.dumps({"version": TRIANGULATION_VERSION, "pycolmap": pycolmap.__version__,
                                   "config": settings}, sort_keys=True).encode())
    for v in views:
        c = v.camera
        h.update(np.asarray([c.width, c.height, c.fx, c.fy, c.cx, c.cy], np.float64).tobytes())
        h.update(np.asarray(c.world_to_camera, np.float64).tobytes())
        if v.image is not None:
            h.update(np.ascontiguousarray(v.image, np.float32).tobytes())
        else:
            data, _ = _image_bytes(v)
            h.update(hashlib.sha256(data).digest())
    return h.hexdigest()


def pose_neighbour_pairs(views: Sequence[View], neighbours: int) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``: each view with its ``neighbours`` nearest views by pose.

    Nearness is ``|c_i - c_j| / s + (1 - cos a_ij)``: the centre distance over the cameras' spread
    ``s`` (largest distance of a centre from their mean) plus the angle between the optical axes, so
    two photos from one spot that look opposite ways are far apart, and both terms run from 0 to about 2.
    """
    centers = np.stack([v.camera.center for v in views])
    axes = np.stack([np.asarray(v.camera.R, np.float64)[2] for v in views])
    spread = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1))) or 1.0
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1) / spread + (1.0 - axes @ axes.T)
    np.fill_diagonal(dist, np.inf)
    k = min(neighbours, len(views) - 1)
    nearest = np.argsort(dist, axis=1, kind="stable")[:, :k]
    return sorted({(min(i, int(j)), max(i, int(j))) for i in range(len(views)) for j in nearest[i]})


def triangulate_posed(views: Sequence[View], config: TriangulationConfig = TriangulationConfig(),
                      cache_dir: str | Path | None = None,
                      log: Callable[[str], None] | None = None) -> Triangulation:
    """Triangulate points from ``views`` with their poses and intrinsics held fixed (see the module docstring).

    Parameters
    ----------
    views : sequence of View
        Posed views with images (files or in memory), e.g. a scene's training views.
    config : TriangulationConfig
    cache_dir : path, optional
        Folder of the cache (default :func:`default_cache_dir`).  Never inside the scene.
    log : callable, optional
        Receives one line per pipeline step.

    Returns
    -------
    Triangulation
        Possibly with no points (too little texture or overlap); the caller decides what is enough.

    Raises
    ------
    NimbusError
        Fewer than two views, an unreadable image, or a cache folder that cannot be written.
    """
    say = log or (lambda _msg: None)
    views = list(views)
    if len(views) < 2:
        raise NimbusError(f"triangulation needs at least two posed views, got {len(views)}")
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    key = triangulation_key(views, config)
    path = folder / f"{key}.npz"
    cached = _read_entry(path)
    if cached is not None:
        return cached._replace(info={**cached.info, "key": key, "cache": str(path), "reused": True})
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="nimbus-triangulate-") as work:
        points, colors, errors, tracks, stats = _run_colmap(views, config, Path(work), say)
    info = {"views": len(views), **stats, "points": int(len(points)),
            "mean_reprojection_error_px": round(float(errors.mean()), 4) if len(errors) else None,
            "mean_track_length": round(float(tracks.mean()), 4) if len(tracks) else None,
            "seconds": round(time.perf_counter() - start, 3)}
    buf = io.BytesIO()
    np.savez_compressed(buf, __info__=np.frombuffer(json.dumps(info).encode(), np.uint8), points=points,
                        colors=colors, errors=errors, track_lengths=tracks)
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError as e:
        raise NimbusError(f"cannot write the triangulation cache {folder} ({e.strerror or e}); set NIMBUS_CACHE "
                          "to a writable folder") from None
    return Triangulation(points, colors, errors, tracks, {**info, "key": key, "cache": str(path), "reused": False})


def _read_entry(path: Path) -> Triangulation | None:
    """The cache entry at ``path``, or None when it is missing or not whole (then it is made again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            info = json.loads(bytes(f["__info__"]).decode())
            arrays = [np.asarray(f[k]) for k in ("points", "colors", "errors", "track_lengths")]
    except (OSError, KeyError, ValueError, EOFError):
        return None
    points, colors, errors, tracks = arrays
    n = len(points)
    if points.shape != (n, 3) or colors.shape != (n, 3) or errors.shape != (n,) or tracks.shape != (n,):
        return None
    return Triangulation(points.astype(np.float64), colors.astype(np.uint8), errors.astype(np.float64),
                         tracks.astype(np.int64), info)


def _run_colmap(views: list[View], config: TriangulationConfig, work: Path, say: Callable[[str], None]):
    """Features, matches and triangulation in ``work``; (points, colors, errors, track lengths, stats)."""
    import pycolmap

    from nimbus.data.colmap import scene_to_reconstruction
    from nimbus.data.scene import Scene

    pycolmap.logging.minloglevel = 2  # warnings and errors only
    pycolmap.set_random_seed(config.seed)
    views = sorted(views, key=lambda v: v.name)  # the order of scene_to_reconstruction's image ids (from 1)
    image_dir = work / "images"
    image_dir.mkdir()
    names = {}
    for i, v in enumerate(views):
        data, suffix = _image_bytes(v)
        names[v.name] = f"{i:06d}{suffix}"
        (image_dir / names[v.name]).write_bytes(data)
    rec = scene_to_reconstruction(Scene(tuple(views)), names)
    database = work / "database.db"
    with pycolmap.Database.open(database) as db:
        for cam in rec.cameras.values():
            db.write_camera(cam, use_camera_id=True)
        for image in rec.images.values():
            db.write_image(pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                           use_image_id=True)
    say(f"extracting SIFT features from {len(views)} posed views")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_num_features
    extraction.num_threads = config.num_threads
    # The images are in the database already, so extraction keeps their known cameras.
    pycolmap.extract_features(database, image_dir, image_names=sorted(names.values()),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.num_threads
    n = len(views)
    if n <= config.exhaustive_max_views:
        pairs = n * (n - 1) // 2
        say(f"matching features (every pair: {pairs})")
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        chosen = pose_neighbour_pairs(views, config.neighbours)
        pairs = len(chosen)
        say(f"matching features ({pairs} pairs: each view with its {config.neighbours} nearest by pose)")
        pair_file = work / "pairs.txt"
        pair_file.write_text("".join(f"{names[views[i].name]} {names[views[j].name]}\n" for i, j in chosen))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pair_file
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    with pycolmap.Database.open(database) as db:
        _, inliers = db.read_two_view_geometry_num_inliers()
    # The pairs triangulation uses: enough inlier matches (COLMAP's min_num_matches).
    verified = sum(1 for k in inliers if k >= options.min_num_matches)
    say(f"triangulating with the poses fixed ({verified} of {pairs} pairs verified)")
    options.num_threads = config.num_threads
    options.random_seed = config.seed
    options.triangulation.ignore_two_view_tracks = False
    (work / "model").mkdir()
    level = pycolmap.logging.minloglevel
    try:
        out = pycolmap.triangulate_points(rec, database, image_dir, work / "model", clear_points=True,
                                          options=options, refine_intrinsics=False)
    finally:
        pycolmap.logging.minloglevel = level
    pts = list(out.points3D.values())
    points = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    errors = np.array([p.error for p in pts], np.float64)
    tracks = np.array([p.track.length() for p in pts], np.int64)
    keep = np.isfinite(points).all(1)
    return points[keep], colors[keep], errors[keep], tracks[keep], {"pairs": int(pairs), "verified_pairs": verified}


__all__ = ["CACHE_SUBDIR", "MIN_TRIANGULATED_POINTS", "MIN_TRIANGULATION_SIDE_PX", "TRIANGULATION_VERSION",
           "Triangulation", "TriangulationConfig", "default_cache_dir",
           "pose_neighbour_pairs", "triangulate_posed", "triangulation_key", "triangulation_skip_reason"]
