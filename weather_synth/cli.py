"""``nimbus-synth``: make scenes (built-in or from photos) and degrade them with weather."""

from __future__ import annotations

import importlib
from typing import Sequence

from nimbus.cli_util import ArgumentParser, HelpFormatter, run_cli

# Subcommand name -> module in weather_synth.commands (order is the order in --help).
COMMANDS = ("scene", "sfm", "degrade", "demo", "preview")


def build_parser() -> ArgumentParser:
    modules = {name: importlib.import_module(f"weather_synth.commands.{name}") for name in COMMANDS}
    epilog = "commands:\n" + "\n".join(
        f"  {name:<8} {m.HELP}\n           e.g. {m.EXAMPLE}" for name, m in modules.items()
    )
    parser = ArgumentParser(
        prog="nimbus-synth",
        description="Make multi-view scenes and weather-degraded benchmarks (haze, rain, snow and their mixes).",
        epilog=epilog,
        formatter_class=HelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, m in modules.items():
        p = sub.add_parser(name, help=m.HELP, description=f"{m.HELP}\n\nexample:\n  {m.EXAMPLE}",
                           formatter_class=HelpFormatter)
        m.add_arguments(p)
        p.set_defaults(_run=m.run)
    return parser


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    return args._run(args)


def main(argv: Sequence[str] | None = None) -> int:
    raise SystemExit(run_cli(_main, argv))


if __name__ == "__main__":
    main()
