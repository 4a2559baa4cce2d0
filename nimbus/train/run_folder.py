"""Run folders: the scene a run was trained on, and its ``config.json`` record (what ``--resume`` reads back).

A scene is named by a path (a COLMAP or transforms.json scene folder) or ``builtin:NAME[:SIZE]``;
``config.json`` records that name, the method, the seed, every config field and the keyword
arguments the scene was loaded with (:data:`SCENE_LOAD_ARGS`), as :meth:`~nimbus.train.runner.Runner.write_config`
writes it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from nimbus.errors import NimbusError

BUILTIN_PREFIX = "builtin:"
#: What ``scene_load_args`` in a run's config.json may hold (the keyword arguments of :func:`load_scene_arg`).
SCENE_LOAD_ARGS = ("downscale",)


def load_scene_arg(spec: str, downscale: int = 1):
    """A scene from a path, or ``builtin:NAME[:SIZE]`` rendered in memory (default size tiny).

    A built-in scene has no ``images_N`` copies, so ``downscale`` other than 1 is refused for it
    (pick a smaller SIZE, or ``--set train_downscale=N``) rather than silently ignored.
    """
    check_downscale(spec, downscale)
    if spec.startswith(BUILTIN_PREFIX):
        from nimbus.data.builtin import render_builtin

        parts = spec[len(BUILTIN_PREFIX):].split(":")
        name, size = parts[0], (parts[1] if len(parts) > 1 else "tiny")
        return render_builtin(name, size=size, seed=0)
    from nimbus.data.io import load_scene

    return load_scene(spec, downscale=downscale)


def check_downscale(spec: str, downscale: int) -> None:
    """Refuse a ``downscale`` that :func:`load_scene_arg` could not honour for ``spec``."""
    if spec.startswith(BUILTIN_PREFIX) and downscale != 1:
        raise NimbusError(f"--downscale {downscale} reads the images_{downscale}/ copies of a scene folder; "
                          f"built-in scenes have none. Pick a smaller size ({BUILTIN_PREFIX}NAME:tiny) or "
                          "train on shrunk images with --set train_downscale=N")


def scene_input_folder(spec: str) -> Path | None:
    """The folder a scene is read from (None for a built-in scene): what ``--out`` must stay apart from."""
    if spec.startswith(BUILTIN_PREFIX):
        return None
    path = Path(spec)
    return path.parent if path.is_file() else path  # a transforms*.json file reads its folder


def read_run_config(run: Path) -> dict:
    """The checked ``config.json`` of run folder ``run``: method, scene, seed, config and scene_load_args.

    Raises NimbusError naming the file and the field for anything that is not what
    :meth:`~nimbus.train.runner.Runner.write_config` writes (:class:`nimbus.schemas.RunConfig`).
    """
    from nimbus.schemas import RunConfig, read_json_file

    fix = "it is not a config.json written by nimbus-train; restore it or start a new run with --out"
    saved = read_json_file(run / "config.json", RunConfig, fix)
    return {**saved, "scene_load_args": saved.get("scene_load_args") or {}}


def config_record(config) -> dict:
    """``config``'s fields as strict JSON values: what config.json's ``"config"`` holds.

    A non-finite float is a setting here (nimbus-paper's unclipped ``ggs_clip=(0, inf)``), so it is
    written as the text ``"inf"`` / ``"-inf"`` / ``"nan"`` (:func:`nimbus.utils.jsonable.jsonable`),
    not as the ``Infinity`` token other JSON readers refuse; :func:`config_from_record` reads it back.
    """
    from nimbus.utils.jsonable import jsonable

    return jsonable(dataclasses.asdict(config), nonfinite="text")


def _field_value(value, numeric: bool):
    if isinstance(value, list):
        return tuple(_field_value(v, numeric) for v in value)
    if numeric and isinstance(value, str) and value in ("inf", "-inf", "nan"):
        return float(value)
    return value


def config_from_record(config_cls, record: dict):
    """The ``config_cls`` instance :func:`config_record` wrote (lists back to tuples; the text of a
    non-finite number back to a float, in fields whose annotation names ``float`` only).

    Raises TypeError / ValueError / NimbusError as ``config_cls(**...)`` does for fields that do not fit.
    """
    numeric = {f.name for f in dataclasses.fields(config_cls) if "float" in str(f.type)}
    return config_cls(**{k: _field_value(v, k in numeric) for k, v in record.items()})
