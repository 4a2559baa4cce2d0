"""Built-in procedural scenes with exact ground truth.

No public weather dataset can be downloaded, and a weather benchmark needs exact
depth, so Nimbus renders its own clean scenes with an analytic ray caster
(:mod:`nimbus.data.builtin.raycast`): world-space procedural textures
(:mod:`~nimbus.data.builtin.textures`), view-independent Lambert shading,
supersampled anti-aliasing, and a backdrop sphere that closes the world, so
every pixel has a finite depth.

Scenes (:mod:`~nimbus.data.builtin.scenes`, :mod:`~nimbus.data.builtin.tabletop`)
    ``garden``    360-degree orbit around a garden table (Mip-NeRF360 garden / bicycle style);
                  z-depth from about 1 m (a tree crown, bushes) to 93 m (backdrop).
    ``street``    forward-facing camera grid looking down a 100 m street (Deblur-NeRF factory / LLFF style);
                  z-depth from about 1.9 m (crates) to 157 m (backdrop).
    ``tabletop``  indoor orbit at 0.65 to 1.4 m around a bonsai on a table in a furnished room
                  (Mip-NeRF360 bonsai / counter / kitchen style); the backdrop (and sky mask) is only
                  what the window shows.

Sizes (:data:`SIZES`)
    ``tiny``      64 x 48 px, 16 views, 2 x 2 samples per pixel (CI; about 0.5 s)
    ``compact``   128 x 96 px, 40 views, 2 x 2 samples, the dense points capped at 12,000 (the
                  README's main job: the smallest size where 3DGS beats rain and snow, see
                  docs/benchmark.md)
    ``small``     240 x 180 px, 40 views, 3 x 3 samples (COLMAP registers every view)
    ``standard``  320 x 240 px, 48 views, 2 x 2 samples
    Supersampling is adaptive (:class:`~nimbus.data.builtin.raycast.RenderSettings`):
    every sample is traced, pixels on edges or with local contrast are shaded at every
    sample, flat ones at their centre.

Outputs
    Views are named ``000.png``, ``001.png``, ...  Each carries the image (float32
    (H, W, 3) in [0, 1]), the z-depth of the ray through the pixel centre (float32
    (H, W), finite) and a sky mask (bool (H, W), True where that ray hits the sky /
    backdrop; indoors, only through the window).  The test split follows the LLFF rule (every 8th view: 000, 008, ...).
    Sparse points come from unprojected depth maps (:mod:`~nimbus.data.builtin.points`).
    World up is +z; units are metres.

Determinism
    The same (scene, size, seed) gives bit-identical images, depths, sky masks, points
    and files.  The seed shifts every texture and jitters object positions
    (centimetres to decimetres) and camera poses (a few centimetres, a fraction of a
    degree), and the orbit's starting angle for ``garden`` and ``tabletop`` (whose
    tree is also grown from the seed).
"""

from __future__ import annotations

import dataclasses
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from nimbus.data.builtin.points import PointCloudConfig, sample_points
from nimbus.data.builtin.raycast import RenderSettings, render_view
from nimbus.data.builtin.scenes import GardenConfig, StreetConfig
from nimbus.data.builtin.tabletop import TabletopConfig
from nimbus.data.scene import Scene, View, llff_test_names
from nimbus.errors import NimbusError

GENERATOR = "nimbus.data.builtin"


@dataclass(frozen=True)
class SizePreset:
    """Image size, view count and anti-aliasing of a built-in scene.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    n_views : int
        Number of cameras.
    samples_per_axis : int
        Supersampling: ``samples_per_axis ** 2`` colour samples per pixel on a regular grid
        (adaptive: see :class:`~nimbus.data.builtin.raycast.RenderSettings`).
    points : PointCloudConfig
        How the sparse "SfM" points are sampled.  SfM on the full-resolution photos of a
        real capture returns on the order of 10^5 points (about a thousand per view); the
        ``small`` and ``standard`` scenes sample at that density (every training view,
        every 2nd pixel, merged in voxels of 0.5 % of the median depth, the textured
        backdrop included), which is what lets 3DGS reach its usual quality in a short
        schedule.  ``tiny`` keeps a sparse
        cloud (a few thousand points) so CI stays fast.
    """

    width: int
    height: int
    n_views: int
    samples_per_axis: int
    points: PointCloudConfig = PointCloudConfig()

    @property
    def render_settings(self) -> RenderSettings:
        return RenderSettings(samples_per_axis=self.samples_per_axis)


_DENSE_POINTS = PointCloudConfig(view_stride=1, pixel_stride=2, voxel_fraction=0.005, max_points=40_000,
                                 include_backdrop=True)

SIZES: dict[str, SizePreset] = {
    "tiny": SizePreset(64, 48, 16, 2),
    "compact": SizePreset(128, 96, 40, 2, dataclasses.replace(_DENSE_POINTS, max_points=12_000)),
    "small": SizePreset(240, 180, 40, 3, _DENSE_POINTS),
    "standard": SizePreset(320, 240, 48, 2, _DENSE_POINTS),
}


@dataclass(frozen=True)
class BuiltinScene:
    """A registered scene: its name, a one-line description and its config (geometry + camera rig)."""

    name: str
    description: str
    config: GardenConfig | StreetConfig | TabletopConfig


SCENES: dict[str, BuiltinScene] = {
    s.name: s for s in (
        BuiltinScene("garden", "360-degree orbit around a garden table: lawn, patio, bushes, trees, shed, hills "
                               "and sky (Mip-NeRF360 garden/bicycle style)", GardenConfig()),
        BuiltinScene("street", "forward-facing camera grid looking down a 100 m street: façades, cars, crates, "
                               "lamp posts, skyline (Deblur-NeRF factory / LLFF style)", StreetConfig()),
        BuiltinScene("tabletop", "indoor orbit at 1.1 to 2.3 object sizes around a bonsai on a table in a furnished "
                                 "room with a window (Mip-NeRF360 bonsai / counter / kitchen style)",
                     TabletopConfig()),
    )
}

#: Default number of render threads (the development machine has two cores).
RENDER_WORKERS = 2


def list_scenes() -> list[str]:
    """Names of the built-in scenes, sorted."""
    return sorted(SCENES)


def get_scene(name: str) -> BuiltinScene:
    """The registered scene ``name``; an unknown name raises :class:`NimbusError` listing the valid ones."""
    if name not in SCENES:
        raise NimbusError(f"unknown built-in scene {name!r}; choose one of: {', '.join(list_scenes())} "
                          "(see `nimbus-synth scene --list`)")
    return SCENES[name]


def get_size(size: str) -> SizePreset:
    if size not in SIZES:
        raise NimbusError(f"unknown scene size {size!r}; choose one of: {', '.join(SIZES)}")
    return SIZES[size]


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise NimbusError(f"seed must be a non-negative integer, got {seed!r}")
    return seed


def manifest(name: str, size: str, seed: int, image_count: int) -> dict:
    """Everything that determines a built-in scene's output (no timestamps: same inputs, same bytes)."""
    from nimbus import __version__

    sc, preset = get_scene(name), get_size(size)
    world = sc.config.world(seed)
    return {
        "generator": GENERATOR,
        "scene": name,
        "description": sc.description,
        "size": size,
        "size_preset": asdict(preset),
        "render_settings": asdict(preset.render_settings),
        "scene_config": asdict(sc.config),
        "lighting": asdict(world.lighting),
        "points_config": asdict(preset.points),
        "seed": seed,
        "nimbus_version": __version__,
        "image_count": image_count,
        "conventions": {
            "world_up": [0.0, 0.0, 1.0],
            "units": "metres",
            "depth": "float32 z-depth of the ray through the pixel centre (finite; backdrop is a surface)",
            "sky": "True where the pixel-centre ray hits the sky / backdrop (indoors: through the window)",
            "test_split": "LLFF rule: every 8th view by name (000, 008, ...)",
        },
    }


def render_builtin(name: str, size: str = "tiny", seed: int = 0, progress: bool = False,
                   workers: int = RENDER_WORKERS) -> Scene:
    """Render a built-in scene in memory.

    Parameters
    ----------
    name : str
        One of :func:`list_scenes`.
    size : str
        ``"tiny"``, ``"small"`` or ``"standard"`` (see :data:`SIZES`).
    seed : int
        Non-negative; the same seed gives bit-identical output.
    progress : bool
        Show a per-view tqdm bar on stderr.
    workers : int
        Views rendered concurrently by threads (default :data:`RENDER_WORKERS`); the
        output is identical for any value.

    Returns
    -------
    Scene
        ``source_format="builtin"``, views with in-memory image / depth / sky mask, the LLFF
        test split, sparse points, and in ``metadata`` the :func:`manifest` plus
        ``depth_range`` ([min, max] z-depth over all views, metres) and ``sparse_points``.
    """
    from tqdm import tqdm

    sc, preset, seed = get_scene(name), get_size(size), _check_seed(seed)
    world = sc.config.world(seed)
    cameras = sc.config.cameras(preset.n_views, preset.width, preset.height, seed)
    workers = max(1, min(int(workers), len(cameras)))
    # Views are independent and numpy releases the GIL in its array loops, so threads overlap;
    # results are collected in view order, so the output does not depend on the thread count.
    with ThreadPoolExecutor(workers) as pool, tqdm(total=len(cameras), desc=f"render {name} ({size})", unit="view",
                                                   file=sys.stderr, disable=not progress, leave=False) as bar:
        views = []
        for i, r in enumerate(pool.map(lambda cam: render_view(world, cam, preset.render_settings), cameras)):
            views.append(View(f"{i:03d}.png", cameras[i], image=r.image, depth=r.depth, sky=r.sky))
            bar.update()
    names = [v.name for v in views]
    test = llff_test_names(names)
    train = [v for v in views if v.name not in set(test)]
    points, colors = sample_points([v.camera for v in train], [v.image for v in train], [v.depth for v in train],
                                   [v.sky for v in train], preset.points, seed)
    meta = manifest(name, size, seed, len(views))
    meta["depth_range"] = [float(min(v.depth.min() for v in views)), float(max(v.depth.max() for v in views))]
    meta["sparse_points"] = int(len(points))
    return Scene(tuple(views), frozenset(test), points, colors, None, "builtin", meta)


def write_builtin(name: str, out: str | Path, size: str = "tiny", seed: int = 0, overwrite: bool = False,
                  progress: bool = False, workers: int = RENDER_WORKERS) -> Path:
    """Render a built-in scene and write it as a COLMAP scene folder, atomically.

    The folder holds what :func:`nimbus.data.io.write_scene_into` writes (``images/``,
    ``sparse/0``, ``depths/<stem>.npy``, ``sky/<stem>.png``, ``train_list.txt``,
    ``test_list.txt``) plus ``manifest.json``; it appears only when complete.  A
    non-empty ``out`` is refused unless ``overwrite``.  ``progress`` and ``workers`` are as
    in :func:`render_builtin`.

    Returns
    -------
    Path
        ``out``.
    """
    from nimbus.data.io import write_scene_into
    from nimbus.utils.fs import atomic_dir, atomic_write_json, check_output_dir

    get_scene(name), get_size(size), _check_seed(seed)
    check_output_dir(out, overwrite)  # fail before a long render, not after
    scene = render_builtin(name, size, seed, progress, workers)
    with atomic_dir(out, overwrite) as tmp:
        write_scene_into(scene, tmp, format="colmap")
        atomic_write_json(tmp / "manifest.json", scene.metadata)
    return Path(out)


__all__ = ["RENDER_WORKERS", "SCENES", "SIZES", "BuiltinScene", "SizePreset", "get_scene", "get_size",
           "list_scenes", "manifest", "render_builtin", "write_builtin"]
