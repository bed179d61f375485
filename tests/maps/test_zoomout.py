"""wpot.maps.zoomout.zoomout: fixed point, vertex relabelling, a different triangulation with known truth, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import wpot
from wpot.mesh import Mesh
from wpot.maps.zoomout import zoomout


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


@pytest.mark.parametrize("samples", [None, 250])  # every vertex in every round; 250 of 600 before the last
def test_recovers_a_relabelled_rotated_copy_from_a_corrupted_map(samples):
    a = wpot.example_mesh(600, seed=2)
    rng = np.random.default_rng(0)
    perm = rng.permutation(a.n_vertices)  # B's vertex j is A's vertex perm[j]
    inv = np.argsort(perm)
    rot = Rotation.random(random_state=3).as_matrix()
    b = Mesh(a.vertices[perm] @ rot.T + [1.0, -2.0, 0.5], inv[a.faces])
    truth = inv  # A's vertex i is B's vertex inv[i]
    start = _noisy(truth, b.n_vertices, 0.4, seed=4)
    out = zoomout(a, b, start, k_end=60, samples=samples).map
    assert np.mean(start == truth) < 0.65
    assert np.mean(out == truth) > 0.97


def test_improves_a_corrupted_map_between_different_triangulations():
    pair = wpot.example_pair(700, seed=5)  # truth: target vertex -> source vertex
    tgt, src, truth = pair.target, pair.source, np.asarray(pair.correspondence)
    start = _noisy(truth, src.n_vertices, 0.4, seed=6)

    def mean_error(t):  # Euclidean, in the source frame, in mean edge lengths
        d = np.linalg.norm(pair.target_in_source_frame - src.vertices[t], axis=1)
        return d.mean() / src.one_ring_mean_edge_length.mean()

    e0, e1, e_truth = mean_error(start), mean_error(zoomout(tgt, src, start, k_end=60).map), mean_error(truth)
    assert e1 < 0.1 * e0
    assert e1 < e_truth + 0.2  # the truth itself is a nearest vertex, about 0.34 edge lengths off
    # every vertex in every round against 400 of the 805 before the last: sampling costs under 5 %
    assert mean_error(zoomout(tgt, src, start, k_end=60, samples=400).map) < 1.05 * e1


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
    with pytest.raises(ValueError, match="k_end=300 exceeds the 100 eigenpairs"):
        zoomout(a, a, ident, k_end=300)
    with pytest.raises(ValueError, match="step must be a positive integer, got 0"):
        zoomout(a, a, ident, step=0)
    with pytest.raises(TypeError, match="mesh_b must be a wpot.Mesh"):
        zoomout(a, a.vertices, ident)


def test_cached_eigenpairs_reads_without_computing(tmp_path):
    from wpot.cache import Cache
    from wpot.spectral import cached_eigenpairs, eigenpairs

    m = wpot.example_mesh(150, seed=3)
    c = Cache("refine-test", cache_dir=tmp_path)
    assert cached_eigenpairs(m, 40, cache=c) is None
    s = eigenpairs(m, 40, cache=c)
    back = cached_eigenpairs(m, 40, cache=c)
    assert back is not None and back.from_cache
    np.testing.assert_array_equal(back.evecs, s.evecs)
    assert cached_eigenpairs(m, 41, cache=c) is None  # another k is another entry
    assert cached_eigenpairs(m, 40, cache=False) is None


def test_zoomout_uses_its_own_spectrum_size_whatever_is_cached(monkeypatch):
    """ZoomOut (and the WKS descriptors of its oriented candidate) read `spectrum_size` eigenpairs per
    mesh, computed once and then read from the cache; what else is cached, such as the smaller spectrum of a
    WKS comparison with fewer eigenpairs, changes neither what it computes nor its result."""
    from wpot import spectral

    a = wpot.example_mesh(300, seed=7)
    b = wpot.example_mesh(320, seed=8)
    asked: list[int] = []
    real = spectral.LaplaceBeltrami.eigenpairs

    def spy(self, k, **kw):
        asked.append(k)
        return real(self, k, **kw)

    monkeypatch.setattr(spectral.LaplaceBeltrami, "eigenpairs", spy)
    monkeypatch.delenv("WPOT_CACHE_DIR", raising=False)  # memory only, emptied
    spectral.spectrum_cache.clear()
    start = np.random.default_rng(0).integers(0, b.n_vertices, a.n_vertices)
    first = zoomout(a, b, start, k_end=30)
    assert sorted(set(asked)) == [100]  # spectrum_size: a tenth of the vertices, at least 100
    asked.clear()
    for k in (40, 300):  # what WKS comparisons with n_eigen=40 and n_eigen >= 300 cache
        spectral.eigenpairs(a, k)
        spectral.eigenpairs(b, k)
    asked.clear()
    np.testing.assert_array_equal(zoomout(a, b, start, k_end=30), first)
    assert asked == []  # its own spectra come from the cache
    spectral.spectrum_cache.clear()
    np.testing.assert_array_equal(zoomout(a, b, start, k_end=30), first)  # and computed again, the same


def _disjoint(parts: list[Mesh], spacing: float = 3.0) -> Mesh:
    """The parts side by side (offset along x), as one mesh with one connected component per part."""
    vs, fs, off = [], [], 0
    for i, m in enumerate(parts):
        vs.append(m.vertices + [spacing * i, 0.0, 0.0])
        fs.append(m.faces + off)
        off += m.n_vertices
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MeshWarning: several components, which is the point here
        return Mesh(np.vstack(vs), np.vstack(fs))


def _relabelled(a: Mesh, seed: int) -> tuple[Mesh, np.ndarray]:
    """A relabelled copy B of ``a`` and the truth (A's vertex i is B's vertex truth[i])."""
    perm = np.random.default_rng(seed).permutation(a.n_vertices)
    inv = np.argsort(perm)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Mesh(a.vertices[perm], inv[a.faces]), inv


@pytest.mark.filterwarnings("ignore::wpot.spectral.SpectralWarning")
def test_a_mesh_of_many_components_is_recovered_like_a_connected_one():
    # a scan-like mesh: one body and 11 small islands (12 zero eigenvalues, above the default k_start of 10).
    # Before, every island's vertices collapsed (no non-constant eigenfunction of the whole mesh reached them by
    # k_end; with an 800-vertex body, 60 % of the vertices were right after ZoomOut from a 70 % start).
    parts = [wpot.example_mesh(300, seed=0)] + [
        Mesh(wpot.example_mesh(50, seed=i).vertices * 0.15, wpot.example_mesh(50, seed=i).faces) for i in range(1, 12)]
    a = _disjoint(parts)
    assert a.n_components == 12
    b, truth = _relabelled(a, 0)
    start = _noisy(truth, b.n_vertices, 0.3, seed=1)
    out = zoomout(a, b, start).map
    assert np.mean(start == truth) < 0.75
    assert np.mean(out == truth) > 0.97
    assert np.unique(out).size > 0.97 * a.n_vertices  # distinct targets, no collapse
    # the same refinement as the connected body alone gets on its own vertices
    body, body_truth = _relabelled(parts[0], 0)
    alone = zoomout(parts[0], body, _noisy(body_truth, body.n_vertices, 0.3, seed=1)).map
    assert np.mean(out[:300] == truth[:300]) >= np.mean(alone == body_truth) - 0.02


@pytest.mark.filterwarnings("ignore::wpot.spectral.SpectralWarning")
def test_two_components_map_onto_a_relabelled_copy():
    a = _disjoint([wpot.example_mesh(200, seed=3), wpot.example_mesh(150, seed=4)])
    b, truth = _relabelled(a, 2)
    out = zoomout(a, b, _noisy(truth, b.n_vertices, 0.4, seed=5), k_end=60).map
    assert np.mean(out == truth) > 0.97
    # a component's vertices stay in the component most of them were mapped to
    lb = b.component_labels
    assert np.all(lb[out] == lb[truth])


@pytest.mark.filterwarnings("ignore::wpot.spectral.SpectralWarning")
def test_components_read_their_own_spectrum_size():
    # 1,500 + 120 vertices: the whole mesh's spectrum_size (162) exceeds the body's own (150), which is what
    # each component's ZoomOut reads; the default k_end must follow the component's
    from wpot.maps.zoomout import spectrum_size

    a = _disjoint([wpot.example_mesh(1500, seed=6), wpot.example_mesh(120, seed=7)])
    assert spectrum_size(a.n_vertices) > spectrum_size(1500)
    b, truth = _relabelled(a, 4)
    out = zoomout(a, b, _noisy(truth, b.n_vertices, 0.3, seed=8), orient=False).map
    assert np.mean(out == truth) > 0.97
