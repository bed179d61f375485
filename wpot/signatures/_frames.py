"""LD-SIFT's local frames (paper Eq. 1 and 28): each vertex's scale S(v) = K D(v) and the dominant plane of its
neighbourhood, shared by the descriptor (`wpot.signatures._ldsift`) and the thickness column
(`wpot.signatures._thickness`), whose rays lie in these frames."""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from wpot.mesh import Mesh

__all__ = ["DEGENERATE_RTOL", "MIN_NEIGHBOURS", "LocalFrames", "check_K", "check_mesh", "local_frames", "positive_finite"]

#: a vertex's covariance neighbourhood N(v) must hold at least this many vertices besides v itself;
#: when the ball of radius S(v) holds fewer, it is grown to the MIN_NEIGHBOURS nearest vertices
MIN_NEIGHBOURS = 3
#: the covariance counts as rank-deficient (no dominant plane) when lambda_2 <= DEGENERATE_RTOL * lambda_1
DEGENERATE_RTOL = 1e-10


@dataclass(frozen=True)
class LocalFrames:
    """Per-vertex LD-SIFT frames (paper Eq. 1 and 28).

    Attributes
    ----------
    frames : (N, 3, 3) float64, rows ``e1, e2, n``: right-handed orthonormal, ``n`` outward
    half_sizes : (N,) float64, ``S(v) = K D(v)``, the half width of each depth image
    n_neighbours : (N,) int64, number of vertices besides v in the covariance neighbourhood
    grown : (N,) bool, neighbourhood grown beyond radius S(v) (fewer than `MIN_NEIGHBOURS` inside)
    degenerate : (N,) bool, rank-deficient covariance: the frame was built from the vertex normal
    """

    frames: np.ndarray
    half_sizes: np.ndarray
    n_neighbours: np.ndarray
    grown: np.ndarray
    degenerate: np.ndarray


def check_mesh(mesh: Mesh) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    d = mesh.one_ring_mean_edge_length
    bad = np.nonzero(~np.isfinite(d) | ~(d > 0))[0]
    if bad.size:
        raise ValueError(
            f"{bad.size} vertices have no edge of positive length (unreferenced or collapsed), e.g. vertices "
            f"{bad[:10].tolist()}; LD-SIFT needs D(v) > 0 at every vertex (Mesh.cleaned() removes them)"
        )
    return mesh


def positive_finite(value: float, name: str, unit: str = "") -> float:
    """``value`` as a float, or ValueError naming ``name`` unless it is a positive finite number (not a bool)."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a positive finite number{unit}, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number{unit}, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number{unit}, got {value!r}")
    return v


def check_K(K: float) -> float:
    return positive_finite(K, "K")


def check_edge(edge: float) -> float:
    return positive_finite(edge, "edge", " (an edge length in the mesh's units)")


def common_edge(meshes) -> float:
    """One edge length for a set of meshes (a library, or a part and its whole): the median over the meshes of
    each one's median vertex mean edge length D(v), to 3 significant digits (so that the signature cache keys
    it is part of stay the same when a library changes a little). So it scales with the meshes exactly under
    powers of ten (millimetres to metres), and within 0.5 % under other factors (the docs' Results page, §8.1:
    what that does to `locate`)."""
    meds = [float(np.median(check_mesh(m).one_ring_mean_edge_length)) for m in meshes]
    if not meds:
        raise ValueError("common_edge needs at least one mesh")
    return float(f"{np.median(meds):.3g}")


def local_frames(mesh: Mesh, *, K: float = 3.0, edge: float | None = None) -> LocalFrames:
    """Scale S(v) and dominant-plane frame (e1, e2, n) of every vertex (paper Eq. 1 and 28).

    ``N(v)`` is the set of vertices within Euclidean distance ``S(v) = K D(v)`` of v, v included (a
    `scipy.spatial.cKDTree` ball query). Corner cases:

    * fewer than `MIN_NEIGHBOURS` vertices besides v in the ball: ``N(v)`` becomes v and its
      `MIN_NEIGHBOURS` nearest vertices (the radius grows to the third-nearest distance); ``S(v)``,
      the image size, is unchanged. Flagged in ``grown``.
    * rank-deficient covariance (``lambda_2 <= 1e-10 lambda_1``: the neighbours are collinear or
      coincide), so there is no dominant plane: ``n`` is the area-weighted vertex normal, ``e1`` the
      leading eigenvector projected onto the plane normal to n (any unit vector normal to n when that
      projection vanishes), ``e2 = n x e1``. Flagged in ``degenerate``, and a `UserWarning` names them.

    ``n`` is turned to the outside (``n . vertex_normal >= 0``) by flipping ``e2``; when the vertex
    normal is perpendicular to the plane's normal, the eigen-solver's sign is kept.

    Parameters
    ----------
    mesh : `wpot.Mesh` with D(v) > 0 at every vertex
    K : scale factor (paper: 3)
    edge : one edge length, in the mesh's units, taken as D(v) at every vertex (``S = K edge``): a scale that does
        not follow the mesh's density, so two meshes of one surface at different densities get the same images;
        None (default): each vertex's own mean edge length, the paper's Eq. 1

    Returns
    -------
    `LocalFrames`
    """
    mesh = check_mesh(mesh)
    K = check_K(K)
    v = mesh.vertices
    n_v = len(v)
    S = K * (mesh.one_ring_mean_edge_length if edge is None else np.full(n_v, check_edge(edge)))
    tree = cKDTree(v)
    balls = tree.query_ball_point(v, r=S)
    counts = np.fromiter((len(b) for b in balls), dtype=np.int64, count=n_v)
    grown = counts - 1 < MIN_NEIGHBOURS
    if grown.any():
        k = min(MIN_NEIGHBOURS + 1, n_v)
        _, nn = tree.query(v[grown], k=k)
        for row, i in zip(np.atleast_2d(nn), np.nonzero(grown)[0]):
            balls[i] = list(row)
        counts[grown] = k
    members = np.concatenate([np.asarray(b, dtype=np.int64) for b in balls])
    owner = np.repeat(np.arange(n_v), counts)
    d = v[members] - v[owner]  # relative to v: Eq. 28 is translation invariant, this keeps precision
    cnt = counts.astype(np.float64)
    mean = np.stack([np.bincount(owner, d[:, a], n_v) for a in range(3)], axis=1) / cnt[:, None]
    cov = np.empty((n_v, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            m2 = np.bincount(owner, d[:, a] * d[:, b], n_v) / cnt
            cov[:, a, b] = cov[:, b, a] = m2 - mean[:, a] * mean[:, b]
    lam, vec = np.linalg.eigh(cov)  # ascending
    e1 = vec[:, :, 2]
    e2 = vec[:, :, 1]
    nrm = np.cross(e1, e2)
    vn = mesh.vertex_normals
    degenerate = lam[:, 1] <= DEGENERATE_RTOL * np.maximum(lam[:, 2], np.finfo(float).tiny)
    if degenerate.any():
        idx = np.nonzero(degenerate)[0]
        nd = vn[idx]
        t = e1[idx] - np.sum(e1[idx] * nd, axis=1, keepdims=True) * nd
        tn = np.linalg.norm(t, axis=1)
        small = tn < 1e-6
        if small.any():  # any unit vector normal to n
            a = np.where(np.abs(nd[small, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
            t[small] = a - np.sum(a * nd[small], axis=1, keepdims=True) * nd[small]
            tn[small] = np.linalg.norm(t[small], axis=1)
        e1[idx] = t / tn[:, None]
        nrm[idx] = nd
        e2[idx] = np.cross(nd, e1[idx])
        warnings.warn(
            f"{idx.size} vertices have a rank-deficient neighbourhood covariance (collinear or coincident "
            f"neighbours, e.g. vertices {idx[:10].tolist()}); their LD-SIFT frames use the vertex normal. "
            "A larger K, or a cleaner mesh, avoids this.",
            UserWarning,
            stacklevel=2,
        )
    flip = np.sum(nrm * vn, axis=1) < 0
    nrm[flip] *= -1.0
    e2[flip] *= -1.0
    frames = np.stack([e1, e2, nrm], axis=1)
    return LocalFrames(frames=frames, half_sizes=S, n_neighbours=counts - 1, grown=grown, degenerate=degenerate)
