"""Simplified copies of large meshes (`wpot.simplify`) and `wpot.zoomout` through them (``max_vertices``)."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import mirror_symmetric
from wpot.maps.zoomout import zoomout
from wpot.mesh import Mesh
from wpot.simplify import lift_map, simplify


@pytest.fixture(scope="module")
def big():
    return mirror_symmetric(2400, seed=3)


@pytest.fixture(scope="module")
def copy(big):
    return simplify(big, 600, device="cpu")


def test_a_small_mesh_is_its_own_copy_and_every_map_is_kept():
    m = mirror_symmetric(300, seed=1)
    s = simplify(m, 300)
    assert not s.simplified and s.coarse is m
    t = np.random.default_rng(0).integers(0, m.n_vertices, m.n_vertices)
    np.testing.assert_array_equal(s.restrict_map(s, t), t)
    np.testing.assert_array_equal(lift_map(s, s, t), t)
    np.testing.assert_allclose(s.interpolate(m.vertices), m.vertices)


def test_the_copy_has_the_size_asked_and_places_every_vertex_on_itself(big, copy):
    """About n vertices, one closed surface; each original vertex lies on its triangle of the copy: the
    barycentric blend of the corners is its closest point, within a fraction of the copy's edge length."""
    c = copy.coarse
    assert copy.simplified and abs(c.n_vertices - 600) <= 6 and c.n_components == 1
    assert c.misoriented_faces.size == 0 and c.degenerate_faces.size == 0
    np.testing.assert_allclose(copy.weights.sum(axis=1), 1.0, atol=1e-6)
    assert copy.weights.min() >= 0
    gap = np.linalg.norm(copy.interpolate(c.vertices) - big.vertices, axis=1)
    assert gap.max() < 0.5 * c.mean_edge_length and np.median(gap) < 0.1 * c.mean_edge_length
    # each vertex of the copy has an original vertex within an original edge or so
    d = np.linalg.norm(big.vertices[copy.nearest] - c.vertices, axis=1)
    assert d.max() < 2.0 * big.mean_edge_length


def test_the_identity_survives_the_round_trip_through_the_copies(big, copy):
    """restrict_map then lift_map of the identity: every original vertex back on itself or a neighbour."""
    ident = np.arange(big.n_vertices)
    coarse = copy.restrict_map(copy, ident)
    near = np.linalg.norm(copy.coarse.vertices[coarse] - copy.coarse.vertices, axis=1)
    assert np.mean(coarse == np.arange(copy.coarse.n_vertices)) > 0.95 and near.max() < 1.5 * copy.coarse.mean_edge_length
    back = lift_map(copy, copy, coarse)
    moved = np.linalg.norm(big.vertices[back] - big.vertices, axis=1)
    assert np.mean(back == ident) > 0.8 and moved.max() < 2.0 * copy.coarse.mean_edge_length


def test_a_seam_takes_the_heaviest_corner_not_a_blend_between_two_places(big, copy):
    """Corners of one triangle sent to two far places: the lifted image is one of those places, never the
    point half-way between them (which lies in neither)."""
    c = copy.coarse
    far = int(np.argmax(np.linalg.norm(c.vertices - c.vertices[0], axis=1)))
    t = np.where(c.vertices[:, 0] > 0, 0, far)  # the copy split in two halves, each sent to one vertex
    out = big.vertices[lift_map(copy, copy, t)]
    d = np.minimum(np.linalg.norm(out - c.vertices[0], axis=1), np.linalg.norm(out - c.vertices[far], axis=1))
    assert d.max() < 1e-9 + 2.0 * big.mean_edge_length


def test_zoomout_through_copies_recovers_a_relabelled_copy(big):
    """A large mesh against a relabelled copy of itself from a 40 % corrupted map: refined on copies of 600
    vertices and carried back, the map lands within about an edge of the truth, as without copies."""
    perm = np.random.default_rng(7).permutation(big.n_vertices)
    inv = np.argsort(perm)
    b = Mesh(big.vertices[perm], inv[big.faces])
    rng = np.random.default_rng(8)
    start = np.where(rng.random(big.n_vertices) < 0.4, rng.integers(0, b.n_vertices, big.n_vertices), inv)
    res = zoomout(big, b, start, k_end=40, max_vertices=600)
    assert res.coarse_vertices is not None and max(res.coarse_vertices) <= 606
    err = np.linalg.norm(b.vertices[res.map] - big.vertices, axis=1) / np.sqrt(big.area)
    assert np.mean(err) < 0.02 and np.mean(start != inv) > 0.35
    assert zoomout(big, b, start, k_end=40, max_vertices=big.n_vertices).coarse_vertices is None


def test_bad_sizes_are_named(big):
    with pytest.raises(ValueError, match="n_vertices"):
        simplify(big, 10)
    with pytest.raises(ValueError, match="max_vertices"):
        zoomout(big, big, np.arange(big.n_vertices), max_vertices=10)
    with pytest.raises(TypeError, match="wpot.Mesh"):
        simplify(big.vertices, 600)
    s = simplify(big, 600)
    with pytest.raises(ValueError, match="coarse_map"):
        lift_map(s, s, np.zeros(5, dtype=int))
    with pytest.raises(ValueError, match="vertex_map"):
        s.restrict_map(s, np.zeros(5, dtype=int))
