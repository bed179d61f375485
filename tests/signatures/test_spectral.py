"""Laplace–Beltrami operator and eigenpairs: hand checks, matrix properties, closed-form spectra."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from wpot.cache import Cache
from wpot.mesh import Mesh, MeshWarning
from wpot.spectral import (
    LaplaceBeltrami,
    SpectralWarning,
    Spectrum,
    cached_eigenpairs,
    choose_solver,
    eigenpairs,
    laplace_beltrami,
)


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> Mesh:
    t = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(t.vertices, t.faces)


def grid_square(n: int) -> Mesh:
    """Unit square [0,1]², n×n vertices, alternating diagonals (a mesh with boundary)."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            faces += [[a, b, c], [a, c, d]] if (i + j) % 2 == 0 else [[a, b, d], [b, c, d]]
    return Mesh(v, np.array(faces))


# ------------------------------------------------------------------------------ hand checks
def test_right_triangle_by_hand():
    # angles: 90° at v0, 45° at v1 and v2. w_ij = (cot of the angle opposite edge ij) / 2 (boundary).
    m = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    W, M = laplace_beltrami(m)
    w01 = w02 = 0.5 * 1.0  # opposite 45° angles
    w12 = 0.5 * 0.0  # opposite the right angle
    expected = np.array(
        [[w01 + w02, -w01, -w02], [-w01, w01 + w12, -w12], [-w02, -w12, w02 + w12]]
    )
    np.testing.assert_allclose(W.toarray(), expected, atol=1e-15)
    # Voronoi areas (circumcentre = midpoint of the hypotenuse): 1/4 at the right angle, 1/8 at the others
    np.testing.assert_allclose(M.diagonal(), [0.25, 0.125, 0.125], atol=1e-15)


def test_rhombus_of_two_equilateral_triangles_by_hand():
    h = np.sqrt(3) / 2
    m = Mesh([[0, 0, 0], [1, 0, 0], [0.5, h, 0], [0.5, -h, 0]], [[0, 1, 2], [1, 0, 3]])
    W, M = laplace_beltrami(m)
    c60 = 1 / np.sqrt(3)
    # interior edge (0,1): two opposite 60° angles; boundary edges: one
    assert W[0, 1] == pytest.approx(-(c60 + c60) / 2, abs=1e-15)
    for i, j in [(0, 2), (1, 2), (0, 3), (1, 3)]:
        assert W[i, j] == pytest.approx(-c60 / 2, abs=1e-15)
    assert W[2, 3] == 0
    # equilateral triangles: each vertex gets a third of each incident triangle
    tri = np.sqrt(3) / 4
    np.testing.assert_allclose(M.diagonal(), [2 * tri / 3, 2 * tri / 3, tri / 3, tri / 3], atol=1e-15)


def test_obtuse_triangle_mixed_area():
    # obtuse angle at v0: mixed Voronoi areas give area/2 there and area/4 at the other two (Meyer et al.)
    m = Mesh([[0, 0, 0], [2, 0, 0], [-1, 0.5, 0]], [[0, 1, 2]])
    _, M = laplace_beltrami(m)
    a = m.area
    np.testing.assert_allclose(M.diagonal(), [a / 2, a / 4, a / 4], rtol=1e-12)


# ------------------------------------------------------------------------------ matrix properties
@pytest.mark.parametrize("which", ["sphere", "square_with_boundary"])
def test_laplacian_properties(which):
    m = icosphere(2) if which == "sphere" else grid_square(9)
    W, M = laplace_beltrami(m)
    assert sp.issparse(W) and sp.issparse(M)
    Wd = W.toarray()
    np.testing.assert_allclose(Wd, Wd.T, atol=1e-14)  # symmetric
    np.testing.assert_allclose(Wd.sum(axis=1), 0, atol=1e-12)  # rows sum to zero
    ev = np.linalg.eigvalsh(Wd)
    assert ev.min() > -1e-10 * ev.max()  # PSD: W is the stiffness (= -igl.cotmatrix)
    assert np.all(np.diag(Wd) > 0)
    assert M.diagonal().sum() == pytest.approx(m.area, rel=1e-12)  # total mass = surface area
    assert np.count_nonzero(M.toarray() - np.diag(M.diagonal())) == 0  # lumped (diagonal)
    if which == "square_with_boundary":
        assert len(m.boundary_edges) > 0


def test_neumann_spectrum_of_unit_square():
    # Neumann eigenvalues of [0,1]²: π²(a² + b²) → 0, π², π², 2π², 4π², 4π², 5π², 5π²
    m = grid_square(31)
    s = eigenpairs(m, k=8, solver="lanczos", cache=False)
    expected = np.pi**2 * np.array([0, 1, 1, 2, 4, 4, 5, 5])
    assert abs(s.evals[0]) < 1e-8
    np.testing.assert_allclose(s.evals[1:], expected[1:], rtol=0.02)


# ------------------------------------------------------------------------------ eigenpairs
def test_sphere_eigenvalues_and_multiplicities():
    radius = 3.0  # arbitrary: the spectrum is computed on the area-normalized mesh
    # area 1 <=> R² = 1/(4π); λ_l = l(l+1)/R² with multiplicity 2l+1 (l = 0..4: 1+3+5+7+9 = 25)
    ls = np.repeat(np.arange(5), 2 * np.arange(5) + 1)
    expected = ls * (ls + 1) * 4 * np.pi
    errors = []
    for sub in (2, 3):
        m = icosphere(sub, radius=radius)
        s = eigenpairs(m, k=25, cache=False)
        assert abs(s.evals[0]) < 1e-8 and s.n_zero == 1
        assert s.area == pytest.approx(m.area)
        errors.append(np.abs(s.evals[1:] / expected[1:] - 1).max())
        # clusters: the spread inside an l-block is far below the gap to the next block
        for l in range(1, 4):
            block, nxt = s.evals[ls == l], s.evals[ls == l + 1]
            assert block.max() - block.min() < 0.1 * (nxt.min() - block.max())
    assert errors[1] < 0.04  # 642 vertices: within 4% up to l = 4
    assert errors[1] < 0.4 * errors[0]  # and converging under refinement (O(h²): ~1/4 per subdivision)


def test_rescaled_is_the_spectrum_of_the_mesh_at_its_own_size():
    radius = 3.0
    m = icosphere(3, radius=radius)
    s = eigenpairs(m, k=10, cache=False)
    raw = s.rescaled(normalized=False)
    assert not raw.normalized and raw.rescaled(normalized=False) is raw
    # the sphere of radius R: λ_l = l(l+1)/R², whatever the area
    ls = np.repeat(np.arange(3), 2 * np.arange(3) + 1)[1:]
    np.testing.assert_allclose(raw.evals[1:9], ls * (ls + 1) / radius**2, rtol=0.01)
    # eigenpairs of W φ = λ M φ with the un-normalized mass, M-orthonormal
    W, M = laplace_beltrami(m)
    np.testing.assert_allclose(W @ raw.evecs, (M @ raw.evecs) * raw.evals, atol=1e-8 * radius)
    np.testing.assert_allclose(raw.evecs.T @ (M @ raw.evecs), np.eye(10), atol=1e-9)
    back = raw.rescaled(normalized=True)
    assert back.normalized
    np.testing.assert_allclose(back.evals, s.evals, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(back.evecs, s.evecs, rtol=1e-13, atol=1e-13)


def test_dense_and_lanczos_agree_and_are_m_orthonormal():
    m = icosphere(3)
    lb = LaplaceBeltrami(m)
    d = lb.eigenpairs(30, solver="dense")
    z = lb.eigenpairs(30, solver="lanczos")
    assert (d.solver, z.solver) == ("dense", "lanczos")
    np.testing.assert_allclose(z.evals[1:], d.evals[1:], rtol=1e-9)
    for s in (d, z):
        gram = s.evecs.T @ (lb.mass[:, None] * s.evecs)
        np.testing.assert_allclose(gram, np.eye(30), atol=1e-9)
        # W φ = λ M φ
        res = lb.W @ s.evecs - (lb.mass[:, None] * s.evecs) * s.evals[None, :]
        assert np.abs(res).max() < 1e-8 * s.evals.max()
    assert lb.mass.sum() == pytest.approx(1.0)
    # the factorization is built once per shift and reused
    lu = lb.factorization()
    lb.eigenpairs(10, solver="lanczos")
    assert lb.factorization() is lu


def test_sliced_agrees_with_dense_on_degenerate_clusters():
    # the sphere's eigenvalues come in clusters of 2l + 1: a cut between two runs inside a cluster would give
    # vectors that are not orthogonal. 8 runs of 16 pairs for 100 eigenpairs (l = 0..9)
    m = icosphere(3)
    lb = LaplaceBeltrami(m)
    d = lb.eigenpairs(100, solver="dense")
    s = lb.eigenpairs(100, solver="sliced", per_slice=16)
    assert s.solver == "sliced"
    np.testing.assert_allclose(s.evals[1:], d.evals[1:], rtol=1e-9)
    gram = s.evecs.T @ (lb.mass[:, None] * s.evecs)
    np.testing.assert_allclose(gram, np.eye(100), atol=1e-9)
    res = lb.W @ s.evecs - (lb.mass[:, None] * s.evecs) * s.evals[None, :]
    assert np.abs(res).max() < 1e-8 * s.evals.max()
    ls = np.repeat(np.arange(10), 2 * np.arange(10) + 1)
    for l in range(10):  # each cluster spans the same space as dense's
        a, b = d.evecs[:, ls == l], s.evecs[:, ls == l]
        cos = np.linalg.svd(a.T @ (lb.mass[:, None] * b), compute_uv=False)
        assert cos.min() > 1 - 1e-8
    with pytest.raises(ValueError, match="per_slice"):
        lb.eigenpairs(100, solver="sliced", per_slice=1)


def test_sliced_defaults_agree_with_scipy_eigsh(monkeypatch):
    # the "auto" path for k > LANCZOS_MAX_PAIRS: runs of SLICE_PAIRS pairs; eigenvalues, M-orthonormality and the
    # WKS they feed must match one scipy eigsh run at machine precision. A perturbed sphere (no exact clusters)
    import scipy.sparse.linalg as sla

    import wpot.spectral as spectral
    from wpot.signatures._wks import wks_energies, wks_from_eigenpairs

    m0 = icosphere(3)
    rng = np.random.default_rng(3)
    m = Mesh(m0.vertices * (1 + 0.05 * rng.standard_normal((m0.n_vertices, 1))), m0.faces)
    lb = LaplaceBeltrami(m)
    k = 3 * spectral.SLICE_PAIRS
    runs = []
    eigsh = sla.eigsh

    def spy(*args, **kwargs):
        runs.append(kwargs["k"])
        return eigsh(*args, **kwargs)

    with monkeypatch.context() as mp:
        mp.setattr(spectral.sla, "eigsh", spy)
        s = lb.eigenpairs(k, solver="sliced")
    assert len(runs) >= 4 and set(runs) == {spectral.SLICE_PAIRS}  # several runs, each of the default size
    w, v = sla.eigsh(lb.W, k=k + 10, M=lb.M.tocsr(), sigma=spectral.DEFAULT_SHIFT, which="LM", tol=0,
                     v0=np.random.default_rng(0).standard_normal(lb.n_vertices))
    order = np.argsort(w)[:k]
    w, v = w[order], v[:, order]
    np.testing.assert_allclose(s.evals[1:], w[1:], rtol=1e-10)
    gram = s.evecs.T @ (lb.mass[:, None] * s.evecs)
    np.testing.assert_allclose(gram, np.eye(k), atol=1e-9)
    grid = wks_energies(s, n_energies=100, scale_invariant=True)
    ours = wks_from_eigenpairs(s.evals[1:], s.evecs[:, 1:], grid.energies, grid.sigma)
    ref = wks_from_eigenpairs(w[1:], v[:, 1:], grid.energies, grid.sigma)
    assert np.abs(ours - ref).max() <= 1e-8 * np.abs(ref).max()


def test_choose_solver_rule():
    assert choose_solver(500, 500) == "dense"  # k >= N - 1: ARPACK cannot
    assert choose_solver(200, 20) == "dense"  # small N
    assert choose_solver(1000, 20) == "lanczos"
    assert choose_solver(2000, 500) == "dense"  # N <= 4k
    assert choose_solver(3400, 500) == "sliced"
    assert choose_solver(5000, 500) == "sliced"
    assert choose_solver(5000, 100) == "lanczos"  # one run of <= LANCZOS_MAX_PAIRS
    assert choose_solver(5000, 101) == "sliced"


def test_k_larger_than_n_is_an_error():
    m = icosphere(0)  # 12 vertices
    with pytest.raises(ValueError, match=r"k=20 .* only N=12"):
        eigenpairs(m, k=20)
    with pytest.raises(ValueError, match="k must be >= 1"):
        eigenpairs(m, k=0)
    with pytest.raises(ValueError, match="lanczos"):
        LaplaceBeltrami(m).eigenpairs(11, solver="lanczos")
    s = eigenpairs(m, k=12, cache=False)  # k = N is fine (dense)
    assert s.evals.shape == (12,) and s.evecs.shape == (12, 12)


def test_unreferenced_vertex_is_a_clear_error():
    t = trimesh.creation.icosphere(1)
    v = np.vstack([t.vertices, [[5.0, 5.0, 5.0]]])
    with pytest.warns(MeshWarning):
        m = Mesh(v, t.faces)
    with pytest.raises(ValueError, match="zero mass"):
        eigenpairs(m, k=5)


def test_several_components_repeat_the_zero_eigenvalue():
    a = trimesh.creation.icosphere(2)
    b = trimesh.creation.icosphere(2)
    v = np.vstack([a.vertices, b.vertices + [4.0, 0, 0]])
    f = np.vstack([a.faces, b.faces + len(a.vertices)])
    with pytest.warns(MeshWarning):
        m = Mesh(v, f)
    with pytest.warns(SpectralWarning, match="2 connected components"):
        s = eigenpairs(m, k=10, cache=False)
    assert s.n_zero == 2
    assert np.all(np.abs(s.evals[:2]) < 1e-8) and s.evals[2] > 1.0
    assert np.all(np.isfinite(s.evecs))


def test_spectrum_is_frozen_and_validated():
    s = eigenpairs(icosphere(1), k=5, cache=False)
    with pytest.raises(Exception):
        s.evals = np.zeros(5)
    with pytest.raises(ValueError):
        s.evecs[0, 0] = 1.0
    with pytest.raises(ValueError, match="evals must be"):
        Spectrum(evals=np.zeros(3), evecs=np.zeros((4, 2)), area=1.0)
    with pytest.raises(ValueError, match="NaN"):
        Spectrum(evals=np.array([0, np.nan]), evecs=np.zeros((4, 2)), area=1.0)
    # a slice keeps every other field, and stays read-only
    low = s.first(3)
    assert low.k == 3 and low.area == s.area and low.n_zero == s.n_zero and low.solver == s.solver
    np.testing.assert_array_equal(low.evecs, s.evecs[:, :3])
    with pytest.raises(ValueError):
        low.evecs[0, 0] = 1.0
    assert s.first(5) is s


def test_eigenpairs_are_cached_by_content(tmp_path):
    cache = Cache("spectrum-test", cache_dir=tmp_path)
    m = icosphere(2)
    first = eigenpairs(m, k=10, cache=cache)
    assert not first.from_cache
    again = eigenpairs(Mesh(m.vertices.copy(), m.faces.copy()), k=10, cache=cache)  # equal content
    assert again.from_cache
    np.testing.assert_array_equal(again.evals, first.evals)
    np.testing.assert_array_equal(again.evecs, first.evecs)
    assert again.solver == first.solver and again.n_zero == first.n_zero
    # from disk in a "new process": a fresh cache object on the same folder
    fresh = eigenpairs(m, k=10, cache=Cache("spectrum-test", cache_dir=tmp_path))
    assert fresh.from_cache
    np.testing.assert_array_equal(fresh.evecs, first.evecs)
    # different parameters are a different entry
    assert not eigenpairs(m, k=11, cache=cache).from_cache
    moved = m.transformed(translation=[1.0, 0, 0])
    assert not eigenpairs(moved, k=10, cache=cache).from_cache
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eigenpairs(m, k=10, cache=cache)  # a one-component mesh gives no warning, cached or not


# ------------------------------------------------------------------------------ the cache itself
def test_cache_round_trip_and_bounds(tmp_path):
    c = Cache("unit", max_entries=2, cache_dir=tmp_path)
    a = {"x": np.arange(6.0).reshape(2, 3), "n": 3, "name": "dense"}
    got = c.put("fp1", {"k": 5, "tol": 0.1}, a)
    assert got["x"].flags.writeable is False
    back = Cache("unit", cache_dir=tmp_path).get("fp1", {"tol": 0.1, "k": 5})  # key order irrelevant
    np.testing.assert_array_equal(back["x"], a["x"])
    assert int(back["n"]) == 3 and str(back["name"]) == "dense"
    assert Cache("unit", cache_dir=tmp_path).get("fp1", {"k": 5, "tol": 0.1000000001}) is None  # exact floats
    assert Cache("unit", cache_dir=tmp_path).get("fp2", {"k": 5, "tol": 0.1}) is None
    # memory level is bounded (LRU); the disk level still has everything
    c.put("fp2", {}, {"x": np.zeros(1)})
    c.put("fp3", {}, {"x": np.zeros(1)})
    assert len(c) == 2
    assert c.get("fp1", {"k": 5, "tol": 0.1}) is not None  # re-read from disk
    # no leftover temporary files
    assert not list((tmp_path / "unit").glob("*.tmp"))
    with pytest.raises(TypeError, match="dtype object"):
        c.put("fp4", {}, {"x": np.array([{}], dtype=object)})


def test_cache_without_disk_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.delenv("WPOT_CACHE_DIR", raising=False)
    c = Cache("memonly")
    assert c.directory is None
    c.put("fp", {"a": 1}, {"x": np.ones(2)})
    assert c.get("fp", {"a": 1}) is not None
    monkeypatch.setenv("WPOT_CACHE_DIR", str(tmp_path))
    assert Cache("memonly").directory == tmp_path / "memonly"
    assert Cache("memonly", cache_dir=False).directory is None


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong_key"])
def test_corrupt_cache_entry_is_recomputed_with_a_warning(tmp_path, damage):
    from wpot.cache import CacheWarning

    c = Cache("unit", cache_dir=tmp_path)
    params = {"k": 3}
    c.put("fp", params, {"x": np.arange(1000.0)})
    path = c.path_for(c.key("fp", params))
    raw = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(raw[: len(raw) // 2])
    elif damage == "garbage":
        path.write_bytes(b"not a zip file at all")
    else:  # a valid file stored under another entry's name
        other = Cache("unit", cache_dir=tmp_path)
        other.put("other", params, {"x": np.zeros(3)})
        path.write_bytes(other.path_for(other.key("other", params)).read_bytes())
    fresh = Cache("unit", cache_dir=tmp_path)
    with pytest.warns(CacheWarning, match="corrupt cache entry"):
        assert fresh.get("fp", params) is None
    assert not path.exists()  # discarded
    calls = []
    entry = fresh.get_or_compute("fp", params, lambda: calls.append(1) or {"x": np.arange(1000.0)})
    assert calls == [1]
    np.testing.assert_array_equal(entry["x"], np.arange(1000.0))
    assert Cache("unit", cache_dir=tmp_path).get("fp", params) is not None  # rewritten, readable


def test_the_components_warning_is_given_once_per_mesh_not_once_per_use(tmp_path):
    a = trimesh.creation.icosphere(2)
    v = np.vstack([a.vertices, a.vertices * 0.5 + [4.0, 0, 0]])
    f = np.vstack([a.faces, a.faces + len(a.vertices)])
    with pytest.warns(MeshWarning):
        m = Mesh(v, f)
    cache = Cache("spectrum-warn-test", cache_dir=tmp_path)
    with pytest.warns(SpectralWarning, match="2 connected components"):
        first = eigenpairs(m, k=12, cache=cache)
    with pytest.warns(MeshWarning):
        copy = Mesh(m.vertices.copy(), m.faces.copy())
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpectralWarning)  # a second use of the same mesh (an equal copy too): silent
        again = eigenpairs(copy, k=12, cache=cache)
        found = cached_eigenpairs(m, k=12, cache=cache)
        from_disk = eigenpairs(m, k=12, cache=Cache("spectrum-warn-test", cache_dir=tmp_path))
    assert again.from_cache and found is not None and from_disk.from_cache
    assert again.n_zero == found.n_zero == from_disk.n_zero == first.n_zero == 2
    # a computation (here without the cache) warns again: the warning belongs to computing the spectrum
    with pytest.warns(SpectralWarning, match="2 connected components"):
        eigenpairs(m, k=12, cache=False)


def test_kept_makes_each_object_once_and_forgets_the_least_recently_used():
    from wpot.cache import Kept

    made = []
    kept = Kept(2)

    def make(k):
        return lambda: made.append(k) or object()

    a = kept.get("a", make("a"))
    kept.get("b", make("b"))
    assert kept.get("a", make("a")) is a  # kept: not made again, and now the most recent
    kept.get("c", make("c"))  # "b", the least recently used, goes
    assert kept.get("a", make("a")) is a
    kept.get("b", make("b"))
    assert made == ["a", "b", "c", "b"]
    kept.clear()
    assert kept.get("a", make("a")) is not a and made[-1] == "a"
