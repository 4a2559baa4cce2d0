"""What every Nimbus command-line tool shares: error handling and argument helpers."""

from __future__ import annotations

import argparse
import sys
from typing import Callable, Sequence

from nimbus.errors import NimbusError


def run_cli(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """Run ``main``; a :class:`NimbusError` becomes one ``error: ...`` line and exit code 2."""
    try:
        return int(main(argv) or 0)
    except NimbusError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted; no partial output was kept", file=sys.stderr)
        return 130


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps example blocks as written and shows defaults."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the project's error format (one ``error:`` line, exit 2)."""

    def error(self, message: str) -> None:  # noqa: D401 - argparse API
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)
