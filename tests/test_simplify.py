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


def test_the_copy_is_cached_by_content_and_read_back_as_made(tmp_path):
    """A copy stored on disk and read back by another cache (as by another process) is the copy made afresh:
    the same mesh and the same places of the original's vertices on it."""
    from wpot.cache import Cache

    m = mirror_symmetric(1500, seed=11)
    made = simplify(m, 400, cache=Cache("simplified-test", cache_dir=tmp_path))
    assert len(list(tmp_path.rglob("*.npz"))) == 1
    back = simplify(Mesh(m.vertices, m.faces), 400, cache=Cache("simplified-test", cache_dir=tmp_path))
    fresh = simplify(m, 400, cache=False)
    for other in (back, fresh):
        assert other.coarse.fingerprint == made.coarse.fingerprint
        for name in ("corners", "weights", "nearest"):
            np.testing.assert_array_equal(getattr(other, name), getattr(made, name))
    assert len(list(tmp_path.rglob("*.npz"))) == 1  # read, not stored again
    with pytest.raises(TypeError, match="cache"):
        simplify(m, 400, cache="yes")


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


# ----------------------------------------------------------------------------- spectral signatures through the copy
def _wks(max_vertices: int, n_eigen: int = 40):
    from wpot.signatures import WKS
    from wpot.signatures._wks import WKSOptions

    return WKS(WKSOptions(n_eigen=n_eigen, n_energies=40, max_vertices=max_vertices), spectrum_cache=False)


def test_a_spectral_signature_of_a_large_mesh_is_its_copys_blended_to_every_vertex(big):
    """Above ``max_vertices`` the eigenvalues are the copy's, close to the mesh's own (the lowest frequencies
    survive decimation), and the WKS blended from the copy differs from the mesh's own WKS less than the WKS of
    another triangulation of the same surface at the mesh's own density does (the variation every comparison
    of two meshes already lives with)."""
    from scipy.spatial import cKDTree

    through, direct = _wks(1200), _wks(0)
    assert through.copy_of(big) is not None and direct.copy_of(big) is None
    ev_copy, ev_full = through.fit_input(big).evals, direct.fit_input(big).evals
    assert len(ev_copy) == len(ev_full) == 40
    np.testing.assert_allclose(ev_copy[1:], ev_full[1:], rtol=0.02)
    direct.fit([big])
    through.set_state({"energies": direct.energies})
    a, b = through(big), direct(big)
    assert a.shape == b.shape == (big.n_vertices, 40)
    other = mirror_symmetric(big.n_vertices, seed=11)  # the same surface, its own random triangulation
    c = direct(other)[cKDTree(other.vertices).query(big.vertices)[1]]
    assert np.linalg.norm(a - b) < 0.8 * np.linalg.norm(c - b)


def test_the_copy_is_made_once_and_a_small_mesh_is_seen_as_it_is(big):
    s = _wks(1200)
    assert s.copy_of(big) is s.copy_of(big) is simplify(big, 1200)  # the copy zoomout(max_vertices=1200) refines through
    renamed = Mesh(big.vertices, big.faces, name="renamed")
    assert simplify(renamed, 1200).full is renamed and simplify(renamed, 1200).coarse is s.copy_of(big).coarse
    small = mirror_symmetric(300, seed=1)
    assert s.copy_of(small) is None and s.spectral_mesh(small) is small
    import pickle

    assert pickle.loads(pickle.dumps(s)).copy_of(big).coarse.n_vertices == s.copy_of(big).coarse.n_vertices


def test_spectral_max_vertices_is_checked_and_kept_out_of_keys_at_its_default():
    from wpot.signatures import WKS
    from wpot.signatures._wks import WKSOptions
    from wpot.spectral import SPECTRAL_MAX_VERTICES

    with pytest.raises(ValueError, match=r"spectral_max_vertices must be 0 \(off\) or at least 1000, got 999"):
        WKSOptions(max_vertices=999)
    assert WKSOptions(n_eigen=40, max_vertices=1200).copy_vertices == 1200
    assert WKSOptions(n_eigen=800, max_vertices=1200).copy_vertices == 1600  # the copy resolves the eigenpairs
    assert WKSOptions(max_vertices=0).copy_vertices == 0 and not WKSOptions(max_vertices=0).copies(10**6)
    assert WKSOptions(n_eigen=40, max_vertices=1200).copies(1201) and not WKSOptions(n_eigen=40, max_vertices=1200).copies(1200)
    with pytest.raises(ValueError, match="spectral_max_vertices"):
        WKSOptions(max_vertices=-1)
    assert WKSOptions().max_vertices == SPECTRAL_MAX_VERTICES
    assert "max_vertices" not in WKS().params() and "spectral_max_vertices" not in WKS().run_key()
    assert WKS(WKSOptions(max_vertices=0)).run_key()["spectral_max_vertices"] == 0
