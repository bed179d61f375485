"""The `wpot` command end to end (subprocesses), on a handful of small generated shapes."""
from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import FAST_CLI, make_dataset
from wpot.maps.locate import LocateWarning


def wpot(*args: str, cwd: Path | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wpot", *args], capture_output=True, text=True, timeout=timeout, cwd=cwd)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("cli-data"), n_per_class=2)


def _one_line_error(r: subprocess.CompletedProcess, *fragments: str) -> None:
    assert r.returncode == 2, (r.returncode, r.stderr)
    # one line from wpot (Warp itself may print a device notice on start-up, e.g. no CUDA driver)
    lines = [ln for ln in r.stderr.strip().splitlines() if not ln.startswith("Warp ")]
    assert len(lines) == 1 and lines[0].startswith("wpot: error:"), r.stderr
    assert "Traceback" not in r.stderr
    for f in fragments:
        assert f in lines[0], lines[0]


@pytest.mark.slow
def test_demo_prints_a_distance_and_saves_a_picture(tmp_path):
    r = wpot("demo", "--out", str(tmp_path / "demo"), "--n", "200")  # the default is 400 vertices
    assert r.returncode == 0, r.stderr
    printed = float(re.search(r"^distance: (\S+)", r.stdout, re.M).group(1))
    info = json.loads((tmp_path / "demo" / "comparison.json").read_text())
    assert printed == pytest.approx(info["distance"], rel=1e-5)
    png = (tmp_path / "demo" / "correspondence.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert info["median_error_edge_lengths"] < 2.0  # the example pair's ground truth
    angle = float(re.search(r"rotation off by (\S+) degrees", r.stdout).group(1))
    assert angle < 5.0
    # --zoomout refines the map: against the known truth it is no worse, and the picture and npz show it
    rz = wpot("demo", "--out", str(tmp_path / "dz"), "--n", "200", "--zoomout")
    assert rz.returncode == 0, rz.stderr
    iz = json.loads((tmp_path / "dz" / "comparison.json").read_text())
    assert iz["median_error_edge_lengths"] == pytest.approx(info["median_error_edge_lengths"])
    assert iz["median_error_edge_lengths_zoomout"] <= iz["median_error_edge_lengths"]
    assert np.load(tmp_path / "dz" / "correspondence.npz")["correspondence_zoomout"].shape == (200,)


@pytest.mark.slow
def test_compare_partial_is_exact_and_certified_against_its_objective(dataset, tmp_path):
    r = wpot("compare", str(dataset / "blob1.off"), str(dataset / "flat2.off"), *FAST_CLI, "--transport", "partial",
             "--out", str(tmp_path / "p"))
    assert r.returncode == 0, r.stderr
    m = re.search(r"^converged: True, the exact optimum \(beta = inf; certified gap (\S+) of the objective, Eq. 17",
                  r.stdout, re.M)
    assert m and float(m.group(1)) <= 1e-6
    info = json.loads((tmp_path / "p" / "comparison.json").read_text())
    assert info["beta"] is None and len(info["history"]) == 1


@pytest.mark.slow
def test_compare_two_files(dataset, tmp_path):
    r = wpot("compare", str(dataset / "blob1.off"), str(dataset / "flat2.off"), *FAST_CLI, "--out", str(tmp_path / "c"))
    assert r.returncode == 0, r.stderr
    printed = float(re.search(r"^distance: (\S+)", r.stdout, re.M).group(1))
    info = json.loads((tmp_path / "c" / "comparison.json").read_text())
    assert printed == pytest.approx(info["distance"], rel=1e-5)
    assert info["history"][-1][1] == pytest.approx(info["distance"], rel=1e-6)
    z = np.load(tmp_path / "c" / "correspondence.npz")
    assert z["correspondence"].shape == z["mass1"].shape and z["correspondence"].max() < len(z["mass2"])
    assert z["confidence"].shape == z["correspondence"].shape and z["region"].shape == z["mass2"].shape
    assert 0 <= z["confidence"].min() <= z["confidence"].max() <= 1 and z["region"].all()  # balanced: all of B
    assert (tmp_path / "c" / "correspondence.png").is_file()
    # the default is the exact LP: its one step is beta = infinity (null in the JSON, which has no infinity)
    assert info["beta"] is None and info["history"] == [[None, info["distance"]]]
    assert re.search(r"^converged: True, the exact optimum \(beta = inf; certified gap \S+ of U", r.stdout, re.M)
    # the interior-point start and annealing reach the same distance, and record D(beta) along the way
    infos = {}
    for m in ("ipm", "anneal"):
        r2 = wpot("compare", str(dataset / "blob1.off"), str(dataset / "flat2.off"), *FAST_CLI, "--ot-method", m,
                  "--out", str(tmp_path / m))
        assert r2.returncode == 0, r2.stderr
        infos[m] = json.loads((tmp_path / m / "comparison.json").read_text())
        assert re.search(r"^converged: True at beta \S+ \(\d+ Newton steps", r2.stdout, re.M)
        assert infos[m]["distance"] == pytest.approx(info["distance"], rel=1e-6)
    assert 1 < len(infos["ipm"]["history"]) < len(infos["anneal"]["history"])
    # a lower --match-ratio can only match more pairs; the summary says which ratio, and why no registration
    matched = lambda out, ratio: int(re.search(rf"matched pairs \(G > {ratio} m1\): (\d+) of", out).group(1))
    r3 = wpot("compare", str(dataset / "blob1.off"), str(dataset / "flat2.off"), *FAST_CLI, "--match-ratio", "0.3")
    assert r3.returncode == 0, r3.stderr
    assert matched(r3.stdout, "0.3") >= matched(r.stdout, "0.9")
    for out in (r.stdout, r3.stdout):
        assert re.search(r"^registration: (scale \S+ \((the size ratio of the two shapes|fitted)\), rms residual|none, fewer than 3 non-collinear pairs matched \()", out, re.M), out
    _one_line_error(wpot("compare", str(dataset / "blob1.off"), str(dataset / "flat2.off"), "--match-ratio", "1.5"),
                    "--match-ratio must be in (0, 1], got 1.5")


@pytest.mark.slow
def test_compare_zoomout_saves_the_refinement_of_the_saved_map(dataset, tmp_path):
    import wpot as w

    a, b = dataset / "blob1.off", dataset / "blob2.off"
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--zoomout", "--out", str(tmp_path / "z"))
    assert r.returncode == 0, r.stderr
    z = np.load(tmp_path / "z" / "correspondence.npz")
    ma, mb = w.load_mesh(a), w.load_mesh(b)
    res = w.zoomout(ma, mb, z["correspondence"])
    expected = res.map
    np.testing.assert_array_equal(z["correspondence_zoomout"], expected)
    # the orientation confidence is printed and saved, as the API gives it
    printed = float(re.search(r"^ZoomOut: orientation confidence (\S+) ", r.stdout, re.M).group(1))
    assert printed == pytest.approx(res.orientation_confidence, abs=0.005)
    info = json.loads((tmp_path / "z" / "comparison.json").read_text())
    assert info["zoomout_orientation_confidence"] == pytest.approx(res.orientation_confidence)
    assert info["zoomout_mended"] is res.mended and ("was mended" in r.stdout) is res.mended
    assert info["zoomout_reanchored"] is res.reanchored and ("mapped again" in r.stdout) is res.reanchored
    changed = float(re.search(r"^ZoomOut: (\S+)% of A's vertices changed their match", r.stdout, re.M).group(1))
    assert changed == pytest.approx(100 * np.mean(expected != z["correspondence"]), abs=0.05)
    assert json.loads((tmp_path / "z" / "comparison.json").read_text())["zoomout"] is True


@pytest.mark.slow
def test_compare_locate_saves_the_located_map_of_the_api(dataset, tmp_path):
    import wpot as w

    a, b = dataset / "blob1.off", dataset / "flat2.off"
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--transport", "partial", "--locate", "--out", str(tmp_path / "l"))
    assert r.returncode == 0, r.stderr
    z = np.load(tmp_path / "l" / "correspondence.npz")
    ma, mb = w.load_mesh(a), w.load_mesh(b)
    c = w.Comparer(transport="partial", n_eigen=30, n_energies=30, device="cpu", cache_dir=False)
    c.compare(ma, mb)  # fits the WKS energies to the pair, as the CLI does
    pm = c.locate(ma, mb)
    np.testing.assert_array_equal(z["correspondence_locate"], pm.correspondence)
    np.testing.assert_allclose(z["confidence_locate"], pm.confidence)
    np.testing.assert_array_equal(z["region_locate"], pm.region())
    n = int(re.search(r"^locate: (\d+) consistent anchor matches", r.stdout, re.M).group(1))
    info = json.loads((tmp_path / "l" / "comparison.json").read_text())["locate"]
    assert n == info["n_anchors"] == len(pm.anchors)
    printed = float(re.search(r"^placement confidence ([\d.]+):", r.stdout, re.M).group(1))
    assert printed == pytest.approx(info["placement_confidence"], abs=0.005)
    assert info["placement_confidence"] == pytest.approx(pm.placement_confidence)
    if np.isfinite(pm.side_margin):  # the side margin, printed and saved (JSON: "inf" and null otherwise)
        assert float(re.search(r"^side margin ([\d.]+):", r.stdout, re.M).group(1)) == pytest.approx(pm.side_margin,
                                                                                               abs=5e-4)
        assert info["side_margin"] == pytest.approx(pm.side_margin)
    else:
        assert info["side_margin"] == ("inf" if np.isinf(pm.side_margin) else None)
    for name in ("other_side", "other_place"):  # the other answers, saved when the map has them
        if getattr(pm, name) is None:
            assert f"correspondence_locate_{name}" not in z
        else:
            np.testing.assert_array_equal(z[f"correspondence_locate_{name}"], getattr(pm, name))
    _one_line_error(wpot("compare", str(a), str(b), "--zoomout", "--locate"), "--zoomout and --locate")
    # --locate-orient-weight is LocateOptions(orient_weight=...)
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--transport", "partial", "--locate", "--locate-orient-weight",
             "0.3", "--out", str(tmp_path / "w"))
    assert r.returncode == 0, r.stderr
    weighed = c.locate(ma, mb, options=w.LocateOptions(orient_weight=0.3))
    np.testing.assert_array_equal(np.load(tmp_path / "w" / "correspondence.npz")["correspondence_locate"],
                                  weighed.correspondence)
    # --locate-aligned is LocateOptions(aligned=True)
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--transport", "partial", "--locate", "--locate-aligned",
             "--out", str(tmp_path / "al"))
    assert r.returncode == 0, r.stderr
    with pytest.warns(LocateWarning, match="aligned"):  # these two blobs are not in one frame
        aligned = c.locate(ma, mb, options=w.LocateOptions(aligned=True))
    assert "aligned=True" in r.stderr
    np.testing.assert_array_equal(np.load(tmp_path / "al" / "correspondence.npz")["correspondence_locate"],
                                  aligned.correspondence)
    # --locate-scale is LocateOptions(scale=...), printed and saved
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--transport", "partial", "--locate", "--locate-scale", "1.2",
             "--out", str(tmp_path / "s"))
    assert r.returncode == 0, r.stderr
    scaled = c.locate(ma, mb, options=w.LocateOptions(scale=1.2))
    np.testing.assert_array_equal(np.load(tmp_path / "s" / "correspondence.npz")["correspondence_locate"],
                                  scaled.correspondence)
    assert json.loads((tmp_path / "s" / "comparison.json").read_text())["locate"]["scale"] == scaled.scale == 1.2
    assert "A's lengths times 1.2 are B's" in r.stdout
    # --locate-landmarks FILE is Comparer.locate(landmarks=...), its rows read as (vertex of A, vertex of B)
    marks = np.array([[0, pm.correspondence[0]], [ma.n_vertices - 1, 3]])
    (tmp_path / "marks.txt").write_text("# vertex of A, vertex of B\n" + "\n".join(f"{i} {j}" for i, j in marks))
    r = wpot("compare", str(a), str(b), *FAST_CLI, "--transport", "partial", "--locate", "--locate-landmarks",
             str(tmp_path / "marks.txt"), "--out", str(tmp_path / "m"))
    assert r.returncode == 0, r.stderr
    pinned = c.locate(ma, mb, landmarks=marks)
    np.testing.assert_array_equal(np.load(tmp_path / "m" / "correspondence.npz")["correspondence_locate"],
                                  pinned.correspondence)
    assert json.loads((tmp_path / "m" / "comparison.json").read_text())["locate"]["landmarks"] == 2
    assert re.search(r"^landmarks: 2 from .*marks\.txt; the map puts them a mean of", r.stdout, re.M)


@pytest.mark.slow
def test_all_vs_all_classify_report(dataset, tmp_path):
    run = tmp_path / "run"
    r = wpot("all-vs-all", str(dataset), "--signature", "wks", "--transport", "balanced", "--out", str(run), "--no-progress",
             "--ot-method", "anneal", *FAST_CLI)  # D(beta) along the annealing
    assert r.returncode == 0, r.stderr
    assert "6 of 6 pairs" in r.stdout
    r = wpot("classify", str(run), "--trials", "200")
    assert r.returncode == 0, r.stderr
    # two well-separated classes: every query's nearest training shape is of its class
    assert re.search(r"200 trials: 100\.0%", r.stdout), r.stdout
    assert re.search(r"leave-one-out 1-NN at level 'class' \(2 groups\): 100\.0%", r.stdout), r.stdout
    info = json.loads((run / "classification.json").read_text())
    assert info["one_shot"]["mean"] == 1.0 and info["not_converged"] == 0
    # D(beta) on the powers of ten, ending at the last annealing beta, where D(beta) is D(inf)
    betas = np.array([b for b, _ in info["one_shot_per_beta"]])
    np.testing.assert_allclose(np.log10(betas), np.round(np.log10(betas)), atol=1e-12)
    assert np.all(np.diff(betas) > 0) and info["one_shot_per_beta"][-1][1] == 1.0
    assert "did not converge" not in r.stderr
    assert info["draws"] is None
    # random draws of k shapes per class: with k = the class size each draw is the whole run
    r = wpot("classify", str(run), "--trials", "200", "--draws", "3", "--per-class", "2")
    assert r.returncode == 0, r.stderr
    assert "over 3 random draws of 2 shapes per class: one-shot 100.0%" in r.stdout, r.stdout
    d = json.loads((run / "classification.json").read_text())["draws"]
    assert d["n_draws"] == 3 and d["one_shot"] == [1.0] * 3 and d["leave_one_out"] == [1.0] * 3
    _one_line_error(wpot("classify", str(run), "--draws", "3", "--per-class", "3"), "--per-class 3", "fewer shapes")
    # a pair the solver did not converge on is flagged, never used silently
    import sqlite3

    con = sqlite3.connect(run / "wpot.sqlite")
    con.execute("UPDATE pairs SET converged = 0 WHERE rowid = (SELECT min(rowid) FROM pairs WHERE i <> j)")
    con.commit()
    con.close()
    r = wpot("classify", str(run), "--trials", "200")
    assert r.returncode == 0 and "warning: 1 of 6 pairs did not converge" in r.stderr, r.stderr
    assert json.loads((run / "classification.json").read_text())["not_converged"] == 1
    r = wpot("report", str(run), "--trials", "200")
    assert r.returncode == 0, r.stderr
    text = (run / "report.md").read_text()
    assert "- not converged (1; their distances may be wrong): " in text  # the pair classify warned about
    # export: CSV with names, NPZ without pickles; both warn about the pair that did not converge
    from wpot.runs.store import RunStore

    with RunStore(run) as store:
        d_run, names_run = store.distance_matrix(), store.names
    r = wpot("export", str(run))
    assert r.returncode == 0 and "pairs did not converge" in r.stderr, r.stderr
    rows = list(csv.reader((run / "distances.csv").open()))
    assert rows[0] == ["", *names_run] and [row[0] for row in rows[1:]] == names_run
    np.testing.assert_array_equal(np.array([[float(x) for x in row[1:]] for row in rows[1:]]), d_run)
    r = wpot("export", str(run), "--out", str(tmp_path / "d.npz"))
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "d.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["distances"], d_run)
        assert z["names"].tolist() == names_run and z["converged"].sum() == len(d_run) * (len(d_run) - 1) - 2
        assert z["distances_beta"].shape == (len(z["betas"]), len(d_run), len(d_run))
        np.testing.assert_allclose(z["distances_beta"][-1], d_run, rtol=1e-6)  # the last decade is D(inf)
        assert sorted(set(z["labels_class"])) == sorted(set(n.rstrip("0123456789") for n in names_run))
    _one_line_error(wpot("export", str(run), "--out", str(tmp_path / "d.txt")), "export writes .csv or .npz")
    assert "| OT (balanced) | — | 83.3 | 100.0 | 100.0 |" in text
    assert "| OT (partial) | — | 97.3 | — | 98.6 |" in text
    assert (run / "distance_matrix.png").is_file() and (run / "confusion.png").is_file()
    assert "![one-shot confusion](confusion.png)" in text
    assert "One-shot classes below 100 % (and what they were taken for): none." in text
    # make one shape of each class the other's nearest: both are named, with what they were taken for
    con = sqlite3.connect(run / "wpot.sqlite")
    names = dict(con.execute("SELECT idx, name FROM shapes"))
    labels = dict(con.execute("SELECT idx, label FROM labels WHERE level = 'class'"))
    i = min(k for k in labels if labels[k] == labels[0] and k != 0)
    j = min(k for k in labels if labels[k] != labels[0])
    con.execute("UPDATE pairs SET distance = 1e-9 * distance WHERE i = ? AND j = ?", (min(i, j), max(i, j)))
    con.commit()
    con.close()
    r = wpot("classify", str(run), "--trials", "200")
    assert r.returncode == 0, r.stderr
    info = json.loads((run / "classification.json").read_text())
    wrong = {(w["shape"], w["nearest"]) for w in info["leave_one_out_wrong"]["class"]}
    assert wrong == {(names[i], names[j]), (names[j], names[i])}
    for a, b in wrong:
        assert f"{a} ({labels[[k for k in names if names[k] == a][0]]}) -> {b}" in r.stdout, r.stdout
    conf = np.array(info["one_shot"]["confusion"])
    np.testing.assert_allclose(conf.sum(1), 1.0)
    assert np.diag(conf).mean() == pytest.approx(info["one_shot"]["mean"])  # two classes of two: equal weights
    assert info["one_shot"]["mean"] < 1 and "classes below 100%: " in r.stdout
    # the same folder with other parameters is refused, in one line
    r = wpot("all-vs-all", str(dataset), "--transport", "partial", "--out", str(run), "--no-progress", *FAST_CLI)
    _one_line_error(r, "other settings", "--transport: stored balanced, requested partial")
    # an incomplete run exports with the gap marked (an empty cell), and says so
    con = sqlite3.connect(run / "wpot.sqlite")
    con.execute("DELETE FROM pairs WHERE i = 0 AND j = 1")
    con.commit()
    con.close()
    r = wpot("export", str(run), "--out", str(tmp_path / "part.csv"))
    assert r.returncode == 0 and "the run is incomplete: 1 pairs are missing" in r.stderr, r.stderr
    rows = list(csv.reader((tmp_path / "part.csv").open()))
    assert rows[1][2] == "" and rows[2][1] == "" and "5 of 6 pairs" in r.stdout


@pytest.mark.slow
def test_partial_all_vs_all_with_labels(dataset, tmp_path):
    csv = tmp_path / "labels.csv"
    names = sorted(p.stem for p in dataset.glob("*.off"))
    csv.write_text("name,kind,shape\n" + "".join(f"{n},{n[:4]},{'round' if n.startswith('blob') else 'long'}\n" for n in names))
    run = tmp_path / "prun"
    r = wpot("all-vs-all", str(dataset), "--transport", "partial", "--labels", str(csv), "--out", str(run), "--no-progress", *FAST_CLI)
    assert r.returncode == 0, r.stderr
    assert "10 of 10 pairs" in r.stdout  # 6 pairs + 4 self-comparisons
    r = wpot("classify", str(run), "--trials", "100")
    assert r.returncode == 0, r.stderr
    assert "level 'kind'" in r.stdout and "level 'shape'" in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize(
    "args, fragments",
    [
        (["compare", "missing-a.off", "missing-b.off"], ["not found", "missing-a.off"]),
        (["all-vs-all", "no-such-folder", "--out", "r"], ["no such folder", "no-such-folder"]),
        (["classify", "no-such-run"], ["no wpot run", "no-such-run"]),
        (["report", "no-such-run"], ["no wpot run"]),
        (["compare", "a.off", "b.off", "--transport", "partial", "--ot-method", "ipm"], ["--ot-method ipm", "balanced"]),
        (["compare", "a.off", "b.off", "--transport", "partial", "--zoomout"], ["--zoomout", "whole", "--transport partial"]),
        (["compare", "a.off", "b.off", "--locate-edge", "whole"], ["--locate-edge", "add --locate"]),
        (["compare", "a.off", "b.off", "--locate-orient-weight", "0.3"], ["--locate-orient-weight", "add --locate"]),
        (["compare", "a.off", "b.off", "--locate-scale", "fit"], ["--locate-scale", "add --locate"]),
        (["compare", "a.off", "b.off", "--locate-aligned"], ["--locate-aligned", "add --locate"]),
        (["compare", "a.off", "b.off", "--locate", "--locate-scale", "0"], ["--locate-scale", "positive number"]),
        (["compare", "a.off", "b.off", "--locate", "--locate-edge", "whole"], ["--signature wks", "--signature ldsift"]),
    ],
)
def test_bad_input_exits_2_with_one_line(args, fragments, tmp_path):
    _one_line_error(wpot(*args, cwd=tmp_path), *fragments)


@pytest.mark.slow
def test_labels_csv_missing_and_unparsable_mesh(dataset, tmp_path):
    _one_line_error(wpot("all-vs-all", str(dataset), "--out", str(tmp_path / "r"), "--labels", "nope.csv", cwd=tmp_path), "label CSV not found")
    bad = tmp_path / "bad.off"
    bad.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")
    _one_line_error(wpot("compare", str(bad), str(dataset / "blob1.off")), "bad.off")


def test_method_options_reach_the_comparer():
    from wpot.cli import build_parser, config_from_args
    from wpot.comparison import Comparer

    a = build_parser().parse_args(["compare", "a.off", "b.off", "--max-vertices", "50", "--pooling", "cell",
                                   "--scale-invariant", "--device", "cpu"])
    p = Comparer(config_from_args(a), device="cpu").params()
    assert p["pooling"] == "cell" and p["scale_invariant"] is True and p["max_vertices"] == 50
    d = Comparer(config_from_args(build_parser().parse_args(["compare", "a.off", "b.off", "--max-vertices", "50",
                                                                "--device", "cpu"])), device="cpu").params()
    assert d["pooling"] == "none" and d["scale_invariant"] is False  # the library's defaults
    # --ot-method: auto (default) leaves the choice to the Comparer (and the run key as before auto existed);
    # anneal and ipm are passed on for balanced transport, anneal for partial transport (ipm is refused there)
    def solver(*extra):
        args = build_parser().parse_args(["compare", "a.off", "b.off", "--device", "cpu", *extra])
        return Comparer(config_from_args(args), device="cpu").params()["solver_options"]

    assert solver() == {} and solver("--ot-method", "auto") == {}
    assert solver("--ot-method", "anneal") == {"method": "anneal"} and solver("--ot-method", "ipm") == {"method": "ipm"}
    assert solver("--transport", "partial", "--ot-method", "anneal") == {"method": "anneal"}
    assert solver("--transport", "partial") == {}


def test_ldsift_slab_reaches_the_comparer_and_runs_stored_before_it_resume():
    from wpot.cli import build_parser, config_from_args
    from wpot.comparison import Comparer

    def params(*extra):
        args = build_parser().parse_args(["compare", "a.off", "b.off", "--signature", "ldsift", "--device", "cpu", *extra])
        return Comparer(config_from_args(args), device="cpu").params()

    assert params("--ldsift-slab", "0.25")["ldsift_slab"] == 0.25
    # the default, 1, was the only slab before the option existed: the run key is the one of then
    assert "ldsift_slab" not in params() and params() == params("--ldsift-slab", "1")


def test_percentages_never_round_up_to_100_or_down_to_0():
    from wpot.evaluate import format_percent as _pct

    assert _pct(1.0) == "100.0%" and _pct(0.0) == "0.0%" and _pct(0.5) == "50.0%"
    assert _pct(0.9998) == "99.98%" and _pct(0.99996) == "99.996%" and _pct(0.99949) == "99.9%"
    assert _pct(0.00004) == "0.004%" and _pct(0.0004) == "0.04%"
    assert _pct(1 - 1e-9) == "99.9999%"  # at most 4 decimals; short of 100 % shows as 99.9999 %
    assert _pct(0.9997, decimals=0) == "99.97%" and _pct(0.97, decimals=0) == "97%" and _pct(1.0, decimals=0) == "100%"
    with pytest.raises(ValueError, match="decimals"):
        _pct(0.5, decimals=-1)


def test_summary_says_why_balanced_transport_matched_nothing():
    from types import SimpleNamespace

    from wpot.cli import _summary_lines

    res = SimpleNamespace(converged=True, beta=1e9, n_newton=10, n_linear=100)
    c = SimpleNamespace(distance=1.0, transport="balanced", signature="wks", result=res, matched=np.zeros((0, 2)),
                        correspondence=np.zeros(100), mass1=np.full(100, 0.01), mass2=np.full(120, 1 / 120),
                        registration=None)
    text = "\n".join(_summary_lines(c, 0.9))
    # 120 > 100 / 0.9: no vertex of A can put 0.9 of its mass on one vertex of B
    assert "only when 120 <= 100/0.9; use --transport partial" in text
    assert "only when" not in "\n".join(_summary_lines(c, 0.8))  # 120 <= 125: the sizes are not the reason


@pytest.mark.slow
def test_retrieve_prints_and_saves_the_library_ranking(dataset, tmp_path):
    """`wpot retrieve` ranks the classes as `Comparer.retrieve` does on the same meshes (LD-SIFT with its
    thickness column at 2, the command's default), prints them best first and saves the whole ranking."""
    import wpot as wp_
    from wpot.io import save_mesh

    blob = wp_.load_mesh(dataset / "blob1.off")
    part = wp_.cut(blob, np.arange(blob.n_vertices // 2))[0]
    save_mesh(part, tmp_path / "part.off")
    library = sorted(p for p in dataset.glob("*.off") if p.stem != "blob1")
    # a list file as all-vs-all reads it: paths relative to the list, '#' comments
    rel = [os.path.relpath(p, tmp_path) for p in library]
    (tmp_path / "list.txt").write_text("# the library\n" + "\n".join(f"{q}  # {Path(q).stem}" for q in rel))
    r = wpot("retrieve", str(tmp_path / "part.off"), str(tmp_path / "list.txt"), "--out", str(tmp_path / "r.json"),
             "--device", "cpu")
    assert r.returncode == 0, r.stderr
    saved = json.loads((tmp_path / "r.json").read_text())
    c = wp_.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    ref = c.retrieve(wp_.load_mesh(tmp_path / "part.off"), [wp_.load_mesh(p) for p in library],
                     [wp_.class_label(p.stem) for p in library])
    assert saved["classes"] == list(ref.classes)
    np.testing.assert_allclose(saved["scores"], ref.scores, rtol=1e-6, atol=1e-9)
    assert saved["whole_costs"] == pytest.approx(dict(zip((p.stem for p in library), ref.whole_costs)))
    printed = re.findall(r"^\s+\d+\. (\S+)\s+score", r.stdout, re.M)
    assert printed == list(ref.classes)
    assert saved["margin"] == pytest.approx(ref.margin) and f"margin {ref.margin:.3g}" in r.stdout
    # LD-SIFT at the thickness the probability was calibrated for: printed and saved
    assert ref.calibrated and saved["probability"] == pytest.approx(ref.probability)
    assert f"probability that {ref.label} is right {ref.probability:.2f}" in r.stdout
    # one LD-SIFT edge length for the part and the library, the library's: printed and saved
    from wpot.signatures._frames import common_edge

    edge = common_edge([wp_.load_mesh(p) for p in library])
    assert saved["ldsift_edge"] == pytest.approx(edge) and f"library, {edge:.3g}" in r.stdout
    bad = wpot("retrieve", str(tmp_path / "part.off"), str(dataset), "--k-nearest", "0")
    _one_line_error(bad, "--k-nearest must be at least 1")
    bad = wpot("retrieve", str(tmp_path / "part.off"), str(tmp_path / "nowhere"))
    _one_line_error(bad, "no such folder or list file")
    bad = wpot("retrieve", str(tmp_path / "part.off"), str(library[0]))
    _one_line_error(bad, "got the single mesh")


@pytest.mark.slow
def test_retrieve_calibrates_on_the_library_once_and_reuses_it(dataset, tmp_path):
    """`wpot retrieve --calibration F`: the first call fits the library's calibration (as
    `Comparer.calibrate_retrieval` does) and saves it to F; later calls read F and print the same probability; a
    calibration of other settings, or a file that is not one, is a one-line error naming the flag."""
    import wpot as wp_
    from wpot.io import save_mesh
    from wpot.maps.retrieval import RetrievalCalibration

    blob = wp_.load_mesh(dataset / "blob1.off")
    save_mesh(wp_.cut(blob, np.arange(blob.n_vertices // 2))[0], tmp_path / "part.off")
    cal_file = tmp_path / "cal.json"
    args = ("retrieve", str(tmp_path / "part.off"), str(dataset), "--calibration", str(cal_file),
            "--calibration-parts", "3", "--device", "cpu", "--out", str(tmp_path / "r.json"))
    first = wpot(*args)
    assert first.returncode == 0, first.stderr
    assert "calibrated on the library" in first.stdout and cal_file.exists()
    assert not (tmp_path / "cal.json.lookups.jsonl").exists()  # the lookups' record, once the result is saved
    cal = RetrievalCalibration.from_json(cal_file.read_text())
    library = sorted(dataset.glob("*.off"))
    ref = wp_.Comparer(signature="ldsift", device="cpu", cache_dir=False).calibrate_retrieval(
        [wp_.load_mesh(p) for p in library], [wp_.class_label(p.stem) for p in library], n_parts=3)
    assert cal.n_parts == 3 and cal.coefficients == pytest.approx(ref.coefficients, rel=1e-6)
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["calibration"] == str(cal_file)
    assert saved["probability"] == pytest.approx(cal.probability(saved["margin"]))
    assert "(the library's own calibration)" in first.stdout
    again = wpot(*args)
    assert again.returncode == 0, again.stderr
    assert "calibrated on the library" not in again.stdout
    assert json.loads((tmp_path / "r.json").read_text())["probability"] == pytest.approx(saved["probability"])
    bad = wpot(*args, "--k-nearest", "1")
    _one_line_error(bad, "was fitted with other settings than these")
    fewer = tmp_path / "fewer"
    fewer.mkdir()
    for p in library[1:]:
        (fewer / p.name).write_bytes(p.read_bytes())
    _one_line_error(wpot("retrieve", str(tmp_path / "part.off"), str(fewer), "--calibration", str(cal_file),
                         "--device", "cpu"), "was fitted on another library")
    cal_file.write_text("not json")
    _one_line_error(wpot(*args), f"--calibration {cal_file}: not a RetrievalCalibration's JSON")
