"""Subcommands of ``nimbus-bench``: each verb's module defines HELP, EXAMPLE, add_arguments(parser) and run(args).

The library code they call lives beside them in :mod:`benchmark` (:mod:`~benchmark.score`,
:mod:`~benchmark.reference`, :mod:`~benchmark.tradeoff`, :mod:`~benchmark.stability`,
:mod:`~benchmark.grid`, ...).
"""
