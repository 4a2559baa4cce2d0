"""Reference data shipped inside the package (``README.md`` here says what each file holds).

``paper/``
    The paper's reported numbers, transcribed from ``nimbusgs.tex``: the per-weather
    comparisons (``*.csv``) and the ablation and runtime tables (``ablations/``).
``regression_tiny.json``
    This repository's own figures for the CI regression grid (:mod:`benchmark.reference`).

Read through :mod:`importlib.resources`, so an installed (not only an editable) package finds
them; ``pyproject.toml`` declares them as package data.
"""

from __future__ import annotations

import csv
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # importlib.resources.abc is Python 3.11+
    from importlib.resources.abc import Traversable

#: This folder.  A regular install unpacks package data as files, so this is a real path
#: (``nimbus-bench reference update --regression`` rewrites a file in it).
DATA_DIR = Path(str(files(__name__)))
#: The paper's per-weather comparison tables (``*.csv``).
PAPER_DIR = DATA_DIR / "paper"
#: The paper's ablation and complexity / runtime tables.
PAPER_ABLATIONS_DIR = PAPER_DIR / "ablations"
#: The committed figures of :data:`benchmark.reference.REGRESSION_GRID`.
REGRESSION_REFERENCE = DATA_DIR / "regression_tiny.json"


def read_csv(path: Traversable) -> list[dict[str, str]]:
    """The lines of one of the reference CSV files, as dicts by column name."""
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))
