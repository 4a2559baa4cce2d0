"""Subcommands of ``nimbus-bench``: each verb's module defines HELP, EXAMPLE, add_arguments(parser) and run(args).

The library code they call lives beside them in :mod:`benchmark` (:mod:`~benchmark.score`,
:mod:`~benchmark.reference`, :mod:`~benchmark.tradeoff`, :mod:`~benchmark.stability`,
:mod:`~benchmark.hostile`, :mod:`~benchmark.grid`, ...); :mod:`.case_report` is the frame shared by
the two case reports, not a verb.
"""
