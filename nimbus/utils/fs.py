"""Atomic file and directory writes.

Every output Nimbus writes goes to a temporary path beside its destination and
is renamed into place only when complete, so an interrupted job never leaves a
half-written file or directory behind, and a user's existing data is never
replaced unless they asked for it (``overwrite=True``).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from nimbus.errors import NimbusError


#: errno values of a full disk (or a spent quota): the user can fix them, so they end in one error line.
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def write_problem(e: OSError, path: str | os.PathLike | None, need: int | None = None) -> NimbusError | None:
    """The one-line :class:`NimbusError` for an ``OSError`` the user can fix while writing ``path`` (a full disk or
    quota, naming the folder, the bytes needed where known and the bytes free; a name longer than the file system
    takes), or None for any other error (left to raise as it is)."""
    path = Path(path) if path is not None else None
    if e.errno in DISK_FULL and path is None:
        return NimbusError("no space left on a device being written to; free some space and run the command again")
    if e.errno in DISK_FULL:
        folder = path.parent
        try:
            free = f", {shutil.disk_usage(folder).free:,} bytes free"
        except OSError:
            free = ""
        needed = f" ({path.name} needs {need:,} bytes{free})" if need is not None else (f" ({free[2:]})" if free
                                                                                      else "")
        return NimbusError(f"no space left on the device of {folder}{needed}; free some space or choose another "
                           "output folder (the file was not written; nothing partial was kept)")
    if e.errno == errno.ENAMETOOLONG:
        name = path if path is not None else Path(str(e.filename))
        longest = max((len(part.encode("utf-8", "surrogateescape")) for part in name.parts), default=0)
        return NimbusError(f"the file name {shown(name.name)} is too long for the file system of {name.parent} "
                           f"({longest} bytes in one name; most take {NAME_MAX}): rename the input it comes from")
    return None


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``.

    A full disk (:data:`DISK_FULL`) or a name too long for the file system raises one-line :class:`NimbusError`
    (:func:`write_problem`) and leaves nothing: neither the temporary file nor a changed ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:200]}.tmp-", dir=path.parent)
    except OSError as e:
        problem = write_problem(e, path, len(data))
        if problem is None:
            raise
        raise problem from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        problem = write_problem(e, path, len(data)) if isinstance(e, OSError) else None
        if problem is None:
            raise
        raise problem from None
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def nonfinite_field(obj: Any, where: str = "", allow_inf: bool = False) -> str | None:
    """The key path (``psnr``, ``per_view[3].ssim``) of the first NaN (or, unless ``allow_inf``, infinite) float in
    a JSON-ready ``obj``, or None.  A NaN score sorts and averages as garbage, and strict JSON has neither."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) or (allow_inf and not math.isnan(obj)) else (where or "the value")
    if isinstance(obj, dict):
        for k, v in obj.items():
            found = nonfinite_field(v, f"{where}.{k}" if where else str(k), allow_inf)
            if found:
                return found
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            found = nonfinite_field(v, f"{where}[{i}]", allow_inf)
            if found:
                return found
    return None


def refuse_nonfinite_record(obj: Any, what: str, allow_inf: bool = False) -> None:
    """NimbusError naming ``what`` (a file, a store) and the field when ``obj`` holds a NaN (or, unless
    ``allow_inf``, an infinite) float."""
    field = nonfinite_field(obj, allow_inf=allow_inf)
    if field is not None:
        kind = "NaN" if allow_inf else "not a finite number (NaN or inf)"
        raise NimbusError(f"refusing to write {what}: its field {field} is {kind}; a record with it would read "
                          "back as garbage. Nothing was written")


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented, key-sorted JSON (stable bytes for the same object).

    A NaN is refused (:func:`refuse_nonfinite_record`), naming the field.  An infinity still means something in
    these files (the PSNR of identical images) and is written as Python's ``Infinity``.
    """
    refuse_nonfinite_record(obj, str(path), allow_inf=True)
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


#: The longest name (one path component) Linux, macOS and Windows file systems take, in bytes.
NAME_MAX = 255
#: How much of a refused value a message shows: enough to find it, never a whole file's worth.
SHOWN_CHARS = 80


def shown(value: object) -> str:
    """``repr(value)`` cut to :data:`SHOWN_CHARS` characters, for messages about a value read from data."""
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


def confined_path(root: str | os.PathLike, name: str | os.PathLike, what: str = "file") -> Path:
    """``root / name`` with symlinks resolved, refused unless it lies inside ``root``.

    The one rule for a path read from data rather than typed by the user: a name in a scene's
    files (a COLMAP ``images.txt`` name, a ``transforms.json`` ``file_path``, a split list, a
    mask or depth name), a scene's own model and split files, a results store record's
    ``run_dir``, a name that becomes a file of an output folder.  It goes through here before
    anything is read from or written to it, so a hostile name such as ``/etc/passwd`` or
    ``../../x.png`` (or a symlink that leads outside) cannot make Nimbus touch files outside
    the scene, the store or the output folder.  The message names ``what`` (the field) and shows
    the name cut short (:func:`shown`); it never reads, so never shows, what the name leads to.
    """
    if not isinstance(name, (str, os.PathLike)) or not str(name) or "\x00" in str(name):
        raise NimbusError(f"invalid {what} name {shown(name)}: expected a relative path inside {root}")
    check_name_length(name, what)
    base = Path(root).resolve()
    path = (base / name).resolve()
    if path != base and base not in path.parents:
        raise NimbusError(f"{what} name {shown(str(name))} points outside {root}; names must be relative paths "
                          "inside the folder (no absolute paths, no '..', no links leading out)")
    return path


def check_name_length(name: str | os.PathLike, what: str) -> None:
    """NimbusError naming ``what`` when a part of ``name`` is longer than :data:`NAME_MAX` bytes, before the
    operating system answers ENAMETOOLONG from somewhere deep in a read or a write."""
    for part in Path(name).parts:
        size = len(part.encode("utf-8", "surrogateescape"))
        if size > NAME_MAX:
            raise NimbusError(f"{what} name {shown(str(name))} has a part of {size} bytes; file systems take at most "
                              f"{NAME_MAX} bytes per name: shorten it")


def single_name(value: object, what: str) -> str:
    """``value`` if it is a single safe file name, else NimbusError naming ``what``.

    For a value read from data that becomes one component of a path (a results record's
    ``cell_id`` names its run folder, lock and thumbnails): a non-empty string without ``/``,
    ``\\`` or NUL that is not ``.`` or ``..``, at most 255 bytes.
    """
    if (not isinstance(value, str) or value in ("", ".", "..") or any(c in value for c in "/\\\x00")
            or len(value.encode("utf-8", "surrogatepass")) > NAME_MAX):
        raise NimbusError(f"{what} is {shown(value)}, not a single file name (no '/', '\\', '..' or NUL); "
                          "it names a folder or file, so it must stay one name")
    return value


def refuse_overlap(out: str | os.PathLike, inputs, flag: str = "--out") -> None:
    """Refuse an output folder that is, contains or lies inside any of ``inputs``.

    A command that replaces (or fills) ``out`` must never delete or write into what it
    reads: ``--out SCENE --overwrite`` would otherwise remove the scene before failing.
    ``inputs`` are paths (None entries are skipped).
    """
    o = Path(out).resolve()
    for inp in inputs:
        if inp is None:
            continue
        i = Path(inp).resolve()
        if o == i or i in o.parents or o in i.parents:
            rel = "is" if o == i else ("lies inside" if i in o.parents else "contains")
            raise NimbusError(f"{flag} {out} {rel} the input {inp}; choose an output folder apart from the inputs "
                              "(nothing was written or deleted)")


#: The file a command writes into its output folder, naming the command: ``--overwrite`` replaces a folder only
#: when it holds this file naming the same command (:func:`check_output_dir`), i.e. the command's own earlier output.
OUTPUT_MARKER = ".nimbus-output"
#: What marks a folder as a results store (``benchmark.store.STORE_FILE``) or a scene (a COLMAP model where
#: ``nimbus.data.colmap.find_sparse_dir`` looks, a transforms file): no command's output folder goes inside one.
STORE_OR_SCENE_FILES = ("results.jsonl", "sparse/0/cameras.bin", "sparse/0/cameras.txt", "sparse/cameras.bin",
                        "sparse/cameras.txt", "transforms.json", "transforms_train.json")


def check_output_dir(out: str | os.PathLike, overwrite: bool, inputs=(), flag: str = "--out",
                     owner: str | None = None) -> Path:
    """Refuse an unusable output directory before any work starts.

    Refused: an existing non-empty directory unless ``overwrite``; a path that exists and is
    not a directory; a path under a file; a folder that cannot be created or written
    (read-only, no permission); and a folder that is, contains or lies inside any of
    ``inputs`` (see :func:`refuse_overlap`).  Nothing is created or deleted here.

    With ``owner`` (the command, e.g. ``"nimbus-bench report"``), the rule of a command that replaces its
    output folder as a whole: ``overwrite`` replaces only that command's own earlier output, a folder holding
    an :data:`OUTPUT_MARKER` that names ``owner`` (:func:`mark_output`; :func:`atomic_dir` writes it); any
    other non-empty folder is refused, and so is a folder inside a results store or a scene
    (:data:`STORE_OR_SCENE_FILES`), whose files are not the command's to replace or mix with.
    """
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise NimbusError(f"{flag} {out} is a link to {shown(os.readlink(out))}, which does not exist; give a "
                          f"folder path, or remove the link (nothing was written)")
    refuse_overlap(out, inputs, flag)
    try:
        if out.exists() and not out.is_dir():
            raise NimbusError(f"{flag} {out} exists and is not a directory; choose another {flag}")
        if owner is not None:
            _refuse_inside_store_or_scene(out, flag)
        if out.is_dir() and any(out.iterdir()):
            if not overwrite:
                raise NimbusError(f"{flag} {out} is not empty; pass --overwrite to replace it or choose another {flag}")
            if owner is not None:
                _refuse_foreign(out, owner, flag)
        probe = out if out.is_dir() else next((p for p in out.resolve().parents if p.exists()), None)
    except PermissionError:
        raise NimbusError(f"{flag} {out} cannot be read (permission denied); choose another {flag}") from None
    if probe is None or not probe.is_dir():
        raise NimbusError(f"{flag} {out} lies under {probe}, which is not a directory; choose another {flag}")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise NimbusError(f"{flag} {out} cannot be written ({probe} is read-only or not ours); choose another {flag}")
    return out


def _refuse_inside_store_or_scene(out: Path, flag: str) -> None:
    for folder in out.resolve().parents:
        found = next((f for f in STORE_OR_SCENE_FILES if (folder / f).is_file()), None)
        if found is not None:
            kind = "results store" if found == STORE_OR_SCENE_FILES[0] else "scene"
            raise NimbusError(f"{flag} {out} lies inside the {kind} {folder} (it holds {found}); write outputs apart "
                              f"from stores and scenes: choose another {flag} (nothing was written or deleted)")


def _refuse_foreign(out: Path, owner: str, flag: str) -> None:
    try:
        made_by = (out / OUTPUT_MARKER).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError):
        made_by = None
    if made_by != owner:
        by = f"by {shown(made_by)}" if made_by else f"by {owner} (it has no {OUTPUT_MARKER} naming it)"
        raise NimbusError(f"{flag} {out} was not written {by}; --overwrite replaces only {owner}'s own earlier "
                          f"output: choose another {flag}, or empty the folder yourself (nothing was written or "
                          "deleted)")


def mark_output(folder: str | os.PathLike, owner: str) -> None:
    """Write :data:`OUTPUT_MARKER` naming ``owner`` into ``folder``: a later ``--overwrite`` of ``owner`` may replace
    it (:func:`check_output_dir`)."""
    atomic_write_text(Path(folder) / OUTPUT_MARKER, owner + "\n")


@contextlib.contextmanager
def atomic_dir(out: str | os.PathLike, overwrite: bool = False, owner: str | None = None) -> Iterator[Path]:
    """Build a directory at a temporary path and move it to ``out`` on success.

    Yields the temporary directory to write into.  On any exception (including
    KeyboardInterrupt) the temporary directory is removed and ``out`` is left as
    it was.  An existing non-empty ``out`` is refused unless ``overwrite``; when
    overwriting, the old directory is removed only after the new one is complete.
    With ``owner``, :func:`check_output_dir`'s rule of replacing only ``owner``'s own
    output applies, and the finished folder is marked as ``owner``'s (:func:`mark_output`).
    """
    out = check_output_dir(out, overwrite, owner=owner)
    # A folder left by a killed run (``.NAME.tmp-*`` whose process is gone) is ours to remove.
    remove_stale_temps(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    except OSError as e:
        problem = write_problem(e, out)
        if problem is None:
            raise
        raise problem from None
    try:
        os.chmod(tmp, 0o755)  # mkdtemp makes 0700; the result should look like any other directory
        (tmp / ".owner").write_text(str(os.getpid()))
        yield tmp
        (tmp / ".owner").unlink(missing_ok=True)
        if owner is not None:
            mark_output(tmp, owner)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        problem = write_problem(e, tmp) if isinstance(e, OSError) else None
        if problem is None:
            raise
        raise problem from None
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def remove_stale_temps(out: str | os.PathLike) -> list[Path]:
    """Remove ``.NAME.tmp-*`` / ``.NAME.old-*`` siblings of ``out`` left by a killed process.

    :func:`atomic_dir` names its temporary folder ``.NAME.tmp-<random>`` and records its pid
    in a ``.owner`` file inside; one whose pid is no longer alive (or that has no owner
    record and has not been touched for an hour) is a leftover.  Returns what was removed.
    """
    out = Path(out)
    removed = []
    if not out.parent.is_dir():
        return removed
    for p in out.parent.glob(f".{glob.escape(out.name)}.*-*"):
        if not p.is_dir() or not (p.name.startswith(f".{out.name}.tmp-") or p.name.startswith(f".{out.name}.old-")):
            continue
        if _owner_alive(p):
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
    return removed


def _owner_alive(tmp: Path) -> bool:
    owner = tmp / ".owner"
    try:
        pid = int(owner.read_text().strip())
    except (OSError, ValueError):
        try:
            return time.time() - tmp.stat().st_mtime < 3600
        except OSError:
            return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


#: Environment variable that moves the Nimbus cache folder (LPIPS weights, undistorted images).
CACHE_ENV = "NIMBUS_CACHE"


def cache_root() -> Path:
    """The Nimbus cache folder: ``$NIMBUS_CACHE`` if set, else ``~/.cache/nimbus`` (nothing is created here)."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "nimbus"


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
