"""Mesh and correspondence I/O: round trips, real files, every invalid-input class, and a fuzz test."""
from __future__ import annotations

import signal
import warnings
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wpot.examples import example_mesh
from wpot.io import (
    MESH_FORMATS,
    load_mesh,
    load_vertex_map,
    load_vts,
    save_mesh,
    save_vertex_map,
    save_vts,
)
from wpot.mesh import Mesh, MeshWarning, cut

MESH_EXTS = [".off", ".ply", ".obj", ".mat"]


@pytest.fixture(scope="module")
def small() -> Mesh:
    """A small closed mesh with awkward (full-precision) coordinates."""
    m = example_mesh(120, seed=3)
    rng = np.random.default_rng(0)
    return Mesh(m.vertices * np.pi + rng.normal(scale=1e-9, size=m.vertices.shape), m.faces)


def _off_text(v, f) -> str:
    return f"OFF\n{len(v)} {len(f)} 0\n" + "".join(f"{a} {b} {c}\n" for a, b, c in v) + "".join(
        f"{len(t)} " + " ".join(map(str, t)) + "\n" for t in f
    )


def _parse_off_independently(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A minimal OFF reader for checking (whitespace tokens, '#' comments, triangles only)."""
    toks = []
    for line in path.read_text().splitlines():
        toks += line.split("#", 1)[0].split()
    assert toks[0] == "OFF"
    nv, nf = int(toks[1]), int(toks[2])
    pos = 4
    v = np.array(toks[pos : pos + 3 * nv], dtype=np.float64).reshape(nv, 3)
    pos += 3 * nv
    f = np.array(toks[pos : pos + 4 * nf], dtype=np.int64).reshape(nf, 4)
    assert np.all(f[:, 0] == 3)
    return v, f[:, 1:]


# ------------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("ext", MESH_EXTS)
def test_mesh_round_trip_is_exact(small, tmp_path, ext):
    p = save_mesh(small, tmp_path / f"m{ext}")
    back = load_mesh(p)
    assert back == small  # bit-identical vertices and faces, same order


@pytest.mark.parametrize("ext", MESH_EXTS)
def test_round_trip_keeps_unreferenced_vertices_in_place(tmp_path, ext):
    v = np.array([[9.0, 9, 9], [0, 0, 0], [1, 0, 0], [0, 1, 0], [8.0, 8, 8], [0, 0, 1]])
    f = np.array([[1, 3, 2], [1, 2, 5], [1, 5, 3], [2, 3, 5]])
    with pytest.warns(MeshWarning):
        m = Mesh(v, f)
    with pytest.warns(MeshWarning) as rec:
        back = load_mesh(save_mesh(m, tmp_path / f"iso{ext}"))
    assert back == m
    msg = str(rec[0].message)
    assert f"iso{ext}" in msg and "2 unreferenced vertices (vertices [0, 4])" in msg
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(tmp_path / f"iso{ext}", warn=False) == m


@pytest.mark.parametrize(
    "layout",
    ["Shape_df", "shape", "top_vert", "top_xyz"],
)
@pytest.mark.parametrize("triv_dtype", [np.float64, np.int32, np.uint16])
def test_shrec_mat_layouts(small, tmp_path, layout, triv_dtype):
    """SHREC'19-style MATLAB meshes: struct with VERT/TRIV, or top-level VERT/TRIV or X/Y/Z/TRIV."""
    v, triv = small.vertices, (small.faces + 1).astype(triv_dtype)
    if layout in ("Shape_df", "shape"):
        content = {layout: {"VERT": v, "TRIV": triv, "n": len(v), "m": len(triv)}}
    elif layout == "top_vert":
        content = {"VERT": v, "TRIV": triv}
    else:
        content = {"X": v[:, 0], "Y": v[:, 1], "Z": v[:, 2], "TRIV": triv}
    p = tmp_path / "shape.mat"
    scipy.io.savemat(p, content)
    assert load_mesh(p) == small


def test_mat_with_several_meshes_needs_variable(small, tmp_path):
    other = small.transformed(scale=2.0)
    p = tmp_path / "two.mat"
    scipy.io.savemat(p, {
        "surface": {"X": small.vertices[:, 0], "Y": small.vertices[:, 1], "Z": small.vertices[:, 2],
                    "TRIV": small.faces + 1},
        "Shape_df": {"VERT": other.vertices, "TRIV": other.faces + 1},
    })
    with pytest.raises(ValueError, match=r"several variables hold a mesh: \['Shape_df', 'surface'\]"):
        load_mesh(p)
    assert load_mesh(p, variable="surface") == small
    assert load_mesh(p, variable="Shape_df") == other
    with pytest.raises(ValueError, match="variable 'nope' does not hold a mesh"):
        load_mesh(p, variable="nope")
    with pytest.raises(ValueError, match=".mat files only"):
        load_mesh(tmp_path / "x.off", variable="surface")


@pytest.mark.parametrize(
    "content, pattern",
    [
        ({"surface": {"X": [0.0, 1, 0], "Y": [0.0, 0, 1], "Z": [0.0, 0, 0], "TRIV": [[0, 1, 2]]}},
         r"indices below 1 in faces \[0\].*1-based"),
        ({"foo": np.eye(3)}, r"no mesh found.*variables \['foo'\]"),
        ({"Shape_df": {"VERT": np.zeros((3, 2)), "TRIV": [[1, 2, 3]]}}, r"VERT must have shape \(N, 3\), got \(3, 2\)"),
        ({"Shape_df": {"VERT": np.eye(3), "TRIV": [[1, 2, 3, 1]]}}, r"TRIV must have shape \(F, 3\), got \(1, 4\)"),
        ({"Shape_df": {"VERT": np.eye(3), "TRIV": [[1, 2, 3], [1, 2.5, 3]]}}, r"non-integer entries in faces \[1\]"),
        ({"Shape_df": {"VERT": np.eye(3), "TRIV": [[1, 2, 4]]}}, r"faces index vertices outside \[0, 2\]: faces \[0\]"),
        ({"Shape_df": {"VERT": "abc", "TRIV": [[1, 2, 3]]}}, r"VERT is not a numeric array"),
        ({"surface": {"X": [0.0, 1], "Y": [0.0, 0, 1], "Z": [0.0, 0, 0], "TRIV": [[1, 2, 3]]}}, "different lengths"),
    ],
)
def test_mat_invalid_content(tmp_path, content, pattern):
    p = tmp_path / "bad.mat"
    scipy.io.savemat(p, content)
    with pytest.raises(ValueError, match=pattern) as exc:
        load_mesh(p)
    assert str(p) in str(exc.value)


def test_vts_and_map_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    idx = rng.integers(0, 1000, size=57)
    assert np.array_equal(load_vts(save_vts(idx, tmp_path / "a.vts"), n_vertices=1000), idx)
    assert (tmp_path / "a.vts").read_text().splitlines()[0] == str(idx[0] + 1)  # 1-based on disk
    for base in (0, 1):
        p = save_vertex_map(idx, tmp_path / f"map{base}.txt", base=base)
        assert p.read_text().splitlines()[3] == str(idx[3] + base)
        back = load_vertex_map(p, base=base, n_vertices=1000)
        assert back.dtype == np.int64 and np.array_equal(back, idx)


# -------------------------------------------------------------------------------------- real files
@pytest.mark.parametrize("name", ["cat0", "david0", "michael5"])
def test_tosca5k_off_order_and_count_preserved(tosca5k, name):
    p = tosca5k / f"{name}.off"
    v, f = _parse_off_independently(p)
    m = load_mesh(p, warn=False)
    assert m.n_vertices == len(v) and m.n_faces == len(f)
    assert np.array_equal(m.faces, f)
    assert np.allclose(m.vertices, v, rtol=1e-15, atol=0)
    gt = load_vts(tosca5k / "corres" / f"{name}.vts", n_vertices=m.n_vertices)
    sym = load_vts(tosca5k / "corres" / f"{name}.sym.vts", n_vertices=m.n_vertices)
    assert gt.shape == sym.shape == (5000,) and gt.dtype == np.int64
    assert gt.min() >= 0 and not np.array_equal(gt, sym)
    raw = np.loadtxt(tosca5k / "corres" / f"{name}.vts", dtype=np.int64)
    assert np.array_equal(gt, raw - 1)


def test_tosca_lowres_mat_matches_raw_struct(shared_data):
    p = shared_data / "tosca_lowres" / "cat0.mat"
    if not p.exists():
        pytest.skip(f"{p} not found")
    s = scipy.io.loadmat(p)["surface"][0, 0]
    m = load_mesh(p)
    assert (m.n_vertices, m.n_faces) == (3400, 6768)
    assert np.array_equal(m.vertices, np.column_stack([s["X"].ravel(), s["Y"].ravel(), s["Z"].ravel()]))
    assert np.array_equal(m.faces, s["TRIV"].astype(np.int64) - 1)


def test_pyfm_camel_maps_are_zero_based(shared_data):
    """The pyFM maps: line i of <i>_to_<j> is the camel-j vertex for camel-i vertex i, 0-based."""
    d = shared_data / "pyfm_examples" / "camel_gallop"
    if not (d / "maps" / "1_to_3").exists():
        pytest.skip(f"pyFM camel maps not found in {d}")
    src = load_mesh(d / "camel-gallop-01.off", warn=False)
    dst = load_mesh(d / "camel-gallop-03.off", warn=False)
    v, _ = _parse_off_independently(d / "camel-gallop-01.off")
    assert np.allclose(src.vertices, v, rtol=1e-15, atol=0)
    fmap = load_vertex_map(d / "maps" / "1_to_3", base=0, n_vertices=dst.n_vertices)
    assert fmap.shape == (src.n_vertices,)
    assert fmap.min() == 0 and fmap.max() == dst.n_vertices - 1  # uses the whole 0..N-1 range
    with pytest.raises(ValueError, match="looks 0-based: pass base=0"):
        load_vertex_map(d / "maps" / "1_to_3")
    # a sensible map: matched points are close (same camel, nearby poses), on average
    dist = np.linalg.norm(src.vertices - dst.vertices[fmap], axis=1)
    assert np.median(dist) < 0.1 * src.bounding_box_diagonal


def test_real_nonmanifold_edges_reported_with_independent_count(shared_data):
    p = shared_data / "pyfm_examples" / "camel_gallop" / "camel-gallop-01.off"
    if not p.exists():
        pytest.skip(f"{p} not found")
    _, f = _parse_off_independently(p)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    n_nm = int((counts > 2).sum())
    assert n_nm > 0  # this file has some (a known defect of the data)
    with pytest.warns(MeshWarning, match=f"{n_nm} non-manifold edges") as rec:
        load_mesh(p)
    assert "camel-gallop-01.off" in str(rec[0].message) and "not repaired" in str(rec[0].message)


# ------------------------------------------------------------------------------------------------- STL
def _stl_binary(corners: np.ndarray) -> bytes:
    """A binary STL of facets ``corners`` ((F, 3, 3)), written here by hand (80-byte header, count, records)."""
    rec = np.zeros(len(corners), dtype=np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]))
    rec["v"] = corners
    return b"written by a test".ljust(80, b" ") + np.uint32(len(corners)).tobytes() + rec.tobytes()


def _stl_ascii(corners: np.ndarray) -> str:
    body = "".join("facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in tri)
                   + "endloop\nendfacet\n" for tri in corners.tolist())
    return "solid test\n" + body + "endsolid test\n"


def _first_use(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of ``mesh`` in order of first use by its faces, and its faces renumbered to match."""
    ids, first = np.unique(mesh.faces.reshape(-1), return_index=True)
    order = ids[np.argsort(first)]
    number = np.empty(mesh.n_vertices, dtype=np.int64)
    number[order] = np.arange(len(order))
    return mesh.vertices[order], number[mesh.faces]


def test_stl_is_welded_back_to_the_mesh(small, tmp_path):
    corners = small.vertices[small.faces]  # (F, 3, 3): what an STL stores
    v, f = _first_use(small)
    # ASCII keeps full precision: exactly the mesh, vertices in order of first use
    (tmp_path / "a.stl").write_text(_stl_ascii(corners))
    back = load_mesh(tmp_path / "a.stl")
    assert back.n_vertices == small.n_vertices
    np.testing.assert_array_equal(back.vertices, v)
    np.testing.assert_array_equal(back.faces, f)
    # binary stores float32: the same mesh with rounded coordinates
    (tmp_path / "b.stl").write_bytes(_stl_binary(corners))
    back = load_mesh(tmp_path / "b.stl")
    np.testing.assert_array_equal(back.vertices, v.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(back.faces, f)


def test_stl_slivers_dropped_signed_zeros_welded_garbage_refused(tmp_path):
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    corners = tet[faces].copy()
    corners[1, 0] = [-0.0, -0.0, 0.0]  # the same point, written with signed zeros
    sliver = np.array([[[1.0, 0, 0], [1.0, 0, 0], [0, 1, 0]]])  # two corners coincide: no area
    (tmp_path / "t.stl").write_bytes(_stl_binary(np.concatenate([corners[:2], sliver, corners[2:]])))
    with pytest.warns(MeshWarning, match=r"t\.stl: dropped 1 STL facets whose corners coincide"):
        m = load_mesh(tmp_path / "t.stl")
    assert m.n_vertices == 4 and m.n_faces == 4  # a closed tetrahedron: no hole, no extra vertex
    assert m == Mesh(*_first_use(Mesh(tet, faces)))
    (tmp_path / "g.stl").write_bytes(b"not an STL file at all" * 10)
    with pytest.raises(ValueError, match=r"g\.stl: malformed STL file"):
        load_mesh(tmp_path / "g.stl")
    (tmp_path / "e.stl").write_text("solid empty\nendsolid empty\n")
    with pytest.raises(ValueError, match=r"e\.stl: malformed STL file: no facets found"):
        load_mesh(tmp_path / "e.stl")


# ----------------------------------------------------------------------------------- invalid input
def test_missing_file_and_unknown_extension(tmp_path):
    missing = tmp_path / "nope.off"
    for fn in (load_mesh, load_vts, load_vertex_map):
        with pytest.raises(FileNotFoundError, match="nope.off"):
            fn(missing)
    with pytest.raises(OSError):
        load_mesh(tmp_path / "dir.off" if (tmp_path / "dir.off").mkdir() is None else None)
    (tmp_path / "m.stp").write_text("ISO-10303-21;\n")
    with pytest.raises(ValueError, match=r"unsupported mesh file extension '.stp'; supported: .off, .ply, .obj, .stl, .mat"):
        load_mesh(tmp_path / "m.stp")
    with pytest.raises(ValueError, match="supported"):
        save_mesh(Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]), tmp_path / "m.stp")
    with pytest.raises(ValueError, match="reads STL but does not write it"):
        save_mesh(Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]), tmp_path / "m.stl")
    assert set(MESH_FORMATS) == set(MESH_EXTS) | {".stl"}
    from wpot.datasets import MESH_EXTENSIONS

    assert set(MESH_EXTENSIONS) == set(MESH_FORMATS)  # a folder yields only files load_mesh reads


QUAD_V = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0], [3, 0, 0]]


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
def test_polygons_refused_naming_faces(tmp_path, ext):
    faces = [[0, 1, 2], [0, 1, 2, 3], [1, 4, 5], [1, 4, 6, 5, 2]]  # faces 1 and 3 are not triangles
    p = tmp_path / f"poly{ext}"
    if ext == ".off":
        p.write_text(_off_text(QUAD_V, faces))
    elif ext == ".obj":
        p.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in QUAD_V)
                     + "".join("f " + " ".join(str(i + 1) for i in t) + "\n" for t in faces))
    else:
        p.write_text(
            "ply\nformat ascii 1.0\nelement vertex 7\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
            + "".join(f"{a} {b} {c}\n" for a, b, c in QUAD_V)
            + "".join(f"{len(t)} " + " ".join(map(str, t)) + "\n" for t in faces)
        )
    with pytest.raises(ValueError, match=r"2 faces are not triangles \(vertex counts \[4, 5\]\): faces \[1, 3\]") as e:
        load_mesh(p)
    assert str(p) in str(e.value)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", r"faces index vertices outside \[0, 2\].*faces \[0\]"),
        ("OFF\n3 1 0\n0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n", r"NaN or infinite coordinates: vertices \[1\]"),
        ("OFF\n3 1 0\n0 0 0\n1 inf 0\n0 1 0\n3 0 1 2\n", r"NaN or infinite coordinates: vertices \[1\]"),
        ("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n", "truncated"),
        ("OFF\n0 0 0\n", "empty mesh: no vertices"),
        ("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n", "empty mesh: no faces"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 1\n", r"repeat a vertex.*faces \[0\]"),
        ("OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n", "vertex 1 has fewer than 3 coordinates"),
        ("OFF\nthree 1 0\n", "vertex count: expected an integer"),
        ("PLY\n", "first line must be the OFF keyword"),
        ("", "the file is empty"),
    ],
)
def test_invalid_off_content(tmp_path, text, pattern):
    p = tmp_path / "bad.off"
    p.write_text(text)
    with pytest.raises(ValueError, match=pattern) as e:
        load_mesh(p)
    assert str(p) in str(e.value)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 7\n", r"outside \[0, 2\] \(0-based\): faces \[1\]"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"outside \[0, 2\].*faces \[0\]"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "empty mesh: no faces"),
        ("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n", r"NaN or infinite coordinates: vertices \[2\]"),
    ],
)
def test_invalid_obj_content(tmp_path, text, pattern):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(ValueError, match=pattern):
        load_mesh(p)


def test_obj_relative_indices_and_texture_coordinates_keep_vertex_order(tmp_path):
    p = tmp_path / "t.obj"
    p.write_text("v 5 5 5\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\n"
                 "f 3/1/1 4/2/1 5/3/1\nf -4/1 -3/2 -1/3\n")
    with pytest.warns(MeshWarning, match=r"unreferenced vertices \(vertices \[0\]\)"):
        m = load_mesh(p)
    assert np.array_equal(m.vertices[:, 0], [5, 0, 1, 1, 0])
    assert np.array_equal(m.faces, [[2, 3, 4], [1, 2, 4]])


def test_obj_with_objects_groups_and_materials_keeps_file_order(tmp_path):
    """trimesh splits an OBJ at 'usemtl' and regroups faces; the reader restores the file's face order."""
    p = _write(tmp_path / "o.obj", "mtllib x.mtl\no a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl m1\nf 1 2 3\no b\ng gg\n"
               "v 5 5 5\nv 6 5 5\nv 5 6 5\nusemtl m2\nf 4 5 6\ns 1\nf 1 2 4\n")
    m = load_mesh(p, warn=False)
    assert np.array_equal(m.vertices[:, 0], [0, 1, 0, 5, 6, 5])
    assert np.array_equal(m.faces, [[0, 1, 2], [3, 4, 5], [0, 1, 3]])


def test_ply_truncated_binary(small, tmp_path):
    p = save_mesh(small, tmp_path / "m.ply")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 7])
    with pytest.raises(ValueError, match="truncated"):
        load_mesh(p)


def test_mesh_warnings_from_files_name_the_file(tmp_path):
    # zero-area triangle (vertex 3 on edge 0-1), plus a second component
    v = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 0, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]]
    p = tmp_path / "defects.off"
    p.write_text(_off_text(v, [[0, 1, 2], [0, 1, 3], [4, 5, 6]]))
    with pytest.warns(MeshWarning) as rec:
        load_mesh(p)
    msg = str(rec[0].message)
    assert msg.startswith(str(p)) and "1 zero-area triangles (faces [1])" in msg
    assert "2 connected components" in msg


@pytest.mark.parametrize(
    "text, kwargs, pattern",
    [
        ("1\n2\n0\n", {}, r"1 indices below 1 .* lines \[3\] \(first: 0\); the file looks 0-based: pass base=0"),
        ("1\n2\n9\n", {"n_vertices": 5}, r"1 indices exceed the mesh's 5 vertices on lines \[3\] \(first: 9"),
        ("1\n2 3\n", {}, r"line 2 must hold exactly one vertex index"),
        ("1\nx\n", {}, r"line 2: expected an integer vertex index, got 'x'"),
        ("1\n2.5\n", {}, r"line 2: expected an integer"),
        ("1\n\n3\n", {}, r"line 2 must hold exactly one"),
        ("\n\n", {}, "empty"),
        ("", {}, "empty"),
        ("1\n-4\n", {}, r"indices below 1 .*lines \[2\]"),
    ],
)
def test_invalid_index_files(tmp_path, text, kwargs, pattern):
    p = tmp_path / "bad.vts"
    p.write_text(text)
    with pytest.raises(ValueError, match=pattern) as e:
        load_vts(p, **kwargs)
    assert str(p) in str(e.value)
    assert np.array_equal(load_vts(_write(tmp_path / "ok.vts", "3\n1.0\n2\n\n")), [2, 0, 1])  # trailing blank ok


def _write(p: Path, text: str) -> Path:
    p.write_text(text)
    return p


def test_vertex_map_base_and_saver_validation(tmp_path):
    p = _write(tmp_path / "m.txt", "0\n4\n2\n")
    assert np.array_equal(load_vertex_map(p, base=0, n_vertices=5), [0, 4, 2])
    with pytest.raises(ValueError, match="exceed the mesh's 4 vertices on lines \\[2\\]"):
        load_vertex_map(p, base=0, n_vertices=4)
    with pytest.raises(ValueError, match="base must be 0 or 1, got 2"):
        load_vertex_map(p, base=2)
    with pytest.raises(ValueError, match="non-negative"):
        save_vts(np.array([1, -1]), tmp_path / "x.vts")
    with pytest.raises(ValueError, match="1-D integer array"):
        save_vertex_map(np.array([1.5]), tmp_path / "x.txt")


# -------------------------------------------------------------------------------------------- fuzzing
@contextmanager
def _time_limit(seconds: int):
    """Fail (instead of hanging) if a reader runs longer than ``seconds`` (POSIX main thread only)."""
    if not hasattr(signal, "SIGALRM"):
        yield
        return

    def handler(signum, frame):
        raise TimeoutError(f"reader still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


READERS = {
    ".off": load_mesh, ".ply": load_mesh, ".obj": load_mesh, ".mat": load_mesh,
    ".vts": load_vts, ".txt": lambda p: load_vertex_map(p, n_vertices=100),
}


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, bytes]:
    """Valid files of every format (a small mesh, and a real TOSCA mesh's first lines when present)."""
    d = tmp_path_factory.mktemp("seeds")
    m, _ = cut(example_mesh(120), np.arange(60))
    out = {ext: save_mesh(m, d / f"s{ext}").read_bytes() for ext in MESH_EXTS}
    out[".vts"] = save_vts(np.arange(0, 90, 3), d / "s.vts").read_bytes()
    out[".txt"] = save_vertex_map(np.arange(0, 90, 3), d / "s.txt").read_bytes()
    return out


def _read_or_refuse(tmp_path: Path, ext: str, data: bytes) -> None:
    p = tmp_path / f"fuzz{ext}"
    p.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)
        with _time_limit(20):
            try:
                READERS[ext](p)
            except (ValueError, OSError):
                pass  # the only acceptable failures


FUZZ = settings(max_examples=100, deadline=timedelta(seconds=10), derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.mark.parametrize("ext", list(READERS))
@FUZZ
@given(data=st.binary(max_size=400))
def test_fuzz_random_bytes(tmp_path, ext, data):
    _read_or_refuse(tmp_path, ext, data)


@pytest.mark.parametrize("ext", list(READERS))
@FUZZ
@given(cut_at=st.floats(0.0, 1.0), flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=6))
def test_fuzz_truncated_and_corrupted_files(tmp_path, seeds, ext, cut_at, flips):
    b = bytearray(seeds[ext][: int(cut_at * len(seeds[ext]))])
    for where, value in flips:
        if b:
            b[min(int(where * len(b)), len(b) - 1)] = value
    _read_or_refuse(tmp_path, ext, bytes(b))


def test_fuzz_truncated_real_file(tosca5k, tmp_path):
    data = (tosca5k / "cat0.off").read_bytes()
    rng = np.random.default_rng(0)
    for at in rng.integers(0, len(data), size=6):
        _read_or_refuse(tmp_path, ".off", data[:at])
