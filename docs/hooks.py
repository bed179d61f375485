"""MkDocs hooks: the pages that follow the code are generated at build time, never written by hand.

- **API reference**: the source trees of ``wpot`` and ``render`` are walked, and every public module or package
  (no path component starting with ``_``) gets one page holding ``::: module.path`` for mkdocstrings, which
  reads the docstrings statically (griffe: nothing is imported, so no Warp kernel is compiled). The navigation
  follows the package tree, so the reference follows the layout, whatever it becomes. The overview page lists
  every public ``wpot.*`` name (``wpot._EXPORTS``, read from the source with ``ast``) beside its module.
- **CLI**: ``wpot.cli.build_parser()`` is imported and every subcommand's ``--help`` is written from argparse.
- **Tutorials**: the notebooks in ``notebooks/`` are handed to mkdocs-jupyter where they are (not copied), as
  pages ``notebooks/<name>/``; they are stored executed, so the site shows their outputs without running them.

mkdocs.yml names the sections ("API reference", "Tutorials") whose navigation entries are filled in here.
"""
from __future__ import annotations

import ast
import os
import sys
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
#: the top-level packages whose modules get API pages
PACKAGES = ("wpot", "render")
NOTEBOOKS = ROOT / "notebooks"
API_SECTION, TUTORIALS_SECTION = "API reference", "Tutorials"


# ----------------------------------------------------------------------------------------------- the package tree
def _public(parts: tuple[str, ...]) -> bool:
    return not any(p.startswith("_") for p in parts)


def modules() -> list[str]:
    """Dotted names of every public module and package under `PACKAGES`, in tree order."""
    names: list[str] = []
    for pkg in PACKAGES:
        base = ROOT / pkg
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if not _public(parts) or "__pycache__" in parts:
                continue
            # a module inside a folder that is not a package is not importable: skip it
            if not all((ROOT.joinpath(*parts[:k]) / "__init__.py").is_file() for k in range(1, len(parts))):
                continue
            names.append(".".join(parts))
    return sorted(set(names), key=lambda n: n.split("."))


def is_package(name: str) -> bool:
    return (ROOT.joinpath(*name.split(".")) / "__init__.py").is_file()


def api_path(name: str) -> str:
    return f"api/{name}.md"


def _nav_for(prefix: str, names: list[str]) -> list:
    """Nested navigation: a package is a section holding its own page, its modules, then its subpackages."""
    children = [n for n in names if n.startswith(prefix + ".") and n.count(".") == prefix.count(".") + 1]
    entries: list = [{prefix: api_path(prefix)}]
    for child in children:
        if is_package(child):
            entries.append({child: _nav_for(child, names)})
        else:
            entries.append({child: api_path(child)})
    return entries


def api_nav(names: list[str]) -> list:
    nav: list = [{"Overview": "api/index.md"}]
    for pkg in PACKAGES:
        if pkg in names:
            nav.append({pkg: _nav_for(pkg, names)})
    return nav


# --------------------------------------------------------------------------------------------- generated pages
def public_names() -> dict[str, str]:
    """``wpot._EXPORTS`` (public name -> defining module), read from the source without importing it."""
    tree = ast.parse((ROOT / "wpot" / "__init__.py").read_text(encoding="utf-8"))
    for node in tree.body:
        target = node.target if isinstance(node, ast.AnnAssign) else (
            node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1 else None)
        if isinstance(target, ast.Name) and target.id == "_EXPORTS" and node.value is not None:
            return dict(ast.literal_eval(node.value))
    return {}


def _page_of(module: str, names: list[str]) -> str:
    """The generated page that documents ``module``: its own, or its nearest public parent package's."""
    parts = module.split(".")
    while parts and ".".join(parts) not in names:
        parts.pop()
    return ".".join(parts) if parts else PACKAGES[0]


def api_page(name: str) -> str:
    kind = "package" if is_package(name) else "module"
    source = name.replace(".", "/") + ("/__init__.py" if kind == "package" else ".py")
    lines = [f"# `{name}`", "", f"*{kind}* · source: `{source}`", ""]
    if name == PACKAGES[0]:
        lines += ["Its public names are imported lazily, so they are listed on the [overview](index.md), each "
                  "beside the module that defines it.", ""]
    lines += [f"::: {name}", "    options:", "      show_submodules: false", ""]
    return "\n".join(lines)


def api_index(names: list[str]) -> str:
    lines = [
        "# API reference",
        "",
        "Generated from the docstrings at build time: one page per public module or package of `wpot` and "
        "`render`, in the order of the source tree (the navigation on the left). Docstrings give array shapes "
        "like `(N, 3) float64` and the paper's equation numbers; [The method](../method.md) maps the equations "
        "to modules.",
        "",
        "## Every public `wpot.*` name",
        "",
        "`import wpot` is cheap: each name below is imported from its module when first used (Warp is loaded "
        "only by a name that needs it).",
        "",
        "| name | defined in |",
        "| --- | --- |",
    ]
    for pub, module in sorted(public_names().items(), key=lambda kv: (kv[1], kv[0].lower())):
        page = _page_of(module, names)
        lines.append(f"| [`wpot.{pub}`]({page}.md#{module}.{pub}) | [`{module}`]({page}.md) |")
    lines += ["", "## Modules", ""]
    for name in names:
        depth = name.count(".")
        lines.append(f"{'    ' * depth}- [`{name}`]({name}.md)")
    return "\n".join(lines) + "\n"


def cli_page() -> str:
    """Every subcommand's help, as argparse formats it (80 columns)."""
    import argparse

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        if str(ROOT) not in sys.path:
            sys.path.insert(0, str(ROOT))
        from wpot.cli import build_parser

        parser = build_parser()
        subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        lines = [
            "# Command line",
            "",
            "Generated at build time from `wpot.cli.build_parser()`: what `wpot COMMAND --help` prints. "
            "The stage pages of the guide say when to use each option; [Results](results.md) says how well.",
            "",
            "```text",
            parser.format_help().rstrip(),
            "```",
            "",
        ]
        for name, sub in subs.choices.items():
            lines += [f"## `wpot {name}`", "", "```text", sub.format_help().rstrip(), "```", ""]
        return "\n".join(lines)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def notebooks() -> list[Path]:
    return sorted(NOTEBOOKS.glob("*.ipynb"))


def _notebook_title(path: Path) -> str:
    import json

    try:
        for cell in json.loads(path.read_text(encoding="utf-8")).get("cells", []):
            if cell.get("cell_type") == "markdown":
                first = "".join(cell.get("source", "")).strip().splitlines()
                if first and first[0].startswith("# "):
                    return first[0][2:].split(":")[0].strip()
    except (OSError, ValueError):
        pass
    return path.stem.replace("_", " ")


# --------------------------------------------------------------------------------------------------- the hooks
def _replace_section(nav: list, title: str, entries: list) -> bool:
    for item in nav:
        if isinstance(item, dict) and title in item:
            item[title] = entries
            return True
        if isinstance(item, dict):
            for value in item.values():
                if isinstance(value, list) and _replace_section(value, title, entries):
                    return True
    return False


def on_config(config):
    nav = config.get("nav")
    if nav:
        _replace_section(nav, API_SECTION, api_nav(modules()))
        tutorials = [{"About the notebooks": "tutorials/index.md"}]
        tutorials += [{_notebook_title(nb): nb.relative_to(ROOT).as_posix()} for nb in notebooks()]
        _replace_section(nav, TUTORIALS_SECTION, tutorials)
    return config


@event_priority(50)  # before mkdocs-jupyter's on_files, which turns the .ipynb files into pages
def on_files(files: Files, config) -> Files:
    names = modules()
    files.append(File.generated(config, "api/index.md", content=api_index(names)))
    for name in names:
        files.append(File.generated(config, api_path(name), content=api_page(name)))
    files.append(File.generated(config, "cli.md", content=cli_page()))
    for nb in notebooks():
        # a real file of the repository, read where it is (mkdocs-jupyter wraps it, so not File.generated)
        files.append(File(nb.relative_to(ROOT).as_posix(), src_dir=str(ROOT), dest_dir=config["site_dir"],
                          use_directory_urls=config["use_directory_urls"]))
    return files
