"""wpot.maps.locate: a part located in a whole by geodesic consistency."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from wpot.examples import example_partial
from wpot.maps.locate import LocateOptions, PartMap, candidate_matches, consistent_matches, locate_part
from wpot.mesh import Mesh, MeshWarning


@pytest.fixture(scope="module")
def partial():
    return example_partial(1500, fraction=0.4)


def _planted_signatures(ex, outliers: float, seed: int = 0):
    """Signatures that put the true match among an anchor's candidates only where they are not replaced by
    noise: the whole's are random, the part's are its true images' plus a little noise, and a share
    ``outliers`` of the part's vertices get unrelated rows (their nearest signatures are anywhere)."""
    rng = np.random.default_rng(seed)
    sw = rng.normal(size=(ex.full.n_vertices, 16))
    sp = sw[ex.correspondence] + 0.05 * rng.normal(size=(ex.part.n_vertices, 16))
    bad = rng.random(ex.part.n_vertices) < outliers
    sp[bad] = rng.normal(size=(int(bad.sum()), 16))
    return sp, sw


def _errors_in_edges(ex, pred):
    full = ex.full
    return np.linalg.norm(full.vertices[pred] - full.vertices[ex.correspondence], axis=1) / full.edge_lengths.mean()


def test_candidate_matches_are_the_nearest_signatures_nearest_first():
    rng = np.random.default_rng(3)
    sp, sw = rng.normal(size=(40, 8)), rng.normal(size=(25, 8))
    anchors = np.array([0, 7, 39, 12])
    d = np.linalg.norm(sp[anchors][:, None] - sw[None], axis=2)
    got = candidate_matches(sp, sw, anchors, 5, "l2", "cpu")
    assert np.array_equal(got, np.argsort(d, axis=1)[:, :5])
    # k beyond the whole's vertices: every vertex, ranked
    assert np.array_equal(candidate_matches(sp, sw, anchors, 99, "l2", "cpu"), np.argsort(d, axis=1))


def test_consistent_matches_recovers_a_planted_isometry():
    # points in the plane, moved rigidly: Euclidean distances are the geodesics of a flat sheet
    rng = np.random.default_rng(1)
    a = rng.random((30, 2))
    rot = np.array([[0.6, -0.8], [0.8, 0.6]])
    b_true = a @ rot.T + 5.0
    k = 6
    owner = np.repeat(np.arange(30), k)
    targets = rng.random((30 * k, 2)) * 1.6 + 4.2  # decoys over the same area
    true_slot = rng.integers(0, k, size=30)
    targets[np.arange(30) * k + true_slot] = b_true
    pa = a[owner]
    d_part = np.linalg.norm(pa[:, None] - pa[None], axis=2)
    d_whole = np.linalg.norm(targets[:, None] - targets[None], axis=2)
    kept = consistent_matches(d_part, d_whole, owner, sigma0=0.01, rel_tol=0.02)
    assert sorted(kept.tolist()) == sorted((np.arange(30) * k + true_slot).tolist())


def test_part_found_through_noisy_candidates(partial):
    sp, sw = _planted_signatures(partial, outliers=0.4)
    pm = locate_part(partial.part, partial.full, sp, sw)
    assert isinstance(pm, PartMap) and pm.correspondence.shape == (partial.part.n_vertices,)
    err = _errors_in_edges(partial, pm.correspondence)
    assert np.median(err) < 1.5 and np.quantile(err, 0.9) < 3.0
    # every kept anchor pair is a true match (to within the triangulations' difference)
    ex_err = np.linalg.norm(partial.full.vertices[pm.anchors[:, 1]]
                            - partial.full.vertices[partial.correspondence[pm.anchors[:, 0]]], axis=1)
    assert len(pm.anchors) >= 20 and np.all(ex_err < 6.0 * partial.full.edge_lengths.mean())
    # the region is the cap's place in the whole (by area, against the true images and their neighbours)
    truth = np.zeros(partial.full.n_vertices, dtype=bool)
    truth[partial.correspondence] = True
    truth |= (partial.full.adjacency @ truth.astype(float)) > 0
    area = partial.full.vertex_areas
    found = pm.region()
    precision = area[found & truth].sum() / area[found].sum()
    recall = area[found & truth].sum() / area[truth].sum()
    assert precision > 0.9 and recall > 0.8
    assert np.all((pm.confidence >= 0) & (pm.confidence <= 1)) and np.all(pm.residual >= 0)


def test_a_whole_with_a_second_component(partial):
    """A loose piece in the whole (a scan's debris): the distances to it are infinite, the map must not notice."""
    from wpot.examples import example_mesh

    debris = example_mesh(120)
    full = partial.full
    with pytest.warns(MeshWarning, match="2 connected components"):
        whole = Mesh(np.r_[full.vertices, 0.2 * debris.vertices + [6.0, 0.0, 0.0]],
                     np.r_[full.faces, debris.faces + full.n_vertices])
    sp, sw = _planted_signatures(partial, outliers=0.4)
    sw = np.r_[sw, np.random.default_rng(5).normal(size=(debris.n_vertices, sw.shape[1]))]
    pm = locate_part(partial.part, whole, sp, sw)
    assert pm.correspondence.max() < full.n_vertices  # nothing lands on the debris
    err = _errors_in_edges(partial, pm.correspondence)
    assert np.median(err) < 1.5 and np.all(np.isfinite(pm.residual)) and not pm.region()[full.n_vertices:].any()


def test_kept_geodesics_and_a_prepared_whole_give_the_same_map(partial):
    """The distances kept from an earlier part, or all of the whole's computed up front, are the ones a cold call
    computes: the maps agree exactly."""
    from wpot.maps.locate import clear_geodesics, prepare_whole

    sp, sw = _planted_signatures(partial, outliers=0.3, seed=4)
    clear_geodesics()
    cold = locate_part(partial.part, partial.full, sp, sw)
    again = locate_part(partial.part, partial.full, sp, sw)
    clear_geodesics()
    prepare_whole(partial.full)
    prepared = locate_part(partial.part, partial.full, sp, sw)
    for pm in (again, prepared):
        np.testing.assert_array_equal(pm.correspondence, cold.correspondence)
        np.testing.assert_array_equal(pm.residual, cold.residual)
        assert pm.placement_confidence == cold.placement_confidence and pm.orientation == cold.orientation
    with pytest.raises(TypeError, match="whole must be a wpot.Mesh"):
        prepare_whole(partial.full.vertices)


def test_rigid_motion_of_the_whole_changes_nothing(partial):
    sp, sw = _planted_signatures(partial, outliers=0.3, seed=2)
    base = locate_part(partial.part, partial.full, sp, sw, options=LocateOptions(orient=False))
    rot = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))  # proper
    moved = Mesh(partial.full.vertices @ rot.T + [3.0, -1.0, 2.0], partial.full.faces)
    other = locate_part(partial.part, moved, sp, sw, options=LocateOptions(orient=False))
    assert np.mean(other.correspondence == base.correspondence) > 0.99
    np.testing.assert_allclose(other.residual, base.residual, atol=1e-3)


def test_a_part_at_another_scale_is_found_with_its_scale(partial):
    """A part shrunk to 0.8 of its size (a data set normalised shape by shape): with one scale assumed, its
    geodesic distances disagree with the whole's by 25 % and the map is lost; ``scale="fit"`` finds 1 / 0.8 to
    within a step of its grid, and the map is the unshrunk part's."""
    from wpot.maps.locate import SCALE_RANGE, SCALE_STEPS, LocateWarning

    sp, sw = _planted_signatures(partial, outliers=0.4)
    small = Mesh(0.8 * partial.part.vertices, partial.part.faces)
    with pytest.warns(LocateWarning, match=r"agree [\d.]+ times better with the whole's at 1\.\d+ times their "
                      r"length.*LocateOptions\(scale='fit'\)"):
        same = locate_part(small, partial.full, sp, sw)
    fit = locate_part(small, partial.full, sp, sw, options=LocateOptions(scale="fit"))
    given = locate_part(small, partial.full, sp, sw, options=LocateOptions(scale=1.25))
    step = (SCALE_RANGE ** (2.0 / (SCALE_STEPS - 1))) ** 0.5
    assert same.scale == 1.0 and given.scale == 1.25
    assert abs(np.log(fit.scale / 1.25)) <= np.log(step) / 2 + 1e-9
    assert np.median(_errors_in_edges(partial, same.correspondence)) > 2.0
    for pm in (fit, given):
        err = _errors_in_edges(partial, pm.correspondence)
        assert np.median(err) < 1.5 and np.quantile(err, 0.9) < 3.0 and len(pm.anchors) > 2 * len(same.anchors)
    # the part at its own scale: no warning, the fit stays at 1, and the map is the default's
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)
        base = locate_part(partial.part, partial.full, sp, sw)
    unit = locate_part(partial.part, partial.full, sp, sw, options=LocateOptions(scale="fit"))
    assert unit.scale == 1.0 and np.array_equal(unit.correspondence, base.correspondence)
    assert "scale 1.2" in repr(given) and "scale" not in repr(base)


def test_comparer_describes_a_part_of_given_scale_at_the_whole_s_size(partial):
    """`Comparer.locate` with LD-SIFT at the whole's edge length (``edge="whole"``), which sees a part at its own
    size: a part shrunk to 0.8 with ``scale=1.25`` given is described and located grown back by 1.25, as a fitted
    scale is, so the map is the one of the part at the whole's size at scale 1, and reports 1.25. At each mesh's own
    edge length (the default), LD-SIFT is scale-free and the part is located as it is."""
    from wpot.comparison import Comparer

    c = Comparer(signature="ldsift", device="cpu", cache_dir=False)
    small = partial.part.transformed(scale=0.8)
    pm = c.locate(small, partial.full, options=LocateOptions(edge="whole", scale=1.25))
    ref = c.locate(small.transformed(scale=1.25), partial.full, options=LocateOptions(edge="whole", scale=1.0))
    assert pm.scale == 1.25 and ref.scale == 1.0
    np.testing.assert_array_equal(pm.correspondence, ref.correspondence)
    np.testing.assert_allclose(pm.residual, ref.residual)
    own = c.locate(small, partial.full, options=LocateOptions(scale=1.25))
    direct = locate_part(small, partial.full, c.signatures(small), c.signatures(partial.full), metric="l2",
                         options=LocateOptions(scale=1.25), device="cpu")
    np.testing.assert_array_equal(own.correspondence, direct.correspondence)
    assert own.scale == 1.25


def test_cat_head_found_in_another_pose(tosca5k):
    """A cat's head cut from one pose, located in another pose (a different triangulation) with LD-SIFT:
    far nearer the truth than the partial transport's own map on the same signatures."""
    import warnings

    from wpot.comparison import Comparer
    from wpot.paper.head import clean_region, geodesic_from, region_fraction_radius
    from wpot.datasets import tosca_ground_truth
    from wpot.evaluate import GeodesicDistances
    from wpot.io import load_mesh
    from wpot.maps.locate import LocateWarning
    from wpot.mesh import cut

    folder = tosca5k / "vtx_5k" if (tosca5k / "vtx_5k").is_dir() else tosca5k
    src, whole = load_mesh(folder / "cat0.off"), load_mesh(folder / "cat1.off")
    snout = int(np.argmin(src.vertices[:, 1]))  # TOSCA's animals face -y
    d = geodesic_from(src, snout)
    part, idx = cut(src, clean_region(src, d <= region_fraction_radius(src, d, 0.25), snout))
    vts_s, vts_t = tosca_ground_truth(folder, "cat0", "cat1")
    inv = np.full(src.n_vertices, -1)
    inv[idx] = np.arange(len(idx))
    in_part = inv[vts_s] >= 0
    p_vertices, truth = inv[vts_s][in_part], vts_t[in_part]
    geo = GeodesicDistances(whole)
    c = Comparer(signature="ldsift", transport="partial", max_vertices=300, vertices_per_sample=20, pooling="cell",
                 device="cpu", cache_dir=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)  # one scale: no doubt about it
        pm = c.locate(part, whole)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        transport_map = c.compare(part, whole).correspondence
    err = geo.pairwise(pm.correspondence[p_vertices], truth) / np.sqrt(whole.area)
    err_transport = geo.pairwise(transport_map[p_vertices], truth) / np.sqrt(whole.area)
    assert err.mean() < 0.08 and err.mean() < err_transport.mean() / 3
    # the more confident half of the matches is the better half
    order = np.argsort(-pm.confidence[p_vertices], kind="stable")
    half = len(order) // 2
    assert err[order[:half]].mean() < 0.7 * err[order[half:]].mean()
    # the matched region holds most of the head's true place, and little else
    true_region = np.zeros(whole.n_vertices, dtype=bool)
    true_region[truth] = True
    area = whole.vertex_areas
    found = pm.region()
    hull = (whole.adjacency @ true_region.astype(float) > 0) | true_region
    assert area[found & hull].sum() / area[found].sum() > 0.8
    # retrieval: the mean nearest-signature cost is that of the signatures' cost matrix
    from wpot.cost import cost_matrix

    chamfer = cost_matrix(c.signatures(part), c.signatures(whole), metric="l2").min(axis=1).mean()
    assert c.nearest_signature_distance(part, whole) == pytest.approx(chamfer, rel=1e-6)
    # the head enlarged by 1.25 (a data set scaled shape by shape): at one scale it is lost, with a warning that
    # names the option; scale="fit" finds 1 / 1.25 and the head's place
    big = part.transformed(scale=1.25)
    with pytest.warns(LocateWarning, match="different scales.*scale='fit'"):
        lost = c.locate(big, whole)
    fit = c.locate(big, whole, options=LocateOptions(scale="fit"))
    err_lost = geo.pairwise(lost.correspondence[p_vertices], truth) / np.sqrt(whole.area)
    err_fit = geo.pairwise(fit.correspondence[p_vertices], truth) / np.sqrt(whole.area)
    assert abs(np.log(fit.scale * 1.25)) < np.log(1.1)
    assert err_fit.mean() < 0.08 and err_lost.mean() > 2 * err_fit.mean()


def _fold(part, whole, idx, radius: float):
    """The true map ``idx`` with a disc of the part (``radius`` around its most central vertex) reflected in
    place, across the plane through the disc's centre that holds its normal (as a limb mapped turned about its
    axis would be): the disc's images stay near it but reverse orientation. Returns the map and the disc."""
    from scipy.spatial import cKDTree

    p = part.vertices
    c = int(np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1)))
    n = part.vertex_normals[c]
    e = np.cross(n, [0.0, 0.0, 1.0])
    u = np.cross(n, e / np.linalg.norm(e))  # the mirror plane holds n and e
    disc = np.linalg.norm(p - p[c], axis=1) < radius
    t = idx.copy()
    t[disc] = cKDTree(whole.vertices).query(p[disc] - 2.0 * ((p[disc] - p[c]) @ u)[:, None] * u)[1]
    return t, disc


def _smooth_signatures(mesh, seed: int = 0):
    """(N, 16) smooth functions of the position, with no mirror symmetry: like real signatures, a vertex's
    neighbours have nearly its signature and its mirror image does not."""
    rng = np.random.default_rng(seed)
    return np.sin(mesh.vertices @ rng.normal(scale=2.0, size=(3, 16)) + rng.uniform(0.0, 2.0 * np.pi, 16))


def test_orientation_step_redraws_a_fold_and_finds_the_side():
    """Step 4 (`_orient`) on a part of a mirror-symmetric whole: a small stretch reflected in place, which the
    repair through the whole's symmetry (`keep_orientation`, candidate (a)) leaves as it is, is redrawn from
    its neighbours (candidate (b)); a map sent whole onto the mirror side comes back."""
    from helpers import mirror_symmetric

    from wpot.maps.locate import _orient, _Redraw
    from wpot.mesh import cut
    from wpot.maps.symmetry import keep_orientation, reflection_symmetry
    from wpot.maps.orientation import orientation_score
    from wpot.sampling import farthest_point_sampling

    whole = mirror_symmetric(1500, seed=1)
    sym = reflection_symmetry(whole, cache=False)
    assert sym is not None
    part, idx = cut(whole, whole.vertices[:, 0] > 0.15)  # one side, clear of the symmetry plane
    draw = _Redraw(part, whole, farthest_point_sampling(part, 96).indices)
    sw = _smooth_signatures(whole)
    sp = sw[idx]

    def cost(t):
        return float(np.mean(np.linalg.norm(sp - sw[t], axis=1)))

    edge = whole.edge_lengths.mean()

    def err(t):
        return np.linalg.norm(whole.vertices[t] - whole.vertices[idx], axis=1) / edge

    folded, disc = _fold(part, whole, idx, 0.3)
    assert np.median(err(folded)[disc]) > 1.5 and orientation_score(part, whole, folded) < 0.97
    old = keep_orientation(part, whole, folded, refine=lambda t0: draw.rounds(t0, 2), symmetry_of="b")[0]
    assert np.median(err(old)[disc]) > 1.5  # the repair through the symmetry does not see it
    far = 0.1 * np.sqrt(whole.area)
    t, score, c, _, _ = _orient(draw, folded, cost, 2, far=far)
    assert np.median(err(t)[disc]) < 0.5 and np.quantile(err(t), 0.9) < 1.0
    assert score > 0.97 and c == pytest.approx(cost(t)) and c < cost(folded)
    t, score, _, side, alt = _orient(draw, sym.map[idx], cost, 2, far=far)  # the mirror image of the true map
    assert np.quantile(err(t), 0.9) < 1.0 and score > 0.97
    # candidate (b), the mirror side unfolded, costs more, and is the other side's answer
    assert side > 0.0 and np.median(np.linalg.norm(whole.vertices[alt] - whole.vertices[sym.map[idx]], axis=1)) < edge


def test_other_side_tells_a_map_from_its_mirror_image():
    """`_other_side`: a map, its mirror image and the map with a minority of its images mirrored, each read
    against the true map and against its mirror; a part on the plane of symmetry has no side."""
    from helpers import mirror_symmetric

    from wpot.maps.locate import _other_side
    from wpot.maps.symmetry import reflection_symmetry

    whole = mirror_symmetric(1500, seed=1)
    mirror = reflection_symmetry(whole, cache=False).map
    far = 0.1 * np.sqrt(whole.area)
    x = whole.vertices[:, 0]
    idx = np.nonzero(x > 0.15)[0]
    some = idx.copy()
    some[::3] = mirror[idx[::3]]  # a third of the images mirrored
    cands = [idx, mirror[idx], some]
    assert _other_side(whole, mirror, idx, cands, far).tolist() == [False, True, False]
    assert _other_side(whole, mirror, mirror[idx], cands, far).tolist() == [True, False, True]
    plane = np.nonzero(np.abs(x) < 0.2 * far)[0]
    assert _other_side(whole, mirror, plane, [plane, mirror[plane]], far) is None


def _pick(scores, costs, weight=None) -> int:
    """The candidate step 4 keeps (`_orient`): the least of `_rule`, the first on a tie."""
    from wpot.maps.locate import _rule

    return int(np.argmin(_rule(scores, costs, weight)))


def test_orientation_step_picks_the_cheapest_of_the_well_oriented():
    from wpot.maps.locate import ORIENT_MARGIN

    assert ORIENT_MARGIN == 0.5
    assert _pick([0.9, 0.5, -0.2], [3.0, 1.0, 0.0]) == 1  # -0.2 is more than 0.5 below the best
    assert _pick([0.9, 0.3, 0.95], [3.0, 1.0, 2.0]) == 2
    assert _pick([np.nan, 0.8, 0.6], [0.0, 5.0, 1.0]) == 2  # NaN reads as -1
    assert _pick([0.5, 0.5], [1.0, 1.0]) == 0


def test_orientation_weight_trades_relative_cost_against_orientation():
    from wpot.maps.locate import ORIENT_WEIGHT

    w = ORIENT_WEIGHT
    # a cost 1 % above the least is worth 0.01 / w of orientation score
    assert _pick([0.5, 0.5 + 0.02 / w], [100.0, 101.0], w) == 1
    assert _pick([0.5, 0.5 + 0.005 / w], [100.0, 101.0], w) == 0
    assert _pick([0.9, 0.3, 0.95], [3.0, 1.0, 2.0], w) == 1  # the others cost 100 % and 200 % more
    assert _pick([np.nan, 0.8, 0.6], [100.0, 100.0, 100.0], w) == 1  # NaN reads as -1
    assert _pick([0.5, 0.5], [1.0, 1.0], w) == 0  # a tie: the first
    # the costs' scale does not matter; weight 0 is the least cost whatever the orientation
    assert _pick([0.2, 0.6, 0.1], [5.0, 5.2, 4.9], w) == _pick([0.2, 0.6, 0.1], [500.0, 520.0, 490.0], w) == 1
    assert _pick([0.9, -0.9], [1.01, 1.0], 0.0) == 1
    # the margin rule (the default) would take the cheaper of the two well-oriented maps here
    assert _pick([0.9, 0.6], [1.0, 0.99]) == 1 and _pick([0.9, 0.6], [1.0, 0.99], w) == 0
    with pytest.raises(ValueError, match="orient_weight"):
        LocateOptions(orient_weight=-1.0)


def test_bad_input_is_named(partial):
    sp, sw = _planted_signatures(partial, outliers=0.0)
    with pytest.raises(ValueError, match="part_signatures must be"):
        locate_part(partial.part, partial.full, sp[:-1], sw)
    with pytest.raises(ValueError, match="different widths"):
        locate_part(partial.part, partial.full, sp[:, :8], sw)
    with pytest.raises(TypeError, match="whole must be a wpot.Mesh"):
        locate_part(partial.part, "full", sp, sw)
    with pytest.raises(ValueError, match="n_anchors"):
        LocateOptions(n_anchors=2)
    with pytest.raises(ValueError, match="tol"):
        LocateOptions(tol=0.0)
    with pytest.raises(ValueError, match="n_polish"):
        LocateOptions(n_polish=-1)
    for bad in ("fitted", 0, -1.0, float("inf"), True):
        with pytest.raises(ValueError, match=r"scale must be one of \('same', 'fit'\) or a positive number"):
            LocateOptions(scale=bad)
    with pytest.raises(TypeError, match="LocateOptions"):
        locate_part(partial.part, partial.full, sp, sw, options={"n_anchors": 10})
    import wpot

    # the whole's edge length is LD-SIFT's: asked of another signature, it is refused, not ignored
    with pytest.raises(ValueError, match="edge='whole'.*signature='wks'"):
        wpot.Comparer(signature="wks", device="cpu", cache_dir=False).locate(
            partial.part, partial.full, options=LocateOptions(edge="whole"))


def test_a_part_of_several_components_is_refused_naming_the_remedy(partial):
    from wpot.examples import example_mesh

    debris = example_mesh(120)
    p = partial.part
    with pytest.warns(MeshWarning, match="2 connected components"):
        part = Mesh(np.r_[p.vertices, 0.1 * debris.vertices + [6.0, 0.0, 0.0]], np.r_[p.faces, debris.faces + p.n_vertices])
    sp, sw = _planted_signatures(partial, outliers=0.0)
    sp = np.r_[sp, np.random.default_rng(1).normal(size=(debris.n_vertices, sp.shape[1]))]
    with pytest.raises(ValueError, match=r"part has 2 connected components.*keep_largest_component=True"):
        locate_part(part, partial.full, sp, sw)


def test_a_part_larger_than_the_whole_is_named(partial):
    from wpot.maps.locate import LocateWarning

    sp, sw = _planted_signatures(partial, outliers=0.0)
    # the whole as the part and the part as the whole: swapped arguments
    with pytest.warns(LocateWarning, match=r"the part's area is 2\.\d+ times that of the whole.*swapped"):
        locate_part(partial.full, partial.part, sw, sp)
    # a true part raises no such warning
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)
        locate_part(partial.part, partial.full, sp, sw)


def test_placement_confidence_separates_a_unique_place_a_second_place_and_no_place(partial):
    """Step 5: a part whose candidates hold one consistent place is trusted; the same part in a whole that holds
    its place twice (two copies, the candidates split between them) is not, and its rival is the other copy;
    nor is a part whose signatures fit nowhere (unrelated rows, so no large consistent set exists)."""
    import warnings

    from wpot.maps.locate import PLACEMENT_DOUBT, LocateWarning

    full = partial.full
    sp, sw = _planted_signatures(partial, outliers=0.3, seed=7)
    one = locate_part(partial.part, full, sp, sw)
    assert one.placement_confidence > 3 * PLACEMENT_DOUBT
    assert len(one.rival) < 0.5 * len(one.anchors)
    assert one.other_place is None  # the place is not in doubt

    with pytest.warns(MeshWarning, match="2 connected components"):
        twice = Mesh(np.r_[full.vertices, full.vertices + [5.0 * np.ptp(full.vertices[:, 0]), 0.0, 0.0]],
                     np.r_[full.faces, full.faces + full.n_vertices])
    pm = locate_part(partial.part, twice, sp, np.r_[sw, sw])
    assert pm.placement_confidence < PLACEMENT_DOUBT
    # the two places are the two copies
    sides = [pm.anchors[:, 1] >= full.n_vertices, pm.rival[:, 1] >= full.n_vertices]
    assert len(pm.rival) > 0.5 * len(pm.anchors) and sides[0].all() != sides[1].all()
    assert sides[0].all() or not sides[0].any()
    # the other answer is the same map on the other copy, vertex for vertex where the copies' signatures agree
    n = full.n_vertices
    assert pm.other_place is not None and pm.other_place.shape == pm.correspondence.shape
    on_second = pm.other_place >= n
    assert on_second.all() != (pm.correspondence >= n).all() and (on_second.all() or not on_second.any())
    assert np.mean(pm.other_place % n == pm.correspondence % n) > 0.9

    noise = np.random.default_rng(8).normal(size=sp.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LocateWarning)  # few consistent matches: warned about, and low
        nowhere = locate_part(partial.part, full, noise, sw)
    assert nowhere.placement_confidence < PLACEMENT_DOUBT


def test_a_part_wound_against_itself_is_named_and_not_oriented(partial):
    """A patch of the part's triangles wound the wrong way turns every orientation read there: locate names the
    part and the repair (`Mesh.cleaned`), leaves the side unchecked (orientation NaN), and places the part as
    well as the rewound one does without its orientation step; the rewound part is oriented again."""
    import warnings

    from wpot.maps.locate import LocateWarning

    part = partial.part
    faces = part.faces.copy()
    patch = np.argsort(np.linalg.norm(part.vertices[part.faces].mean(axis=1) - part.vertices[0], axis=1))[:40]
    faces[patch] = faces[patch][:, ::-1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)  # the mesh says so too, when it is made
        wound = Mesh(part.vertices, faces, name="scan-7")
    assert wound.misoriented_faces.size > 0
    sp, sw = _planted_signatures(partial, outliers=0.2)
    with pytest.warns(LocateWarning, match=r"scan-7.*part has \d+ triangles wound against.*Mesh\.cleaned\(\)"):
        pm = locate_part(wound, partial.full, sp, sw)
    assert np.isnan(pm.orientation)
    plain = locate_part(part, partial.full, sp, sw, options=LocateOptions(orient=False))
    np.testing.assert_array_equal(pm.correspondence, plain.correspondence)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)
        fixed = locate_part(wound.cleaned()[0], partial.full, sp, sw)
    assert np.isfinite(fixed.orientation)


def test_polish_weighs_the_near_anchors_around_a_hole():
    """Step 3's polish: on a flat sheet, the part a square frame around a hole, so that the part's geodesics
    between opposite sides go around the hole and are longer than the whole's. Redrawn from its exact images, the
    map drifts by about two edges when distances are compared as they are (the far anchors, stretched most,
    outweigh the near ones), and stays within an edge when they are compared relative to their length."""
    from wpot.maps.locate import _Redraw
    from wpot.maps.seams import LOG_OFFSET
    from wpot.mesh import cut
    from wpot.sampling import farthest_point_sampling

    n = 41
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    v[:, :2] += np.random.default_rng(0).uniform(-0.2, 0.2, size=(n * n, 2)) / (n - 1)
    corner = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.r_[np.c_[corner, corner + 1, corner + n + 1], np.c_[corner, corner + n + 1, corner + n]]
    whole = Mesh(v, faces)
    r = np.linalg.norm(v[:, :2] - 0.5, axis=1)
    part, idx = cut(whole, (r > 0.2) & (np.abs(v[:, :2] - 0.5).max(axis=1) < 0.45))
    draw = _Redraw(part, whole, farthest_point_sampling(part, 96).indices)
    edge = whole.edge_lengths.mean()

    def drift(t):
        return np.linalg.norm(whole.vertices[t] - whole.vertices[idx], axis=1).mean() / edge

    absolute = drift(draw.rounds(idx.copy(), 1))
    relative = drift(draw.rounds(idx.copy(), 1, offset=LOG_OFFSET * max(part.mean_edge_length, edge)))
    assert absolute > 1.5 and relative < 1.0


def test_step_4_rule_values_in_closed_form():
    """`_rule`: the relative cost r = cost / least cost − 1, less weight × orientation score; with no weight, r
    for the candidates oriented within `ORIENT_MARGIN` of the best and inf for the others. Step 4 keeps its least."""
    from wpot.maps.locate import ORIENT_MARGIN, _rule

    scores, costs = [0.9, 0.9 - ORIENT_MARGIN - 0.01, np.nan], [2.0, 1.0, 2.5]
    assert _rule(scores, costs).tolist() == [1.0, np.inf, np.inf]
    low = 0.9 - ORIENT_MARGIN - 0.01
    assert np.allclose(_rule(scores, costs, 0.3), [1.0 - 0.3 * 0.9, -0.3 * low, 1.5 + 0.3])  # NaN reads as -1
    assert _pick(scores, costs) == 0 and _pick(scores, costs, 0.3) == 1


def test_side_margin_read_on_a_mirror_symmetric_whole_and_not_read_without_one():
    """A part of one side of a mirror-symmetric whole has no symmetry of its own, so a map onto the other side
    cannot keep orientation: with signatures blind to the mirror (the same at a point and its mirror image) the
    side is still orientation's call, the map is on the true side and its side margin is not in doubt. A whole
    in which no mirror is found, or ``orient=False``, leaves the side unread (NaN)."""
    from helpers import mirror_symmetric, sphere_points

    from wpot.maps.locate import SIDE_DOUBT
    from wpot.maps.symmetry import reflection_symmetry
    from wpot.mesh import cut

    whole = mirror_symmetric(1500, seed=1)
    part, idx = cut(whole, whole.vertices[:, 0] > 0.15)
    blind = _smooth_signatures(whole) + _smooth_signatures(Mesh(whole.vertices * [-1.0, 1.0, 1.0], whole.faces))
    for weight in (None, 0.3):
        pm = locate_part(part, whole, blind[idx], blind, options=LocateOptions(orient_weight=weight))
        x = whole.vertices
        assert np.median(np.linalg.norm(x[pm.correspondence] - x[idx], axis=1)) < whole.mean_edge_length
        assert pm.side_margin >= SIDE_DOUBT  # inf where every candidate kept the true side
        if pm.other_side is not None:  # the other side's answer: most of its images nearer the mirror side
            mirror = x[idx] * [-1.0, 1.0, 1.0]
            assert np.mean(np.linalg.norm(x[pm.other_side] - mirror, axis=1)
                           < np.linalg.norm(x[pm.other_side] - x[idx], axis=1)) > 0.5
        else:
            assert np.isinf(pm.side_margin)
        back = json.loads(json.dumps(pm.summary(), allow_nan=False))  # plain JSON, inf written "inf"
        assert back["side_margin"] == ("inf" if np.isinf(pm.side_margin) else pytest.approx(pm.side_margin))
        assert back["placement_confidence"] == pm.placement_confidence and back["n_anchors"] == len(pm.anchors)
    unread = locate_part(part, whole, blind[idx], blind, options=LocateOptions(orient=False))
    assert np.isnan(unread.side_margin) and unread.other_side is None
    assert json.loads(json.dumps(unread.summary(), allow_nan=False))["side_margin"] is None

    # a sphere with one bump: its mirror planes (every plane through the bump's axis) single none out
    u, f = sphere_points(1200, seed=2)
    bumpy = Mesh(u * (1.0 + 0.3 * np.exp((u @ np.array([0.6, 0.0, 0.8]) - 1.0) / 0.16))[:, None], f)
    assert reflection_symmetry(bumpy) is None
    sig = _smooth_signatures(bumpy)
    part, idx = cut(bumpy, bumpy.vertices[:, 2] > 0.2)
    assert np.isnan(locate_part(part, bumpy, sig[idx], sig).side_margin)


def test_a_landmark_chooses_the_place_and_the_side(partial):
    """Landmarks decide what the signatures and geodesics cannot: in a whole that holds the part's place twice
    (two copies), one landmark on either copy puts the whole map there, with no rival left (the other copy
    disagrees with the landmark); on a mirror-symmetric whole with signatures blind to the mirror, one landmark
    on either side puts the map on that side, even the side whose map reverses orientation."""
    from helpers import mirror_symmetric

    from wpot.maps.locate import PLACEMENT_DOUBT
    from wpot.maps.symmetry import reflection_symmetry
    from wpot.mesh import cut

    full, n = partial.full, partial.full.n_vertices
    sp, sw = _planted_signatures(partial, outliers=0.3, seed=7)
    with pytest.warns(MeshWarning, match="2 connected components"):
        twice = Mesh(np.r_[full.vertices, full.vertices + [5.0 * np.ptp(full.vertices[:, 0]), 0.0, 0.0]],
                     np.r_[full.faces, full.faces + full.n_vertices])
    free = locate_part(partial.part, twice, sp, np.r_[sw, sw])
    v = int(np.argmax(np.linalg.norm(partial.part.vertices - partial.part.vertices.mean(axis=0), axis=1)))
    for copy in (0, 1):
        pm = locate_part(partial.part, twice, sp, np.r_[sw, sw],
                         landmarks=[[v, partial.correspondence[v] + copy * n]])
        assert (pm.correspondence // n == copy).all()
        assert np.median(_errors_in_edges(partial, pm.correspondence % n)) < 1.0  # the true map, on that copy
        assert np.mean(pm.correspondence % n == free.correspondence % n) > 0.8  # nearly the free one
        assert pm.placement_confidence > PLACEMENT_DOUBT and pm.other_place is None
        assert [v, partial.correspondence[v] + copy * n] in pm.anchors.tolist()

    whole = mirror_symmetric(1500, seed=1)
    mirror = reflection_symmetry(whole, cache=False).map
    part, idx = cut(whole, whole.vertices[:, 0] > 0.15)
    blind = _smooth_signatures(whole) + _smooth_signatures(Mesh(whole.vertices * [-1.0, 1.0, 1.0], whole.faces))
    x, edge = whole.vertices, whole.mean_edge_length
    w = int(np.argmax(part.vertices[:, 0]))  # the farthest from the plane of symmetry
    for truth in (idx, mirror[idx]):
        pm = locate_part(part, whole, blind[idx], blind, options=LocateOptions(orient_weight=0.3),
                         landmarks=[[w, truth[w]]])
        assert np.median(np.linalg.norm(x[pm.correspondence] - x[truth], axis=1)) < edge
        assert np.isinf(pm.side_margin)  # the landmark ruled the other side out


def test_landmarks_checked_and_disagreeing_landmarks_named(partial):
    """Bad ``landmarks`` are refused naming the keyword; two that cannot both be right (the geodesic distance
    between them on the part far from that on the whole) are warned about, naming them."""
    from wpot.maps.locate import LocateWarning

    sp, sw = _planted_signatures(partial, outliers=0.0)
    part, full, t = partial.part, partial.full, partial.correspondence
    for bad, match in (([1, 2], r"landmarks must be \(L, 2\)"), (np.zeros((0, 2), int), r"L >= 1"),
                       ([[0, full.n_vertices]], r"landmarks\[:, 1\] holds 1 indices outside"),
                       ([[part.n_vertices, 0]], r"landmarks\[:, 0\] holds 1 indices outside"),
                       ([[0.5, 3]], "vertex indices"), ([[0, 1], [0, 2]], "vertex 0 of the part more than once")):
        with pytest.raises(ValueError, match=match):
            locate_part(part, full, sp, sw, landmarks=bad)
    far = np.linalg.norm(part.vertices - part.vertices[0], axis=1)
    a, b = 0, int(np.argmax(far))
    with pytest.warns(LocateWarning, match="landmarks 0 and 1 disagree"):
        locate_part(part, full, sp, sw, landmarks=[[a, t[a]], [b, t[a]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)  # two right landmarks: no warning
        pm = locate_part(part, full, sp, sw, landmarks=[[a, t[a]], [b, t[b]]])
    assert np.median(_errors_in_edges(partial, pm.correspondence)) < 1.0


def test_turn_of_a_map_in_closed_form_and_in_step_4_s_rule():
    """`_turn`: a mesh turned by θ about any axis and mapped vertex for vertex onto itself turns by θ / 180°, at
    any scale and translation; `_rule` adds each candidate's turn to its value under both rules."""
    from helpers import mirror_symmetric

    from wpot.maps.locate import _rule, _turn

    mesh = mirror_symmetric(400, seed=3)
    ident = np.arange(mesh.n_vertices)
    for deg, axis in ((0.0, [0, 0, 1]), (60.0, [1, 2, 3]), (150.0, [0, 1, 0]), (180.0, [1, 0, 0])):
        k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        th = np.radians(deg)
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rot = np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx  # Rodrigues
        moved = Mesh(2.5 * mesh.vertices @ rot.T + [1.0, -2.0, 0.5], mesh.faces)
        assert _turn(moved, mesh, ident) == pytest.approx(deg / 180.0, abs=1e-6)
    scores, costs, turns = [0.8, 0.8], [1.0, 1.05], [0.9, 0.1]
    assert np.allclose(_rule(scores, costs, 0.3, turns), [0.9 - 0.24, 0.05 + 0.1 - 0.24])
    assert np.allclose(_rule(scores, costs, None, turns), [0.9, 0.15])
    assert _pick(scores, costs) == 0 and int(np.argmin(_rule(scores, costs, None, turns))) == 1
    assert _turn(mesh, mesh, np.zeros(mesh.n_vertices, dtype=np.int64)) == 1.0  # every image at one vertex
    with pytest.raises(ValueError, match="aligned"):
        LocateOptions(aligned="yes")


def test_aligned_part_keeps_its_map_and_a_turned_one_is_named(partial):
    """With ``aligned=True`` a part given in the whole's frame is located as without it, its map turning it by
    next to nothing; the example's part as given (moved rigidly by the example's rotation, more than 90°) gets a
    `LocateWarning` that names the option."""
    from wpot.maps.locate import TURN_DOUBT, LocateWarning, _turn

    sp, sw = _planted_signatures(partial, outliers=0.3, seed=7)
    home = Mesh((partial.part.vertices - partial.translation) @ partial.rotation, partial.part.faces)
    free = locate_part(home, partial.full, sp, sw)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LocateWarning)
        pm = locate_part(home, partial.full, sp, sw, options=LocateOptions(aligned=True))
    assert np.median(_errors_in_edges(partial, pm.correspondence)) < 1.0
    assert np.mean(pm.correspondence == free.correspondence) > 0.95
    assert 180.0 * _turn(home, partial.full, pm.correspondence) < 10.0
    angle = np.degrees(np.arccos((np.trace(partial.rotation) - 1.0) / 2.0))
    assert angle > TURN_DOUBT  # the example's own motion
    with pytest.warns(LocateWarning, match="aligned"):
        locate_part(partial.part, partial.full, sp, sw, options=LocateOptions(aligned=True))
