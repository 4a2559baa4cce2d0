"""``nimbus-synth``: make scenes (built-in or from photos) and degrade them with weather."""

from nimbus.cli_util import SubcommandTool

# Subcommand name -> module defining it (order is the order in --help).
COMMANDS = {name: f"weather_synth.commands.{name}"
            for name in ("scene", "sfm", "undistort", "degrade", "demo", "preview")}

TOOL = SubcommandTool(
    "nimbus-synth",
    "Make multi-view scenes and weather-degraded benchmarks (haze, rain, snow and their mixes).",
    COMMANDS,
)
build_parser, main = TOOL.build_parser, TOOL.main

if __name__ == "__main__":
    main()
