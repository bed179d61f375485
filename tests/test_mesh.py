"""The Mesh type: validation errors and warnings, immutability, derived quantities, cleaned(), cut()."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from wpot.examples import example_mesh
from wpot.mesh import Mesh, MeshWarning, cut, edge_paths

# a closed tetrahedron (4 vertices, 4 outward faces) and a unit square (2 triangles)
TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
SQ_V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
SQ_F = np.array([[0, 1, 2], [0, 2, 3]])


def _no_warnings(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kw)


@pytest.fixture(scope="module")
def blob() -> Mesh:
    return example_mesh(300)


# ------------------------------------------------------------------------------------- construction
def test_arrays_are_converted_and_read_only():
    m = _no_warnings(Mesh, TET_V.tolist(), TET_F.astype(np.uint16))
    assert m.vertices.dtype == np.float64 and m.vertices.shape == (4, 3)
    assert m.faces.dtype == np.int64 and m.faces.shape == (4, 3)
    for arr in (m.vertices, m.faces, m.face_areas, m.face_normals, m.vertex_normals, m.edges, m.edge_lengths,
                m.boundary_edges, m.one_ring_mean_edge_length, m.component_labels, m.one_ring(0)):
        with pytest.raises(ValueError, match="read-only"):
            arr[...] = 0
    with pytest.raises(AttributeError):
        m.vertices = TET_V  # type: ignore[misc]


def test_input_arrays_are_copied():
    v = TET_V.copy()
    m = Mesh(v, TET_F)
    v[0] = 99.0
    assert np.array_equal(m.vertices, TET_V)


def test_integral_float_faces_accepted_non_integer_refused():
    assert Mesh(TET_V, TET_F.astype(float)) == Mesh(TET_V, TET_F)
    f = TET_F.astype(float)
    f[2, 1] = 1.5
    with pytest.raises(ValueError, match=r"non-integer entries in faces \[2\]"):
        Mesh(TET_V, f)


@pytest.mark.parametrize(
    "vertices, faces, pattern",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty mesh: no vertices"),
        (TET_V, np.zeros((0, 3), int), "empty mesh: no faces"),
        (TET_V[:, :2], TET_F, r"vertices must have shape \(N, 3\), got \(4, 2\)"),
        (TET_V, np.array([[0, 1, 2, 3]]), r"triangles only.*got \(1, 4\)"),
        (TET_V, TET_F.ravel(), r"faces must have shape \(F, 3\)"),
        (TET_V, np.array([[0, 1, 2], [0, 1, 4], [0, -1, 2]]), r"2 faces index vertices outside \[0, 3\]: faces \[1, 2\]"),
        (TET_V, np.array([[0, 1, 2], [1, 1, 3]]), r"1 faces repeat a vertex.*faces \[1\]"),
        (np.array([["a", "b", "c"]]), [[0, 0, 0]], "vertices must be a numeric"),
    ],
)
def test_fatal_problems_raise_naming_them(vertices, faces, pattern):
    with pytest.raises(ValueError, match=pattern):
        Mesh(vertices, faces)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_coordinates_named(bad):
    v = TET_V.copy()
    v[1, 2] = bad
    v[3, 0] = bad
    with pytest.raises(ValueError, match=r"2 vertices have NaN or infinite coordinates: vertices \[1, 3\]"):
        Mesh(v, TET_F)


# ------------------------------------------------------------------------------------------ warnings
def _warning_text(vertices, faces) -> str:
    with pytest.warns(MeshWarning) as rec:
        Mesh(vertices, faces)
    assert len(rec) == 1
    return str(rec[0].message)


def test_zero_area_triangle_warned_with_count_and_index():
    v = np.vstack([TET_V, [[0.5, 0.0, 0.0]]])  # vertex 4 on edge (0, 1)
    f = np.vstack([TET_F, [[0, 1, 4]]])
    msg = _warning_text(v, f)
    assert "1 zero-area triangles (faces [4])" in msg


def test_unreferenced_vertices_warned_with_indices():
    v = np.vstack([TET_V[:2], [[5.0, 5, 5]], TET_V[2:], [[6.0, 6, 6]]])  # vertices 2 and 5 unused
    f = np.array([[0, 3, 1], [0, 1, 4], [0, 4, 3], [1, 3, 4]])
    msg = _warning_text(v, f)
    assert "2 unreferenced vertices (vertices [2, 5])" in msg


def test_nonmanifold_edge_warned():
    v = np.vstack([SQ_V, [[0.5, 0.5, 1.0]]])
    f = np.vstack([SQ_F, [[0, 2, 4]]])  # edge (0, 2) is shared by three triangles
    msg = _warning_text(v, f)
    assert "1 non-manifold edges" in msg and "[0, 2]" in msg


def test_several_components_warned_with_sizes():
    v = np.vstack([TET_V, SQ_V + 10])
    f = np.vstack([TET_F, SQ_F + 4])
    msg = _warning_text(v, f)
    assert "2 connected components (vertex counts [4, 4])" in msg


def test_warnings_about_several_components_name_the_mesh(tmp_path):
    """The mesh's name (its file's path, from load_mesh) starts every warning about its components: the defect
    warning, the repeated zero eigenvalue of its spectrum, a sample too few for its pieces; also after cleaned()."""
    import trimesh

    from wpot.io import load_mesh, save_mesh
    from wpot.sampling import farthest_point_sampling
    from wpot.spectral import SpectralWarning, eigenpairs

    s = trimesh.creation.icosphere(1)
    v, f = np.vstack([s.vertices, s.vertices + [3.0, 0, 0]]), np.vstack([s.faces, s.faces + len(s.vertices)])
    with pytest.warns(MeshWarning, match=r"^pieces: mesh defects: 2 connected components"):
        named = Mesh(v, f, name="pieces")
    assert named.name == "pieces" and named == Mesh(v, f, warn=False) and Mesh(v, f, warn=False).name is None
    assert named.fingerprint == Mesh(v, f, warn=False).fingerprint  # the name is not content
    assert named.transformed(translation=[1.0, 0, 0]).name == "pieces"
    save_mesh(named, tmp_path / "two.off")
    with pytest.warns(MeshWarning, match=re.escape(f"{tmp_path / 'two.off'}: mesh defects: 2 connected")):
        m = load_mesh(tmp_path / "two.off")
    assert m.name == str(tmp_path / "two.off")
    with pytest.warns(SpectralWarning, match=re.escape(f"{m.name}: the mesh has 2 connected components")):
        eigenpairs(m, k=20, cache=False)
    with pytest.warns(UserWarning, match=re.escape(f"{m.name}: ") + r"\d+ vertices lie in parts of the mesh"):
        farthest_point_sampling(m, 1)
    with pytest.warns(MeshWarning, match=re.escape(f"{m.name}: mesh defects: 2 connected")):
        cleaned, _ = m.cleaned()
    assert cleaned.name == m.name
    assert m.cleaned(keep_largest_component=True)[0].name == m.name


def test_warn_false_silences_but_still_raises():
    v = np.vstack([TET_V, [[9.0, 9, 9]]])
    _no_warnings(Mesh, v, TET_F, warn=False)
    with pytest.raises(ValueError, match="outside"):
        Mesh(TET_V, TET_F + 1, warn=False)


def test_clean_mesh_gives_no_warning(blob):
    _no_warnings(Mesh, blob.vertices, blob.faces)


# ------------------------------------------------------------------------------ derived quantities
def test_tetrahedron_closed_forms():
    m = Mesh(TET_V, TET_F)
    assert m.area == pytest.approx(1.5 + np.sqrt(3) / 2)
    assert len(m.edges) == 6 and len(m.boundary_edges) == 0 and m.n_components == 1
    # outward normals: the slanted face points along (1,1,1)/sqrt(3)
    assert np.allclose(m.face_normals[3], np.ones(3) / np.sqrt(3))
    assert np.allclose(m.face_normals[0], [0, 0, -1])
    assert np.allclose(m.one_ring(0), [1, 2, 3])
    # D(v) of vertex 0: three unit edges
    assert m.one_ring_mean_edge_length[0] == pytest.approx(1.0)
    assert m.one_ring_mean_edge_length[1] == pytest.approx((1 + 2 * np.sqrt(2)) / 3)


def test_blob_topology_and_one_ring_mean(blob):
    m = blob
    assert m.n_vertices - len(m.edges) + m.n_faces == 2  # sphere: Euler characteristic 2
    a = m.adjacency
    assert (a != a.T).nnz == 0
    i = 17
    ring = m.one_ring(i)
    expected = np.mean(np.linalg.norm(m.vertices[ring] - m.vertices[i], axis=1))
    assert m.one_ring_mean_edge_length[i] == pytest.approx(expected)
    assert np.allclose(np.linalg.norm(m.vertex_normals, axis=1), 1.0)
    with pytest.raises(ValueError, match="vertex index"):
        m.one_ring(m.n_vertices)


def test_rigid_motion_and_relabelling_invariance(blob):
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    moved = blob.transformed(q, translation=[1.0, -2.0, 3.0])
    assert moved.area == pytest.approx(blob.area)
    assert np.allclose(np.sort(moved.edge_lengths), np.sort(blob.edge_lengths))
    assert np.allclose(moved.face_normals, blob.face_normals @ q.T)
    assert blob.transformed(scale=2.0).area == pytest.approx(4 * blob.area)
    perm = rng.permutation(blob.n_vertices)
    rel = blob.relabelled(perm)
    assert np.array_equal(rel.vertices, blob.vertices[perm])
    assert rel.area == pytest.approx(blob.area)
    assert np.allclose(rel.one_ring_mean_edge_length, blob.one_ring_mean_edge_length[perm])
    assert rel.fingerprint != blob.fingerprint
    assert Mesh(blob.vertices, blob.faces).fingerprint == blob.fingerprint
    with pytest.raises(ValueError, match="permutation"):
        blob.relabelled(perm[:-1])


# -------------------------------------------------------------------------------------------- cleaned
def test_cleaned_removes_defects_and_index_map_lines_up():
    # tetrahedron + isolated vertex (index 2) + a zero-area face + a duplicate face + a far component
    v = np.vstack([TET_V[:2], [[7.0, 7, 7]], TET_V[2:], [[0.5, 0, 0]], SQ_V + 10])
    f = np.array([[0, 3, 1], [0, 1, 4], [0, 4, 3], [1, 3, 4], [0, 1, 5], [0, 3, 1], [6, 7, 8], [6, 8, 9]])
    with pytest.warns(MeshWarning):
        m = Mesh(v, f)
    clean, index_map = _no_warnings_allowed_components(m.cleaned)
    assert index_map.dtype == np.int64
    assert np.array_equal(clean.vertices, m.vertices[index_map])  # positions line up
    assert 2 not in index_map and 5 not in index_map  # isolated vertex and the degenerate face's apex
    old_faces = {tuple(sorted(t)) for t in m.faces.tolist()}
    new_faces = [tuple(sorted(t)) for t in index_map[clean.faces].tolist()]
    assert set(new_faces) <= old_faces and len(new_faces) == len(set(new_faces)) == 6
    largest, imap = _no_warnings(m.cleaned, keep_largest_component=True)
    assert np.array_equal(imap, [0, 1, 3, 4])
    assert np.array_equal(largest.vertices, TET_V)
    assert largest.area == pytest.approx(Mesh(TET_V, TET_F).area)


def _no_warnings_allowed_components(fn):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out = fn()
    defects = [str(w.message).split(". Results")[0] for w in rec]  # the list of problems, before the advice
    assert all("connected components" in d and "unreferenced" not in d and "zero-area" not in d for d in defects)
    return out


# ----------------------------------------------------------------------------------------------- cut
def test_cut_index_map_faces_and_boundary(blob):
    m = blob
    mask = m.vertices[:, 0] > 0.2
    part, index_map = cut(m, mask)
    assert np.array_equal(part.vertices, m.vertices[index_map])
    assert mask[index_map].all()
    # faces of the part are exactly the faces of m with all three vertices in the mask
    kept = m.faces[mask[m.faces].all(axis=1)]
    assert np.array_equal(index_map[part.faces], kept)
    # boundary of the part: edges of kept faces that the full (closed) mesh shares with a dropped face
    und = np.sort(np.concatenate([kept[:, [0, 1]], kept[:, [1, 2]], kept[:, [2, 0]]]), axis=1)
    e, c = np.unique(und, axis=0, return_counts=True)
    expected_boundary = e[c == 1]
    got = np.sort(index_map[part.boundary_edges], axis=1)
    assert np.array_equal(np.unique(got, axis=0), expected_boundary)
    assert len(expected_boundary) > 0
    # the same cut from integer indices
    part2, map2 = cut(m, np.nonzero(mask)[0])
    assert part2 == part and np.array_equal(map2, index_map)


def test_cut_drops_mask_vertices_without_a_triangle():
    m = Mesh(TET_V, TET_F)
    part, index_map = cut(m, [0, 1, 2])
    assert np.array_equal(index_map, [0, 1, 2]) and part.n_faces == 1
    with pytest.raises(ValueError, match="keeps no triangle"):
        cut(m, [0, 1])
    with pytest.raises(ValueError, match=re.escape("out of range [0, 3]: [7]")):
        cut(m, [0, 1, 7])
    with pytest.raises(ValueError, match=r"shape \(4,\)"):
        cut(m, np.ones(3, dtype=bool))


def test_vertex_areas_are_a_third_of_each_triangle_and_sum_to_the_area():
    # two triangles sharing an edge, areas 0.5 and 1.0, and an unreferenced vertex
    m = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 1, 0], [5, 5, 5]], float),
             np.array([[0, 1, 2], [1, 3, 2]]), warn=False)
    np.testing.assert_allclose(m.face_areas, [0.5, 1.0])
    np.testing.assert_allclose(m.vertex_areas, [0.5 / 3, 1.5 / 3, 1.5 / 3, 1.0 / 3, 0.0])
    assert m.vertex_areas.sum() == pytest.approx(m.area) and not m.vertex_areas.flags.writeable


def test_voronoi_areas_are_the_dual_cells_of_a_regular_grid_and_sum_to_the_area():
    # a 6 x 6 grid of squares of side h, each cut into two right triangles: an interior vertex's Voronoi cell
    # (the mixed area, circumcentres at the hypotenuses' midpoints) is the h x h square around it
    h, n = 0.3, 7
    x, y = np.meshgrid(np.arange(n) * h, np.arange(n) * h, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    m = Mesh(v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]), warn=False)
    interior = idx[1:-1, 1:-1].ravel()
    np.testing.assert_allclose(m.voronoi_areas[interior], h * h, rtol=1e-12)
    assert m.voronoi_areas.sum() == pytest.approx(m.area) and not m.voronoi_areas.flags.writeable
    from wpot.spectral import laplace_beltrami

    np.testing.assert_array_equal(laplace_beltrami(m)[1].diagonal(), m.voronoi_areas)  # the mass matrix's diagonal


def test_edge_paths_are_scipys_undirected_shortest_paths():
    # the graph is symmetric, so the directed search gives what an undirected one does, in every form asked
    from scipy.sparse.csgraph import dijkstra

    m = example_mesh(300, seed=2)
    src = np.array([0, 17, 123])
    undirected = dijkstra(m.edge_graph, directed=False, indices=src)
    np.testing.assert_array_equal(edge_paths(m, src), undirected)
    np.testing.assert_array_equal(edge_paths(m, 17), undirected[1])
    np.testing.assert_array_equal(edge_paths(m, src, min_only=True), undirected.min(axis=0))
    r = float(np.median(undirected[0]))
    np.testing.assert_array_equal(edge_paths(m, 0, limit=r), np.where(undirected[0] <= r, undirected[0], np.inf))
    # a one-ring neighbour is one edge away
    j = int(m.one_ring(0)[0])
    assert edge_paths(m, 0)[j] == pytest.approx(np.linalg.norm(m.vertices[0] - m.vertices[j]))


def test_boundary_rings_count_edges_from_the_cut():
    from wpot.mesh import boundary_rings, cut

    m = example_mesh(900)
    part, _ = cut(m, m.vertices[:, 2] > np.median(m.vertices[:, 2]))
    rings = boundary_rings(part)
    border = np.unique(part.boundary_edges.ravel())
    assert np.all(rings[border] == 0) and rings.max() >= 3
    # one ring in: a neighbour of the border that is not on it
    inner = np.setdiff1d(np.unique(part.adjacency[border].indices), border)
    assert np.all(rings[inner] == 1)
    assert np.all(np.isinf(boundary_rings(m)))  # a closed surface has no cut

