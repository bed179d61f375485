"""Left from right: the orientation of a vertex map, and a shape's left/right (reflective) symmetry.

WKS, and every intrinsic signature, is blind to orientation: a body and its mirror image have the same
Laplace–Beltrami spectrum and eigenfunctions up to sign, so a WKS transport plan mixes the two sides of a
symmetric shape, and ZoomOut (`wpot.zoomout`) makes the map consistent with one side, on TOSCA often the
mirror one (the docs' Results page). Orientation is what tells the two apart, and it is cheap to measure extrinsically:

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

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from wpot._validate import vertex_map
from wpot.mesh import NO_OUTSIDE, Mesh, winding

__all__ = ["LOCAL_RADIUS", "OrientationWarning", "local_orientation", "map_score", "orientation_score",
           "orientation_terms", "spread", "terms_score", "unreadable", "winding"]

#: `local_orientation`'s neighbourhood, times sqrt(area)
LOCAL_RADIUS = 0.1


class OrientationWarning(UserWarning):
    """A mesh whose orientation cannot be read (inconsistent winding, or no enclosed volume)."""


def unreadable(mesh: Mesh) -> str:
    """Why the orientation of a map from or onto ``mesh`` cannot be read ("" when it can), with the repair: faces
    wound against their neighbours (a patch of them reverses the sign of every map there), or no enclosed
    volume to tell the outside by (`winding`)."""
    wound = mesh.misoriented_faces.size
    if wound:
        return f"has {wound} triangles wound against their neighbours (Mesh.cleaned() rewinds them)"
    if winding(mesh) == 0:
        return NO_OUTSIDE
    return ""


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
    terms = orientation_terms(mesh_a, mesh_b, t)
    if terms is None:
        side = "mesh_a" if winding(mesh_a) == 0 else "mesh_b"
        warnings.warn(f"the orientation of a map cannot be scored: {side} {NO_OUTSIDE}", OrientationWarning,
                      stacklevel=2)
        return float("nan")
    score = terms_score(*terms)
    if np.isnan(score):
        warnings.warn("the orientation of a map cannot be scored: every face of mesh_a maps to a degenerate "
                      "triangle", OrientationWarning, stacklevel=2)
    return score


def orientation_terms(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
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


def terms_score(num: np.ndarray, den: np.ndarray) -> float:
    """The area-weighted mean sign: sum num / sum den (NaN when every image is degenerate)."""
    total = float(den.sum())
    return float(num.sum()) / total if total > 0 else float("nan")


def map_score(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray) -> float:
    """`orientation_score` without its warnings (NaN when it cannot be read), for the callers that act on it."""
    terms = orientation_terms(mesh_a, mesh_b, t)
    return float("nan") if terms is None else terms_score(*terms)


def local_orientation(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike, *, radius: float = LOCAL_RADIUS
                      ) -> np.ndarray:
    """The orientation score of the map around each vertex of A, (N_A,) in [-1, 1] (NaN where every image
    nearby is degenerate, or where a winding cannot be read): `orientation_score`'s face terms summed over the
    faces at each vertex and spread over about ``radius`` sqrt(area) of A by repeated one-ring averaging.
    A ZoomOut map is often mirrored on some symmetric part only (both legs, say): its global score is then
    near 0 and this one is negative there."""
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    terms = orientation_terms(mesh_a, mesh_b, t)
    if terms is None:
        return np.full(mesh_a.n_vertices, np.nan)
    return spread(mesh_a, *terms, radius)


def spread(mesh_a: Mesh, num: np.ndarray, den: np.ndarray, radius: float) -> np.ndarray:
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
