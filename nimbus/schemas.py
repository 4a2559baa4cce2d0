"""The declared shape of every JSON record Nimbus reads back: one schema per record kind.

A record read from a file is checked against its schema before any field of it is used, so a damaged or
hand-edited record ends in one line naming the file, the line (for a JSON Lines file) and the field::

    bench/results.jsonl line 7: field 'psnr' must be a number or null, got 'abc'

instead of a traceback, or a wrong table, somewhere later.  The kinds:

:class:`ResultRecord`
    One line of a benchmark store's ``results.jsonl`` (:mod:`benchmark.store`; written by
    :func:`benchmark.cell.run_cell`).  A store is read line by line: a line that does not fit is skipped
    with a warning naming it, and the rest of the store still reads.
:class:`RunConfig`
    A run folder's ``config.json`` (:meth:`nimbus.train.runner.Runner.write_config`; read by ``--resume``,
    ``nimbus-view``, a benchmark cell resuming its partial run and ``nimbus-bench decompose``).  One file is
    the input, so a mismatch is an error.
:class:`TransformsFile` and :class:`TransformsFrame`
    A Blender / nerfstudio ``transforms.json`` scene (:mod:`nimbus.data.transforms`): the file, then each of
    its frames as the reader reaches it (a file of a million frames is never held twice).
:class:`SceneManifest`
    The ``manifest.json`` of a built-in scene folder (:func:`nimbus.data.builtin.write_builtin`).
:class:`SettingManifest`
    The ``manifest.json`` of a degraded setting folder (``nimbus-synth degrade``; :mod:`weather_synth.dataset`).

Fields a schema does not name are allowed (a newer writer may add some); a field it names must have its type.
Types are strict: ``"1"`` is no number and ``true`` no integer.  Where a number is expected, the ``NaN`` and
``Infinity`` tokens (which Python's :mod:`json` reads) are refused: every writer here stores a non-finite value as
null or as text (:func:`nimbus.utils.jsonable.jsonable`).  What a schema cannot say (a ``cell_id`` that is one
file name, a ``run_dir`` inside the store) is checked by the reader after it.

The schemas are pydantic models used only to check (:func:`check`, :func:`problem`): readers keep the
plain dict they parsed.  The docs' Record schemas page (made by ``docs/hooks.py``) lists every field.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from nimbus.cli_util import MAX_SEED
from nimbus.errors import NimbusError
from nimbus.utils.fs import shown

#: A non-empty string.
Text = Annotated[str, Field(min_length=1)]
#: A seed every Nimbus tool accepts (:data:`nimbus.cli_util.MAX_SEED`).
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]
#: A finite number (an integer is one too), or null where none was measured.
Measure = Optional[float]
#: Status of a finished cell attempt: ``ok`` (scored) or ``error`` (its ``error`` says why).
ResultStatus = Literal["ok", "error"]


class Schema(BaseModel):
    """What every record schema shares: strict JSON types, finite numbers, unknown fields allowed."""

    model_config = ConfigDict(extra="allow", strict=True, allow_inf_nan=False)


# --- results.jsonl -----------------------------------------------------------------------------------------
class PerViewScore(Schema):
    """One test view's scores in a results record's ``per_view``."""

    name: str
    psnr: Measure = None
    ssim: Measure = None
    lpips: Measure = None


class ResultRecord(Schema):
    """One line of ``results.jsonl``: one finished attempt of one benchmark cell (:func:`benchmark.cell.run_cell`)."""

    # What the cell is (benchmark.cell.Cell).
    cell_id: Text = Field(description="the cell's id; names its run folder, lock and thumbnails (one file name)")
    scene: Text = Field(description="scene name: a built-in scene, or a scene folder's name")
    size: Text = Field(description="built-in scene size, or the image folder of a scene folder (images, images_N)")
    weather: Text = Field(description="weather setting (H, R+S, H@physical, ...) or clean")
    method: Text = Field(description="registered method name")
    preset: Text = Field(description="trainer preset")
    seed: Seed = Field(description="training seed")
    overrides: dict[str, str] = Field(default={}, description="--set overrides, key -> value text")
    # What happened to it.
    status: ResultStatus = Field(description="ok (scored) or error")
    error: Optional[str] = Field(default=None, description="why an error record failed")
    traceback: Optional[str] = None
    format: Optional[str] = Field(default=None, description="record format, nimbus-bench-cell/1")
    run_dir: Optional[str] = Field(default=None, description="the run folder, relative to the store root")
    resumed_from_iteration: Optional[int] = None
    # Scores against the clean test views (null: no finite value, e.g. the PSNR of identical images).
    psnr: Measure = Field(default=None, description="mean PSNR (dB) against the clean test views")
    ssim: Measure = Field(default=None, description="mean SSIM (ssim_protocol)")
    lpips: Measure = Field(default=None, description="mean LPIPS (lpips_net)")
    psnr_vs_input: Measure = None
    ssim_vs_input: Measure = None
    # The degraded test views themselves against the clean ones, scored alike (weather cells; absent in old records).
    input_psnr: Measure = Field(default=None, description="mean PSNR (dB) of the degraded test views themselves "
                                "against the clean ones (no reconstruction); weather cells only")
    input_ssim: Measure = Field(default=None, description="mean SSIM of the degraded test views (ssim_protocol)")
    input_lpips: Measure = Field(default=None, description="mean LPIPS of the degraded test views (lpips_net)")
    ssim_protocol: Optional[str] = None
    lpips_net: Optional[str] = None
    per_view: Optional[list[PerViewScore]] = Field(default=None, description="each test view's scores")
    notes: Optional[list] = None
    # Cost and size of the trained model.
    train_time_s: Measure = None
    wall_time_s: Measure = None
    peak_memory_mb: Measure = None
    threads: Optional[int] = Field(default=None, description="torch CPU threads the training ran with (results "
                                   "at small size move with it by float rounding; absent in old records)")
    cells_at_once: Optional[int] = Field(default=None, description="the most benchmark cells that trained at the "
                                         "same time while this one did (train_time_s grows with them; absent in "
                                         "old records)")
    render_fps: Measure = None
    num_gaussians: Optional[int] = None
    num_params: Optional[int] = None
    iterations: Optional[int] = None
    # Provenance.
    config: Optional[dict] = Field(default=None, description="every field of the method's config")
    config_hash: Optional[str] = None
    input_sha256: Optional[str] = Field(default=None, description="sha256 of the degraded data's manifest")
    output_sha256: Optional[dict[str, str]] = Field(default=None, description="render name -> sha256")
    scene_path: Optional[str] = Field(default=None, description="the scene folder the cell trained on")
    scene_hash: Optional[str] = Field(default=None, description="a hash of that scene's content")
    scene_kind: Optional[Literal["builtin", "capture", "photos", "tree"]] = Field(
        default=None,
        description="what --scenes was given: a built-in scene, a capture, a photo folder, a dataset tree")
    eval_protocol: Optional[str] = Field(default=None, description="the evaluation protocol (default, paper)")
    versions: Optional[dict] = None
    protocol: Optional[dict] = None
    host: Optional[str] = None
    started_at: Optional[str] = Field(default=None, description="UTC, ISO 8601")
    finished_at: Optional[str] = Field(default=None, description="UTC, ISO 8601")


# --- a run folder's config.json ----------------------------------------------------------------------------
class SceneLoadArgs(BaseModel):
    """The keyword arguments a run's scene was loaded with (:data:`nimbus.train.run_folder.SCENE_LOAD_ARGS`)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    downscale: Annotated[int, Field(ge=1)] = 1


class RunConfig(Schema):
    """A run folder's ``config.json`` (:meth:`nimbus.train.runner.Runner.write_config`)."""

    method: Text = Field(description="registered method name")
    scene: Text = Field(description="the scene: a folder or transforms file path, or builtin:NAME[:SIZE]")
    seed: Seed = Field(description="the training seed")
    config: dict = Field(description="every field of the method's config (checked by the config dataclass)")
    scene_load_args: Optional[SceneLoadArgs] = None
    config_type: Optional[str] = None
    nimbus_version: Optional[str] = None
    device: Optional[str] = None


# --- scene manifests ---------------------------------------------------------------------------------------
#: A camera value of a transforms.json (image size, focal length, principal point, angle or lens coefficient).
CameraValue = Optional[float]
#: OpenGL camera-to-world: 4x4, or its top 3x4.
Matrix = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=3, max_length=4)]


class TransformsCamera(Schema):
    """Camera keys a transforms.json gives at the top level (shared by every frame) or per frame."""

    w: CameraValue = None
    h: CameraValue = None
    fl_x: CameraValue = None
    fl_y: CameraValue = None
    cx: CameraValue = None
    cy: CameraValue = None
    camera_angle_x: CameraValue = None
    camera_angle_y: CameraValue = None
    k1: CameraValue = None
    k2: CameraValue = None
    k3: CameraValue = None
    k4: CameraValue = None
    p1: CameraValue = None
    p2: CameraValue = None
    camera_model: Optional[str] = None


class TransformsFrame(TransformsCamera):
    """One entry of a transforms.json's ``frames``."""

    file_path: str = Field(description="the image, relative to the scene folder")
    transform_matrix: Matrix = Field(description="OpenGL camera-to-world, 4x4 or its top 3x4")
    mask_path: Optional[str] = None
    depth_file_path: Optional[str] = None


class TransformsFile(TransformsCamera):
    """A Blender / nerfstudio ``transforms.json``; each frame is a :class:`TransformsFrame`, checked as it is read."""

    frames: Annotated[list, Field(min_length=1, description="the views, each a TransformsFrame")]
    train_filenames: list[str] = []
    val_filenames: list[str] = []
    test_filenames: list[str] = []
    ply_file_path: Optional[str] = None


class SceneManifest(Schema):
    """A built-in scene folder's ``manifest.json`` (:func:`nimbus.data.builtin.manifest`)."""

    scene: Optional[str] = None
    size: Optional[str] = None
    seed: Seed = Field(description="the seed it was rendered with (the benchmark's own scenes: 0)")
    image_count: Optional[int] = None
    conventions: Optional[dict] = None


class SettingView(Schema):
    """One view of a degraded setting's manifest: its files, relative to the setting folder."""

    name: str
    image: str
    clean: str
    layers: Optional[str] = None
    split: Optional[Literal["train", "test"]] = None


class SettingManifest(Schema):
    """A degraded setting folder's ``manifest.json`` (:func:`weather_synth.dataset.degrade_scene`)."""

    setting: Optional[str] = None
    protocol: Optional[str] = None
    seed: Optional[int] = None
    config: Optional[dict] = None
    input: Optional[dict] = None
    scene: Optional[dict] = None
    summary: Optional[dict] = None
    views: list[SettingView] = Field(description="every view: its degraded image, clean image and layers")


# --- checking ----------------------------------------------------------------------------------------------
_TYPE_WORDS = {"string_type": "a string", "float_type": "a number", "int_type": "an integer",
               "bool_type": "true or false", "dict_type": "an object", "model_type": "an object",
               "list_type": "a list", "none_required": "null"}


def _json_kind(value: object) -> str:
    """What a JSON value is, in a message's words."""
    if value is None:
        return "null"
    for python, words in ((bool, "true or false"), (dict, "an object"), (list, "a list"), (str, "a string"),
                          (int, "an integer"), (float, "a number")):
        if isinstance(value, python):
            return words
    return type(value).__name__


def _field(loc: tuple) -> str:
    """``frames[2].file_path`` from a pydantic error location."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _describe(error: dict, nullable: bool) -> str:
    """One pydantic error as ``field 'x' must be ..., got ...`` (for the whole record: ``holds a list, ...``)."""
    kind, loc, value, ctx = error["type"], error["loc"], error.get("input"), error.get("ctx") or {}
    field = _field(loc)
    if not loc:
        return f"holds {_json_kind(value)}, not an object" if kind in ("model_type", "dict_type") else error["msg"]
    subject = f"field {field!r}"
    if kind == "missing":
        return f"{subject} is missing"
    if kind in _TYPE_WORDS:
        return f"{subject} must be {_TYPE_WORDS[kind]}{' or null' if nullable else ''}, got {shown(value)}"
    if kind == "finite_number":
        return f"{subject} must be a finite number, got {shown(value)}"
    if kind == "literal_error":
        return f"{subject} must be {ctx.get('expected', 'one of the listed values')}, got {shown(value)}"
    if kind == "string_too_short":
        return f"{subject} must not be empty"
    if kind in ("greater_than_equal", "less_than_equal"):
        op, bound = (">=", ctx.get("ge")) if kind == "greater_than_equal" else ("<=", ctx.get("le"))
        return f"{subject} must be {op} {bound}, got {shown(value)}"
    if kind == "too_short" and ctx.get("min_length") == 1:
        return f"{subject} must not be empty"
    if kind in ("too_short", "too_long"):
        return f"{subject} must have {'at least' if kind == 'too_short' else 'at most'} " \
               f"{ctx.get('min_length', ctx.get('max_length'))} entries, got {ctx.get('actual_length')}"
    if kind == "extra_forbidden":
        return f"{subject} is not a known key"
    if kind == "recursion_loop":
        return f"{subject} is nested too deeply"
    return f"{subject}: {error['msg']}, got {shown(value)}"


def _nullable(schema: type[BaseModel], loc: tuple) -> bool:
    """Whether the field at ``loc`` also takes null (``Optional``), for the message: the annotations are
    followed down through models, lists and dicts."""
    annotation: Any = schema
    for part in loc:
        annotation = _unwrap(annotation)
        if isinstance(part, str) and isinstance(annotation, type) and issubclass(annotation, BaseModel):
            field = annotation.model_fields.get(part)
            if field is None:
                return False
            annotation = field.annotation
        elif get_origin(annotation) in (list, dict):
            annotation = get_args(annotation)[-1] if get_args(annotation) else Any
        else:
            return False
    return type(None) in get_args(annotation)


def _unwrap(annotation: Any) -> Any:
    """``X`` of ``Optional[X]`` / ``Annotated[X, ...]``."""
    while True:
        args = [a for a in get_args(annotation) if a is not type(None)]
        if get_origin(annotation) is Annotated or (type(None) in get_args(annotation) and len(args) == 1):
            annotation = args[0]
        else:
            return annotation


def problem(schema: type[BaseModel], value: object) -> str | None:
    """What is wrong with ``value`` as a record of ``schema``, as one phrase naming the field; None if it fits."""
    try:
        schema.model_validate(value)
    except ValidationError as e:
        errors = e.errors(include_url=False)
        return _describe(errors[0], _nullable(schema, errors[0]["loc"]))
    except RecursionError:
        return "is nested too deeply"
    return None


def check(schema: type[BaseModel], value: Any, where: str, fix: str = "") -> Any:
    """``value`` as it is if it fits ``schema``, else NimbusError ``"<where>: <problem>[; <fix>]"``."""
    why = problem(schema, value)
    if why is not None:
        raise NimbusError(f"{where}: {why}" + (f"; {fix}" if fix else ""))
    return value


def parse_json(text: str | bytes) -> Any:
    """``json.loads``, with a ValueError (its message says what) for anything it cannot read.

    Python's parser recurses once per nesting level and raises RecursionError, not a ValueError, on a line
    such as 200,000 ``[``; a digit string past Python's limit raises a plain ValueError.
    """
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    except UnicodeDecodeError:
        raise ValueError("not UTF-8 text") from None
    except json.JSONDecodeError as e:
        raise ValueError(e.msg if e.lineno == 1 else f"{e.msg} at line {e.lineno}, column {e.colno}") from None


def read_json_file(path: str | os.PathLike, schema: type[BaseModel], fix: str) -> dict:
    """The JSON object in file ``path``, checked against ``schema``; NimbusError naming the file otherwise.

    For a file that is the input by itself (a run's config.json, a manifest): a file that cannot be read or
    parsed, or does not fit, is one error line ending in ``fix``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise NimbusError(f"{path} is not a UTF-8 text file; {fix}") from None
    except OSError as e:
        raise NimbusError(f"cannot read {path} ({e.strerror or e.__class__.__name__}); {fix}") from None
    try:
        value = parse_json(text)
    except ValueError as e:
        raise NimbusError(f"{path} is not valid JSON ({str(e)[:120]}); {fix}") from None
    return check(schema, value, str(path), fix)
