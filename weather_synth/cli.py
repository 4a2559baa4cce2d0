"""``nimbus-synth``: make scenes (built-in or from photos) and degrade them with weather."""

import nimbus.cli  # noqa: F401  (first: the OpenMP wait policy, before anything loads torch)
from nimbus.cli_util import SubcommandTool
from weather_synth.config import PROTOCOL_SUMMARIES, PROTOCOLS

# Subcommand name -> module defining it (order is the order in --help).
COMMANDS = {name: f"weather_synth.commands.{name}"
            for name in ("scene", "sfm", "undistort", "degrade", "demo", "preview")}

#: Named in the tool's --help: which protocol draws what per view and per scene.
PROTOCOLS_HELP = "Synthesis protocols (degrade / demo --protocol): " + "; ".join(
    f"{name}{' (default)' if name == PROTOCOLS[0] else ''}: {what}" for name, what in PROTOCOL_SUMMARIES.items()) + "."

TOOL = SubcommandTool(
    "nimbus-synth",
    "Make multi-view scenes and weather-degraded benchmarks (haze, rain, snow and their mixes). " + PROTOCOLS_HELP,
    COMMANDS,
)
build_parser, main = TOOL.build_parser, TOOL.main

if __name__ == "__main__":
    main()
