"""What every Nimbus command-line tool shares: error handling and argument helpers."""

from __future__ import annotations

import argparse
import sys
import warnings
from typing import Callable, Sequence

from nimbus.errors import NimbusError, SkippedRecordWarning

#: Seeds every Nimbus tool accepts: non-negative and below 2**32, the largest seed every generator
#: a seed reaches takes (COLMAP's is an unsigned 32-bit int; numpy's legacy seeding stops there too).
MAX_SEED = 2**32 - 1


def check_seed(seed: object, what: str = "seed") -> int:
    """``seed`` as an int in [0, :data:`MAX_SEED`]; anything else raises :class:`NimbusError`."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise NimbusError(f"{what} must be an integer in [0, {MAX_SEED}], got {seed!r}; pick a smaller "
                          "non-negative seed")
    return seed


def seed_arg(text: str) -> int:
    """argparse type of ``--seed``: an integer in [0, :data:`MAX_SEED`], else a usage error (exit 2, one line)."""
    try:
        return check_seed(int(text))
    except (ValueError, NimbusError):
        raise argparse.ArgumentTypeError(f"seed must be an integer in [0, {MAX_SEED}], got {text!r}; pick a "
                                         "smaller non-negative seed") from None


def pick_by_name(items: Sequence, spec: str | None, what: str, list_command: str) -> list:
    """The ``items`` (each with a ``name``) named in a comma-separated ``spec``, in ``items`` order.

    None, ``""`` or ``all`` selects every item.  An unknown name is a :class:`NimbusError` that lists
    the valid names and the command (``list_command``) that describes them.
    """
    if spec is None or spec.strip() in ("", "all"):
        return list(items)
    by_name = {item.name: item for item in items}
    names = [n.strip() for n in spec.split(",") if n.strip()]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise NimbusError(f"unknown {what}(s) {', '.join(unknown)}; choose from {', '.join(by_name)} "
                          f"({list_command} describes them)")
    return [item for item in items if item.name in names]


def run_cli(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """Run ``main``; a :class:`NimbusError` becomes one ``error: ...`` line and exit code 2, and a
    :class:`SkippedRecordWarning` one ``warning: ...`` line (other warnings show as Python shows them)."""
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, SkippedRecordWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        return int(main(argv) or 0)
    except NimbusError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        # A full disk or a name too long for the file system, met by a write outside the atomic writers (a log
        # line, a library's own file): the user's to fix, so one line too.  Any other OSError is a bug's traceback.
        from nimbus.utils.fs import write_problem

        problem = write_problem(e, e.filename if isinstance(e.filename, str) else None)
        if problem is None:
            raise
        print(f"error: {problem}", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = shown


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps example blocks as written and shows defaults."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the project's error format (one ``error:`` line, exit 2)."""

    def error(self, message: str) -> None:  # noqa: D401 - argparse API
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


class SubcommandTool:
    """A command-line tool whose subcommands each live in their own module.

    ``commands`` maps subcommand name -> module path, in ``--help`` order.  Each module
    defines ``HELP`` (one line), ``EXAMPLE`` (one command line), ``add_arguments(parser)``
    and ``run(args) -> int``.  ``--help`` lists every subcommand with its example.
    """

    def __init__(self, prog: str, description: str, commands: dict[str, str]) -> None:
        self.prog, self.description, self.commands = prog, description, commands

    def build_parser(self) -> ArgumentParser:
        import importlib

        modules = {name: importlib.import_module(mod) for name, mod in self.commands.items()}
        width = max(len(name) for name in modules) + 2
        epilog = "commands:\n" + "\n".join(
            f"  {name:<{width}} {m.HELP}\n  {'':<{width}} e.g. {m.EXAMPLE}" for name, m in modules.items())
        parser = ArgumentParser(prog=self.prog, description=self.description, epilog=epilog,
                                formatter_class=HelpFormatter)
        sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
        for name, m in modules.items():
            p = sub.add_parser(name, help=m.HELP, description=f"{m.HELP}\n\nexample:\n  {m.EXAMPLE}",
                               formatter_class=HelpFormatter)
            m.add_arguments(p)
            p.set_defaults(_run=m.run)
        return parser

    def run(self, argv: Sequence[str] | None = None) -> int:
        """Parse ``argv`` and run the subcommand (a NimbusError propagates; see :meth:`main`)."""
        args = self.build_parser().parse_args(argv)
        return args._run(args)

    def main(self, argv: Sequence[str] | None = None) -> int:
        """Console-script entry point: ``error: ...`` and exit 2 on a user error."""
        raise SystemExit(run_cli(self.run, argv))
