"""Reading and writing meshes and ground-truth correspondences.

Meshes
------
`load_mesh` reads

* ``.off``, ``.ply``, ``.obj`` through trimesh's format parsers, with every kind of processing off
  (no vertex merging, no removal of unreferenced vertices, no re-ordering: OBJ is read with
  ``maintain_order=True``, PLY with ``fix_texture=False``), so vertex ``i`` of the `Mesh` is vertex
  ``i`` of the file. trimesh silently triangulates polygons; wpot refuses them instead: a small
  independent scan of the file (OFF face-count column, OBJ ``f`` lines, PLY raw face lists) finds
  every face that is not a triangle and the error names them. The scan also checks that trimesh
  returned exactly the vertex and face counts the file declares (a truncated OFF is an error, not a
  smaller mesh).
* ``.stl`` (binary or ASCII, through trimesh's parser): a soup of facets with no shared vertices, so
  corners with identical coordinates are welded into one vertex (exact equality only: a tolerance would
  move the geometry), numbered in order of first use. Facets whose corners then coincide are dropped with
  a `MeshWarning` that counts them. Binary STL stores float32 coordinates. STL is read, never written
  (`save_mesh` refuses it: it could not give the same mesh back).
* ``.mat`` (MATLAB v5/v7, read with `scipy.io.loadmat`) in two layouts:

  - TOSCA: a struct (usually named ``surface``) with fields ``X``, ``Y``, ``Z`` (N-vectors) and
    ``TRIV`` ((F, 3), 1-based);
  - SHREC'19 style: a struct (e.g. ``Shape_df`` or ``shape``) with fields ``VERT`` ((N, 3)) and
    ``TRIV`` ((F, 3), 1-based), or top-level variables ``VERT`` and ``TRIV`` (or ``X``, ``Y``, ``Z``,
    ``TRIV``).

  The first variable holding one of these layouts is used; when several do, the error lists them and
  ``variable=`` picks one. ``TRIV`` is always 1-based: a 0 in it is an error (never guessed away).
  MATLAB v7.3 files are HDF5 and are not read (re-save them with ``save(..., '-v7')``).

`save_mesh` writes OFF and OBJ as text with 17 significant digits, PLY as binary little-endian with
``double`` coordinates (trimesh's own PLY writer stores float32), and ``.mat`` in the TOSCA layout,
so that ``load_mesh(save_mesh(m, p)) == m`` exactly.

Correspondences
---------------
* `load_vts`: TOSCA/SCAPE/FAUST-style ``.vts`` landmark files, one 1-based vertex index per line
  (``tosca_isometric_5k/vtx_5k/corres/<name>.vts``: 5,000 lines; line ``i`` of two shapes of a class
  are corresponding vertices).
* `load_vertex_map`: one vertex index per line; line ``i`` is the vertex of the *target* shape matched
  to vertex ``i`` of the *source* shape. SHREC'19 ``i_j.txt`` files are 1-based (the default,
  ``base=1``). The pyFM example maps (``pyfm_examples/camel_gallop/maps/<i>_to_<j>`` and
  ``pyfm_examples/lion2cat``) are **0-based**: checked on the data, ``1_to_3`` has 4,999 lines
  (= vertices of camel-gallop-01) with values 0..5001 (camel-gallop-03 has 5,002 vertices), and
  ``lion2cat`` has 5,000 lines (lion-00) with values 0..7206 (cat-00 has 7,207); read them with
  ``base=0``. A 0 in a file read with ``base=1`` is an error that suggests ``base=0``.

All results are 0-based int64. ``n_vertices=`` checks the range against the mesh the indices refer to.

Errors: a missing file raises `FileNotFoundError` (an `OSError`) naming the path; an unknown extension
raises `ValueError` listing the supported ones; malformed content raises `ValueError` naming the file
and the problem. Mesh warnings (`MeshWarning`) raised while loading are re-issued with the file name.
"""
from __future__ import annotations

import io
import os
import re
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike

from wpot.mesh import Mesh, MeshWarning, _listed

__all__ = [
    "MESH_FORMATS",
    "load_mesh",
    "save_mesh",
    "load_vts",
    "save_vts",
    "load_vertex_map",
    "save_vertex_map",
]

#: file extensions `load_mesh` reads (`save_mesh` writes all but ".stl")
MESH_FORMATS = (".off", ".ply", ".obj", ".stl", ".mat")

PathLike = str | os.PathLike


# ---------------------------------------------------------------------------------------------- helpers
class _Malformed(ValueError):
    """Internal: a problem found while parsing (the message is prefixed with the file later)."""


def _read_bytes(path: PathLike) -> tuple[Path, bytes]:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(2, "No such file", str(p))
    return p, p.read_bytes()  # IsADirectoryError / PermissionError are OSErrors too


def _suffix(p: Path) -> str:
    ext = p.suffix.lower()
    if ext not in MESH_FORMATS:
        raise ValueError(
            f"{p}: unsupported mesh file extension {p.suffix!r}; supported: {', '.join(MESH_FORMATS)}"
        )
    return ext


def _guarded(p: Path, what: str, fn: Callable[[], Any]) -> Any:
    """Run a parser; turn whatever a malformed file makes it raise into a ValueError naming the file."""
    try:
        return fn()
    except OSError:
        raise
    except _Malformed as exc:
        raise ValueError(f"{p}: malformed {what} file: {exc}") from None
    except Exception as exc:  # third-party parsers raise anything (IndexError, struct.error, ...)
        raise ValueError(f"{p}: malformed {what} file ({type(exc).__name__}: {exc})") from None


def _int_token(tok: str, where: str) -> int:
    try:
        return int(tok)
    except ValueError:
        raise _Malformed(f"{where}: expected an integer, got {tok[:40]!r}") from None


def _strip_comments(text: str) -> list[str]:
    """Non-empty lines with ``#`` comments removed (as trimesh's OFF reader does)."""
    if "#" not in text:
        return [ln for ln in (x.strip() for x in text.splitlines()) if ln]
    out = []
    for ln in text.splitlines():
        ln = ln.split("#", 1)[0].strip()
        if ln:
            out.append(ln)
    return out


def _decode(data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _reject_polygons(arity: np.ndarray) -> None:
    bad = np.nonzero(arity != 3)[0]
    if bad.size:
        sizes = sorted(set(int(a) for a in arity[bad]))
        raise _Malformed(
            f"{bad.size} faces are not triangles (vertex counts {sizes[:_MAX_SIZES]}): faces {_listed(bad)} "
            "(0-based, in file order); wpot reads triangle meshes only: triangulate them first "
            "(trimesh would have done so silently, changing the face list)"
        )


_MAX_SIZES = 5


# -------------------------------------------------------------------------------------------------- OFF
_OFF_HEAD = re.compile(r"^(ST)?(C)?(N)?(4)?n?OFF(?:\s+(.*))?$")


def _scan_off(text: str) -> tuple[int, list[list[int]] | np.ndarray]:
    """Declared vertex count and each face's 0-based vertex list, from the OFF text."""
    lines = _strip_comments(text)
    if not lines:
        raise _Malformed("the file is empty")
    m = _OFF_HEAD.match(lines[0])
    if m is None:
        raise _Malformed(f"the first line must be the OFF keyword, got {lines[0][:40]!r}")
    if m.group(4):
        raise _Malformed("4OFF (4-D vertices) is not supported")
    rest = m.group(5)
    pos = 1
    if rest is None:
        if len(lines) < 2:
            raise _Malformed("missing the line with vertex and face counts")
        rest = lines[1]
        pos = 2
    counts = rest.split()
    if len(counts) < 2:
        raise _Malformed(f"the counts line needs 'n_vertices n_faces [n_edges]', got {rest[:40]!r}")
    nv = _int_token(counts[0], "vertex count")
    nf = _int_token(counts[1], "face count")
    if nv < 0 or nf < 0:
        raise _Malformed(f"negative counts: {nv} vertices, {nf} faces")
    body = lines[pos:]
    if len(body) < nv + nf:
        raise _Malformed(
            f"the header declares {nv} vertices and {nf} faces ({nv + nf} lines) but only "
            f"{len(body)} lines follow: the file is truncated"
        )
    for i in range(nv):
        if len(body[i].split()) < 3:
            raise _Malformed(f"vertex {i} has fewer than 3 coordinates: {body[i][:60]!r}")
    # fast path: every face line is "3 a b c"
    try:
        tok = np.array(" ".join(body[nv : nv + nf]).split(), dtype=np.int64)
    except (ValueError, OverflowError):
        tok = np.zeros(0, dtype=np.int64)
    if tok.size == 4 * nf:
        rows = tok.reshape(nf, 4)
        if np.all(rows[:, 0] == 3):
            return nv, np.ascontiguousarray(rows[:, 1:])
    faces = []  # slow path: per line, to name the offending face
    for j in range(nf):
        toks = body[nv + j].split()
        k = _int_token(toks[0], f"face {j}")
        if k < 0 or len(toks) < k + 1:
            raise _Malformed(f"face {j} declares {k} vertices but lists {len(toks) - 1}: {body[nv + j][:60]!r}")
        faces.append([_int_token(t, f"face {j}") for t in toks[1 : k + 1]])
    return nv, faces


def _triangles(faces: list[list[int]] | np.ndarray, nv: int) -> np.ndarray:
    """(F, 3) int64 from per-face vertex lists (or an (F, 3) array), refusing polygons and
    out-of-range indices by name."""
    if isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] == 3:
        f = faces.astype(np.int64, copy=False)
    else:
        _reject_polygons(np.array([len(x) for x in faces], dtype=np.int64))
        f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    bad = np.nonzero(np.any((f < 0) | (f >= nv), axis=1))[0]
    if bad.size:
        raise _Malformed(
            f"{bad.size} faces index vertices outside [0, {nv - 1}] (0-based): faces {_listed(bad)} "
            f"(first: {f[bad[0]].tolist()})"
        )
    return f


def _agree(kind: str, f_scan: np.ndarray, f_trimesh: np.ndarray, nv: int, v: np.ndarray) -> None:
    """trimesh must return exactly the file's vertex count and faces (no silent re-indexing)."""
    if len(v) != nv or f_scan.shape != f_trimesh.shape or not np.array_equal(f_scan, f_trimesh):
        raise _Malformed(
            f"trimesh's {kind} parser returned {len(v)} vertices and {len(f_trimesh)} faces that differ from "
            f"the file's {nv} vertices and {len(f_scan)} faces; refusing a re-indexed mesh"
        )


def _read_off(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    from trimesh.exchange.off import load_off

    nv, faces = _scan_off(_decode(data))
    f = _triangles(faces, nv)
    kw = load_off(io.BytesIO(data))
    v = np.asarray(kw["vertices"], dtype=np.float64).reshape(-1, 3)
    _agree("OFF", f, np.asarray(kw["faces"], dtype=np.int64).reshape(-1, 3), nv, v)
    return v, f


# -------------------------------------------------------------------------------------------------- OBJ
def _scan_obj(text: str) -> tuple[int, list[list[int]], bool]:
    """Number of ``v`` lines, each ``f`` line's 0-based vertex list, and whether relative (negative)
    indices occur (resolved here against the vertices defined so far, as the OBJ format says)."""
    text = text.replace("\\\r\n", "").replace("\\\n", "")  # line continuations, as trimesh does
    nv = 0
    faces = []
    relative = False
    for ln in text.splitlines():
        ln = ln.split("#", 1)[0].strip()
        if ln.startswith("v ") or ln.startswith("v\t"):
            nv += 1
        elif ln.startswith("f ") or ln.startswith("f\t"):
            j = len(faces)
            idx = [_int_token(t.split("/", 1)[0], f"face {j}") for t in ln.split()[1:]]
            relative = relative or any(i < 0 for i in idx)
            faces.append([i - 1 if i > 0 else nv + i if i < 0 else -1 for i in idx])  # OBJ has no index 0
    return nv, faces, relative


def _read_obj(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    from trimesh.exchange.obj import load_obj

    nv, faces, relative = _scan_obj(_decode(data))
    f = _triangles(faces, nv)
    if len(f) == 0:
        return np.zeros((nv, 3)), f  # no faces: Mesh reports an empty mesh
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # trimesh's texture bookkeeping on odd UVs
        out = load_obj(
            io.BytesIO(data),
            maintain_order=True,
            group_material=False,
            skip_materials=True,
            split_objects=False,
            split_groups=False,
        )
    geometry = out.get("geometry", {}) if isinstance(out, dict) else {}
    if not geometry:
        raise _Malformed("trimesh found no mesh in the file")
    parts = list(geometry.values())
    v = np.asarray(parts[0].get("vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    for kw in parts[1:]:  # trimesh splits at 'usemtl'; with maintain_order each part has all vertices
        if not np.array_equal(np.asarray(kw.get("vertices"), dtype=np.float64).reshape(-1, 3), v):
            raise _Malformed(f"trimesh split the file into {len(parts)} meshes with different vertex lists")
    ft = np.concatenate(
        [np.asarray(kw["faces"], dtype=np.int64).reshape(-1, 3) for kw in parts if kw.get("faces") is not None]
        or [np.zeros((0, 3), dtype=np.int64)]
    )
    if relative:
        # trimesh (maintain_order=True) leaves relative indices unresolved: keep the scan's faces and
        # check only the vertex and face counts
        ft = f if len(ft) == len(f) else ft
    elif len(parts) > 1 and ft.shape == f.shape:
        # the parts come grouped by material, not in file order: compare as sets of rows, keep file order
        ft = f if np.array_equal(f[np.lexsort(f.T)], ft[np.lexsort(ft.T)]) else ft
    _agree("OBJ", f, ft, nv, v)
    return v, f


# -------------------------------------------------------------------------------------------------- PLY
_PLY_TYPES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}


def _scan_ply_header(data: bytes) -> None:
    """Refuse headers whose element counts cannot fit in the file (before trimesh allocates for them)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise _Malformed("missing 'ply' magic or 'end_header'")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body_len = len(data) - end - len("end_header")
    binary = None
    need = 0
    elements: list[list[Any]] = []  # [name, count, min_bytes_binary, min_tokens_ascii]
    for ln in header:
        toks = ln.split()
        if not toks:
            continue
        if toks[0] == "format" and len(toks) >= 2:
            binary = toks[1] != "ascii"
        elif toks[0] == "element":
            if len(toks) < 3:
                raise _Malformed(f"bad element line {ln[:60]!r}")
            count = _int_token(toks[2], f"element {toks[1]} count")
            if count < 0:
                raise _Malformed(f"negative element count in {ln[:60]!r}")
            elements.append([toks[1], count, 0, 0])
        elif toks[0] == "property" and elements:
            if len(toks) >= 5 and toks[1] == "list":
                elements[-1][2] += _PLY_TYPES.get(toks[2], 1)
            else:
                elements[-1][2] += _PLY_TYPES.get(toks[1], 1) if len(toks) > 1 else 1
            elements[-1][3] += 1
    if binary is None:
        raise _Malformed("missing 'format' line")
    for _, count, nbytes, ntok in elements:
        need += count * (nbytes if binary else 2 * ntok)
    if need > body_len:
        raise _Malformed(
            f"the header declares elements {[(e[0], e[1]) for e in elements]} needing at least {need} "
            f"bytes but only {body_len} follow: the file is truncated"
        )


def _ply_face_lists(raw: Any) -> Any:
    """The per-face vertex-index lists from trimesh's raw PLY face element."""
    data = raw["data"]
    names = ("vertex_indices", "vertex_index")
    if isinstance(data, dict):
        for n in names:
            if n in data:
                return data[n]
        raise _Malformed(f"face element has no vertex_indices property (has {sorted(data)})")
    if isinstance(data, np.ndarray) and data.dtype.names:
        fields = data.dtype.names
        name = fields[0] if len(fields) == 1 else next((n for n in names if n in fields), None)
        if name is None:
            raise _Malformed(f"face element has no vertex_indices property (has {list(fields)})")
        col = data[name]
        return col["f1"] if col.dtype.names else col
    return data


def _read_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    from trimesh.exchange.ply import load_ply

    _scan_ply_header(data)
    kw = load_ply(io.BytesIO(data), fix_texture=False, skip_materials=True)
    raw = kw.get("metadata", {}).get("_ply_raw", {})
    v = kw.get("vertices")
    v = np.zeros((0, 3)) if v is None else np.asarray(v, dtype=np.float64).reshape(-1, 3)
    face_el = raw.get("face")
    if face_el is None or not face_el.get("length"):
        return v, np.zeros((0, 3), dtype=np.int64)
    lists = _ply_face_lists(face_el)
    if isinstance(lists, np.ndarray) and lists.dtype != object and lists.ndim == 2:
        arity = np.full(len(lists), lists.shape[1], dtype=np.int64)
    else:
        arity = np.array([len(np.atleast_1d(x)) for x in lists], dtype=np.int64)
    _reject_polygons(arity)
    f = np.array([np.asarray(x, dtype=np.int64) for x in lists], dtype=np.int64).reshape(-1, 3)
    nv = int(raw["vertex"]["length"]) if "vertex" in raw else len(v)
    f = _triangles(f, nv)
    _agree("PLY", f, np.asarray(kw.get("faces"), dtype=np.int64).reshape(-1, 3), nv, v)
    return v, f


# -------------------------------------------------------------------------------------------------- STL
def _read_stl(data: bytes) -> tuple[np.ndarray, np.ndarray, int]:
    """Binary or ASCII STL: a soup of facets, each with its own three corners. Corners with identical
    coordinates are welded into one vertex (exact equality, -0.0 == 0.0; no tolerance, which would move
    the geometry), numbered in order of first use; facets whose corners then coincide (zero-area slivers
    that STL writers leave) are dropped and counted. Returns vertices, faces and the number dropped."""
    from trimesh.exchange.stl import load_stl

    kw = load_stl(io.BytesIO(data))
    if "vertices" in kw:
        parts = [kw]
    else:  # several ASCII solids, or nothing recognizable at all
        parts = list((kw.get("geometry") or {}).values())
    parts = [q for q in parts if q.get("vertices") is not None and len(q["vertices"])]
    if not parts:
        raise _Malformed("no facets found (an empty solid, or not an STL file)")
    soup = np.concatenate([np.asarray(q["vertices"], dtype=np.float64)[np.asarray(q["faces"]).reshape(-1)] for q in parts])
    soup = soup.reshape(-1, 3) + 0.0  # -0.0 -> 0.0, so that signed zeros weld
    points, welded = np.unique(soup, axis=0, return_inverse=True)
    f = welded.reshape(-1, 3)
    collapsed = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    f = f[~collapsed]
    used, first = np.unique(f.reshape(-1), return_index=True)
    used = used[np.argsort(first)]  # the vertices of the kept facets, in order of first use
    number = np.empty(len(points), dtype=np.int64)
    number[used] = np.arange(len(used))
    return points[used], number[f], int(collapsed.sum())


# -------------------------------------------------------------------------------------------------- MAT
_TOSCA_FIELDS = ("X", "Y", "Z", "TRIV")
_SHREC_FIELDS = ("VERT", "TRIV")


def _mat_candidates(d: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Variables (name -> field dict) holding a mesh in the TOSCA or SHREC'19 layout."""
    found: dict[str, dict[str, Any]] = {}
    for key, val in d.items():
        if key.startswith("__") or not isinstance(val, np.ndarray) or not val.dtype.names or val.size < 1:
            continue
        rec = val.flat[0]
        fields = {n: rec[n] for n in val.dtype.names}
        if all(k in fields for k in _TOSCA_FIELDS) or all(k in fields for k in _SHREC_FIELDS):
            found[key] = fields
    top = {k: v for k, v in d.items() if not k.startswith("__")}
    if all(k in top for k in _TOSCA_FIELDS) or all(k in top for k in _SHREC_FIELDS):
        found["<top level>"] = top
    return found


def _mat_array(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x)
    while a.dtype == object and a.size == 1:  # MATLAB cells/structs wrap values in 1x1 object arrays
        a = np.asarray(a.flat[0])
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise _Malformed(f"field {name} is not a numeric array (dtype {a.dtype})")
    return a


#: MAT v5 data types scipy reads (miINT8 ... miUINT32, miSINGLE, miDOUBLE, miINT64, miUINT64, miMATRIX,
#: miCOMPRESSED, miUTF8/16/32)
_MAT5_TYPES = frozenset([1, 2, 3, 4, 5, 6, 7, 9, 12, 13, 14, 15, 16, 17, 18])


def _check_mat5_elements(buf: bytes, little: bool, depth: int = 0) -> None:
    """Walk a MAT v5 element stream and refuse unknown data types and sizes past the buffer's end.

    scipy 1.17's ``loadmat`` reads an unknown data type inside a matrix without checking it and crashes the
    interpreter (SIGSEGV, found by benchmarks/fuzz_readers.py); a tag walk before it turns such files into a
    ValueError. Compressed elements are inflated (up to 1 GiB) and walked too; matrices are walked inside."""
    if depth > 32:
        raise _Malformed("MAT elements nested more than 32 deep")
    import struct
    import zlib

    u32 = "<I" if little else ">I"
    pos = 0
    while pos + 8 <= len(buf):
        (first,) = struct.unpack_from(u32, buf, pos)
        if first >> 16:  # small data element: type and size in one word, data in the next 4 bytes
            mdtype, nbytes, start, step = first & 0xFFFF, first >> 16, pos + 4, 8
            if nbytes > 4:
                raise _Malformed(f"small MAT element at byte {pos} declares {nbytes} bytes (at most 4)")
        else:
            mdtype = first
            (nbytes,) = struct.unpack_from(u32, buf, pos + 4)
            start = pos + 8
            step = 8 + (nbytes if mdtype == 15 else (nbytes + 7) // 8 * 8)
        if mdtype not in _MAT5_TYPES:
            raise _Malformed(f"unknown MAT data type {mdtype} at byte {pos}")
        if start + nbytes > len(buf):
            raise _Malformed(f"MAT element at byte {pos} declares {nbytes} bytes but only {len(buf) - start} follow")
        body = buf[start:start + nbytes]
        if mdtype == 15:
            d = zlib.decompressobj()
            try:
                inner = d.decompress(body, 1 << 30)
            except zlib.error as exc:
                raise _Malformed(f"compressed MAT element at byte {pos}: {exc}") from None
            if d.unconsumed_tail:
                raise _Malformed(f"compressed MAT element at byte {pos} inflates past 1 GiB")
            _check_mat5_elements(inner, little, depth + 1)
        elif mdtype == 14:
            _check_mat5_dims(body, little, pos)
            _check_mat5_elements(body, little, depth + 1)
        pos += step


def _check_mat5_dims(body: bytes, little: bool, pos: int) -> None:
    """Refuse a matrix whose dimensions claim more elements than its bytes can hold (scipy would allocate for
    the claim first: benchmarks/fuzz_readers.py found a small file that asked for many GiB). Every element of a
    dense, character, logical, cell or struct array takes at least one byte of the file; sparse arrays
    (class 5) store only their non-zeros and are not checked."""
    import struct

    e = "<" if little else ">"
    if len(body) < 24:
        return  # too short to hold flags and dimensions: scipy's own checks refuse it
    mdtype, nbytes = struct.unpack_from(e + "II", body, 0)
    if mdtype != 6 or nbytes < 4:  # array flags (miUINT32) come first in a well-formed matrix
        return
    mclass = struct.unpack_from(e + "I", body, 8)[0] & 0xFF
    dtype, dbytes = struct.unpack_from(e + "II", body, 16)
    if mclass == 5 or dtype != 5 or dbytes % 4 or 24 + dbytes > len(body):  # dims: miINT32
        return
    dims = struct.unpack_from(e + f"{dbytes // 4}i", body, 24)
    n = 1
    for d in dims:
        if d < 0:
            raise _Malformed(f"MAT matrix at byte {pos} has a negative dimension {dims}")
        n *= d
    if n > len(body):
        raise _Malformed(f"MAT matrix at byte {pos} declares dimensions {dims} ({n} elements) in {len(body)} bytes")


def _read_mat(data: bytes, variable: str | None) -> tuple[np.ndarray, np.ndarray]:
    import scipy.io

    if len(data) >= 128 and data[126:128] in (b"IM", b"MI") and data[124:126] in (b"\x00\x01", b"\x01\x00"):
        _check_mat5_elements(data[128:], little=data[126:128] == b"IM")
    try:
        d = scipy.io.loadmat(io.BytesIO(data), squeeze_me=False, struct_as_record=True)
    except NotImplementedError as exc:
        raise _Malformed(
            f"{exc}. MATLAB v7.3 (HDF5) files are not supported; re-save with save(..., '-v7')"
        ) from None
    found = _mat_candidates(d)
    names = sorted(k for k in d if not k.startswith("__"))
    if variable is not None:
        if variable not in found:
            raise _Malformed(
                f"variable {variable!r} does not hold a mesh (variables with a mesh: {sorted(found)}; "
                f"all variables: {names})"
            )
        fields = found[variable]
    elif not found:
        raise _Malformed(
            "no mesh found: expected a struct with fields X, Y, Z, TRIV (TOSCA) or VERT, TRIV (SHREC'19), "
            f"or such top-level variables; the file has variables {names}"
        )
    elif len(found) > 1:
        raise _Malformed(f"several variables hold a mesh: {sorted(found)}; pick one with variable=")
    else:
        fields = next(iter(found.values()))
    if "VERT" in fields:
        v = _mat_array(fields["VERT"], "VERT").astype(np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise _Malformed(f"VERT must have shape (N, 3), got {v.shape}")
    else:
        cols = [_mat_array(fields[k], k).astype(np.float64).ravel() for k in "XYZ"]
        if not (len(cols[0]) == len(cols[1]) == len(cols[2])):
            raise _Malformed(f"X, Y, Z have different lengths {[len(c) for c in cols]}")
        v = np.column_stack(cols)
    t = _mat_array(fields["TRIV"], "TRIV")
    if t.size == 0:
        t = np.zeros((0, 3))
    if t.ndim != 2 or t.shape[1] != 3:
        raise _Malformed(f"TRIV must have shape (F, 3), got {t.shape}")
    tf = t.astype(np.float64)
    bad = np.nonzero(~np.all(np.isfinite(tf) & (tf == np.round(tf)), axis=1))[0]
    if bad.size:
        raise _Malformed(f"TRIV has non-integer entries in faces {_listed(bad)}")
    if tf.size and tf.min() < 1:
        bad = np.nonzero(np.any(tf < 1, axis=1))[0]
        raise _Malformed(
            f"TRIV has indices below 1 in faces {_listed(bad)} (first: {tf[bad[0]].astype(np.int64).tolist()}); "
            "TRIV is 1-based in TOSCA/SHREC'19 files"
        )
    if tf.size and tf.max() > np.iinfo(np.int64).max // 2:
        raise _Malformed(f"TRIV index {tf.max():g} is too large")
    return v, tf.astype(np.int64) - 1


# ------------------------------------------------------------------------------------------- public API
def load_mesh(path: PathLike, *, warn: bool = True, variable: str | None = None) -> Mesh:
    """Read a triangle mesh, keeping the file's vertex order and count (STL: welded, in order of first use).

    Parameters
    ----------
    path : ``.off``, ``.ply``, ``.obj``, ``.stl`` (welded, see the module docstring) or ``.mat``
        (TOSCA / SHREC'19 layouts)
    warn : emit `MeshWarning` (naming the file) for defects: zero-area triangles, unreferenced
        vertices, non-manifold edges, several connected components.
    variable : ``.mat`` only: the variable that holds the mesh, when the file has several.

    Returns
    -------
    Mesh with ``vertices`` (N, 3) float64 and ``faces`` (F, 3) int64 (0-based), in file order.

    Raises
    ------
    FileNotFoundError : the file does not exist (other `OSError` for unreadable paths).
    ValueError : unknown extension, malformed content, non-triangle faces, or a mesh that fails
        `wpot.mesh.validate` (NaN/inf coordinates, out-of-range faces, empty mesh); the message names
        the file and the problem.
    """
    p = Path(path)
    ext = _suffix(p)
    if variable is not None and ext != ".mat":
        raise ValueError(f"{p}: variable= applies to .mat files only, got {variable!r}")
    p, data = _read_bytes(p)
    readers = {".off": _read_off, ".obj": _read_obj, ".ply": _read_ply}
    fmt = ext[1:].upper()
    if ext == ".mat":
        v, f = _guarded(p, "MATLAB", lambda: _read_mat(data, variable))
    elif ext == ".stl":
        v, f, dropped = _guarded(p, fmt, lambda: _read_stl(data))
        if dropped and warn:
            warnings.warn(f"{p}: dropped {dropped} STL facets whose corners coincide (zero-area slivers)", MeshWarning, stacklevel=2)
    else:
        v, f = _guarded(p, fmt, lambda: readers[ext](data))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MeshWarning)
        try:
            mesh = Mesh(v, f, warn=warn)
        except ValueError as exc:
            raise ValueError(f"{p}: invalid mesh: {exc}") from None
    for w in caught:
        if issubclass(w.category, MeshWarning):
            warnings.warn(f"{p}: {w.message}", MeshWarning, stacklevel=2)
        else:  # pragma: no cover - pass anything else through unchanged
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    mesh._name = str(p)  # later warnings about it (its spectrum, its sampling) name the file too
    return mesh


def _fmt_rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    lines = [prefix + " ".join(fmt % x for x in row) for row in a.tolist()]
    return "\n".join(lines) + "\n"


def save_mesh(mesh: Mesh, path: PathLike) -> Path:
    """Write a mesh so that `load_mesh` reads it back exactly (same vertices, faces and order).

    OFF and OBJ: text, coordinates with 17 significant digits. PLY: binary little-endian, ``double``
    x, y, z and ``int`` vertex indices. ``.mat``: the TOSCA layout (struct ``surface`` with column
    vectors ``X``, ``Y``, ``Z`` and 1-based ``TRIV``), MATLAB v5.

    Returns the path written.
    """
    if not isinstance(mesh, Mesh):
        raise ValueError(f"save_mesh expects a wpot.Mesh, got {type(mesh).__name__}")
    p = Path(path)
    ext = _suffix(p)
    if ext == ".stl":
        raise ValueError(
            f"{p}: wpot reads STL but does not write it: STL keeps float32 corners per facet and no shared "
            "vertices, so the mesh read back would not be this one; write .ply (binary, double) instead"
        )
    v = mesh.vertices
    f = mesh.faces
    if ext == ".off":
        text = f"OFF\n{len(v)} {len(f)} 0\n" + _fmt_rows(v, "", "%.17g") + _fmt_rows(f, "3 ", "%d")
        p.write_text(text)
    elif ext == ".obj":
        text = "# written by wpot\n" + _fmt_rows(v, "v ", "%.17g") + _fmt_rows(f + 1, "f ", "%d")
        p.write_text(text)
    elif ext == ".ply":
        if len(v) > np.iinfo(np.int32).max:
            raise ValueError(f"too many vertices for a PLY with int indices: {len(v)}")
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment written by wpot\n"
            f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        fdt = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
        frec = np.empty(len(f), dtype=fdt)
        frec["n"] = 3
        frec["idx"] = f
        with open(p, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(np.ascontiguousarray(v, dtype="<f8").tobytes())
            fh.write(frec.tobytes())
    else:  # .mat
        import scipy.io

        surface = {
            "X": v[:, :1].copy(),
            "Y": v[:, 1:2].copy(),
            "Z": v[:, 2:3].copy(),
            "TRIV": (f + 1).astype(np.float64),
        }
        scipy.io.savemat(p, {"surface": surface}, do_compression=True)
    return p


def _read_index_file(path: PathLike, what: str, base: int, n_vertices: int | None) -> np.ndarray:
    p, data = _read_bytes(path)

    def parse() -> np.ndarray:
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError as exc:
            raise _Malformed(f"not a text file ({exc})") from None
        lines = text.splitlines()
        while lines and not lines[-1].strip():
            lines.pop()
        out = np.empty(len(lines), dtype=np.int64)
        for i, ln in enumerate(lines):
            toks = ln.split()
            if len(toks) != 1:
                raise _Malformed(f"line {i + 1} must hold exactly one vertex index, got {ln[:60]!r}")
            tok = toks[0]
            try:
                out[i] = int(tok)
            except ValueError:
                try:
                    x = float(tok)
                except ValueError:
                    x = float("nan")
                if not np.isfinite(x) or x != round(x) or abs(x) > 2.0**62:
                    raise _Malformed(f"line {i + 1}: expected an integer vertex index, got {tok[:40]!r}") from None
                out[i] = int(x)
            except OverflowError:
                raise _Malformed(f"line {i + 1}: vertex index {tok[:40]} is too large") from None
        return out

    idx = _guarded(p, what, parse)
    if idx.size == 0:
        raise ValueError(f"{p}: empty {what} file: no vertex indices")
    low = np.nonzero(idx < base)[0]
    if low.size:
        hint = "; the file looks 0-based: pass base=0" if base == 1 and idx[low].min() == 0 else ""
        raise ValueError(
            f"{p}: {low.size} indices below {base} (the file is read as {base}-based) on lines "
            f"{_listed(low + 1)} (first: {int(idx[low[0]])}){hint}"
        )
    idx = idx - base
    if n_vertices is not None:
        high = np.nonzero(idx >= n_vertices)[0]
        if high.size:
            raise ValueError(
                f"{p}: {high.size} indices exceed the mesh's {n_vertices} vertices on lines {_listed(high + 1)} "
                f"(first: {int(idx[high[0]]) + base} in the file, {base}-based)"
            )
    return idx


def load_vts(path: PathLike, *, n_vertices: int | None = None) -> np.ndarray:
    """Read a ``.vts`` landmark file: one 1-based vertex index per line.

    Returns
    -------
    (K,) int64, 0-based vertex indices in file order. With ``n_vertices``, indices beyond the mesh
    raise `ValueError`.
    """
    return _read_index_file(path, "VTS", 1, n_vertices)


def load_vertex_map(path: PathLike, *, base: int = 1, n_vertices: int | None = None) -> np.ndarray:
    """Read a point-to-point map: line ``i`` holds the target vertex matched to source vertex ``i``.

    Parameters
    ----------
    base : index of the first vertex in the file: 1 for SHREC'19 ``i_j.txt`` (default), 0 for the
        pyFM example maps (see the module docstring).
    n_vertices : vertex count of the target mesh, to check the range.

    Returns
    -------
    (N_source,) int64, 0-based target vertex indices.
    """
    if base not in (0, 1):
        raise ValueError(f"base must be 0 or 1, got {base!r}")
    return _read_index_file(path, "vertex map", base, n_vertices)


def _write_index_file(indices: ArrayLike, path: PathLike, base: int) -> Path:
    a = np.asarray(indices)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"indices must be a 1-D integer array, got shape {a.shape} and dtype {a.dtype}")
    if a.size and a.min() < 0:
        raise ValueError(f"indices must be non-negative (0-based), got {_listed(a[a < 0])}")
    p = Path(path)
    p.write_text("".join(f"{int(i) + base}\n" for i in a))
    return p


def save_vts(indices: ArrayLike, path: PathLike) -> Path:
    """Write (K,) 0-based vertex indices as a 1-based ``.vts`` file (inverse of `load_vts`)."""
    return _write_index_file(indices, path, 1)


def save_vertex_map(vertex_map: ArrayLike, path: PathLike, *, base: int = 1) -> Path:
    """Write a (N,) 0-based vertex map, one index per line, ``base``-based (inverse of `load_vertex_map`)."""
    if base not in (0, 1):
        raise ValueError(f"base must be 0 or 1, got {base!r}")
    return _write_index_file(vertex_map, path, base)
