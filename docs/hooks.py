"""mkdocs hooks (``hooks:`` in mkdocs.yml): pages made at build time from the code and the records.

* ``reference/<tool>.md``: each command-line tool's ``--help`` and every verb's, rendered from the tools' own
  argparse parsers (``build_parser()``), so the command reference cannot go stale.
* ``reference/methods.md``: every registered method (``nimbus.methods.registry.METHODS``) with what it changes.
* ``reference/tools.md``: ``tools/README.md``, the developer and research scripts of a checkout (not installed).
* ``reference/records.md``: the declared schema of every record Nimbus reads back (``nimbus.schemas``): each
  field, its JSON type, whether it is required, what it holds.
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


def _json_type(prop: dict, defs: dict) -> str:
    """A JSON Schema property as words: ``number or null``, ``list of PerViewScore``, ``non-empty string``."""
    if "anyOf" in prop:
        return " or ".join(_json_type(p, defs) for p in prop["anyOf"])
    if "$ref" in prop:
        return prop["$ref"].rsplit("/", 1)[-1]
    if "enum" in prop or "const" in prop:
        return " or ".join(f'`"{v}"`' for v in prop.get("enum", [prop.get("const")]))
    kind = prop.get("type", "any value")
    if kind == "array":
        low, high = prop.get("minItems"), prop.get("maxItems")
        count = ("" if low is None and high is None else f" ({low} entries)" if low == high
                 else f" ({low or 0}-{high} entries)" if high is not None else f" (at least {low})")
        items = prop.get("items")
        return f"list{count}" + (f" of {_json_type(items, defs)}" if items else "")
    if kind == "object":
        values = prop.get("additionalProperties")
        return f"object of {_json_type(values, defs)}" if isinstance(values, dict) else "object"
    words = {"string": "string", "number": "number (finite)", "integer": "integer", "null": "null",
             "boolean": "true or false"}.get(kind, kind)
    if prop.get("minLength") == 1:
        words = "non-empty " + words
    bounds = [f"{op} {prop[key]}" for key, op in (("minimum", ">="), ("maximum", "<=")) if key in prop]
    return words + (f" ({', '.join(bounds)})" if bounds else "")


def _schema_table(schema: dict, defs: dict) -> list[str]:
    required = set(schema.get("required", []))
    extra = schema.get("additionalProperties", True) is not False
    lines = ["| field | type | required | what it holds |", "| --- | --- | --- | --- |"]
    for name, prop in schema.get("properties", {}).items():
        lines.append(f"| `{name}` | {_json_type(prop, defs)} | {'yes' if name in required else ''} | "
                     f"{prop.get('description', '').replace('|', '/')} |")
    lines += ["", "Other fields are allowed and not checked." if extra else "No other field is allowed.", ""]
    return lines


def records_page() -> str:
    """Each record kind of ``nimbus.schemas``: its fields as a table, then the tables of its nested objects."""
    _checkout_first()
    from nimbus import schemas

    kinds = [("`results.jsonl`: one line per finished cell attempt", schemas.ResultRecord),
             ("A run folder's `config.json`", schemas.RunConfig),
             ("`transforms.json` (Blender / nerfstudio scenes)", schemas.TransformsFile),
             ("`transforms.json`: each entry of `frames`", schemas.TransformsFrame),
             ("A built-in scene's `manifest.json`", schemas.SceneManifest),
             ("A degraded setting's `manifest.json`", schemas.SettingManifest)]
    lines = ["# Record schemas", "",
             "Generated when the site is built, from `nimbus/schemas.py`: the one declared schema of each kind of "
             "record Nimbus reads back, checked on every read before any field is used. A number must be finite "
             "(`NaN` and `Infinity` are refused) and types are strict (`\"1\"` is no number, `true` no integer). A "
             "record that does not fit is one line naming the file, the line of a JSON Lines file, and the field: "
             "skipped with a warning in a results store (the rest still reads), an error for a file that is the "
             "input by itself. What the store does with them: [The benchmark](../benchmark.md#the-results-store).",
             ""]
    for title, model in kinds:
        schema = model.model_json_schema()
        defs = schema.get("$defs", {})
        doc = re.sub(r":\w+:`~?(?:[\w]+\.)*(\w+)`", r"`\1`", model.__doc__.splitlines()[0]).replace("``", "`")
        lines += [f"## {title}", "", f"`nimbus.schemas.{model.__name__}`: {doc}", ""]
        lines += _schema_table(schema, defs)
        for name, sub in defs.items():
            lines += [f"`{name}`:", ""] + _schema_table(sub, defs)
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
    files.append(File.generated(config, "reference/records.md", content=records_page()))
    pages = _table_pages()
    folders = {Path(p).stem for p in pages}
    for uri, source in pages.items():
        files.append(File.generated(config, uri, content=_site_links(source.read_text(), folders)))
    return files


if __name__ == "__main__":
    for tool in sys.argv[1:] or TOOLS:
        print(reference_page(tool))
