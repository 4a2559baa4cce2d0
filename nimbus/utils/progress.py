"""Progress for steps that are usually quick but can be long (a scene of 100,000 frames): shown only when slow.

A step that ends within :data:`SHOW_AFTER_S` prints nothing, so the common small case stays quiet; one
that goes on longer shows a progress bar (or, for a step with no parts to count, one line) on stderr.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm

#: Seconds a step runs before its progress is shown.
SHOW_AFTER_S = 2.0

T = TypeVar("T")


def slow_progress(items: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """``items``, with a progress bar on stderr from :data:`SHOW_AFTER_S` seconds on (erased when done)."""
    return iter(tqdm(items, desc=desc, total=total, unit=unit, file=sys.stderr, delay=SHOW_AFTER_S, leave=False,
                     dynamic_ncols=True))


@contextlib.contextmanager
def note_if_slow(message: str) -> Iterator[None]:
    """Print ``message`` on stderr if the block is still running after :data:`SHOW_AFTER_S` seconds."""
    timer = threading.Timer(SHOW_AFTER_S, lambda: print(message, file=sys.stderr, flush=True))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
