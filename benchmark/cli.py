"""``nimbus-bench``: run the benchmark grid, score renders, write tables and reports, and stress the tools.

Each subcommand lives in its own module of :mod:`benchmark.commands` (see :class:`nimbus.cli_util.SubcommandTool`);
adding a subcommand is one module there and its name in :data:`COMMANDS`.
"""

import nimbus.cli  # noqa: F401  (first: the OpenMP wait policy, before anything loads torch)
from nimbus.cli_util import SubcommandTool

# Subcommand name -> module defining it (order is the order in --help).
COMMANDS = {name: f"benchmark.commands.{name.replace('-', '_')}"
            for name in ("setup-weights", "setup-kernels", "score", "run", "tables", "compare", "reference", "tradeoff",
                         "stability", "report", "export", "decompose")}

TOOL = SubcommandTool(
    "nimbus-bench",
    "Benchmark 3D reconstruction under bad weather: PSNR / SSIM / LPIPS of any method's renders.",
    COMMANDS,
)
build_parser, main = TOOL.build_parser, TOOL.main

if __name__ == "__main__":
    main()
