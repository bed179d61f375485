"""Left from right: the orientation of a vertex map, and a shape's left/right (reflective) symmetry.

WKS, and every intrinsic signature, is blind to orientation: a body and its mirror image have the same
Laplace–Beltrami spectrum and eigenfunctions up to sign, so a WKS transport plan mixes the two sides of a
symmetric shape, and ZoomOut (`wpot.zoomout`) makes the map consistent with one side, on TOSCA the mirror one
in 38 % of the test pairs. Orientation is what tells the two apart, and it is cheap to measure extrinsically:

* `orientation_score`: a map that keeps orientation carries each triangle of A (its vertices in A's
  counter-clockwise order about A's outward normal) onto a triangle of B that is counter-clockwise about B's
  outward normal; a mirror map reverses them. The score is the area-weighted mean of that sign over A's faces,
  in [-1, 1]: near +1 for a good direct map, near -1 for its mirror, near 0 for noise (degenerate images weigh
  nothing). Both meshes' faces must be consistently wound; which way round (outward or inward) is read off the
  sign of the enclosed volume (`winding`).
* `reflection_symmetry`: the self-map that exchanges a shape's left and right. Each vertex is sent to the
  vertex of the most similar WKS signature that is not near it (its mirror image has the same WKS), and
  ZoomOut makes that map consistent; it is kept only when it reverses orientation (score below
  ``-min_score``) and moves the shape (it is not the identity).
* `local_orientation`: the same score around each vertex; a ZoomOut map is often mirrored on a symmetric
  part only (both legs), where it is negative.
* `keep_orientation`: the vertices where the map is mirrored are sent where the map sends their mirror
  images (A's symmetry, else B's), the result is refined (ZoomOut), and the better-scoring map is returned.

The symmetry is cached per mesh content (memory, and disk under ``$WPOT_CACHE_DIR``), so an all-against-all
detects it once per shape.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from wpot._validate import integer_at_least, one_of, vertex_map
from wpot.cache import Cache
from wpot.mesh import Mesh

__all__ = ["orientation_score", "winding", "Symmetry", "reflection_symmetry", "keep_orientation",
           "OrientationWarning", "local_orientation"]

#: symmetry maps, keyed by mesh content and the detection settings
symmetry_cache = Cache("symmetry", max_entries=128, max_bytes=64 << 20)
#: a self-map counts as a reflection when its orientation score is below -MIN_SCORE
MIN_SCORE = 0.3
#: candidate mirror partners lie at least this far (times sqrt(area)) from the vertex
EXCLUSION = 0.1
#: `local_orientation`'s neighbourhood, times sqrt(area)
LOCAL_RADIUS = 0.1
#: ZoomOut's last resolution for the symmetry map (`reflection_symmetry`'s ``k_end``). On eight TOSCA 5k
#: shapes the map's orientation score was -0.28 to -0.96 at 100 (dog10 below `MIN_SCORE`: no symmetry) and
#: -0.43 to -0.99 at 200, for about 1 s instead of 0.4 s
SYMMETRY_K_END = 200
#: version of the detection, part of the cache key
_VERSION = 4


class OrientationWarning(UserWarning):
    """A mesh whose orientation cannot be read (inconsistent winding, or no enclosed volume)."""


def _signed_volume(mesh: Mesh) -> float:
    """The volume the surface encloses, signed by its winding; an open surface is first closed by capping each
    boundary loop with a fan to the loop's own centroid (a fan to one common point, the cone the surface spans
    from its centroid, reads a bent open limb inside out)."""
    v = mesh.vertices - mesh.vertices.mean(axis=0)
    f = mesh.faces
    vol = float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum())
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(half, axis=1)
    n = np.int64(max(mesh.n_vertices, 1))
    _, inv, cnt = np.unique(key[:, 0] * n + key[:, 1], return_inverse=True, return_counts=True)
    border = half[cnt[inv] == 1]  # boundary half-edges, in their face's direction
    if len(border):
        from scipy.sparse.csgraph import connected_components

        g = sp.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(int(n), int(n)))
        # each boundary loop is a connected component of the boundary edges (the other vertices are singletons)
        _, loop = np.unique(connected_components(g, directed=False)[1][border[:, 0]], return_inverse=True)
        centre = np.zeros((int(loop.max()) + 1, 3))
        np.add.at(centre, loop, v[border[:, 0]])
        centre /= np.bincount(loop)[:, None]
        # the cap triangle (centre, j, i) runs the boundary edge i -> j the other way, as a neighbour face would
        vol += float(np.einsum("ij,ij->i", centre[loop], np.cross(v[border[:, 1]], v[border[:, 0]])).sum())
    return vol / 6.0


def winding(mesh: Mesh) -> int:
    """+1 when the faces wind counter-clockwise about the outward normal (positive enclosed volume), -1 when
    they wind the other way, 0 when that cannot be told (the signed volume is below 1 % of what a sphere of the
    same area encloses: a flat or nearly flat patch). An open surface (a scan, a cap, a cut limb) reads as the
    closed surface its boundary loops' caps make (`_signed_volume`)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    vol = _signed_volume(mesh)
    # a sphere of the same area encloses area^1.5 / (6 sqrt(pi))
    if abs(vol) < 0.01 * mesh.area ** 1.5 / (6.0 * np.sqrt(np.pi)):
        return 0
    return 1 if vol > 0 else -1


def orientation_score(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike) -> float:
    """How much the vertex map A -> B keeps orientation, in [-1, 1] (see the module docstring).

    For each face (i, j, k) of A the image triangle (T(i), T(j), T(k)) on B has the doubled-area vector
    n = (b_j - b_i) x (b_k - b_i); its sign against B's vertex normals at the three images, weighted by |n|,
    is averaged: score = sum <n, nB> / sum |n| with nB the unit sum of those normals. Multiplied by both
    meshes' `winding`, so it does not depend on which way each file winds its faces.

    Returns NaN (with an `OrientationWarning`) when a winding cannot be read or every image is degenerate.
    """
    for name, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
        if not isinstance(m, Mesh):
            raise TypeError(f"{name} must be a wpot.Mesh, got {type(m).__name__}")
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    terms = _terms(mesh_a, mesh_b, t)
    if terms is None:
        side = "mesh_a" if winding(mesh_a) == 0 else "mesh_b"
        warnings.warn(f"the orientation of a map cannot be scored: {side} encloses no volume to tell its outside "
                      "from its inside (an open or flat surface)", OrientationWarning, stacklevel=2)
        return float("nan")
    score = _mean(*terms)
    if np.isnan(score):
        warnings.warn("the orientation of a map cannot be scored: every face of mesh_a maps to a degenerate "
                      "triangle", OrientationWarning, stacklevel=2)
    return score


def _terms(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Per face of A, (F,) each: ``<n, nB>`` times both meshes' `winding`, and ``|n|``, for its image triangle
    (see `orientation_score`); None when a winding cannot be read."""
    sign = winding(mesh_a) * winding(mesh_b)
    if sign == 0:
        return None
    img = t[mesh_a.faces]  # (F, 3) vertices of B
    pb = mesh_b.vertices
    n = np.cross(pb[img[:, 1]] - pb[img[:, 0]], pb[img[:, 2]] - pb[img[:, 0]])
    nb = mesh_b.vertex_normals[img].sum(axis=1)
    nb /= np.maximum(np.linalg.norm(nb, axis=1, keepdims=True), 1e-300)
    return sign * np.einsum("ij,ij->i", n, nb), np.linalg.norm(n, axis=1)


def _mean(num: np.ndarray, den: np.ndarray) -> float:
    """The area-weighted mean sign: sum num / sum den (NaN when every image is degenerate)."""
    total = float(den.sum())
    return float(num.sum()) / total if total > 0 else float("nan")


def _score(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray) -> float:
    """`orientation_score` without its warnings (NaN when it cannot be read), for the callers that act on it."""
    terms = _terms(mesh_a, mesh_b, t)
    return float("nan") if terms is None else _mean(*terms)


def local_orientation(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike, *, radius: float = LOCAL_RADIUS
                      ) -> np.ndarray:
    """The orientation score of the map around each vertex of A, (N_A,) in [-1, 1] (NaN where every image
    nearby is degenerate, or where a winding cannot be read): `orientation_score`'s face terms summed over the
    faces at each vertex and spread over about ``radius`` sqrt(area) of A by repeated one-ring averaging.
    A ZoomOut map is often mirrored on some symmetric part only (both legs, say): its global score is then
    near 0 and this one is negative there."""
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    terms = _terms(mesh_a, mesh_b, t)
    if terms is None:
        return np.full(mesh_a.n_vertices, np.nan)
    return _spread(mesh_a, *terms, radius)


def _spread(mesh_a: Mesh, num: np.ndarray, den: np.ndarray, radius: float) -> np.ndarray:
    """Face terms summed at each vertex of A and averaged over about ``radius`` sqrt(area): (N_A,) num / den."""
    f = mesh_a.faces
    n = mesh_a.n_vertices
    vnum = np.bincount(f.reshape(-1), np.repeat(num, 3), minlength=n)
    vden = np.bincount(f.reshape(-1), np.repeat(den, 3), minlength=n)
    adj = mesh_a.adjacency
    avg = sp.diags(1.0 / (np.asarray(adj.sum(axis=1)).ravel() + 1.0)) @ (adj + sp.eye(n))
    steps = int(min(400, np.ceil((radius * np.sqrt(mesh_a.area) / mesh_a.mean_edge_length) ** 2)))
    for _ in range(steps):
        vnum, vden = avg @ vnum, avg @ vden
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(vden > 0, vnum / vden, np.nan)


@dataclass(frozen=True)
class Symmetry:
    """A shape's left/right symmetry (`reflection_symmetry`).

    Attributes
    ----------
    map : (N,) int64, the mirror vertex of each vertex (an involution up to the mesh's sampling).
    score : its `orientation_score` against itself (near -1: it reverses orientation).
    displacement : mean distance from a vertex to its mirror image, over sqrt(area).
    residual : how far the map is from an isometry: ``||C Λ - Λ C|| / ||C Λ||`` for its functional map C on
        the first 10 non-constant eigenfunctions (eigenvalues Λ); 0 for an exact symmetry. Only a weak test:
        0.05 for the test suite's mirror-symmetric shape (900 random vertices), 0.075 for the reversing
        self-map ZoomOut finds on the example surface, which has no symmetry.
    """

    map: np.ndarray
    score: float
    displacement: float
    residual: float


def _signature(spec) -> np.ndarray:
    """WKS on 100 energies, each energy scaled to unit RMS (the mirror test compares shapes of the signature,
    not its magnitude)."""
    from wpot.signatures import wks

    sig = wks(spec, n_energies=100)
    return sig / np.maximum(np.sqrt((sig * sig).mean(axis=0, keepdims=True)), 1e-300)


def _commutator_residual(mesh: Mesh, spec, t: np.ndarray, k: int = 10) -> float:
    from wpot.spectral import laplace_beltrami

    mass = laplace_beltrami(mesh)[1].diagonal()
    lo = spec.n_zero
    phi, lam = spec.evecs[:, lo:lo + k], spec.evals[lo:lo + k]
    c = (phi * (mass / mass.sum())[:, None]).T @ phi[t]
    return float(np.linalg.norm(c * (lam[:, None] - lam[None, :])) / np.linalg.norm(c * lam[None, :]))


def _mirror_candidates(mesh: Mesh, sig: np.ndarray, exclusion: float, block: int = 1024) -> np.ndarray:
    """For each vertex, the vertex of the nearest signature among those farther than ``exclusion`` sqrt(area)."""
    v = mesh.vertices
    r2 = (exclusion * np.sqrt(mesh.area)) ** 2
    ss = np.einsum("ij,ij->i", sig, sig)
    vv = np.einsum("ij,ij->i", v, v)
    out = np.empty(mesh.n_vertices, dtype=np.int64)
    for s in range(0, mesh.n_vertices, block):
        d = ss[None, :] - 2.0 * (sig[s:s + block] @ sig.T)
        near = (vv[None, :] - 2.0 * (v[s:s + block] @ v.T) + vv[s:s + block, None]) < r2
        d[near] = np.inf
        out[s:s + block] = np.argmin(d, axis=1)
    return out


def reflection_symmetry(mesh: Mesh, *, n_eigen: int | None = None, min_score: float = MIN_SCORE,
                        exclusion: float = EXCLUSION, k_end: int = SYMMETRY_K_END,
                        cache: bool = True) -> Symmetry | None:
    """The self-map exchanging left and right of a mirror-symmetric shape, or None when none is found.

    Parameters
    ----------
    mesh : the shape (one connected, consistently wound surface)
    n_eigen : eigenpairs for the WKS and ZoomOut (the vertex count when fewer); default
        `wpot.maps.zoomout.spectrum_size` (500, WKS's, from 5,000 vertices up, so that a WKS comparison's cached
        spectrum serves). Whatever else is cached, the result depends on the mesh and these options alone
    min_score : the map must score below ``-min_score`` (`orientation_score` of the mesh against itself)
    exclusion : a vertex's mirror candidate lies at least this far from it, times sqrt(area)
    k_end : ZoomOut's last spectral resolution for the self-map (`wpot.zoomout`, which starts at 10; fewer
        when ``spectrum_size`` gives fewer eigenpairs)
    cache : reuse (and store) the result in `symmetry_cache`

    Returns
    -------
    `Symmetry`, or None when the detected self-map does not reverse orientation or barely moves the shape, or
    the mesh's winding cannot be read. A shape with no mirror symmetry may still get a smooth reversing
    self-map that is far from an isometry: its ``residual`` says so (`keep_orientation` only uses a flip that
    scores better than the map it replaces).
    """
    from wpot.maps.zoomout import spectrum_size, zoomout
    from wpot.spectral import eigenpairs

    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    n_eigen = spectrum_size(mesh.n_vertices) if n_eigen is None else integer_at_least("n_eigen", n_eigen, 2)
    k_end = integer_at_least("k_end", k_end, 10)
    params = {"n_eigen": int(n_eigen), "min_score": float(min_score), "exclusion": float(exclusion),
              "k_end": int(k_end), "version": _VERSION}
    if cache:
        hit = symmetry_cache.get(mesh.fingerprint, params)
        if hit is not None:
            if not bool(hit["found"]):
                return None
            return Symmetry(np.array(hit["map"]), float(hit["score"]), float(hit["displacement"]),
                            float(hit["residual"]))
    found = None
    if winding(mesh) != 0 and mesh.n_vertices >= 8:
        spec = eigenpairs(mesh, min(n_eigen, mesh.n_vertices))  # from the spectrum cache when it is there
        cand = _mirror_candidates(mesh, _signature(spec), exclusion)
        sym = zoomout(mesh, mesh, cand, k_end=min(k_end, spectrum_size(mesh.n_vertices)), orient=False)
        score = _score(mesh, mesh, sym)
        disp = float(np.linalg.norm(mesh.vertices[sym] - mesh.vertices, axis=1).mean() / np.sqrt(mesh.area))
        if score < -min_score and disp > 0.5 * exclusion:
            found = Symmetry(sym, score, disp, _commutator_residual(mesh, spec, sym))
    if cache:
        entry = {"found": found is not None}
        if found is not None:
            entry.update(map=found.map, score=found.score, displacement=found.displacement,
                         residual=found.residual)
        symmetry_cache.put(mesh.fingerprint, params, entry)
    return found


def keep_orientation(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike,
                     refine: Callable[[np.ndarray], np.ndarray] | None = None, *, symmetry_of: str = "a"
                     ) -> tuple[np.ndarray, float, bool]:
    """A map A -> B that keeps orientation.

    Where the map reverses orientation (`local_orientation` < 0: the whole map, or a symmetric part of it such
    as both legs), those vertices of A are sent where the map sends their mirror images under A's symmetry
    (``t[S_A(i)]``; with no symmetry found on A, B's: ``S_B(t[i])``); the result is passed through ``refine``
    (e.g. ZoomOut, which also smooths the seams) and kept when its `orientation_score` is higher.
    ``symmetry_of="b"`` uses B's symmetry only: for a part A of a whole B, whose own symmetry (a limb's, a
    head's) need not be the whole's left/right.

    Returns
    -------
    (map (N_A,) int64, its orientation score, whether it was changed).
    """
    one_of("symmetry_of", symmetry_of, ("a", "b"))
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    terms = _terms(mesh_a, mesh_b, t)  # once: the score and where the map is mirrored
    score = float("nan") if terms is None else _mean(*terms)
    if np.isnan(score):
        return t, score, False
    wrong = _spread(mesh_a, *terms, LOCAL_RADIUS) < 0
    if not wrong.any():
        return t, score, False
    sym = reflection_symmetry(mesh_a) if symmetry_of == "a" else None
    if sym is not None:
        flipped = np.where(wrong, t[sym.map], t)
    else:
        sym = reflection_symmetry(mesh_b)
        if sym is None:
            return t, score, False
        flipped = np.where(wrong, sym.map[t], t)
    if refine is not None:
        flipped = np.asarray(refine(flipped), dtype=np.int64)
    score2 = _score(mesh_a, mesh_b, flipped)
    if score2 > score:
        return flipped, score2, True
    return t, score, False
