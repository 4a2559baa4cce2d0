"""``nimbus-bench``: score renders against ground truth, and (later) run, tabulate and stress the benchmark.

Each subcommand lives in its own module, which defines ``HELP`` (one line), ``EXAMPLE``
(one command line), ``add_arguments(parser)`` and ``run(args) -> int``; adding a
subcommand is one entry in :data:`COMMANDS`.
"""

from __future__ import annotations

import importlib
from typing import Sequence

from nimbus.cli_util import ArgumentParser, HelpFormatter, run_cli

# Subcommand name -> module defining it (order is the order in --help).
COMMANDS = {
    "setup-weights": "benchmark.weights",
    "score": "benchmark.score",
}


def build_parser() -> ArgumentParser:
    modules = {name: importlib.import_module(mod) for name, mod in COMMANDS.items()}
    epilog = "commands:\n" + "\n".join(
        f"  {name:<14} {m.HELP}\n                 e.g. {m.EXAMPLE}" for name, m in modules.items()
    )
    parser = ArgumentParser(
        prog="nimbus-bench",
        description="Benchmark 3D reconstruction under bad weather: PSNR / SSIM / LPIPS of any method's renders.",
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
