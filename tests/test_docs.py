"""The README stays short and its snippets stay true; the documentation site builds strictly.

The README is the front page (at most 150 lines, none over 300 characters); everything else lives on the site
(`docs/`, `mkdocs.yml`), whose strict build fails on a broken link, a page left out of the navigation or a
docstring mkdocstrings cannot read. CI builds the site too (`.ci/run`); here it is built when mkdocs is
installed (`pip install -e ".[docs]"`).
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import wpot

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES, MAX_LINE_CHARS = 150, 300


def _readme() -> str:
    return README.read_text(encoding="utf-8")


def _python_snippets() -> list[str]:
    return re.findall(r"```python\n(.*?)```", _readme(), re.S)


def test_readme_is_short():
    lines = _readme().splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines (at most {MAX_LINES}): move the rest to docs/"
    long = [(i + 1, len(line)) for i, line in enumerate(lines) if len(line) > MAX_LINE_CHARS]
    assert not long, f"README.md lines over {MAX_LINE_CHARS} characters (line, length): {long}"


def _wpot_names() -> list[str]:
    names: set[str] = set()
    for snippet in _python_snippets():
        code = "\n".join(line.split("#", 1)[0] for line in snippet.splitlines())  # comments are prose
        names.update(re.findall(r"\bwpot(?:\.[A-Za-z_]\w*)+", code))
    return sorted(names)


def test_readme_has_python_snippets_that_use_wpot():
    assert len(_python_snippets()) >= 3, "the README shows three snippets: compare, all-vs-all, find a part"
    assert _wpot_names(), "the README's snippets name no wpot.* attribute"


def _resolve(dotted: str):
    """``wpot.a.b.c`` by attribute access from ``wpot`` (a submodule not yet imported is imported)."""
    obj, path = wpot, "wpot"
    for part in dotted.split(".")[1:]:
        path = f"{path}.{part}"
        try:
            obj = getattr(obj, part)
        except AttributeError:
            obj = importlib.import_module(path)
    return obj


@pytest.mark.parametrize("name", _wpot_names())
def test_every_wpot_name_in_the_readme_resolves(name):
    assert _resolve(name) is not None, name


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("mkdocs") is None and importlib.util.find_spec("mkdocs") is None,
                    reason='mkdocs is not installed (pip install -e ".[docs]")')
def test_the_site_builds_strictly(tmp_path):
    for plugin in ("material", "mkdocstrings_handlers.python", "mkdocs_jupyter"):
        if importlib.util.find_spec(plugin.split(".")[0]) is None:
            pytest.skip(f'{plugin} is not installed (pip install -e ".[docs]")')
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-8000:]
    site = tmp_path / "site"
    for page in ("index.html", "results/index.html", "cli/index.html", "api/index.html",
                 "notebooks/quickstart/index.html"):
        assert (site / page).is_file(), f"the site has no {page}"
    # the CLI page is generated from the parser: every subcommand is on it
    from wpot.cli import build_parser

    subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    cli = (site / "cli" / "index.html").read_text(encoding="utf-8")
    for command in subs.choices:
        assert f"wpot {command}" in cli, f"the CLI page does not show `wpot {command}`"
