"""Locating a part in a whole shape and mapping it, by geodesic consistency.

Partial transport (Eq. 17–26) finds where a part's signatures fit in a whole, but each vertex chooses on its
own: between two poses of one body, LD-SIFT (extrinsic) follows the pose and WKS (intrinsic) is bent by the
part's boundary, so the transport's map lands on the true place for few vertices and nothing ties
neighbouring vertices together. What a pose change keeps is the intrinsic geometry: a part cut from one pose is
isometric to its place in another, so geodesic distances measured inside the part are, up to its boundary,
those between the matching points of the whole. `locate_part` uses the signatures only to propose matches and
geodesic distances to choose among them and to fill in the map:

1. **Candidates.** ``n_anchors`` farthest-point samples of the part (the anchors), each with the
   ``n_candidates`` vertices of the whole whose signatures are nearest (the signature's own cost).
2. **Consistency** (spectral matching, Leordeanu & Hebert 2005). Two candidate matches (a, b) and (a', b')
   agree when ``|d_P(a, a') − d_W(b, b')| ≲ σ = tol·√area(W) + rel_tol·min(d_P, d_W)``; the agreement matrix
   ``exp(−(Δd/σ)²/2)`` (zero between two candidates of one anchor) has a leading eigenvector whose large
   entries are the largest mutually consistent set. Matches are taken greedily in that order, each at most
   one per anchor and within 3 σ of every match already taken. Wrong candidates rarely agree with many
   others; mirror images of the right ones do (a left/right reflection is an isometry), see step 4. The part's
   distances are read at the whole's scale: as they are (``scale="same"``), times a given factor, or
   (``scale="fit"``) times the factor of a grid from 1 / `SCALE_RANGE` to `SCALE_RANGE` whose consistent set
   agrees most (the sum of its agreement matrix), for shapes that were scaled one by one.
3. **Dense map.** Every vertex v of the part gets the vertex w of the whole whose geodesic distances to the
   matched anchors' images are nearest its own to the anchors: ``argmin_w ‖d_P(v, A) − d_W(w, B)‖``. Then,
   ``n_rounds`` times, ``n_refine`` farthest-point samples of the part and their current images serve as the
   anchors, which spreads them evenly. Last, after step 4 (when the anchors' images are at their best), the map
   is *polished*: redrawn ``n_polish`` more times with each distance compared relative to its length,
   ``log(d + h)`` in place of ``d``, h = `wpot.maps.seams.LOG_OFFSET` mean edge lengths of the coarser mesh (as
   `wpot.maps.seams.reanchor` describes its vertices). A part's boundary and a change of pose stretch a geodesic
   in proportion to its length (a path around a hole), so in the absolute comparison the far anchors outweigh
   the near ones, which place a vertex best. Before step 4 the relative comparison would amplify the errors of
   misplaced anchors instead.
4. **Orientation** (``orient=True``). A map can reverse orientation in two ways: onto the mirror side (a
   left/right reflection is an isometry), or in place, reflected across a part that is nearly symmetric itself
   (a limb turned about its axis, a head front to back), where distances to the anchors cannot tell the two
   sides of the part apart. Three candidates: (a) the stretches that reverse orientation sent through the
   whole's left/right symmetry (`wpot.maps.symmetry.keep_orientation` with ``symmetry_of="b"``); (b) the map
   *unfolded*: redrawn (``n_rounds`` times) from the anchors where it keeps orientation
   (`wpot.maps.orientation.local_orientation` > 0), then once from all of them; (c) the mirror image of the map
   through the whole's symmetry, unfolded the same way. Orientation alone does not choose the side: a limb
   mapped onto the other limb and unfolded keeps orientation too. LD-SIFT does, as it is not mirror-invariant:
   on the ground truth of the development benchmark (`benchmarks/partial_poses.py`) the true side's mean
   signature cost was below the mirror side's in nearly every pair (the docs' Results page). So of the
   candidates oriented within `ORIENT_MARGIN` of the best one, the one with the least mean signature cost is
   kept. Those parts were cut from meshes made like the whole's (one mesher, one density); on a part meshed
   apart the costs tell less, and ``orient_weight`` instead keeps the candidate of least ``cost / least cost − 1 −
   orient_weight · orientation score`` (`ORIENT_WEIGHT`). A part given in the whole's frame (``aligned``) also
   pays each candidate's turn onto the whole, which a map onto the mirror side makes large. A whole whose
   symmetry is not detected gets (a) and (b) only. A part or whole whose orientation cannot be read (triangles
   wound against their neighbours, or no outside: `wpot.maps.orientation.unreadable`) skips this step, with a
   `LocateWarning` that names it and its repair. How near the choice of side was is the result's ``side_margin``:
   the rule's value of the best candidate on the other side of the whole less that of the one kept (a candidate
   is on the other side when most of the part's lateral images lie nearer the mirror images of the kept map's
   than its own), and that candidate, polished like the kept map, is the result's ``other_side``.

5. **Rival placement.** The candidate matches that lie neither where the map sends their anchors nor at the
   mirror image of that (farther than ``rival_tol``) are put through step 2 again: their largest consistent
   set is the best other place for the part. The result's ``placement_confidence`` is the share of the
   anchors that vouch for the chosen place and not for that rival: low when the part fits nowhere, or about
   as well elsewhere (one leg of a quadruped on another leg). Below `PLACEMENT_DOUBT`, the rival's matches draw a
   second map (steps 3 and 4, polished), the result's ``other_place``: the signatures that would choose between
   the two places are what proposed both, so the choice is left to a caller who can tell them apart.

**Landmarks** (``landmarks``): vertex pairs (part, whole) the caller knows to match, for what the geometry leaves
open (which of four legs; which side). They are matches of anchors of their own, taken first in step 2, where only
the candidates within 3 σ of all of them enter the agreement matrix; in steps 3 and 4 they are refinement anchors
whose images stay their given matches; step 4 considers only the candidates that send them within ``rival_tol``
(on average) of the best candidate's; step 5's rival must agree with them too.

The result (`PartMap`) also says which matches to trust: the ``residual`` of each vertex (how far its
geodesic distances to the consistent matches are from its image's, a fraction of √area(W)) and a
``confidence`` from it; and which part of the whole was matched (`PartMap.region`: the images of the part's
vertices and the gaps between them).

Assumptions: the part and the whole are at the same scale (a part of the same object or of a same-size one), or
``scale`` says how they differ; geodesics inside the part are those of the whole, which holes or a cut across a
narrow neck bend (the part's boundary makes some paths longer; ``rel_tol`` absorbs a share of that). Cost: one
heat-method solve per anchor and per distinct candidate, and a nearest-neighbour search in ``n_refine``
dimensions, plus, the first time a whole is met, its symmetry for step 4 (`wpot.maps.symmetry.reflection_symmetry`,
then cached), and steps 3-4 once more for a part whose place is in doubt (``other_place``); step 2 is run at
`SCALE_STEPS` + 2 trial scales by Lanczos (for ``"fit"``, or for ``"same"``'s warning). The geodesic distances
computed on a whole are kept for the next part located in it (`KEEP_GEODESICS`), and `prepare_whole` computes
them all at once for a whole that many parts will be located in.
Timings and accuracy: the docs' Results page (Parts across poses).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from wpot import _validate
from wpot.cache import Kept
from wpot.mesh import Mesh, edge_paths, named
from wpot.cost import cost_matrix, nearest_rows, paired_costs
from wpot.evaluate import GeodesicDistances
from wpot.maps.orientation import local_orientation, orientation_score, unreadable
from wpot.maps.registration import fit_similarity
from wpot.maps.seams import LOG_OFFSET
from wpot.maps.symmetry import keep_orientation, reflection_symmetry
from wpot.sampling import farthest_point_sampling

__all__ = ["LocateOptions", "PartMap", "locate_part", "prepare_whole", "clear_geodesics", "LocateWarning",
           "candidate_matches", "consistent_matches",
           "PLACEMENT_DOUBT", "SIDE_DOUBT", "KEEP_GEODESICS", "ORIENT_MARGIN", "ORIENT_WEIGHT", "SCALE_RANGE",
           "SCALE_STEPS", "SCALE_DOUBT", "TURN_DOUBT"]


#: step 4 chooses among the maps oriented within this of the best one (orientation scores lie in [-1, 1])
ORIENT_MARGIN = 0.5
#: `LocateOptions.orient_weight` for parts meshed apart from the whole: a mean signature cost 1 % above another's
#: weighs as much as 0.033 of orientation score. Chosen on parts re-meshed at the whole's density, checked on
#: parts meshed apart (TOSCA's low-res poses) and on FAUST's people (the docs' Results page)
ORIENT_WEIGHT = 0.3
#: a `PartMap.placement_confidence` below this: the part may not be where the map puts it
PLACEMENT_DOUBT = 0.1
#: a `PartMap.side_margin` below this: the map may be on the mirror side. The least round value under which every
#: gross failure of TOSCA's re-meshed parts (1x, 2x, 0.5x, 56 pairs each; ``edge="whole",
#: orient_weight=ORIENT_WEIGHT``, LD-SIFT turned by its gradients) was doubted by it or by `PLACEMENT_DOUBT`;
#: checked on `tosca_lowres`, FAUST's people, the parts cut from the source's mesh at the defaults, and larger
#: TOSCA sets, where it misses some (the docs' Results page)
SIDE_DOUBT = 0.15
#: ``LocateOptions(scale="fit")`` tries the scales of the part from 1 / SCALE_RANGE to SCALE_RANGE
SCALE_RANGE = 1.5
#: ... on a geometric grid of this many scales (steps of about 8 %), then half a step to each side of the best
SCALE_STEPS = 11
#: with ``scale="same"``, a `LocateWarning` when the candidate matches agree most at a scale more than 10 % from
#: 1, and by more than this factor over their agreement at 1. Chosen on FAUST's people (whose 5k meshes were
#: scaled one by one), checked on TOSCA's parts, which share their wholes' scale (the docs' Results page)
SCALE_DOUBT = 1.5
#: with ``aligned=True``, a `LocateWarning` when the kept map turns the part by more than this (degrees): nearer a
#: half turn than none, so the part may not be in the whole's frame
TURN_DOUBT = 90.0


class LocateWarning(UserWarning):
    """Too few consistent matches to place the part reliably."""


@dataclass(frozen=True)
class LocateOptions:
    """Options of `locate_part` (see the module docstring for what each step does).

    n_anchors : farthest-point samples of the part that get candidates (step 1)
    n_candidates : candidates per anchor, by signature cost (step 1)
    tol, rel_tol : the consistency tolerance σ = tol·√area(whole) + rel_tol·(the shorter distance) (step 2)
    n_refine : anchors of each refinement round (steps 3 and 4)
    n_rounds : refinement rounds (step 3), and unfolding rounds (step 4)
    n_polish : rounds of step 3's polish after step 4, distances compared relative to their length (0: none)
    orient : repair the parts of the map that reverse orientation through the whole's symmetry (step 4)
    region_tol : a vertex of the whole is in `PartMap.region` when an image of a vertex of the part lies within
        this (a fraction of √area(whole), along its edges) of it: about two edges on a 5,000-vertex shape,
        which closes the gaps between the images without reaching far past the part's border
    rival_tol : a candidate match belongs to the chosen placement when its vertex lies within this (a fraction
        of √area(whole)) of where the map sends its anchor; the others may form a rival placement (step 5). Also
        how far from its mirror image a vertex's image must lie to have a side (`PartMap.side_margin`)
    edge : for LD-SIFT in `Comparer.locate`, when the comparer leaves its edge length unset
        (`wpot.signatures.LDSIFTOptions.edge`): ``"own"`` (default) each mesh's own, the paper's Eq. 1;
        ``"whole"`` the whole's (`wpot.signatures._frames.common_edge`) for both meshes, so that a part meshed at
        another density sees images of its whole's size. "whole" locates parts meshed apart better and parts cut
        from a mesh like the whole's worse, which decided the default (the docs' Results page)
    orient_weight : None (default): step 4 keeps, of the candidates oriented within `ORIENT_MARGIN` of the best,
        the one of least mean signature cost; a number w >= 0: the one of least ``cost / least cost − 1 − w ·
        orientation score``. For a part meshed apart from the whole, ``edge="whole", orient_weight=ORIENT_WEIGHT``
        (the docs' Results page)
    scale : how the part's lengths compare with the whole's. ``"same"`` (default): one scale, as for a part cut
        from a scan of the same object, with a `LocateWarning` when the matches agree far better at another
        (`SCALE_DOUBT`); ``"fit"``: found in step 2, as the scale of the part's geodesic distances
        (from 1 / `SCALE_RANGE` to `SCALE_RANGE`) at which the candidate matches agree most (``consistent_matches``'
        total agreement), for shapes normalised one by one (a data set whose shapes were each scaled on its own,
        so that a part's pose and its whole's were scaled apart); a number s > 0: the part's lengths times s are
        the whole's (1.0: one scale, without ``"same"``'s check). Steps 2-5 then read the part's geodesic
        distances times that scale (`PartMap.scale`). `locate_part` uses the signatures it is given;
        `Comparer.locate` describes the part again at the whole's scale (given or fitted) when LD-SIFT's edge
        length is set (``edge="whole"``), as each mesh's own edge length does not depend on the scale
    aligned : the part is given in the whole's frame (scanned in one place, the same way up and facing the same
        way; a pose may still turn its limbs). Step 4 then adds each candidate's turn to its rule value: the angle
        of the rotation of the least-squares similarity taking the part's vertices onto their images
        (`wpot.maps.registration.fit_similarity`), over 180°, so that a map onto the mirror side or turned half
        round, which a near-symmetric body's own shape cannot tell from the right one, costs up to a whole unit.
        A `LocateWarning` names the option when the kept map turns the part by more than `TURN_DOUBT` degrees.
        False (default): the part may be given in any position, and nothing depends on it
    """

    n_anchors: int = 64
    n_candidates: int = 10
    tol: float = 0.03
    rel_tol: float = 0.1
    n_refine: int = 96
    n_rounds: int = 2
    n_polish: int = 1
    orient: bool = True
    region_tol: float = 0.03
    rival_tol: float = 0.1
    edge: str = "own"
    orient_weight: float | None = None
    scale: str | float = "same"
    aligned: bool = False

    def __post_init__(self) -> None:
        _validate.integer_at_least("n_anchors", self.n_anchors, 3)
        _validate.integer_at_least("n_candidates", self.n_candidates, 1)
        _validate.positive_finite("tol", self.tol)
        _validate.nonnegative_finite("rel_tol", self.rel_tol)
        _validate.integer_at_least("n_refine", self.n_refine, 3)
        _validate.integer_at_least("n_rounds", self.n_rounds, 0)
        _validate.integer_at_least("n_polish", self.n_polish, 0)
        _validate.boolean("orient", self.orient)
        _validate.boolean("aligned", self.aligned)
        if self.orient_weight is not None:
            _validate.nonnegative_finite("orient_weight", self.orient_weight)
        _validate.positive_finite("region_tol", self.region_tol)
        _validate.positive_finite("rival_tol", self.rival_tol)
        _validate.one_of("edge", self.edge, ("whole", "own"))
        _validate.one_of_or_positive("scale", self.scale, ("same", "fit"))


@dataclass(frozen=True)
class PartMap:
    """A part located in a whole and mapped onto it (`locate_part`).

    Attributes
    ----------
    correspondence : (N_P,) int64, the vertex of the whole for each vertex of the part
    residual : (N_P,) float64, ‖d_P(v, A) − d_W(T(v), B)‖ / √K over √area(whole), with (A, B) the K consistent
        matches of step 2: how far the vertex's geodesic distances to them are from its image's (small: the
        match agrees with the anchors; large: the map strays from them there, or the anchors themselves are
        wrong, which raises it everywhere)
    confidence : (N_P,) float64 in [0, 1], ``exp(−residual / tol) · (1 + o) / 2`` with o the map's orientation
        score around the vertex (`wpot.maps.orientation.local_orientation`: 1 where the map keeps orientation, −1
        where it is mirrored or folded, 0 where it cannot be read): ranks the matches by trust (on the
        development pairs the more confident points are the more accurate; the docs' Results page)
    image_distance : (N_W,) float64, per vertex of the whole the distance along its edges to the nearest image
        of a vertex of the part, over √area(whole) (0 on the images)
    cost : the mean signature cost between each vertex of the part and its image (`wpot.cost.paired_costs`).
        As a distance for retrieval on the development benchmark it ranks the part's own class better than the
        partial transport's distance (Eq. 27) or the mean residual, and worse than the mean distance from each
        vertex's signature to the nearest signature of the whole (no map at all;
        `Comparer.nearest_signature_distance`); the docs' Results page has the figures
    anchors : (K, 2) int64, the consistent matches (part vertex, whole vertex) of step 2, the caller's landmarks
        among them
    orientation : the final map's `wpot.maps.orientation.orientation_score` (NaN when it cannot be read)
    region_tol : the default threshold of `region`
    rival : (R, 2) int64, the largest consistent set of candidate matches that are not in this placement (step
        5): another place where the part fits about as well, when it is about as large as ``anchors``
    placement_confidence : in [0, 1], ``(K − R) / n_anchors``: the share of the part's anchors that vouch for
        this placement and for no other. Near 0 when the part fits nowhere (few consistent matches) or
        about as well elsewhere (one leg of a quadruped on another); below `PLACEMENT_DOUBT`, doubt the whole
        map, not only its low-``confidence`` vertices
    scale : the factor by which the part's lengths were taken to give the whole's (`LocateOptions.scale`: 1 with
        ``"same"``, the fitted one with ``"fit"``)
    side_margin : >= 0, how far step 4's rule (`LocateOptions.orient_weight`) preferred this side of the whole to
        the mirror side: the rule's value of the best candidate map on the other side less the kept one's (a
        relative mean signature cost, less ``orient_weight`` times an orientation score). Below `SIDE_DOUBT` the
        map may be on the mirror side (a left limb on the right one): the side was a near-tie. ``inf`` when no
        candidate lay on the other side (or, with ``orient_weight`` None, none there was oriented within
        `ORIENT_MARGIN` of the best, or the landmarks ruled that side out); NaN when the side was not read (no
        left/right symmetry found in the whole, an orientation that cannot be read, ``orient=False``, or a part on
        the plane of symmetry)
    other_side : (N_P,) int64 or None, the map step 4 preferred on the other side of the whole (its candidate of
        least rule value there, polished like ``correspondence``): where the side is in doubt, the other answer, for
        a caller who can tell left from right (None when no candidate lay on the other side, or the side was not
        read)
    other_place : (N_P,) int64 or None, where ``placement_confidence`` is below `PLACEMENT_DOUBT`, the map drawn
        from the ``rival`` matches (steps 3 and 4, polished like ``correspondence``): the other answer where the
        place is in doubt, for a caller who can tell the two places apart (a front leg from a hind one; None when
        the place is not in doubt or the rival holds fewer than 3 matches)
    """

    correspondence: np.ndarray
    residual: np.ndarray
    confidence: np.ndarray
    image_distance: np.ndarray
    cost: float
    anchors: np.ndarray
    orientation: float
    region_tol: float
    rival: np.ndarray
    placement_confidence: float
    scale: float = 1.0
    side_margin: float = float("nan")
    other_side: np.ndarray | None = None
    other_place: np.ndarray | None = None

    def region(self, threshold: float | None = None) -> np.ndarray:
        """(N_W,) bool, the vertices of the whole that the part matched: ``image_distance <= threshold``
        (default ``region_tol``)."""
        t = self.region_tol if threshold is None else _validate.positive_finite("threshold", threshold)
        return self.image_distance <= t

    def summary(self) -> dict:
        """The map's pair-level figures as plain JSON values (for result files): anchors, median residual and
        confidence, orientation, region size, placement confidence, rivals, side margin and scale. JSON has no
        inf or NaN: a side margin of inf is written "inf", and a NaN (orientation or side not read) None."""
        def number(x: float) -> float | str | None:
            return None if np.isnan(x) else "inf" if np.isinf(x) else float(x)

        return {"n_anchors": int(len(self.anchors)), "median_residual": float(np.median(self.residual)),
                "median_confidence": float(np.median(self.confidence)), "orientation": number(self.orientation),
                "region_vertices": int(self.region().sum()), "placement_confidence": float(self.placement_confidence),
                "n_rival": int(len(self.rival)), "side_margin": number(self.side_margin), "scale": float(self.scale)}

    def __repr__(self) -> str:
        return (f"PartMap({len(self.correspondence)} -> {len(self.image_distance)} vertices, {len(self.anchors)} "
                f"consistent anchors, median residual {np.median(self.residual):.3g}, "
                f"orientation {self.orientation:.2f}, region {int(self.region().sum())} vertices, placement confidence "
                f"{self.placement_confidence:.2f}, side margin {self.side_margin:.3g}"
                + ("" if self.scale == 1.0 else f", scale {self.scale:.3g}") + ")")


#: meshes whose geodesic distances (`wpot.evaluate.GeodesicDistances`, the rows computed so far) `locate_part` keeps
#: between calls, the most recently used last: a whole that parts are located in one after another keeps the rows
#: of the earlier parts (rows are ``N`` float32 each, so a whole's are at most N² float32: 100 MB at 5,000 vertices)
KEEP_GEODESICS = 3
_GEODESICS = Kept(KEEP_GEODESICS)


def _geodesics(mesh: Mesh) -> GeodesicDistances:
    """The kept `GeodesicDistances` of ``mesh`` (by its fingerprint), or new ones (`KEEP_GEODESICS`)."""
    return _GEODESICS.get(mesh.fingerprint, lambda: GeodesicDistances(mesh))


def clear_geodesics() -> None:
    """Forget the geodesic distances kept between calls (`KEEP_GEODESICS`), freeing their memory."""
    _GEODESICS.clear()


def prepare_whole(whole: Mesh, *, symmetry: bool = True) -> None:
    """The one-off set-up of a whole that many parts will be located in: its left/right symmetry (step 4;
    `wpot.maps.symmetry.reflection_symmetry`, cached) and its geodesic distances from every vertex, kept for the
    next `locate_part` calls (`KEEP_GEODESICS`; N heat-method solves and N² float32). Without it, each call
    computes the rows it needs and keeps them for the next; the maps are the same either way."""
    if not isinstance(whole, Mesh):
        raise TypeError(f"whole must be a wpot.Mesh, got {type(whole).__name__}")
    if symmetry:
        reflection_symmetry(whole)
    g = _geodesics(whole)
    for start in range(0, whole.n_vertices, 256):  # the rows are kept; each block's stacked copy is dropped
        g.from_sources(np.arange(start, min(start + 256, whole.n_vertices)))


def candidate_matches(sig_part: np.ndarray, sig_whole: np.ndarray, anchors: np.ndarray, k: int, metric: str,
                      device: str | None = None) -> np.ndarray:
    """Step 1: (A, k) int, for each of the (A,) ``anchors`` (vertices of the part) the k vertices of the whole
    whose signatures (rows of ``sig_whole`` (N_W, D)) are nearest its own (a row of ``sig_part`` (N_P, D)) in
    ``metric`` (`wpot.cost.cost_matrix`), nearest first; k is clipped to N_W."""

    c = np.asarray(cost_matrix(sig_part[anchors], sig_whole, metric=metric, device=device))
    k = min(k, c.shape[1])
    top = np.argpartition(c, k - 1, axis=1)[:, :k]
    order = np.argsort(np.take_along_axis(c, top, axis=1), axis=1)
    return np.take_along_axis(top, order, axis=1)


def consistent_matches(d_part: np.ndarray, d_whole: np.ndarray, owner: np.ndarray, *, sigma0: float,
                       rel_tol: float) -> np.ndarray:
    """Step 2: the indices of a mutually consistent set of candidate matches.

    d_part (M, M): geodesic distances on the part between the candidates' anchors; d_whole (M, M): on the
    whole between their targets; owner (M,): each candidate's anchor (at most one match per anchor is kept).
    Returns the kept candidates, in the order taken."""
    return _consistent(d_part, d_whole, owner, sigma0, rel_tol)[0]


def _deviation(d_part, d_whole, sigma0, rel_tol) -> tuple[np.ndarray, np.ndarray]:
    """Step 2's deviations |d_part − d_whole| and tolerances σ = sigma0 + rel_tol · min(d_part, d_whole), for
    distances of any matching shape; two matches agree within 3 σ."""
    return np.abs(d_part - d_whole), sigma0 + rel_tol * np.minimum(d_part, d_whole)


def _agreement(d_part, d_whole, owner, sigma0, rel_tol):
    """Step 2's agreement matrix (M, M), deviations |d_part − d_whole| and tolerances σ (`_deviation`)."""
    dev, sig = _deviation(d_part, d_whole, sigma0, rel_tol)
    w = np.exp(-0.5 * (dev / sig) ** 2)
    w[owner[:, None] == owner[None, :]] = 0.0
    return w, dev, sig


def _consistent(d_part, d_whole, owner, sigma0, rel_tol, exact: bool = True, forced=()) -> tuple[np.ndarray, float]:
    """`consistent_matches`, and the total agreement among the matches it keeps (the sum of the agreement matrix
    over their pairs). ``exact=False`` finds the leading eigenvector by Lanczos (`scipy.sparse.linalg.eigsh`),
    many times faster, but near-ties in the greedy order can then fall the other way: good enough to compare
    scales (`_scaled_matches`), not for the matches kept. ``forced``: indices of matches known to be right (the
    caller's landmarks), taken first; the eigenvector is then that of the matches within 3 σ of all of them."""
    w, dev, sig = _agreement(d_part, d_whole, owner, sigma0, rel_tol)
    near = dev <= 3.0 * sig  # near[i, j]: i within 3 σ of j (heat-method distances are not quite symmetric)
    forced = np.asarray(forced, dtype=np.int64)
    ok = near[:, forced].all(axis=1)  # within 3 σ of every match taken so far (all True without landmarks)
    if forced.size:
        w = w * ok[:, None] * ok[None, :]
    if exact or len(w) < 3 or not w.any():
        vec = np.linalg.eigh(w)[1][:, -1]
    else:
        from scipy.sparse.linalg import eigsh

        vec = eigsh(w, k=1, which="LA", v0=np.ones(len(w)))[1][:, 0]
    x = np.abs(vec)  # the Perron vector of a nonnegative symmetric matrix (its sign is arbitrary)
    ok &= x > 0
    taken: list[int] = [int(m) for m in forced]
    used: set[int] = {int(owner[m]) for m in forced}
    for m in np.argsort(-x, kind="stable"):
        if not ok[m] or owner[m] in used:
            continue
        taken.append(int(m))
        used.add(int(owner[m]))
        ok &= near[:, m]
    kept = np.asarray(taken, dtype=np.int64)
    return kept, float(w[np.ix_(kept, kept)].sum() / 2.0)


def _scale_totals(d_part, d_whole, owner, opt: "LocateOptions", sigma0: float, forced=()) -> dict[float, float]:
    """Step 2's total agreement (Lanczos, `_consistent`) with the part's distances times each scale of a grid of
    `SCALE_STEPS` from 1 / `SCALE_RANGE` to `SCALE_RANGE` (1 among them), then half a step to each side of the
    best: {scale: total}."""
    def total_at(s: float) -> float:
        return _consistent(s * d_part, d_whole, owner, sigma0, opt.rel_tol, exact=False, forced=forced)[1]

    grid = SCALE_RANGE ** np.linspace(-1.0, 1.0, SCALE_STEPS)
    total = {float(s): total_at(s) for s in grid}
    best = max(total, key=total.get)
    step = np.sqrt(grid[1] / grid[0])
    for s in (best / step, best * step):
        total[float(s)] = total_at(s)
    return total


def _scaled_matches(d_part, d_whole, owner, opt: "LocateOptions", sigma0: float, name: str | None = None,
                    forced=()) -> tuple[np.ndarray, float]:
    """Step 2 at the part's scale (`LocateOptions.scale`): the consistent matches (``forced`` first, see
    `_consistent`), and the scale s by which the part's geodesic distances ``d_part`` were multiplied. With
    ``"same"``, a `LocateWarning` (naming the part, ``name``) when the matches agree `SCALE_DOUBT` times better
    at a scale more than 10 % from 1."""
    if opt.scale not in ("same", "fit"):
        s = float(opt.scale)
        return _consistent(s * d_part, d_whole, owner, sigma0, opt.rel_tol, forced=forced)[0], s
    total = _scale_totals(d_part, d_whole, owner, opt, sigma0, forced)
    best = max(total, key=total.get)
    gain = total[best] / max(total[1.0], 1e-300)
    if opt.scale == "same" and abs(np.log(best)) > np.log(1.1) and gain > SCALE_DOUBT:
        warnings.warn(named(name, f"the part's geodesic distances agree {gain:.1f} times better with the whole's "
                            f"at {best:.2f} times their length: are the part and the whole at different scales "
                            "(shapes normalised one by one)? LocateOptions(scale='fit') finds the scale"),
                      LocateWarning, stacklevel=3)
    s = best if opt.scale == "fit" else 1.0
    return _consistent(s * d_part, d_whole, owner, sigma0, opt.rel_tol, forced=forced)[0], s


def _distances(geo, sources: np.ndarray) -> np.ndarray:
    """(S, N) float64 geodesic distances from ``sources`` (`wpot.evaluate.GeodesicDistances`), with the
    distance to another connected component (infinite) replaced by twice the largest finite one: far, so
    that matches across components disagree, but finite, so that profiles can be compared."""
    d = geo.from_sources(sources).astype(np.float64)
    bad = ~np.isfinite(d)
    if bad.any():
        d[bad] = 2.0 * (d[~bad].max() if (~bad).any() else 1.0)
    return d


def _image_distance(whole: Mesh, images: np.ndarray) -> np.ndarray:
    """(N_W,) distance along the edges of ``whole`` from each vertex to the nearest of ``images``."""
    return edge_paths(whole, np.unique(images), min_only=True)


class _Redraw:
    """Steps 3 and 4: a map of the part drawn from matched anchors by their geodesic distances, with the
    distances from the part's refinement anchors ``src`` computed once. The caller's landmarks (``pins``, (L, 2)
    part and whole vertices) are refinement anchors too, whose images stay their given matches."""

    def __init__(self, part: Mesh, whole: Mesh, src: np.ndarray, g_part=None, g_whole=None,
                 part_scale: float = 1.0, pins: np.ndarray | None = None) -> None:
        pins = np.zeros((0, 2), dtype=np.int64) if pins is None else np.asarray(pins, dtype=np.int64)
        self.part, self.whole = part, whole
        self.src, self.fixed = np.r_[np.asarray(src, dtype=np.int64), pins[:, 0]], pins[:, 1]
        self.pinned = slice(len(self.src) - len(pins), None)  # the landmarks' places in src
        self.g_part = _geodesics(part) if g_part is None else g_part
        self.g_whole = _geodesics(whole) if g_whole is None else g_whole
        self.part_scale = float(part_scale)
        self.d_src = self.on_part(self.src).T  # (N_P, n_refine + L)

    def on_part(self, sources: np.ndarray) -> np.ndarray:
        """(S, N_P) geodesic distances on the part from ``sources``, at the whole's scale (times ``part_scale``)."""
        return self.part_scale * _distances(self.g_part, sources)

    def dense(self, from_part: np.ndarray, to_whole: np.ndarray) -> np.ndarray:
        """Each vertex of the part to the vertex of the whole whose geodesic distances to ``to_whole`` are
        nearest its own to ``from_part``: (N_P,) int64."""

        return nearest_rows(self.on_part(from_part).T, _distances(self.g_whole, to_whole).T)[0]

    def _kept(self, keep: np.ndarray | None) -> np.ndarray:
        """(n_refine + L,) bool, the refinement anchors used: ``keep``'s, and the landmarks always."""
        k = np.ones(len(self.src), dtype=bool) if keep is None else np.array(keep, dtype=bool)
        k[self.pinned] = True
        return k

    def rounds(self, t: np.ndarray, n: int, keep: np.ndarray | None = None, offset: float | None = None
               ) -> np.ndarray:
        """``n`` rounds of the map redrawn from ``src`` (those where ``keep``, (n_refine + L,) bool) and their
        current images (the landmarks' given ones); with ``offset`` h, the distances d compared as log(d + h)
        (step 3's polish)."""

        k = self._kept(keep)
        f = (lambda d: d) if offset is None else (lambda d: np.log(d + offset))
        for _ in range(n):
            images = t[self.src]
            images[self.pinned] = self.fixed
            t = nearest_rows(f(self.d_src[:, k]), f(_distances(self.g_whole, images[k]).T))[0]
        return t

    def unfold(self, t: np.ndarray, n: int) -> np.ndarray:
        """Step 4 (b): the map redrawn ``n`` times from the anchors where it keeps orientation (and the
        landmarks), then once from all of them."""

        for _ in range(n):
            keep = self._kept(np.nan_to_num(local_orientation(self.part, self.whole, t), nan=0.0)[self.src] > 0)
            if keep.sum() < 3 or keep.all():
                break
            t = self.rounds(t, 1, keep)
        return self.rounds(t, 1)


def _orient(draw: _Redraw, t: np.ndarray, cost, n_rounds: int, weight: float | None = None, far: float = 0.0,
            pins: np.ndarray | None = None, aligned: bool = False
            ) -> tuple[np.ndarray, float, float, float, np.ndarray | None]:
    """Step 4: the candidates (a)-(c) of the module docstring, and of them the one of least `_rule` value (by
    orientation score and ``cost(map)``, the mean signature cost; the first on a tie). Returns the map, its
    orientation score, its cost, its side margin (`PartMap.side_margin`; ``far``: `_other_side`'s distance, in
    the whole's units) and the candidate of least rule value on the other side (the first there when all are
    inf; None when no candidate lies there). With ``pins`` (L, 2), the caller's landmarks (part vertex, whole
    vertex), only the candidates that send them within ``far`` (on average) of the best one's are eligible.
    ``aligned``: each candidate's `_turn` joins its rule value (`LocateOptions.aligned`)."""

    part, whole, n = draw.part, draw.whole, max(1, n_rounds)
    cands = [keep_orientation(part, whole, t, refine=lambda t0: draw.rounds(t0, n), symmetry_of="b")[0],
             draw.unfold(t, n)]
    sym = reflection_symmetry(whole)
    if sym is not None:
        cands.append(draw.unfold(sym.map[t], n))
    scores = [orientation_score(part, whole, c) for c in cands]
    costs = [cost(c) for c in cands]
    rule = _rule(scores, costs, weight, [_turn(part, whole, c) for c in cands] if aligned else None)
    if pins is not None and len(pins):
        d = _distances(draw.g_whole, pins[:, 1])  # (L, N_W)
        miss = np.array([d[np.arange(len(pins)), c[pins[:, 0]]].mean() for c in cands])
        rule = np.where(miss <= miss.min() + far, rule, np.inf)
    best = int(np.argmin(rule))
    kept = (cands[best], float(scores[best]), float(costs[best]))
    other = None if sym is None else _other_side(whole, sym.map, cands[best], cands, far)
    if other is None:
        return (*kept, float("nan"), None)
    there = np.flatnonzero(other)
    if not there.size:
        return (*kept, float("inf"), None)
    alt = int(there[np.argmin(rule[there])])
    return (*kept, float(rule[alt] - rule[best]), cands[alt])


def _oriented(draw: _Redraw, t: np.ndarray, cost, opt: LocateOptions, far: float, unread: bool,
              pins: np.ndarray | None = None) -> tuple:
    """Step 4 (when ``opt.orient`` and the orientation can be read, ``unread`` False; ``pins``: the caller's
    landmarks, `_orient`) and the polish after it. Returns the map, its orientation score (NaN when unread) and
    mean cost, its local orientation (N_P,), the side margin (NaN when not read) and the best map on the other
    side (polished too; None when there is none)."""
    part, whole = draw.part, draw.whole
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an orientation that cannot be read leaves the map as it is (NaN)
        oriented, side, other = opt.orient and not unread, float("nan"), None
        if oriented:
            t, score, mean_cost, side, other = _orient(draw, t, cost, opt.n_rounds, opt.orient_weight, far, pins,
                                                       opt.aligned)
        if opt.n_polish:
            h = LOG_OFFSET * max(part.mean_edge_length * draw.part_scale, whole.mean_edge_length)
            t = draw.rounds(t, opt.n_polish, offset=h)
            other = None if other is None else draw.rounds(other, opt.n_polish, offset=h)
        if opt.n_polish or not oriented:  # NaN: a patch wound the wrong way reverses every orientation read on it
            score = float("nan") if unread else orientation_score(part, whole, t)
            mean_cost = cost(t)
        local = np.zeros(part.n_vertices) if unread else np.nan_to_num(local_orientation(part, whole, t), nan=0.0)
    return t, score, mean_cost, local, side, other


def _rule(scores, costs, weight: float | None = None, turns=None) -> np.ndarray:
    """Step 4's rule: a value per candidate, the least kept (`_orient`). ``costs`` are positive mean signature
    costs, r = cost / least cost − 1; a NaN orientation score reads as −1. With ``weight`` None, r for the
    candidates whose orientation score is within `ORIENT_MARGIN` of the best and inf for the others; else
    r − weight · score. ``turns`` (`LocateOptions.aligned`): each candidate's `_turn`, added."""
    o = np.nan_to_num(np.asarray(scores, dtype=np.float64), nan=-1.0)
    c = np.asarray(costs, dtype=np.float64)
    r = c / max(float(c.min()), 1e-300) - 1.0
    if turns is not None:
        r = r + np.asarray(turns, dtype=np.float64)
    if weight is None:
        return np.where(o >= o.max() - ORIENT_MARGIN, r, np.inf)
    return r - weight * o


def _turn(part: Mesh, whole: Mesh, t: np.ndarray) -> float:
    """How far the map ``t`` (N_P,) turns the part onto the whole, in half turns (0 to 1): the angle of the proper
    rotation of the least-squares similarity taking the part's vertices onto their images, over 180°; 1 when the
    images do not determine a rotation (they lie on a line or at one point)."""
    try:
        return fit_similarity(part.vertices, whole.vertices[t]).rotation_degrees / 180.0
    except ValueError:
        return 1.0


def _other_side(whole: Mesh, mirror: np.ndarray, chosen: np.ndarray, cands: list, far: float) -> np.ndarray | None:
    """(len(cands),) bool: the candidate maps that lie on the other side of the whole from ``chosen``, (N_P,)
    vertices of the whole. Over the vertices of the part whose image under ``chosen`` is farther than ``far``
    (straight-line) from its mirror image (``mirror`` (N_W,), the whole's symmetry), a candidate is on the other
    side when more than half of its images lie nearer the mirror image than the chosen image. None when no image
    is that far from its mirror: a part on the plane of symmetry has no side (a map reflected in place is
    orientation's to tell)."""
    x = whole.vertices
    at, across = x[chosen], x[mirror[chosen]]
    lateral = np.linalg.norm(at - across, axis=1) > far
    if not lateral.any():
        return None
    at, across = at[lateral], across[lateral]
    near = [np.linalg.norm(x[c[lateral]] - across, axis=1) < np.linalg.norm(x[c[lateral]] - at, axis=1)
            for c in cands]
    return np.array([np.mean(n) > 0.5 for n in near])


def _rival(g_whole, whole: Mesh, images: np.ndarray, owner: np.ndarray, target: np.ndarray, d_anchor: np.ndarray,
           d_target: np.ndarray, opt: LocateOptions, scale: float, forced: np.ndarray) -> np.ndarray:
    """Step 5: of the candidate matches (``owner`` (M,) their anchor, ``target`` (M,) their vertex of the whole),
    those farther than ``rival_tol`` from where the map sends their anchor (``images`` (A,)) and from its mirror
    image, and within 3 σ of the caller's landmarks (``forced``, indices of matches), and of them the largest
    consistent set (`consistent_matches`; ``d_anchor`` (A, A) and ``d_target`` (M, M) as in step 2). Returns
    its indices into the candidates."""
    dev, sig = _deviation(d_anchor[np.ix_(owner, owner[forced])], d_target[:, forced], opt.tol * scale, opt.rel_tol)
    near = (dev > 3.0 * sig).any(axis=1)  # a match that disagrees with a landmark is no rival
    sym = reflection_symmetry(whole) if opt.orient else None
    for im in (images,) if sym is None else (images, sym.map[images]):
        uniq, at = np.unique(im, return_inverse=True)
        near |= _distances(g_whole, uniq)[at[owner], target] <= opt.rival_tol * scale
    away = np.nonzero(~near)[0]
    if away.size < 3:
        return away[:0]
    return away[consistent_matches(d_anchor[np.ix_(owner[away], owner[away])], d_target[np.ix_(away, away)],
                                   owner[away], sigma0=opt.tol * scale, rel_tol=opt.rel_tol)]


def check_part(part: Mesh, whole: Mesh, category: type[Warning], whole_is: str = "the whole", stacklevel: int = 3
               ) -> None:
    """Warn (``category``) when ``part`` is larger than ``whole`` (area more than 5 % above), which a part of it
    cannot be: the two swapped, or meshes at different scales. ``whole_is`` names the whole in the message;
    ``stacklevel`` is `warnings.warn`'s (3: the caller of check_part's caller)."""
    ratio = part.area / whole.area
    if ratio > 1.05:
        warnings.warn(named(part.name, f"the part's area is {ratio:.2f} times that of {whole_is}, so it cannot be a "
                            "part of it: are the part and the whole swapped, or at different scales?"), category,
                      stacklevel=stacklevel)


def _landmarks(value: ArrayLike | None, part: Mesh, whole: Mesh) -> np.ndarray:
    """`locate_part`'s ``landmarks`` checked: (L, 2) int64 (empty without them), each row a vertex of the part and
    the vertex of the whole known to match it, no vertex of the part twice."""
    if value is None:
        return np.zeros((0, 2), dtype=np.int64)
    pins = np.asarray(value)
    if pins.ndim != 2 or pins.shape[1] != 2 or not len(pins):
        raise ValueError("landmarks must be (L, 2), L >= 1, a vertex of the part and the vertex of the whole it "
                         f"matches in each row, got shape {pins.shape}")
    cols = [_validate.vertex_map(f"landmarks[:, {j}]", pins[:, j], len(pins), m.n_vertices).tolist()
            for j, m in ((0, part), (1, whole))]
    twice = sorted({v for v in cols[0] if cols[0].count(v) > 1})
    if twice:
        raise ValueError(f"landmarks name vertex {twice[0]} of the part more than once: a vertex has one match")
    return np.stack(cols, axis=1).astype(np.int64)


def _check_inputs(part, whole, sp_: np.ndarray, sw: np.ndarray, opt) -> None:
    """`locate_part`'s arguments checked, each error naming the argument; a part larger than the whole warned
    about (`check_part`)."""
    for name, m in (("part", part), ("whole", whole)):
        if not isinstance(m, Mesh):
            raise TypeError(f"{name} must be a wpot.Mesh, got {type(m).__name__}")
    if not isinstance(opt, LocateOptions):
        raise TypeError(f"options must be a wpot.maps.locate.LocateOptions, got {type(opt).__name__}")
    for name, s, m in (("part_signatures", sp_, part), ("whole_signatures", sw, whole)):
        if s.ndim != 2 or s.shape[0] != m.n_vertices:
            raise ValueError(f"{name} must be ({m.n_vertices}, D), one row per vertex, got shape {s.shape}")
    if sp_.shape[1] != sw.shape[1]:
        raise ValueError(f"part_signatures and whole_signatures have different widths ({sp_.shape[1]} and "
                         f"{sw.shape[1]}): compute both with the same signature settings")
    if part.n_vertices < 3:
        raise ValueError(f"part has {part.n_vertices} vertices; at least 3 are needed")
    check_part(part, whole, LocateWarning, stacklevel=4)
    if part.n_components > 1:
        raise ValueError(f"part has {part.n_components} connected components: locate places one connected part by "
                         "geodesic consistency, and no geodesic joins two components. Locate each component on its "
                         "own (Mesh.cleaned(keep_largest_component=True) keeps the largest)")


def _check_landmarks(pins: np.ndarray, d_part: np.ndarray, d_whole: np.ndarray, opt: LocateOptions,
                     scale: float) -> None:
    """Warn (`LocateWarning`) when two of the caller's landmarks disagree: their geodesic distance on the part
    (``d_part`` (L, L), at the whole's scale) differs from that on the whole (``d_whole`` (L, L)) by more than
    step 2's 3 σ, so they cannot all be right (or the scale is not the one assumed)."""
    dev, sig = _deviation(d_part, d_whole, opt.tol * scale, opt.rel_tol)
    excess = dev - 3.0 * sig
    i, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
    if excess[i, j] > 0:
        warnings.warn(f"landmarks {i} and {j} disagree: {d_part[i, j]:.3g} apart on the part (at the whole's scale) "
                      f"and {d_whole[i, j]:.3g} on the whole, so they cannot both be right; the map follows them "
                      "where it can (check their vertex indices, and the part's scale)", LocateWarning, stacklevel=3)


def locate_part(part: Mesh, whole: Mesh, part_signatures: ArrayLike, whole_signatures: ArrayLike, *,
                metric: str = "l2", options: LocateOptions | None = None, landmarks: ArrayLike | None = None,
                device: str | None = None) -> PartMap:
    """Locate ``part`` in ``whole`` and map it onto it (see the module docstring).

    Parameters
    ----------
    part, whole : the meshes (same scale; the part need not be cut from this pose of the whole)
    part_signatures (N_P, D), whole_signatures (N_W, D) : per-vertex signatures (e.g. `Comparer.signatures`);
        they only propose candidate matches
    metric : their cost (`wpot.cost.cost_matrix`: "l2" for LD-SIFT and HKS, "wks" for WKS)
    options : `LocateOptions` (default: its defaults)
    landmarks : (L, 2) ints or None, vertices of the part and of the whole known to match (a morphometric
        landmark placed on both): they join step 2's matches first, so that only the candidates consistent with
        all of them are kept, step 4 keeps only maps that send them near their matches, and step 5's rival must
        agree with them too. One landmark away from the rest of the part's like places (a hoof, not a knee)
        tells the part's place (which leg), and one off the plane of symmetry its side.
    device : Warp device for the signature costs

    Returns
    -------
    `PartMap` (its ``anchors`` include the landmarks). Warns (`LocateWarning`) when fewer than 3 consistent
    matches are found (the map is then unreliable, as its residuals say) and when two landmarks disagree.
    """

    opt = LocateOptions() if options is None else options
    sp_ = np.asarray(part_signatures, dtype=np.float64)
    sw = np.asarray(whole_signatures, dtype=np.float64)
    _check_inputs(part, whole, sp_, sw, opt)
    pins = _landmarks(landmarks, part, whole)
    scale = float(np.sqrt(whole.area))
    g_part, g_whole = _geodesics(part), _geodesics(whole)

    # steps 1-2; farthest-point sampling is greedy, so one run gives both the anchors and step 3's sources as
    # its first n_anchors and n_refine samples. The landmarks are matches of anchors of their own, taken first
    spread = farthest_point_sampling(part, min(max(opt.n_anchors, opt.n_refine), part.n_vertices)).indices
    anchors, src = spread[:opt.n_anchors], spread[:opt.n_refine]
    cand = candidate_matches(sp_, sw, anchors, opt.n_candidates, metric, device)
    seeds = np.r_[anchors, pins[:, 0]]
    owner = np.r_[np.repeat(np.arange(len(anchors)), cand.shape[1]), len(anchors) + np.arange(len(pins))]
    target = np.r_[cand.ravel(), pins[:, 1]]
    forced = np.arange(cand.size, len(target))
    d_anchor = _distances(g_part, seeds)[:, seeds]
    uniq, inv = np.unique(target, return_inverse=True)
    d_target = _distances(g_whole, uniq)[:, uniq][np.ix_(inv, inv)]
    kept, part_scale = _scaled_matches(d_anchor[np.ix_(owner, owner)], d_target, owner, opt, opt.tol * scale,
                                       part.name, forced)
    d_anchor = part_scale * d_anchor
    if len(pins):
        _check_landmarks(pins, d_anchor[len(anchors):, len(anchors):], d_target[np.ix_(forced, forced)], opt, scale)
    a, b = seeds[owner[kept]], target[kept]
    if len(kept) < 3:
        warnings.warn(f"only {len(kept)} consistent matches between the part and the whole: the part could not "
                      "be placed reliably (are they at the same scale, and is the part in the whole?)",
                      LocateWarning, stacklevel=2)

    # steps 3 and 4
    draw = _Redraw(part, whole, src, g_part, g_whole, part_scale, pins)
    t = draw.rounds(draw.dense(a, b), opt.n_rounds)
    rival = _rival(g_whole, whole, t[seeds], owner, target, d_anchor, d_target, opt, scale, forced)

    def cost(t: np.ndarray) -> float:
        return float(np.mean(paired_costs(sp_, sw, t, metric=metric, device=device)))

    unread = [(name, m, why) for name, m in (("part", part), ("whole", whole)) if (why := unreadable(m))]
    if unread and opt.orient:
        name, m, why = unread[0]
        warnings.warn(named(m.name, f"the {name} {why}, so locate cannot tell left from right: the map is not "
                            "checked for mirroring (PartMap.orientation NaN)"), LocateWarning, stacklevel=2)
    far = opt.rival_tol * scale
    t, score, mean_cost, local, side, other = _oriented(draw, t, cost, opt, far, bool(unread), pins)
    if opt.aligned and (turn := 180.0 * _turn(part, whole, t)) > TURN_DOUBT:
        warnings.warn(named(part.name, f"with aligned=True the part is taken to be in the whole's frame, but its map "
                            f"turns it by {turn:.0f} degrees onto the whole: unless the pose turned it that far, "
                            "give the part in the whole's frame, or leave aligned False"), LocateWarning, stacklevel=2)
    placement = min(max(len(kept) - len(rival), 0) / len(anchors), 1.0)
    elsewhere = None
    if placement < PLACEMENT_DOUBT and len(rival) >= 3:  # step 5's other place, mapped like this one
        elsewhere = draw.rounds(draw.dense(seeds[owner[rival]], target[rival]), opt.n_rounds)
        elsewhere = _oriented(draw, elsewhere, cost, opt, far, bool(unread), pins)[0]

    # residuals against step 2's anchors, which do not depend on the refined map itself
    fp0, fw0 = draw.on_part(a).T, _distances(g_whole, b).T
    res = np.linalg.norm(fp0 - fw0[t], axis=1) / np.sqrt(max(len(a), 1)) / scale
    confidence = np.exp(-res / opt.tol) * (1.0 + np.clip(local, -1.0, 1.0)) / 2.0
    return PartMap(correspondence=t.astype(np.int64), residual=res, confidence=confidence,
                   image_distance=_image_distance(whole, t) / scale, cost=mean_cost,
                   anchors=np.stack([a, b], axis=1).astype(np.int64), orientation=float(score),
                   region_tol=opt.region_tol,
                   rival=np.stack([seeds[owner[rival]], target[rival]], axis=1).astype(np.int64),
                   placement_confidence=float(placement), scale=part_scale, side_margin=side,
                   other_side=None if other is None else other.astype(np.int64),
                   other_place=None if elsewhere is None else elsewhere.astype(np.int64))
