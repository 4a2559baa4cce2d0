"""Checkpoint files: what they may hold, and how they are written and read back.

A checkpoint is one ``torch.save`` of a dict of tensors and plain values only
(:func:`check_plain`), read back with ``torch.load(weights_only=True)``, so a run folder
received from someone else cannot execute anything on ``--resume``.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
from pathlib import Path
from typing import Any

import torch

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

#: The latest checkpoint of a run folder, and the state before a step that diverged.
CHECKPOINT = "checkpoint.pt"
LAST_GOOD = "checkpoint_last_good.pt"

#: What a checkpoint may hold: tensors and these plain values, in dicts / lists / tuples.  This is what
#: ``torch.load(weights_only=True)`` rebuilds without running code from the file, so a run folder received
#: from someone else cannot execute anything on ``--resume``.
PLAIN_TYPES = (type(None), bool, int, float, str)


def check_plain(obj: Any, where: str = "state") -> None:
    """Raise TypeError unless ``obj`` is tensors and :data:`PLAIN_TYPES` in dicts, lists and tuples.

    Called on every checkpoint before it is written, so a method that puts a numpy scalar,
    a dataclass or a module into its ``state_dict()`` fails at once (a
    programming error) instead of writing a checkpoint that ``--resume`` would refuse.
    """
    if isinstance(obj, torch.Tensor) or type(obj) in PLAIN_TYPES:
        return
    if type(obj) in (dict, collections.OrderedDict):  # modules' state_dict() are OrderedDicts
        for k, v in obj.items():
            if type(k) not in (str, int):
                raise TypeError(f"{where} has a {type(k).__name__} key {k!r}; checkpoint keys must be str or int")
            check_plain(v, f"{where}[{k!r}]")
        return
    if type(obj) in (list, tuple):
        for i, v in enumerate(obj):
            check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"{where} is a {type(obj).__module__}.{type(obj).__qualname__}; a checkpoint holds only "
                    "tensors, None, bool, int, float and str in dicts, lists and tuples (torch.load weights_only)")




def write_checkpoint(path: str | os.PathLike, state: dict) -> Path:
    """Check ``state`` (:func:`check_plain`) and write it to ``path`` atomically."""
    check_plain(state)
    buf = io.BytesIO()
    torch.save(state, buf)
    return atomic_write_bytes(path, buf.getvalue())


def read_checkpoint(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict:
    """The state saved in ``path``, tensors moved to ``device``.

    The file is read with ``torch.load(weights_only=True)``: only tensors and plain values
    are rebuilt, never arbitrary objects, since unpickling those can run code that the
    file names.  A file holding anything else (a foreign or tampered file, a checkpoint of
    an old Nimbus that pickled objects), or a truncated one, raises :class:`NimbusError`.
    """
    path = Path(path)
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError:
        raise NimbusError(f"checkpoint {path} holds objects other than tensors and plain values (a file "
                          "from an older Nimbus, or one that was tampered with); Nimbus does not load such "
                          "files because unpickling them can run code. Start a new run with --out "
                          "(nothing was loaded)") from None
    except Exception as e:  # a truncated, empty or foreign file
        raise NimbusError(f"cannot read checkpoint {path} ({e.__class__.__name__}: {str(e)[:200]}); it is "
                          "corrupt or not a Nimbus checkpoint. Start a new run with --out") from None
