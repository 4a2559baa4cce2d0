"""Structure from motion: a folder of photos -> a COLMAP scene, with pycolmap on the CPU.

Pipeline: SIFT feature extraction, exhaustive or sequential matching with
geometric verification, incremental mapping; the largest reconstruction is
kept.  With a distorted camera model (the default ``SIMPLE_RADIAL``, right for
real photos) the registered photos are then undistorted to ``PINHOLE`` cameras
(``pycolmap.undistort_images``: images are resampled and slightly cropped);
with ``SIMPLE_PINHOLE`` / ``PINHOLE`` (synthetic or already undistorted photos)
they are copied unchanged.  The output is a scene folder ``images/`` +
``sparse/0`` that :func:`nimbus.data.io.load_scene` reads; only registered photos
are kept in it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, NamedTuple

import pycolmap

from nimbus.data.colmap import PINHOLE_MODELS, read_colmap
from nimbus.data.io import list_images
from nimbus.data.scene import Scene
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir, check_output_dir

MATCHERS = ("exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True)
class SfmConfig:
    """Settings of :func:`run_sfm`.

    Attributes
    ----------
    matcher : str
        ``"exhaustive"`` (every pair; best up to a few hundred photos) or
        ``"sequential"`` (neighbours in file-name order; for video frames).
    seed : int
        Seed of COLMAP's random number generator (RANSAC, mapping); the same
        seed and photos give the same reconstruction.
    max_image_size : int
        Photos are downscaled to this longest side, in pixels, for feature
        extraction only (COLMAP's default 3200; 1600 is ample for SfM and faster).
    max_num_features : int
        SIFT features kept per photo (COLMAP's default).
    camera_model : str
        COLMAP camera model to estimate; distorted models are undistorted afterwards.
    single_camera : bool
        All photos share one camera (same device and zoom): fewer unknowns, more robust.
    min_model_size : int
        Smallest reconstruction (registered photos) COLMAP keeps; small on purpose so
        that a dozen photos can make a scene (COLMAP's default is 10).
    sequential_overlap : int
        With the sequential matcher, each photo is matched with this many following ones.
    num_threads : int
        Threads for extraction, matching and mapping.  1 makes runs reproducible bit for bit
        (COLMAP's multi-threaded extraction and bundle adjustment vary run to run, enough to
        change the result); -1 uses every core.
    """

    matcher: str = "exhaustive"
    seed: int = 0
    max_image_size: int = 1600
    max_num_features: int = 8192
    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = False
    min_model_size: int = 3
    sequential_overlap: int = 10
    num_threads: int = 1

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise NimbusError(f"unknown matcher {self.matcher!r}; use one of {MATCHERS}")
        if self.camera_model not in CAMERA_MODELS:
            raise NimbusError(f"unsupported camera model {self.camera_model!r}; use one of {CAMERA_MODELS}")
        if self.num_threads == 0 or self.num_threads < -1:
            raise NimbusError(f"num_threads must be -1 (all cores) or positive, got {self.num_threads}")
        if self.max_image_size < 64 or self.max_num_features < 64 or self.min_model_size < 2:
            raise NimbusError("max_image_size and max_num_features must be >= 64 and min_model_size >= 2")


class SfmResult(NamedTuple):
    """What :func:`run_sfm` returns: the written scene, registered and total photo counts."""

    scene: Scene
    registered: int
    total: int


def list_photos(photos_dir: str | os.PathLike) -> list[str]:
    """Photo names (relative posix paths, sorted) under ``photos_dir``; NimbusError if there are none."""
    photos_dir = Path(photos_dir)
    if not photos_dir.is_dir():
        raise NimbusError(f"photo folder {photos_dir} does not exist; check the path")
    photos = list_images(photos_dir)
    if not photos:
        raise NimbusError(f"{photos_dir} has no photos (.png, .jpg, .tif, .bmp); point to the folder of images")
    return photos


def run_sfm(photos_dir: str | os.PathLike, out_dir: str | os.PathLike, overwrite: bool = False,
            config: SfmConfig = SfmConfig(), log: Callable[[str], None] | None = None, **changes) -> SfmResult:
    """Recover cameras and sparse points from photos and write a COLMAP scene to ``out_dir``.

    Parameters
    ----------
    photos_dir : path
        Folder of photos (searched recursively); it is only read.
    out_dir : path
        The scene folder to create (atomically: nothing is left on failure).
    overwrite : bool
        Replace a non-empty ``out_dir``.
    config : SfmConfig
        Settings; keyword ``changes`` override its fields (``seed=1, matcher="sequential"``).
    log : callable, optional
        Receives one line per pipeline step (progress for the CLI).

    Returns
    -------
    SfmResult
        ``(scene, registered, total)``: the scene as read back from ``out_dir``,
        the number of registered photos and of photos found.

    Raises
    ------
    NimbusError
        No photos, output folder not empty (without ``overwrite``) or inside the
        photos, or no reconstruction (too little overlap or texture).
    """
    config = replace(config, **changes)
    say = log or (lambda _msg: None)
    photos_dir, out_dir = Path(photos_dir), Path(out_dir)
    photos = list_photos(photos_dir)
    src, dst = photos_dir.resolve(), out_dir.resolve()
    if dst == src or dst in src.parents or src in dst.parents:
        raise NimbusError(f"--out {out_dir} must be outside the photo folder {photos_dir} (and not contain it)")
    check_output_dir(out_dir, overwrite)

    pycolmap.logging.minloglevel = 2  # warnings and errors only: COLMAP's info log floods the terminal
    pycolmap.set_random_seed(config.seed)
    with tempfile.TemporaryDirectory(prefix="nimbus-sfm-") as work, atomic_dir(out_dir, overwrite) as tmp:
        work = Path(work)
        rec = _reconstruct(photos_dir, photos, work, config, say)
        say(f"writing the scene ({rec.num_reg_images()} registered photos)")
        _write_scene(rec, photos_dir, work, Path(tmp), config)
    scene = read_colmap(out_dir)
    return SfmResult(scene, len(scene), len(photos))


def _reconstruct(photos_dir: Path, photos: list[str], work: Path, config: SfmConfig,
                 say: Callable[[str], None]) -> pycolmap.Reconstruction:
    """Features, matches and incremental mapping; the largest reconstruction."""
    database = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_num_features
    extraction.num_threads = config.num_threads
    mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.AUTO
    say(f"extracting SIFT features from {len(photos)} photos")
    pycolmap.extract_features(database, photos_dir, image_names=photos, camera_mode=mode,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    say(f"matching features ({config.matcher})")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.num_threads
    if config.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.sequential_overlap
        pairing.num_threads = config.num_threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    say("incremental mapping")
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = config.min_model_size
    options.random_seed = config.seed
    options.num_threads = config.num_threads
    options.mapper.num_threads = config.num_threads
    models = pycolmap.incremental_mapping(database, photos_dir, work / "sparse", options)
    models = [m for m in models.values() if m.num_reg_images() > 0]
    if not models:
        raise NimbusError(
            f"structure from motion found no reconstruction in {photos_dir} ({len(photos)} photos): the photos "
            "need more overlap (each part of the scene seen from several nearby viewpoints) and texture; "
            "try --matcher exhaustive, more photos, or --single-camera if one camera took them all")
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()))


def _write_scene(rec: pycolmap.Reconstruction, photos_dir: Path, work: Path, out: Path, config: SfmConfig) -> None:
    """``out/images`` (registered photos) + ``out/sparse/0``, undistorting a distorted camera model."""
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True)
    names = sorted(rec.images[i].name for i in rec.reg_image_ids())
    if config.camera_model in PINHOLE_MODELS:
        for name in names:
            (out / "images" / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(photos_dir / name, out / "images" / name)
        rec.write(sparse)
        return
    model_dir = work / "largest"
    model_dir.mkdir()
    rec.write(model_dir)
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, model_dir, photos_dir, image_names=names)
    shutil.move(undistorted / "images", out / "images")
    for f in (undistorted / "sparse").iterdir():
        shutil.move(f, sparse / f.name)
