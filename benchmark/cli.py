"""``nimbus-bench``: score renders against ground truth, and (later) run, tabulate and stress the benchmark.

Each subcommand lives in its own module (see :class:`nimbus.cli_util.SubcommandTool`);
adding a subcommand is one entry in :data:`COMMANDS`.
"""

from nimbus.cli_util import SubcommandTool

# Subcommand name -> module defining it (order is the order in --help).
COMMANDS = {
    "setup-weights": "benchmark.setup_weights",
    "score": "benchmark.score",
    "run": "benchmark.run",
    "tables": "benchmark.tables_cmd",
    "reference": "benchmark.reference",
    "tradeoff": "benchmark.tradeoff",
    "stability": "benchmark.stability",
    "hostile": "benchmark.hostile",
}

TOOL = SubcommandTool(
    "nimbus-bench",
    "Benchmark 3D reconstruction under bad weather: PSNR / SSIM / LPIPS of any method's renders.",
    COMMANDS,
)
build_parser, main = TOOL.build_parser, TOOL.main

if __name__ == "__main__":
    main()
