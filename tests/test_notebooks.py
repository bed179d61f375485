"""The notebooks: stored as executed tutorials, and re-executed here with small settings, their results checked.

A notebook holds no checks of its own. Each test executes a notebook top to bottom in a fresh kernel, then runs
one more cell in that kernel (`PROBES`) that prints the variables the checks need as JSON, and asserts bounds on
them (a broken solver, signature or pipeline fails them).

The kernel is the interpreter running the tests: a temporary ``python3`` kernel spec pointing at
``sys.executable`` is put first on ``JUPYTER_PATH`` (the installed spec runs whatever ``python`` is on PATH).
Notebooks that need ``../shared/data`` are skipped with a reason when it is absent (the ``tosca5k`` fixture).

The stored outputs come from the same small settings: ``python tests/test_notebooks.py`` re-executes every
notebook and writes it back with its outputs (run it after editing a notebook).
"""
from __future__ import annotations

import ast
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

#: real notebooks and Dask clusters: slow (deselect with -m "not slow")
pytestmark = pytest.mark.slow

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
#: per-cell limit; small settings run in about a minute per notebook on a 2-core CPU
CELL_TIMEOUT = 900
#: the stored notebooks together stay below this many bytes (small settings, PNG figures at modest dpi)
MAX_STORED_BYTES = 1_500_000
#: per notebook, a Python expression evaluated in its kernel after the last cell; the test reads its value
PROBES = {
    "quickstart.ipynb": """{
        "full": FULL,
        "converged": [bool(res.result.converged), bool(pres.result.converged)],
        "balanced_auc": float(err.auc),
        "zoomout_auc": float(err_zo.auc),
        "partial_mass_in_part": float(mass_in_part),
        "partial_rotation_error_deg": float(rot_err_deg),
        "partial_scale": float(reg.scale),
    }""",
    "tosca_classification.ipynb": """{
        "full": FULL,
        "n_shapes": len(names),
        "distances": {f"{s}-{t}": stores[s, t].distance_matrix().tolist() for s, t in COMBOS},
        "accuracy": {f"{s}-{t}": {"one_shot": results[s, t][0].mean, "loo": results[s, t][1].accuracy}
                     for s, t in COMBOS},
    }""",
    "partial_heads.ipynb": """{
        "full": FULL,
        "n_heads": len(heads),
        "distances": D.tolist(),
        "mass_in_head": mass_in_head,
        "mass_in_head_density": mass_in_head_density,
        "class_accuracy": retrieval.class_accuracy,
        "locate_error": locate_error,
        "transport_error": transport_error,
    }""",
    "locating_parts.ipynb": """{
        "full": FULL,
        "n_parts": len(cases),
        "error": {n: r["error"] for n, r in results.items()},
        "doubted": {n: bool(r["doubt"]) for n, r in results.items()},
        "landmark_error": {n: w["error"] for n, w in with_landmark.items()},
        "aligned_error": {n: a["error"] for n, a in in_frame.items()},
        "aligned_warned": {n: a["warned"] for n, a in in_frame.items()},
    }""",
}
_PROBE_TAG = "WPOT_PROBE "


def _kernel_environment(tmp: Path) -> dict[str, str]:
    """Environment variables for a kernel running this interpreter with the notebooks' small settings."""
    spec = tmp / "jupyter" / "kernels" / "python3"
    spec.mkdir(parents=True, exist_ok=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (ipykernel)",
        "language": "python",
    }))
    return {
        "JUPYTER_PATH": str(tmp / "jupyter"),
        "WPOT_NOTEBOOK_FULL": "0",
        "MPLBACKEND": "module://matplotlib_inline.backend_inline",
        # the small runs write into tempfile.mkdtemp() folders: keep them under tmp
        "TMPDIR": str(tmp),
    }


@pytest.fixture
def kernel_env(tmp_path, monkeypatch):
    """Small settings, and a ``python3`` kernel that runs this interpreter."""
    for key, value in _kernel_environment(tmp_path).items():
        monkeypatch.setenv(key, value)
    # keep the user's signature cache out of it: notebooks choose their own (temporary) caches
    monkeypatch.delenv("WPOT_CACHE_DIR", raising=False)
    return tmp_path


def execute(name: str, probe: str | None = None) -> tuple[nbformat.NotebookNode, dict | None]:
    """Execute notebook ``name`` in a fresh kernel; with ``probe``, also evaluate that expression in the kernel
    afterwards. Returns the executed notebook (without the probe cell) and the probe's value."""
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    n = len(nb.cells)
    if probe is not None:
        nb.cells.append(nbformat.v4.new_code_cell(f"import json as _json\nprint({_PROBE_TAG!r} + _json.dumps({probe}))"))
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3", record_timing=False,
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()
    value = None
    if probe is not None:
        text = "".join(o.get("text", "") for o in nb.cells[-1].outputs if o.get("output_type") == "stream")
        lines = [line for line in text.splitlines() if line.startswith(_PROBE_TAG)]
        assert lines, f"the probe printed nothing; its outputs: {nb.cells[-1].outputs}"
        value = json.loads(lines[0][len(_PROBE_TAG):])
        del nb.cells[n:]
    return nb, value


# ------------------------------------------------------------------------------------------- stored files
def _notebooks() -> list[Path]:
    return sorted(NOTEBOOKS.glob("*.ipynb"))


def test_notebooks_are_stored_as_executed_tutorials():
    """Each notebook is stored run top to bottom with the small settings (figures included, no errors, no
    stderr), holds no test checks, uses the README's API, reads the WPOT_NOTEBOOK_FULL flag, and they are small."""
    names = [p.name for p in _notebooks()]
    assert set(PROBES) <= set(names)
    total = 0
    for path in _notebooks():
        name, total = path.name, total + path.stat().st_size
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert [c.execution_count for c in code] == list(range(1, len(code) + 1)), f"{name} is not stored executed in order"
        outputs = [o for c in code for o in c.outputs]
        assert not [o for o in outputs if o.output_type == "error"], f"{name} stores an error"
        assert not [o for o in outputs if o.get("name") == "stderr"], f"{name} stores warnings or other stderr output"
        assert any("image/png" in o.get("data", {}) for o in outputs), f"{name} stores no figure"
        assert "small settings" in "".join(o.get("text", "") for o in code[0].outputs), f"{name}: not the small settings"
        assert any("WPOT_NOTEBOOK_FULL" in c.source for c in code[:2]), f"{name} reads no WPOT_NOTEBOOK_FULL flag"
        for c in code:
            tree = ast.parse("\n".join(line for line in c.source.splitlines() if not line.lstrip().startswith(("%", "!"))))
            assert not any(isinstance(node, ast.Assert) for node in ast.walk(tree)), f"{name} keeps an assert: {c.source}"
            assert "WPOT_SUMMARY" not in c.source and "wpot.comparison" not in c.source, f"{name}: {c.source}"
    assert total < MAX_STORED_BYTES, f"the stored notebooks take {total} bytes"


def test_quickstart_uses_the_readme_api():
    source = "\n".join(c.source for c in nbformat.read(NOTEBOOKS / "quickstart.ipynb", as_version=4).cells)
    assert "wpot.compare(" in source and "wpot.Comparer(" in source


# ------------------------------------------------------------------------------------------- executed
def test_quickstart(kernel_env):
    _, s = execute("quickstart.ipynb", PROBES["quickstart.ipynb"])
    assert s["full"] is False
    assert all(s["converged"]), "a transport did not converge"
    # the generated pair is the same surface: a working WKS + OT map is mostly right
    assert s["balanced_auc"] > 0.5
    assert s["zoomout_auc"] >= s["balanced_auc"]  # wpot.zoomout refines the map, never worse here
    # partial transport puts most of the part's mass on the true part, and the registration recovers the motion
    assert s["partial_mass_in_part"] > 0.6
    assert s["partial_rotation_error_deg"] < 30
    assert 0.7 < s["partial_scale"] < 1.4


@pytest.mark.data
def test_tosca_classification(kernel_env, shared_data, monkeypatch):
    if not (shared_data / "tosca_lowres").is_dir():
        pytest.skip(f"TOSCA low-resolution meshes not found at {shared_data / 'tosca_lowres'}")
    monkeypatch.setenv("WPOT_DATA", str(shared_data))
    _, s = execute("tosca_classification.ipynb", PROBES["tosca_classification.ipynb"])
    assert s["full"] is False and s["n_shapes"] >= 6
    for key, d in s["distances"].items():
        d = np.array(d, dtype=float)
        assert d.shape == (s["n_shapes"],) * 2 and np.isfinite(d).all(), f"{key}: missing pairs"
        np.testing.assert_allclose(d, d.T, err_msg=f"{key}: not symmetric")
    acc = s["accuracy"]["wks-balanced"]
    assert acc["loo"] >= 0.75 and acc["one_shot"] >= 0.6


@pytest.mark.data
def test_partial_heads(kernel_env, tosca5k, monkeypatch):
    monkeypatch.setenv("WPOT_DATA", str(tosca5k))
    _, s = execute("partial_heads.ipynb", PROBES["partial_heads.ipynb"])
    assert s["full"] is False and s["n_heads"] >= 2
    assert np.isfinite(np.array(s["distances"], dtype=float)).all(), "some comparisons gave no distance"
    assert min(s["mass_in_head"].values()) > 0.5
    # cells of one size on head and parent put more of the head's mass on the true head (HEAD: 0.80 vs 0.57)
    dens = s["mass_in_head_density"]
    assert set(dens) == set(s["mass_in_head"]) and min(dens.values()) > 0.5
    assert sum(dens.values()) > sum(s["mass_in_head"].values())
    assert s["class_accuracy"] >= 0.5
    # a head against another pose of its class: the located map lands near the truth, the transport's does not
    assert set(s["locate_error"]) == set(s["transport_error"]) and s["locate_error"]
    for h, e in s["locate_error"].items():
        assert e < 0.1 and e < s["transport_error"][h] / 2, (h, e, s["transport_error"][h])


@pytest.mark.data
def test_locating_parts(kernel_env, faust5k, monkeypatch):
    monkeypatch.setenv("WPOT_DATA", str(faust5k))
    _, s = execute("locating_parts.ipynb", PROBES["locating_parts.ipynb"])
    assert s["full"] is False and s["n_parts"] >= 8
    err, doubted, landmark = s["error"], s["doubted"], s["landmark_error"]
    assert set(err) == set(doubted) == set(landmark)
    # what the notebook tells a user: a map that is wrong is doubted (its place or its side), and most are right
    assert all(doubted[n] for n, e in err.items() if e > 0.3), (err, doubted)
    assert np.median([e for n, e in err.items() if not doubted[n]]) < 0.05
    # one landmark a part, inside it and off its centre: every map right, and better on the whole
    assert max(landmark.values()) < 0.1, landmark
    assert np.mean(list(landmark.values())) < np.mean(list(err.values()))
    # in the whole's frame (FAUST's poses 0 and 1 face one way): no warning, no map wrong, and better on the whole
    aligned = s["aligned_error"]
    assert set(aligned) == set(err) and not any(s["aligned_warned"].values())
    assert max(aligned.values()) < 0.3 and np.mean(list(aligned.values())) < np.mean(list(err.values()))


# ------------------------------------------------------------------------------------------- storing
def store_outputs(names: list[str] | None = None) -> None:
    """Execute the notebooks with the small settings and write them back with their outputs."""
    with tempfile.TemporaryDirectory() as tmp:
        env = _kernel_environment(Path(tmp))
        saved = {k: os.environ.get(k) for k in [*env, "WPOT_CACHE_DIR"]}
        os.environ.update(env)
        os.environ.pop("WPOT_CACHE_DIR", None)
        try:
            for path in _notebooks():
                if names and path.name not in names:
                    continue
                nb, _ = execute(path.name)
                nbformat.write(nb, path)
                print(f"{path.relative_to(ROOT)}: {path.stat().st_size / 1e3:.0f} kB")
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


if __name__ == "__main__":
    store_outputs(sys.argv[1:])
