"""Subcommands of ``nimbus-synth``: each module defines HELP, EXAMPLE, add_arguments(parser) and run(args)."""
