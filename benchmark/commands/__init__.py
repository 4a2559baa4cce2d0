"""Subcommands of ``nimbus-bench``: each verb's module defines HELP, EXAMPLE, add_arguments(parser) and run(args).

The library code they call lives beside them in :mod:`benchmark` (:mod:`~benchmark.score`,
:mod:`~benchmark.reference`, :mod:`~benchmark.tradeoff`, :mod:`~benchmark.stability`,
:mod:`~benchmark.grid`, ...).
"""

#: ``--help`` of the ``--methods`` row order of ``tables``, ``report`` and ``compare`` (split by
#: :func:`benchmark.store.split_method_labels`).
METHODS_ORDER_HELP = ("row order: comma list of methods listed first; a method the store holds under several sets of "
                      "--set overrides is named with them, e.g. nimbus[lambda_dehaze=0] or nimbus[a=1,b=2] (keys sorted)")
