"""Where a benchmark scene comes from: a built-in scene, a scene folder, a photo folder or a degraded dataset tree.

``nimbus-bench run --scenes`` takes a comma list whose items are resolved here into :class:`SceneSource`:

built-in name (``garden``)
    Rendered into ``ROOT/scenes/<name>-<size>`` and degraded by the synthesiser, as always.
scene folder (COLMAP ``images/`` + ``sparse/0``, or ``transforms.json``)
    A clean capture.  Its views (``images_<N>/`` with ``--downscale N``) are copied once into
    ``ROOT/scenes/<folder>`` (``<folder>-images_<N>``) (what the clean ceiling trains on) and degraded from there
    with the run's settings and ``--depth auto`` (:data:`CAPTURE_DEPTH`).
photo folder (photos, no poses)
    Posed first by SfM (:func:`nimbus.data.sfm.run_sfm`, as ``nimbus-synth sfm``) into
    ``ROOT/sfm/<folder>-<hash>``, reused by a later run, then as a scene folder.
degraded dataset tree, ours
    What ``nimbus-synth degrade`` writes: ``index.json`` and one scene folder per setting
    (``H/``, ``H+R/``, ...), each with ``clean/``.  One scene, named after the tree's folder.
degraded dataset tree, the authors' layout (GitHub lyy-ovo/NimbusGS)
    One folder per setting, one folder per scene inside, each scene with ``images/`` (degraded),
    ``sparse/0``, ``clean/`` (or ``gt_clean/``) and ``input/`` (COLMAP's raw copy, not read).
    Settings are found by folder name: ``haze``, ``rain``, ``snow`` joined by ``_``, ``+`` or ``-``
    (``haze_rain_snow`` is ``H+R+S``), or our tokens (``H+R``).  Every scene of the tree is one
    benchmark scene, named after its folder.

A tree is scored against its ``clean/`` images as given: each of its settings is copied (its
``images/``, ``sparse/`` or ``transforms.json``, split lists and clean images; not ``input/``) into
``ROOT/data/<scene>-images/<SETTING>/`` with a :data:`LINKED` file that names the source.  Nothing is ever written into the user's folders; everything derived lies under
the benchmark root.  Tables and reports name an external scene by its folder name; its records
carry ``scene_path`` (the resolved folder given: the capture, the photo folder or the tree) and
``scene_hash`` (:func:`scene_hash`), and a root refuses a second scene of the same name with
another hash (:func:`register_sources`, :func:`benchmark.store.check_scene_hashes`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

from nimbus.errors import NimbusError

#: Kinds of :class:`SceneSource`.
BUILTIN, CAPTURE, PHOTOS, TREE = "builtin", "capture", "photos", "tree"
#: The file that stands for ``manifest.json`` in a setting folder copied from a user's tree.
LINKED = "linked.json"
SOURCES_DIR = "sources"
SFM_DIR = "sfm"
#: Depth source of a capture's synthesis (``nimbus-synth degrade --depth auto``): the scene's depth maps when
#: every view has one, else a quick 3DGS fit (``recon``).
CAPTURE_DEPTH = "auto"
#: Entries of a tree's scene folder that are copied into the root (``input/`` is COLMAP's raw copy: not read).
_TREE_ENTRIES = ("images", "sparse", "transforms.json", "train_list.txt", "test_list.txt", "masks", "depths")
_CLEAN_DIRS = ("clean", "gt_clean")
#: Files whose content (not only name and size) enters :func:`scene_hash`: the cameras and the split.
_CONTENT_HASHED = re.compile(r"(^|/)(sparse/.*|transforms[^/]*\.json|[^/]*_list\.txt)$")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")


@dataclass(frozen=True)
class SceneSource:
    """One benchmark scene and where its data comes from (module docstring).

    Attributes
    ----------
    name : str
        The name tables give it: the built-in name or the folder's name.
    kind : {"builtin", "capture", "photos", "tree"}
    size : str
        The second part of its data name (``<name>-<size>``): the built-in size, or ``images`` /
        ``images_<N>`` (the image folder read) for a folder.
    path : str
        Resolved folder given on the command line ("" for a built-in scene).
    scene_hash : str
        :func:`scene_hash` of ``path`` ("" for a built-in scene until its folder is rendered).
    downscale : int
        ``images_<N>`` of a capture or photo folder (1: ``images/``).
    settings : tuple of (str, str)
        A tree's settings: setting name -> resolved scene folder of that setting.
    """

    name: str
    kind: str
    size: str
    path: str = ""
    scene_hash: str = ""
    downscale: int = 1
    settings: tuple[tuple[str, str], ...] = ()

    @property
    def data_name(self) -> str:
        from benchmark.store import data_name_of

        return data_name_of(self.name, self.size)

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "settings": dict(self.settings)}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneSource":
        return cls(d["name"], d["kind"], d["size"], d.get("path", ""), d.get("scene_hash", ""),
                   int(d.get("downscale", 1)), tuple(sorted(d.get("settings", {}).items())))

    def record_fields(self) -> dict:
        """``scene_path``, ``scene_hash`` and ``scene_kind`` as every record of this scene carries them."""
        return {"scene_path": self.path, "scene_hash": self.scene_hash, "scene_kind": self.kind}


# --- hashing --------------------------------------------------------------------------------
def scene_hash(folder: str | os.PathLike, skip: Iterable[str] = ("input",)) -> str:
    """A cheap content hash of a scene folder: sha256 (hex) over its files, in sorted path order.

    Each file contributes its path relative to ``folder`` and its size; the camera files
    (``sparse/**``, ``transforms*.json``) and the split lists (``*_list.txt``) also their bytes.
    Images are not read: a photo rewritten with other pixels but the same size is not told apart
    (mtimes are left out so that a copied dataset keeps its hash).  Hidden files and the top-level
    folders in ``skip`` (COLMAP's raw ``input/``) are left out; links are followed.
    """
    folder = Path(folder)
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=True):
        rel_dir = Path(dirpath).relative_to(folder)
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".")
                             and not (rel_dir == Path(".") and d in skip))
        for f in sorted(filenames):
            if f.startswith("."):
                continue
            p = Path(dirpath) / f
            rel = (rel_dir / f).as_posix()
            h.update(f"{rel}\0{p.stat().st_size}\0".encode())
            if _CONTENT_HASHED.search(rel):
                h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


# --- resolving --------------------------------------------------------------------------------
def setting_from_folder(name: str) -> str | None:
    """Our setting name (``H+R``) for a tree's setting folder name (``haze_rain``, ``H+R``), None if it is none."""
    from weather_synth.settings import parse_setting

    text = re.sub(r"[\s_\-]+", "+", name.strip())
    try:
        return parse_setting(text).name
    except NimbusError:
        return None


def _check_name(name: str, path: Path) -> str:
    from nimbus.data.builtin import SIZES, list_scenes

    if not _NAME.match(name):
        raise NimbusError(f"{path}: its folder name {name!r} names the scene in tables and run folders and must be "
                          "letters, digits, '.', '_', '+' or '-' (not starting with one of the last four); rename "
                          "the folder or link it under such a name")
    if name in {f"{s}-{z}" for s in list_scenes() for z in SIZES}:
        raise NimbusError(f"{path}: its folder name {name!r} is the data name of a built-in scene; rename the folder "
                          "or link it under another name")
    return name


def _image_folder(downscale: int) -> str:
    return "images" if downscale == 1 else f"images_{downscale}"


def _is_scene(folder: Path) -> bool:
    from nimbus.data.colmap import find_sparse_dir

    return folder.is_dir() and (find_sparse_dir(folder) is not None or (folder / "transforms.json").is_file()
                                or (folder / "transforms_train.json").is_file())


def _authors_tree(folder: Path) -> dict[str, dict[str, Path]]:
    """scene name -> setting -> scene folder, for a tree in the authors' layout (empty when it is not one)."""
    scenes: dict[str, dict[str, Path]] = {}
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        setting = setting_from_folder(sub.name)
        if setting is None:
            continue
        for scene in sorted(p for p in sub.iterdir() if _is_scene(p)):
            scenes.setdefault(scene.name, {})[setting] = scene
    return scenes


def _our_tree(folder: Path) -> dict[str, Path]:
    """setting -> setting folder of a ``nimbus-synth degrade`` output (empty when it is not one)."""
    from weather_synth.dataset import INDEX, MANIFEST

    if not (folder / INDEX).is_file():
        return {}
    return {p.name: p for p in sorted(folder.iterdir())
            if p.is_dir() and (p / MANIFEST).is_file() and setting_from_folder(p.name) == p.name}


def _clean_dir(scene: Path) -> Path | None:
    return next((scene / d for d in _CLEAN_DIRS if (scene / d).is_dir()), None)


def resolve_scenes(items: Sequence[str], size: str, downscale: int = 1,
                   log: Callable[[str], None] | None = None) -> list[SceneSource]:
    """The :class:`SceneSource` of each ``--scenes`` item (a tree in the authors' layout gives one per scene).

    An item is a built-in scene name when it is one (without a path separator: ``./garden`` is a
    folder), else a folder.  ``size`` is the built-in scenes' size; ``downscale`` picks ``images_<N>`` of scene and
    photo folders (a tree is read as it is: ``images/`` and ``clean/``).

    Raises
    ------
    NimbusError
        An unknown built-in name, a missing folder, a folder that is none of the module docstring's
        kinds, a scene folder without ``images_<N>``, a tree scene without ``clean/``, or a folder name
        that cannot name a scene.
    """
    from nimbus.data.builtin import get_scene, get_size, list_scenes
    from nimbus.data.scene_files import list_images

    say = log or (lambda _m: None)
    out: list[SceneSource] = []
    for item in items:
        path = Path(item).expanduser()
        if os.sep not in item and item in list_scenes():  # a folder of that name in the working directory: ./NAME
            get_size(size)
            out.append(SceneSource(item, BUILTIN, size))
            continue
        if os.sep not in item and not path.is_dir():
            get_scene(item)  # the unknown-name error, listing the built-in scenes
        if not path.exists():
            raise NimbusError(f"--scenes: {item} does not exist; give a built-in scene ({', '.join(list_scenes())}) "
                              "or a scene, photo or dataset folder")
        if not path.is_dir():
            raise NimbusError(f"--scenes: {item} is a file; give a scene, photo or dataset folder")
        path = path.resolve()
        ours, authors = _our_tree(path), _authors_tree(path)
        if ours:
            name = _check_name(path.name, path)
            missing = [s for s, p in ours.items() if _clean_dir(p) is None]
            if missing:
                raise NimbusError(f"{path}: setting(s) {', '.join(missing)} have no clean/ folder to score against")
            out.append(SceneSource(name, TREE, "images", str(path), scene_hash(path),
                                   settings=tuple((s, str(p)) for s, p in sorted(ours.items()))))
            say(f"{path}: a degraded dataset (nimbus-synth degrade), settings {', '.join(ours)}")
            continue
        if authors:
            for scene, settings in authors.items():
                name = _check_name(scene, path / next(iter(settings.values())))
                missing = [str(p) for p in settings.values() if _clean_dir(p) is None]
                if missing:
                    raise NimbusError(f"{missing[0]} has no clean/ (or gt_clean/) folder of clean images to score "
                                      "against; a degraded dataset tree needs one in every scene folder")
                h = hashlib.sha256("".join(f"{s}\0{scene_hash(p)}\0" for s, p in sorted(settings.items()))
                                   .encode()).hexdigest()
                out.append(SceneSource(name, TREE, "images", str(path), h,
                                       settings=tuple((s, str(p)) for s, p in sorted(settings.items()))))
            say(f"{path}: a degraded dataset in the authors' layout, {len(authors)} scene(s) "
                f"({', '.join(authors)})")
            continue
        name = _check_name(path.name, path)
        if _is_scene(path):
            if downscale != 1 and not (path / _image_folder(downscale)).is_dir():
                raise NimbusError(f"--downscale {downscale}: {path} has no {_image_folder(downscale)}/ folder; "
                                  "give a --downscale it has, or 1")
            out.append(SceneSource(name, CAPTURE, _image_folder(downscale), str(path), scene_hash(path),
                                   downscale=downscale))
            continue
        if list_images(path) or list_images(path / "images"):
            if downscale != 1:
                raise NimbusError(f"--downscale {downscale} does not apply to a photo folder ({path}): SfM poses the "
                                  "photos as they are; pass --downscale 1, or pose them first with nimbus-synth sfm "
                                  "and give the scene folder")
            out.append(SceneSource(name, PHOTOS, "images", str(path), scene_hash(path)))
            continue
        raise NimbusError(f"--scenes: {path} is neither a scene folder (images/ + sparse/0, or transforms.json), a "
                          "photo folder nor a degraded dataset tree (one folder per setting, e.g. haze/, rain/)")
    names = [s.data_name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise NimbusError(f"--scenes names two different scenes {dup[0].rsplit('-', 1)[0]!r}; tables name a scene "
                          "by its folder, so give folders different names (e.g. by linking one under another name)")
    return out


# --- the root's record of its scenes ------------------------------------------------------
def source_file(root: str | os.PathLike, data_name: str) -> Path:
    return Path(root) / SOURCES_DIR / f"{data_name}.json"


def load_source(root: str | os.PathLike, data_name: str) -> SceneSource | None:
    """The source a root recorded for a data name, None for a scene it has none of (a built-in one of an old root)."""
    f = source_file(root, data_name)
    if not f.is_file():
        return None
    return SceneSource.from_dict(json.loads(f.read_text()))


def _mixed_scene_error(name: str, old_hash: str, old_path: str, new: SceneSource, root) -> NimbusError:
    return NimbusError(f"{root} already holds a scene named {name!r} with another content ({old_path or 'built-in'}, "
                       f"hash {old_hash[:12]}; now {new.path}, hash {new.scene_hash[:12]}): a store never mixes two "
                       "scenes under one name; use another --root, or rename the folder")


def register_sources(root: str | os.PathLike, sources: Sequence[SceneSource]) -> None:
    """Record each external source under ``ROOT/sources/`` (what the cells and records read).

    Raises
    ------
    NimbusError
        The root already holds, under the same name (and size), a scene with another hash,
        in ``sources/`` or in the store's records.
    """
    from benchmark.store import ResultsStore, data_name_of
    from nimbus.utils.fs import atomic_write_json

    stored = {}
    for rec in ResultsStore(root).records():
        if rec.get("scene_hash"):
            stored.setdefault(data_name_of(rec.get("scene"), rec.get("size")),
                              (rec["scene_hash"], rec.get("scene_path", "")))
    for s in sources:
        if s.kind == BUILTIN:
            continue
        old = load_source(root, s.data_name)
        if old is not None and old.scene_hash != s.scene_hash:
            raise _mixed_scene_error(s.name, old.scene_hash, old.path, s, root)
        if s.data_name in stored and stored[s.data_name][0] != s.scene_hash:
            raise _mixed_scene_error(s.name, *stored[s.data_name], s, root)
        if old != s:
            atomic_write_json(source_file(root, s.data_name), s.to_dict())


def builtin_fields(root: str | os.PathLike, data_name: str) -> dict:
    """``scene_path`` / ``scene_hash`` / ``scene_kind`` of a rendered built-in scene (``ROOT/scenes/<data_name>``)."""
    folder = (Path(root) / "scenes" / data_name).resolve()
    return {"scene_path": str(folder), "scene_hash": scene_hash(folder) if folder.is_dir() else "",
            "scene_kind": BUILTIN}


# --- preparing the data ---------------------------------------------------------------------------
def prepare_source(root: Path, source: SceneSource, settings: Sequence[str], clean: Path,
                   family_out: Path, log: Callable[[str], None] | None) -> None:
    """Make the clean scene ``clean`` of an external source and, for a tree, its setting folders
    ``family_out/<SETTING>`` (the default family: a tree's settings as given).

    A capture's degraded settings are synthesised by the caller from ``clean``
    (:func:`benchmark.cell.prepare_data`, depth :data:`CAPTURE_DEPTH`).  Called under the scene's data
    lock; each folder is written atomically, and what is already there is kept.
    """
    say = log or (lambda _m: None)
    if source.kind == TREE:
        available = dict(source.settings)
        for s in settings:
            out = family_out / s
            if not (out / LINKED).is_file():
                say(f"copying setting {s} of {source.name} ({available[s]}) -> {out}")
                _copy_setting(Path(available[s]), out, source)
        if not (clean / "manifest.json").is_file():
            first = Path(available[sorted(available)[0]])  # every setting has the same views and clean images
            say(f"writing the clean views of {source.name} ({first}) -> {clean}")
            _write_tree_clean(first, clean)
        return
    scene_dir = Path(source.path)
    if source.kind == PHOTOS:
        scene_dir = _sfm(root, source, say)
    if not (clean / "manifest.json").is_file():
        say(f"copying {scene_dir}/{_image_folder(source.downscale)} as the clean scene -> {clean}")
        _write_capture_clean(scene_dir, source, clean)


def _manifest_of(scene, source: str) -> dict:
    return {"format": "nimbus-bench-clean-scene/1", "source": source, "views": len(scene.views)}


def _write_capture_clean(scene_dir: Path, source: SceneSource, clean: Path) -> None:
    """The capture's views (at its downscale) as a scene folder of the root: what the ceiling trains on."""
    from nimbus.data.io import load_scene, write_scene_into
    from nimbus.data.scene import write_split_lists
    from nimbus.utils.fs import atomic_dir, atomic_write_json

    scene = load_scene(scene_dir, downscale=source.downscale)
    with atomic_dir(clean, overwrite=True) as tmp:
        write_scene_into(scene, tmp)
        write_split_lists(scene, tmp)
        atomic_write_json(tmp / "manifest.json", {**_manifest_of(scene, source.path), "downscale": source.downscale})


def _write_tree_clean(scene_dir: Path, clean: Path) -> None:
    """One setting's cameras with its ``clean/`` images as a scene folder of the root (the clean ceiling's)."""
    from benchmark.score import ImageIndex
    from nimbus.data.io import load_scene, write_scene_into
    from nimbus.data.scene import Scene, write_split_lists
    from nimbus.utils.fs import atomic_dir, atomic_write_json

    scene = load_scene(scene_dir)
    index = ImageIndex(_clean_dir(scene_dir))
    views = []
    for v in scene.views:
        p = index.find(v.name)
        if p is None:
            raise NimbusError(f"{scene_dir}: view {v.name} has no clean image in {index.folder}")
        views.append(dataclasses.replace(v, image_path=p, image=None))
    clean_scene = Scene(tuple(views), scene.test_names, scene.points, scene.colors, scene.root, scene.source_format)
    with atomic_dir(clean, overwrite=True) as tmp:
        write_scene_into(clean_scene, tmp)
        write_split_lists(clean_scene, tmp)
        atomic_write_json(tmp / "manifest.json", _manifest_of(scene, str(scene_dir)))


def _copy_setting(scene_dir: Path, out: Path, source: SceneSource) -> None:
    """``out`` as a copy of a tree scene's cameras, images, split and clean images (``gt_clean/`` as ``clean/``),
    with :data:`LINKED` naming the source.

    Copied, not linked: a scene loader refuses a model folder that a link leads out of, and a copy
    can never be written through into the user's folder.
    """
    import shutil

    from benchmark.score import CLEAN_DIR
    from nimbus.utils.fs import atomic_dir, atomic_write_json

    with atomic_dir(out, overwrite=True) as tmp:
        for entry in _TREE_ENTRIES:
            src = scene_dir / entry
            if src.is_dir():
                shutil.copytree(src, tmp / entry)
            elif src.is_file():
                shutil.copyfile(src, tmp / entry)
        shutil.copytree(_clean_dir(scene_dir), tmp / CLEAN_DIR)
        atomic_write_json(tmp / LINKED, {"source": str(scene_dir), "scene_hash": scene_hash(scene_dir),
                                         "tree": source.path})


def _sfm(root: Path, source: SceneSource, say: Callable[[str], None]) -> Path:
    """The photo folder posed by SfM into ``ROOT/sfm/<name>-<hash>`` (reused when there)."""
    from nimbus.data.sfm import run_sfm

    out = Path(root) / SFM_DIR / f"{source.name}-{source.scene_hash[:12]}"
    if (out / "manifest.json").is_file():
        say(f"reusing the SfM of {source.path} in {out}")
        return out
    photos = Path(source.path)
    say(f"{photos} has no poses: running SfM (nimbus-synth sfm) -> {out}")
    result = run_sfm(photos, out, overwrite=True, log=lambda m: say(f"sfm: {m}"))
    say(f"sfm: registered {result.registered} / {result.total} photos")
    return out
