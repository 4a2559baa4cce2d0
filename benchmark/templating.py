"""The Jinja2 templates of ``benchmark/templates/`` (package data): the report's page and the writer's HTML table.

Autoescaping is on: every value is HTML-escaped unless it is already :class:`markupsafe.Markup` (a section
rendered by another template).  ``| url`` makes a relative path a URL (``+``, spaces and ``%`` in file names
survive); an undefined name is an error, not an empty string.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from urllib.parse import quote


def url(path: str | os.PathLike) -> str:
    """A relative path as a URL path (escaped for HTML by the template)."""
    return quote(Path(path).as_posix())


@functools.cache
def environment():
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("benchmark", "templates"), autoescape=True,
                             undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    env.filters["url"] = url
    return env


def render_template(template: str, /, **context):
    """Template ``template`` rendered with ``context``, as :class:`markupsafe.Markup` (safe to put in another)."""
    from markupsafe import Markup

    return Markup(environment().get_template(template).render(**context))
