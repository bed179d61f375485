"""Subsampling a mesh for transport: farthest-point samples, their cells, and what the transport sees.

The transport runs on every vertex, or on ``k`` farthest-point samples per mesh (`farthest_point_sampling`):
a common count (``max_vertices``) or a common density (``vertices_per_sample``). Each sample stands for
its cell (the vertices nearest to it), either by its own signature (``pooling="none"``) or by the cell's
mean signature with the cell's size as mass (``pooling="cell"``: the full-resolution problem, one unit
of mass per vertex, coarse-grained onto the samples; exact when signatures are constant on cells).
Correspondences found on the samples are extended back to every vertex through the cells
(`Subsample.extend`).

`FarthestPointSampler` is the sampling stage of a `wpot.Comparer`: its options in one frozen
`SamplerOptions`, its samples cached per mesh.
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from typing import Any, Mapping, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from wpot import _validate
from wpot.mesh import Mesh, edge_paths, named

__all__ = ["FPS_METRICS", "POOLINGS", "SamplerOptions", "FarthestPointSampler", "Subsample", "Points",
           "farthest_point_sampling"]

FPS_METRICS = ("geodesic", "euclidean")
#: how a farthest-point sample stands for its mesh (see `SamplerOptions`)
POOLINGS = ("none", "cell")
#: pooling="cell" warns when one mesh has more than this many times as many vertices per sample as the other
MAX_CELL_RATIO = 2.0
#: the warning of ``pooling="cell"`` without subsampling
POOLING_WITHOUT_SAMPLES = (
    "pooling='cell' averages each sample's cell, and nothing is subsampled without max_vertices or "
    "vertices_per_sample: every vertex is used, as its own cell, so pooling changes nothing; give one of them "
    "to subsample"
)


@dataclass(frozen=True)
class Subsample:
    """A farthest-point sample of a mesh's vertices, with the map from every vertex to its nearest sample.

    Attributes
    ----------
    indices : (k,) int64, sampled vertex indices, in the order FPS picked them
    nearest : (N,) int64, position in ``indices`` of each vertex's nearest sample (``indices[nearest]`` is
        the sampled vertex standing for each vertex; sampled vertices map to themselves)
    radius : the covering radius, the largest distance of a vertex to its nearest sample
    metric : "geodesic" (shortest paths along mesh edges) or "euclidean"
    """

    indices: np.ndarray
    nearest: np.ndarray
    radius: float
    metric: str

    @property
    def n_samples(self) -> int:
        return len(self.indices)

    def extend(self, per_sample: ArrayLike) -> np.ndarray:
        """Lift a per-sample array ``(k, ...)`` to every vertex ``(N, ...)`` through the nearest-sample map."""
        a = np.asarray(per_sample)
        if a.shape[:1] != (self.n_samples,):
            raise ValueError(f"expected an array with {self.n_samples} rows (one per sample), got shape {a.shape}")
        return a[self.nearest]

    @property
    def counts(self) -> np.ndarray:
        """(k,) int64, the size of each sample's cell: the number of vertices whose nearest sample it is (≥ 1)."""
        return np.bincount(self.nearest, minlength=self.n_samples)

    def pool(self, per_vertex: ArrayLike) -> np.ndarray:
        """The mean of a per-vertex array ``(N, ...)`` over each sample's cell: ``(k, ...)`` float64.

        The inverse of `extend` for piecewise-constant data (``pool(extend(x)) == x``).
        """
        a = np.asarray(per_vertex, dtype=np.float64)
        if a.shape[:1] != self.nearest.shape:
            raise ValueError(f"expected an array with {self.nearest.shape[0]} rows (one per vertex), got shape {a.shape}")
        out = np.zeros((self.n_samples,) + a.shape[1:])
        np.add.at(out, self.nearest, a)
        return out / self.counts.reshape((-1,) + (1,) * (a.ndim - 1))


class Points(NamedTuple):
    """What the transport sees of one mesh (`Comparer.points`).

    signatures : (k, d) float64, one row per point (every vertex, or per sample)
    masses : (k,) float64 summing to 1, or None for uniform masses
    subsample : the `Subsample` the points come from, or None for every vertex
    """

    signatures: np.ndarray
    masses: np.ndarray | None
    subsample: Subsample | None


def farthest_point_sampling(mesh: Mesh, k: int, *, metric: str = "geodesic", start: int | None = None) -> Subsample:
    """Farthest-point sampling of ``k`` vertices of ``mesh``, spread over the surface.

    Greedy: the first sample is ``start`` (default: the vertex farthest from the centroid, which does not
    depend on the vertex order); each next sample is the vertex farthest from all samples so far. The
    result covers the mesh with radius ``radius`` and every two samples are at least that far apart
    (the 2-approximation of the k-center problem).

    Parameters
    ----------
    metric : "geodesic" (default) measures distance along the surface by shortest paths on the edge
        graph (Dijkstra with edge lengths; it overestimates the true geodesic by a few percent on good
        triangulations, but never jumps across a gap as a straight line does, e.g. between touching legs).
        Each new source's Dijkstra is cut off at the current covering radius, so the cost stays about
        O(N log N) per sample only early on and shrinks as the samples densify. "euclidean" uses straight
        lines in R³ (faster, O(kN)). Disconnected parts are reached because an unreached vertex is
        infinitely far.

    Returns
    -------
    Subsample, whose ``nearest`` map assigns each vertex to its nearest sample in the same metric
    (the geodesic Voronoi cell for "geodesic").
    """
    _validate.one_of("metric", metric, FPS_METRICS)
    n = mesh.n_vertices
    k = int(k)
    if not 1 <= k <= n:
        raise ValueError(f"k must be between 1 and the number of vertices ({n}), got {k}")
    v = mesh.vertices
    if start is None:
        start = int(np.argmax(np.einsum("ij,ij->i", v - v.mean(0), v - v.mean(0))))
    elif not 0 <= int(start) < n:
        raise ValueError(f"start must be a vertex index in [0, {n - 1}], got {start}")
    idx = np.empty(k, dtype=np.int64)
    idx[0] = int(start)
    if metric == "euclidean":
        mind = np.full(n, np.inf)
        for t in range(k):
            d = v - v[idx[t]]
            np.minimum(mind, np.einsum("ij,ij->i", d, d), out=mind)
            if t + 1 < k:
                idx[t + 1] = int(np.argmax(mind))
        from scipy.spatial import cKDTree

        dist, nearest = cKDTree(v[idx]).query(v)
        return Subsample(idx, nearest.astype(np.int64), float(dist.max()), metric)

    from scipy.sparse.csgraph import dijkstra

    mind = np.full(n, np.inf)
    for t in range(k):
        radius = float(mind.max())
        d = edge_paths(mesh, int(idx[t]), limit=radius)
        np.minimum(mind, d, out=mind)
        mind[idx[t]] = 0.0
        if t + 1 < k:
            idx[t + 1] = int(np.argmax(mind))
    dist, _, src = dijkstra(mesh.edge_graph, directed=False, indices=idx, min_only=True, return_predecessors=True)
    pos = np.full(n, -1, dtype=np.int64)
    pos[idx] = np.arange(k)
    nearest = np.where(src >= 0, pos[np.maximum(src, 0)], -1)
    nearest[idx] = np.arange(k)  # a sample maps to itself even when two samples coincide
    if np.any(nearest < 0):  # only when k is smaller than the number of connected parts
        from scipy.spatial import cKDTree

        lost = np.nonzero(nearest < 0)[0]
        nearest[lost] = cKDTree(v[idx]).query(v[lost])[1]
        dist = np.where(np.isfinite(dist), dist, 0.0)
        warnings.warn(named(
            mesh.name, f"{lost.size} vertices lie in parts of the mesh that hold no sample (k={k} is smaller than "
            f"the number of connected parts, {mesh.n_components}); they were assigned to the nearest sample in a "
            "straight line"),
            stacklevel=2,
        )
    return Subsample(idx, nearest, float(dist.max()), metric)



@dataclass(frozen=True)
class SamplerOptions:
    """Which points of a mesh the transport sees.

    Attributes
    ----------
    max_vertices : subsample a mesh with more vertices than this to this many farthest-point samples
        (None, default: every vertex)
    vertices_per_sample : sample at a common density instead of a common count: a mesh of N vertices gets
        ``max(3, round(N / vertices_per_sample))`` samples (at most ``max_vertices`` when both are given),
        so every cell holds about ``vertices_per_sample`` vertices whatever the mesh's size. With
        ``pooling="cell"`` this is what a part against a whole needs: with a common count the part's cells
        are smaller, and the averaging smooths the two sides unequally. None (default): only
        ``max_vertices`` decides.
    fps_metric : "geodesic" (default) or "euclidean", see `farthest_point_sampling`
    pooling : ``"none"`` (default): a sample keeps its own signature, masses are uniform. ``"cell"``: a
        sample carries its cell's mean signature (`Subsample.pool`) and a mass proportional to the cell's
        size. It suits whole shapes meshed alike, whose signatures are noisy at the vertex scale
        (classification); for a part against a whole use it with ``vertices_per_sample``. Its effect: the
        docs' Results page. Without ``max_vertices`` or ``vertices_per_sample`` nothing is subsampled, every
        vertex is its own cell and ``"cell"`` changes nothing: it warns.
    """

    max_vertices: int | None = None
    vertices_per_sample: float | None = None
    fps_metric: str = "geodesic"
    pooling: str = "none"

    def __post_init__(self) -> None:
        if self.max_vertices is not None:
            object.__setattr__(self, "max_vertices", _validate.integer_at_least("max_vertices", self.max_vertices, 3))
        if self.vertices_per_sample is not None:
            object.__setattr__(self, "vertices_per_sample",
                               _validate.number_at_least("vertices_per_sample", self.vertices_per_sample, 1))
        _validate.one_of("fps_metric", self.fps_metric, FPS_METRICS)
        _validate.one_of("pooling", self.pooling, POOLINGS)
        if self.pooling == "cell" and not self.subsamples:
            warnings.warn(POOLING_WITHOUT_SAMPLES, UserWarning, stacklevel=4)

    @property
    def subsamples(self) -> bool:
        """True when some mesh may be subsampled (``max_vertices`` or ``vertices_per_sample`` is set)."""
        return self.max_vertices is not None or self.vertices_per_sample is not None

    def n_samples(self, n_vertices: int) -> int:
        """How many points stand for a mesh of ``n_vertices`` vertices (``n_vertices`` itself: no subsampling).

        ``max(3, round(N / vertices_per_sample))`` when ``vertices_per_sample`` is set, then at most
        ``max_vertices``; never more than N.
        """
        n = int(n_vertices)
        k = n
        if self.vertices_per_sample is not None:
            k = max(3, int(round(n / self.vertices_per_sample)))
        if self.max_vertices is not None:
            k = min(k, self.max_vertices)
        return min(k, n)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SamplerOptions":
        return cls(**dict(d))


class FarthestPointSampler:
    """The sampling stage: `SamplerOptions` plus the farthest-point samples computed so far, per mesh.

    ``points(mesh, signatures)`` is what the transport sees of a mesh; ``subsample(mesh)`` the sample
    behind it (None when every vertex is used). Samples are kept per (mesh content, sample count), so
    two comparers with the same ``fps_metric`` can share them (`share_samples_with`).
    """

    def __init__(self, options: SamplerOptions | None = None) -> None:
        self.options = options or SamplerOptions()
        #: the samples computed so far, by (mesh fingerprint, sample count)
        self.samples: dict[tuple[str, int], Subsample] = {}

    def __repr__(self) -> str:
        return f"FarthestPointSampler({self.options!r}, {len(self.samples)} meshes sampled)"

    def share_samples_with(self, other: "FarthestPointSampler") -> None:
        """Use ``other``'s sample store (both then see each other's samples); only with the same metric."""
        if other.options.fps_metric != self.options.fps_metric:
            raise ValueError(f"samples of fps_metric={other.options.fps_metric!r} cannot serve "
                             f"fps_metric={self.options.fps_metric!r}")
        self.samples = other.samples

    def subsample(self, mesh: Mesh) -> Subsample | None:
        """The farthest-point sample used for ``mesh`` (None when every vertex is used)."""
        k = self.options.n_samples(mesh.n_vertices)
        if k >= mesh.n_vertices:
            return None
        key = (mesh.fingerprint, k)
        s = self.samples.get(key)
        if s is None:
            s = farthest_point_sampling(mesh, k, metric=self.options.fps_metric)
            self.samples[key] = s
        return s

    def points(self, mesh: Mesh, signatures: np.ndarray) -> Points:
        """What the transport sees of ``mesh`` given its per-vertex ``signatures`` (N, d): every vertex, or
        its farthest-point samples (see ``pooling``)."""
        s = self.subsample(mesh)
        if s is None:
            return Points(signatures, None, None)
        if self.options.pooling == "none":
            return Points(signatures[s.indices], None, s)
        return Points(s.pool(signatures), s.counts / mesh.n_vertices, s)

    def check_cells(self, mesh_a: Mesh, mesh_b: Mesh, *, stacklevel: int = 3) -> None:
        """Warn when ``pooling="cell"`` would average over cells of very different sizes on A and B."""
        o = self.options
        if o.pooling != "cell" or not o.subsamples:
            return
        per_cell = [m.n_vertices / o.n_samples(m.n_vertices) for m in (mesh_a, mesh_b)]
        if max(per_cell) > MAX_CELL_RATIO * min(per_cell):
            warnings.warn(
                f"pooling='cell' averages signatures over {per_cell[0]:.1f} vertices per sample on mesh_a and "
                f"{per_cell[1]:.1f} on mesh_b: the two shapes are smoothed unequally (as for a part against a "
                "whole), which biases the distance; sample at a common density (vertices_per_sample) or use "
                "pooling='none' here",
                UserWarning,
                stacklevel=stacklevel,
            )
