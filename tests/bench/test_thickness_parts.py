"""benchmarks/thickness_parts.py: parts cut as described, and agreement figures on cases whose answer is known."""
from __future__ import annotations

import argparse
import importlib

import numpy as np
import pytest


@pytest.fixture(scope="module")
def tp():
    return importlib.import_module("benchmarks.thickness_parts")


def test_a_ball_part_is_one_piece_of_the_whole_at_the_share_asked(tp):
    from wpot.examples import example_mesh
    from wpot.mesh import boundary_rings

    m = example_mesh(900)
    part, idx = tp.ball_part(m, np.random.default_rng(0), 0.3)
    assert part.n_components == 1
    assert 0.2 * m.n_vertices < part.n_vertices <= 0.3 * m.n_vertices + 1
    np.testing.assert_array_equal(part.vertices, m.vertices[idx])  # the index map is the ground truth
    rings = boundary_rings(part)  # what the benchmark compares at: a ball's cut is its boundary
    border = np.unique(part.boundary_edges.ravel())
    assert np.all(rings[border] == 0) and rings.max() >= 3


def test_agreement_counts_the_share_within_5_percent_and_skips_missing_values(tp):
    whole = np.ones(6)
    part = np.array([1.0, 1.04, 0.96, 1.2, np.nan, 0.5])
    got = tp.agreement(part, whole)
    assert got["n"] == 5 and got["within"] == pytest.approx(3 / 5)
    r = np.log([1.0, 1.04, 0.96, 1.2, 0.5])
    assert got["mean_abs_log"] == pytest.approx(np.abs(r).mean()) and got["median_log"] == pytest.approx(np.median(r))
    assert tp.agreement(np.array([np.nan]), np.ones(1))["n"] == 0


def test_the_report_pools_by_vertex(tp, tmp_path):
    from benchmarks.jsonl_store import JsonlStore

    store = JsonlStore(tmp_path, keys=("shape", "part"), folder="arrays")
    for k, (n, within) in enumerate(((100, 1.0), (300, 0.0))):
        ag = {"n": n, "within": within, "mean_abs_log": within, "median_log": -within}
        store.add({"method": "ball", "shape": "tosca:s", "part": f"0.15:{k}", "dataset": "tosca", "share": 0.15,
                   "far": n, "own": n // 2, "all": ag, "own_only": ag, "filled": ag, "capped": ag}, None)
    lines = []
    tp.report(store, argparse.Namespace(dataset=["tosca"], rings=5), lines.append)
    row = [line for line in lines if line.startswith("| tosca | 15% |")][0]
    # 100 vertices all within and 300 none: 25 % pooled by vertex (not 50 % by part); half of them measured
    assert "| 2 | 50.0% | 25.0%, 0.250, -0.500 |" in row
