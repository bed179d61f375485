"""Pairwise shape comparison: signatures → cost → OT plan → distance, correspondence, matches, registration.

The pieces (paper §2–§5):

* per-vertex signatures, WKS (§2.3, Eq. 5, compared by the normalized L1 of Eq. 29) or LD-SIFT (§2.2, L2);
* the cost matrix ``C(k, l)`` between the two signature sets, then the balanced (Eq. 6–16) or partial
  (Eq. 17–26) statistical-physics transport plan ``G`` annealed in β (Algorithm 1);
* the distance: ``U`` at convergence for balanced transport, and ``SU`` (Eq. 27) for partial transport,
  ``SU(A, B) = U(A, B) − ½ (U(A, A) + U(B, B))``, where U is the solver's regularized objective
  (Eq. 17: transport plus the two χ² mass penalties) and the self-comparisons are cached per shape;
* the correspondence (argmax of each plan row, §4.1.3), the matched pairs ``G(i, j) > 0.9·m1(i)`` and a
  similarity transform (scale, rotation, translation) fitted to them (§5.1, Fig. 1).

Partial transport's mass penalty is, by default, relative to the cost scale and to the problem size
(`solver_mass_penalty`, ``penalty_scale="relative"``), so that one value means the same trade-off for
every signature, cost unit and ``max_vertices``; ``penalty_scale="paper"`` is exactly Eq. 17 with
``α = mass_penalty/ρ²``.

`Comparer` is the caching set-up class (signatures per shape in memory and on disk, one WKS energy grid
shared by every shape it sees); `compare` is the one-shot function.

Large meshes: ``max_vertices`` (a common count) or ``vertices_per_sample`` (a common density) subsamples
each mesh by farthest-point sampling (`farthest_point_sampling`) before transport. Signatures are still computed on the full mesh, then taken at the samples; the
correspondence is extended back to every vertex through its nearest sample. Without ``max_vertices``, a
problem whose dense ``N1 × N2`` float64 matrices would not fit in the device's free memory raises
`ProblemTooLargeError` naming the option.
"""
from __future__ import annotations

import hashlib
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike

from wpot.mesh import Mesh

__all__ = [
    "DEFAULT_MASS_PENALTY",
    "PENALTY_SCALES",
    "Comparison",
    "Comparer",
    "ProblemTooLargeError",
    "Registration",
    "Subsample",
    "Points",
    "compare",
    "farthest_point_sampling",
    "fit_similarity",
    "cost_scale",
    "solver_mass_penalty",
    "solver_memory_bytes",
]

SIGNATURES = ("wks", "ldsift")
TRANSPORTS = ("balanced", "partial")
#: how `mass_penalty` is read for partial transport (see `solver_mass_penalty`)
PENALTY_SCALES = ("relative", "paper")
#: default relative mass penalty κ (``penalty_scale="relative"``), chosen by the HEAD experiment
#: (benchmarks/head_partial.py, LD-SIFT, heads vs full TOSCA cats/horses at 250 samples): at κ = 0.01 the
#: region of the full shape that receives the head's mass has the size of the head (participation ratio
#: 0.195 vs 0.205 of the samples), 58 % of the mass lands on the true head (20 % by chance) and every head
#: retrieves its class and its very parent; κ ≥ 1 is nearly balanced (the paper's α = 1/ρ² is κ ≈ 0.6
#: for LD-SIFT and ≈ 9 for WKS there), κ ≤ 0.003 collapses onto a few pairs (support < 7 %).
DEFAULT_MASS_PENALTY = 0.01
#: the signature distance each signature uses (paper §3.1: L2 for LD-SIFT; §3.2, Eq. 29 for WKS)
SIGNATURE_METRIC = {"wks": "wks", "ldsift": "l2"}
#: balanced transport between two point sets of at least this many points each starts with the interior-point
#: method unless ``solver_options`` names a method (see `Comparer`)
AUTO_IPM_POINTS = 2000
#: how many dense N1×N2 float64 arrays the solver keeps at once (C, the plan G, φ' for the Hessian and one
#: work array). Used only to estimate memory before a solve.
SOLVER_DENSE_MATRICES = 4
#: fraction of the device's free memory a solve may plan to use
MEMORY_FRACTION = 0.8
FPS_METRICS = ("geodesic", "euclidean")
#: how a farthest-point sample stands for its mesh (see `Comparer`, ``pooling``)
POOLINGS = ("cell", "none")
#: pooling="cell" warns when one mesh has more than this many times as many vertices per sample as the other
MAX_CELL_RATIO = 2.0
#: signatures kept in a `Comparer`'s memory cache, by count and bytes (the disk cache has no bound)
MAX_CACHED_SHAPES = 128
MAX_CACHED_BYTES = 2 << 30


class ProblemTooLargeError(ValueError):
    """The dense transport problem does not fit in the chosen device's memory (use ``max_vertices``)."""


# ----------------------------------------------------------------------------------------- registration
@dataclass(frozen=True)
class Registration:
    """A similarity transform ``x ↦ scale · R x + t`` (paper §5.1, Fig. 1).

    Attributes
    ----------
    scale : float, > 0
    rotation : (3, 3) float64, a proper rotation (det = +1)
    translation : (3,) float64
    rms : weighted root-mean-square residual ``|scale·R·s + t − d|`` over the fitted pairs
    n_pairs : number of point pairs it was fitted to
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    rms: float
    n_pairs: int

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous matrix of the transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def apply(self, x: Mesh | ArrayLike) -> Mesh | np.ndarray:
        """Transform a mesh (returns a new `Mesh`) or points ``(n, 3)`` (returns ``(n, 3)`` float64)."""
        if isinstance(x, Mesh):
            return x.transformed(self.rotation, self.translation, self.scale)
        p = np.asarray(x, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (n, 3), got {p.shape}")
        return self.scale * p @ self.rotation.T + self.translation

    def inverse(self) -> "Registration":
        """The inverse transform ``y ↦ (1/scale) Rᵀ (y − t)`` (rms expressed in the source's units)."""
        rt = self.rotation.T
        return Registration(1.0 / self.scale, rt, -(rt @ self.translation) / self.scale, self.rms / self.scale, self.n_pairs)


def fit_similarity(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None, *, with_scale: bool = True) -> Registration:
    """Weighted least-squares similarity transform taking ``source`` onto ``target`` (Umeyama 1991).

    Minimizes ``Σ w_i |s · R p_i + t − q_i|²`` over rotations R (det +1, no reflections), scales s > 0
    (fixed to 1 when ``with_scale`` is false) and translations t, in closed form from the SVD of the
    weighted cross-covariance.

    Parameters
    ----------
    source, target : (n, 3) float64, corresponding points p_i and q_i
    weights : (n,) non-negative, default uniform

    Raises
    ------
    ValueError : mismatched shapes, negative or all-zero weights, fewer than 3 points, or points that are
        (numerically) collinear, for which the rotation is not determined.
    """
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or q.shape != p.shape:
        raise ValueError(f"source and target must both have shape (n, 3), got {p.shape} and {q.shape}")
    n = len(p)
    if n < 3:
        raise ValueError(f"a similarity transform needs at least 3 point pairs, got {n}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be finite, non-negative and not all zero (sum {w.sum()!r}, min {w.min()!r})")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("source and target must be finite")
    w = w / w.sum()
    mp = w @ p
    mq = w @ q
    pc = p - mp
    qc = q - mq
    cov = (qc * w[:, None]).T @ pc  # Σ w q p^T, (3, 3)
    u, d, vt = np.linalg.svd(cov)
    var_p = float(w @ np.einsum("ij,ij->i", pc, pc))
    if var_p <= 0 or d[1] <= 1e-12 * max(d[0], np.finfo(float).tiny):
        raise ValueError(
            f"the source points are (numerically) collinear or coincident (singular values {d.tolist()}); "
            "a rotation is not determined"
        )
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float((d * sign).sum() / var_p) if with_scale else 1.0
    if scale <= 0:
        raise ValueError(f"the best similarity has a non-positive scale ({scale}); the pairs are inconsistent")
    trans = mq - scale * rot @ mp
    res = scale * p @ rot.T + trans - q
    rms = float(np.sqrt(w @ np.einsum("ij,ij->i", res, res)))
    return Registration(scale, rot, trans, rms, n)


# ------------------------------------------------------------------------------------------ subsampling
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


def _edge_graph(mesh: Mesh):
    import scipy.sparse as sp

    e = mesh.edges
    n = mesh.n_vertices
    w = mesh.edge_lengths
    # zero-length edges would be dropped by csgraph (0 = no edge); give them a tiny positive length
    w = np.maximum(w, np.finfo(float).tiny)
    g = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return g


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
    if metric not in FPS_METRICS:
        raise ValueError(f"metric must be one of {FPS_METRICS}, got {metric!r}")
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

    g = _edge_graph(mesh)
    mind = np.full(n, np.inf)
    for t in range(k):
        radius = float(mind.max())
        d = dijkstra(g, directed=False, indices=int(idx[t]), limit=radius if np.isfinite(radius) else np.inf)
        np.minimum(mind, d, out=mind)
        mind[idx[t]] = 0.0
        if t + 1 < k:
            idx[t + 1] = int(np.argmax(mind))
    dist, _, src = dijkstra(g, directed=False, indices=idx, min_only=True, return_predecessors=True)
    pos = np.full(n, -1, dtype=np.int64)
    pos[idx] = np.arange(k)
    nearest = np.where(src >= 0, pos[np.maximum(src, 0)], -1)
    nearest[idx] = np.arange(k)  # a sample maps to itself even when two samples coincide
    if np.any(nearest < 0):  # only when k is smaller than the number of connected parts
        from scipy.spatial import cKDTree

        lost = np.nonzero(nearest < 0)[0]
        nearest[lost] = cKDTree(v[idx]).query(v[lost])[1]
        dist = np.where(np.isfinite(dist), dist, 0.0)
        warnings.warn(
            f"{lost.size} vertices lie in parts of the mesh that hold no sample (k={k} is smaller than the number "
            f"of connected parts, {mesh.n_components}); they were assigned to the nearest sample in a straight line",
            stacklevel=2,
        )
    return Subsample(idx, nearest, float(dist.max()), metric)


# ----------------------------------------------------------------------------------------- mass penalty
def cost_scale(C: Any) -> float:
    """The cost scale ``s(C)`` of the relative mass penalty: the mean of ``C`` over all pairs.

    It is the transport cost of the independent plan ``ρ1 ⊗ ρ2`` (the β → 0 limit of the annealing), scales
    linearly with ``C``, and does not change when points are duplicated (and barely when they are
    resampled), which is what makes the relative penalty scale- and size-free. ``C`` is an (N1, N2)
    NumPy array or a float64 ``wp.array``.
    """
    if hasattr(C, "numpy") and not isinstance(C, np.ndarray):
        C = C.numpy()
    c = np.asarray(C, dtype=np.float64)
    if c.ndim != 2 or c.size == 0:
        raise ValueError(f"the cost matrix must be a non-empty (N1, N2) array, got shape {c.shape}")
    return float(c.mean())


def solver_mass_penalty(C: Any, mass_penalty: float, *, penalty_scale: str = "relative") -> float:
    """The factor ``a`` handed to `wpot.ot.solve_partial`, whose χ² penalty is ``α_i(k) = a / ρ_i(k)²`` (Eq. 17).

    ``penalty_scale="paper"`` returns ``mass_penalty`` itself: ``mass_penalty = 1`` is exactly the paper's
    ``α = 1/ρ²`` (§2.5). ``penalty_scale="relative"`` (the default of `Comparer`) returns

        a = κ · s(C) / N̄,     s(C) = mean_{k,l} C(k, l) (`cost_scale`),   N̄ = √(N1 N2),   κ = mass_penalty.

    Why. Compare uses uniform references ρ_i = 1/N_i. Write the masses as densities ``w_i = m_i / ρ_i``
    (``E_ρ[w] = 1``). The penalty of side i is then ``Σ_k a N_i² m_i(k)² = a N_i · E_ρi[w_i²]``, and
    ``E_ρ[w²] = 1 + χ²(m‖ρ)`` (Pearson). With the paper's ``a = 1`` it is ``N_i (1 + χ²)``: putting all
    the mass uniformly on a fraction f of the points costs ``N_i (1/f − 1)``, which grows with N and is
    compared with transport costs ``Σ C G`` of the order of ``s(C)``, in whatever unit the signature
    distance has. With ``a = κ s / N̄`` the objective becomes

        U = Σ C G + κ s(C) [ (N1/N̄) E_ρ1[w1²] + (N2/N̄) E_ρ2[w2²] ],

    so (for N1 = N2, or when both sides are resampled together)

    * scaling C by λ scales U by λ: the plan and masses do not change (scale-free);
    * duplicating every point (or resampling both shapes at another density) leaves the densities w, the
      transport cost and s(C) unchanged: the plan is the same up to the splitting (size-free);
    * κ alone sets the trade-off: concentrating side i on a fraction f costs ``κ (1/f − 1)`` mean costs.
      Closed form: if a fraction f of B costs 0 to every point of A and the rest costs c, the mass
      B's fraction receives is ``q = min(1, f + f / (2κ))``; it takes all the mass once ``κ ≤ f / (2(1 − f))``.
      In general a region whose cost is lower by Δ receives ``f + f(1 − f) Δ / (2 κ s)``.

    κ → ∞ is balanced transport with the reference masses; κ → 0 collapses onto the cheapest pairs.
    When N1 ≠ N2 the solver's single factor cannot give both sides the weight κ s exactly; the geometric
    mean N̄ weights side i by ``√(N_i / N_j)`` (symmetric in A and B, exact when N1 = N2).

    Raises
    ------
    ValueError : unknown ``penalty_scale``, ``mass_penalty`` not positive and finite, or (relative) a cost
        matrix with zero mean (every signature identical: there is no cost scale).
    """
    if penalty_scale not in PENALTY_SCALES:
        raise ValueError(f"penalty_scale must be one of {PENALTY_SCALES}, got {penalty_scale!r}")
    mp = float(mass_penalty)
    if not (np.isfinite(mp) and mp > 0):
        raise ValueError(f"mass_penalty must be a positive finite number, got {mass_penalty!r}")
    if penalty_scale == "paper":
        return mp
    n1, n2 = (int(x) for x in C.shape)
    s = cost_scale(C)
    if not s > 0:
        raise ValueError(
            f"the relative mass penalty needs a cost matrix with a positive mean, got mean {s!r} for a {n1} x {n2} "
            "cost (all signatures identical?); use penalty_scale='paper' to give the factor directly"
        )
    return mp * s / math.sqrt(n1 * n2)


# ----------------------------------------------------------------------------------------------- memory
def solver_memory_bytes(n1: int, n2: int) -> int:
    """Estimated peak memory of one dense solve: `SOLVER_DENSE_MATRICES` float64 ``(n1, n2)`` arrays."""
    return int(SOLVER_DENSE_MATRICES) * int(n1) * int(n2) * 8


def _free_memory(device: str) -> int:
    import warp as wp

    return int(wp.get_device(device).free_memory)


def check_problem_size(n1: int, n2: int, device: str, *, free_bytes: int | None = None) -> None:
    """Raise `ProblemTooLargeError` (naming ``max_vertices``) when an ``n1 × n2`` solve cannot fit on ``device``."""
    need = solver_memory_bytes(n1, n2)
    free = _free_memory(device) if free_bytes is None else int(free_bytes)
    budget = MEMORY_FRACTION * free
    if need > budget:
        k = max(1, int(math.sqrt(budget / (SOLVER_DENSE_MATRICES * 8))))
        raise ProblemTooLargeError(
            f"a {n1} x {n2} vertex comparison needs about {need / 2**30:.1f} GiB for the solver's "
            f"{SOLVER_DENSE_MATRICES} dense N1 x N2 float64 matrices, but device {device!r} has "
            f"{free / 2**30:.1f} GiB free; pass max_vertices (at most about {k} here) to subsample both "
            "meshes by farthest-point sampling"
        )


# ----------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Comparison:
    """The comparison of shape A with shape B.

    Attributes
    ----------
    distance : U at convergence (balanced, Eq. 6) or SU (partial, Eq. 27, with the self-comparisons)
    correspondence : (N_A,) int64, for each vertex of A the vertex of B with the largest plan entry in its
        row (when subsampled: the row of A's nearest sample, and B's sampled vertex)
    matched : (K, 2) int64 pairs (i in A, j in B) with ``G(i, j) > 0.9·m1(i)`` (vertex indices of the full
        meshes). With balanced transport and uniform masses, a vertex of A (mass 1/N_A) fits in one vertex of
        B (mass 1/N_B) only when N_B ≤ N_A / 0.9, so between meshes of quite different sizes few or no pairs
        match (the paper's Fig. 1 contrast); partial transport adapts the masses.
    matched_weight : (K,) float64, the plan entries ``G(i, j)`` of the matched pairs
    mass1 : (n_A,) float64, the mass each (sampled) vertex of A sends, ``Σ_l G(k, l)`` (uniform for balanced)
    mass2 : (n_B,) float64, the mass each (sampled) vertex of B receives
    registration : similarity transform taking A onto B fitted to the matched pairs weighted by G
        (§5.1), or None when fewer than 3 non-collinear pairs matched
    result : the solver's `OTResult` for A vs B (on the sampled vertices when subsampled)
    self_energies : (U(A, A), U(B, B)) for partial transport, else None
    history : (n_β, 2) float64, columns β and D(β): U_β (balanced) or SU_β (partial) at each annealing β
    sample_a, sample_b : the `Subsample` of each mesh, or None when not subsampled
    """

    distance: float
    correspondence: np.ndarray
    matched: np.ndarray
    matched_weight: np.ndarray
    mass1: np.ndarray
    mass2: np.ndarray
    registration: Registration | None
    result: Any
    signature: str
    transport: str
    self_energies: tuple[float, float] | None = None
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    sample_a: Subsample | None = None
    sample_b: Subsample | None = None

    def __repr__(self) -> str:
        # a summary for notebooks: the dataclass default would print every array, the OT result's included
        sizes = f"{len(self.correspondence)}->{len(self.sample_b.nearest) if self.sample_b is not None else len(self.mass2)} vertices"
        if self.sample_a is not None or self.sample_b is not None:
            sizes += f" (transport on {len(self.mass1)}x{len(self.mass2)} samples)"
        reg = "none" if self.registration is None else (
            f"scale {self.registration.scale:.4g}, rms {self.registration.rms:.4g} on {self.registration.n_pairs} pairs")
        return (f"Comparison({self.signature}, {self.transport}, {sizes}, distance={self.distance:.6g}, "
                f"converged={bool(getattr(self.result, 'converged', False))}, matched={len(self.matched)} pairs, "
                f"registration: {reg})")


# ----------------------------------------------------------------------------------- energy bookkeeping
def transport_energy(result: Any, transport: str) -> float:
    """The U entering the distance: ``cost`` (Eq. 6) for balanced, ``objective`` (Eq. 17) for partial."""
    return float(result.cost if transport == "balanced" else result.objective)


def energy_history(result: Any, transport: str) -> np.ndarray:
    """(n_β, 2) float64: β and U_β from the solver's per-β history (the same quantity as `transport_energy`).

    For partial transport the per-β objective is used when the solver records it (``BetaStep.objective``);
    otherwise the per-β transport cost, and the store says which (`history_quantity`).
    """
    rows = []
    for step in getattr(result, "history", ()) or ():
        rows.append((float(step.beta), _step_energy(step, transport)))
    return np.asarray(rows, dtype=np.float64).reshape(-1, 2)


def history_quantity(transport: str) -> str:
    return "cost" if transport == "balanced" else "objective"


def _step_energy(step: Any, transport: str) -> float:
    if transport == "balanced":
        return float(step.cost)
    obj = getattr(step, "objective", None)
    return float(step.cost if obj is None else obj)


def debias_history(h_ab: np.ndarray, h_aa: np.ndarray, h_bb: np.ndarray) -> np.ndarray:
    """SU_β (Eq. 27) on the β grid of ``h_ab``; each self history is read at the same β (its last value
    after it converged, NaN before its first β)."""
    out = np.array(h_ab, dtype=np.float64, copy=True).reshape(-1, 2)
    if len(out) == 0:
        return out
    out[:, 1] = out[:, 1] - 0.5 * (history_at(h_aa, out[:, 0]) + history_at(h_bb, out[:, 0]))
    return out


def history_at(h: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Value of a (β, U) history at each β in ``betas``: the last entry with β' ≤ β (1e-9 relative slack in log β),
    NaN where β is below the first recorded β."""
    h = np.asarray(h, dtype=np.float64).reshape(-1, 2)
    betas = np.asarray(betas, dtype=np.float64)
    if len(h) == 0:
        return np.full(betas.shape, np.nan)
    lb = np.log(h[:, 0])
    pos = np.searchsorted(lb, np.log(betas) + 1e-9, side="right") - 1
    return np.where(pos >= 0, h[np.maximum(pos, 0), 1], np.nan)


# --------------------------------------------------------------------------------------------- comparer
def _digest(obj: Any) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=_json_default).encode()).hexdigest()[:16]


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return [float(x) for x in o.ravel()]
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


class Comparer:
    """A comparison session: fixed settings, signatures cached per shape, one shared WKS energy grid.

    Parameters
    ----------
    signature : "wks" (intrinsic, §2.3; cost Eq. 29) or "ldsift" (extrinsic, §2.2; L2 cost)
    transport : "balanced" (Eq. 6–16) or "partial" (Eq. 17–26)
    max_vertices : subsample meshes with more vertices than this by farthest-point sampling (None: never;
        then a problem too large for the device raises `ProblemTooLargeError`)
    vertices_per_sample : sample at a common density instead of a common count: a mesh of N vertices gets
        ``max(3, round(N / vertices_per_sample))`` farthest-point samples (capped at ``max_vertices`` when both
        are given), so every cell holds about ``vertices_per_sample`` vertices whatever the mesh's size. Use it
        with ``pooling="cell"`` for a part against a whole cut from meshes of the same vertex density (HEAD):
        with a common count, the part's cells are smaller and the averaging smooths the two sides unequally.
        None (default): only ``max_vertices`` decides.
    fps_metric : "geodesic" or "euclidean", see `farthest_point_sampling`
    pooling : how a sample stands for the mesh when it is subsampled (``max_vertices``, ``vertices_per_sample``). ``"none"`` (default): the
        sampled vertex's own signature, uniform masses. ``"cell"``: each sample carries the mean signature of
        its cell (the vertices nearest to it, `Subsample.pool`) and a mass proportional to the cell's size,
        i.e. the paper's full-resolution problem (one unit of mass per vertex) coarse-grained onto the
        samples, exact when signatures are constant on cells. Use ``"cell"`` for whole shapes meshed alike
        (classification): on the 76 TOSCA shapes at 200 samples (emd) it raises LD-SIFT one-shot 1-NN from
        51.6 % to 70.4 % (leave-one-out 73.7 → 88.2 %; area-weighted cells did less: 64.2 %, 85.5 %), and LD-SIFT
        partial (κ = 0.01, `wpot all-vs-all`) from 45.2 % to 79.5 % (leave-one-out 67.1 → 98.7 %). For a
        part against a whole, sample at a common density (``vertices_per_sample``): with a common count their
        cells differ in size, the averaging smooths the two sides unequally, and on HEAD (6 heads, LD-SIFT
        partial, κ = 0.01) parent retrieval fell from 6/6 to 2/6; a comparison warns when one mesh has over
        `MAX_CELL_RATIO` times as many vertices per sample. With ``vertices_per_sample=20`` (19 heads × 19 full
        shapes, κ = 0.01) 80 % of each head's mass lands on its true head against 57 % without pooling, and
        the head's vertices land 0.06 √area from their true place against 0.40; parent retrieval is 16/19
        against 19/19 without pooling (class 19/19 both).
        Cell masses are unequal (up to ~40x on TOSCA's wolves); the solver handles that (every pair of the
        76-shape LD-SIFT run converged, to ``ot.emd``'s optimum within 1e-7).
    device : Warp device for signatures, cost and solver; None is Warp's default, resolved once here
    mass_penalty : partial transport's χ² penalty factor. With ``penalty_scale="relative"`` (default) it is
        κ in ``α(k) = κ · mean(C) / (√(N1 N2) ρ(k)²)``: spreading all of a side's mass on a fraction f of its
        points costs κ (1/f − 1) mean costs, whatever the cost's unit and the number of points (see
        `solver_mass_penalty`); default `DEFAULT_MASS_PENALTY`, chosen by the HEAD experiment. Smaller values
        allow more partial matches (κ ≤ f/(2(1−f)) lets a region of fraction f that is clearly cheaper
        take all the mass); large values approach balanced transport.
    penalty_scale : "relative" (default, above) or "paper": ``α(k) = mass_penalty / ρ(k)²``, so
        ``penalty_scale="paper", mass_penalty=1.0`` is exactly the paper's Eq. 17.
    n_eigen, n_energies : WKS parameters (paper: 500 eigenpairs, 200 energies)
    scale_invariant : WKS of the meshes at their own size (False, default, the paper's §3.2: size is part of
        the shape, and a part keeps the size it has in the whole) or scaled to area 1 (True: for meshes in
        unrelated units, or when size must not count). See `wpot.signatures.wks`.
    energies : a fixed WKS energy grid (n_energies,) shared by all shapes; when None, the grid is built by
        `fit_energies` (from a dataset) or, for a lone pair, from the two shapes' spectra
    ldsift_K, ldsift_resolution : LD-SIFT scale constant K (paper 3) and image size (paper 21)
    ldsift_slab : LD-SIFT depth slab half-thickness in units of S(v) (default 1.0; 0.25 classifies articulated
        shapes such as TOSCA better, 1.0 keeps the broad features of smooth ones: `wpot.signatures.ldsift`).
        It enters the run key only when it is not 1.0, so runs stored before the option existed resume
    cache_dir : folder for the on-disk signature cache (`wpot.cache.Cache`, content-keyed npz); None uses
        ``$WPOT_CACHE_DIR`` when set (else memory only); False keeps signatures in memory only
    solver_options : extra keyword arguments for `wpot.ot.solve_balanced` / `solve_partial` (beta0, tol, ...).
        Balanced transport with no ``method`` here anneals (Algorithm 1, D(β) from the first β) when a side
        has fewer than `AUTO_IPM_POINTS` points, and starts with the interior-point method (``"ipm"``, the same
        D(∞); the history starts at its hand-off β) when both have at least that many: on full-resolution
        5,000-vertex TOSCA pairs annealing is an order of magnitude slower (cat0–cat1: 1,529 Newton steps
        against 116; on an H100 annealing took 70 s and ``ipm`` 4–6 s a pair; on a 2-core CPU ``ipm`` took
        310 s in all while annealing had solved 3 of its 16 β after 14 minutes). ``method="anneal"`` forces annealing.
    match_ratio : a pair (i, j) is matched when ``G(i, j) > match_ratio · m1(i)`` (paper: 0.9)
    """

    def __init__(
        self,
        *,
        signature: str = "wks",
        transport: str = "balanced",
        max_vertices: int | None = None,
        fps_metric: str = "geodesic",
        pooling: str = "none",
        vertices_per_sample: float | None = None,
        device: str | None = None,
        mass_penalty: float = DEFAULT_MASS_PENALTY,
        penalty_scale: str = "relative",
        n_eigen: int = 500,
        n_energies: int = 200,
        scale_invariant: bool = False,
        energies: ArrayLike | None = None,
        ldsift_K: float = 3.0,
        ldsift_resolution: int = 21,
        ldsift_slab: float | None = None,
        cache_dir: str | Path | None | bool = None,
        solver_options: Mapping[str, Any] | None = None,
        match_ratio: float = 0.9,
    ) -> None:
        if signature not in SIGNATURES:
            raise ValueError(f"signature must be one of {SIGNATURES}, got {signature!r}")
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        if max_vertices is not None and (int(max_vertices) != max_vertices or max_vertices < 3):
            raise ValueError(f"max_vertices must be an integer >= 3 or None, got {max_vertices!r}")
        if fps_metric not in FPS_METRICS:
            raise ValueError(f"fps_metric must be one of {FPS_METRICS}, got {fps_metric!r}")
        if vertices_per_sample is not None:
            try:
                vps = float(vertices_per_sample)
            except (TypeError, ValueError):
                vps = float("nan")
            if isinstance(vertices_per_sample, bool) or not (np.isfinite(vps) and vps >= 1):
                raise ValueError(f"vertices_per_sample must be a number >= 1 or None, got {vertices_per_sample!r}")
        if pooling not in POOLINGS:
            raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
        if not (np.isfinite(mass_penalty) and mass_penalty > 0):
            raise ValueError(f"mass_penalty must be a positive finite number, got {mass_penalty!r}")
        if penalty_scale not in PENALTY_SCALES:
            raise ValueError(f"penalty_scale must be one of {PENALTY_SCALES}, got {penalty_scale!r}")
        from wpot.signatures._wks import check_scale_invariant

        check_scale_invariant(scale_invariant)
        if not 0 < match_ratio <= 1:
            raise ValueError(f"match_ratio must be in (0, 1], got {match_ratio!r}")
        self.signature = signature
        self.transport = transport
        self.max_vertices = None if max_vertices is None else int(max_vertices)
        self.fps_metric = fps_metric
        self.pooling = pooling
        self.vertices_per_sample = None if vertices_per_sample is None else float(vertices_per_sample)
        self.device = _resolve_device(device)
        self.mass_penalty = float(mass_penalty)
        self.penalty_scale = penalty_scale
        self.n_eigen = int(n_eigen)
        self.n_energies = int(n_energies)
        self.scale_invariant = bool(scale_invariant)
        self.ldsift_K = float(ldsift_K)
        self.ldsift_resolution = int(ldsift_resolution)
        from wpot.signatures._ldsift import SLAB, _check_slab

        self.ldsift_slab = SLAB if ldsift_slab is None else _check_slab(ldsift_slab)
        self.solver_options = dict(solver_options or {})
        self.match_ratio = float(match_ratio)
        self.cache_dir = cache_dir
        from wpot.cache import Cache

        self._sig_cache = Cache("signatures", max_entries=MAX_CACHED_SHAPES, max_bytes=MAX_CACHED_BYTES, cache_dir=cache_dir)
        self._spectrum_cache = _spectrum_cache(cache_dir)
        self._energies: np.ndarray | None = None
        if energies is not None:
            self.energies = energies
        self._samples: dict[tuple[str, int], Subsample] = {}
        self._self_energies: dict[tuple[str, str], tuple[float, np.ndarray]] = {}

    # ------------------------------------------------------------------------------ parameters
    def params(self) -> dict[str, Any]:
        """Every setting that changes a distance, as JSON-able values (the pipeline's run key)."""
        p: dict[str, Any] = {
            "signature": self.signature,
            "transport": self.transport,
            "max_vertices": self.max_vertices,
            "fps_metric": self.fps_metric if self._subsamples else None,
            "pooling": self.pooling if self._subsamples else None,
            "match_ratio": self.match_ratio,
            "solver_options": {k: self.solver_options[k] for k in sorted(self.solver_options)},
        }
        if self.vertices_per_sample is not None:  # absent otherwise, so runs stored before it existed still resume
            p["vertices_per_sample"] = self.vertices_per_sample
        if self.transport == "partial":
            p["mass_penalty"] = self.mass_penalty
            p["penalty_scale"] = self.penalty_scale
        if self.signature == "wks":
            p.update(n_eigen=self.n_eigen, n_energies=self.n_energies, scale_invariant=self.scale_invariant)
        else:
            p.update(ldsift_K=self.ldsift_K, ldsift_resolution=self.ldsift_resolution)
            if self.ldsift_slab != 1.0:  # absent = 1.0, the only slab before the option: those runs still resume
                p["ldsift_slab"] = self.ldsift_slab
        return p

    def options(self) -> dict[str, Any]:
        """The constructor arguments that rebuild this `Comparer` (``Comparer(**c.options())``)."""
        return dict(
            signature=self.signature, transport=self.transport, max_vertices=self.max_vertices,
            fps_metric=self.fps_metric, pooling=self.pooling, vertices_per_sample=self.vertices_per_sample,
            device=self.device, mass_penalty=self.mass_penalty,
            penalty_scale=self.penalty_scale, n_eigen=self.n_eigen, n_energies=self.n_energies,
            scale_invariant=self.scale_invariant, energies=self._energies, ldsift_K=self.ldsift_K,
            ldsift_resolution=self.ldsift_resolution, ldsift_slab=self.ldsift_slab, cache_dir=self.cache_dir,
            solver_options=dict(self.solver_options), match_ratio=self.match_ratio,
        )

    def __repr__(self) -> str:
        p = self.params()
        grid = "" if self.signature != "wks" else (
            ", energies: none yet" if self._energies is None else f", energies: {len(self._energies)} fitted")
        dev = "" if self.device is None else f", device={self.device!r}"
        return "Comparer(" + ", ".join(f"{k}={v!r}" for k, v in p.items() if v is not None and v != {}) + dev + grid + ")"

    def with_options(self, **changes: Any) -> "Comparer":
        """A new `Comparer` with some settings changed (e.g. ``mass_penalty`` in a sweep).

        It shares this one's signature cache (keyed by the signature parameters, so always safe) unless
        ``cache_dir`` changes, its WKS energy grid unless ``energies`` is given or ``scale_invariant``
        changes, and its farthest-point samples when ``fps_metric`` is unchanged (they are kept per sample count).
        Self-comparisons (Eq. 27) are not shared: they depend on every setting.
        """
        kw = self.options()
        unknown = sorted(set(changes) - set(kw))
        if unknown:
            raise ValueError(f"unknown Comparer options {unknown}; known: {sorted(kw)}")
        if "energies" not in changes and changes.get("scale_invariant", self.scale_invariant) != self.scale_invariant:
            kw["energies"] = None  # a grid is fitted for one scale convention: refit
        kw.update(changes)
        new = Comparer(**kw)
        if new.cache_dir == self.cache_dir:
            new._sig_cache = self._sig_cache
            new._spectrum_cache = self._spectrum_cache
        if new.fps_metric == self.fps_metric:
            new._samples = self._samples
        return new

    @property
    def energies(self) -> np.ndarray | None:
        """The shared WKS energy grid (n_energies,) float64, or None until fitted."""
        return self._energies

    @energies.setter
    def energies(self, value: ArrayLike | None) -> None:
        if value is None:
            self._energies = None
            return
        e = np.asarray(value, dtype=np.float64).ravel().copy()
        if e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError(f"energies must be a finite increasing grid of at least 2 values, got {e.size} values")
        e.setflags(write=False)
        if self._energies is not None and not np.array_equal(self._energies, e):
            self._self_energies.clear()  # WKS depends on the grid (signatures are keyed by it)
        self._energies = e

    def fit_energies(self, meshes: Sequence[Mesh]) -> np.ndarray:
        """Build one WKS energy grid from the spectra of all ``meshes`` (`wpot.wks_energies`), and keep it."""
        from wpot.signatures._wks import wks_energies
        from wpot.spectral import eigenpairs

        # as `wks` does, a mesh with fewer vertices than n_eigen uses all its eigenpairs
        spectra = [eigenpairs(m, min(self.n_eigen, m.n_vertices), cache=self._spectrum_cache) for m in meshes]
        self.energies = _energy_grid(wks_energies(spectra, n_energies=self.n_energies, scale_invariant=self.scale_invariant))
        return self.energies

    # ------------------------------------------------------------------------------ signatures
    def _signature_params(self) -> dict[str, Any]:
        from wpot.signatures import _ldsift, _wks

        p: dict[str, Any] = {"signature": self.signature}
        if self.signature == "wks":
            p.update(n_eigen=self.n_eigen, n_energies=self.n_energies, scale_invariant=self.scale_invariant,
                     energies=self._energies, version=_wks.VERSION)
        else:
            p.update(K=self.ldsift_K, resolution=self.ldsift_resolution, version=_ldsift.VERSION)
            if self.ldsift_slab != 1.0:  # signatures cached before the option existed were all at slab 1.0
                p["slab"] = self.ldsift_slab
        return p

    def _signature_key(self) -> str:
        return _digest(self._signature_params())

    def signatures(self, mesh: Mesh) -> np.ndarray:
        """Per-vertex signatures of the full mesh, (N, d) float64, read-only.

        Cached by mesh content and signature parameters (`wpot.cache.Cache`, namespace "signatures"):
        in memory, and on disk under ``cache_dir`` (or ``$WPOT_CACHE_DIR``). WKS needs the energy grid
        first (`fit_energies`, the ``energies`` argument, or `compare`, which fits it to its pair).
        """
        if self.signature == "wks" and self._energies is None:
            raise ValueError("the WKS energy grid is not set: call fit_energies(meshes) or pass energies=")
        entry = self._sig_cache.get_or_compute(
            mesh.fingerprint, self._signature_params(), lambda: {"signature": self._compute_signatures(mesh)}
        )
        sig = entry["signature"]
        if sig.shape[0] != mesh.n_vertices:
            raise ValueError(f"signature rows ({sig.shape[0]}) do not match the mesh's {mesh.n_vertices} vertices")
        return sig

    def _compute_signatures(self, mesh: Mesh) -> np.ndarray:
        if self.signature == "wks":
            from wpot.signatures._wks import wks

            return np.asarray(wks(mesh, n_eigen=self.n_eigen, n_energies=self.n_energies, energies=self._energies,
                                  scale_invariant=self.scale_invariant, cache=self._spectrum_cache), dtype=np.float64)
        from wpot.signatures._ldsift import ldsift

        return np.asarray(ldsift(mesh, K=self.ldsift_K, resolution=self.ldsift_resolution, slab=self.ldsift_slab,
                                 device=self.device), dtype=np.float64)

    @property
    def _subsamples(self) -> bool:
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

    def subsample(self, mesh: Mesh) -> Subsample | None:
        """The farthest-point sample used for ``mesh`` (None when every vertex is used, see `n_samples`)."""
        k = self.n_samples(mesh.n_vertices)
        if k >= mesh.n_vertices:
            return None
        key = (mesh.fingerprint, k)
        s = self._samples.get(key)
        if s is None:
            s = farthest_point_sampling(mesh, k, metric=self.fps_metric)
            self._samples[key] = s
        return s

    def points(self, mesh: Mesh) -> "Points":
        """What the transport sees of ``mesh``: every vertex, or its farthest-point sample (see ``pooling``)."""
        sig = self.signatures(mesh)
        s = self.subsample(mesh)
        if s is None:
            return Points(sig, None, None)
        if self.pooling == "none":
            return Points(sig[s.indices], None, s)
        return Points(s.pool(sig), s.counts / mesh.n_vertices, s)

    def _check_cells(self, mesh_a: Mesh, mesh_b: Mesh) -> None:
        """Warn when ``pooling="cell"`` would average over cells of very different sizes (see ``pooling``)."""
        if self.pooling != "cell" or not self._subsamples:
            return
        per_cell = [m.n_vertices / self.n_samples(m.n_vertices) for m in (mesh_a, mesh_b)]
        if max(per_cell) > MAX_CELL_RATIO * min(per_cell):
            warnings.warn(
                f"pooling='cell' averages signatures over {per_cell[0]:.1f} vertices per sample on mesh_a and "
                f"{per_cell[1]:.1f} on mesh_b: the two shapes are smoothed unequally (as for a part against a "
                "whole), which biases the distance; sample at a common density (vertices_per_sample) or use "
                "pooling='none' here",
                UserWarning,
                stacklevel=3,
            )

    # ------------------------------------------------------------------------------ transport
    def transport_plan(self, mesh_a: Mesh, mesh_b: Mesh) -> Any:
        """Solve the transport between the (sampled) signatures of A and B; returns the solver's `OTResult`."""
        self._check_cells(mesh_a, mesh_b)
        return self._solve(self.points(mesh_a), self.points(mesh_b))

    def _solve(self, pa: "Points", pb: "Points") -> Any:
        from wpot.cost import cost_matrix
        from wpot import ot

        check_problem_size(len(pa.signatures), len(pb.signatures), self.device)
        c = cost_matrix(pa.signatures, pb.signatures, metric=SIGNATURE_METRIC[self.signature], device=self.device)
        if self.transport == "balanced":
            opts = dict(self.solver_options)
            if "method" not in opts and min(len(pa.signatures), len(pb.signatures)) >= AUTO_IPM_POINTS:
                opts["method"] = "ipm"
            return ot.solve_balanced(c, pa.masses, pb.masses, device=self.device, **opts)
        a = solver_mass_penalty(c, self.mass_penalty, penalty_scale=self.penalty_scale)
        return ot.solve_partial(c, pa.masses, pb.masses, mass_penalty=a, device=self.device, **self.solver_options)

    def self_transport(self, mesh: Mesh) -> Any:
        """Solve ``mesh`` against itself (the self-comparison of Eq. 27); returns the `OTResult`, not cached."""
        p = self.points(mesh)
        return self._solve(p, p)

    def self_energy(self, mesh: Mesh) -> tuple[float, np.ndarray]:
        """U(A, A) and its per-β history ((n_β, 2) float64), for Eq. 27; cached per shape (the plan is not kept)."""
        key = (mesh.fingerprint, self._signature_key())
        r = self._self_energies.get(key)
        if r is None:
            res = self.self_transport(mesh)
            r = (transport_energy(res, self.transport), energy_history(res, self.transport))
            self._self_energies[key] = r
        return r

    def compare(self, mesh_a: Mesh, mesh_b: Mesh) -> Comparison:
        """Compare A with B; see `Comparison`. For WKS with no grid yet, the grid is fitted to A and B."""
        for name, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
            if not isinstance(m, Mesh):
                raise TypeError(f"{name} must be a wpot.Mesh, got {type(m).__name__}")
        if self.signature == "wks" and self._energies is None:
            self.fit_energies([mesh_a, mesh_b])
        self._check_cells(mesh_a, mesh_b)
        pa, pb = self.points(mesh_a), self.points(mesh_b)
        sub_a, sub_b = pa.subsample, pb.subsample
        res = self._solve(pa, pb)
        hist = energy_history(res, self.transport)
        self_e = None
        if self.transport == "balanced":
            distance = transport_energy(res, "balanced")
        else:
            from wpot.ot import debiased

            (uaa, haa), (ubb, hbb) = self.self_energy(mesh_a), self.self_energy(mesh_b)
            distance = float(debiased(transport_energy(res, "partial"), uaa, ubb))
            self_e = (uaa, ubb)
            hist = debias_history(hist, haa, hbb)
        return _assemble(res, sub_a, sub_b, mesh_a, mesh_b, distance, self_e, hist, self.signature, self.transport, self.match_ratio)


def _assemble(res, sub_a, sub_b, mesh_a, mesh_b, distance, self_e, hist, signature, transport, match_ratio) -> Comparison:
    plan = np.asarray(res.plan, dtype=np.float64)
    m1 = np.asarray(res.mass1, dtype=np.float64) if getattr(res, "mass1", None) is not None else plan.sum(1)
    m2 = np.asarray(res.mass2, dtype=np.float64) if getattr(res, "mass2", None) is not None else plan.sum(0)
    rows_best = np.argmax(plan, axis=1)
    ia = np.arange(len(plan)) if sub_a is None else sub_a.indices
    jb = np.arange(plan.shape[1]) if sub_b is None else sub_b.indices
    corr_sampled = jb[rows_best]
    correspondence = corr_sampled if sub_a is None else sub_a.extend(corr_sampled)
    ii, jj = np.nonzero(plan > match_ratio * m1[:, None])
    weight = plan[ii, jj]
    matched = np.stack([ia[ii], jb[jj]], axis=1).astype(np.int64)
    registration = None
    if len(matched) >= 3:
        try:
            registration = fit_similarity(mesh_a.vertices[matched[:, 0]], mesh_b.vertices[matched[:, 1]], weight)
        except ValueError:
            registration = None  # degenerate (collinear) matches; documented as None
    return Comparison(
        distance=float(distance),
        correspondence=correspondence.astype(np.int64),
        matched=matched,
        matched_weight=weight,
        mass1=m1,
        mass2=m2,
        registration=registration,
        result=res,
        signature=signature,
        transport=transport,
        self_energies=self_e,
        history=hist,
        sample_a=sub_a,
        sample_b=sub_b,
    )


def _energy_grid(out: Any) -> np.ndarray:
    """Accept `wks_energies`' return value: the grid itself, or a (grid, sigma) pair / object with ``energies``."""
    if hasattr(out, "energies"):
        out = out.energies
    elif isinstance(out, tuple):
        out = out[0]
    return np.asarray(out, dtype=np.float64)


def _spectrum_cache(cache_dir: Any) -> Any:
    """The spectrum cache for a `Comparer`'s ``cache_dir``: the process-wide one (``$WPOT_CACHE_DIR``) for None,
    else one under that folder (memory only for False), as for the signatures."""
    if cache_dir is None:
        return True
    from wpot.cache import Cache
    from wpot.spectral import spectrum_cache

    return Cache("spectrum", max_entries=spectrum_cache.max_entries, max_bytes=spectrum_cache.max_bytes, cache_dir=cache_dir)


def _resolve_device(device: str | None) -> str:
    from wpot._warp import resolve_device

    return str(resolve_device(device))


def compare(
    mesh_a: Mesh,
    mesh_b: Mesh,
    *,
    signature: str = "wks",
    transport: str = "balanced",
    max_vertices: int | None = None,
    device: str | None = None,
    mass_penalty: float = DEFAULT_MASS_PENALTY,
    penalty_scale: str = "relative",
    **options: Any,
) -> Comparison:
    """Compare two meshes by statistical-physics optimal transport of their vertex signatures.

    One-shot form of `Comparer` (which see for every option, e.g. ``n_eigen``, ``solver_options``,
    ``fps_metric``); for many pairs, build one `Comparer` so signatures are computed once per shape
    and every shape shares one WKS energy grid.

    Returns
    -------
    Comparison : distance (U or SU, Eq. 27), correspondence (N_A,), matched pairs, masses, registration,
        and the solver's `OTResult`.
    """
    return Comparer(
        signature=signature, transport=transport, max_vertices=max_vertices, device=device, mass_penalty=mass_penalty,
        penalty_scale=penalty_scale, **options
    ).compare(mesh_a, mesh_b)
