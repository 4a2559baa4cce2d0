"""Structure from motion: a folder of photos -> a COLMAP scene, with pycolmap on the CPU.

Pipeline: SIFT feature extraction, exhaustive or sequential matching with
geometric verification, incremental mapping; the largest reconstruction is
kept.  With a distorted camera model (``SIMPLE_RADIAL``, right for real photos)
the registered photos are then undistorted to ``PINHOLE`` cameras
(``pycolmap.undistort_images``: images are resampled and slightly cropped);
with ``SIMPLE_PINHOLE`` / ``PINHOLE`` (synthetic or already undistorted photos)
they are copied unchanged.  The output is a scene folder ``images/`` +
``sparse/0`` + ``manifest.json`` that :func:`nimbus.data.io.load_scene` reads;
only registered photos are kept in it.

Calibration
    A reprojection error below a pixel does not mean the intrinsics are right: from
    few views on a smooth orbit, a wrong focal length with matching poses explains the
    matches as well as the right one (a 36-view capture self-calibrated 538 px for a
    camera that 252 views put at 829 px, at 0.82 px).  So the pipeline takes what is
    known about the camera as a prior (the photos' EXIF focal length, ``focal_px``,
    ``fov_deg`` or full ``camera_params``; ``fix_intrinsics`` keeps it fixed in bundle
    adjustment), and measures what the photos pinned down: :class:`CalibrationReport`
    (printed by ``nimbus-synth sfm``, stored under ``"calibration"`` in the scene's
    ``manifest.json``) compares the focal length with the prior and with COLMAP's
    default guess, probes whether the photos constrain the focal length at all, and
    warns on strong distortion, short tracks, low overlap and unregistered photos.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections import Counter
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import pycolmap

from nimbus.data.colmap import PINHOLE_MODELS, read_colmap
from nimbus.data.images import image_size
from nimbus.data.scene_files import list_images
from nimbus.data.scene import Scene
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir, atomic_write_json, check_output_dir
from nimbus.utils.jsonable import jsonable

GENERATOR = "nimbus.data.sfm"
MATCHERS = ("exhaustive", "sequential")
#: ``auto`` picks one of the others from the number of photos (:func:`choose_camera_model`).
CAMERA_MODELS = ("auto", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")

FOCAL_DEFAULT_FACTOR = 1.2
"""COLMAP's starting focal length without a prior, in units of the longest image side (its
``default_focal_length_factor``): a 43 mm lens on a 35 mm camera.  The report compares the recovered
focal length with it because most cameras lie within a factor two of it."""

FOCAL_PLAUSIBLE_RANGE = (0.5, 2.0)
"""Recovered focal / (:data:`FOCAL_DEFAULT_FACTOR` x longest side) outside this range is flagged:
0.6 to 2.4 x the longest side, 35 mm-equivalent 22 to 86 mm.  Phone main cameras (24 to 28 mm) and
standard zooms fall inside; a wider or longer lens is possible but rare enough to be worth a look."""

FOCAL_PRIOR_TOLERANCE = 0.10
"""Recovered focal differing from the prior by more than this fraction is flagged.  EXIF focal
lengths are nominal (rounded, and focusing changes the effective focal by a few per cent); SfM that
constrains the focal at all agrees with a correct prior within a few per cent (garden orbit sweep, 240 x 180 px:
within 0.5 % at 40 and 80 views; 2 % from the 5 photos of 20 that registered)."""

FOCAL_SPREAD_TOLERANCE = 0.10
"""With one camera per photo (COLMAP's default for photos without EXIF), per-photo focal lengths
whose (max - min) / median exceeds this are flagged: photos of one camera should agree, and a wide
spread means each photo's focal was fitted to noise (use ``single_camera`` or a prior)."""

FOCAL_PROBE_STEP = 0.2
"""The focal-sensitivity probe re-runs bundle adjustment with every focal length fixed this fraction
higher (and lower) and measures how much the mean reprojection error rises."""

FOCAL_PROBE_MIN_RISE = 0.05
"""If moving the focal length by :data:`FOCAL_PROBE_STEP` raises the mean reprojection error by less
than this fraction (5 %), the photos do not constrain the focal length: other poses absorb the change,
and the recovered value is a guess however small the error is.  The garden orbit sweep showed rises of
35 to 82 % where the focal came out within 2 % (9 % for 5 registered views with a prior)."""

FOCAL_PROBE_CAP = 10.0
"""The focal probe's rise is reported up to this (1000 %): a trial adjustment that diverges (seen on a
well-constrained 80-view orbit) only says the focal length is pinned down, not by how much."""

STRONG_DISTORTION = 0.05
"""Distortion displacing the image corners by more than this fraction of their distance from the
principal point is flagged (about 5 % of the half-diagonal): ordinary lenses after in-camera
correction stay well under it; beyond it the photos are wide-angle or fisheye, or the distortion
term absorbed a wrong focal length."""

SHORT_TRACKS = 3.0
"""Mean track length (photos per 3D point) below this is flagged: with most points seen in two photos,
focal length and distortion are fitted from pairwise geometry only, which constrains them weakly."""

LOW_OVERLAP_POINTS = 50
"""A registered photo sharing fewer than this many 3D points with its best-connected neighbour (on
average over photos) is low overlap: its pose hangs on few correspondences."""

MIN_REGISTERED_FRACTION = 0.9
"""Fewer than this fraction of the photos registered is flagged: the missing views leave holes."""

HIGH_REPROJECTION_PX = 2.0
"""Mean reprojection error above this (pixels of the photos as given) is flagged; COLMAP's own filter
drops observations above 4 px, and a good calibration gives well under 1 px."""

FEW_VIEWS = 8
"""``camera_model="auto"`` estimates no distortion (``SIMPLE_PINHOLE``) below this many photos: a
handful of views cannot separate a radial term from the focal length and the poses.  A judgement, not
a measurement; give the model explicitly when the photos are known to be distorted."""

EXIF_FOCAL_AGREEMENT = 0.01
"""EXIF focal lengths (in pixels) of all photos must agree within this fraction to make one prior."""


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
        COLMAP camera model to estimate, or ``"auto"`` (default: ``SIMPLE_RADIAL``, or
        ``SIMPLE_PINHOLE`` below :data:`FEW_VIEWS` photos; :func:`choose_camera_model`).
        Distorted models are undistorted afterwards.
    single_camera : bool or None
        True: all photos share one camera (same device and zoom): fewer unknowns, more robust.
        False: COLMAP's default, a camera per photo unless their EXIF says they match.  None
        (default): share one camera when every photo has the same size and the same or no EXIF
        focal length (:func:`choose_camera_sharing`).
    min_model_size : int
        Smallest reconstruction (registered photos) COLMAP keeps; small on purpose so
        that a dozen photos can make a scene (COLMAP's default is 10).
    sequential_overlap : int
        With the sequential matcher, each photo is matched with this many following ones.
    num_threads : int
        Threads for extraction, matching and mapping.  1 makes runs reproducible bit for bit
        (COLMAP's multi-threaded extraction and bundle adjustment vary run to run, enough to
        change the result); -1 uses every core.
    focal_px : float or None
        Prior focal length in pixels of the photos as given (overrides EXIF).
    fov_deg : float or None
        Prior horizontal field of view in degrees, in (0, 180) (overrides EXIF).
    camera_params : tuple of float or None
        Every parameter of ``camera_model`` in COLMAP's order (e.g. SIMPLE_RADIAL: f, cx, cy, k),
        in pixels of the photos as given; needs an explicit ``camera_model``.
    fix_intrinsics : bool
        Keep the prior's intrinsics (focal length and distortion) fixed in bundle adjustment
        instead of starting from them; needs a prior (one of the three above, or EXIF).
    use_exif : bool
        Use the photos' EXIF focal length as the prior when no other is given.
    focal_probe : bool
        Measure whether the photos constrain the focal length (:data:`FOCAL_PROBE_STEP`):
        two extra bundle adjustments, a few per cent of the mapping time.
    """

    matcher: str = "exhaustive"
    seed: int = 0
    max_image_size: int = 1600
    max_num_features: int = 8192
    camera_model: str = "auto"
    single_camera: bool | None = None
    min_model_size: int = 3
    sequential_overlap: int = 10
    num_threads: int = 1
    focal_px: float | None = None
    fov_deg: float | None = None
    camera_params: tuple[float, ...] | None = None
    fix_intrinsics: bool = False
    use_exif: bool = True
    focal_probe: bool = True

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise NimbusError(f"unknown matcher {self.matcher!r}; use one of {MATCHERS}")
        if self.camera_model not in CAMERA_MODELS:
            raise NimbusError(f"unsupported camera model {self.camera_model!r}; use one of {CAMERA_MODELS}")
        if self.num_threads == 0 or self.num_threads < -1:
            raise NimbusError(f"num_threads must be -1 (all cores) or positive, got {self.num_threads}")
        if self.max_image_size < 64 or self.max_num_features < 64 or self.min_model_size < 2:
            raise NimbusError("max_image_size and max_num_features must be >= 64 and min_model_size >= 2")
        given = [flag for flag, v in (("--focal", self.focal_px), ("--fov", self.fov_deg),
                                      ("--camera-params", self.camera_params)) if v is not None]
        if len(given) > 1:
            raise NimbusError(f"{' and '.join(given)} both describe the camera; give only one of them")
        if self.focal_px is not None and not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise NimbusError(f"--focal must be a positive number of pixels, got {self.focal_px}")
        if self.fov_deg is not None and not (math.isfinite(self.fov_deg) and 0 < self.fov_deg < 180):
            raise NimbusError(f"--fov must be a horizontal field of view in degrees in (0, 180), got {self.fov_deg}")
        if self.camera_params is not None:
            if self.camera_model == "auto":
                raise NimbusError("--camera-params needs --camera-model (the model the parameters belong to), "
                                  "e.g. --camera-model SIMPLE_RADIAL --camera-params 800,400,300,0.01")
            names = _param_names(self.camera_model)
            if len(self.camera_params) != len(names):
                raise NimbusError(f"--camera-params for {self.camera_model} needs {len(names)} values "
                                  f"({', '.join(names)}), got {len(self.camera_params)}")
            if not all(math.isfinite(v) for v in self.camera_params) or self.camera_params[0] <= 0:
                raise NimbusError(f"--camera-params must be finite with a positive focal length, got "
                                  f"{','.join(map(str, self.camera_params))}")

    @property
    def has_explicit_prior(self) -> bool:
        return self.focal_px is not None or self.fov_deg is not None or self.camera_params is not None


def _param_names(model: str) -> list[str]:
    """COLMAP's parameter names of ``model`` (``["f", "cx", "cy", "k"]`` for SIMPLE_RADIAL)."""
    cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, 2, 2)
    return [p.strip() for p in cam.params_info.split(",")]


def choose_camera_model(requested: str, n_photos: int) -> tuple[str, str]:
    """The camera model to estimate and why.

    Parameters
    ----------
    requested : str
        :attr:`SfmConfig.camera_model` (``"auto"`` or a model name, which is kept).
    n_photos : int
        Number of photos.

    Returns
    -------
    (model, reason) : tuple of str
    """
    if requested != "auto":
        return requested, "given with --camera-model"
    if n_photos < FEW_VIEWS:
        return "SIMPLE_PINHOLE", (f"auto: {n_photos} photos (< {FEW_VIEWS}) cannot separate lens distortion from "
                                  "the focal length, so none is estimated (give --camera-model SIMPLE_RADIAL if "
                                  "the photos are distorted)")
    return "SIMPLE_RADIAL", (f"auto, {n_photos} photos: a focal length and one radial term, the fewest that fit "
                             "real lenses")


def choose_camera_sharing(photos_dir: Path, photos: list[str], config: SfmConfig) -> tuple[bool, str]:
    """Whether the photos share one camera (``config.single_camera``, or decided when it is None), and why.

    A capture is usually one device at one zoom, and one shared camera has one focal length to fit
    instead of one per photo.  Per-photo cameras fitted from few views drift apart: on the tabletop orbit
    at 36 views they gave 5 deg / 30 % pose errors and a wild distortion term, one shared camera 0.13 deg /
    0.45 %.  So photos of one size whose EXIF focal lengths agree (or are absent) share a camera; photos of
    several sizes or zooms keep COLMAP's camera per photo.
    """
    if config.single_camera is not None:
        return bool(config.single_camera), ("one camera shared by every photo (--single-camera)"
                                            if config.single_camera else "a camera per photo (--camera-per-photo)")
    sizes = {_photo_size(Path(photos_dir) / p) for p in photos}
    if len(sizes) > 1:
        return False, f"a camera per photo: the photos have {len(sizes)} sizes"
    focals = [exif_focal_px(Path(photos_dir) / p) for p in photos] if config.use_exif else []
    found = [f for f in focals if f is not None]
    if found and (len(found) < len(photos)
                  or max(found) - min(found) > EXIF_FOCAL_AGREEMENT * float(np.median(found))):
        return False, "a camera per photo: their EXIF focal lengths differ or are missing in some"
    w, h = next(iter(sizes))
    return True, (f"one shared camera: every photo is {w}x{h} with the same or no EXIF focal length "
                  "(--camera-per-photo to fit each)")


@dataclass(frozen=True)
class CameraPrior:
    """What is known about the camera before SfM.

    Attributes
    ----------
    source : str
        ``"exif"``, ``"--focal"``, ``"--fov"`` or ``"--camera-params"``.
    focal_px : float
        Focal length in pixels of the photos as given.
    params : tuple of float
        Every parameter of the camera model (principal point at the image centre and no
        distortion unless ``--camera-params`` said otherwise).
    """

    source: str
    focal_px: float
    params: tuple[float, ...]


class SfmResult(NamedTuple):
    """What :func:`run_sfm` returns: the written scene, registered and total photo counts, and the calibration."""

    scene: Scene
    registered: int
    total: int
    calibration: "CalibrationReport"


def list_photos(photos_dir: str | os.PathLike) -> list[str]:
    """Photo names (relative posix paths, sorted) under ``photos_dir``; NimbusError if there are none."""
    photos_dir = Path(photos_dir)
    if not photos_dir.is_dir():
        raise NimbusError(f"photo folder {photos_dir} does not exist; check the path")
    photos = list_images(photos_dir)
    if not photos:
        raise NimbusError(f"{photos_dir} has no photos (.png, .jpg, .tif, .bmp); point to the folder of images")
    return photos


# --- EXIF ------------------------------------------------------------------------------------------

_EXIF_IFD = 0x8769
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_FOCAL_PLANE_X_RES = 0xA20E
_FOCAL_PLANE_UNIT = 0xA210
_EXIF_IMAGE_WIDTH = 0xA002
#: FocalPlaneResolutionUnit -> millimetres (EXIF 2.3: 2 inch, 3 cm; 4 mm and 5 um are common extensions).
_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


def _rational(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def exif_focal_px(path: str | os.PathLike) -> float | None:
    """The focal length in pixels that a photo's EXIF states, or None.

    ``FocalLengthIn35mmFilm`` is converted as COLMAP does (36 mm spans the longest image side);
    otherwise ``FocalLength`` (mm) times the sensor's ``FocalPlaneXResolution`` (pixels per unit),
    rescaled when the photo was resized after capture (``ExifImageWidth``).  Photos without EXIF
    (PNG, most synthetic or exported images) or with unreadable values give None; so does a
    missing Pillow.
    """
    try:
        from PIL import Image
    except ImportError:  # Pillow comes with matplotlib; without it EXIF priors are simply not read
        return None
    try:
        with Image.open(path) as im:
            width, height = im.size
            exif = im.getexif()
            sub = dict(exif.get_ifd(_EXIF_IFD)) if exif else {}
    except Exception:  # a corrupt header is reported by feature extraction, not here
        return None
    tags = {**dict(exif or {}), **sub}
    longest = max(width, height)
    f35 = _rational(tags.get(_FOCAL_35MM))
    if f35 is not None:
        return f35 / 36.0 * longest
    f_mm, x_res = _rational(tags.get(_FOCAL_LENGTH)), _rational(tags.get(_FOCAL_PLANE_X_RES))
    try:
        unit = _UNIT_MM.get(int(tags.get(_FOCAL_PLANE_UNIT, 2)))  # EXIF's default unit is the inch
    except (TypeError, ValueError):
        unit = None
    if f_mm is None or x_res is None or unit is None:
        return None
    focal = f_mm * x_res / unit
    exif_width = _rational(tags.get(_EXIF_IMAGE_WIDTH))
    if exif_width is not None and exif_width != width:
        focal *= width / exif_width
    return focal


def _photo_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, refused above the pixel limit (:func:`nimbus.data.images.image_size`):
    every photo is sized before pycolmap decodes any, so a decompression bomb stops here."""
    return image_size(path)


def resolve_prior(photos_dir: Path, photos: list[str], config: SfmConfig, model: str) -> tuple[CameraPrior | None,
                                                                                                 list[str]]:
    """The camera prior from the config or the photos' EXIF, and notes on how it was found.

    Raises NimbusError when a prior is given for photos of different sizes (one set of pixel
    intrinsics cannot fit them) or ``fix_intrinsics`` has no prior to keep.
    """
    notes: list[str] = []
    sizes = {_photo_size(photos_dir / p) for p in photos} if (config.has_explicit_prior or config.use_exif) else set()
    if config.has_explicit_prior and len(sizes) > 1:
        listed = ", ".join(f"{w}x{h}" for w, h in sorted(sizes)[:4])
        raise NimbusError(f"the photos have {len(sizes)} different sizes ({listed}); "
                          "a prior in pixels fits one size only: resize them to one size or drop --focal / --fov / "
                          "--camera-params")
    prior = None
    if config.camera_params is not None:
        params = tuple(float(v) for v in config.camera_params)
        cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, *next(iter(sizes)))
        cam.params = list(params)
        prior = CameraPrior("--camera-params", float(cam.mean_focal_length()), params)
    elif config.focal_px is not None or config.fov_deg is not None:
        width, height = next(iter(sizes))
        if config.focal_px is not None:
            focal, source = float(config.focal_px), "--focal"
        else:
            focal, source = (width / 2.0) / math.tan(math.radians(config.fov_deg) / 2.0), "--fov"
        prior = CameraPrior(source, focal, _default_params(model, focal, width, height))
    elif config.use_exif:
        focals = [exif_focal_px(photos_dir / p) for p in photos]
        found = [f for f in focals if f is not None]
        if not found:
            notes.append("no EXIF focal length in the photos: the focal length is self-calibrated")
        elif len(found) < len(photos):
            notes.append(f"EXIF focal length in {len(found)} of {len(photos)} photos only: not used as a prior")
        elif len(sizes) > 1:
            notes.append("EXIF focal lengths found, but the photos differ in size: not used as one prior")
        elif (max(found) - min(found)) > EXIF_FOCAL_AGREEMENT * float(np.median(found)):
            notes.append(f"EXIF focal lengths differ between photos ({min(found):.0f} to {max(found):.0f} px, a zoom "
                         "lens?): not used as one prior")
        else:
            width, height = next(iter(sizes))
            focal = float(np.median(found))
            prior = CameraPrior("exif", focal, _default_params(model, focal, width, height))
    if config.fix_intrinsics and prior is None:
        raise NimbusError("--fix-intrinsics needs a camera prior to keep: give --focal PX, --fov DEG or "
                          "--camera-params, or photos whose EXIF states the focal length")
    return prior, notes


def _default_params(model: str, focal: float, width: int, height: int) -> tuple[float, ...]:
    """``model``'s parameters for ``focal``, principal point at the image centre, no distortion."""
    cam = pycolmap.Camera.create_from_model_name(1, model, focal, width, height)
    return tuple(float(v) for v in cam.params)


# --- the pipeline -------------------------------------------------------------------------------------

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
        ``(scene, registered, total, calibration)``: the scene as read back from ``out_dir``,
        the number of registered photos and of photos found, and the :class:`CalibrationReport`
        (also in ``out_dir/manifest.json`` under ``"calibration"``).

    Raises
    ------
    NimbusError
        No photos, a photo that is not a PNG, JPEG, TIFF or BMP or is larger than the pixel limit
        (:func:`nimbus.data.images.image_size`), output folder not empty (without ``overwrite``) or inside
        the photos, a prior that does not fit the photos, or no reconstruction (too little overlap or texture).
    """
    config = replace(config, **changes)
    say = log or (lambda _msg: None)
    photos_dir, out_dir = Path(photos_dir), Path(out_dir)
    photos = list_photos(photos_dir)
    for p in photos:  # sized from their headers before pycolmap decodes them: an oversized photo is refused here
        _photo_size(photos_dir / p)
    src, dst = photos_dir.resolve(), out_dir.resolve()
    if dst == src or dst in src.parents or src in dst.parents:
        raise NimbusError(f"--out {out_dir} must be outside the photo folder {photos_dir} (and not contain it)")
    check_output_dir(out_dir, overwrite)
    model, reason = choose_camera_model(config.camera_model, len(photos))
    shared, sharing = choose_camera_sharing(photos_dir, photos, config)
    config = replace(config, single_camera=shared)
    prior, notes = resolve_prior(photos_dir, photos, config, model)
    if prior is not None:
        say(f"camera prior from {prior.source}: focal {prior.focal_px:.1f} px"
            + (" (kept fixed)" if config.fix_intrinsics else " (refined)"))

    pycolmap.logging.minloglevel = 2  # warnings and errors only: COLMAP's info log floods the terminal
    pycolmap.set_random_seed(config.seed)
    with tempfile.TemporaryDirectory(prefix="nimbus-sfm-") as work, atomic_dir(out_dir, overwrite) as tmp:
        work = Path(work)
        rec = _reconstruct(photos_dir, photos, work, config, model, prior, say)
        say("measuring the calibration")
        report = calibration_report(rec, len(photos), model, reason, prior, config, notes, sharing)
        say(f"writing the scene ({rec.num_reg_images()} registered photos)")
        _write_scene(rec, photos_dir, work, Path(tmp), model)
        atomic_write_json(Path(tmp) / "manifest.json", {
            "generator": GENERATOR, "photos": len(photos), "registered": report.registered,
            "sfm_config": jsonable(asdict(config), nonfinite="text"), "calibration": report.to_dict()})
    scene = read_colmap(out_dir)
    return SfmResult(scene, len(scene), len(photos), report)


def _reconstruct(photos_dir: Path, photos: list[str], work: Path, config: SfmConfig, model: str,
                 prior: CameraPrior | None, say: Callable[[str], None]) -> pycolmap.Reconstruction:
    """Features, matches and incremental mapping; the largest reconstruction."""
    database = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    if prior is not None:
        # Every new camera starts from these parameters and is marked as having a prior focal length.
        reader.camera_params = ",".join(repr(float(v)) for v in prior.params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_num_features
    extraction.num_threads = config.num_threads
    mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.AUTO
    # AUTO makes a camera per photo when the photos carry no EXIF, as plain PNGs and most exports do
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
    say(f"incremental mapping ({model})")
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = config.min_model_size
    options.random_seed = config.seed
    options.num_threads = config.num_threads
    options.mapper.num_threads = config.num_threads
    if config.fix_intrinsics:
        # Neither bundle adjustment nor the absolute-pose solver of each new image may move them.
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        options.ba_refine_principal_point = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    models = pycolmap.incremental_mapping(database, photos_dir, work / "sparse", options)
    models = [m for m in models.values() if m.num_reg_images() > 0]
    if not models:
        raise NimbusError(
            f"structure from motion found no reconstruction in {photos_dir} ({len(photos)} photos): the photos "
            "need more overlap (each part of the scene seen from several nearby viewpoints) and texture; "
            "try --matcher exhaustive or more photos" + ("" if config.single_camera else
                                                         ", or --single-camera if one camera took them all"))
    return max(models, key=lambda m: (m.num_reg_images(), m.num_points3D()))


def _write_scene(rec: pycolmap.Reconstruction, photos_dir: Path, work: Path, out: Path, model: str) -> None:
    """``out/images`` (registered photos) + ``out/sparse/0``, undistorting a distorted camera model."""
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True)
    names = sorted(rec.images[i].name for i in rec.reg_image_ids())
    if model in PINHOLE_MODELS:
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


# --- the calibration report ---------------------------------------------------------------------------

@dataclass(frozen=True)
class CalibrationReport:
    """How well the photos determined the cameras, with warnings (see the module's threshold constants).

    Attributes
    ----------
    registered, total : int
        Registered photos and photos found.
    camera_model : str
        The model estimated, and ``model_reason`` why it was chosen.
    model_reason : str
    prior_source : str or None
        ``"exif"``, ``"--focal"``, ``"--fov"``, ``"--camera-params"`` or None (self-calibrated).
    prior_focal_px : float or None
    fixed : bool
        The prior's intrinsics were kept fixed in bundle adjustment.
    cameras : int
        Distinct cameras among the registered photos.
    camera_sharing : str
        Why the photos share one camera or have one each (:func:`choose_camera_sharing`).
    focal_px : float
        Median recovered focal length over the registered photos' cameras, pixels of the photos as given.
    focal_spread : float
        (max - min) / median of those focal lengths (0 for one camera).
    focal_vs_prior : float or None
        ``focal_px / prior_focal_px - 1``.
    longest_side_px : int
        Longest side of the photos (the largest over cameras).
    focal_vs_default : float
        ``focal_px / (FOCAL_DEFAULT_FACTOR * longest_side_px)``.
    focal_probe_rise : float or None
        Relative rise of the mean reprojection error when every focal length is fixed
        :data:`FOCAL_PROBE_STEP` off its value and bundle adjustment runs again (the smaller of the
        two directions), at most :data:`FOCAL_PROBE_CAP`; None when not measured (fixed intrinsics, or
        probing off).
    distortion : float
        Largest displacement of an image corner by the lens model, as a fraction of the corner's
        distance from the principal point (0 for pinhole models; inf where the model does not invert
        at a corner, which only a wildly wrong distortion does; None in :meth:`to_dict`).
    distortion_px : float
        The same in pixels.
    reprojection_error_px : float
        Mean reprojection error.
    mean_track_length : float
        Mean number of photos observing a 3D point.
    points : int
        3D points.
    observations_per_view : float
        Mean 3D points observed per registered photo.
    shared_points_best_neighbour : float
        Mean over registered photos of the 3D points shared with the photo that shares the most.
    flags : tuple of str
        A short code per warning, in the same order: ``registered``, ``focal-prior``, ``focal-range``,
        ``focal-spread``, ``focal-unconstrained``, ``distortion``, ``short-tracks``, ``low-overlap``,
        ``reprojection``.
    warnings : tuple of str
        One sentence each: what is suspicious and what to do.
    notes : tuple of str
        How the prior was found (EXIF) and other remarks that are not warnings.
    """

    registered: int
    total: int
    camera_model: str
    model_reason: str
    prior_source: str | None
    prior_focal_px: float | None
    fixed: bool
    cameras: int
    camera_sharing: str
    focal_px: float
    focal_spread: float
    focal_vs_prior: float | None
    longest_side_px: int
    focal_vs_default: float
    focal_probe_rise: float | None
    distortion: float
    distortion_px: float
    reprojection_error_px: float
    mean_track_length: float
    points: int
    observations_per_view: float
    shared_points_best_neighbour: float
    flags: tuple[str, ...]
    warnings: tuple[str, ...]
    notes: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready: floats rounded, tuples as lists, and a distortion that does not invert at the corners
        (infinite) as None, since strict JSON has no infinity."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = round(v, 6) if math.isfinite(v) else None
            elif isinstance(v, tuple):
                d[k] = list(v)
        return d

    def lines(self) -> list[str]:
        """The report as printed by ``nimbus-synth sfm``."""
        prior = (f"{self.prior_focal_px:.1f} px from {self.prior_source}"
                 + (" (kept fixed)" if self.fixed else "") if self.prior_source else "none (self-calibrated)")
        vs_prior = f", {self.focal_vs_prior:+.1%} vs prior" if self.focal_vs_prior is not None else ""
        spread = f", spread {self.focal_spread:.1%} over {self.cameras} cameras" if self.cameras > 1 else ""
        probe = ("not measured" if self.focal_probe_rise is None else
                 f"error +{self.focal_probe_rise:.1%} with the focal {FOCAL_PROBE_STEP:.0%} off")
        out = [
            "calibration:",
            f"  registered       {self.registered} / {self.total} photos",
            f"  camera model     {self.camera_model} ({self.model_reason})",
            f"  cameras          {self.cameras} ({self.camera_sharing or 'as COLMAP grouped the photos'})",
            f"  prior            {prior}",
            f"  focal length     {self.focal_px:.1f} px{vs_prior}; {self.focal_vs_default:.2f} x "
            f"({FOCAL_DEFAULT_FACTOR} x longest side {self.longest_side_px} px){spread}",
            f"  focal probe      {probe}",
            ("  distortion       " + (f"{self.distortion:.1%} of the corner radius ({self.distortion_px:.1f} px)"
                                      if math.isfinite(self.distortion) else "extreme: the lens model does not invert "
                                      "at the image corners")),
            f"  reprojection     {self.reprojection_error_px:.2f} px mean",
            f"  tracks           {self.points} points, mean track length {self.mean_track_length:.2f} photos",
            f"  overlap          {self.observations_per_view:.0f} points per photo, "
            f"{self.shared_points_best_neighbour:.0f} shared with its best neighbour",
        ]
        out += [f"  note: {n}" for n in self.notes]
        out += [f"WARNING: {w}" for w in self.warnings] or ["  no warnings"]
        return out


def calibration_report(rec: pycolmap.Reconstruction, total: int, model: str, reason: str,
                       prior: CameraPrior | None, config: SfmConfig, notes: list[str] | tuple = (),
                       sharing: str = "") -> CalibrationReport:
    """Measure a reconstruction's calibration and collect the warnings (the thresholds are module constants).

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The reconstruction before undistortion (its cameras carry the estimated distortion).
    total : int
        Photos given to SfM.
    model, reason : str
        The estimated camera model and why it was chosen (:func:`choose_camera_model`).
    prior : CameraPrior or None
    config : SfmConfig
        ``fix_intrinsics`` and ``focal_probe`` are read.
    notes : sequence of str
        Remarks to carry into the report.
    sharing : str
        Why the photos share a camera or not (:func:`choose_camera_sharing`).
    """
    reg = list(rec.reg_image_ids())
    cam_ids = sorted({rec.images[i].camera_id for i in reg})
    cams = [rec.cameras[c] for c in cam_ids]
    per_view_focal = np.array([rec.cameras[rec.images[i].camera_id].mean_focal_length() for i in reg])
    focal = float(np.median(per_view_focal))
    spread = float((per_view_focal.max() - per_view_focal.min()) / focal) if len(cams) > 1 else 0.0
    longest = max(max(c.width, c.height) for c in cams)
    vs_default = focal / (FOCAL_DEFAULT_FACTOR * longest)
    vs_prior = focal / prior.focal_px - 1.0 if prior is not None else None
    dist, dist_px = max((_distortion(c) for c in cams), key=lambda d: d[0])
    track = float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0
    shared = _shared_points_best_neighbour(rec, reg)
    probe = None
    if config.focal_probe and not config.fix_intrinsics and rec.num_points3D() > 0:
        probe = _focal_probe(rec)
    error = float(rec.compute_mean_reprojection_error())

    flags, warnings = [], []

    def warn(code: str, text: str) -> None:
        flags.append(code)
        warnings.append(text)

    if len(reg) < MIN_REGISTERED_FRACTION * total:
        warn("registered", f"only {len(reg)} of {total} photos registered (< {MIN_REGISTERED_FRACTION:.0%}): the "
             "others had too few matches; take more photos between them"
             + ("" if config.single_camera else ", or try --single-camera"))
    if vs_prior is not None and abs(vs_prior) > FOCAL_PRIOR_TOLERANCE:
        warn("focal-prior", f"the focal length {focal:.0f} px is {vs_prior:+.0%} off the prior {prior.focal_px:.0f} "
             f"px ({prior.source}; tolerance {FOCAL_PRIOR_TOLERANCE:.0%}): if the prior is right, rerun with "
             "--fix-intrinsics")
    lo, hi = FOCAL_PLAUSIBLE_RANGE
    if not lo <= vs_default <= hi:
        warn("focal-range", f"the focal length {focal:.0f} px is {vs_default:.2f} x the usual {FOCAL_DEFAULT_FACTOR} "
             f"x longest side ({FOCAL_DEFAULT_FACTOR * longest:.0f} px; plausible {lo}-{hi} x): unless the lens is "
             "that wide or long, the calibration is wrong; give --focal or --fov")
    if spread > FOCAL_SPREAD_TOLERANCE:
        warn("focal-spread", f"the {len(cams)} per-photo cameras disagree on the focal length by {spread:.0%} "
             f"(> {FOCAL_SPREAD_TOLERANCE:.0%}): if one camera took every photo, rerun with --single-camera (and a "
             "prior if you know one)")
    if probe is not None and probe < FOCAL_PROBE_MIN_RISE:
        warn("focal-unconstrained", f"the photos do not pin the focal length down: fixing it "
             f"{FOCAL_PROBE_STEP:.0%} off raises the reprojection error by only {probe:.1%} (< "
             f"{FOCAL_PROBE_MIN_RISE:.0%}), so {focal:.0f} px is a guess however small the error; give --focal / "
             "--fov (and --fix-intrinsics), or add photos from more varied viewpoints")
    if dist > STRONG_DISTORTION:
        warn("distortion", f"strong lens distortion: the corners move by {dist:.0%} of their radius "
             f"({dist_px:.0f} px, > {STRONG_DISTORTION:.0%}); fine for a wide-angle lens, otherwise the distortion "
             "term absorbed a wrong focal length (give --focal, or --camera-model SIMPLE_PINHOLE for undistorted "
             "photos)")
    if track < SHORT_TRACKS:
        warn("short-tracks", f"short tracks: a 3D point is seen in {track:.1f} photos on average (< {SHORT_TRACKS}), "
             "so the intrinsics rest on pairwise geometry; take more overlapping photos")
    if shared < LOW_OVERLAP_POINTS:
        warn("low-overlap", f"low overlap: a photo shares {shared:.0f} points with its best neighbour on average "
             f"(< {LOW_OVERLAP_POINTS}); take photos closer together, or larger / more textured ones")
    if error > HIGH_REPROJECTION_PX:
        warn("reprojection", f"mean reprojection error {error:.2f} px (> {HIGH_REPROJECTION_PX} px): the camera "
             "model does not fit; try --camera-model RADIAL or OPENCV, or check for rolling shutter / motion blur")
    return CalibrationReport(
        registered=len(reg), total=total, camera_model=model, model_reason=reason,
        prior_source=prior.source if prior else None, prior_focal_px=prior.focal_px if prior else None,
        fixed=bool(config.fix_intrinsics), cameras=len(cams), camera_sharing=sharing, focal_px=focal,
        focal_spread=spread, focal_vs_prior=vs_prior, longest_side_px=int(longest), focal_vs_default=float(vs_default),
        focal_probe_rise=probe, distortion=float(dist), distortion_px=float(dist_px),
        reprojection_error_px=error, mean_track_length=track, points=int(rec.num_points3D()),
        observations_per_view=float(rec.compute_mean_observations_per_reg_image()) if reg else 0.0,
        shared_points_best_neighbour=shared, flags=tuple(flags), warnings=tuple(warnings), notes=tuple(notes))


def _distortion(cam: pycolmap.Camera) -> tuple[float, float]:
    """(fraction, pixels): the largest corner displacement between ``cam`` and a pinhole of its focal length."""
    if cam.model_name in PINHOLE_MODELS:
        return 0.0, 0.0
    corners = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], np.float64)
    centre = np.array([cam.principal_point_x, cam.principal_point_y])
    rays = np.asarray(cam.cam_from_img(corners), np.float64)  # undistorted normalised coordinates
    pinhole = rays * np.array([cam.focal_length_x, cam.focal_length_y]) + centre
    shift = np.linalg.norm(pinhole - corners, axis=1)
    if not np.all(np.isfinite(shift)):  # the model does not invert at the corner: extreme distortion
        return math.inf, math.inf
    radius = np.linalg.norm(corners - centre, axis=1)
    i = int(np.argmax(shift / radius))
    return float(shift[i] / radius[i]), float(shift[i])


def _shared_points_best_neighbour(rec: pycolmap.Reconstruction, reg: list[int]) -> float:
    """Mean over registered images of the 3D points shared with their best-connected other image."""
    pairs: Counter = Counter()
    for point in rec.points3D.values():
        ids = sorted({e.image_id for e in point.track.elements})
        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                pairs[ids[a], ids[b]] += 1
    best = dict.fromkeys(reg, 0)
    for (a, b), n in pairs.items():
        best[a] = max(best.get(a, 0), n)
        best[b] = max(best.get(b, 0), n)
    return float(np.mean([best[i] for i in reg])) if reg else 0.0


def _focal_probe(rec: pycolmap.Reconstruction) -> float:
    """Smallest relative rise of the mean reprojection error over focal x (1 +- FOCAL_PROBE_STEP), re-adjusted.

    Each trial copies the reconstruction, scales every camera's focal length, and runs a bundle
    adjustment of poses and points (distortion free, focal fixed); if the error hardly rises, the
    photos accept a focal length 20 % off just as well.
    """
    errors = []
    # factor 1 is the control: the same adjustment at the recovered focal, so a rise measures the focal alone
    for factor in (1.0, 1.0 + FOCAL_PROBE_STEP, 1.0 - FOCAL_PROBE_STEP):
        trial = pycolmap.Reconstruction(rec)
        for cam in trial.cameras.values():
            params = np.asarray(cam.params, np.float64).copy()
            params[list(cam.focal_length_idxs())] *= factor
            cam.params = params
        options = pycolmap.BundleAdjustmentOptions()
        options.refine_focal_length = False
        options.refine_principal_point = False
        options.refine_extra_params = True
        options.print_summary = False
        level = pycolmap.logging.minloglevel
        try:
            pycolmap.bundle_adjustment(trial, options)
            error = float(trial.compute_mean_reprojection_error())
        except Exception:  # a failed solve means the focal change could not be absorbed
            error = math.inf
        finally:
            pycolmap.logging.minloglevel = level  # bundle_adjustment turns COLMAP's info log back on
        errors.append(error if math.isfinite(error) else math.inf)
    base = max(errors[0], 1e-9)
    return float(min(min(errors[1:]) / base - 1.0, FOCAL_PROBE_CAP))


__all__ = ["CAMERA_MODELS", "MATCHERS", "CalibrationReport", "CameraPrior", "SfmConfig", "SfmResult",
           "calibration_report", "choose_camera_model", "choose_camera_sharing", "exif_focal_px", "list_photos",
           "resolve_prior", "run_sfm"]
