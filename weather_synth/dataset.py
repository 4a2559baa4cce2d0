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
                                 when no image had to be renamed to .png)
        depths/, masks/          the scene's depth maps and masks, when it has them
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

So 3DGS, gsplat or nerfstudio train on ``OUT/H+R`` directly and a benchmark
scores renders against ``clean/``.  Views are processed one at a time (memory
does not grow with the number of views); every setting folder is written
atomically (a temporary folder renamed into place when complete), so an
interrupted run leaves only complete settings.  The same input, config and
seed give the same bytes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

from nimbus import __version__
from nimbus.data.images import encode_png
from nimbus.data.io import SCENE_FORMATS, check_not_input, write_scene_into
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir, atomic_write_bytes, atomic_write_json, check_output_dir, sha256_file
from weather_synth.archive import encode_layers, jsonable
from weather_synth.config import SynthConfig
from weather_synth.settings import WeatherSetting
from weather_synth.synth import Synthesizer

FORMAT = "nimbus-synth-degrade/1"
MANIFEST = "manifest.json"
INDEX = "index.json"
LAYER_DIR = "layers"
CLEAN_DIR = "clean"
IMAGE_DIR = "images"


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


def png_name(name: str) -> str:
    """The output image name of a view: unchanged when it ends in ``.png``, else with ``.png``."""
    return name if name.endswith(".png") else str(Path(name).with_suffix(".png").as_posix())


def layer_name(name: str) -> str:
    return str(Path(LAYER_DIR, Path(png_name(name)).with_suffix(".npz")).as_posix())


def degrade_scene(scene: Scene, out: str | os.PathLike, settings: Sequence[WeatherSetting], config: SynthConfig,
                  overwrite: bool = False, progress: bool = True, source: str | None = None) -> list[SettingSummary]:
    """Degrade ``scene`` in every setting and write the dataset ``out`` (module docstring).

    Parameters
    ----------
    scene : Scene
    out : path
        Output folder; refused when non-empty unless ``overwrite`` (then each
        written setting folder replaces its old version atomically).
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
    from tqdm import tqdm

    if not settings:
        raise NimbusError("no weather settings given; use e.g. --weather all")
    if not scene.views:
        raise NimbusError("the scene has zero views; nothing to degrade")
    out = check_output_dir(out, overwrite)
    check_not_input(scene, out)
    fmt = scene.source_format if scene.source_format in SCENE_FORMATS else "colmap"
    renamed = any(png_name(v.name) != v.name for v in scene.views)
    names = [png_name(v.name) for v in scene.views]
    if len(set(names)) != len(names):
        raise NimbusError("views would share an output file name once written as .png; rename the images")
    summaries = []
    input_sums: dict[str, str] = {}
    clean_copy: Path | None = None  # clean/ of the first finished setting: later settings copy its files
    with Synthesizer(scene, config) as synth:
        synth.prepare(list(settings))
        for setting in settings:
            start = time.perf_counter()
            with atomic_dir(out / setting.name, overwrite=True) as tmp:
                t_sum, cov_sum, view_records = 0.0, 0.0, []
                _write_scene_files(scene, tmp, fmt, renamed, clean_copy)
                bar = tqdm(scene.views, desc=f"{setting.name:<6}", unit="view", file=sys.stderr,
                           disable=not progress, leave=True, dynamic_ncols=True)
                for view in bar:
                    J = view.load_image()
                    if view.name not in input_sums:
                        input_sums[view.name] = _input_sha256(view, J)
                    res = synth.degrade(view, setting, J)
                    out_name = png_name(view.name)
                    image_bytes = encode_png(res.image)
                    atomic_write_bytes(tmp / IMAGE_DIR / out_name, image_bytes)
                    if renamed and clean_copy is None:
                        atomic_write_bytes(tmp / CLEAN_DIR / out_name, encode_png(J))
                    layer_bytes = encode_layers(res.layers, config.layer_compression)
                    atomic_write_bytes(tmp / layer_name(view.name), layer_bytes)
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
                n = len(scene.views)
                summary = SettingSummary(setting.name, n, t_sum / n if setting.haze else None, cov_sum / n,
                                         time.perf_counter() - start)
                atomic_write_json(tmp / MANIFEST, jsonable(_manifest(scene, setting, config, synth, view_records,
                                                                     summary, fmt, source)))
            summary.seconds = time.perf_counter() - start
            summaries.append(summary)
            clean_copy = out / setting.name / CLEAN_DIR
    atomic_write_json(out / INDEX, jsonable({
        "format": FORMAT, "version": __version__, "protocol": config.protocol, "seed": config.seed,
        "source": source, "settings": [s.to_dict() for s in summaries],
    }))
    return summaries


def _input_sha256(view: View, image) -> str:
    """Checksum of the view's input: its image file, or the 8-bit PNG of an in-memory image."""
    if view.image is None and view.image_path is not None:
        return sha256_file(view.image_path)
    return hashlib.sha256(encode_png(image)).hexdigest()


def _write_scene_files(scene: Scene, tmp: Path, fmt: str, renamed: bool, clean_copy: Path | None) -> None:
    """Cameras, points, split, depths and masks in the input's format; clean images in ``clean/``.

    The scene writer copies (or encodes) the clean images into ``images/``; they
    move to ``clean/`` and the degraded images take their place.  When names must
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
    """Replace the rewritten COLMAP model by the input's own files (keeps tracks and camera models)."""
    if scene.source_format != "colmap" or scene.root is None or scene.metadata.get("downscale", 1) != 1:
        return
    src = Path(scene.root) / scene.metadata.get("sparse_dir", "sparse/0")
    if not src.is_dir():
        return
    dst = tmp / "sparse" / "0"
    shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for f in sorted(src.iterdir()):
        if f.is_file():
            shutil.copyfile(f, dst / f.name)


def _manifest(scene: Scene, setting: WeatherSetting, config: SynthConfig, synth: Synthesizer, views: list,
              summary: SettingSummary, fmt: str, source: str | None) -> dict:
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
            "metadata": scene.metadata,
        },
        "scene": synth.describe(),
        "summary": summary.to_dict(),
        "layers": {
            "transmission": "(H, W) float32 camera-to-surface transmission (haze)",
            "airlight": "(3,) float32 RGB airlight, display values (haze)",
            "depth": "(H, W) float32 z-depth used for haze, scene units, inf = sky (haze; only when estimated "
                     "by --depth sparse / onnx, else see depths/ and masks/)",
            "rain": "(H, W) float32 additive rain radiance before attenuation (rain)",
            "snow": "(H, W) float32 snow alpha (snow)",
            "rain_depth": "(H, W) float32 z-depth of the dominant rain slice, inf = none, 0 = no depth (rain)",
            "snow_depth": "(H, W) float32 z-depth of the dominant snow slice, inf = none, 0 = no depth (snow)",
        },
        "views": views,
    }


def format_summary(summaries: Sequence[SettingSummary]) -> str:
    """The end-of-run table: setting, views, mean transmission, particle coverage, seconds."""
    lines = [f"{'setting':<8} {'views':>5} {'mean t':>7} {'particles':>9} {'seconds':>7}"]
    for s in summaries:
        t = f"{s.mean_transmission:.3f}" if s.mean_transmission is not None else "-"
        lines.append(f"{s.setting:<8} {s.views:>5} {t:>7} {s.particle_coverage:>8.1%} {s.seconds:>7.1f}")
    return "\n".join(lines)
