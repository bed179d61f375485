"""What the `wpot` command tells its user: progress, which WKS grid a distance used, mesh repair, meshes too
small, messages in the command's own words, the subsampling, and the help.

The command runs in-process (`wpot.cli.main`) on small generated meshes, with a short spectrum."""
from __future__ import annotations

import io
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from helpers import Clock, cli, make_dataset, one_line_error

FAST = ["--n-eigen", "30", "--n-energies", "30"]








@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("msg-data"), n_per_class=2)


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory) -> Path:
    """An all-vs-all run over `dataset` (balanced WKS, FAST)."""
    from wpot.runs.loop import run_all_vs_all

    folder = tmp_path_factory.mktemp("msg-run") / "run"
    run_all_vs_all(dataset, folder, progress=False, n_eigen=30, n_energies=30).close()
    return folder


def defective_copy(src: Path, dst: Path) -> int:
    """``src`` with one isolated vertex and one zero-area triangle (on two more vertices) appended; returns the
    vertex count of ``src``. Repairing it gives ``src`` back exactly."""
    from wpot.io import load_mesh, save_mesh
    from wpot.mesh import Mesh

    m = load_mesh(src)
    n = m.n_vertices
    v = np.vstack([m.vertices, m.vertices.mean(0) + 5.0, m.vertices[m.faces[0, 0]], m.vertices[m.faces[0, 1]]])
    f = np.vstack([m.faces, [[m.faces[0, 0], n + 1, n + 2]]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        save_mesh(Mesh(v, f, warn=False), dst)
    return n


# ------------------------------------------------------------------------------------------- 1. progress


def test_a_comparison_reports_each_step_with_its_time(pair):
    import wpot
    from wpot.progress import Progress

    a, b = (wpot.load_mesh(p) for p in pair)
    buf = io.StringIO()
    comparer = wpot.Comparer(n_eigen=30, n_energies=30, max_vertices=100, transport="partial", device="cpu",
                             cache_dir=False, progress=Progress(buf, clock=Clock()))
    comparer.compare(a, b)
    lines = buf.getvalue().splitlines()
    assert lines == [
        "Laplace-Beltrami spectrum of A (300 vertices, 30 eigenpairs) ... 1.0 s",
        "Laplace-Beltrami spectrum of B (300 vertices, 30 eigenpairs) ... 1.0 s",
        "WKS signatures of A (300 vertices) ... 1.0 s",
        "farthest-point sampling of A: 100 of 300 vertices ... 1.0 s",
        "WKS signatures of B (300 vertices) ... 1.0 s",
        "farthest-point sampling of B: 100 of 300 vertices ... 1.0 s",
        "partial transport on farthest-point samples, 100 x 100 ... 1.0 s",
        "self-comparison of A (Eq. 27) ... 1.0 s",
        "self-comparison of B (Eq. 27) ... 1.0 s",
    ]
    # a comparer made from it by with_options reports to the same place
    buf.truncate(0)
    buf.seek(0)
    comparer.with_options(transport="balanced").compare(a, b)
    assert "balanced transport on farthest-point samples, 100 x 100 ... 1.0 s" in buf.getvalue().splitlines()


def test_a_terminal_also_sees_the_annealing_betas(pair):
    import wpot
    from wpot.progress import Progress

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    a, b = (wpot.load_mesh(p) for p in pair)
    out = Terminal()
    c = wpot.Comparer(n_eigen=30, n_energies=30, max_vertices=60, device="cpu", cache_dir=False,
                      solver_options={"method": "anneal"}, progress=Progress(out, clock=Clock())).compare(a, b)
    text = out.getvalue()
    assert "annealing:" in text and "beta/s" in text
    # the bar (redrawn at most every 0.1 s) shows a solved beta's U, as the result's history records it
    assert any(f"beta {st.beta:.3g}, U {st.cost:.9g}" in text for st in c.result.history)
    # the stage's time comes on a line of its own once the bar has been drawn
    assert "balanced transport on farthest-point samples, 60 x 60: 1.0 s" in text.splitlines()
    # the exact solver (the default for balanced transport) has no betas to count: no bar
    out = Terminal()
    wpot.Comparer(n_eigen=30, n_energies=30, max_vertices=60, device="cpu", cache_dir=False,
                  progress=Progress(out, clock=Clock())).compare(a, b)
    assert "annealing:" not in out.getvalue()
    assert "balanced transport on farthest-point samples, 60 x 60 ... 1.0 s" in out.getvalue().splitlines()


def test_a_stage_that_fails_says_so():
    from wpot.progress import Progress

    buf = io.StringIO()
    with pytest.raises(RuntimeError):
        with Progress(buf, clock=Clock()).stage("transport"):
            raise RuntimeError("solver broke")
    assert buf.getvalue() == "transport ... 1.0 s (stopped)\n"


def test_progress_off_by_default_in_python_and_as_progress_checks_its_argument(pair, capsys):
    import wpot
    from wpot.progress import Progress, as_progress

    a, b = (wpot.load_mesh(p) for p in pair)
    capsys.readouterr()
    wpot.compare(a, b, n_eigen=30, n_energies=30, device="cpu", cache_dir=False)
    assert "transport" not in capsys.readouterr().err
    assert as_progress(True).enabled and not as_progress(False).enabled and not as_progress(None).enabled
    p = Progress(io.StringIO())
    assert as_progress(p) is p
    with pytest.raises(TypeError, match="progress must be True, False or a wpot.progress.Progress"):
        as_progress("yes")
    silent = io.StringIO()
    q = Progress(silent, enabled=False)
    with q.stage("nothing"):
        pass
    q.write("nothing")
    bar = q.bar(3, "nothing")
    bar.update()
    bar.close()
    assert silent.getvalue() == ""


def test_progress_is_on_for_a_terminal_unless_told_otherwise():
    from wpot.cli import progress_enabled

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert progress_enabled(None, Terminal()) and not progress_enabled(None, io.StringIO())
    assert not progress_enabled(False, Terminal()) and progress_enabled(True, io.StringIO())


def test_compare_progress_flags(pair, capsys):
    a, b = pair
    step = re.compile(r"^balanced transport on every vertex, 300 x 300 \.\.\. \d+\.\d s$", re.M)
    code, _, err = cli(capsys, "compare", a, b, *FAST, "--progress")
    assert code == 0 and step.search(err) and "Laplace-Beltrami spectrum of A" in err, err
    code, _, err = cli(capsys, "compare", a, b, *FAST, "--no-progress")
    assert code == 0 and not step.search(err), err
    code, _, err = cli(capsys, "compare", a, b, *FAST)  # stderr is not a terminal here
    assert code == 0 and not step.search(err), err
    code, _, err = cli(capsys, "demo", "--n", "200", "--out", a.parent / "demo", "--progress", *FAST)
    assert code == 0 and "balanced transport on every vertex, 200 x 200 ... " in err, err


def test_every_phase_of_an_all_vs_all_has_a_bar(dataset, tmp_path):
    from wpot.runs.loop import run_all_vs_all
    from wpot.progress import Progress

    buf = io.StringIO()
    run_all_vs_all(dataset, tmp_path / "run", progress=Progress(buf), n_eigen=30, n_energies=30).close()
    text = buf.getvalue()
    # into a stream that is not a terminal: a line per step, no bar redrawn with carriage returns
    for phase in ("reading meshes", "spectra", "signatures", "pairs"):
        assert re.search(rf"^{phase}: \d+/\d+ \(\d+%\), \d+\.\d s$", text, re.M), (phase, text)
    assert re.search(r"^pairs: 6/6 \(100%\), ", text, re.M) and "\r" not in text, text


# ------------------------------------------------------------------------------------- 2. the energy grid
def test_compare_says_which_grid_and_a_run_s_grid_gives_the_run_s_distance(run, dataset, capsys, tmp_path):
    from wpot.runs.store import RunStore

    with RunStore(run) as store:
        d_run, names, grid = store.distance_matrix(), store.names, store.signature_state()["energies"]
    i, j = names.index("blob1"), names.index("flat2")
    a, b = dataset / "blob1.off", dataset / "flat2.off"
    code, out, _ = cli(capsys, "compare", a, b, *FAST, "--out", tmp_path / "alone")
    assert code == 0
    assert "WKS energy grid: fitted to this pair (30 energies" in out
    assert "an all-vs-all run fits one energy grid to its whole dataset" in out and "--energies-from RUN" in out
    alone = json.loads((tmp_path / "alone" / "comparison.json").read_text())
    assert alone["signature_state"]["fitted_to"] == "this pair" and len(alone["signature_state"]["energies"]) == 30
    assert alone["signature_state"]["energies"] != grid  # the pair's grid is not the dataset's

    code, out, _ = cli(capsys, "compare", a, b, *FAST, "--energies-from", run, "--out", tmp_path / "with-run")
    assert code == 0
    assert f"WKS energy grid: from the run {run}, fitted to its 4 shapes (30 energies" in out
    saved = json.loads((tmp_path / "with-run" / "comparison.json").read_text())
    assert saved["signature_state"] == {"fitted_to": "run", "run": str(run), "n_shapes": 4, "energies": grid}
    assert saved["distance"] == pytest.approx(d_run[i, j], rel=1e-9)  # the run's distance for this pair

    # settings that the grid was not fitted for are refused; other differences are pointed out
    line = one_line_error(*cli(capsys, "compare", a, b, "--n-eigen", "30", "--n-energies", "40",
                                "--energies-from", run)[::2])
    assert "--n-energies: the run's 30, here 40" in line and "n_energies" not in line
    code, out, _ = cli(capsys, "compare", a, b, *FAST, "--energies-from", run, "--max-vertices", "50")
    assert code == 0 and "--max-vertices: the run's none, here 50; so this is not the run's distance" in out
    line = one_line_error(*cli(capsys, "compare", a, b, "--signature", "ldsift", "--energies-from", run)[::2])
    assert "LD-SIFT has no fitted grid" in line


def test_compare_help_explains_why_a_run_gives_another_distance():
    from wpot.cli import build_parser

    text = " ".join(_subparser(build_parser(), "compare").format_help().split())
    assert "fits one grid to its whole dataset" in text and "paper section 3.2" in text
    assert "--energies-from RUN" in text


# ------------------------------------------------------------------------------------------- 3. repair
def test_a_defective_mesh_is_refused_with_advice_to_repair_and_repaired_with_repair(pair, capsys, tmp_path):
    a, b = pair
    bad = tmp_path / "bad.off"
    n = defective_copy(a, bad)
    code, _, err = cli(capsys, "compare", bad, b, *FAST)
    line = one_line_error(code, err)
    assert "--repair" in line and "Mesh.cleaned" not in err, err
    assert re.search(r"^wpot: warning: .*mesh defects: .*--repair removes", err, re.M), err  # the load warning too

    code, out, err = cli(capsys, "compare", bad, b, *FAST, "--repair", "--out", tmp_path / "fixed")
    assert code == 0, err
    assert "--repair A: removed 1 zero-area triangle, 3 unreferenced vertices" in out
    assert "--repair B: nothing to repair" in out
    assert f"A: {bad} ({n} of its {n + 3} vertices after --repair)" in out
    code, _, _ = cli(capsys, "compare", a, b, *FAST, "--out", tmp_path / "clean")
    assert code == 0
    fixed, clean = (np.load(tmp_path / d / "correspondence.npz") for d in ("fixed", "clean"))
    # the repaired mesh is the clean one: the same map, on the file's vertex numbering (-1: removed vertices)
    np.testing.assert_array_equal(fixed["correspondence"], np.r_[clean["correspondence"], [-1, -1, -1]])
    np.testing.assert_array_equal(fixed["index_map_a"], np.arange(n))
    # per-vertex confidence (A) and matched region (B) on the files' numbering too: NaN / False where removed
    np.testing.assert_array_equal(fixed["confidence"], np.r_[clean["confidence"], [np.nan] * 3])
    np.testing.assert_array_equal(fixed["region"], clean["region"])
    info = json.loads((tmp_path / "fixed" / "comparison.json").read_text())
    assert info["repair"] is True
    assert info["distance"] == json.loads((tmp_path / "clean" / "comparison.json").read_text())["distance"]


def test_all_vs_all_repair(dataset, capsys, tmp_path):
    import shutil

    from wpot.runs.store import RunStore

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    defective_copy(dataset / "blob2.off", data / "blob2.off")
    line = one_line_error(*cli(capsys, "all-vs-all", data, "--out", tmp_path / "r0", *FAST)[::2])
    assert "--repair" in line and "Mesh.cleaned" not in line
    code, out, err = cli(capsys, "all-vs-all", data, "--out", tmp_path / "r1", "--repair", *FAST)
    assert code == 0, err
    assert "--repair: blob2: removed 1 zero-area triangle, 3 unreferenced vertices" in out
    with RunStore(tmp_path / "r1") as store:
        assert store.get("repairs") == {"blob2": "1 zero-area triangle, 3 unreferenced vertices"}
        assert np.isfinite(store.distance_matrix()).all()
    # its shapes are the repaired ones: without --repair the run is not resumed
    line = one_line_error(*cli(capsys, "all-vs-all", data, "--out", tmp_path / "r1", *FAST)[::2])
    assert "--repair: stored on, requested off" in line


def test_largest_component_drops_stray_pieces(dataset, capsys, tmp_path):
    """--largest-component keeps each mesh's largest piece (after --repair's fixes): the run's distances are
    those of the meshes without their stray pieces, and a resume must ask for the same repair."""
    import shutil

    import wpot
    from wpot.runs.store import RunStore

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    m = wpot.load_mesh(dataset / "blob2.off")
    piece = m.vertices[m.faces[0]] + [10.0, 0.0, 0.0]  # a detached triangle beside the blob
    wpot.save_mesh(wpot.Mesh(np.vstack([m.vertices, piece]), np.vstack([m.faces, m.n_vertices + np.arange(3)[None]]),
                             warn=False), data / "blob2.off")
    code, out, err = cli(capsys, "all-vs-all", data, "--out", tmp_path / "big", "--largest-component", *FAST)
    assert code == 0, err
    assert "--largest-component: blob2: removed 1 smaller component (3 vertices)" in out
    code, _, err = cli(capsys, "all-vs-all", dataset, "--out", tmp_path / "clean", *FAST)
    assert code == 0, err
    with RunStore(tmp_path / "big") as big, RunStore(tmp_path / "clean") as clean:
        assert big.get("repair") == "largest" and big.names == clean.names
        np.testing.assert_allclose(big.distance_matrix(), clean.distance_matrix(), rtol=1e-9, atol=0)
    for flags, said in ((["--repair"], "--repair alone"), ([], "neither")):
        line = one_line_error(*cli(capsys, "all-vs-all", data, "--out", tmp_path / "big", *flags, *FAST)[::2])
        assert f"--repair/--largest-component: stored --largest-component, requested {said}" in line


def test_repair_mesh_says_what_it_removed(pair):
    import wpot
    from wpot.mesh import repair_mesh

    m = wpot.load_mesh(pair[0])
    same, index_map, removed = repair_mesh(m)
    assert removed == "" and same == m and np.array_equal(index_map, np.arange(m.n_vertices))
    doubled = wpot.Mesh(m.vertices, np.vstack([m.faces, m.faces[:2]]), warn=False)
    assert repair_mesh(doubled)[2] == "2 duplicate triangles"
    # the mesh, a duplicate triangle, and a piece of a shifted copy (its other vertices unreferenced): "largest"
    # keeps the mesh, with no warning about the piece it drops, and its index map points into the input
    piece = m.faces[(m.faces == 0).any(axis=1)] + m.n_vertices  # the fan around a vertex: one piece
    twin = wpot.Mesh(np.vstack([m.vertices, m.vertices + 5.0]), np.vstack([m.faces, m.faces[:1], piece]), warn=False)
    n_piece = len(np.unique(piece))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kept, index_map, removed = repair_mesh(twin, "largest")
    assert removed == (f"1 duplicate triangle, {m.n_vertices - n_piece} unreferenced vertices, "
                       f"1 smaller component ({n_piece} vertices)")
    assert kept.n_vertices == m.n_vertices and np.array_equal(kept.vertices, twin.vertices[index_map])
    assert np.array_equal(index_map, np.arange(m.n_vertices))
    assert repair_mesh(twin, "none")[0] is twin
    with pytest.raises(ValueError, match="repair must be"):
        repair_mesh(twin, "all")


# ------------------------------------------------------------------------------------ 4. too small a mesh
def test_a_mesh_too_small_is_refused_at_once(pair, capsys, tmp_path):
    import wpot
    from wpot.progress import Progress

    tri = tmp_path / "tri.off"
    tri.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    code, _, err = cli(capsys, "compare", tri, pair[1], "--progress")
    line = one_line_error(code, err)
    assert f"A ({tri}) has only 3 vertices" in line and "needs at least 10" in line and "--n-eigen 500" in line
    assert "unit" not in line and "spectrum of" not in err  # refused before any spectrum
    # in Python, by its keywords
    t, b = wpot.load_mesh(tri), wpot.load_mesh(pair[1])
    buf = io.StringIO()
    with pytest.raises(ValueError, match=r"mesh_a has only 3 vertices.*at least 10 of them \(n_eigen=500\)"):
        wpot.Comparer(device="cpu", cache_dir=False, progress=Progress(buf)).compare(t, b)
    assert buf.getvalue() == ""
    assert wpot.comparison.min_vertices(wpot.ComparisonConfig.from_keywords(n_eigen=10))[0] == 10
    with pytest.raises(ValueError, match="n_eigen must be an integer >= 10, got 5"):  # WKS needs 10 eigenpairs
        wpot.ComparisonConfig.from_keywords(n_eigen=5)
    assert wpot.comparison.min_vertices(wpot.ComparisonConfig.from_keywords(signature="ldsift"))[0] == 3
    # in an all-vs-all, before the run folder is made
    data = tmp_path / "data"
    data.mkdir()
    (data / "tri.off").write_text(tri.read_text())
    for p in pair:
        (data / p.name).write_bytes(p.read_bytes())
    line = one_line_error(*cli(capsys, "all-vs-all", data, "--out", tmp_path / "run", *FAST)[::2])
    assert "shape 'tri'" in line and "has only 3 vertices" in line and "--n-eigen 30" in line
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------- 5. messages in the CLI's words
#: a bad value for every flag that takes one, and what the one-line error must say
BAD_VALUES = {
    "--max-vertices": (["--max-vertices", "1"], "--max-vertices must be an integer >= 3, got 1"),
    "--vertices-per-sample": (["--vertices-per-sample", "0.5"], "--vertices-per-sample must be a number >= 1, got 0.5"),
    "--mass-penalty": (["--mass-penalty", "-1"], "--mass-penalty must be a positive finite number, got -1.0"),
    "--n-eigen": (["--n-eigen", "5"], "--n-eigen must be an integer >= 10, got 5"),
    "--n-energies": (["--n-energies", "3"], "--n-energies must be an integer > 28"),
    "--ldsift-slab": (["--signature", "ldsift", "--ldsift-slab", "-1"], "--ldsift-slab must be a positive finite number"),
    "--ldsift-thickness": (["--signature", "ldsift", "--ldsift-thickness", "-1"],
                           "--ldsift-thickness must be a finite number >= 0, got -1"),
    "--ldsift-orientation": (["--signature", "ldsift", "--ldsift-orientation", "pca"],
                             "--ldsift-orientation must be one of ('frame', 'gradient'), got 'pca'"),
    "--hks-n-times": (["--signature", "hks", "--hks-n-times", "1"], "--hks-n-times must be an integer >= 2, got 1"),
    "--spectral-max-vertices": (["--spectral-max-vertices", "500"],
                                "--spectral-max-vertices must be 0 (off) or at least 1000, got 500"),
    "--match-ratio": (["--match-ratio", "1.5"], "--match-ratio must be in (0, 1], got 1.5"),
    "--device": (["--device", "nowhere"], "--device: unknown Warp device 'nowhere'"),
    "--energies-from": (["--energies-from", "no-such-run"], "--energies-from: no such run folder: no-such-run"),
    "--out": (["--out", "FILE"], "--out FILE is a file; give a folder"),
    "--signature": (["--signature", "sift"], "argument --signature: invalid choice"),
    "--transport": (["--transport", "half"], "argument --transport: invalid choice"),
    "--pooling": (["--pooling", "max"], "argument --pooling: invalid choice"),
    "--ot-method": (["--ot-method", "sinkhorn"], "argument --ot-method: invalid choice"),
    "--locate-edge": (["--locate-edge", "half"], "argument --locate-edge: invalid choice"),
    "--locate-orient-weight": (["--locate", "--locate-orient-weight", "-1"],
                               "--locate-orient-weight must be a finite number >= 0, got -1"),
    "--locate-scale": (["--locate", "--locate-scale", "big"],
                       "--locate-scale must be same, fit or a positive number, got 'big'"),
    "--locate-landmarks": (["--locate", "--locate-landmarks", "FILE"], "--locate-landmarks FILE holds no landmarks"),
}
#: flags of the other commands
OTHER_BAD_VALUES = [
    (["demo", "--n", "10"], "--n must be an integer >= 50, got 10"),
    (["all-vs-all", "DATA", "--out", "r", "--jobs", "-1"], "--jobs must be >= 0, got -1"),
    (["all-vs-all", "DATA", "--out", "r", "--scheduler", "here"], "--scheduler must be \"local\" or a Dask address"),
    (["all-vs-all", "DATA", "--out", "r", "--labels", "none.csv"], "label CSV not found: none.csv"),
    (["classify", "RUN", "--trials", "0"], "--trials must be >= 1, got 0"),
    (["classify", "RUN", "--seed", "-1"], "--seed must be >= 0, got -1"),
    (["classify", "RUN", "--draws", "-1"], "--draws must be >= 0, got -1"),
    (["classify", "RUN", "--draws", "5", "--per-class", "1"], "--per-class must be >= 2"),
    (["report", "RUN", "--trials", "0"], "--trials must be >= 1, got 0"),
    (["report", "RUN", "--seed", "-1"], "--seed must be >= 0, got -1"),
    (["export", "RUN", "--out", "d.txt"], "export writes .csv or .npz"),
]


def _subparser(parser, name):
    import argparse

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def test_every_flag_that_takes_a_value_has_a_bad_value_test():
    from wpot.cli import build_parser

    parser = build_parser()
    tested = set(BAD_VALUES) | {[x for x in args if x.startswith("--")][-1] for args, _ in OTHER_BAD_VALUES}
    for command in ("demo", "compare", "all-vs-all", "classify", "export", "report"):
        for action in _subparser(parser, command)._actions:
            if action.option_strings and action.nargs != 0 and action.dest != "help":
                assert action.option_strings[0] in tested, (command, action.option_strings)


@pytest.mark.parametrize("flag", sorted(BAD_VALUES))
def test_a_bad_value_is_named_by_its_flag(flag, pair, capsys, tmp_path):
    from wpot.cli import flag_table

    args, expected = BAD_VALUES[flag]
    (tmp_path / "FILE").write_text("")
    args = [str(tmp_path / "FILE") if x == "FILE" else x for x in args]
    expected = expected.replace("FILE", str(tmp_path / "FILE"))
    try:
        code, _, err = cli(capsys, "compare", *pair, *FAST, *args)
    except SystemExit as exc:  # argparse's own refusal of a choice
        code, err = exc.code, capsys.readouterr().err
        assert code == 2 and expected in err, err
        return
    line = one_line_error(code, err)
    assert expected in line, line
    keywords = [k for k in flag_table() if "_" in k]
    assert not any(re.search(rf"(?<![\w-]){k}(?!\w)", line) for k in keywords), line


def test_loaded_mesh_maps_file_indices_both_ways():
    """`_Loaded.from_input` inverts `to_input` (the file's vertices as the used mesh's), and gives -1 for a
    vertex --repair removed; without a repair both are the identity."""
    from wpot.cli import _Loaded

    kept = np.array([0, 2, 3, 5])  # the file's vertices 1 and 4 removed
    m = _Loaded(None, "f.off", kept, n_input=6)
    assert m.from_input(m.to_input(np.arange(4))).tolist() == [0, 1, 2, 3]
    assert m.from_input([1, 4, 5]).tolist() == [-1, -1, 3]
    plain = _Loaded(type("M", (), {"n_vertices": 6})(), "f.off")
    assert plain.from_input([4, 1]).tolist() == [4, 1] and plain.to_input([4, 1]).tolist() == [4, 1]


def test_a_bad_landmark_file_is_named_by_line_before_any_comparison(pair, capsys, tmp_path):
    """``--locate-landmarks``: each fault of the file named with its line, in the command's words (A, B, 0-based
    vertices, --repair), before the comparison starts; and the flag wants --locate."""
    import wpot

    n_a, n_b = wpot.load_mesh(pair[0]).n_vertices, wpot.load_mesh(pair[1]).n_vertices
    marks = tmp_path / "marks.txt"
    cases = [("# a comment\n0 1\n2 x\n", "line 3: expected two vertex indices"),
             ("0 1 2\n", "line 1: expected two vertex indices"),
             (f"0, {n_b}\n", f"line 1: B has no vertex {n_b} (it has {n_b}, numbered from 0)"),
             (f"{n_a} 0\n", f"line 1: A has no vertex {n_a}"),
             ("5 1\n\n5 2\n", "lines 1 and 3 both give vertex 5 of A a match"),
             ("-1 2\n", "line 1: expected two vertex indices")]
    for text, expected in cases:
        marks.write_text(text)
        code, out, err = cli(capsys, "compare", *pair, *FAST, "--locate", "--locate-landmarks", marks)
        line = one_line_error(code, err)
        assert f"--locate-landmarks {marks}" in line and expected in line, line
        assert "distance" not in out  # refused before the comparison
    line = one_line_error(*cli(capsys, "compare", *pair, *FAST, "--locate-landmarks", marks)[::2])
    assert "--locate-landmarks gives --locate landmarks; add --locate" in line
    line = one_line_error(*cli(capsys, "compare", *pair, *FAST, "--locate", "--locate-landmarks",
                               tmp_path / "none.txt")[::2])
    assert f"--locate-landmarks: file not found: {tmp_path / 'none.txt'}" in line


@pytest.mark.parametrize("args, expected", OTHER_BAD_VALUES)
def test_other_commands_name_their_flags(args, expected, run, dataset, capsys):
    args = [str(run) if x == "RUN" else str(dataset) if x == "DATA" else x for x in args]
    line = one_line_error(*cli(capsys, *args)[::2])
    assert expected in line, line


def test_library_messages_are_worded_with_flags():
    from wpot.cli import cli_words

    assert cli_words("pass scale_invariant=True (CLI --scale-invariant); or more eigenpairs (n_eigen)") == \
        "pass --scale-invariant; or more eigenpairs (--n-eigen)"
    assert cli_words("n_eigen=100 but the mesh has only 42 vertices") == "--n-eigen 100 but the mesh has only 42 vertices"
    assert cli_words("pass max_vertices (at most about 300 here)") == "pass --max-vertices (at most about 300 here)"
    assert cli_words("use pooling='none' here") == "use --pooling none here"
    assert cli_words("slab must be a positive finite number") == "--ldsift-slab must be a positive finite number"
    assert cli_words("n_times must be an integer >= 2, got 1") == "--hks-n-times must be an integer >= 2, got 1"
    # one-word names are English except as the subject of a rule
    assert cli_words("balanced transport must converge; transport must be one of") == \
        "balanced transport must converge; --transport must be one of"
    assert cli_words("Repair the mesh with Mesh.cleaned().") == "Repair the mesh with --repair."
    assert cli_words("consider Mesh.cleaned(keep_largest_component=True).") == "consider --largest-component."
    assert cli_words("Mesh.cleaned() removes them (keep_largest_component=True drops the smaller components) and "
                     "returns the index map.") == \
        "--repair removes them (--largest-component drops the smaller components)."
    assert cli_words("fps_metric must be one of ('geodesic',)") == "fps_metric must be one of ('geodesic',)"  # no flag


def test_warnings_are_worded_with_flags(dataset, capsys):
    # blob1 has 100 vertices: a WKS with 120 eigenpairs uses all 100, and says so
    code, _, err = cli(capsys, "compare", dataset / "blob1.off", dataset / "blob2.off", "--n-eigen", "120",
                       "--n-energies", "30", "--progress")
    assert code == 0
    assert re.search(r"^wpot: warning: --n-eigen 120 but the mesh has only 100 vertices", err, re.M), err
    assert "n_eigen" not in err
    # the warning came while A's signatures were computed: it has a line of its own, and so has the step's time
    assert re.search(r"^WKS signatures of A \(100 vertices\) \.\.\. \nwpot: warning: .*\n"
                     r"WKS signatures of A \(100 vertices\): \d+\.\d s$", err, re.M), err


def test_a_line_written_during_a_stage_breaks_it():
    from wpot.progress import Progress

    buf = io.StringIO()
    p = Progress(buf, clock=Clock())
    with p.stage("spectrum"):
        p.write("a note")
    assert buf.getvalue() == "spectrum ... \na note\nspectrum: 1.0 s\n"


def test_a_resume_mismatch_lists_only_what_differs_by_flag(run, dataset, capsys):
    from wpot.runs.loop import run_all_vs_all
    from wpot.runs.store import RunMismatchError, param_differences

    line = one_line_error(*cli(capsys, "all-vs-all", dataset, "--out", run, *FAST, "--max-vertices", "50")[::2])
    assert line.endswith(f"{run} holds a run with other settings: --max-vertices: stored none, requested 50. "
                         "Use another --out folder, or rerun with the stored settings to resume."), line
    line = one_line_error(*cli(capsys, "all-vs-all", dataset, "--out", run, "--signature", "ldsift",
                                "--ot-method", "ipm")[::2])
    assert "settings: --signature: stored wks, requested ldsift; --ot-method: stored auto, requested ipm. " in line
    # in Python, by keyword; the differences are also given as data
    with pytest.raises(RunMismatchError) as info:
        run_all_vs_all(dataset, run, progress=False, n_eigen=30, n_energies=30, max_vertices=50, pooling="cell")
    assert info.value.differences == (("max_vertices", None, 50), ("pooling", "none", "cell"))
    assert "fps_metric" not in str(info.value)
    # an option with no flag is named when it differs, and only then
    stored = {"signature": "wks", "transport": "balanced", "max_vertices": 50, "fps_metric": "geodesic",
              "pooling": "none", "solver_options": {}}
    assert param_differences(stored, {**stored, "fps_metric": "euclidean"}) == [("fps_metric", "geodesic", "euclidean")]
    assert param_differences(stored, {**stored, "solver_options": {"tol": 1e-8}}) == [("solver_options.tol", None, 1e-8)]


# ------------------------------------------------------------------------------------------ 6. subsampling
def test_the_summary_says_what_the_transport_ran_on(pair, capsys):
    from wpot.cli import build_parser, config_from_args

    a, b = pair
    code, out, _ = cli(capsys, "compare", a, b, *FAST, "--max-vertices", "100")
    assert code == 0
    assert "transport on 100 x 100 farthest-point samples of 300 x 300 vertices" in out
    assert re.search(r"^matched pairs \(G > 0\.9 m1\): \d+ of 100 samples of A$", out, re.M), out
    config = config_from_args(build_parser().parse_args(["compare", "a", "b", *FAST, "--max-vertices", "100"]))
    assert f"settings: {config.describe()}" in out
    code, out, _ = cli(capsys, "compare", a, b, *FAST)
    assert "transport on every vertex: 300 x 300" in out
    assert re.search(r"^matched pairs \(G > 0\.9 m1\): \d+ of 300 vertices of A$", out, re.M), out


# ------------------------------------------------------------------------------------------------ 7. help
def test_help_describes_arguments_defaults_and_formats():
    from wpot.cli import build_parser
    from wpot.io import MESH_FORMATS

    parser = build_parser()

    def helps(command: str) -> dict[str, str]:
        out = {}
        for a in _subparser(parser, command)._actions:
            out[a.option_strings[0] if a.option_strings else a.dest] = a.help or ""
        return out

    compare = helps("compare")
    assert all(ext in compare["mesh_a"] for ext in MESH_FORMATS) and "the second shape" in compare["mesh_b"]
    assert "default: none, every vertex is used" in compare["--max-vertices"]
    assert "default: none, nothing is saved" in compare["--out"]
    assert all(ext in helps("all-vs-all")["source"] for ext in MESH_FORMATS)
    assert all(ext in parser.format_help() for ext in MESH_FORMATS)
    for command in ("classify", "export"):
        assert "run folder" in helps(command)["run"]
    report = helps("report")
    assert "run folders" in report["runs"] and "trials" in report["--trials"] and "seed" in report["--seed"]
    assert "seed" in helps("classify")["--seed"]
    # all-vs-all's --out is required: so in its usage (no brackets) and in its help
    avs = _subparser(parser, "all-vs-all")
    assert re.search(r"\] --out OUT \[", " ".join(avs.format_usage().split()))
    assert "required" in helps("all-vs-all")["--out"]
    for command in ("demo", "compare", "all-vs-all"):
        assert {"--progress", "--no-progress", "--repair"} <= set(helps(command))


def test_classify_names_shapes_that_are_the_same_mesh(dataset, capsys, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    shutil.copy(dataset / "blob1.off", data / "blob7.off")
    code, _, err = cli(capsys, "all-vs-all", data, "--out", tmp_path / "run", *FAST)
    assert code == 0 and "warning: these shapes are the same mesh (the same vertices and triangles): blob1 = blob7" \
        in err
    code, out, err = cli(capsys, "classify", tmp_path / "run")
    assert code == 0 and "the same mesh (the same vertices and triangles): blob1 = blob7. Their distance is 0" in err
    assert "leave-one-out" in out
