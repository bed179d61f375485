"""Outputs of the `wpot` command that must not mislead: what it overwrites, refuses, names and prints.

The command runs in-process (`wpot.cli.main`) on small generated meshes, with a short spectrum."""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from helpers import FAST_CLI


def cli(capsys, *args) -> tuple[int, str, str]:
    """Run the command in this process: exit code, stdout, stderr (without Warp's own start-up notices)."""
    from wpot.cli import main

    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    strip = lambda text: "\n".join(ln for ln in text.splitlines() if not ln.startswith("Warp "))
    return code, strip(out), strip(err)


def one_line_error(code: int, err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith("wpot: error:")]
    assert code == 2 and len(lines) == 1, (code, err)
    return lines[0]


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """Two 300-vertex triangulations of one surface, as files."""
    from wpot.examples import example_pair
    from wpot.io import save_mesh

    folder = tmp_path_factory.mktemp("pair")
    p = example_pair(300, seed=0, n_target=300)
    save_mesh(p.source, folder / "a.off")
    save_mesh(p.target, folder / "b.off")
    return folder / "a.off", folder / "b.off"


# ------------------------------------------------------------------------------- compare --out and --force
def test_compare_refuses_to_overwrite_a_comparison_without_force(pair, capsys, tmp_path):
    out = tmp_path / "cmp"
    code, _, _ = cli(capsys, "compare", *pair, *FAST_CLI, "--out", out)
    assert code == 0
    first = (out / "comparison.json").read_text()
    line = one_line_error(*cli(capsys, "compare", *pair, *FAST_CLI, "--max-vertices", "100", "--out", out)[::2])
    assert f"--out {out} already holds a comparison (comparison.json, correspondence.npz, correspondence.png)" in line
    assert "--force" in line and (out / "comparison.json").read_text() == first  # refused before any work
    code, _, _ = cli(capsys, "compare", *pair, *FAST_CLI, "--max-vertices", "100", "--out", out, "--force")
    assert code == 0 and json.loads((out / "comparison.json").read_text())["n_points"] == [100, 100]
    # a folder without a comparison in it is fine
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("mine")
    assert cli(capsys, "compare", *pair, *FAST_CLI, "--out", tmp_path / "empty")[0] == 0


# ------------------------------------------------------------------------------------------ small ones
def test_pooling_cell_without_subsampling_is_refused_in_the_cli_and_warned_in_python(pair, capsys):
    import wpot
    from wpot.cli import cli_words

    line = one_line_error(*cli(capsys, "compare", *pair, *FAST_CLI, "--pooling", "cell")[::2])
    assert "--pooling cell" in line and "--max-vertices or --vertices-per-sample" in line
    # with subsampling it is taken (no error at parsing)
    from wpot.cli import build_parser, config_from_args

    args = build_parser().parse_args(["compare", "a", "b", "--pooling", "cell", "--vertices-per-sample", "5"])
    assert config_from_args(args).sampler.pooling == "cell"
    with pytest.warns(UserWarning, match=r"pooling='cell'.*without max_vertices or vertices_per_sample") as rec:
        wpot.ComparisonConfig.from_keywords(pooling="cell")
    assert "--pooling cell" in cli_words(str(rec[0].message)) and "--max-vertices" in cli_words(str(rec[0].message))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        wpot.ComparisonConfig.from_keywords(pooling="cell", max_vertices=100)
        wpot.ComparisonConfig.from_keywords(pooling="none")


def test_n_eigen_below_what_wks_needs_is_refused_with_the_minimum(pair, capsys):
    import wpot
    from wpot.signatures._spectral import MIN_EIGENPAIRS

    assert MIN_EIGENPAIRS == 10
    line = one_line_error(*cli(capsys, "compare", *pair, "--n-eigen", "5")[::2])
    assert "--n-eigen must be an integer >= 10, got 5" in line
    line = one_line_error(*cli(capsys, "compare", *pair, "--signature", "hks", "--n-eigen", "9")[::2])
    assert "--n-eigen must be an integer >= 10, got 9" in line
    with pytest.raises(ValueError, match="n_eigen must be an integer >= 10, got 5"):
        wpot.Comparer(n_eigen=5)


def test_a_folder_given_to_compare_is_called_a_folder(pair, capsys, tmp_path):
    line = one_line_error(*cli(capsys, "compare", pair[0].parent, pair[1])[::2])
    assert f"A: {pair[0].parent} is a folder, not a mesh file" in line and "compare takes two mesh files" in line
    assert "all-vs-all" in line and "not found" not in line
    line = one_line_error(*cli(capsys, "compare", pair[0], tmp_path)[::2])
    assert f"B: {tmp_path} is a folder" in line
    line = one_line_error(*cli(capsys, "retrieve", tmp_path, pair[0].parent)[::2])
    assert f"part: {tmp_path} is a folder" in line and "one mesh file" in line
    assert "mesh file not found" in one_line_error(*cli(capsys, "compare", tmp_path / "none.off", pair[1])[::2])


def test_the_components_warnings_name_their_mesh(pair, capsys, tmp_path):
    """Each warning about a mesh's pieces starts with its file: the defect, and its spectrum's repeated 0."""
    from wpot.io import load_mesh, save_mesh
    from wpot.mesh import Mesh

    a = load_mesh(pair[0])
    v = np.vstack([a.vertices, a.vertices + [5.0, 0, 0]])
    f = np.vstack([a.faces, a.faces + a.n_vertices])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        save_mesh(Mesh(v, f), tmp_path / "two.off")
    code, _, err = cli(capsys, "compare", tmp_path / "two.off", pair[1], *FAST_CLI)
    warned = [ln for ln in err.splitlines() if ln.startswith("wpot: warning:")]
    assert code == 0 and len(warned) == 2, err
    assert all(ln.startswith(f"wpot: warning: {tmp_path / 'two.off'}: ") for ln in warned), warned
    assert "2 connected components" in warned[0] and "eigenvalue 0 repeats 2 times" in warned[1]


# ------------------------------------------------------------------------------------- retrieve --progress
def test_retrieve_reports_the_library_s_set_up_with_progress(capsys, tmp_path):
    from helpers import make_dataset
    from wpot.io import load_mesh, save_mesh
    from wpot.mesh import cut

    library = make_dataset(tmp_path / "lib", n_per_class=2)
    blob = load_mesh(library / "blob1.off")
    save_mesh(cut(blob, np.arange(blob.n_vertices // 2))[0], tmp_path / "part.off")
    args = ["retrieve", tmp_path / "part.off", library, "--signature", "wks", *FAST_CLI, "--device", "cpu"]
    code, out, err = cli(capsys, *args, "--progress")
    assert code == 0, err
    lines = err.splitlines()
    assert "\r" not in err  # stderr is not a terminal here: a line per step
    for step in ("reading meshes: 4/4 (100%)", "spectra: 4/4 (100%)", "WKS signatures of the library: 4/4 (100%)"):
        assert any(ln.startswith(step) for ln in lines), (step, err)
    assert re.search(r"^WKS signatures of the part \(\d+ vertices\) \.\.\. \d+\.\d s$", err, re.M), err
    ranked = re.findall(r"^\s+\d+\. (\S+)\s+score", out, re.M)
    code, out2, err2 = cli(capsys, *args)  # not a terminal, no --progress: no report, the same ranking
    assert code == 0 and "signatures of the library" not in err2 and re.findall(r"^\s+\d+\. (\S+)\s+score", out2, re.M) == ranked
    code, _, err3 = cli(capsys, *args, "--no-progress")
    assert code == 0 and "reading meshes" not in err3
