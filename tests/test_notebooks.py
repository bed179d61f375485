"""Execute every notebook in ``notebooks/`` top to bottom with its small settings, and check its results.

Each notebook ends with a cell that asserts loose bounds on its own results (a broken solver, signature or
pipeline fails them) and prints one ``WPOT_SUMMARY {json}`` line; the tests here read that line back and
check the numbers again, so a notebook whose checks were edited away still fails.

The kernel is the interpreter running the tests: a temporary ``python3`` kernel spec pointing at
``sys.executable`` is put first on ``JUPYTER_PATH`` (the installed spec runs whatever ``python`` is on PATH).
Notebooks that need ``../shared/data`` are skipped with a reason when it is absent (the ``tosca5k`` fixture).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
#: per-cell limit; small settings run in about a minute per notebook on a 2-core CPU
CELL_TIMEOUT = 900


@pytest.fixture
def kernel_env(tmp_path, monkeypatch):
    """Small settings, and a ``python3`` kernel that runs this interpreter."""
    spec = tmp_path / "jupyter" / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (wpot tests)",
        "language": "python",
    }))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path / "jupyter"))
    monkeypatch.setenv("WPOT_NOTEBOOK_FULL", "0")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    # keep the user's signature cache out of it: notebooks choose their own (temporary) caches
    monkeypatch.delenv("WPOT_CACHE_DIR", raising=False)
    # the small runs write into tempfile.mkdtemp() folders: put them under pytest's (self-pruning) tmp_path
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    return tmp_path


def execute(name: str) -> nbformat.NotebookNode:
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=CELL_TIMEOUT, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    )
    client.execute()
    return nb


def summary(nb: nbformat.NotebookNode) -> dict:
    """The ``WPOT_SUMMARY`` JSON printed by the notebook's last code cell."""
    last = [c for c in nb.cells if c.cell_type == "code"][-1]
    for out in last.get("outputs", []):
        if out.get("output_type") == "stream":
            for line in out.get("text", "").splitlines():
                if line.startswith("WPOT_SUMMARY "):
                    return json.loads(line[len("WPOT_SUMMARY "):])
    raise AssertionError(f"the last cell printed no WPOT_SUMMARY line; its outputs: {last.get('outputs')}")


def test_notebooks_are_stored_without_outputs():
    """Committed notebooks carry no outputs or execution counts (clean diffs), and each has a FULL flag."""
    names = sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))
    assert {"quickstart.ipynb", "tosca_classification.ipynb", "partial_heads.ipynb"} <= set(names)
    for name in names:
        nb = nbformat.read(NOTEBOOKS / name, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(not c.outputs and c.execution_count is None for c in code), f"{name} has stored outputs"
        assert any("WPOT_NOTEBOOK_FULL" in c.source for c in code[:2]), f"{name} reads no WPOT_NOTEBOOK_FULL flag"


def test_quickstart(kernel_env):
    s = summary(execute("quickstart.ipynb"))
    assert s["full"] is False
    # the generated pair is the same surface: a working WKS + OT map is mostly right
    assert s["balanced_auc"] > 0.5
    assert s["zoomout_auc"] >= s["balanced_auc"]  # wpot.zoomout refines the map, never worse here
    # partial transport puts most of the part's mass on the true part, and the registration recovers the motion
    assert s["partial_mass_in_part"] > 0.6
    assert s["partial_rotation_error_deg"] < 30
    assert 0.7 < s["partial_scale"] < 1.4


@pytest.mark.data
def test_tosca_classification(kernel_env, tosca5k, monkeypatch):
    monkeypatch.setenv("WPOT_DATA", str(tosca5k))
    s = summary(execute("tosca_classification.ipynb"))
    assert s["full"] is False and s["n_shapes"] >= 6
    acc = s["accuracy"]["wks-balanced"]
    assert acc["loo"] >= 0.75 and acc["one_shot"] >= 0.6


@pytest.mark.data
def test_partial_heads(kernel_env, tosca5k, monkeypatch):
    monkeypatch.setenv("WPOT_DATA", str(tosca5k))
    s = summary(execute("partial_heads.ipynb"))
    assert s["full"] is False and s["n_heads"] >= 2
    assert min(s["mass_in_head"].values()) > 0.5
    # cells of one size on head and parent put more of the head's mass on the true head (HEAD: 0.80 vs 0.57)
    dens = s["mass_in_head_density"]
    assert set(dens) == set(s["mass_in_head"]) and min(dens.values()) > 0.5
    assert sum(dens.values()) > sum(s["mass_in_head"].values())
    assert s["class_accuracy"] >= 0.5
