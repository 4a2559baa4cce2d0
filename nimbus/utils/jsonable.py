"""Plain JSON values for every file the project writes (results, scores, manifests, records)."""

from __future__ import annotations

import math
import os
from typing import Any, Literal

import numpy as np

#: The spelling of each non-finite float under ``nonfinite="text"`` (``float()`` reads them back).
_TEXT = {math.inf: "inf", -math.inf: "-inf"}


def jsonable(obj: Any, nonfinite: Literal["null", "text"] = "null") -> Any:
    """``obj`` with every value JSON can hold as it is: what :func:`json.dumps` writes as strict JSON.

    Dict keys become ``str``; tuples, lists and numpy arrays become lists; numpy scalars become
    Python numbers; paths become ``str``; containers are converted recursively.

    Strict JSON (RFC 8259) has no Infinity or NaN, and the tokens :mod:`json` writes for them
    are refused by other readers, so no non-finite float is written as a number.  What it
    becomes depends on what the file records, and the caller says which:

    ``"null"`` (default): measurements (scores, results records, reports)
        null, "no finite value": the PSNR of two identical images, a failed metric.  Tables
        show it as n/a.
    ``"text"``: parameters and sampled values (the synthesizer's manifests)
        ``"inf"``, ``"-inf"``, ``"nan"``.  There infinity is a setting (``haze.beta=inf``: an
        opaque medium) that null, "not set", would misreport; the strings keep it readable.
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v, nonfinite) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, nonfinite) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), nonfinite)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if nonfinite == "null" else _TEXT.get(obj, "nan")
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj
