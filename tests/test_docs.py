"""The documentation: the site builds strictly (no broken link or anchor, no page left out of the navigation),
its command reference covers every verb of every tool, and the README's links point at files that exist."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (it comes with the test extra: pip install -e '.[test]')")
    pytest.importorskip("material", reason="mkdocs-material is not installed (it comes with the test extra)")
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # the theme's notice about its successor, not a warning of ours
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                            str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, f"mkdocs build --strict failed:\n{build.stdout}\n{build.stderr}"
    return out


def test_site_builds_strictly(site):
    assert (site / "index.html").is_file()
    for page in ("install", "data", "weather", "methods", "benchmark", "tables", "viewer-report", "performance", "cli"):
        assert (site / page / "index.html").is_file(), page


@pytest.mark.parametrize("tool, module", [("nimbus-synth", "weather_synth.cli"), ("nimbus-bench", "benchmark.cli")])
def test_command_reference_has_every_verb(site, tool, module):
    import importlib

    html = (site / "reference" / tool / "index.html").read_text()
    for verb in importlib.import_module(module).COMMANDS:
        assert f'id="{verb}"' in html, f"{tool} {verb} is missing from the generated command reference"
        assert f"usage: {tool} {verb}" in html


def test_single_command_tools_have_their_help(site):
    for tool in ("nimbus-train", "nimbus-view"):
        assert f"usage: {tool}" in (site / "reference" / tool / "index.html").read_text()


def test_every_registered_method_is_listed(site):
    from nimbus.methods.registry import METHODS

    html = (site / "reference" / "methods" / "index.html").read_text()
    for name in METHODS:
        assert f"<code>{name}</code>" in html, name


def test_readme_links_resolve():
    readme = (ROOT / "README.md").read_text()
    links = [t for t in re.findall(r"\]\(([^)\s]+)\)", readme) if "://" not in t and not t.startswith("#")]
    assert links, "the README links into docs/"
    missing = [t for t in links if not (ROOT / t.split("#")[0]).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"
