"""The paper-style tables ``nimbus-bench tables`` writes: one table model, one writer, one module per layout.

==============================  ==============================================================
module                          role
==============================  ==============================================================
:mod:`.model`                   :class:`~.model.Table` (columns, groups, blocks of rows, notes) and the mark rule
:mod:`.writer`                  the one writer: LaTeX, Markdown, long-format CSV; files into a folder
:mod:`.results`                 what the tables read from the results store (finished cells, protocols, means)
:mod:`.comparison`              per-weather method comparisons (``weather_<W>``), ours and the paper's
:mod:`.margins`                 Ours against each other method per setting (``margins``): where it wins
:mod:`.ablation`                the ablation tables (``ablation_*``), ours and the paper's
:mod:`.runtime`                 complexity / runtime (``runtime``), ours and the paper's
:mod:`.provenance`              the counted cells by device, CPU ISA, torch and code; the same-input check
:mod:`.summary`                 the plain-text summary ``nimbus-bench run`` prints
:mod:`.decompose`               one run's decomposition against the ground truth (``nimbus-bench decompose``)
==============================  ==============================================================

A layout module builds :class:`~.model.Table` objects: ``tables(df, method_order) -> (tables,
skipped)`` from the store and ``paper() -> {layout: table}`` from the paper's numbers (package
data, :mod:`benchmark.data`).  A new layout is one such module plus one line in
:data:`benchmark.commands.tables.LAYOUTS`.
"""
