"""The public surface: every exported name resolves, the documented choices are the registered ones, the
README's commands are the ones CI runs, the demo needs only the base install, and Warp starts quietly."""
from __future__ import annotations

import importlib
import pydoc
import re
import subprocess
import sys
import tomllib

import pytest

import wpot
from conftest import DEVICES, ROOT


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
    # the first installs the base package only (no extras), then runs the demo
    assert re.search(r"pip install -e \. && wpot demo ", cmds[0]), cmds[0]
    assert "[" not in cmds[0], f"the demo command must not install extras: {cmds[0]}"
    # the second installs the test extras, then runs the tests
    assert re.fullmatch(r'pip install -e "\.\[dev\]" && python -m pytest .*', cmds[1]), cmds[1]


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert _readme_commands()[1] in ci_lines


def test_ci_runs_the_demo_on_the_base_install_before_the_dev_extras():
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    demo = [i for i, line in enumerate(ci_lines) if line.startswith("pip install -e . && wpot demo ")]
    assert demo, "the CI script must run the README's demo on the base install"
    assert demo[0] < ci_lines.index(_readme_commands()[1])


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _name(requirement: str) -> str:
    return re.split(r"[\s\[<>=!~;]", requirement.strip(), maxsplit=1)[0].lower()


def test_base_dependencies_hold_no_test_tool():
    project = _pyproject()["project"]
    base = {_name(r) for r in project["dependencies"]}
    test_only = {_name(r) for r in project["optional-dependencies"]["dev"]} - base
    assert {"pytest", "cvxpy", "dask"} <= test_only
    assert "psutil" in base  # Warp reports no free CPU memory without it, and a comparison would refuse to run
    assert "pot" in base  # the exact solver's LP on the sparse support (POT's network simplex)


#: top-level modules of the dev extras (and what they pull in) that the demo must not need
TEST_ONLY_MODULES = ("pytest", "xdist", "hypothesis", "cvxpy", "dask", "distributed", "nbclient",
                     "nbformat", "ipykernel")


@pytest.mark.slow
def test_demo_imports_no_test_tool_and_prints_no_cuda_warning(tmp_path):
    """The demo, run as the README's first command runs it, in a fresh interpreter: nothing from the dev
    extras is imported, and on a machine without a GPU Warp's "no CUDA driver" warning is not printed."""
    code = (
        "import sys\n"
        "from wpot.cli import main\n"
        f"sys.argv = ['wpot', 'demo', '--n', '120', '--out', {str(tmp_path)!r}]\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        f"print('IMPORTED', sorted({{m.split('.')[0] for m in sys.modules}} & set({TEST_ONLY_MODULES!r})))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "IMPORTED []" in r.stdout, r.stdout
    assert (tmp_path / "correspondence.png").is_file()
    assert "CUDA" not in r.stderr, r.stderr


@pytest.mark.parametrize("name,what", [("compare", "function"), ("Comparer", "class")])
def test_help_lists_every_signature_and_transport(name, what):
    from wpot.config import TRANSPORTS
    from wpot.signatures import signature_names

    text = pydoc.render_doc(getattr(wpot, name), renderer=pydoc.plaintext)
    for value in signature_names() + TRANSPORTS:
        assert f'"{value}"' in text, f"help(wpot.{name}) does not name {value!r}"


# ----------------------------------------------------------------------------------------------- Warp start-up
def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_warp_start_up_prints_no_cuda_line():
    r = _run("from wpot._warp import resolve_device; print(resolve_device(None))")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() in {"cpu", "cuda:0"}
    assert "CUDA" not in r.stderr, r.stderr


@pytest.mark.slow
def test_warp_start_up_drops_only_the_driver_warning():
    """`init` captures descriptor 2 while Warp starts: the "no driver" line is dropped, any other line is
    written back, and an exception from Warp's start-up propagates with descriptor 2 restored."""
    fake = (
        "import os, warp\n"
        "def fake_init():\n"
        "    os.write(2, b'Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution '\n"
        "                b'will not be available.\\nWarp warning: something the user must see\\n')\n"
        "    {after}\n"
        "warp.init = fake_init\n"
        "from wpot import _warp\n"
        "try:\n    _warp.init()\nexcept RuntimeError as e:\n    os.write(2, f'raised: {{e}}\\n'.encode())\n"
        "os.write(2, b'still writable\\n')\n"
    )
    r = _run(fake.format(after="pass"))
    assert r.returncode == 0, r.stderr
    assert r.stderr == "Warp warning: something the user must see\nstill writable\n"
    r = _run(fake.format(after="raise RuntimeError('broken install')"))
    assert r.stderr == "Warp warning: something the user must see\nraised: broken install\nstill writable\n"


@pytest.mark.slow
@pytest.mark.skipif("cuda" in DEVICES, reason="this machine has a CUDA device")
@pytest.mark.parametrize("name", ["cuda", "cuda:0"])
def test_cuda_without_gpu_is_one_clean_error(name):
    r = _run(
        "import sys\n"
        "from wpot._warp import resolve_device\n"
        f"try:\n    resolve_device({name!r})\nexcept ValueError as e:\n    print(e)\n    sys.exit(3)\n"
    )
    assert r.returncode == 3, r.stderr
    assert r.stderr == ""  # no raw Warp CUDA error before the message
    assert f"device {name!r} needs a CUDA GPU" in r.stdout and "['cpu']" in r.stdout
