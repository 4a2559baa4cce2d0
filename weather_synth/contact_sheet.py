"""Contact sheets: a labelled grid of images (rows: clean + weather settings, columns: views) to look at.

:func:`dataset_contact_sheet` reads a dataset written by
:func:`weather_synth.dataset.degrade_scene` (the ``OUT`` folder, or one setting
folder) through its manifests, so it needs no scene reader.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from nimbus.data.images import read_image, to_uint8
from nimbus.errors import NimbusError
from nimbus.utils.fs import confined_path
from weather_synth.dataset import MANIFEST, read_setting_manifest
from weather_synth.settings import ALL_SETTING_NAMES

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BACKGROUND = 32
_TEXT = (235, 235, 235)
# Tile widths the CLIs accept (pixels): narrower tiles are unreadable, wider ones make sheets of gigabytes.
MIN_TILE_WIDTH, MAX_TILE_WIDTH = 16, 4096


def check_sheet_options(views: int, tile_width: int) -> None:
    """Refuse a column count or tile width the sheet cannot be drawn with (before any work starts)."""
    if views < 1:
        raise NimbusError(f"--views must be at least 1, got {views}")
    if not MIN_TILE_WIDTH <= tile_width <= MAX_TILE_WIDTH:
        raise NimbusError(f"--tile-width must be {MIN_TILE_WIDTH} to {MAX_TILE_WIDTH} pixels, got {tile_width}")


def _fit(img: np.ndarray, width: int) -> np.ndarray:
    """Resize to ``width`` keeping the aspect ratio; nearest-neighbour when enlarging (shows true pixels)."""
    h, w = img.shape[:2]
    height = max(1, int(round(h * width / w)))
    interp = cv2.INTER_NEAREST if width >= w else cv2.INTER_AREA
    return cv2.resize(img, (width, height), interpolation=interp)


def _label(canvas: np.ndarray, text: str, x: int, y: int, scale: float) -> None:
    cv2.putText(canvas, text, (x, y), _FONT, scale, _TEXT, 1, cv2.LINE_AA)


def make_contact_sheet(rows: Sequence[tuple[str, Sequence[np.ndarray]]], column_labels: Sequence[str],
                       tile_width: int = 160, gap: int = 4) -> np.ndarray:
    """A labelled grid, uint8 RGB.

    Parameters
    ----------
    rows : sequence of (label, images)
        Each row's images (float32 (H, W, 3) in [0, 1] or uint8), one per column.
    column_labels : sequence of str
    tile_width : int
        Width every image is resized to (pixels).
    gap : int
        Pixels between tiles.
    """
    if not rows or not column_labels:
        raise NimbusError("a contact sheet needs at least one row and one column")
    tiles = [[_fit(to_uint8(im) if im.dtype != np.uint8 else im, tile_width) for im in imgs] for _, imgs in rows]
    tile_h = max(t.shape[0] for r in tiles for t in r)
    scale = 0.45
    label_w = max(cv2.getTextSize(lbl, _FONT, scale, 1)[0][0] for lbl, _ in rows) + 2 * gap + 6
    header_h = 22
    n_cols = len(column_labels)
    W = label_w + n_cols * (tile_width + gap) + gap
    H = header_h + len(rows) * (tile_h + gap) + gap
    canvas = np.full((H, W, 3), _BACKGROUND, np.uint8)
    for j, text in enumerate(column_labels):
        x = label_w + j * (tile_width + gap)
        _label(canvas, str(text)[:24], x + 2, header_h - 7, scale)
    for i, ((text, _), row) in enumerate(zip(rows, tiles)):
        y = header_h + i * (tile_h + gap)
        _label(canvas, text, gap + 2, y + tile_h // 2 + 5, scale)
        for j, t in enumerate(row[:n_cols]):
            x = label_w + j * (tile_width + gap)
            canvas[y:y + t.shape[0], x:x + t.shape[1]] = t
    return canvas


def find_settings(dataset: str | os.PathLike) -> list[tuple[str, Path, dict]]:
    """``(setting name, folder, manifest)`` of every setting in a dataset folder (or of one setting folder)."""
    dataset = Path(dataset)
    if not dataset.is_dir():
        raise NimbusError(f"dataset folder {dataset} does not exist; give the --out folder of `nimbus-synth degrade`")
    folders = [dataset] if (dataset / MANIFEST).is_file() else sorted(p for p in dataset.iterdir()
                                                                        if (p / MANIFEST).is_file())
    found = []
    for f in folders:
        m = read_setting_manifest(f)
        found.append((m.get("setting", f.name), f, m))
    if not found:
        raise NimbusError(f"{dataset} holds no degraded settings (no */{MANIFEST}); "
                          "make one with `nimbus-synth degrade SCENE --out DIR`")
    order = {n: i for i, n in enumerate(ALL_SETTING_NAMES)}
    return sorted(found, key=lambda x: (order.get(x[0], len(order)), x[0]))


def depth_label(manifest: dict) -> str | None:
    """``"depth recon 0.88"``: a setting's depth source and mean depth consistency, or None when it used no depth."""
    depth = (manifest.get("scene") or {}).get("depth")
    if not isinstance(depth, dict):
        return None
    mean = (depth.get("consistency") or {}).get("mean")
    src = str(depth.get("source", "?")).split(":", 1)[0]
    return f"depth {src} {mean:.2f}" if isinstance(mean, (int, float)) else f"depth {src}"


def depth_lines(dataset: str | os.PathLike) -> list[str]:
    """What ``nimbus-synth preview`` prints about the dataset's depth: source, why, consistency (one line each)."""
    lines, seen = [], set()
    for name, _, m in find_settings(dataset):
        depth = (m.get("scene") or {}).get("depth")
        if not isinstance(depth, dict):
            continue
        cons = depth.get("consistency") or {}
        mean, tol = cons.get("mean"), cons.get("tolerance")
        text = f"depth: {depth.get('source')}"
        if depth.get("reason"):
            text += f" (picked by {depth.get('requested')}: {depth['reason']})"
        if isinstance(mean, (int, float)) and isinstance(tol, (int, float)):
            text += (f"; consistency {mean:.3f} (share of pixels whose depth agrees within {tol:.0%} with the "
                     "nearest other view's)")
        if text not in seen:
            seen.add(text)
            lines.append(text)
    return lines


def dataset_contact_sheet(dataset: str | os.PathLike, max_views: int = 6, tile_width: int = 160,
                          views: Sequence[str] | None = None) -> np.ndarray:
    """Contact sheet of a degraded dataset: a clean row, then one row per setting; uint8 RGB.

    Parameters
    ----------
    max_views : int
        Columns: this many views spread evenly over the scene (when ``views`` is None).
    views : sequence of str, optional
        View names to show instead.
    """
    settings = find_settings(dataset)
    records = {v["name"]: v for v in settings[0][2]["views"]}
    names = list(records)
    if views is None:
        if max_views < 1:
            raise NimbusError(f"max views must be >= 1, got {max_views}")
        idx = np.unique(np.linspace(0, len(names) - 1, min(max_views, len(names))).round().astype(int))
        views = [names[i] for i in idx]
    unknown = [v for v in views if v not in records]
    if unknown:
        raise NimbusError(f"views not in the dataset: {unknown[:5]}; it has {names[:5]}...")
    first = settings[0][1]
    # Names come from the manifests, which may come from anyone: read only inside each setting folder.
    rows = [("clean", [read_image(confined_path(first, records[v]["clean"], "image")) for v in views])]
    for name, folder, m in settings:
        recs = {v["name"]: v for v in m["views"]}
        label = depth_label(m) if "H" in name.split("+") else None  # the haze rows: where depth shows
        rows.append((f"{name}  [{label}]" if label else name, [read_image(confined_path(folder, recs[v]["image"], "image")) for v in views]))
    return make_contact_sheet(rows, [Path(v).stem for v in views], tile_width)
