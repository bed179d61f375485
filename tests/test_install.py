"""What `pip install -e .` sets up (pyproject.toml): a plain path entry for the repository root, which a folder named
wpot in the working directory cannot shadow; and the extras the notebooks need."""
from __future__ import annotations

import ast
import json
import os
import site
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_the_editable_install_is_a_path_entry_for_the_repository_root():
    """setuptools writes a plain .pth entry (the project folder) for an editable install when every package maps
    into one folder named as the packages' root (``package-dir = {"" = "."}``); otherwise it installs an import
    hook, which runs after Python's own path search and so loses to a namespace folder named wpot."""
    setuptools = pytest.importorskip("setuptools")
    tool = _pyproject()["tool"]["setuptools"]
    assert tool["package-dir"] == {"": "."}
    packages = setuptools.find_packages(str(ROOT), include=tool["packages"]["find"]["include"])
    assert {"wpot", "wpot.maps", "wpot.runs", "render"} <= set(packages)
    try:  # the rule setuptools' editable_wheel applies (a private helper: checked where this version has it)
        from setuptools.command.editable_wheel import _simple_layout
    except ImportError:
        return
    assert _simple_layout(packages, tool["package-dir"], str(ROOT))


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python -S -c code`` in ``cwd``: no site-packages but what ``code`` adds, no PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSAFEPATH")}
    return subprocess.run([sys.executable, "-S", "-c", textwrap.dedent(code)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.slow
def test_import_wpot_beside_a_clone_named_wpot(tmp_path):
    """Python started in the folder that holds a clone named ``wpot``: with the root on sys.path as the editable
    install's .pth puts it, ``import wpot`` is the package; with an import hook (the other editable mode),
    the clone's folder is taken for an empty namespace package."""
    (tmp_path / "wpot").symlink_to(ROOT, target_is_directory=True)
    pth = tmp_path / "site"
    pth.mkdir()
    (pth / "__editable__.wpot-0.1.0.pth").write_text(f"{tmp_path / 'wpot'}\n")  # what setuptools writes
    r = _python(f"""
        import site
        site.addsitedir({str(pth)!r})
        for p in {site.getsitepackages()!r}:
            site.addsitedir(p)
        import wpot
        print(wpot.__file__)
        wpot.load_mesh
    """, tmp_path)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.split()[0]) == tmp_path / "wpot" / "wpot" / "__init__.py"
    # the other mechanism: a finder on sys.meta_path that knows where wpot is, as setuptools' hook does
    hook = _python(f"""
        import importlib.util, sys

        class Hook:
            @staticmethod
            def find_spec(name, path=None, target=None):
                if name == "wpot":
                    return importlib.util.spec_from_file_location(
                        "wpot", {str(ROOT / 'wpot' / '__init__.py')!r}, submodule_search_locations=[{str(ROOT / 'wpot')!r}])

        sys.meta_path.append(Hook)
        import wpot
        print(wpot.__file__, hasattr(wpot, "load_mesh"))
    """, tmp_path)
    assert hook.returncode == 0, hook.stderr
    assert hook.stdout.split() == ["None", "False"]  # the namespace folder won


def _notebook_imports() -> set[str]:
    mods = set()
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        for cell in json.loads(nb.read_text())["cells"]:
            if cell["cell_type"] != "code":
                continue
            src = "\n".join(ln for ln in "".join(cell["source"]).splitlines() if not ln.lstrip().startswith(("%", "!")))
            for node in ast.walk(ast.parse(src)):
                if isinstance(node, ast.Import):
                    mods |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    mods.add(node.module.split(".")[0])
    return mods


def test_the_notebooks_extra_has_jupyterlab_and_what_the_notebooks_import():
    project = _pyproject()["project"]
    extra = project["optional-dependencies"]["notebooks"]
    names = {r.split(">")[0].split("=")[0].split("[")[0].strip().lower() for r in project["dependencies"] + extra}
    assert {"jupyterlab", "ipywidgets"} <= names  # ipywidgets: tqdm.auto's progress bars as widgets
    #: import name -> distribution name, where they differ
    dist = {"IPython": "ipython", "cv2": "opencv-contrib-python-headless", "igl": "libigl", "ot": "pot"}
    missing = sorted(m for m in _notebook_imports() - set(sys.stdlib_module_names) - {"wpot", "render"}
                     if dist.get(m, m).lower() not in names)
    assert not missing, f"the notebooks import {missing}, which neither the base install nor the notebooks extra has"
