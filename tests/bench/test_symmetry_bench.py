"""benchmarks/symmetry.py: the mirror's error and the report, on cases whose answer is known."""
from __future__ import annotations

import argparse
import importlib

import numpy as np
import pytest

from helpers import mirror_symmetric


@pytest.fixture(scope="module")
def sb():
    return importlib.import_module("benchmarks.symmetry")


def test_the_error_is_zero_for_the_truth_and_the_mirror_distance_for_the_identity(sb):
    m = mirror_symmetric()
    pts = np.arange(m.n_vertices)
    mirrored = m.vertices * np.array([-1.0, 1.0, 1.0])
    mirrors = np.argmin(np.linalg.norm(mirrored[:, None] - m.vertices[None], axis=2), axis=1)
    assert sb.mirror_error(m, mirrors, pts, mirrors) == 0.0
    want = np.linalg.norm(m.vertices - m.vertices[mirrors], axis=1).mean() / np.sqrt(m.area)
    assert sb.mirror_error(m, pts, pts, mirrors) == pytest.approx(want) and want > 0.1


def test_the_report_counts_found_shapes_and_compares_only_those_both_find(sb, tmp_path):
    from benchmarks.jsonl_store import JsonlStore

    a = argparse.Namespace(dataset=["faust"], oriented_k=50)
    test, peer = sb.variants(a)
    store = JsonlStore(tmp_path, keys=("dataset", "shape"), folder="arrays")
    rows = {"s1": ((0.020, 0.030), 1.0), "s2": ((0.025, None), 2.0), "s3": ((0.040, 0.030), 3.0)}
    for shape, ((e_test, e_peer), sec) in rows.items():
        for method, e in ((test, e_test), (peer, e_peer)):
            rec = {"method": method, "dataset": "faust", "shape": shape, "seconds": sec, "found": e is not None}
            store.add(rec if e is None else {**rec, "error": e, "score": -0.9, "residual": 0.05}, None)
    lines = []
    sb.report(store, a, lines.append)
    row = [line for line in lines if line.startswith("| faust_5k |")][0]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "3"
    assert cells[2] == "3 of 3, 0.0283 (0.040), 2.0 s" and cells[3] == "2 of 3, 0.0300 (0.030), 2.0 s"
    # s1 and s3 found by both: 0.030 / 0.030; s1 better by 0.010, s3 worse by 0.010
    assert cells[4] == "2: 0.0300 / 0.0300, 1 / 1"
