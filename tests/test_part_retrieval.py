"""The scoring of benchmarks/part_retrieval.py (issue 23's class retrieval from a library of whole shapes):
top-1, the rank of the part's class, unfinished parts left out, and bad arguments refused by flag."""
from __future__ import annotations

import json

import pytest

from conftest import load_benchmark


@pytest.fixture(scope="module")
def pr():
    return load_benchmark("part_retrieval")


def test_top1_and_rank_of_the_class(pr):
    parts = {"cat0_limb-S": {"class": "cat", "kind": "limb", "fraction": 0.08},
             "dog2_head-L": {"class": "dog", "kind": "head", "fraction": 0.25},
             "wolf0_cut-L": {"class": "wolf", "kind": "cut", "fraction": 0.4}}
    d = {("cat0_limb-S", "dog3"): 0.5, ("cat0_limb-S", "cat2"): 0.7, ("cat0_limb-S", "cat4"): 0.9,
         ("dog2_head-L", "dog3"): 0.2, ("dog2_head-L", "cat2"): 0.7, ("dog2_head-L", "cat4"): 0.1,
         ("wolf0_cut-L", "wolf1"): 0.1, ("wolf0_cut-L", "cat2"): 0.7}  # wolf0_cut-L: one whole missing
    recs = [{"method": pr.method(1.0), "part": p, "whole": w, "distance": v} for (p, w), v in d.items()]
    recs.append({"method": pr.method(0.0), "part": "wolf0_cut-L", "whole": "cat4", "distance": 0.0})
    rows = pr.score(recs, parts, 1.0)
    assert set(rows) == {"cat0_limb-S", "dog2_head-L"}  # the unfinished part is not scored
    assert rows["cat0_limb-S"] == {"top1": False, "rank": 2, "taken_for": "dog3", "kind": "limb", "large": False}
    assert rows["dog2_head-L"]["top1"] is False and rows["dog2_head-L"]["rank"] == 2
    assert rows["dog2_head-L"]["taken_for"] == "cat4" and rows["dog2_head-L"]["large"]
    alone = pr.score(recs, parts, 0.0)["wolf0_cut-L"]  # another weight, scored apart; no wolf in its library
    assert alone["top1"] is False and alone["rank"] is None


@pytest.mark.parametrize("weights, says", [("1,x", "numbers separated by commas"), ("-1", "finite and >= 0")])
def test_bad_arguments_are_refused_by_flag(pr, tmp_path, weights, says):
    (tmp_path / "parts.jsonl").write_text(json.dumps({"part": "cat0_head-L", "class": "cat"}) + "\n")
    with pytest.raises(SystemExit, match=f"--weights .*{says}|--weights must be {says}"):
        pr.main(["--parts", str(tmp_path), "--out", str(tmp_path / "out"), "--weights", weights])
    with pytest.raises(SystemExit, match="--ldsift-slab must be a positive number"):
        pr.main(["--parts", str(tmp_path), "--out", str(tmp_path / "out"), "--ldsift-slab", "0"])
    with pytest.raises(SystemExit, match="--parts .*no parts.jsonl"):
        pr.main(["--parts", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
