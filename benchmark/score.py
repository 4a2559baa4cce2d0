"""Score any method's renders against a scene's ground truth (``nimbus-bench score``).

Renders are matched to the scene's views by name: for view ``images/000.png`` the
render is ``RENDERS/000.png`` or ``RENDERS/000.jpg`` (any image extension; views in
sub-folders keep their sub-folder).  A nerfbaselines render folder (images under
``color/``) is recognised.  The ground truth of each view is, in this order of
preference, ``--gt-dir/<name>``, ``SCENE/clean/<name>`` (datasets written by
``nimbus-synth degrade``: ``images/`` holds the degraded inputs there), or the
scene's own image.  Missing or mis-sized renders are an error that lists them: a
benchmark figure over a subset of the views would not be comparable.

The results file holds per-view values, the sha256 of every prediction and ground
truth file, the protocols and the software versions, so a figure can be traced back to
the exact images it came from.

A view with a validity mask (``masks/``, ``mask_path``; 0 = ignore the pixel) is scored
over its valid pixels only (:data:`nimbus.metrics.MASK_PROTOCOL`); the results say so
(``masked``, ``masks``, per view ``valid_fraction``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from benchmark.metrics import Scorer, summarize
from nimbus.data import load_scene
from nimbus.data.images import read_image
from nimbus.data.scene_files import format_names, image_size, list_images
from nimbus.errors import NimbusError
from nimbus.metrics import LPIPS
from nimbus.train.views import view_mask
from nimbus.utils.fs import sha256_file
from nimbus.utils.jsonable import jsonable

FORMAT = "nimbus-bench-score/1"
SPLITS = ("test", "train", "all")
CLEAN_DIR = "clean"        # ground-truth folder of a weather_synth setting folder
NERFBASELINES_DIR = "color"  # where nerfbaselines writes its renders
SCORE_CHUNK = 8            # views read and scored at a time (bounds memory for large scenes)
FLOAT_RENDER_SUFFIX = ".npy"  # float32 (H, W, 3) renders in [0, 1], what the paper protocol scores


# --- matching ----------------------------------------------------------------------------
class ImageIndex:
    """Image files of a folder, looked up by view name: exact name first, else same path without extension."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.files = list_images(folder)
        self.exact = set(self.files)
        self.by_stem: dict[str, list[str]] = {}
        for f in self.files:
            self.by_stem.setdefault(str(Path(f).with_suffix("")), []).append(f)

    def find(self, name: str) -> Path | None:
        """The file for view ``name``, None when there is none; NimbusError when several fit."""
        if name in self.exact:
            return self.folder / name
        hits = self.by_stem.get(str(Path(name).with_suffix("")), [])
        if len(hits) > 1:
            raise NimbusError(f"{self.folder} has several images for view {name}: {', '.join(sorted(hits))}; "
                              "keep one")
        return self.folder / hits[0] if hits else None


def _select_views(scene, split: str) -> list:
    if split not in SPLITS:
        raise NimbusError(f"unknown split {split!r}; use one of {', '.join(SPLITS)}")
    views = {"test": scene.test_views, "train": scene.train_views, "all": list(scene.views)}[split]
    if not views:
        raise NimbusError(f"the scene has no {split} views (see its test_list.txt / train_list.txt); "
                          "choose another --split")
    return views


def _ground_truth(scene, scene_dir: Path, views: list, gt_dir: Path | None) -> tuple[list[Path], str]:
    """Ground-truth file of each view and where they came from."""
    if gt_dir is None and (scene_dir / CLEAN_DIR).is_dir():
        gt_dir, source = scene_dir / CLEAN_DIR, f"{CLEAN_DIR}/ (clean images of a degraded dataset)"
    elif gt_dir is not None:
        if not gt_dir.is_dir():
            raise NimbusError(f"--gt-dir {gt_dir} is not a folder")
        source = f"--gt-dir {gt_dir}"
    else:
        source = "the scene's images"
    paths, missing = [], []
    index = ImageIndex(gt_dir) if gt_dir is not None else None
    for v in views:
        p = index.find(v.name) if index is not None else v.image_path
        if p is None or not Path(p).is_file():
            missing.append(v.name)
        paths.append(p)
    if missing:
        where = gt_dir if gt_dir is not None else scene_dir
        raise NimbusError(f"{len(missing)} of {len(views)} views have no ground-truth image in {where}: "
                          f"{format_names(missing)}")
    return paths, source


def _renders(pred_dir: Path, views: list) -> tuple[list[Path], Path, int]:
    """Render file of each view, the folder they were found in, and how many render files went unused."""
    if pred_dir.exists() and not pred_dir.is_dir():
        raise NimbusError(f"renders folder {pred_dir} is a file; give the folder that holds the renders")
    if not pred_dir.is_dir():
        raise NimbusError(f"renders folder {pred_dir} does not exist")
    index = ImageIndex(pred_dir)
    found = [index.find(v.name) for v in views]
    if not any(found) and (pred_dir / NERFBASELINES_DIR).is_dir():
        return _renders(pred_dir / NERFBASELINES_DIR, views)
    if not index.files:
        raise NimbusError(f"renders folder {pred_dir} holds no images; render the views first")
    missing = [v.name for v, p in zip(views, found) if p is None]
    if missing:
        raise NimbusError(
            f"{len(missing)} of {len(views)} views have no render in {pred_dir}: {format_names(missing)} "
            f"(expected e.g. {Path(missing[0]).with_suffix('.png')}); render every view of the split, or choose "
            "another --split"
        )
    return found, pred_dir, len(index.files) - len(set(found))


def _float_renders(pred_dir: Path, views: list) -> list[Path]:
    """The float render (``<stem>.npy``) of each view, or NimbusError listing the views without one."""
    found = [pred_dir / Path(v.name).with_suffix(FLOAT_RENDER_SUFFIX) for v in views]
    missing = [v.name for v, p in zip(views, found) if not p.is_file()]
    if missing:
        raise NimbusError(f"{len(missing)} of {len(views)} views have no float render in {pred_dir}: "
                          f"{format_names(missing)} (expected e.g. {found[0].name}); the paper protocol scores float "
                          "renders, which nimbus-bench run --protocol paper saves beside the PNGs")
    return found


def read_float_render(path: Path) -> "np.ndarray":
    """A float render (``.npy``, float32 (H, W, 3)); never unpickles."""
    import numpy as np

    img = np.load(path, allow_pickle=False)
    if img.ndim != 3 or img.shape[2] != 3:
        raise NimbusError(f"{path} is not a float render of shape (H, W, 3) (got {img.shape})")
    return img.astype(np.float32, copy=False)


def _size(path: Path) -> tuple[int, int]:
    if path.suffix == FLOAT_RENDER_SUFFIX:
        import numpy as np

        shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
        return shape[1], shape[0]
    return image_size(path)


def _check_sizes(views: list, preds: list[Path], gts: list[Path]) -> None:
    bad = []
    for v, p, g in zip(views, preds, gts):
        ps, gs = _size(p), image_size(g)
        if ps != gs:
            bad.append(f"{p.name} is {ps[0]}x{ps[1]}, ground truth {gs[0]}x{gs[1]}")
    if bad:
        raise NimbusError(f"{len(bad)} render(s) do not match the ground truth's size: {'; '.join(bad[:5])}"
                          f"{' ...' if len(bad) > 5 else ''}; render at the ground truth's resolution "
                          "(or pick the matching --downscale)")


# --- scoring -----------------------------------------------------------------------------
def score_renders(pred_dir: str | Path, scene_dir: str | Path, split: str = "test", ssim_protocol: str = "3dgs",
                  lpips_net: "str | LPIPS | None" = "vgg", gt_dir: str | Path | None = None, downscale: int = 1,
                  device: str | None = None, progress: Callable[[int, int], None] | None = None,
                  quantize: bool = True) -> dict:
    """Score the renders in ``pred_dir`` against the ground truth of a scene.

    Parameters
    ----------
    pred_dir : path
        Folder of renders named after the views (``<stem>.png`` / ``.jpg``).
    scene_dir : path
        A scene folder :func:`nimbus.data.load_scene` reads (COLMAP or transforms.json); its
        split lists select the views.
    split : {"test", "train", "all"}
    ssim_protocol : {"3dgs", "skimage", "dmpix"}
    lpips_net : {"vgg", "alex"}, None or LPIPS
        None skips LPIPS; pass an :class:`nimbus.metrics.LPIPS` to reuse a loaded network.
        Without the weights set up, LPIPS is None with a note.
    gt_dir : path, optional
        Folder of ground-truth images (default ``SCENE/clean`` when it exists, else the scene's images).
    downscale : int
        Read the scene's ``images_<d>`` folder (Mip-NeRF360 layout).
    device : str, optional
        LPIPS device (default CUDA when available, else CPU).
    progress : callable(done, total), optional
        Called after each chunk of views.
    quantize : bool
        True: the benchmark's default, both images through an 8-bit round trip (renders are
        PNGs).  False: the paper's evaluation, float renders (``<stem>.npy`` in ``pred_dir``,
        float32 (H, W, 3) in [0, 1]) against the ground truth as read, no rounding.

    Returns
    -------
    dict
        JSON-ready: ``per_view`` (name, psnr, ssim, lpips, file paths and sha256), ``mean``,
        ``protocol``, ``notes``, ``versions`` and the inputs.  Non-finite values are None.
    """
    pred_dir, scene_dir = Path(pred_dir), Path(scene_dir)
    if not scene_dir.exists():
        raise NimbusError(f"scene folder {scene_dir} does not exist")
    _refuse_dataset_root(scene_dir)
    scene = load_scene(scene_dir, downscale=downscale)
    views = _select_views(scene, split)
    gts, gt_source = _ground_truth(scene, scene_dir, views, None if gt_dir is None else Path(gt_dir))
    if quantize:
        preds, pred_dir, unused = _renders(pred_dir, views)
    else:
        preds, unused = _float_renders(pred_dir, views), 0
    _check_sizes(views, preds, gts)
    read_pred = read_image if quantize else read_float_render

    scorer = Scorer(ssim_protocol, lpips_net, quantize=quantize, device=device)
    values: dict[str, list] = {}
    for s in range(0, len(views), SCORE_CHUNK):
        chunk = slice(s, s + SCORE_CHUNK)
        # A view's validity mask (masks/, mask_path) limits its scores to the valid pixels.
        part = scorer([read_pred(p) for p in preds[chunk]], [read_image(g) for g in gts[chunk]],
                      [view_mask(v) for v in views[chunk]])
        for k, v in part.items():
            values.setdefault(k, []).extend(v)
        if progress is not None:
            progress(min(s + SCORE_CHUNK, len(views)), len(views))
    names = [v.name for v in views]
    result = summarize(names, values, scorer)
    for rec, p, g in zip(result["per_view"], preds, gts):
        rec.update(pred=str(p), gt=str(g), pred_sha256=sha256_file(p), gt_sha256=sha256_file(g))
    if unused:
        result["notes"].append(f"{unused} image(s) in {pred_dir} are not {split} views and were not scored")
    result.update({
        "format": FORMAT,
        "pred_dir": str(pred_dir.resolve()),
        "scene": str(scene_dir.resolve()),
        "ground_truth": gt_source,
        "split": split,
        "views": len(views),
        "downscale": downscale,
        "versions": versions(),
    })
    return jsonable(result)


def _refuse_dataset_root(scene_dir: Path) -> None:
    """A ``nimbus-synth degrade`` output root holds one scene per setting; say which folder to pass."""
    if (scene_dir / "index.json").is_file() and not (scene_dir / "sparse").exists() \
            and not (scene_dir / "transforms.json").exists():
        settings = sorted(p.name for p in scene_dir.iterdir() if (p / CLEAN_DIR).is_dir())
        if settings:
            raise NimbusError(f"{scene_dir} is a degraded dataset with one scene per weather setting "
                              f"({', '.join(settings)}); pass one of them, e.g. --gt {scene_dir / settings[0]}")


def versions() -> dict[str, str]:
    """Software versions that can change the figures (:func:`nimbus.versions.software_versions`)."""
    from nimbus.versions import software_versions

    return software_versions()


def format_table(result: dict) -> str:
    """Per-view table, the mean and the protocols, as printed by ``nimbus-bench score``."""
    rows = result["per_view"]
    width = max([len("mean")] + [len(r["name"]) for r in rows])

    def fmt(v: float | None, spec: str) -> str:
        return "n/a" if v is None else format(v, spec)

    lines = [f"{'view':<{width}}  {'PSNR':>7}  {'SSIM':>6}  {'LPIPS':>6}"]
    for r in rows + [dict(result["mean"], name="mean")]:
        if r.get("name") == "mean":
            lines.append("-" * len(lines[0]))
        # PSNR is None only where it was infinite (identical images; JSON has no inf).
        psnr_s = "inf" if r["psnr"] is None else format(r["psnr"], "7.3f")
        lines.append(f"{r['name']:<{width}}  {psnr_s:>7}  {fmt(r['ssim'], '6.4f'):>6}  {fmt(r['lpips'], '6.4f'):>6}")
    proto = result["protocol"]
    lines += [f"PSNR:  {proto['psnr']}",
              f"SSIM:  {proto['ssim']} ({proto['ssim_reference']})",
              f"LPIPS: {proto['lpips'] or 'not computed'}"]
    lines += [f"note: {n}" for n in result["notes"]]
    return "\n".join(lines)
