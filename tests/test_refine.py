"""wpot.refine.zoomout: fixed point, vertex relabelling, a different triangulation with known truth, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import wpot
from wpot.mesh import Mesh
from wpot.refine import zoomout


def _noisy(truth: np.ndarray, n_b: int, fraction: float, seed: int) -> np.ndarray:
    """``truth`` with a ``fraction`` of its entries sent to random vertices of B."""
    rng = np.random.default_rng(seed)
    t = truth.copy()
    hit = rng.random(len(t)) < fraction
    t[hit] = rng.integers(0, n_b, hit.sum())
    return t


def test_exact_map_is_a_fixed_point():
    a = wpot.example_mesh(400, seed=1)
    ident = np.arange(a.n_vertices)
    np.testing.assert_array_equal(zoomout(a, a, ident, k_end=60), ident)
    small = wpot.example_mesh(60, seed=1)  # fewer vertices than the default k_end: it is clamped to 60
    np.testing.assert_array_equal(zoomout(small, small, np.arange(60)), np.arange(60))


def test_recovers_a_relabelled_rotated_copy_from_a_corrupted_map():
    a = wpot.example_mesh(600, seed=2)
    rng = np.random.default_rng(0)
    perm = rng.permutation(a.n_vertices)  # B's vertex j is A's vertex perm[j]
    inv = np.argsort(perm)
    rot = Rotation.random(random_state=3).as_matrix()
    b = Mesh(a.vertices[perm] @ rot.T + [1.0, -2.0, 0.5], inv[a.faces])
    truth = inv  # A's vertex i is B's vertex inv[i]
    start = _noisy(truth, b.n_vertices, 0.4, seed=4)
    out = zoomout(a, b, start, k_end=60)
    assert np.mean(start == truth) < 0.65
    assert np.mean(out == truth) > 0.97


def test_improves_a_corrupted_map_between_different_triangulations():
    pair = wpot.example_pair(700, seed=5)  # truth: target vertex -> source vertex
    tgt, src, truth = pair.target, pair.source, np.asarray(pair.correspondence)
    start = _noisy(truth, src.n_vertices, 0.4, seed=6)

    def mean_error(t):  # Euclidean, in the source frame, in mean edge lengths
        d = np.linalg.norm(pair.target_in_source_frame - src.vertices[t], axis=1)
        return d.mean() / src.one_ring_mean_edge_length.mean()

    e0, e1, e_truth = mean_error(start), mean_error(zoomout(tgt, src, start, k_end=60)), mean_error(truth)
    assert e1 < 0.1 * e0
    assert e1 < e_truth + 0.2  # the truth itself is a nearest vertex, about 0.34 edge lengths off


def test_bad_input():
    a = wpot.example_mesh(200, seed=0)
    ident = np.arange(a.n_vertices)
    with pytest.raises(ValueError, match=r"shape \(N_A,\) = \(200,\)"):
        zoomout(a, a, ident[:-1])
    bad = ident.copy()
    bad[7] = 200
    with pytest.raises(ValueError, match=r"correspondence\[7\] = 200"):
        zoomout(a, a, bad)
    with pytest.raises(ValueError, match="integers"):
        zoomout(a, a, ident + 0.5)
    with pytest.raises(ValueError, match="k_start must be <= k_end"):
        zoomout(a, a, ident, k_start=50, k_end=40)
    with pytest.raises(ValueError, match="k_end=300 exceeds the 200 eigenpairs"):
        zoomout(a, a, ident, k_end=300)
    with pytest.raises(ValueError, match="step must be a positive integer, got 0"):
        zoomout(a, a, ident, step=0)
    with pytest.raises(TypeError, match="mesh_b must be a wpot.Mesh"):
        zoomout(a, a.vertices, ident)
