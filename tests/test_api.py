"""The public surface: every exported name resolves, and the README's commands are the ones CI runs."""
from __future__ import annotations

import importlib
import re

import pytest

import wpot
from conftest import ROOT


@pytest.mark.parametrize("name", wpot.__all__)
def test_every_exported_name_resolves(name):
    assert getattr(wpot, name) is not None


def test_unknown_name_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_thing"):
        wpot.no_such_thing  # noqa: B018


@pytest.mark.parametrize("module", ["wpot.ot", "wpot.signatures", "render"])
def test_subpackage_all_resolves(module):
    mod = importlib.import_module(module)
    assert mod.__all__, f"{module} has an empty __all__"
    for name in mod.__all__:
        assert getattr(mod, name) is not None, f"{module}.{name}"


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S)
    assert block, "README must open with a ```bash block holding the two set-up commands"
    return [line.strip() for line in block.group(1).strip().splitlines() if line.strip()]


def test_readme_opens_with_install_and_test_commands():
    cmds = _readme_commands()
    assert len(cmds) == 2, cmds
    assert "pip install" in cmds[0] and "wpot demo" in cmds[0]
    assert "pytest" in cmds[1]


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert _readme_commands()[1] in ci_lines
