"""The scoring of benchmarks/part_retrieval.py (issue 23's class retrieval from a library of whole shapes):
top-1, the rank of the part's class, unfinished parts left out, and bad arguments refused by flag."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import importlib


@pytest.fixture(scope="module")
def pr():
    return importlib.import_module("benchmarks.part_retrieval")


def test_both_scorings_of_one_part(pr):
    """Nearest whole against `retrieve` on costs built so that they disagree: cat2 explains nine of the part's
    ten vertices best but the tenth (a vertex the pose moved) badly, so its mean loses to dog3's."""
    from wpot.maps.retrieval import RetrievalOptions

    costs = np.column_stack([np.r_[np.full(9, 1.1), 1.0],   # dog3
                             np.r_[np.full(9, 0.9), 5.0],   # cat2
                             np.full(10, 3.0),              # cat4
                             np.full(10, 3.0)])             # dog5
    wholes = ["dog3", "cat2", "cat4", "dog5"]
    r = pr.score_part(costs, wholes, "cat", RetrievalOptions())
    assert r["nearest whole"] == {"top1": False, "rank": 2, "taken_for": "dog3"}
    assert r["retrieve"].pop("margin") > 0
    assert r["retrieve"] == {"top1": True, "rank": 1, "taken_for": "cat (cat2)"}
    # by its nearest member alone and without standardising, retrieve is the nearest whole's class
    raw = pr.score_part(costs, wholes, "cat", RetrievalOptions(k_nearest=1, standardize=False))["retrieve"]
    assert raw == {"top1": False, "rank": 2, "taken_for": "dog (dog3)", "margin": pytest.approx(1.31 - 1.09)}
    # a part sampled: the sample's rows, each weighing its cell (here the first vertex stands for nine)
    from wpot.sampling import Subsample

    cell = Subsample(indices=np.array([0, 9]), nearest=np.r_[np.zeros(9, int), 1], radius=1.0, metric="euclidean")
    sampled = pr.score_part(costs, wholes, "cat", RetrievalOptions(), cell)
    full = pr.score_part(costs, wholes, "cat", RetrievalOptions())
    assert sampled["retrieve"].pop("margin") == pytest.approx(full["retrieve"].pop("margin"), rel=1e-12)
    assert sampled == full
    # a class the library lacks has no rank
    none = pr.score_part(costs, wholes, "wolf", RetrievalOptions())
    assert none["nearest whole"]["rank"] is None and none["retrieve"]["rank"] is None


def test_stored_costs_are_scored_and_reported(pr, tmp_path):
    """Costs stored by the run (npz beside pairs.jsonl) give the same scores as `score_part`; a part without
    stored costs is left out; the report names every failure with what the part was taken for."""
    from wpot.maps.retrieval import RetrievalOptions

    from benchmarks.jsonl_store import JsonlStore

    parts = {"cat0_limb-S": {"class": "cat", "kind": "limb", "fraction": 0.08},
             "dog2_head-L": {"class": "dog", "kind": "head", "fraction": 0.25}}
    store = JsonlStore(tmp_path, keys=("part", "library"), folder="costs")
    rng = np.random.default_rng(0)
    costs = rng.uniform(1, 2, size=(12, 4))
    wholes = ["dog3", "cat2", "cat4", "wolf1"]
    o = RetrievalOptions()
    store.add({"method": pr.method(2.0, None, o.edge), "part": "cat0_limb-S", "library": pr.LIBRARY},
              {"costs": costs.astype(np.float32), "wholes": np.array(wholes)})
    # costs stored at each mesh's own edge lengths are another method: not scored as the library's
    assert pr.method(2.0, None, "own") != pr.method(2.0, None, "library")
    rows = pr.score(JsonlStore(tmp_path, keys=("part", "library"), folder="costs"), parts, 2.0, None, o)
    assert set(rows) == {"cat0_limb-S"}  # dog2_head-L has no costs yet
    expect = pr.score_part(costs.astype(np.float32).astype(np.float64), wholes, "cat", o)
    assert {k: rows["cat0_limb-S"][k] for k in pr.SCORINGS} == expect
    assert rows["cat0_limb-S"]["kind"] == "limb" and rows["cat0_limb-S"]["large"] is False
    pr.report(store, parts, [2.0], None, o, None, tmp_path, lambda m: None)
    text = (tmp_path / "results.md").read_text()
    for sc in pr.SCORINGS:
        top1 = expect[sc]["top1"]
        assert f"| 2 | {sc} | {float(top1):.1%} (1) |" in text
        assert (f"w = 2, {sc}: none" in text) == top1


@pytest.mark.parametrize("weights, says", [("1,x", "numbers separated by commas"), ("-1", "finite and >= 0")])
def test_bad_arguments_are_refused_by_flag(pr, tmp_path, weights, says):
    (tmp_path / "parts.jsonl").write_text(json.dumps({"part": "cat0_head-L", "class": "cat"}) + "\n")
    with pytest.raises(SystemExit, match=f"--weights .*{says}|--weights must be {says}"):
        pr.main(["--parts", str(tmp_path), "--out", str(tmp_path / "out"), "--weights", weights])
    with pytest.raises(SystemExit, match="--ldsift-slab must be a positive number"):
        pr.main(["--parts", str(tmp_path), "--out", str(tmp_path / "out"), "--ldsift-slab", "0"])
    with pytest.raises(SystemExit, match="--parts .*no parts.jsonl"):
        pr.main(["--parts", str(tmp_path / "none"), "--out", str(tmp_path / "out")])


def test_margin_line_counts_the_misses_among_the_least_sure(pr):
    """Ten parts; the two misses have the two smallest margins, so the least sure 20 % hold both."""
    rows = {f"p{k}": {"retrieve": {"margin": float(k), "top1": k >= 2}} for k in range(10)}
    line = pr.margin_line(2.0, rows, share=0.2)
    assert "smallest margins (2) hold 2 of the 2 misses; top-1 over the other parts 100.0%" in line
    assert "largest margin 1" in line
    rows["p9"]["retrieve"]["top1"] = False  # a confident miss
    assert "hold 2 of the 3 misses; top-1 over the other parts 87.5%" in pr.margin_line(2.0, rows, share=0.2)


def test_logistic_fit_recovers_planted_coefficients_and_bins_by_count():
    """benchmarks/retrieval_calibration.py: the logistic fit finds the coefficients outcomes were drawn from,
    and the reliability bins hold about equal counts with their mean probability and accuracy."""
    cal = importlib.import_module("benchmarks.retrieval_calibration")
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.0, 2.0, 20000)
    y = (rng.random(x.size) < 1.0 / (1.0 + np.exp(-(0.5 + 3.0 * x)))).astype(float)
    a, b = cal.fit_logistic(x, y)
    assert a == pytest.approx(0.5, abs=0.1) and b == pytest.approx(3.0, abs=0.15)
    assert all(np.isnan(cal.fit_logistic(x, np.ones_like(x))))  # every part right: nothing to fit
    p = np.linspace(0.05, 0.95, 100)
    ok = (np.arange(100) % 2).astype(float)
    bins = cal.reliability(p, ok)
    assert [n for n, _, _ in bins] == [10] * 10
    assert bins[0][1] == pytest.approx(p[:10].mean()) and bins[0][2] == pytest.approx(0.5)


def test_calibration_sets_name_their_data_or_take_the_default(tmp_path):
    """benchmarks/retrieval_calibration.py: a set is RESULTS PARTS [DATA]; without DATA the default data folder,
    and a DATA that is not a folder, or a set of another length, stops the run with its reason."""
    cal = importlib.import_module("benchmarks.retrieval_calibration")
    assert cal._set(["r", "p"], tmp_path) == (Path("r"), Path("p"), tmp_path)
    (tmp_path / "faust").mkdir()
    assert cal._set(["r", "p", str(tmp_path / "faust")], tmp_path)[2] == tmp_path / "faust"
    with pytest.raises(SystemExit, match="is not a folder"):
        cal._set(["r", "p", str(tmp_path / "nowhere")], tmp_path)
    with pytest.raises(SystemExit, match="RESULTS PARTS"):
        cal._set(["r"], tmp_path)
