"""benchmarks/ldsift_support.py: the recall of LD-SIFT's candidates, on cases whose answer is known."""
from __future__ import annotations

import argparse
import importlib

import numpy as np
import pytest


@pytest.fixture(scope="module")
def ls():
    return importlib.import_module("benchmarks.ldsift_support")


def test_a_shape_against_itself_finds_every_query(ls):
    """The re-meshing is the target itself and the template the identity: every query's own vertex has its exact
    signature (cost 0), so recall@1, recall@n and either-side recall are all 1."""
    from wpot.examples import example_mesh

    m = example_mesh(700)
    ident = np.arange(m.n_vertices)
    a = argparse.Namespace(candidates=3, radius=1e-6, device="cpu")
    sig = ls.signatures(ls.ldsift(3.0, m), m)
    rec = ls.recall(sig, sig, *ls.queries_on(m, m, ident, ident, ident, m, 40), m, a)
    assert rec["recall1"] == rec["recall"] == rec["either"] == 1.0


def test_the_mirror_counts_only_as_either(ls):
    """A truth sent elsewhere (every query's truth moved to a far vertex) and a mirror that is the identity: nothing
    is recalled, but every query is found on the mirror side."""
    from wpot.examples import example_mesh

    m = example_mesh(700)
    ident = np.arange(m.n_vertices)
    far = np.argmax(np.linalg.norm(m.vertices[:, None] - m.vertices[None], axis=2), axis=1)
    a = argparse.Namespace(candidates=1, radius=1e-6, device="cpu")
    sig = ls.signatures(ls.ldsift(3.0, m), m)
    rec = ls.recall(sig, sig, *ls.queries_on(m, m, ident, far, ident, m, 40), m, a)
    assert rec["recall"] == rec["recall1"] == 0.0 and rec["either"] == 1.0


def test_the_report_gives_the_largest_gap_to_the_control(ls, tmp_path):
    from benchmarks.jsonl_store import JsonlStore

    store = JsonlStore(tmp_path, keys=("pair", "density"), folder="arrays")
    for pair, recalls in (("p1", {0.5: 0.2, 1.0: 0.5, 2.0: 0.6}), ("p2", {0.5: 0.4, 1.0: 0.5, 2.0: 0.4})):
        for F, r in recalls.items():
            store.add({"method": "K3", "pair": f"tosca:{pair}", "density": f"F{F:g}", "dataset": "tosca", "K": 3.0,
                       "F": F, "recall": r, "either": r, "recall1": r / 2}, None)  # stored before the orientation
            store.add({"method": "K3-gradient", "pair": f"tosca:{pair}", "density": f"F{F:g}", "dataset": "tosca",
                       "K": 3.0, "orientation": "gradient", "F": F, "recall": 0.7, "either": 0.8, "recall1": 0.4}, None)
    lines = []
    ls.report(store, argparse.Namespace(dataset=["tosca"], candidates=10), lines.append)
    row = [line for line in lines if line.startswith("| 3 | frame |")][0]
    # means 0.3 / 0.5 / 0.5: the largest gap to 1x is 0.2 (at 0.5x)
    assert "0.300 (0.300) / 0.150, 2 pairs" in row and row.rstrip().endswith("| 0.200 |")
    beside = [line for line in lines if line.startswith("| 3 | gradient |")][0]  # the other orientation, its own row
    assert beside.count("0.700 (0.800) / 0.400, 2 pairs") == 3 and beside.rstrip().endswith("| 0.000 |")
