"""Plain-text pieces of the benchmark's reports (stability, tradeoff): CSV of row dicts, short messages."""

from __future__ import annotations

import csv
import io
from typing import Any, Callable, Iterable, Sequence


def rows_csv(rows: Iterable[dict], columns: Sequence[str], cell: Callable[[dict, str], Any]) -> str:
    """CSV text: a header of ``columns``, then ``cell(row, column)`` for each row (``\\n`` line ends)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([cell(r, c) for c in columns])
    return buf.getvalue()


def shorten(text: str, n: int) -> str:
    """``text`` on one line (runs of white space made one space), cut to ``n`` characters with ``...``."""
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."
