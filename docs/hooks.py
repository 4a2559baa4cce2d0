"""mkdocs hooks (``hooks:`` in mkdocs.yml): pages made at build time from the code and the records.

* ``reference/<tool>.md``: each command-line tool's ``--help`` and every verb's, rendered from the tools' own
  argparse parsers (``build_parser()``), so the command reference cannot go stale.
* ``reference/methods.md``: every registered method (``nimbus.methods.registry.METHODS``) with what it changes.
* ``reference/tools.md``: ``tools/README.md``, the developer and research scripts of a checkout (not installed).
* ``results/*.md``: the READMEs of the committed table folders (``tables/README.md``, ``tables/<folder>/README.md``)
  and of the reference data (``benchmark/data/README.md``), so the site links to the recorded results and the
  history of how each figure came to be stays beside its table.

Run ``python docs/hooks.py [TOOL]`` to print the generated reference Markdown without building the site.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: tool -> module whose ``build_parser()`` builds its parser (the console scripts of pyproject.toml).
TOOLS = {
    "nimbus-synth": "weather_synth.cli",
    "nimbus-train": "nimbus.cli.train",
    "nimbus-view": "nimbus.cli.view",
    "nimbus-bench": "benchmark.cli",
}
#: ``--help`` is rendered at this width whatever the terminal of the build.
HELP_COLUMNS = 100


def _checkout_first() -> None:
    """Document this checkout, not another installed copy of the packages."""
    if sys.path[:1] != [str(ROOT)]:
        sys.path.insert(0, str(ROOT))


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The verbs of a tool, in ``--help`` order (empty for a tool without verbs)."""
    for action in parser._actions:  # argparse keeps subparsers here and nowhere public
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _help(parser: argparse.ArgumentParser) -> str:
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_COLUMNS)  # argparse reads the width from the environment
    try:
        return parser.format_help().rstrip() + "\n"
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def _fence(text: str) -> str:
    return "```text\n" + text + "```\n"


def reference_page(tool: str) -> str:
    """The Markdown page of one tool: its ``--help``, then one section per verb with the verb's ``--help``."""
    module = TOOLS[tool]
    _checkout_first()
    parser = importlib.import_module(module).build_parser()
    verbs = _subcommands(parser)
    lines = [f"# {tool}", "",
             f"Generated when the site is built, from `{module}.build_parser()`: exactly what `{tool} --help`"
             + (f" and `{tool} COMMAND --help` print." if verbs else " prints."),
             "", _fence(_help(parser))]
    for name, sub in verbs.items():
        lines += [f"## {name}", "", _fence(_help(sub))]
    return "\n".join(lines)


def methods_page() -> str:
    """The registered methods: name, description, the config fields set on top of the preset."""
    _checkout_first()
    from nimbus.methods.registry import METHODS

    def value(v) -> str:  # as --set reads it
        if callable(v):
            return "(scaled to the preset)"
        if isinstance(v, bool):
            return str(v).lower()
        if isinstance(v, tuple):
            return ",".join(value(x) for x in v)
        return str(v)

    def changes(spec) -> str:
        return ", ".join(f"`{k}={value(v)}`" for k, v in spec.changes.items()) or "-"

    lines = ["# Methods", "",
             "Generated when the site is built, from `nimbus.methods.registry.METHODS`: every name "
             "`nimbus-train --method` and `nimbus-bench run --methods` accept, and the config fields each sets on "
             "top of its presets. What the methods are: [Methods](../methods/index.md).", "",
             "| method | what it is | changes |", "| --- | --- | --- |"]
    lines += [f"| `{name}` | {spec.description.replace('|', '/')} | {changes(spec)} |" for name, spec in METHODS.items()]
    return "\n".join(lines) + "\n"


def _table_pages() -> dict[str, Path]:
    """Site path -> source README of the recorded results."""
    pages = {"results/index.md": ROOT / "tables" / "README.md",
             "results/reference-data.md": ROOT / "benchmark" / "data" / "README.md"}
    for readme in sorted((ROOT / "tables").glob("*/README.md")):
        pages[f"results/{readme.parent.name}.md"] = readme
    return pages


#: A link from one table README to another folder's: ``[x](default_tiny/)`` or ``[x](../default_tiny/README.md)``.
TABLE_LINK = re.compile(r"\]\((?:\.\./)?([\w.+-]+)/(?:README\.md)?(#[\w-]+)?\)")


def _site_links(text: str, folders: set[str]) -> str:
    """Point links between table READMEs at their pages (``results/<folder>.md``)."""
    return TABLE_LINK.sub(lambda m: f"]({m.group(1)}.md{m.group(2) or ''})" if m.group(1) in folders
                          else m.group(0), text)


def on_files(files, config):
    from mkdocs.structure.files import File

    for tool in TOOLS:
        files.append(File.generated(config, f"reference/{tool}.md", content=reference_page(tool)))
    files.append(File.generated(config, "reference/methods.md", content=methods_page()))
    files.append(File.generated(config, "reference/tools.md", content=(ROOT / "tools" / "README.md").read_text()))
    pages = _table_pages()
    folders = {Path(p).stem for p in pages}
    for uri, source in pages.items():
        files.append(File.generated(config, uri, content=_site_links(source.read_text(), folders)))
    return files


if __name__ == "__main__":
    for tool in sys.argv[1:] or TOOLS:
        print(reference_page(tool))
