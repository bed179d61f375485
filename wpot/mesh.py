"""The `Mesh` type: an immutable triangle mesh with validation and cached derived quantities.

Validation lives here, in one place (`validate`), and every constructor goes through it:

* errors (`ValueError`, naming the problem and the offending indices): empty mesh, wrong array shapes,
  NaN/inf coordinates, non-integer or out-of-range face indices, faces that repeat a vertex;
* warnings (`MeshWarning`, with counts): zero-area triangles, unreferenced (isolated) vertices,
  non-manifold edges, several connected components.

Nothing is ever re-indexed silently: per-vertex results line up with the input vertices. Repairs happen
only when asked for, through `Mesh.cleaned`, which returns the index map.
"""
from __future__ import annotations

import hashlib
import warnings
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from numpy.typing import ArrayLike

__all__ = ["Mesh", "MeshWarning", "REPAIR_MODES", "cut", "edge_paths", "repair_mesh", "repair_mode", "repair_setting", "signed_volume", "boundary_caps", "boundary_rings", "validate", "winding"]

#: a triangle whose area is below this fraction of (mean edge length)^2 counts as degenerate
DEGENERATE_AREA_RTOL = 1e-12
_MAX_LISTED = 10


class MeshWarning(UserWarning):
    """A mesh is usable but has a defect that may spoil results (see `Mesh.cleaned`)."""


def _ro(a: np.ndarray) -> np.ndarray:
    """Mark a cached array read-only (a cache a caller could edit in place would be a silent corruption)."""
    a.setflags(write=False)
    return a


def _listed(idx: np.ndarray) -> str:
    idx = np.asarray(idx).ravel()
    head = ", ".join(str(int(i)) for i in idx[:_MAX_LISTED])
    return f"[{head}{', ...' if idx.size > _MAX_LISTED else ''}]"


def _as_vertices(vertices: ArrayLike) -> np.ndarray:
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"vertices must be a numeric (N, 3) array, got {type(vertices).__name__}: {exc}") from None
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {v.shape}")
    return v


def _as_faces(faces: ArrayLike) -> np.ndarray:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(
            f"faces must have shape (F, 3) (triangles only), got {f.shape}; "
            "triangulate polygonal faces before building a Mesh"
        )
    if f.size and not np.issubdtype(f.dtype, np.integer):
        if not np.issubdtype(f.dtype, np.floating) or not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            bad = np.unique(np.nonzero(~np.isfinite(f) | (f != np.round(f)))[0]) if np.issubdtype(f.dtype, np.floating) else np.arange(len(f))
            raise ValueError(f"face indices must be integers; non-integer entries in faces {_listed(bad)}")
    return f.astype(np.int64)


def validate(vertices: np.ndarray, faces: np.ndarray, *, warn: bool = True, name: str | None = None) -> None:
    """Check a mesh; raise `ValueError` for fatal problems and warn (`MeshWarning`) for defects.

    Parameters
    ----------
    vertices : (N, 3) float64
    faces : (F, 3) int64, 0-based
    warn : emit `MeshWarning` for degenerate triangles, isolated vertices, non-manifold edges and
        several connected components.
    name : the mesh's name (`Mesh.name`), which starts the warning's message when given.
    """
    n = len(vertices)
    if n == 0:
        raise ValueError("empty mesh: no vertices")
    if len(faces) == 0:
        raise ValueError(f"empty mesh: no faces (got {n} vertices and 0 triangles)")
    bad_v = np.nonzero(~np.all(np.isfinite(vertices), axis=1))[0]
    if bad_v.size:
        raise ValueError(f"{bad_v.size} vertices have NaN or infinite coordinates: vertices {_listed(bad_v)}")
    bad_f = np.nonzero(np.any((faces < 0) | (faces >= n), axis=1))[0]
    if bad_f.size:
        raise ValueError(
            f"{bad_f.size} faces index vertices outside [0, {n - 1}]: faces {_listed(bad_f)} "
            f"(first: {faces[bad_f[0]].tolist()})"
        )
    rep = np.nonzero((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2]))[0]
    if rep.size:
        raise ValueError(
            f"{rep.size} faces repeat a vertex (not triangles): faces {_listed(rep)} "
            f"(first: {faces[rep[0]].tolist()})"
        )
    if not warn:
        return
    m = Mesh._unchecked(vertices, faces)
    problems = []
    degenerate = m.degenerate_faces
    if degenerate.size:
        problems.append(f"{degenerate.size} zero-area triangles (faces {_listed(degenerate)})")
    isolated = m.unreferenced_vertices
    if isolated.size:
        problems.append(f"{isolated.size} unreferenced vertices (vertices {_listed(isolated)})")
    nm = m.nonmanifold_edges
    if len(nm):
        problems.append(f"{len(nm)} non-manifold edges (shared by 3+ triangles, e.g. {nm[0].tolist()})")
    wound = m.misoriented_faces
    if wound.size:
        problems.append(f"{wound.size} triangles wound against their neighbours (faces {_listed(wound)}), so its "
                        "outside and left from right cannot be read")
    ncomp = m.n_components
    if ncomp > 1:
        sizes = np.bincount(m.component_labels[m.referenced])
        problems.append(f"{ncomp} connected components (vertex counts {sorted(sizes.tolist(), reverse=True)[:_MAX_LISTED]})")
    if problems:
        fixable = degenerate.size or isolated.size or ncomp > 1 or wound.size
        advice = (
            " Mesh.cleaned() removes zero-area triangles and unreferenced vertices, rewinds the triangles wound "
            "against their neighbours "
            "(keep_largest_component=True drops the smaller components) and returns the index map."
            if fixable
            else ""
        )
        if len(nm):
            advice += " Non-manifold edges are not repaired by Mesh.cleaned()."
        warnings.warn(
            named(name, "mesh defects: " + "; ".join(problems) + ". Results near these may be unreliable." + advice),
            MeshWarning,
            stacklevel=3,
        )


class Mesh:
    """An immutable triangle mesh.

    Parameters
    ----------
    vertices : (N, 3) array-like, converted to float64
    faces : (F, 3) array-like of 0-based vertex indices, converted to int64
    validate : run `validate` (errors always; warnings when ``warn`` is true). Default True.
    warn : emit `MeshWarning` for defects (default True).
    name : what the mesh is called in warnings about it (`name`), e.g. its file's path; None: nothing.

    Derived quantities (edges, edge lengths, areas, normals, one-ring adjacency, boundary edges,
    components) are computed on first use and cached. The arrays are read-only.
    """

    __slots__ = ("_vertices", "_faces", "__dict__")

    def __init__(self, vertices: ArrayLike, faces: ArrayLike, *, warn: bool = True, name: str | None = None) -> None:
        v = _as_vertices(vertices).copy()
        f = _as_faces(faces).copy()
        name = None if name is None else str(name)
        validate(v, f, warn=warn, name=name)
        v.setflags(write=False)
        f.setflags(write=False)
        self._vertices = v
        self._faces = f
        self._name = name

    @classmethod
    def _unchecked(cls, vertices: np.ndarray, faces: np.ndarray) -> "Mesh":
        m = cls.__new__(cls)
        m._vertices = vertices
        m._faces = faces
        return m

    # ------------------------------------------------------------------ basics
    @property
    def vertices(self) -> np.ndarray:
        """(N, 3) float64, read-only."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) int64, 0-based, read-only."""
        return self._faces

    @property
    def name(self) -> str | None:
        """What warnings about this mesh call it (`wpot.load_mesh` gives its file's path), or None. Not part of its
        content: equality and `fingerprint` ignore it. `transformed` and `cleaned` keep it."""
        return self.__dict__.get("_name")

    @property
    def n_vertices(self) -> int:
        return len(self._vertices)

    @property
    def n_faces(self) -> int:
        return len(self._faces)

    def __len__(self) -> int:
        return self.n_vertices

    def __repr__(self) -> str:
        return f"Mesh(n_vertices={self.n_vertices}, n_faces={self.n_faces})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Mesh):
            return NotImplemented
        return np.array_equal(self._vertices, other._vertices) and np.array_equal(self._faces, other._faces)

    def __hash__(self) -> int:
        return hash(self.fingerprint)

    @cached_property
    def fingerprint(self) -> str:
        """SHA-1 of the vertex and face bytes: a content key for caches."""
        h = hashlib.sha1()
        h.update(np.ascontiguousarray(self._vertices, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self._faces, dtype="<i8").tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------- geometry
    @cached_property
    def _face_cross(self) -> np.ndarray:
        v = self._vertices
        f = self._faces
        return _ro(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]))

    @cached_property
    def face_areas(self) -> np.ndarray:
        """(F,) float64 triangle areas."""
        return _ro(0.5 * np.linalg.norm(self._face_cross, axis=1))

    @property
    def area(self) -> float:
        """Total surface area."""
        return float(self.face_areas.sum())

    @cached_property
    def vertex_areas(self) -> np.ndarray:
        """(N,) float64 barycentric vertex areas: a third of the area of each triangle a vertex is in (they sum to
        `area`; an unreferenced vertex has 0)."""
        return _ro(np.bincount(self._faces.ravel(), np.repeat(self.face_areas / 3.0, 3), minlength=self.n_vertices))

    @cached_property
    def voronoi_areas(self) -> np.ndarray:
        """(N,) float64 Voronoi vertex areas: `wpot.spectral.laplace_beltrami`'s mass matrix's diagonal."""
        return _ro(_voronoi_areas(self._vertices, self._faces))

    @cached_property
    def _winding(self) -> int:  # `winding`, kept: the map code reads it for every pair
        return _winding(self)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(F, 3) unit normals (right-hand rule on the face order); zero for degenerate faces."""
        c = self._face_cross
        nrm = np.linalg.norm(c, axis=1, keepdims=True)
        return _ro(np.divide(c, nrm, out=np.zeros_like(c), where=nrm > 0))

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """(N, 3) area-weighted unit vertex normals; zero where undefined (isolated vertices)."""
        acc = np.zeros_like(self._vertices)
        for k in range(3):
            np.add.at(acc, self._faces[:, k], self._face_cross)
        nrm = np.linalg.norm(acc, axis=1, keepdims=True)
        return _ro(np.divide(acc, nrm, out=np.zeros_like(acc), where=nrm > 0))

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) int64 unique undirected edges, sorted so that ``edges[:, 0] < edges[:, 1]``."""
        return self._edge_face_count[0]

    @cached_property
    def _half_edges(self) -> np.ndarray:
        f = self._faces
        return _ro(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]))

    @cached_property
    def _edge_face_count(self) -> tuple[np.ndarray, np.ndarray]:
        """Unique undirected edges (sorted rows, lexicographic order) and how many faces use each."""
        h = np.sort(self._half_edges, axis=1)
        n = np.int64(max(self.n_vertices, 1))
        keys, counts = np.unique(h[:, 0] * n + h[:, 1], return_counts=True)  # 1-D unique: much faster
        und = np.column_stack([keys // n, keys % n])
        return _ro(und), _ro(counts)

    @cached_property
    def edge_lengths(self) -> np.ndarray:
        """(E,) float64 lengths of `edges`."""
        e = self.edges
        return _ro(np.linalg.norm(self._vertices[e[:, 0]] - self._vertices[e[:, 1]], axis=1))

    @cached_property
    def mean_edge_length(self) -> float:
        return float(self.edge_lengths.mean())

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        """(B, 2) edges used by exactly one triangle."""
        und, counts = self._edge_face_count
        return _ro(und[counts == 1])

    @cached_property
    def nonmanifold_edges(self) -> np.ndarray:
        """(K, 2) edges used by three or more triangles."""
        und, counts = self._edge_face_count
        return _ro(und[counts > 2])

    @cached_property
    def misoriented_faces(self) -> np.ndarray:
        """(K,) int64 faces wound against their neighbours: the fewest (by area) whose flip makes each surface's
        winding consistent (every edge of two triangles traversed once each way; edges of three or more do not
        take part). Empty for a consistently wound mesh; a Möbius band keeps the faces it cannot fix."""
        return _ro(_misoriented(self._half_edges, self.face_areas, self.n_vertices))

    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        """(N, N) symmetric CSR vertex adjacency (one-ring), entries 1."""
        return _edge_matrix(self, np.ones(len(self.edges)))

    @cached_property
    def edge_graph(self) -> sp.csr_matrix:
        """(N, N) symmetric CSR graph of the edges weighted by their lengths, for shortest paths along the
        surface (`scipy.sparse.csgraph`). A zero-length edge gets the smallest positive float instead, since
        csgraph reads 0 as no edge."""
        return _edge_matrix(self, np.maximum(self.edge_lengths, np.finfo(float).tiny))

    def one_ring(self, i: int) -> np.ndarray:
        """Indices of the vertices sharing an edge with vertex ``i`` (sorted, read-only)."""
        n = self.n_vertices
        if not isinstance(i, (int, np.integer)) or isinstance(i, bool) or not -n <= i < n:
            raise ValueError(f"vertex index must be an integer in [-{n}, {n - 1}], got {i!r}")
        i = int(i) % n
        a = self.adjacency
        ring = a.indices[a.indptr[i] : a.indptr[i + 1]].view()
        ring.setflags(write=False)
        return ring

    @cached_property
    def one_ring_mean_edge_length(self) -> np.ndarray:
        """(N,) mean length of the edges at each vertex (paper Eq. 1, D(v)); NaN for isolated vertices."""
        e = self.edges
        n = self.n_vertices
        tot = np.bincount(e[:, 0], self.edge_lengths, n) + np.bincount(e[:, 1], self.edge_lengths, n)
        deg = np.bincount(e[:, 0], minlength=n) + np.bincount(e[:, 1], minlength=n)
        with np.errstate(invalid="ignore", divide="ignore"):
            return _ro(tot / deg)

    @cached_property
    def referenced(self) -> np.ndarray:
        """(N,) bool: vertex used by at least one face."""
        r = np.zeros(self.n_vertices, dtype=bool)
        r[self._faces.ravel()] = True
        return _ro(r)

    @property
    def unreferenced_vertices(self) -> np.ndarray:
        return np.nonzero(~self.referenced)[0]

    @cached_property
    def degenerate_faces(self) -> np.ndarray:
        """Indices of triangles with (numerically) zero area."""
        scale = self.mean_edge_length ** 2
        return _ro(np.nonzero(self.face_areas <= DEGENERATE_AREA_RTOL * max(scale, np.finfo(float).tiny))[0])

    @cached_property
    def component_labels(self) -> np.ndarray:
        """(N,) connected-component label per vertex (isolated vertices get their own label)."""
        _, labels = sp.csgraph.connected_components(self.adjacency, directed=False)
        return _ro(labels)

    @cached_property
    def n_components(self) -> int:
        """Number of connected components among referenced vertices."""
        return int(np.unique(self.component_labels[self.referenced]).size)

    @cached_property
    def bounding_box_diagonal(self) -> float:
        return float(np.linalg.norm(self._vertices.max(0) - self._vertices.min(0)))

    # ------------------------------------------------------------- editing
    def transformed(self, rotation: ArrayLike | None = None, translation: ArrayLike | None = None, scale: float = 1.0) -> "Mesh":
        """A new mesh with vertices ``scale * vertices @ rotation.T + translation`` (same faces)."""
        v = self._vertices * float(scale)
        if rotation is not None:
            r = np.asarray(rotation, dtype=np.float64)
            if r.shape != (3, 3):
                raise ValueError(f"rotation must have shape (3, 3), got {r.shape}")
            v = v @ r.T
        if translation is not None:
            v = v + np.asarray(translation, dtype=np.float64).reshape(1, 3)
        return Mesh(v, self._faces, warn=False, name=self.name)

    def relabelled(self, permutation: ArrayLike) -> "Mesh":
        """A new mesh whose vertex ``i`` is this mesh's vertex ``permutation[i]``."""
        p = np.asarray(permutation, dtype=np.int64)
        if p.shape != (self.n_vertices,) or not np.array_equal(np.sort(p), np.arange(self.n_vertices)):
            raise ValueError(f"permutation must be a permutation of range({self.n_vertices}), got shape {p.shape}")
        inv = np.empty_like(p)
        inv[p] = np.arange(len(p))
        return Mesh(self._vertices[p], inv[self._faces], warn=False)

    def cleaned(self, *, keep_largest_component: bool = False) -> tuple["Mesh", np.ndarray]:
        """Repair the defects that `validate` warns about, and say how vertices moved.

        Removes zero-area and duplicate triangles, then unreferenced vertices; optionally keeps only
        the largest connected component; rewinds the triangles wound against their neighbours
        (`misoriented_faces`). Non-manifold edges are reported, not repaired.

        Returns
        -------
        mesh : the repaired mesh
        index_map : (N',) int64, ``index_map[i]`` is the index in this mesh of the new vertex ``i``.
        """
        f = self._faces
        keep = np.ones(len(f), dtype=bool)
        keep[self.degenerate_faces] = False
        _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        dup = np.ones(len(f), dtype=bool)
        dup[first] = False
        keep &= ~dup
        f = f[keep]
        if len(f) == 0:
            raise ValueError("cleaning removed every triangle: all faces are degenerate")
        used = np.zeros(self.n_vertices, dtype=bool)
        used[f.ravel()] = True
        if keep_largest_component:
            sub = Mesh._unchecked(self._vertices, f)
            labels = sub.component_labels
            counts = np.bincount(labels[used])
            used &= labels == np.argmax(counts)
            f = f[used[f].all(axis=1)]
        wound = Mesh._unchecked(self._vertices, f).misoriented_faces
        if wound.size:
            f = f.copy()
            f[wound] = f[wound][:, [0, 2, 1]]
        return _reindex(self._vertices, f, used, self.name)


def _misoriented(half: np.ndarray, areas: np.ndarray, n_vertices: int) -> np.ndarray:
    """`Mesh.misoriented_faces` from the (3F, 2) half-edges (face k's edges at rows k, F + k, 2F + k) and the (F,)
    face areas."""
    n_f = len(areas)
    n = np.int64(max(n_vertices, 1))
    directed = half[:, 0].astype(np.int64) * n + half[:, 1]
    if np.unique(directed).size == directed.size:  # no edge traversed twice one way: consistent, manifold
        return np.empty(0, dtype=np.int64)
    face = np.tile(np.arange(n_f), 3)
    lo, hi = np.minimum(half[:, 0], half[:, 1]), np.maximum(half[:, 0], half[:, 1])
    order = np.argsort(lo * n + hi, kind="stable")
    _, first, counts = np.unique((lo * n + hi)[order], return_index=True, return_counts=True)
    pairs = first[counts == 2]
    a, b = order[pairs], order[pairs + 1]
    fa, fb = face[a], face[b]
    # two faces agree when they traverse their shared edge in opposite directions
    agree = (half[a, 0] < half[a, 1]) != (half[b, 0] < half[b, 1])
    # node k: face k as it is; node F + k: face k flipped; an agreeing pair links like states, else unlike
    rows = np.r_[fa, fa + n_f]
    cols = np.r_[np.where(agree, fb, fb + n_f), np.where(agree, fb + n_f, fb)]
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n_f, 2 * n_f))
    n_lab, lab = connected_components(graph, directed=False)
    keep, flip = lab[:n_f], lab[n_f:]
    # choosing the states of label c costs the area of the faces flipped in them
    cost = np.bincount(flip, weights=areas + 1e-300, minlength=n_lab)
    return np.nonzero((keep != flip) & (cost[flip] < cost[keep]))[0].astype(np.int64)


def named(name: str | None, message: str) -> str:
    """``message`` about a mesh, started by its name when it has one (``"cat0.off: mesh defects: ..."``)."""
    return message if not name else f"{name}: {message}"


def _reindex(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray, name: str | None = None
             ) -> tuple[Mesh, np.ndarray]:
    index_map = np.nonzero(keep)[0]
    new_of_old = np.full(len(vertices), -1, dtype=np.int64)
    new_of_old[index_map] = np.arange(index_map.size)
    return Mesh(vertices[index_map], new_of_old[faces], name=name), index_map


def cut(mesh: Mesh, vertex_mask: ArrayLike) -> tuple[Mesh, np.ndarray]:
    """Extract the part of ``mesh`` spanned by the masked vertices (a partial shape).

    Keeps the triangles whose three vertices are all in the mask, then the vertices those triangles
    use (mask vertices left without a triangle are dropped).

    Parameters
    ----------
    mesh : the full shape
    vertex_mask : (N,) bool, or an integer array of vertex indices

    Returns
    -------
    submesh : the partial shape
    index_map : (N_sub,) int64, ``index_map[i]`` is the vertex of ``mesh`` that submesh vertex ``i`` came
        from: the ground-truth map from the part back into the full shape.
    """
    m = np.asarray(vertex_mask)
    if m.dtype == bool:
        if m.shape != (mesh.n_vertices,):
            raise ValueError(f"vertex_mask must have shape ({mesh.n_vertices},), got {m.shape}")
        mask = m
    else:
        if m.size and not np.issubdtype(m.dtype, np.integer):
            raise ValueError(f"vertex_mask must be boolean or integer indices, got dtype {m.dtype}")
        idx = m.astype(np.int64).ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= mesh.n_vertices):
            raise ValueError(f"vertex indices out of range [0, {mesh.n_vertices - 1}]: {_listed(idx[(idx < 0) | (idx >= mesh.n_vertices)])}")
        mask = np.zeros(mesh.n_vertices, dtype=bool)
        mask[idx] = True
    faces = mesh.faces[mask[mesh.faces].all(axis=1)]
    if len(faces) == 0:
        raise ValueError(f"cut keeps no triangle: the {int(mask.sum())} selected vertices span no face")
    used = np.zeros(mesh.n_vertices, dtype=bool)
    used[faces.ravel()] = True
    return _reindex(mesh.vertices, faces, used)


REPAIR_MODES = ("none", "defects", "largest")


def repair_mode(repair: bool | str | None) -> str:
    """``repair`` as one of `REPAIR_MODES`: False or None is "none", True is "defects"."""
    if repair is None or repair is False:
        return "none"
    if repair is True:
        return "defects"
    if isinstance(repair, str) and repair in REPAIR_MODES:
        return repair
    raise ValueError(f"repair must be True, False or one of {', '.join(map(repr, REPAIR_MODES))}, got {repair!r}")


def repair_setting(repair: bool | str | None) -> bool | str:
    """``repair`` as a run stores it and a saved comparison records it: False, True or "largest" (booleans for
    the first two, so that every stored run reads the same way)."""
    mode = repair_mode(repair)
    return {"none": False, "defects": True}.get(mode, mode)


def repair_mesh(mesh: Mesh, mode: bool | str = "defects") -> tuple[Mesh, np.ndarray, str]:
    """`Mesh.cleaned` with an account of what it removed (``mode``: `repair_mode`; "none" returns the mesh).

    Returns
    -------
    mesh, index_map : as `Mesh.cleaned` (``index_map[i]`` is the input index of the repaired mesh's vertex i)
    removed : what was removed or mended, e.g. ``"1 zero-area triangle, 2 unreferenced vertices"``, ``"2 smaller
        components (58 vertices)"`` or ``"3 triangles rewound"``; "" when nothing was
    """
    mode = repair_mode(mode)
    if mode == "none":
        return mesh, np.arange(mesh.n_vertices, dtype=np.int64), ""
    with warnings.catch_warnings():
        if mode == "largest":  # its components are about to go: no MeshWarning about them
            warnings.simplefilter("ignore", MeshWarning)
        fixed, index_map = mesh.cleaned()
    n_degenerate = int(mesh.degenerate_faces.size)
    counts = [
        (n_degenerate, "zero-area triangle", "zero-area triangles"),
        (mesh.n_faces - fixed.n_faces - n_degenerate, "duplicate triangle", "duplicate triangles"),
        (mesh.n_vertices - fixed.n_vertices, "unreferenced vertex", "unreferenced vertices"),
    ]
    removed = [f"{n} {one if n == 1 else many}" for n, one, many in counts if n > 0]
    n_wound = int(mesh.misoriented_faces.size)  # `Mesh.cleaned` rewound them
    if n_wound:
        removed.append(f"{n_wound} triangle{'s' if n_wound > 1 else ''} rewound")
    if mode == "largest" and fixed.n_components > 1:
        n_pieces, n_before = fixed.n_components - 1, fixed.n_vertices
        fixed, inner = fixed.cleaned(keep_largest_component=True)
        index_map = index_map[inner]
        removed.append(f"{n_pieces} smaller component{'s' if n_pieces > 1 else ''} "
                       f"({n_before - fixed.n_vertices} vertices)")
    return fixed, index_map, ", ".join(removed)


# ----------------------------------------------------------------------------- orientation of the surface
def boundary_caps(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The caps that close an open surface: each boundary loop fanned to the loop's own centroid (a fan to one
    common point, the cone the surface spans from its centroid, reads a bent open limb inside out).

    Returns
    -------
    centres : (L, 3) float64, one centroid per boundary loop (L = 0 for a closed surface)
    faces : (B, 3) int64, one cap triangle per boundary edge, indexing ``vstack([mesh.vertices, centres])``
        (the centre of loop l is vertex N + l), wound as the surface's own triangles: each runs its boundary
        edge the other way, as a neighbour face would.
    """
    half = mesh._half_edges
    key = np.sort(half, axis=1)
    n = np.int64(max(mesh.n_vertices, 1))
    _, inv, cnt = np.unique(key[:, 0] * n + key[:, 1], return_inverse=True, return_counts=True)
    border = half[cnt[inv] == 1]  # boundary half-edges, in their face's direction
    if not len(border):
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    g = sp.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(int(n), int(n)))
    # each boundary loop is a connected component of the boundary edges (the other vertices are singletons)
    _, loop = np.unique(connected_components(g, directed=False)[1][border[:, 0]], return_inverse=True)
    centres = np.zeros((int(loop.max()) + 1, 3))
    np.add.at(centres, loop, mesh.vertices[border[:, 0]])
    centres /= np.bincount(loop)[:, None]
    return centres, np.stack([mesh.n_vertices + loop, border[:, 1], border[:, 0]], axis=1).astype(np.int64)


def signed_volume(mesh: Mesh) -> float:
    """The volume the surface encloses, signed by its winding; an open surface is first closed by its
    `boundary_caps`."""
    centres, caps = boundary_caps(mesh)
    v = np.concatenate([mesh.vertices, centres])
    v = v - mesh.vertices.mean(axis=0)
    f = np.concatenate([mesh.faces, caps])
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()) / 6.0


#: why the outside of a surface whose `winding` is 0 cannot be read, for messages about it
NO_OUTSIDE = "encloses no volume to tell its outside from its inside (an open or flat surface)"


def winding(mesh: Mesh) -> int:
    """+1 when the faces wind counter-clockwise about the outward normal (positive enclosed volume), -1 when
    they wind the other way, 0 when that cannot be told (the signed volume is below 1 % of what a sphere of the
    same area encloses: a flat or nearly flat patch). An open surface (a scan, a cap, a cut limb) reads as the
    closed surface its boundary loops' caps make (`signed_volume`)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    return mesh._winding


def edge_paths(mesh: Mesh, sources, *, limit: float = np.inf, min_only: bool = False) -> np.ndarray:
    """Shortest-path lengths along ``mesh``'s edges (Dijkstra on `Mesh.edge_graph`) from ``sources`` to every
    vertex: (len(sources), N), or (N,) for a single source or with ``min_only`` (to the nearest source); inf beyond
    ``limit``. The graph is symmetric, so it is searched as a directed one: the same lengths, without
    `scipy.sparse.csgraph` adding its transpose at every call."""
    from scipy.sparse.csgraph import dijkstra

    return dijkstra(mesh.edge_graph, directed=True, indices=sources, limit=limit, min_only=min_only)


def boundary_rings(mesh: Mesh) -> np.ndarray:
    """(N,) float64, the number of edges from each vertex to the nearest vertex of ``mesh``'s boundary (0 on it;
    inf on a component without one): how far a vertex of a part lies from the cut."""
    from scipy.sparse.csgraph import dijkstra

    border = np.unique(mesh.boundary_edges.ravel())
    if border.size == 0:
        return np.full(mesh.n_vertices, np.inf)
    return dijkstra((mesh.adjacency != 0).astype(float), indices=border, unweighted=True, min_only=True)


def _edge_matrix(mesh: Mesh, values: np.ndarray) -> sp.csr_matrix:
    """(N, N) symmetric CSR matrix with ``values[k]`` at both (i, j) and (j, i) of edge k of ``mesh``, indices
    sorted."""
    e = mesh.edges
    n = mesh.n_vertices
    m = sp.coo_matrix((np.r_[values, values], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n)).tocsr()
    m.sort_indices()
    return m


def _voronoi_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """`Mesh.voronoi_areas`: libigl's Voronoi (mixed) mass matrix's diagonal, (N,) float64."""
    import igl  # local import: libigl is a heavy module

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    return np.asarray(igl.massmatrix(v, f, igl.MASSMATRIX_TYPE_VORONOI).diagonal(), dtype=np.float64)


def _winding(mesh: Mesh) -> int:
    """`winding`, computed (`Mesh._winding` keeps it)."""
    vol = signed_volume(mesh)
    # a sphere of the same area encloses area^1.5 / (6 sqrt(pi))
    if abs(vol) < 0.01 * mesh.area ** 1.5 / (6.0 * np.sqrt(np.pi)):
        return 0
    return 1 if vol > 0 else -1
