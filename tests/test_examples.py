"""Generated example shapes: valid closed surfaces, different triangulations, exact ground truth."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial import cKDTree

from wpot.examples import example_mesh, example_pair, example_partial
from wpot.mesh import Mesh


@pytest.fixture(scope="module")
def pair():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # generated shapes must be defect-free
        return example_pair(600, seed=1)


def _closed_genus0(m: Mesh) -> None:
    assert m.n_components == 1
    assert len(m.boundary_edges) == 0 and len(m.nonmanifold_edges) == 0
    assert m.n_vertices - len(m.edges) + m.n_faces == 2
    assert m.degenerate_faces.size == 0 and m.unreferenced_vertices.size == 0


def test_pair_meshes_are_closed_outward_surfaces(pair):
    for m in (pair.source, Mesh(pair.target_in_source_frame, pair.target.faces)):
        _closed_genus0(m)
        # star-shaped about the origin, so every outward face normal has a positive radial component
        centroids = m.vertices[m.faces].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", m.face_normals, centroids) > 0)


def test_pair_has_different_triangulations_of_the_same_surface(pair):
    s, t = pair.source, pair.target
    assert s.n_vertices == 600 and t.n_vertices == round(1.15 * 600)
    # same surface: areas agree to discretisation error, and every target vertex lies near the source
    assert t.area == pytest.approx(s.area, rel=0.02)
    d, _ = cKDTree(s.vertices).query(pair.target_in_source_frame)
    assert d.max() < 2 * s.mean_edge_length
    # but not the same sampling: few target points coincide with source points
    assert np.mean(d < 1e-3 * s.mean_edge_length) < 0.01


def test_pair_rigid_motion_and_ground_truth(pair):
    r, t = pair.rotation, pair.translation
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    assert np.allclose(pair.target.vertices, pair.target_in_source_frame @ r.T + t)
    # the correspondence is the nearest source vertex (brute force check)
    x = pair.target_in_source_frame
    d2 = ((x[:, None, :] - pair.source.vertices[None, :, :]) ** 2).sum(-1)
    assert np.array_equal(pair.correspondence, d2.argmin(axis=1))
    assert pair.correspondence.dtype == np.int64 and pair.correspondence.shape == (pair.target.n_vertices,)
    for a in (pair.rotation, pair.translation, pair.correspondence, pair.target_in_source_frame):
        assert not a.flags.writeable


def test_shape_has_no_mirror_symmetry(pair):
    """Mirror images across the coordinate and principal planes through the centroid do not fit the shape.

    (A symmetric shape would map onto itself: every mirrored vertex within about an edge length of a
    vertex. Here some land more than 6% of the bounding-box diagonal away, i.e. several edge lengths.)
    """
    m = pair.source
    v = m.vertices
    c = v.mean(axis=0)
    tree = cKDTree(v)
    _, principal = np.linalg.eigh(np.cov((v - c).T))
    for a in np.vstack([np.eye(3), principal.T]):
        mirrored = v - 2 * np.outer((v - c) @ a, a)
        d, _ = tree.query(mirrored)
        assert d.max() > 0.06 * m.bounding_box_diagonal > 1.2 * m.mean_edge_length


def test_deterministic_and_seed_dependent():
    a, b = example_pair(200, seed=5), example_pair(200, seed=5)
    assert a.source == b.source and a.target == b.target
    assert np.array_equal(a.correspondence, b.correspondence)
    c = example_pair(200, seed=6)
    assert c.source == a.source and c.target != a.target
    assert example_mesh(200) == a.source
    assert example_mesh(200, seed=1) != example_mesh(200, seed=2)


def test_partial_is_a_cut_of_the_target_with_index_map():
    p = example_partial(400, seed=2, fraction=0.4)
    pair = example_pair(400, seed=2)
    assert p.full == pair.source and p.target == pair.target
    assert np.array_equal(p.part.vertices, p.target.vertices[p.index_map])
    assert np.array_equal(p.correspondence, pair.correspondence[p.index_map])
    # one disc: a single component with one boundary loop (V - E + F = 1)
    assert p.part.n_components == 1
    assert p.part.n_vertices - len(p.part.edges) + p.part.n_faces == 1
    assert len(p.part.boundary_edges) > 0
    assert abs(p.part.n_vertices / p.target.n_vertices - 0.4) < 0.05
    assert p.part.area < 0.6 * p.target.area
    # the part keeps the target's rigid motion: undoing it puts it on the source surface
    back = (p.part.vertices - p.translation) @ p.rotation
    d, _ = cKDTree(p.full.vertices).query(back)
    assert d.max() < 2 * p.full.mean_edge_length


@pytest.mark.parametrize(
    "call, pattern",
    [
        (lambda: example_pair(10), "n must be an integer >= 50, got 10"),
        (lambda: example_mesh(100.5), "n must be an integer"),
        (lambda: example_partial(200, fraction=0.0), r"fraction must be in \(0, 1\], got 0.0"),
        (lambda: example_partial(200, direction=(0, 0, 0)), "direction must be a nonzero"),
    ],
)
def test_bad_arguments(call, pattern):
    with pytest.raises(ValueError, match=pattern):
        call()
