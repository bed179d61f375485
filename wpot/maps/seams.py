"""Seams of a vertex map, and the regions they cut off re-anchored on the rest.

A map between two poses of a near-cylindrical body (a human) can be right on most of it and turned half round
on a region: the upper body with left and right and front and back exchanged, or both legs swapped. Such a
region keeps the map's orientation, so neither the functional-map energy nor the local orientation
(`wpot.maps.symmetry.keep_orientation`) sees it; what gives it away is its border. Across it, neighbouring
vertices of A land on far-apart places of B: a **seam**. So

1. `map_regions`: the edges of A whose two ends the map sends more than `SEAM_JUMP` sqrt(area(B)) farther
   apart than the edge is long (scaled to B's area) are seams; the connected regions of A that remain once
   they are cut are the map's regions, each with its share of A's area;
2. `reanchor`: when a region other than the largest holds at least `SEAM_REGION` of A's area, the vertices
   outside the largest region are mapped again from it. `SEAM_ANCHORS` vertices spread over the largest region
   (geodesic farthest-point samples) and their images are the anchors; an anchor whose distances to the other
   anchors disagree with its image's (a finger the map has wrong inside the largest region) is left out
   (`ANCHOR_OUTLIER`). Each vertex of A is described by its log geodesic distances to the anchors of A, each
   vertex of B by its distances to their images, and each vertex outside the largest region goes to the vertex
   of B with the nearest description (distances on the two shapes agree for a near-isometry, and the log
   weighs the near anchors most, whose distances a stretched pose changes least; the anchors' spread tells left
   from right and front from back). The map is then refined again (e.g. ZoomOut from a low resolution, which
   smooths the new borders).

Which region is right is decided by size alone: when the larger of two near-equal regions is the wrong one, the
whole map ends up on the wrong side (the docs' Results page).

The distances are shortest paths along the edges (`wpot.mesh.edge_paths`, as in the geodesic
farthest-point sampling of `wpot.sampling`): a few per cent longer than the geodesics, alike on both shapes, and
with no factorization to make, one pass per anchor on each shape, done only for maps with a seam. They place the
vertices as well as the heat method's geodesics did, for less time (the docs' Results page).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from wpot._validate import vertex_map
from wpot.cost import nearest_rows
from wpot.mesh import Mesh, edge_paths

__all__ = ["LOG_OFFSET", "SEAM_ANCHORS", "SEAM_JUMP", "SEAM_REGION", "map_regions", "reanchor"]

#: an edge of A whose ends the map sends farther apart than its length by this (times sqrt(area(B))) is a
#: seam. Chosen on FAUST pairs outside its test list, checked on TOSCA pairs outside it (the docs' Results page)
SEAM_JUMP = 0.05
#: a region cut off by seams, other than the largest, with at least this share of A's area makes `reanchor`
#: map everything outside the largest region again (chosen with `SEAM_JUMP`)
SEAM_REGION = 0.03
#: anchors on the largest region (geodesic farthest-point samples) whose distances describe the other vertices
SEAM_ANCHORS = 32
#: an anchor whose distortion is more than this many times the median anchor's is not used (`_consistent`;
#: with `LOG_OFFSET`, set on TOSCA's development failures, checked on FAUST's and on both test sets)
ANCHOR_OUTLIER = 2.0
#: anchors always kept (the least distorted)
MIN_ANCHORS = 8
#: the offset of the log distances, in mean edge lengths (also `wpot.maps.locate`'s polish)
LOG_OFFSET = 3.0


def map_regions(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The regions of A that a map's seams cut apart (the module docstring).

    Returns ((N_A,) int64 region label of each vertex of A, (R,) float64 each region's share of A's area, by
    Voronoi area). A map without seams has one region per connected component of A."""
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    e = mesh_a.edges
    pos = mesh_b.vertices
    scale = np.sqrt(mesh_b.area)
    # how much farther apart than the edge itself (scaled to B's area) its ends land: an isometry keeps each
    # edge's length, so long edges (coarse or anisotropic meshes) are no seams by themselves
    stretch = (np.linalg.norm(pos[t[e[:, 0]]] - pos[t[e[:, 1]]], axis=1)
               - mesh_a.edge_lengths * (scale / np.sqrt(mesh_a.area)))
    kept = e[stretch <= SEAM_JUMP * scale]
    n = mesh_a.n_vertices
    graph = coo_matrix((np.ones(len(kept)), (kept[:, 0], kept[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    areas = mesh_a.voronoi_areas
    return labels.astype(np.int64), np.bincount(labels, weights=areas) / areas.sum()


def reanchor(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike,
             refine: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, bool]:
    """Map the regions a map's seams cut off again from its largest region (the module docstring).

    Parameters
    ----------
    mesh_a, mesh_b : two connected surfaces, near-isometric
    correspondence : (N_A,) int, a vertex of B for each vertex of A
    refine : applied to the re-anchored map (N_A,) -> (N_A,), e.g. ZoomOut from a low resolution

    Returns
    -------
    (map (N_A,) int64, whether it was changed): the given map when no region but the largest reaches
    `SEAM_REGION` of A's area.
    """
    for side, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
        if m.n_components != 1:
            raise ValueError(f"reanchor needs connected surfaces; {side} has {m.n_components} components")
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    labels, shares = map_regions(mesh_a, mesh_b, t)
    if np.sum(shares >= SEAM_REGION) < 2:
        return t, False
    main = int(np.argmax(shares))
    inside = labels == main
    anchors, rows_a = _anchors(mesh_a, np.nonzero(inside)[0])
    rows_a = rows_a.T / np.sqrt(mesh_a.area)  # (N_A, anchors)
    rows_b = edge_paths(mesh_b, t[anchors]).T / np.sqrt(mesh_b.area)  # (N_B, anchors)
    kept = _consistent(rows_a[anchors], rows_b[t[anchors]])
    # log distances: a stretch of the pose changes long distances more than short ones, and the near anchors,
    # which place a vertex best, weigh most; the offset (a few edges) keeps an anchor's own distance finite
    h = LOG_OFFSET * max(m.mean_edge_length / np.sqrt(m.area) for m in (mesh_a, mesh_b))
    desc_a, desc_b = np.log(rows_a[:, kept] + h), np.log(rows_b[:, kept] + h)
    out = t.copy()
    off = np.nonzero(~inside)[0]
    out[off] = nearest_rows(np.ascontiguousarray(desc_a[off]), np.ascontiguousarray(desc_b))[0]
    if refine is not None:
        out = np.asarray(refine(out), dtype=np.int64)
    return out, True


def _anchors(mesh: Mesh, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(≤ SEAM_ANCHORS,) int64 farthest-point samples of the vertices ``region`` by shortest paths along the
    edges, from the one farthest from their centroid, and their distances to every vertex, (anchors, N)."""
    x = mesh.vertices[region]
    anchors = [int(region[np.argmax(np.linalg.norm(x - x.mean(axis=0), axis=1))])]
    rows = [edge_paths(mesh, anchors[0])]
    nearest = rows[0][region]
    for _ in range(min(SEAM_ANCHORS, region.size) - 1):
        anchors.append(int(region[np.argmax(nearest)]))
        rows.append(edge_paths(mesh, anchors[-1]))
        nearest = np.minimum(nearest, rows[-1][region])
    return np.asarray(anchors, dtype=np.int64), np.stack(rows)


def _consistent(dist_a: np.ndarray, dist_b: np.ndarray) -> np.ndarray:
    """The anchors whose images keep their distances to the others. ``dist_a`` (n, n): the anchors' geodesic
    distances on A, ``dist_b`` (n, n) their images' on B. Each anchor's distortion is the median over the other
    anchors of |d_A − d_B|; the most distorted anchor is dropped while its distortion is more than
    `ANCHOR_OUTLIER` times the median anchor's (a mapped-away finger, or a limb the map has wrong, inside the
    largest region), down to `MIN_ANCHORS`. Returns the kept anchors' positions (sorted)."""
    gap = np.abs(dist_a - dist_b)
    keep = list(range(len(gap)))
    while len(keep) > MIN_ANCHORS:
        distortion = np.median(gap[np.ix_(keep, keep)], axis=1)
        worst = int(np.argmax(distortion))
        if distortion[worst] <= ANCHOR_OUTLIER * np.median(distortion):
            break
        keep.pop(worst)
    return np.asarray(keep, dtype=np.int64)
