"""Building and loading a compiled kernel library, written once for every extension of :mod:`nimbus.kernels`.

An :class:`Extension` is built from C++ sources in ``nimbus/kernels/csrc`` with
:func:`torch.utils.cpp_extension.load` on first use and cached: in
``$NIMBUS_EXT_DIR/<name>_<tree>`` when that variable is set, else in torch's extension
directory (``$TORCH_EXTENSIONS_DIR`` or ``~/.cache/torch_extensions``), ``<name>`` the
extension's name with the torch version and ``<tree>`` a hash of this source folder, so
that two checkouts never share (and rebuild over) one build, and two extensions never
share one folder.  Processes building one library take turns through an OS file lock
(``flock`` on ``nimbus-build.lock`` in the build folder), which the system releases when its
holder exits or is killed: a process holding it knows no live build is running, so torch's own
lock file found then was left by a killed build and is removed at once, while a slow, niced or
paused build is waited for, however long it takes.  Where ``flock`` is missing (not POSIX, or a
file system without it) a torch lock file is judged stale once its folder has been idle for 3
minutes, as before.  A library's sources compile as one translation unit (:meth:`Extension.build`).  The
first build of all three takes about 35 s on two cores (g++ and ninja); later
processes only load the cached library, and an edited source (or ``common.h``) is rebuilt.

:meth:`Extension.available` builds/loads the library once per process and returns False,
after ONE warning line, when that is impossible (no compiler, failed build); the caller
then uses its torch path.  ``NIMBUS_DISABLE_CPP=1`` makes it return False without trying
and without warning, for every extension.

All extensions share the compiler flags below: portable (no ``-march=native``: the cached
library may be shared between machines; sources add their own per-ISA clones, see
``csrc/common.h``), no ``-ffast-math`` and no FMA contraction, so the kernels' arithmetic
runs as written.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
import time
import warnings
from pathlib import Path

import torch

try:
    import fcntl
except ImportError:  # not POSIX: the idle-folder heuristic alone (_wait_for_build)
    fcntl = None

__all__ = ["Extension", "CSRC"]

#: The C++ sources of all extensions (and their shared header, ``common.h``).
CSRC = Path(__file__).resolve().parent / "csrc"

# -fno-trapping-math lets masked selects be vectorised and changes no result.
# -fopenmp: at::parallel_for runs on torch's OpenMP pool.
_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-Wno-psabi")
_LDFLAGS = ("-fopenmp",)
# torch's build lock is a plain file that a killed build leaves behind, after which every
# later load would wait forever; a build takes well under a minute, so an older lock is stale.
_STALE_LOCK_S = 600.0
# A build in progress writes its object files; a lock with nothing in the folder touched for
# this long is stale even if the lock itself is younger than _STALE_LOCK_S.
_IDLE_BUILD_S = 180.0
_LOCK_POLL_S = 0.5
# Each source tree gets its own build folders: two checkouts (a CI clone, a second worktree)
# sharing one would rebuild over each other on every load, and kill each other's builds.
_TREE_TAG = hashlib.sha1(str(CSRC).encode()).hexdigest()[:8]
# The torch version is part of every name: a cached build is only valid for the torch it was built against.
_TORCH_TAG = "_t" + "".join(ch if ch.isalnum() else "_" for ch in torch.__version__)


def _stale_lock_message(build_dir: str) -> str:
    return f"nimbus: removed a stale compiler lock left by an interrupted build in {build_dir}"


def _clear_stale_lock(build_dir: str, idle_s: float = _IDLE_BUILD_S) -> bool:
    """Remove the build lock when it is older than ``_STALE_LOCK_S`` or nothing in ``build_dir`` has changed
    for ``idle_s`` (its build was killed); True when this call removed it."""
    lock = os.path.join(build_dir, "lock")
    try:
        now = time.time()
        if now - os.path.getmtime(lock) > _STALE_LOCK_S or now - _last_activity(build_dir) > idle_s:
            os.remove(lock)
            return True
    except OSError:  # no lock, or another process removed it first
        pass
    return False


def _last_activity(build_dir: str) -> float:
    """Newest modification time of anything in ``build_dir`` (0 when it cannot be read)."""
    try:
        with os.scandir(build_dir) as it:
            return max((e.stat().st_mtime for e in it), default=0.0)
    except OSError:
        return 0.0


def _wait_for_build(build_dir: str, idle_s: float = _IDLE_BUILD_S, poll_s: float = _LOCK_POLL_S) -> None:
    """Wait while another process holds the build lock; remove it once the folder has been idle for
    ``idle_s`` (its build was killed: torch would otherwise wait for it forever)."""
    lock = os.path.join(build_dir, "lock")
    while os.path.exists(lock):
        if _clear_stale_lock(build_dir, idle_s):
            print(_stale_lock_message(build_dir), file=sys.stderr)
            return
        time.sleep(poll_s)


#: The OS-locked file that serialises the builds of one library (in its build folder).
BUILD_LOCK = "nimbus-build.lock"
#: Seconds a process waits for the build lock before it says so.  Loading a cached build holds the lock
#: for a moment too (torch checks the build), so the benchmark's workers, starting together, would each
#: announce a "build" that is only the other's load.
_QUIET_WAIT_S = 3.0


def _flock_within(handle, seconds: float) -> bool:
    """Take ``handle``'s exclusive flock, trying for up to ``seconds``; True when taken."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


@contextlib.contextmanager
def build_turn(build_dir: str, say=None):
    """Hold the build folder's OS lock (``flock`` on :data:`BUILD_LOCK`) for the ``with`` block.

    A process that holds it is the only live builder of this folder, so torch's lock file found
    then is a leftover of a killed build and is removed.  Waiting for another holder is announced
    once through ``say`` (default: one line on stderr).  Where ``flock`` is unavailable, falls back to
    :func:`_wait_for_build` (stale when the folder has been idle for ``_IDLE_BUILD_S``).
    """
    say = say or (lambda msg: print(msg, file=sys.stderr, flush=True))
    handle = None
    if fcntl is not None:
        try:
            handle = open(os.path.join(build_dir, BUILD_LOCK), "a")  # noqa: SIM115 - closed in finally
            if not _flock_within(handle, _QUIET_WAIT_S):
                say(f"nimbus: waiting for another process to finish building the kernels in {build_dir}")
                fcntl.flock(handle, fcntl.LOCK_EX)
        except OSError:  # a file system without flock, or an unwritable folder: the heuristic below
            if handle is not None:
                handle.close()
            handle = None
    try:
        if handle is None:
            _wait_for_build(build_dir)
        else:
            lock = os.path.join(build_dir, "lock")
            with contextlib.suppress(FileNotFoundError):
                os.remove(lock)
                say(_stale_lock_message(build_dir))
        yield
    finally:
        if handle is not None:
            handle.close()  # closing releases the flock


def disabled() -> bool:
    """Whether ``NIMBUS_DISABLE_CPP`` turns every compiled kernel off (any value but empty or ``0``)."""
    return os.environ.get("NIMBUS_DISABLE_CPP", "") not in ("", "0")


class Extension:
    """One compiled library: its sources, its build folder, and whether it loaded in this process.

    Parameters
    ----------
    name : str
        Library name (``torch.ops`` namespaces are set by the sources' ``TORCH_LIBRARY``);
        the torch version is appended.
    sources : tuple of str
        File names in :data:`CSRC`.
    kernel : str
        What the library is, for the warning (``"compositing kernel"``).
    fallback : str
        What is used instead when it is unavailable, for the warning (``"the slower torch compositor"``).
    """

    def __init__(self, name: str, sources: tuple[str, ...], kernel: str, fallback: str) -> None:
        self.name = name + _TORCH_TAG
        self.sources = tuple(CSRC / s for s in sources)
        self.kernel = kernel
        self.fallback = fallback
        self.state: dict = {"tried": False, "ok": False, "error": None, "warned": False}
        self._lock = threading.Lock()

    def build_dir(self) -> str | None:
        """This library's build folder (None: let torch choose, when its private helper is missing)."""
        if os.environ.get("NIMBUS_EXT_DIR"):
            return os.path.join(os.environ["NIMBUS_EXT_DIR"], f"{self.name}_{_TREE_TAG}")
        from torch.utils import cpp_extension

        try:  # torch's default location (a private helper: tolerate its absence)
            return cpp_extension._get_build_directory(self.name, verbose=False) + f"_{_TREE_TAG}"
        except (AttributeError, TypeError):
            return None

    def build(self) -> None:
        """Build (or load the cached build of) the library into this process; raises on failure."""
        from torch.utils import cpp_extension

        build_dir = self.build_dir()
        turn = contextlib.nullcontext()
        if build_dir is not None:
            os.makedirs(build_dir, exist_ok=True)
            turn = build_turn(build_dir)
        with turn:
            sources, includes = [str(p) for p in self.sources], []
            if build_dir is not None and len(self.sources) > 1:
                sources, includes = [self._unity_source(build_dir)], [str(CSRC)]
            cpp_extension.load(
                name=self.name,
                sources=sources,
                extra_include_paths=includes,
                extra_cflags=list(_CFLAGS),
                extra_ldflags=list(_LDFLAGS),
                build_directory=build_dir,
                is_python_module=False,
                verbose=False,
            )

    def _unity_source(self, build_dir: str) -> str:
        """``build_dir/<name>_unity.cpp``: a file that includes every source, compiled as the library's one
        translation unit.  Parsing torch's headers is most of a small source's compile (about 7 of 9 s), so
        one unit per library parses them once: a fresh build costs about 56 s of one core instead of 89.
        Written only when missing or different (a new file time would make ninja compile again); the
        compiler's dependency file still tracks every included source, so an edited one is rebuilt."""
        path = os.path.join(build_dir, f"{self.name}_unity.cpp")
        text = ("// Generated by nimbus/kernels/extension.py: the library's sources as one translation unit.\n"
                + "".join(f'#include "{p.name}"\n' for p in self.sources))
        try:
            with open(path, encoding="utf-8") as fh:
                if fh.read() == text:
                    return path
        except OSError:
            pass
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
        return path

    def available(self, warn: bool = True) -> bool:
        """Whether the library can be used; builds or loads it on the first call.

        Parameters
        ----------
        warn : bool
            On failure, emit one :class:`RuntimeWarning` per process saying why and what
            is used instead.

        Returns
        -------
        bool
            False when ``NIMBUS_DISABLE_CPP=1`` or when the build/load failed (reason in
            :meth:`load_error`).
        """
        if disabled():
            return False
        with self._lock:
            state = self.state
            if not state["tried"]:
                state["tried"] = True
                try:
                    self.build()
                    state["ok"] = True
                except Exception as exc:  # noqa: BLE001 - any build/load failure means "fall back"
                    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
                    # A compiler's "error:" line says more than ninja's closing "build stopped".
                    errors = [ln for ln in lines if "error:" in ln]
                    line = (errors or lines[-1:] or [repr(exc)])[0]
                    state["error"] = f"{type(exc).__name__}: {line[:300]}"
            if not state["ok"] and warn and not state["warned"]:
                state["warned"] = True
                warnings.warn(f"nimbus: compiled {self.kernel} unavailable ({state['error']}); "
                              f"using {self.fallback}", RuntimeWarning,
                              stacklevel=3)  # the caller of the kernel module's available()
            return state["ok"]

    def load_error(self) -> str | None:
        """Why the library could not be built or loaded (one line), or None."""
        return self.state["error"]

    def require(self, who: str) -> None:
        """Raise RuntimeError naming ``who`` unless the library is loaded (builds it if need be)."""
        if not self.state["ok"] and not self.available(warn=False):
            reason = self.load_error() or "disabled by NIMBUS_DISABLE_CPP"
            raise RuntimeError(f"{who}: the compiled kernel is unavailable ({reason}); "
                               "check available() first and use the torch path")
