"""Simplified copies of large meshes, and the maps between a mesh and its copy.

The cost of the spectral steps (`wpot.eigenpairs`, `wpot.zoomout`) grows faster than the vertex count (the docs'
Results page, §6). A shape's low-frequency content, which is what they use, survives a careful simplification, so a large mesh can be matched through a copy of about 10,000 vertices and the
answer carried back to every vertex:

* `simplify` makes the copy by quadric-error decimation (``fast-simplification``, Garland and Heckbert's
  method), then repairs it (`wpot.mesh.Mesh.cleaned`: decimation leaves zero-area triangles, and may split off
  small pieces of a connected shape, which are dropped). Each vertex of the original is placed on its closest
  point of the copy (a Warp BVH query): a triangle of the copy and barycentric weights.
* `Simplified.restrict_map` carries a vertex map between two originals to their copies (each copy vertex
  through the original vertex nearest it), `lift_map` a map between the copies back to the originals: the
  image of an original vertex is the barycentric blend of the images of its triangle's corners (their weighted
  position on the other copy, then the nearest original vertex there), or the image of its heaviest corner
  where the corners' images lie apart (a seam of the map, where a blend would fall between two limbs).

Decimation is deterministic, so the copy of a mesh is the same mesh on every call, and its spectrum is read from
the cache (`wpot.cache`) after the first. The copy itself is cached too (`copy_cache`: memory, and disk under
``$WPOT_CACHE_DIR``), so an all-against-all simplifies each shape once, and the last few copies are kept as meshes
(`KEEP_COPIES`), so the steps of one comparison that each need a mesh's copy (the spectral signatures,
`wpot.zoomout`) share one.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from wpot._validate import integer_at_least
from wpot.cache import Cache, Kept
from wpot._warp import launch_rows, resolve_device
from wpot.mesh import Mesh, MeshWarning

__all__ = ["Simplified", "simplify", "lift_map", "SEAM_EDGES", "copy_cache"]

wp.set_module_options({"enable_backward": False})

#: corners of a triangle whose images lie farther apart than this many mean edge lengths of the target copy
#: straddle a seam of the map: `lift_map` takes the heaviest corner's image there instead of the blend
SEAM_EDGES = 2.0


@wp.kernel
def _closest(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3), face: wp.array(dtype=wp.int32),
             bary: wp.array2d(dtype=wp.float32)):
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh_id, points[i], 1.0e30)
    face[i] = q.face
    bary[i, 0] = q.u  # the closest point is u p0 + v p1 + (1 - u - v) p2 (Warp's convention)
    bary[i, 1] = q.v
    bary[i, 2] = 1.0 - q.u - q.v


@dataclass(frozen=True, eq=False)
class Simplified:
    """A mesh and the copy it is matched through (`simplify`).

    Attributes
    ----------
    full : the original mesh (N vertices)
    coarse : the copy (n vertices); ``full`` itself when it was small enough
    corners : (N, 3) int64, the copy's vertices at the corners of the triangle closest to each original vertex
    weights : (N, 3) float64, the barycentric weights of the closest point in that triangle (rows sum to 1)
    nearest : (n,) int64, the original vertex nearest each vertex of the copy
    """

    full: Mesh
    coarse: Mesh
    corners: np.ndarray
    weights: np.ndarray
    nearest: np.ndarray

    @property
    def simplified(self) -> bool:
        """Whether the copy differs from the original."""
        return self.coarse is not self.full

    @property
    def heaviest(self) -> np.ndarray:
        """(N,) int64, for each original vertex the copy's vertex of largest weight (its nearest corner)."""
        return self.corners[np.arange(len(self.corners)), np.argmax(self.weights, axis=1)]

    def interpolate(self, values: ArrayLike) -> np.ndarray:
        """Values on the copy's vertices, (n, ...), at the original's vertices, (N, ...): barycentric blends."""
        v = np.asarray(values)
        if v.shape[:1] != (self.coarse.n_vertices,):
            raise ValueError(f"values must have one row per vertex of the copy ({self.coarse.n_vertices}), got "
                             f"shape {v.shape}")
        w = self.weights.reshape(self.weights.shape + (1,) * (v.ndim - 1))
        return (w * v[self.corners]).sum(axis=1)

    def restrict_map(self, target: "Simplified", vertex_map: ArrayLike) -> np.ndarray:
        """A map (N_A,) from this original's vertices to ``target``'s original's, as a map (n_A,) between the two
        copies: each copy vertex goes through the original vertex nearest it, and its image to the copy vertex
        of largest weight there."""
        t = np.asarray(vertex_map, dtype=np.int64)
        if t.shape != (self.full.n_vertices,):
            raise ValueError(f"vertex_map must have one entry per vertex of the original ({self.full.n_vertices}), "
                             f"got shape {t.shape}")
        return target.heaviest[t[self.nearest]]


def simplify(mesh: Mesh, n_vertices: int, *, device: str | None = None, cache: Cache | bool = True) -> Simplified:
    """``mesh`` with a copy of about ``n_vertices`` vertices to match it through (the module docstring); a mesh of
    at most ``n_vertices`` vertices is its own copy.

    Parameters
    ----------
    mesh : the original (N vertices)
    n_vertices : the copy's size (decimation lands within a few vertices of it; repairs may remove a few more)
    device : Warp device of the closest-point queries; None means Warp's default device
    cache : True (default): `copy_cache`, and the last `KEEP_COPIES` copies kept as meshes; a `wpot.cache.Cache`:
        that one (nothing kept); False: computed every time

    Raises
    ------
    ValueError : ``n_vertices`` below 100 (too few for the spectra the copy is for).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    n = integer_at_least("n_vertices", n_vertices, 100)
    if not (cache is True or cache is False or isinstance(cache, Cache)):
        raise TypeError(f"cache must be True, False or a wpot.cache.Cache, got {type(cache).__name__}")
    if mesh.n_vertices <= n:
        ident = np.arange(mesh.n_vertices, dtype=np.int64)
        w = np.zeros((mesh.n_vertices, 3))
        w[:, 0] = 1.0
        return Simplified(mesh, mesh, np.repeat(ident[:, None], 3, axis=1), w, ident)
    dev = str(resolve_device(device))
    if cache is False:
        return _simplified(mesh, n, dev)
    if cache is True:
        made = _COPIES.get((mesh.fingerprint, n, dev), lambda: _stored(mesh, n, dev, copy_cache))
        return made if made.full is mesh else replace(made, full=mesh)
    return _stored(mesh, n, dev, cache)


def _stored(mesh: Mesh, n: int, device: str, cache: Cache) -> Simplified:
    """`simplify` of a mesh of more than ``n`` vertices, read from ``cache`` or computed and stored there."""
    params = {"n_vertices": n, "device": device, "version": 1}
    e = cache.get(mesh.fingerprint, params)
    if e is None:
        made = _simplified(mesh, n, device)
        cache.put(mesh.fingerprint, params, {"vertices": made.coarse.vertices, "faces": made.coarse.faces,
                                             "corners": made.corners, "weights": made.weights,
                                             "nearest": made.nearest})
        return made
    # the copy's defects were reported when it was made (`Mesh.cleaned`); the same mesh read back stays quiet
    coarse = Mesh(e["vertices"], e["faces"], warn=False, name=_copy_name(mesh, len(e["vertices"])))
    return Simplified(mesh, coarse, np.asarray(e["corners"]), np.asarray(e["weights"]), np.asarray(e["nearest"]))


def _copy_name(mesh: Mesh, n_vertices: int) -> str:
    """What a copy of ``mesh`` of ``n_vertices`` vertices is called in warnings about it."""
    return f"{mesh.name or 'mesh'} (simplified to {n_vertices} vertices)"


#: the copies `simplify` keeps: a comparison's signatures and its ZoomOut each ask for the same two, which are then
#: made once
KEEP_COPIES = 4
_COPIES = Kept(KEEP_COPIES)
#: each copy's arrays (its vertices and faces, and where the original's vertices lie on it), keyed by the
#: original's content, the size asked and the device of the closest-point queries
copy_cache = Cache("simplified", max_entries=64, max_bytes=256 << 20)


def _simplified(mesh: Mesh, n: int, device: str | None) -> Simplified:
    """`simplify` of a mesh of more than ``n`` vertices, computed."""
    import fast_simplification
    from scipy.spatial import cKDTree

    v, f = fast_simplification.simplify(np.ascontiguousarray(mesh.vertices, dtype=np.float32),
                                        np.ascontiguousarray(mesh.faces, dtype=np.int32),
                                        target_reduction=1.0 - n / mesh.n_vertices)
    name = _copy_name(mesh, len(v))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)  # the defects cleaned() repairs next
        rough = Mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), name=name)
    # a connected shape stays connected: pieces the decimation split off are dropped
    coarse = rough.cleaned(keep_largest_component=mesh.n_components == 1)[0]  # keeps the name
    corners, weights = _closest_points(coarse, mesh.vertices, device)
    nearest = cKDTree(mesh.vertices).query(coarse.vertices)[1].astype(np.int64)
    return Simplified(mesh, coarse, corners, weights, nearest)


def _closest_points(mesh: Mesh, points: np.ndarray, device: str | None) -> tuple[np.ndarray, np.ndarray]:
    """For each point, the corners of ``mesh``'s closest triangle, (P, 3) int64, and the closest point's
    barycentric weights there, (P, 3) float64 (float32 queries, coordinates taken about the mesh's centre)."""
    dev = resolve_device(device)
    origin = mesh.vertices.mean(axis=0)
    pts = wp.array((mesh.vertices - origin).astype(np.float32), dtype=wp.vec3, device=dev)
    idx = wp.array(mesh.faces.astype(np.int32).ravel(), dtype=wp.int32, device=dev)
    bvh = wp.Mesh(points=pts, indices=idx)
    q = wp.array((points - origin).astype(np.float32), dtype=wp.vec3, device=dev)
    face = wp.empty(len(points), dtype=wp.int32, device=dev)
    bary = wp.empty((len(points), 3), dtype=wp.float32, device=dev)
    launch_rows(lambda lo, hi: wp.launch(_closest, dim=hi - lo, inputs=[bvh.id, q[lo:hi]],
                                         outputs=[face[lo:hi], bary[lo:hi]], device=dev), len(points), dev, cols=64)
    w = np.clip(bary.numpy().astype(np.float64), 0.0, 1.0)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    return mesh.faces[face.numpy()].astype(np.int64), w


def lift_map(source: Simplified, target: Simplified, coarse_map: ArrayLike) -> np.ndarray:
    """A map between two copies, (n_A,) copy-of-A vertex -> copy-of-B vertex, as a map between the originals,
    (N_A,) int64: each original vertex of A goes to the blend of its triangle's corners' images (weighted by its
    barycentric weights), then to the original vertex of B nearest that point; where the corners' images lie more
    than `SEAM_EDGES` mean edge lengths of B's copy apart, to its heaviest corner's image instead."""
    from scipy.spatial import cKDTree

    t = np.asarray(coarse_map, dtype=np.int64)
    if t.shape != (source.coarse.n_vertices,):
        raise ValueError(f"coarse_map must have one entry per vertex of A's copy ({source.coarse.n_vertices}), got "
                         f"shape {t.shape}")
    if t.size and (t.min() < 0 or t.max() >= target.coarse.n_vertices):
        raise ValueError(f"coarse_map holds indices outside B's copy [0, {target.coarse.n_vertices - 1}]")
    img = target.coarse.vertices[t[source.corners]]  # (N_A, 3 corners, 3)
    blend = np.einsum("ic,icd->id", source.weights, img)
    spread = np.max([np.linalg.norm(img[:, i] - img[:, j], axis=1) for i, j in ((0, 1), (0, 2), (1, 2))], axis=0)
    seam = spread > SEAM_EDGES * target.coarse.mean_edge_length
    heavy = img[np.arange(len(img)), np.argmax(source.weights, axis=1)]
    point = np.where(seam[:, None], heavy, blend)
    return cKDTree(target.full.vertices).query(point)[1].astype(np.int64)
