"""Outputs of the `wpot` command that must not mislead: what it overwrites, refuses, names and prints.

The command runs in-process (`wpot.cli.main`) on small generated meshes, with a short spectrum."""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from helpers import FAST_CLI, cli, one_line_error








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


# --------------------------------------------------------------------------------- compare --locate --out
def test_the_picture_places_b_by_the_located_map_that_is_reported(capsys, tmp_path, monkeypatch):
    """With --locate, correspondence.png draws the located map over B moved by the inverse of a rigid fit to that
    map (not by the transport's registration), and says its confidence; comparison.json records that fit."""
    import wpot
    import wpot.plot
    from wpot.cli import located_registration
    from wpot.examples import example_pair
    from wpot.io import save_mesh
    from wpot.mesh import cut

    p = example_pair(300, seed=0, n_target=300)
    v = p.source.vertices
    part = cut(p.source, v[:, 0] > np.median(v[:, 0]))[0]
    save_mesh(part, tmp_path / "part.off")
    save_mesh(p.target, tmp_path / "whole.off")
    drawn = {}

    def spy(source, target, correspondence, **kw):
        drawn.update(source=source, target=target, correspondence=np.asarray(correspondence), titles=kw["titles"])

    monkeypatch.setattr(wpot.plot, "plot_correspondence", spy)
    code, out, err = cli(capsys, "compare", tmp_path / "part.off", tmp_path / "whole.off", *FAST_CLI, "--transport",
                         "partial", "--locate", "--out", tmp_path / "l", "--device", "cpu")
    assert code == 0, err
    # the same located map from the API, and the fit to it
    a, b = wpot.load_mesh(tmp_path / "part.off"), wpot.load_mesh(tmp_path / "whole.off")
    pm = wpot.Comparer(n_eigen=30, n_energies=30, transport="partial", device="cpu").locate(a, b)
    np.testing.assert_array_equal(drawn["correspondence"], pm.correspondence)
    reg = located_registration(a, b, pm)
    assert reg.scale == 1.0 and reg.scale_from == "given"
    np.testing.assert_allclose(drawn["target"].vertices, reg.inverse().apply(b).vertices, atol=1e-9)
    info = json.loads((tmp_path / "l" / "comparison.json").read_text())
    saved = info["locate"]["registration"]
    np.testing.assert_allclose(saved["rotation"], reg.rotation, atol=1e-9)
    np.testing.assert_allclose(saved["translation"], reg.translation, atol=1e-9)
    assert saved["scale"] == 1.0 and info["locate"]["median_confidence"] == pytest.approx(np.median(pm.confidence))
    if info["registration"] is not None:  # the transport's own fit is recorded, and is not what placed B
        assert not np.allclose(drawn["target"].vertices,
                               wpot.maps.registration.Registration(**{k: np.asarray(info["registration"][k]) if k in (
                                   "rotation", "translation") else info["registration"][k] for k in (
                                   "scale", "rotation", "translation", "rms", "n_pairs")}).inverse().apply(b).vertices)
    conf = f"median confidence {np.median(pm.confidence):.2f}"
    assert "rigid fit to the located map" in drawn["titles"][1] and conf in drawn["titles"][1]
    assert re.search(rf"^located map: confidence median {np.median(pm.confidence):.2f} \(\d+% of A's vertices above "
                     r"0\.5\); rigid fit of A onto its images \(at the scale locate used, 1\)", out, re.M), out


def test_picture_placement_prefers_the_located_map():
    from types import SimpleNamespace

    from wpot.cli import _Located, picture_placement

    transport = SimpleNamespace(scale=0.38)
    located = SimpleNamespace(scale=1.0)
    pm = SimpleNamespace(confidence=np.array([0.2, 0.6, 0.9]))
    c = SimpleNamespace(registration=transport)
    reg, title = picture_placement(c, _Located(pm, located))
    assert reg is located and "located map (median confidence 0.60)" in title
    reg, title = picture_placement(c, _Located(pm, None))
    assert reg is None and "no rigid fit to the located map" in title
    assert picture_placement(c, None)[0] is transport
    assert picture_placement(SimpleNamespace(registration=None), None) == (None, "B")


# ------------------------------------------------------------------------------ classify and report figures
@pytest.fixture(scope="module")
def odd_run(tmp_path_factory) -> Path:
    """A run over two classes of two shapes and a class of one ("odd"), with a label level "family" that puts
    every shape in one group."""
    from helpers import make_dataset
    from wpot.examples import example_mesh
    from wpot.io import save_mesh
    from wpot.mesh import Mesh
    from wpot.runs.loop import run_all_vs_all

    data = make_dataset(tmp_path_factory.mktemp("odd-data"), n_per_class=2)
    m = example_mesh(110, seed=5)
    save_mesh(Mesh(m.vertices * np.array([0.7, 0.7, 2.2]), m.faces), data / "odd1.off")
    names = sorted(p.stem for p in data.glob("*.off"))
    csv = data.parent / "labels.csv"
    csv.write_text("name,class,family\n" + "".join(f"{n},{n.rstrip('0123456789')},all\n" for n in names))
    run = tmp_path_factory.mktemp("odd-run") / "run"
    run_all_vs_all(data, run, labels=csv, progress=False, n_eigen=30, n_energies=30).close()
    return run


def test_classify_says_what_a_one_shape_class_and_a_one_group_level_mean(odd_run, capsys):
    from wpot.evaluate import format_percent, leave_one_out_1nn
    from wpot.runs.store import RunStore

    code, out, err = cli(capsys, "classify", odd_run, "--trials", "200")
    assert code == 0, err
    with RunStore(odd_run) as store:
        d, labels = store.distance_matrix(), np.array(store.labels("class"))
    res = leave_one_out_1nn(d, labels)
    keep = labels != "odd"
    assert res.score[~keep] == 0  # the one shape of its class: its nearest is always of another class
    line = next(ln for ln in out.splitlines() if ln.startswith("leave-one-out 1-NN at level 'class'"))
    assert line == (f"leave-one-out 1-NN at level 'class' (3 groups): {format_percent(res.accuracy)}; "
                    f"{format_percent(res.score[keep].mean())} without the 1 group of one shape (odd), which "
                    "leave-one-out cannot get right: no other member to find")
    assert "leave-one-out 1-NN at level 'family': not scored, all 5 shapes are in one group (all)" in out
    assert "(1 groups)" not in out
    info = json.loads((odd_run / "classification.json").read_text())
    assert info["leave_one_out"] == {"class": pytest.approx(res.accuracy), "family": None}
    assert info["leave_one_out_without_one_shape_groups"] == {"class": pytest.approx(res.score[keep].mean()),
                                                              "family": None}


def test_report_figures_share_one_class_order_and_mark_a_one_shape_class(odd_run, capsys, monkeypatch, tmp_path):
    import wpot.plot
    import wpot.runs.report

    figures = {}
    for name in ("plot_distance_matrix", "plot_confusion"):
        real = getattr(wpot.plot, name)

        def spy(*args, _real=real, _name=name, **kw):
            figures[_name] = fig = _real(*args, **kw)
            return fig

        monkeypatch.setattr(wpot.runs.report, name, spy)  # the names the report draws with
    code, _, err = cli(capsys, "report", odd_run, "--trials", "200", "--out", tmp_path / "report.md")
    assert code == 0, err
    heat, conf = figures["plot_distance_matrix"].axes[0], figures["plot_confusion"].axes[0]
    top = heat.child_axes[0]
    blocks = [t.get_text() for t in top.xaxis.get_minorticklabels()]
    assert sorted(blocks) == ["blob", "flat", "odd"]
    assert [t.get_text() for t in conf.get_yticklabels()] == blocks == [t.get_text() for t in conf.get_xticklabels()]
    from wpot.runs.store import RunStore

    with RunStore(odd_run) as store:
        names, d = store.names, store.distance_matrix()
    assert sorted(t.get_text() for t in heat.get_yticklabels()) == sorted(names)  # the shapes, named
    off = d[~np.eye(len(d), dtype=bool)]
    assert heat.images[0].get_clim() == pytest.approx((off.min(), off.max()))
    marked = [t for t in conf.texts if t.get_text() == wpot.plot.ONE_MEMBER]
    assert len(marked) == 1 and marked[0].get_position()[1] == blocks.index("odd")
    text = (tmp_path / "report.md").read_text()
    assert "| leave-one-out 1-NN, level `family` (one group) | not scored: every shape is in one group |" in text
    assert "without the 1 group of one shape, which it cannot get right)" in text


def test_retrieve_refuses_a_library_of_one_class_before_any_work(capsys, tmp_path):
    from wpot.examples import example_mesh
    from wpot.io import save_mesh

    (tmp_path / "lib").mkdir()
    for k in range(2):
        save_mesh(example_mesh(60 + 7 * k, seed=k), tmp_path / "lib" / f"blob{k + 1}.off")
    save_mesh(example_mesh(50, seed=5), tmp_path / "part.off")
    code, out, err = cli(capsys, "retrieve", tmp_path / "part.off", tmp_path / "lib", "--device", "cpu", "--progress")
    assert code == 2 and "holds one class ('blob';" in err and "--labels" in err, err
    assert "reading meshes" not in err  # refused before the library is read
