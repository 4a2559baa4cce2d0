"""Write a weather-degraded benchmark dataset: one scene folder per weather setting.

Layout of ``OUT`` (setting folder names: :mod:`weather_synth.settings`)::

    OUT/
      index.json                 settings written, summary table, generator version
      H/  R/  S/  H+R/  H+S/  R+S/  H+R+S/
        images/<name>.png        degraded images (8-bit PNG), what a trainer reads
        clean/<name>             ground-truth clean images (original files copied
                                 byte for byte when they are PNG; else 8-bit PNG)
        sparse/0/ | transforms.json   the input's cameras and points, in the input's
                                 own format (a COLMAP model is copied byte for byte
                                 when no image had to be renamed to .png, all but
                                 the point colours); point colours from the
                                 setting's degraded train views (below)
        depths/, masks/, sky/    the scene's depth maps, validity and sky masks, when it has them
        train_list.txt, test_list.txt   the split
        layers/<stem>.npz        per-view float32 ground-truth layers (below)
        manifest.json            every parameter, every per-view sampled value,
                                 seeds, input checksums, output checksums, version

Layer archives hold the layers of the setting's components (``np.load``):

``transmission`` (H, W)
    camera-to-surface transmission t in [0, 1] (H)
``airlight`` (3,)
    airlight A, RGB display values (H)
``depth`` (H, W)
    z-depth used for the haze, scene units, ``inf`` = sky; only when it was
    estimated (``--depth sparse`` / ``onnx``), else the scene's ``depths/`` (H)
``rain`` (H, W)
    additive rain radiance (sum of streak slices, before any attenuation) (R)
``snow`` (H, W)
    snow alpha ``1 - prod(1 - S_k)`` (S)
``rain_depth``, ``snow_depth`` (H, W)
    z-depth of the particle contributing most at the pixel, ``inf`` where none,
    0 for particles without depth (R, S)

The sparse points keep their positions (and COLMAP tracks) but not their
clean colours: a trainer initialises Gaussians from them, so the clean colours
would leak ground truth into a method that only sees degraded views.  Each
point gets, as SfM on the degraded photos would, the mean 8-bit colour of the
setting's degraded *train* images at the pixel it projects to, over the train
views that see it (:func:`weather_synth.depth.visible_point_indices`, with the
depth config's occlusion test); test views and clean images are never used.
A point no train view sees gets the mean colour of the points that were seen.
The manifest's ``input.point_colours`` records the rule and the counts.

So 3DGS, gsplat or nerfstudio train on ``OUT/H+R`` directly and a benchmark
scores renders against ``clean/``.  Views are processed one at a time (memory
does not grow with the number of views); every setting folder is written
atomically (a temporary folder renamed into place when complete), and a run
that fails or is interrupted (a full disk, a corrupt image, Ctrl-C) removes
every setting it wrote, and the ``OUT`` (and parent folders) it made: one
setting of seven is not the dataset asked for.  Only a setting that an
``--overwrite`` run had already replaced stays (complete; its old version is
gone).  A kill -9 leaves complete settings and a temporary folder.  A temporary folder left by a killed run (``OUT/.SETTING.tmp-*``, whose
owner process is gone) is removed by the next run.  The same input, config
and seed give the same bytes.

Every path written is built with :func:`nimbus.utils.fs.confined_path` from
the temporary folder and the view's name, so no view name (``/abs/t.png``,
``../../t.png``, a link leading out) can make the writer touch a file outside
``OUT``; ``OUT`` may not be, contain or lie inside any of the scene's inputs.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
import struct
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from nimbus import __version__
from nimbus.data.camera import Camera
from nimbus.data.images import encode_png, refuse_nonfinite, to_uint8
from nimbus.data.io import SCENE_FORMATS, write_scene_into
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.utils.fs import (atomic_dir, atomic_write_bytes, atomic_write_json, check_output_dir, confined_path,
                             refuse_overlap, remove_stale_temps, sha256_file)
from nimbus.utils.jsonable import jsonable
from weather_synth.archive import encode_layers
from weather_synth.config import SynthConfig
from weather_synth.depth import DepthConfig, visible_point_indices
from weather_synth.depth_consistency import scene_depth_consistency
from weather_synth.settings import WeatherSetting
from weather_synth.synth import Synthesizer

FORMAT = "nimbus-synth-degrade/1"
MANIFEST = "manifest.json"
INDEX = "index.json"
LAYER_DIR = "layers"
CLEAN_DIR = "clean"
IMAGE_DIR = "images"
# Degraded images wait here (inside the setting's temporary folder) until the scene writer has filled images/.
DEGRADED_STAGING_DIR = "images.degraded"
# Point colour when there is no degraded train view at all to take colours from (mid-grey).
NO_VIEW_POINT_COLOUR = (128, 128, 128)
POINT_COLOUR_RULE = ("mean 8-bit colour of the degraded train images at the point's pixel, over the train views "
                     "that see it; points no train view sees get the mean colour of the seen points")
# COLMAP points3D.bin record: point id (uint64), xyz (3 float64), rgb (3 uint8), error (float64),
# track length (uint64), then (image id, point2D index) int32 pairs.
COLMAP_POINT_HEAD = struct.Struct("<Q3d3BdQ")
COLMAP_RGB_OFFSET = 32
COLMAP_TRACK_ELEMENT_BYTES = 8
# Temporary folders inside OUT: ``.NAME.tmp-*`` (atomic_dir, the depth cache) and ``.NAME.old-*``.
TEMP_NAME = re.compile(r"\.(?P<name>.+)\.(?:tmp|old)-[^/]+")


@dataclass
class SettingSummary:
    """One row of the summary table."""

    setting: str
    views: int
    mean_transmission: float | None
    particle_coverage: float
    seconds: float

    def to_dict(self) -> dict:
        return {"setting": self.setting, "views": self.views, "mean_transmission": self.mean_transmission,
                "particle_coverage": self.particle_coverage}


class DegradedPointColours:
    """Sparse point colours from degraded train views, accumulated one view at a time (memory O(points)).

    A point's colour is the mean 8-bit colour, at the pixel it projects to, of
    the views that see it (:func:`weather_synth.depth.visible_point_indices`);
    a point no added view sees gets the mean colour of the seen points (or,
    when none is seen, the mean colour of the added images).

    Parameters
    ----------
    points : ndarray, shape (N, 3), float64
        The scene's sparse points (world coordinates).
    depth : DepthConfig
        Its occlusion window and tolerance decide which points a view sees.
    """

    def __init__(self, points: np.ndarray, depth: DepthConfig) -> None:
        self.points = np.asarray(points, np.float64).reshape(-1, 3)
        self.depth = depth
        self.sums = np.zeros((len(self.points), 3), np.int64)
        self.counts = np.zeros(len(self.points), np.int64)
        self.pixel_sum = np.zeros(3, np.int64)
        self.pixels = 0
        self.views = 0

    def add(self, camera: Camera, image: np.ndarray) -> None:
        """Add one view: its camera and its 8-bit image, uint8 (H, W, 3) as written."""
        if image.dtype != np.uint8 or image.shape != (camera.height, camera.width, 3):
            raise ValueError(f"expected a uint8 ({camera.height}, {camera.width}, 3) image, got "
                             f"{image.dtype} {image.shape}")
        idx, u, v, _ = visible_point_indices(camera, self.points, self.depth.occlusion_window,
                                             self.depth.occlusion_tolerance)
        self.sums[idx] += image[v, u]  # a view sees each point at most once, so no index repeats
        self.counts[idx] += 1
        self.pixel_sum += image.reshape(-1, 3).sum(0, dtype=np.int64)
        self.pixels += image.shape[0] * image.shape[1]
        self.views += 1

    @property
    def points_seen(self) -> int:
        return int(np.count_nonzero(self.counts))

    def colours(self) -> np.ndarray:
        """uint8 (N, 3): the mean colours, rounded to the nearest level."""
        seen = self.counts > 0
        out = np.empty((len(self.points), 3), np.uint8)
        out[seen] = np.rint(self.sums[seen] / self.counts[seen, None])
        if not seen.all():
            if seen.any():
                fill = np.rint(out[seen].mean(0))
            elif self.pixels:
                fill = np.rint(self.pixel_sum / self.pixels)
            else:
                fill = np.array(NO_VIEW_POINT_COLOUR)
            out[~seen] = fill
        return out

    def describe(self) -> dict:
        return {"source": "degraded train views", "rule": POINT_COLOUR_RULE, "train_views": self.views,
                "points": len(self.points), "points_seen": self.points_seen}


def png_name(name: str) -> str:
    """The output image name of a view: unchanged when it ends in ``.png``, else with ``.png``."""
    return name if name.endswith(".png") else str(Path(name).with_suffix(".png").as_posix())


def layer_file(name: str) -> str:
    """A view's layer archive name inside ``layers/``."""
    return Path(png_name(name)).with_suffix(".npz").as_posix()


def layer_name(name: str) -> str:
    """A view's layer archive name inside the setting folder (as the manifest records it)."""
    return f"{LAYER_DIR}/{layer_file(name)}"


def scene_inputs(scene: Scene) -> list[Path]:
    """Every file and folder ``scene`` is read from: its root and each view's image, depth, mask and sky file."""
    inputs = [Path(scene.root)] if scene.root is not None else []
    for v in scene.views:
        inputs += [Path(p) for p in (v.image_path, v.depth_path, v.mask_path, v.sky_path) if p is not None]
    return inputs


def check_dataset_out(out: str | os.PathLike, overwrite: bool, inputs=()) -> Path:
    """:func:`~nimbus.utils.fs.check_output_dir` for a dataset folder, once leftovers of killed runs are gone.

    A run killed mid-setting leaves ``OUT/.SETTING.tmp-*`` (and perhaps a depth
    cache ``OUT/.depth-cache.tmp-*``); their owner process is dead, so they are
    removed here, before ``OUT`` is judged empty or not.  Folders of a live run
    are kept (``OUT`` is then not empty).  Nothing is deleted in a folder that
    overlaps ``inputs``, nor in one that holds other files and is refused
    without ``overwrite`` anyway.
    """
    out = Path(out)
    refuse_overlap(out, inputs)
    with contextlib.suppress(OSError):  # unreadable or not a folder: check_output_dir says so
        if out.is_dir():
            temps = {p.name: m["name"] for p in out.iterdir() if (m := TEMP_NAME.fullmatch(p.name)) and p.is_dir()}
            if overwrite or all(p.name in temps for p in out.iterdir()):
                for name in set(temps.values()):
                    remove_stale_temps(out / name)
    return check_output_dir(out, overwrite, inputs)


def check_view_names(scene: Scene, out: str | os.PathLike) -> None:
    """Refuse view names that cannot be written into the dataset ``out``, before anything is written.

    Refused: a name that would land outside its folder (absolute, ``..``, a link
    leading out; :func:`~nimbus.utils.fs.confined_path`) and two views that
    would share one output file.  The writes themselves go through
    ``confined_path`` again; this check only makes a bad name fail before any
    file is written.
    """
    images = Path(out) / IMAGE_DIR
    seen: dict[Path, str] = {}
    for v in scene.views:
        name = png_name(v.name)
        key = confined_path(images, name, "view").relative_to(images.resolve())
        confined_path(Path(out) / LAYER_DIR, layer_file(v.name), "view")
        if ".." in Path(name).parts:  # stays inside but is not a plain name (the scene writer refuses it too)
            raise NimbusError(f"view name {v.name!r} contains '..'; names must be plain relative paths "
                              "inside the image folder (fix the scene's image names)")
        if key in seen:
            raise NimbusError(f"views {seen[key]!r} and {v.name!r} would share the output file {key.as_posix()} "
                              "once written as .png; rename the images")
        seen[key] = v.name


def degrade_scene(scene: Scene, out: str | os.PathLike, settings: Sequence[WeatherSetting], config: SynthConfig,
                  overwrite: bool = False, progress: bool = True, source: str | None = None) -> list[SettingSummary]:
    """Degrade ``scene`` in every setting and write the dataset ``out`` (module docstring).

    Parameters
    ----------
    scene : Scene
    out : path
        Output folder; refused when non-empty unless ``overwrite`` (then each
        written setting folder replaces its old version atomically), and when
        it is, contains or lies inside one of the scene's inputs.  When the call
        fails, the settings it wrote and the folders it made are removed again
        (module docstring).
    settings : sequence of WeatherSetting
    config : SynthConfig
    overwrite : bool
    progress : bool
        tqdm bar per setting on stderr.
    source : str or None
        How the scene was named on the command line (recorded in the manifests).

    Returns
    -------
    list of SettingSummary
    """
    if not settings:
        raise NimbusError("no weather settings given; use e.g. --weather all")
    if not scene.views:
        raise NimbusError("the scene has zero views; nothing to degrade")
    out = check_dataset_out(out, overwrite, scene_inputs(scene))
    check_view_names(scene, out)
    created = [p for p in (out, *out.parents) if not p.exists()]  # deepest first
    existed = {s.name for s in settings if (out / s.name).exists()}
    try:
        return _degrade_into(scene, out, settings, config, progress, source)
    except BaseException:
        # A failed run (a full disk, a corrupt image in the fifth setting, Ctrl-C) leaves none of the settings it
        # wrote: one setting of seven is not the dataset asked for.  A setting an --overwrite already replaced
        # is complete and stays (its old version is gone); folders this call made and left empty go too.
        for name in {s.name for s in settings} - existed:
            shutil.rmtree(out / name, ignore_errors=True)
        for p in created:
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


def _degrade_into(scene: Scene, out: Path, settings: Sequence[WeatherSetting], config: SynthConfig,
                  progress: bool, source: str | None) -> list[SettingSummary]:
    """The body of :func:`degrade_scene`, once ``out`` and the view names are checked."""
    from tqdm import tqdm

    fmt = scene.source_format if scene.source_format in SCENE_FORMATS else "colmap"
    renamed = any(png_name(v.name) != v.name for v in scene.views)
    summaries = []
    input_sums: dict[str, str] = {}
    clean_copy: Path | None = None  # clean/ of the first finished setting: later settings copy its files
    with Synthesizer(scene, config, cache_parent=out) as synth:
        synth.prepare(list(settings))
        # How well the views' depth maps agree (weather_synth.depth_consistency), once per scene: the haze of
        # every setting that uses depth is only as view-consistent as these maps.
        consistency = None
        if any(synth.needs_depth(s) for s in settings):
            consistency = scene_depth_consistency(scene, lambda v: synth.depth(v)[0])
        for setting in settings:
            start = time.perf_counter()
            with atomic_dir(out / setting.name, overwrite=True) as tmp:
                t_sum, cov_sum, view_records = 0.0, 0.0, []
                point_colours = DegradedPointColours(scene.points, config.depth)
                bar = tqdm(scene.views, desc=f"{setting.name:<6}", unit="view", file=sys.stderr,
                           disable=not progress, leave=True, dynamic_ncols=True)
                for view in bar:
                    J = view.load_image()
                    if view.name not in input_sums:
                        input_sums[view.name] = _input_sha256(view, J)
                    res = synth.degrade(view, setting, J)
                    out_name = png_name(view.name)
                    refuse_nonfinite(res.image, f"the degraded view {view.name} of setting {setting.name}")
                    degraded = to_uint8(res.image)
                    image_bytes = encode_png(degraded)
                    atomic_write_bytes(confined_path(tmp / DEGRADED_STAGING_DIR, out_name, "view"), image_bytes)
                    if view.name not in scene.test_names:
                        point_colours.add(view.camera, degraded)
                    if renamed and clean_copy is None:
                        atomic_write_bytes(confined_path(tmp / CLEAN_DIR, out_name, "view"), encode_png(J))
                    layer_bytes = encode_layers(res.layers, config.layer_compression)
                    atomic_write_bytes(confined_path(tmp / LAYER_DIR, layer_file(view.name), "view"), layer_bytes)
                    view_records.append({
                        "name": view.name,
                        "image": f"{IMAGE_DIR}/{out_name}",
                        "clean": f"{CLEAN_DIR}/{out_name if renamed else view.name}",
                        "layers": layer_name(view.name),
                        "split": "test" if view.name in scene.test_names else "train",
                        "input_sha256": input_sums[view.name],
                        "image_sha256": hashlib.sha256(image_bytes).hexdigest(),
                        "layers_sha256": hashlib.sha256(layer_bytes).hexdigest(),
                        **res.info,
                    })
                    t_sum += res.mean_transmission or 0.0
                    cov_sum += res.particle_coverage
                bar.close()
                # The scene files go in last: only now are the point colours known.
                _write_scene_files(replace(scene, colors=point_colours.colours()), tmp, fmt, renamed, clean_copy)
                os.replace(tmp / DEGRADED_STAGING_DIR, tmp / IMAGE_DIR)
                n = len(scene.views)
                summary = SettingSummary(setting.name, n, t_sum / n if setting.haze else None, cov_sum / n,
                                         time.perf_counter() - start)
                atomic_write_json(tmp / MANIFEST, jsonable(_manifest(scene, setting, config, synth, view_records,
                                                                     summary, fmt, source, point_colours,
                                                                     consistency), nonfinite="text"))
            summary.seconds = time.perf_counter() - start
            summaries.append(summary)
            clean_copy = out / setting.name / CLEAN_DIR
    atomic_write_json(out / INDEX, jsonable({
        "format": FORMAT, "version": __version__, "protocol": config.protocol, "seed": config.seed,
        "source": source, "settings": [s.to_dict() for s in summaries],
    }, nonfinite="text"))
    return summaries


def _input_sha256(view: View, image) -> str:
    """Checksum of the view's input: its image file, or the 8-bit PNG of an in-memory image."""
    if view.image is None and view.image_path is not None:
        return sha256_file(view.image_path)
    return hashlib.sha256(encode_png(image)).hexdigest()


def _write_scene_files(scene: Scene, tmp: Path, fmt: str, renamed: bool, clean_copy: Path | None) -> None:
    """Cameras, points, split, depths and masks in the input's format; clean images in ``clean/``.

    ``scene`` carries the setting's point colours.  The scene writer copies (or
    encodes) the clean images into ``images/``; they move to ``clean/`` and the
    caller then moves the degraded images into ``images/``.  When names must
    change to ``.png`` the writer gets the new names and the clean PNGs are
    written view by view instead.  Once one setting is complete (``clean_copy``,
    its ``clean/``), later settings copy its clean files rather than encode again.
    """
    def out_view(v: View) -> View:
        name = png_name(v.name) if renamed else v.name
        if clean_copy is not None:
            return replace(v, name=name, image=None, image_path=clean_copy / name)
        return replace(v, name=name)

    rename = png_name if renamed else str
    meta = replace(scene, views=tuple(out_view(v) for v in scene.views),
                   test_names=frozenset(rename(n) for n in scene.test_names))
    write_scene_into(meta, tmp, format=fmt)
    if renamed and clean_copy is None:
        shutil.rmtree(tmp / IMAGE_DIR)
    else:
        os.replace(tmp / IMAGE_DIR, tmp / CLEAN_DIR)
    if not renamed:
        _copy_original_model(scene, tmp)


def _copy_original_model(scene: Scene, tmp: Path) -> None:
    """Replace the rewritten COLMAP model by the input's own files, with ``scene.colors`` as point colours.

    Keeps the input's tracks and camera models: every file is copied byte for
    byte except the points file, whose RGB bytes (text: tokens) alone change.
    The rewritten model stays when the input's points are not ``scene.points``.
    """
    # An undistorted scene's own model still holds the distorted cameras: keep the rewritten (pinhole) one.
    if scene.source_format != "colmap" or scene.root is None or scene.metadata.get("downscale", 1) != 1 \
            or "undistorted" in scene.metadata:
        return
    src = Path(scene.root) / scene.metadata.get("sparse_dir", "sparse/0")
    if not src.is_dir():
        return
    files = {f.name: f.read_bytes() for f in sorted(src.iterdir()) if f.is_file()}
    for name, recolour in (("points3D.bin", _recolour_points3d_bin), ("points3D.txt", _recolour_points3d_txt)):
        if name in files:
            files[name] = recolour(files[name], scene.points, scene.colors)
            if files[name] is None:
                return
    dst = tmp / "sparse" / "0"
    shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for name, data in files.items():
        atomic_write_bytes(dst / name, data)


def _colour_rows(ids: np.ndarray, xyz: np.ndarray, points: np.ndarray) -> np.ndarray | None:
    """Row of each file point in ``points`` (points pair by ascending id, as read_colmap orders them), or None
    when the file's positions are not exactly ``points``."""
    rank = np.empty(len(ids), np.int64)
    rank[np.argsort(ids, kind="stable")] = np.arange(len(ids))
    if len(ids) != len(points) or not np.array_equal(xyz, points[rank]):
        return None
    return rank


def _recolour_points3d_bin(data: bytes, points: np.ndarray, colours: np.ndarray) -> bytes | None:
    """A COLMAP ``points3D.bin`` with the RGB bytes replaced; None when its points are not ``points``."""
    n = struct.unpack_from("<Q", data, 0)[0]
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3))
    rgb_at = np.empty(n, np.int64)
    at = 8
    for i in range(n):
        pid, x, y, z, _, _, _, _, track_length = COLMAP_POINT_HEAD.unpack_from(data, at)
        ids[i], xyz[i], rgb_at[i] = pid, (x, y, z), at + COLMAP_RGB_OFFSET
        at += COLMAP_POINT_HEAD.size + COLMAP_TRACK_ELEMENT_BYTES * track_length
    rows = _colour_rows(ids, xyz, points)
    if rows is None or at != len(data):
        return None
    out = np.frombuffer(data, np.uint8).copy()
    out[rgb_at[:, None] + np.arange(3)] = colours[rows]
    return out.tobytes()


def _recolour_points3d_txt(data: bytes, points: np.ndarray, colours: np.ndarray) -> bytes | None:
    """A COLMAP ``points3D.txt`` with the R G B tokens replaced; None when its points are not ``points``."""
    lines = data.decode().splitlines(keepends=True)
    rows = [i for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    tokens = [lines[i].split() for i in rows]
    ids = np.array([int(t[0]) for t in tokens], np.int64)
    xyz = np.array([[float(c) for c in t[1:4]] for t in tokens], np.float64).reshape(-1, 3)
    order = _colour_rows(ids, xyz, points)
    if order is None:
        return None
    for i, t, row in zip(rows, tokens, order):
        t[4:7] = (str(c) for c in colours[row])
        line = lines[i]
        lines[i] = " ".join(t) + line[len(line.rstrip("\r\n")):]
    return "".join(lines).encode()


def _manifest(scene: Scene, setting: WeatherSetting, config: SynthConfig, synth: Synthesizer, views: list,
              summary: SettingSummary, fmt: str, source: str | None, point_colours: DegradedPointColours,
              consistency: dict | None = None) -> dict:
    described = synth.describe(setting)
    if consistency is not None and "depth" in described:
        described["depth"]["consistency"] = consistency
    return {
        "format": FORMAT,
        "generator": "nimbus-synth degrade",
        "version": __version__,
        "setting": setting.name,
        "components": setting.description,
        "protocol": config.protocol,
        "seed": config.seed,
        "config": config.to_dict(),
        "input": {
            "source": source if source is not None else (str(scene.root) if scene.root else None),
            "format": scene.source_format,
            "written_format": fmt,
            "views": len(scene.views),
            "test_views": sorted(scene.test_names),
            "points": int(len(scene.points)),
            "point_colours": point_colours.describe(),
            "metadata": scene.metadata,
        },
        "scene": described,
        "summary": summary.to_dict(),
        "layers": {
            "transmission": "(H, W) float32 camera-to-surface transmission (haze)",
            "airlight": "(3,) float32 RGB airlight, display values (haze)",
            "depth": "(H, W) float32 z-depth used for haze, scene units, inf = sky (haze; only when estimated "
                     "by --depth recon / sparse / onnx, else see depths/ and sky/)",
            "rain": "(H, W) float32 additive rain radiance before attenuation (rain)",
            "snow": "(H, W) float32 snow alpha (snow)",
            "rain_depth": "(H, W) float32 z-depth of the dominant rain slice, inf = none, 0 = no depth (rain)",
            "snow_depth": "(H, W) float32 z-depth of the dominant snow slice, inf = none, 0 = no depth (snow)",
        },
        "views": views,
    }


def read_setting_manifest(folder: str | os.PathLike) -> dict:
    """The ``manifest.json`` of degraded setting folder ``folder``, checked against
    :class:`nimbus.schemas.SettingManifest`: NimbusError naming the file and the field otherwise."""
    from nimbus.schemas import SettingManifest, read_json_file

    return read_json_file(Path(folder) / MANIFEST, SettingManifest,
                          "regenerate the setting with `nimbus-synth degrade`")


def format_summary(summaries: Sequence[SettingSummary]) -> str:
    """The end-of-run table: setting, views, mean transmission, particle coverage, seconds."""
    lines = [f"{'setting':<8} {'views':>5} {'mean t':>7} {'particles':>9} {'seconds':>7}"]
    for s in summaries:
        t = f"{s.mean_transmission:.3f}" if s.mean_transmission is not None else "-"
        lines.append(f"{s.setting:<8} {s.views:>5} {t:>7} {s.particle_coverage:>8.1%} {s.seconds:>7.1f}")
    return "\n".join(lines)
