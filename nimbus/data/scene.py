"""The one scene model: views, splits and sparse points.

Every reader (COLMAP, transforms.json, built-in scenes) returns a :class:`Scene`
and every writer takes one, so the synthesizer, the trainers and the benchmark
never care where a scene came from.  Camera and image conventions are in
:mod:`nimbus.data.camera` and :mod:`nimbus.data.images`.

Images are loaded lazily from ``View.image_path`` (so a scene of hundreds of
views costs nothing until a view is used) unless the view carries them in memory.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath
from typing import Iterable, Sequence

import numpy as np

from nimbus.data.camera import Camera
from nimbus.data.images import read_depth, read_image, read_mask
from nimbus.errors import NimbusError
from nimbus.utils.fs import check_name_length, confined_path


@dataclass(frozen=True, eq=False)
class View:
    """One photo and the camera that took it.

    Attributes
    ----------
    name : str
        Image file name relative to the scene's image folder (e.g. ``"000.png"``);
        unique within a scene; matches COLMAP's image name.
    camera : Camera
    image_path : Path or None
        File to load the RGB image from (when ``image`` is None).
    depth_path : Path or None
        Optional z-depth map (``.npy`` / 16-bit PNG).
    mask_path : Path or None
        Optional validity mask (PNG; non-zero = the pixel counts, 0 = ignore it in training
        and scoring), the ``masks/`` / nerfstudio ``mask_path`` convention of the peers.
    sky_path : Path or None
        Optional sky mask (PNG; non-zero = the pixel sees the sky / backdrop, at infinite
        depth), written for built-in scenes in ``sky/``; used by haze synthesis only.
    image : ndarray or None
        In-memory float32 (H, W, 3) image in [0, 1]; takes precedence over ``image_path``.
    depth, mask, sky : ndarray or None
        In-memory z-depth (float32 (H, W), inf where there is no surface), bool validity
        mask and bool sky mask; take precedence over the paths.
    """

    name: str
    camera: Camera
    image_path: Path | None = None
    depth_path: Path | None = None
    mask_path: Path | None = None
    image: np.ndarray | None = None
    depth: np.ndarray | None = None
    mask: np.ndarray | None = None
    sky_path: Path | None = None
    sky: np.ndarray | None = None

    def load_image(self) -> np.ndarray:
        """The RGB image, float32 (H, W, 3) in [0, 1], checked against the camera size."""
        if self.image is not None:
            img = self.image
            where = f"view {self.name}"
        elif self.image_path is not None:
            img = read_image(self.image_path)
            where = f"image {self.image_path}"
        else:
            raise NimbusError(f"view {self.name} has no image")
        h, w = img.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise NimbusError(
                f"{where} is {w}x{h} but its camera is {self.camera.width}x{self.camera.height}; "
                "use the image folder that matches the sparse model (e.g. images_4 with --downscale 4)"
            )
        return img

    def load_depth(self) -> np.ndarray | None:
        """The z-depth map, float32 (H, W), or None when the view has none."""
        if self.depth is not None:
            return self.depth
        if self.depth_path is None:
            return None
        d = read_depth(self.depth_path)
        if d.shape != (self.camera.height, self.camera.width):
            raise NimbusError(f"depth map {self.depth_path} has shape {d.shape}; its camera is "
                              f"{self.camera.width}x{self.camera.height}")
        return d

    def load_mask(self) -> np.ndarray | None:
        """The validity mask, bool (H, W) (True = use the pixel), or None when every pixel counts."""
        return self._load_bool(self.mask, self.mask_path, "mask")

    def load_sky(self) -> np.ndarray | None:
        """The sky mask, bool (H, W) (True = sky / backdrop), or None when the view has none."""
        return self._load_bool(self.sky, self.sky_path, "sky mask")

    def _load_bool(self, array: np.ndarray | None, path: Path | None, what: str) -> np.ndarray | None:
        if array is not None:
            return array
        if path is None:
            return None
        m = read_mask(path)
        if m.shape != (self.camera.height, self.camera.width):
            raise NimbusError(f"{what} {path} is {m.shape[1]}x{m.shape[0]}; its camera is "
                              f"{self.camera.width}x{self.camera.height}")
        return m

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def has_depth(self) -> bool:
        return self.depth is not None or self.depth_path is not None


@dataclass(frozen=True, eq=False)
class Scene:
    """A multi-view scene.

    Attributes
    ----------
    views : tuple of View
        All views, sorted by name.
    test_names : frozenset of str
        Names of held-out views; every other view is a training view.
    points : ndarray, shape (N, 3), float64
        Sparse 3D points (SfM-style), possibly empty.
    colors : ndarray, shape (N, 3), uint8
        Their colours.
    root : Path or None
        Folder the scene was read from.
    source_format : str
        ``"colmap"``, ``"transforms"``, ``"builtin"`` or ``"memory"``.
    metadata : dict
        Free-form provenance (e.g. the built-in generator's manifest).
    """

    views: tuple[View, ...]
    test_names: frozenset[str] = frozenset()
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    root: Path | None = None
    source_format: str = "memory"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        views = tuple(sorted(self.views, key=lambda v: v.name))
        names = [v.name for v in views]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise NimbusError(f"duplicate view names in scene: {dup[:5]}")
        unknown = set(self.test_names) - set(names)
        if unknown:
            raise NimbusError(f"test split names views that are not in the scene: {sorted(unknown)[:5]}")
        pts = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        cols = np.asarray(self.colors, dtype=np.uint8).reshape(-1, 3)
        if len(pts) != len(cols):
            raise NimbusError(f"{len(pts)} sparse points but {len(cols)} colours")
        object.__setattr__(self, "views", views)
        object.__setattr__(self, "test_names", frozenset(self.test_names))
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "colors", cols)

    # --- access -------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.views)

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    def view(self, name: str) -> View:
        for v in self.views:
            if v.name == name:
                return v
        raise NimbusError(f"scene has no view named {name!r}")

    @property
    def train_views(self) -> list[View]:
        return [v for v in self.views if v.name not in self.test_names]

    @property
    def test_views(self) -> list[View]:
        return [v for v in self.views if v.name in self.test_names]

    @property
    def camera_centers(self) -> np.ndarray:
        return np.stack([v.camera.center for v in self.views]) if self.views else np.zeros((0, 3))

    @property
    def extent(self) -> float:
        """Scene extent as 3DGS defines it: 1.1 x the largest distance of a camera centre from their mean.

        Learning rates and densification thresholds scale with it.  For a single
        view (or co-located cameras) it falls back to the sparse points' spread, then to 1.
        """
        c = self.camera_centers
        radius = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
        if radius < 1e-8 and len(self.points):
            radius = float(np.max(np.linalg.norm(self.points - self.points.mean(0), axis=1))) / 1.1
        return 1.1 * radius if radius > 1e-8 else 1.0

    # --- derived scenes ------------------------------------------------------------
    def with_views(self, views: Iterable[View]) -> "Scene":
        views = tuple(views)
        keep = {v.name for v in views}
        return replace(self, views=views, test_names=frozenset(n for n in self.test_names if n in keep))

    def with_split(self, test_names: Iterable[str]) -> "Scene":
        return replace(self, test_names=frozenset(test_names))


def llff_test_names(names: Sequence[str], every: int = 8) -> list[str]:
    """The LLFF / Mip-NeRF360 hold-out rule: every ``every``-th image of the sorted names (0, 8, 16, ...)."""
    return [n for i, n in enumerate(sorted(names)) if i % every == 0]


def scene_file(root: str | os.PathLike, name: object, what: str, folder: str | os.PathLike = "") -> Path:
    """``root / folder / name`` for a file name read from a scene file, refused unless it stays in the scene.

    This is the one rule every reader applies to a name it did not make up itself: COLMAP image
    names, ``transforms.json`` ``file_path`` / ``mask_path`` / ``depth_file_path`` /
    ``test_filenames`` / ``ply_file_path``, the split lists, and the depth and mask files found
    for a view.  The name must be a non-empty relative path (``/`` separators) without a ``..``
    component, and the file it names, with every symlink resolved, must lie inside the scene
    folder ``root`` (:func:`nimbus.utils.fs.confined_path`).  So a hostile ``/etc/passwd``,
    ``../../x/t.png`` or a link in ``images/`` that leads out can make Nimbus neither read outside
    the scene nor, through a view name, write outside an output folder.  (An image folder that is
    itself a link to elsewhere is refused too: copy the files into the scene.)

    Parameters
    ----------
    root : path
        The scene folder.
    name : object
        The name as read (anything but a ``str`` is refused).
    what : str
        What the name is and where it came from, for the message (``"image name in sparse/0/images.bin"``).
    folder : path
        Folder inside ``root`` the name is relative to (``"images"``); ``""`` for ``root`` itself.

    Returns
    -------
    Path
        ``root / folder / name`` as given (not resolved), so paths read back look as the user wrote them.
    """
    if not isinstance(name, str) or not name.strip() or "\x00" in name:
        raise NimbusError(f"{what}: {name!r} is not a file name; expected a relative path such as \"images/0001.png\"")
    pure = PurePosixPath(name)
    if pure.is_absolute() or ".." in pure.parts or Path(name).is_absolute():
        raise NimbusError(f"{what}: {name!r} points outside the scene folder {root}; names must be relative paths "
                          "inside the scene (no absolute paths, no '..'); fix the name or move the file into the scene")
    check_name_length(name, what)
    path = Path(root) / folder / name
    try:
        confined_path(root, path.relative_to(root), what)
    except NimbusError:
        raise NimbusError(f"{what}: {name!r} leads outside the scene folder {root} (through a link, to "
                          f"{path.resolve()}); copy the file into the scene instead of linking to it") from None
    return path


def read_split_lists(root: Path, names: Sequence[str]) -> frozenset[str] | None:
    """Test names from ``train_list.txt`` / ``test_list.txt`` in ``root``, or None if neither exists.

    Lists hold one image name per line (blank lines and ``#`` comments ignored); every name must
    be a view of the scene (and so a relative name inside it, see :func:`scene_file`).
    With only ``train_list.txt``, every other view is a test view.  A list that is a link leading
    out of the scene is refused before it is read: its lines, quoted in messages, could be any file's.
    """
    root = Path(root)
    train_f, test_f = root / "train_list.txt", root / "test_list.txt"
    if not train_f.is_file() and not test_f.is_file():
        return None
    known = set(names)

    def read(f: Path) -> list[str]:
        scene_file(root, f.name, f"split list {f.name}")
        try:
            lines = f.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError:
            raise NimbusError(f"{f} is not a UTF-8 text file; it should list one image name per line") from None
        items = [ln.strip() for ln in lines]
        items = [s for s in items if s and not s.startswith("#")]
        for s in items:
            scene_file(root, s, f"{f.name} entry")
        missing = [s for s in items if s not in known]
        if missing:
            raise NimbusError(f"{f} names images that are not in the scene: {missing[:5]}; fix the list")
        return items

    if test_f.is_file():
        test = set(read(test_f))
        if train_f.is_file():
            overlap = set(read(train_f)) & test
            if overlap:
                raise NimbusError(f"{train_f} and {test_f} share views: {sorted(overlap)[:5]}")
        return frozenset(test)
    return frozenset(known - set(read(train_f)))


def write_split_lists(scene: Scene, root: Path) -> None:
    from nimbus.utils.fs import atomic_write_text

    atomic_write_text(Path(root) / "train_list.txt", "".join(v.name + "\n" for v in scene.train_views))
    atomic_write_text(Path(root) / "test_list.txt", "".join(v.name + "\n" for v in scene.test_views))
