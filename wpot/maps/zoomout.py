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
only (both legs); on a near-cylindrical body (a human) it can also settle on a half turn, left and right and
front and back exchanged, which keeps orientation and is still wrong. So by default (``orient=True``) three
candidates are brought to k = `CHOICE_K`:

1. the given map, refined by ZoomOut from k_start;
2. the point maps of two functional maps fitted, at k = `wpot.maps.fmap.FMAP_K`, from WKS descriptors with the
   orientation term (`wpot.maps.fmap`): descriptors from the first `wpot.maps.fmap.FMAP_SPECTRUM` eigenpairs,
   and from all of them. They do not use the given map, so they also rescue a map that is wrong beyond mirroring.

Each is scored by the energy the second functional map minimizes (`wpot.maps.fmap.FmapEnergy`: descriptors,
Laplacian and descriptor commutativity, and orientation, with pyfmaps' weights), evaluated at the k =
`wpot.maps.fmap.FMAP_K` functional map of the candidate's point map; the lowest goes on to k_end, unless two
candidates agree and the third disagrees with both (`AGREEMENT`): the third is then outvoted whatever its energy.
The energy is mostly its orientation term, which a half turn keeps, so a half turn can score lowest; two
candidates that agree with each other and not with it outweigh it (`_choose`). The candidates
are refined and compared on `CHOICE_SAMPLES` farthest-point samples a mesh (each functional map fitted to the
samples' map by least squares), and only the chosen one is mapped at every vertex. Refining before
comparing lets each candidate settle on one side everywhere, so that a map right on the body and mirrored on a
limb is not compared with maps that are still coarse. A map can still be right on the body and mirrored on a
symmetric part (both hind legs of a quadruped), which the energy hardly sees: where the chosen map reverses
orientation locally, its vertices are sent through the shape's left/right symmetry
(`wpot.maps.symmetry.keep_orientation`, which keeps the mended map only when it orients better). A map can also
be right on most of the body and turned half round on a region (the upper body, or both legs swapped), which
keeps orientation: the region's border is then a seam, where neighbouring vertices land far apart, and the
regions the seams cut off are mapped again from the largest one by distances along the surface to anchors on
it (`wpot.maps.seams.reanchor`), and the last rounds start again from k = `SEAM_K`. The same energy gives
the result's orientation confidence (`ZoomOutResult`): a map composed with a left/right symmetry has the same intrinsic
terms, with the orientation term replaced by its reversed form (``orient_reversed``), so the energy of the
mirrored map is known without finding the symmetry, and the confidence compares the chosen map's energy with
that of its mirror and of a candidate on another side.

Large meshes: above ``max_vertices`` (`ZOOMOUT_MAX_VERTICES`) vertices a mesh is matched through a simplified
copy (`wpot.simplify`): the given map is carried to the copies, refined there, and carried back to every vertex
(`wpot.simplify.lift_map`). The spectra, the candidates and every nearest-neighbour search then cost what they
cost at the copy's size. Left and right are decided at a smaller size still: above ``orient_vertices``
(`ORIENT_MAX_VERTICES`) vertices, the candidates, their choice, the mending and the re-anchoring run between
simplified copies of that many vertices, and only the last rounds run on the meshes themselves, from the chosen
map carried back to them; as that map is only as fine as the copies, they start again from `SEAM_K`. Those
steps read the map at every vertex and on every face, which at the meshes' own size costs more than the choice
they serve; the copies keep what they look at (limbs, the left/right symmetry, seams at 0.05 sqrt(area)).

"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from wpot._validate import boolean, integer_at_least, vertex_map
from wpot.maps.fmap import (FMAP_DESCRIPTORS, FMAP_K, FMAP_SPECTRUM, FmapEnergy, SpectralOperators, point_map,
                             squared_eigenfunction_terms)
from wpot.maps.zoom import ZOOMOUT_K_START, ZOOMOUT_N_EIGEN, ZOOMOUT_SAMPLES, ZOOMOUT_STEP, Refiner, positive_int, spectral_basis, spectrum_size
from wpot.maps.orientation import OrientationWarning, unreadable
from wpot.maps.seams import reanchor
from wpot.maps.symmetry import keep_orientation
from wpot.mesh import Mesh, MeshWarning, named
from wpot.signatures._wks import wks_energies, wks_weights
from wpot.simplify import lift_map, simplify
from wpot.spectral import SPECTRAL_MAX_VERTICES

__all__ = ["zoomout", "ZoomOutResult", "spectrum_size", "ZOOMOUT_N_EIGEN", "ZOOMOUT_K_END", "ZOOMOUT_SAMPLES",
           "AGREEMENT", "ORIENTATION_DOUBT", "CHOICE_K", "CHOICE_SAMPLES", "SEAM_K", "ZOOMOUT_MAX_VERTICES",
           "ORIENT_MAX_VERTICES"]

#: default largest spectral resolution (fewer when fewer eigenpairs are available). The schedule (k = 10..200 by
#: 5) was chosen on TOSCA test pairs: a finer step or another start scored lower (the docs' Results page)
ZOOMOUT_K_END = 200
#: a map whose `ZoomOutResult.orientation_confidence` is below this should be checked for left/right (chosen on
#: FAUST pairs outside its test list, reported on the TOSCA and FAUST test pairs: the docs' Results page)
ORIENTATION_DOUBT = 0.1
#: the spectral resolution to which every candidate is refined before they are compared (chosen on FAUST pairs
#: outside its test list, checked on TOSCA pairs outside it: the docs' Results page)
CHOICE_K = 60
#: meshes of more vertices are refined through simplified copies of this many (`wpot.simplify`): the spectral
#: signatures' `wpot.spectral.SPECTRAL_MAX_VERTICES`, so that both read one cached spectrum of each copy
ZOOMOUT_MAX_VERTICES = SPECTRAL_MAX_VERTICES
#: meshes of more vertices have left and right decided on simplified copies of this many (the module docstring):
#: above the 5k data sets' largest meshes (5,004 vertices), on which every choice of the oriented refinement was
#: made and measured, so that they are decided as they were
ORIENT_MAX_VERTICES = 5500
#: farthest-point samples a mesh on which the candidates are brought to `CHOICE_K` and compared, and the mended
#: map refined again (at most ``samples``; the rounds after the choice use ``samples``). Chosen on FAUST pairs
#: outside its test list against 2,000, 1,500 and 700, checked on TOSCA pairs outside it (the docs' Results page)
CHOICE_SAMPLES = 1000
#: the resolution from which a map whose seams' regions were mapped again is refined to k_end
#: (`wpot.maps.seams.reanchor`; chosen on FAUST pairs outside its test list, the docs' Results page)
SEAM_K = 20
#: the candidate whose energy (descriptors from every eigenpair of `spectral_basis`) ranks all candidates
JUDGE = "descriptors_full"
#: two candidate maps whose images lie, at the median vertex, farther apart than this (times sqrt(area(B)))
#: are on different sides (`_choose`, `ZoomOutResult.orientation_confidence`)
AGREEMENT = 0.1


@dataclass(frozen=True)
class ZoomOutResult:
    """A refined vertex map (`zoomout`), and how sure its left/right choice is.

    Attributes
    ----------
    map : (N_A,) int64, for each vertex of A a vertex of B
    orientation_confidence : in [0, 1]: ``1 − E / E_other`` with E the chosen candidate's energy
        (`wpot.maps.fmap.FmapEnergy`, at k = `wpot.maps.fmap.FMAP_K`) and E_other the lowest energy of a map on
        another side: its own mirror image (E with the orientation term reversed) or the other candidate when
        the two disagree (their images at the median vertex more than `AGREEMENT` sqrt(area(B)) apart). Near 0:
        another side fits about as well, doubt the map (0 when an outvoted candidate had the lower energy). NaN
        when the orientation could not be weighed (``orient=False``, several connected components, or a surface
        with no readable outside)
    candidate : the candidate chosen, ``"given"`` (the map passed in, refined), ``"descriptors"`` or
        ``"descriptors_full"`` (the orientation-aware functional maps'); ``"given"`` when there was no choice
    energies : each candidate's energy, by name, and its mirror image's (``"<name>_mirror"``)
    mended : whether the chosen candidate was mirrored on a part and mended there through the shape's left/right
        symmetry (the confidence weighs the choice made before)
    coarse_vertices : (n_A, n_B), the vertex counts of the simplified copies the map was refined on
        (``max_vertices``); None when it was refined on the meshes themselves
    orientation_vertices : (n_A, n_B), the vertex counts of the copies left and right were decided on
        (``orient_vertices``); None when on the meshes the map was refined on (or not decided)
    reanchored : whether regions cut off by the chosen map's seams (a half turn of the upper body, swapped
        legs) were mapped again from the rest of it (`wpot.maps.seams.reanchor`)
    """

    map: np.ndarray
    orientation_confidence: float = float("nan")
    candidate: str = "given"
    energies: dict = field(default_factory=dict)
    mended: bool = False
    coarse_vertices: tuple[int, int] | None = None
    reanchored: bool = False
    orientation_vertices: tuple[int, int] | None = None

    def __array__(self, dtype=None, copy=None):
        return self.map if dtype is None else self.map.astype(dtype)


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
    max_vertices: int | None = ZOOMOUT_MAX_VERTICES,
    orient_vertices: int | None = ORIENT_MAX_VERTICES,
) -> ZoomOutResult:
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
        serves); the oriented candidates' WKS descriptors use the first `wpot.maps.fmap.FMAP_SPECTRUM` of them
        and all of them
    orient : keep left and right apart (default): bring three candidates to k = `CHOICE_K`, the given map
        refined and the maps of two orientation-aware functional maps fitted from WKS descriptors (only for two
        connected surfaces with a readable outside), and go on to k_end with the one of lowest functional-map
        energy (the module docstring). False: the plain ZoomOut of the given map, which settles
        on either side
    samples : vertices of each mesh (farthest-point samples) mapped in the rounds before the last, which maps
        every vertex (default `ZOOMOUT_SAMPLES` = 2000; the oriented candidates are compared on at most
        `CHOICE_SAMPLES` of them); None maps every vertex in every round
    max_vertices : a mesh of more vertices is refined through a simplified copy of this many (`wpot.simplify`;
        default `ZOOMOUT_MAX_VERTICES`), and the map carried back to its every vertex; None: never. The other
        options then apply to the copies
    orient_vertices : with ``orient``, a mesh (or ``max_vertices``' copy) of more vertices has left and right
        decided on a simplified copy of this many (default `ORIENT_MAX_VERTICES`), whose spectrum is its own
        default `spectrum_size`; the rounds after the choice run on the meshes. None: never

    Returns
    -------
    `ZoomOutResult`: the refined map (N_A,) int64 (also ``np.asarray(result)``), its orientation confidence,
    and which candidate was chosen.

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
    if max_vertices is not None:
        max_vertices = integer_at_least("max_vertices", max_vertices, 100)
    if orient_vertices is not None:
        orient_vertices = integer_at_least("orient_vertices", orient_vertices, 100)
    if max_vertices is not None and max(mesh_a.n_vertices, mesh_b.n_vertices) > max_vertices:
        sa, sb = simplify(mesh_a, max_vertices), simplify(mesh_b, max_vertices)
        res = zoomout(sa.coarse, sb.coarse, sa.restrict_map(sb, t), k_start=k_start, k_end=k_end, step=step,
                      n_eigen=n_eigen, orient=orient, samples=samples, max_vertices=None,
                      orient_vertices=orient_vertices)
        return dataclasses.replace(res, map=lift_map(sa, sb, res.map),
                                   coarse_vertices=(sa.coarse.n_vertices, sb.coarse.n_vertices))
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

    if not orient or not _orientable(mesh_a, mesh_b):
        return ZoomOutResult(refine(t, k_start, k_end, step))
    res, k_next = _decided(refine, t, orient_vertices, k_start, k_end, step)
    # on to k_end from the samples' images; or, with no rounds left, once more at CHOICE_K with the functional map
    # of every vertex (as ZoomOut's last round does)
    k_sel = min(CHOICE_K, k_end)
    out = refine(res.map, k_sel, k_sel, step) if k_next > k_end else refine(res.map, k_next, k_end, step)
    return dataclasses.replace(res, map=out)


def _decided(refine: Refiner, t: np.ndarray, orient_vertices: int | None, k_start: int, k_end: int, step: int
             ) -> tuple[ZoomOutResult, int]:
    """`_oriented` between ``refine``'s meshes, or between their copies (`_orientation_copies`) with the chosen
    map carried back to the meshes. Returns the result, whose map (N_A,) is still to be refined on, and the
    resolution that refinement goes on from."""
    mesh_a, mesh_b = refine.mesh_a, refine.mesh_b
    choice_samples = None if refine.samples is None else min(refine.samples, CHOICE_SAMPLES)
    copies = _orientation_copies(mesh_a, mesh_b, orient_vertices)
    if copies is None:
        return _oriented(refine.with_samples(choice_samples), mesh_a, mesh_b, t,
                         _oriented_problems(mesh_a, mesh_b, refine.n_eigen, k_end), k_start, k_end, step)
    ca, cb = copies
    res, k_next = _oriented(Refiner(ca.coarse, cb.coarse, None, choice_samples), ca.coarse, cb.coarse,
                            ca.restrict_map(cb, t), _oriented_problems(ca.coarse, cb.coarse, None, k_end),
                            k_start, k_end, step)
    # a map carried back from the copies is only as fine as their vertices: like a re-anchored one, its last
    # rounds start again from SEAM_K
    return dataclasses.replace(res, map=lift_map(ca, cb, res.map),
                               orientation_vertices=(ca.coarse.n_vertices, cb.coarse.n_vertices)), min(k_next, SEAM_K)


def _orientation_copies(mesh_a: Mesh, mesh_b: Mesh, orient_vertices: int | None):
    """The simplified copies (`wpot.simplify.Simplified`) of A and B on which left and right are decided, or None
    to decide on the meshes themselves: when neither has more than ``orient_vertices`` vertices, or when a copy
    could not be oriented (several pieces, or no readable outside, where the meshes themselves have one)."""
    if orient_vertices is None or max(mesh_a.n_vertices, mesh_b.n_vertices) <= orient_vertices:
        return None
    with warnings.catch_warnings():
        # a defect the decimation leaves (a non-manifold edge) is the copy's, not the caller's mesh's: the copy is
        # checked below, and one that cannot be oriented is not used
        warnings.simplefilter("ignore", MeshWarning)
        copies = simplify(mesh_a, orient_vertices), simplify(mesh_b, orient_vertices)
    if any(_unreadable(c.coarse) for c in copies):
        return None
    return copies


def _oriented(choice: Refiner, mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray, problems: dict[str, FmapEnergy],
              k_start: int, k_end: int, step: int) -> tuple[ZoomOutResult, int]:
    """`zoomout`'s decision of left and right (``orient=True``) between A and B, two connected surfaces with a
    readable outside: the candidates brought to `CHOICE_K` by ``choice`` (on its samples) and compared, the chosen
    one mended and re-anchored (the module docstring). Returns the result, whose map (N_A,) is the chosen one
    still to be refined on, and the resolution that refinement goes on from."""
    k_sel = min(CHOICE_K, k_end)
    # the candidates are brought to k_sel and compared on the choice's samples; only the chosen one maps every vertex
    sa, sb = choice.points(mesh_a), choice.points(mesh_b)
    starts = {"given": (t[sa], k_start)}
    for name, problem in problems.items():
        starts[name] = (sb[point_map(problem.ops_a.phi[sa], problem.ops_b.phi[sb], problem.fit())], problem.k + step)
    cands = {n: choice.coarse(t0, min(k0, k_sel), k_sel, step) for n, (t0, k0) in starts.items()}
    judge = problems[JUDGE]
    fit_a, phi_b = np.linalg.pinv(judge.ops_a.phi[sa]), judge.ops_b.phi  # least squares on the samples
    terms = {n: judge.terms(fit_a @ phi_b[c]) for n, (_, c) in cands.items()}
    energies = {n: sum(v for k, v in tm.items() if k != "orient_reversed") for n, tm in terms.items()}
    # a map composed with a left/right symmetry: the same intrinsic terms, the orientation term reversed
    mirrors = {n: energies[n] - tm["orient"] + tm["orient_reversed"] for n, tm in terms.items()}
    apart = _disagreements(mesh_b, {n: c for n, (_, c) in cands.items()})
    chosen = _choose(apart, energies)
    others = [mirrors[chosen]] + [energies[n] for n in cands if n != chosen and apart[frozenset((n, chosen))]]
    confidence = float(np.clip(1.0 - energies[chosen] / max(min(others), 1e-300), 0.0, 1.0))
    # right on the body and mirrored on a symmetric part (both hind legs): the energy hardly sees it, the local
    # orientation does; those vertices go through the shape's left/right symmetry, and the map, refined again
    # to CHOICE_K on the choice's samples, is kept when it orients better (`wpot.maps.symmetry.keep_orientation`)
    best, _, mended = keep_orientation(mesh_a, mesh_b, choice.full(cands[chosen][0]), refine=lambda m: choice.full(
        choice.coarse(m[sa], min(k_start, k_sel), k_sel, step)[0]))
    # right on most of the body and turned half round on a region (the upper body, both legs): the orientation
    # keeps it, the map's seams give it away; the regions they cut off are mapped again from the largest one
    # (`wpot.maps.seams.reanchor`), and the last rounds start again from a low resolution, SEAM_K
    best, reanchored = reanchor(mesh_a, mesh_b, best)
    if reanchored:
        k_next = min(SEAM_K, k_sel)
    else:
        k_next = k_sel + step if mended else max(k_sel + step, starts[chosen][1])
    res = ZoomOutResult(best, confidence, chosen, {**energies, **{f"{n}_mirror": e for n, e in mirrors.items()}},
                        mended, reanchored=reanchored)
    return res, k_next


def _unreadable(mesh: Mesh) -> str:
    """Why the orientation-aware candidates cannot be built on ``mesh`` ("" when they can): several connected
    components, or an orientation that cannot be read (`wpot.maps.orientation.unreadable`)."""
    if mesh.n_components != 1:
        return (f"has {mesh.n_components} connected components (Mesh.cleaned(keep_largest_component=True) keeps "
                "the largest)")
    return unreadable(mesh)


def _disagreements(mesh_b: Mesh, images: dict[str, np.ndarray]) -> dict[frozenset, bool]:
    """`_disagree` for every two candidates, keyed by the pair of names. ``images``: each candidate's images
    (vertices of B) of the same vertices of A."""
    names = list(images)
    return {frozenset((p, q)): _disagree(mesh_b, images[p], images[q]) for i, p in enumerate(names)
            for q in names[i + 1:]}


def _choose(apart: dict[frozenset, bool], energies: dict[str, float]) -> str:
    """The candidate that goes on to k_end: of the lowest energy, among the two that agree when exactly one pair
    of candidates agrees (`_disagreements`; with three, the third is outvoted), else among all; on a tie
    ``"given"``, then the first in ``energies``' order. Chosen on FAUST pairs outside its test list, checked on
    TOSCA pairs outside it (the docs' Results page)."""
    agree = [pair for pair, differ in apart.items() if not differ]
    pool = [n for n in energies if len(agree) != 1 or n in agree[0]]
    return min(pool, key=lambda n: (energies[n], n != "given"))


def _disagree(mesh_b: Mesh, t1: np.ndarray, t2: np.ndarray) -> bool:
    """Whether two maps into B (of the same vertices of A) send the median vertex more than `AGREEMENT`
    sqrt(area(B)) apart."""
    gap = np.linalg.norm(mesh_b.vertices[t1] - mesh_b.vertices[t2], axis=1)
    return bool(np.median(gap) > AGREEMENT * np.sqrt(mesh_b.area))


def _orientable(mesh_a: Mesh, mesh_b: Mesh) -> bool:
    """Whether zoomout can weigh left against right between A and B; when not, an `OrientationWarning` names the
    mesh and its repair (`_unreadable`)."""
    for side, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
        why = _unreadable(m)
        if why:
            warnings.warn(named(m.name, f"{side} {why}, so zoomout cannot weigh left against right: the map is plain "
                                "ZoomOut's, which may be mirrored (orientation_confidence NaN)"),
                          OrientationWarning, stacklevel=3)
            return False
    return True


def _oriented_problems(mesh_a: Mesh, mesh_b: Mesh, n_eigen: int | None, k_end: int) -> dict[str, FmapEnergy]:
    """The orientation-aware functional-map energies between A and B, two surfaces `_orientable`
    (`wpot.maps.fmap.FmapEnergy` at k = min(`wpot.maps.fmap.FMAP_K`, k_end)), by candidate name: WKS descriptors
    from the first `wpot.maps.fmap.FMAP_SPECTRUM` eigenpairs (``"descriptors"``) and from all of them (`JUDGE`,
    whose energy also ranks the candidates; one problem when there are no more). The descriptors' terms are each
    shape's cached `wpot.maps.fmap.squared_eigenfunction_terms` weighed by the pair's WKS weights."""
    meshes = (mesh_a, mesh_b)
    k = min(FMAP_K, k_end)
    specs = [spectral_basis(m, n_eigen) for m in meshes]
    ops = [SpectralOperators(m, s, k) for m, s in zip(meshes, specs)]

    # the terms of every WKS descriptor are weighted sums of those of the squared eigenfunctions, once per shape
    squares = [squared_eigenfunction_terms(o, s) for o, s in zip(ops, specs)]

    def problem(spectra) -> FmapEnergy:
        # scale-invariant WKS on one grid for both shapes, every second energy of a grid twice as fine (pyfmaps')
        grid = wks_energies(spectra, n_energies=2 * FMAP_DESCRIPTORS, scale_invariant=True)
        desc = []
        for sq, s in zip(squares, spectra):
            w = wks_weights(s.rescaled(normalized=True).nonzero_evals, grid.energies, grid.sigma)[:, ::2]
            desc.append(sq.combined(np.pad(w, ((0, sq.coefficients.shape[1] - len(w)), (0, 0)))))
        return FmapEnergy(*ops, *desc)

    low = [s.first(FMAP_SPECTRUM) for s in specs]
    if all(a is b for a, b in zip(low, specs)):
        return {JUDGE: problem(specs)}
    return {"descriptors": problem(low), JUDGE: problem(specs)}
