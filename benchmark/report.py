"""Plain-text pieces of the benchmark's reports (stability, the HTML report): short messages."""

from __future__ import annotations


def shorten(text: str, n: int) -> str:
    """``text`` on one line (runs of white space made one space), cut to ``n`` characters with ``...``."""
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."
