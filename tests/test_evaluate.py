"""Classification statistics on hand-made distance matrices, and geodesic errors where they are known."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from wpot.evaluate import (
    GeodesicDistances,
    classification_draws,
    correspondence_error,
    cumulative_curve,
    curve_auc,
    leave_one_out_1nn,
    leave_one_out_levels,
    one_shot_1nn,
    part_retrieval,
    summarize_correspondence,
    symmetric_flip,
)
from wpot.mesh import Mesh


def line_distances(x):
    x = np.asarray(x, dtype=float)
    return np.abs(x[:, None] - x[None, :])


# ----------------------------------------------------------------------------- classification
def test_separated_classes_are_always_right():
    d = line_distances([0, 1, 2, 10, 11, 12, 20, 21])
    lab = ["a", "a", "a", "b", "b", "b", "c", "c"]
    r = one_shot_1nn(d, lab, n_trials=500, seed=1)
    assert r.mean == 1.0 and r.std == 0.0
    assert leave_one_out_1nn(d, lab).accuracy == 1.0


def test_leave_one_out_one_misclassified_shape():
    # the "a" at 8 is nearer to the "b" at 10 than to any "a"; every other shape's nearest is its own class
    x = [0, 1, 2, 8, 10, 11, 12]
    lab = ["a", "a", "a", "a", "b", "b", "b"]
    r = leave_one_out_1nn(line_distances(x), lab)
    assert r.accuracy == pytest.approx(6 / 7)
    assert r.score.tolist() == [1, 1, 1, 0, 1, 1, 1]
    assert r.nearest[3] == 4


def test_one_shot_expected_accuracy_analytic():
    # A = {0, 1}, B = {3, 10}. The 4 equally likely training sets give accuracies 1, 1/2, 1, 1/2 over the
    # 2 remaining shapes (the B at 3 is nearer the A's than the B at 10): mean 3/4, std 1/4.
    d = line_distances([0, 1, 3, 10])
    lab = ["A", "A", "B", "B"]
    t = 4000
    r = one_shot_1nn(d, lab, n_trials=t, seed=7)
    assert set(np.unique(r.accuracies)) <= {0.5, 1.0}
    assert abs(r.mean - 0.75) < 5 * 0.25 / np.sqrt(t)
    assert r.std == pytest.approx(0.25, abs=0.02)
    # the A left out is always right; the B left out is the one at 3 half of the time, and it is taken for an A
    assert r.classes == ("A", "B")
    np.testing.assert_allclose(r.confusion[0], [1.0, 0.0])
    assert abs(r.confusion[1, 0] - 0.5) < 5 * 0.5 / np.sqrt(t)
    np.testing.assert_allclose(r.confusion.sum(1), 1.0)
    assert r.class_accuracy == {"A": 1.0, "B": pytest.approx(r.confusion[1, 1])}


def test_one_shot_matches_exhaustive_enumeration():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(7, 2))
    pts[:3] += 1.0
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    lab = np.array([0, 0, 0, 1, 1, 2, 2])
    members = [np.nonzero(lab == c)[0] for c in range(3)]
    accs = []
    counts = np.zeros((3, 3))
    for train in itertools.product(*members):  # every training set, each equally likely
        train = np.array(train)
        test = np.setdiff1d(np.arange(7), train)
        pred = lab[train[np.argmin(d[np.ix_(test, train)], axis=1)]]
        accs.append(np.mean(pred == lab[test]))
        np.add.at(counts, (lab[test], pred), 1)
    exact_mean, exact_std = np.mean(accs), np.std(accs)
    exact_confusion = counts / counts.sum(1, keepdims=True)
    t = 6000
    r = one_shot_1nn(d, lab, n_trials=t, seed=11, chunk=1000)
    assert set(np.round(np.unique(r.accuracies), 12)) <= set(np.round(accs, 12))
    assert abs(r.mean - exact_mean) < 5 * exact_std / np.sqrt(t) + 1e-12
    # each confusion entry is a mean of per-trial fractions in [0, 1]: within 5 / sqrt(t) of the exact value
    np.testing.assert_allclose(r.confusion, exact_confusion, atol=5 * 0.5 / np.sqrt(t))
    # the mean accuracy is the diagonal weighted by each class's test count
    n_test = np.bincount(lab) - 1
    assert (np.diag(r.confusion) * n_test).sum() / n_test.sum() == pytest.approx(r.mean, rel=1e-12)


def test_ties_are_split_not_biased():
    n = 6
    d = np.ones((n, n))
    np.fill_diagonal(d, 0)
    lab = ["a", "a", "a", "b", "b", "c"]
    # leave-one-out: every other shape ties; credit = same-class share among the n - 1 others
    r = leave_one_out_1nn(d, lab)
    np.testing.assert_allclose(r.score, [2 / 5] * 3 + [1 / 5] * 2 + [0])
    # one-shot: the 3 training shapes tie, exactly one has the right class
    r = one_shot_1nn(d, lab, n_trials=50)
    assert r.mean == pytest.approx(1 / 3)
    # so every tested query's vote is split evenly; "c" has one shape, always the training one: never tested
    np.testing.assert_allclose(r.confusion[:2], 1 / 3)
    assert np.isnan(r.confusion[2]).all()


def test_relabelling_invariance_and_levels():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(12, 3))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    genus = np.array(list("aabbccddeeff"))
    family = np.array(list("xxxxxxyyyyyy"))
    perm = rng.permutation(12)
    res = leave_one_out_levels(d, {"genus": genus, "family": family})
    res_p = leave_one_out_levels(d[np.ix_(perm, perm)], {"genus": genus[perm], "family": family[perm]})
    for k in res:
        assert res[k].accuracy == pytest.approx(res_p[k].accuracy)
        np.testing.assert_allclose(res_p[k].score, res[k].score[perm])
    # coarser grouping can only help 1-NN
    assert res["family"].accuracy >= res["genus"].accuracy


def test_classification_rejects_bad_input():
    d = line_distances([0, 1, 2, 3])
    with pytest.raises(ValueError, match="labels"):
        leave_one_out_1nn(d, ["a", "b"])
    bad = d.copy()
    bad[0, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        one_shot_1nn(bad, ["a", "a", "b", "b"])
    with pytest.raises(ValueError, match="square"):
        leave_one_out_1nn(d[:3], ["a", "a", "b"])
    with pytest.raises(ValueError, match="no shape is left"):
        one_shot_1nn(d, ["a", "b", "c", "d"])


def test_part_retrieval():
    # full shapes c0, c1 (class c) and h0 (class h); parts cut from c0, c1, h0 sit near 0.1, 1.6, 5.1
    names = ["c0", "c1", "h0", "pc0", "pc1", "ph0"]
    lab = ["c", "c", "h", "c_part", "c_part", "h_part"]
    d = line_distances([0.0, 1.0, 5.0, 0.1, 1.6, 3.2])  # pc1 is nearer c1 (0.6): right; ph0 nearer h0 (1.8)
    r = part_retrieval(d, names, lab, {"pc0": "c0", "pc1": "c1", "ph0": "h0"})
    assert r.nearest == {"pc0": "c0", "pc1": "c1", "ph0": "h0"}
    assert r.class_accuracy == 1.0 and r.parent_accuracy == 1.0
    d = line_distances([0.0, 1.0, 5.0, 0.6, 0.4, 2.9])  # pc0 -> c1 (same class, wrong parent); ph0 -> c1
    r = part_retrieval(d, names, lab, {"pc0": "c0", "pc1": "c1", "ph0": "h0"})
    assert r.nearest == {"pc0": "c1", "pc1": "c0", "ph0": "c1"}
    assert r.class_accuracy == pytest.approx(2 / 3) and r.parent_accuracy == 0.0
    with pytest.raises(ValueError, match="not found"):
        part_retrieval(d, names, lab, {"pc9": "c0"})


# ----------------------------------------------------------------------------- geodesics
def grid(n=31, size=1.0):
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return Mesh(v, np.r_[np.c_[a, b, c], np.c_[a, c, d]])


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(3, radius=2.0)
    return Mesh(s.vertices, s.faces)


def great_circle(m, i, j, r=2.0):
    v = m.vertices
    return r * np.arccos(np.clip(np.sum(v[i] * v[j], axis=-1) / r**2, -1, 1))


def test_flat_grid_heat_distance_is_euclidean():
    m = grid()
    g = GeodesicDistances(m)
    src = np.array([0, 480, 17])
    rows = g.from_sources(src)
    eucl = np.linalg.norm(m.vertices[src][:, None] - m.vertices[None], axis=-1)
    assert np.abs(rows - eucl).max() < 0.05  # heat method, 30x30 grid of a unit square
    assert np.all(rows[np.arange(3), src] == 0)
    assert g.diameter() == pytest.approx(np.sqrt(2), rel=0.02)


def test_sphere_great_circle_and_normalizations(sphere):
    m = sphere
    g = GeodesicDistances(m)
    rng = np.random.default_rng(0)
    truth = rng.integers(0, m.n_vertices, 200)
    pred = rng.integers(0, m.n_vertices, 200)
    exact = great_circle(m, pred, truth)
    np.testing.assert_allclose(g.pairwise(truth, pred), exact, atol=0.03 * np.pi * 2)
    assert g.diameter() == pytest.approx(2 * np.pi, rel=0.03)  # antipodes: pi * r
    e = correspondence_error(g, pred, truth, normalization="sqrt_area")
    np.testing.assert_allclose(e.errors, e.raw / np.sqrt(m.area))
    np.testing.assert_allclose(e.raw, exact, atol=0.03 * np.pi * 2)
    d = correspondence_error(g, pred, truth, normalization="diameter")
    assert d.scale == pytest.approx(2 * np.pi, rel=0.03)
    s = correspondence_error(g, pred, truth, normalization="shrec19")
    assert s.scale <= d.scale * 1.03 and s.scale > 0.9 * 2 * np.pi  # 200 random points span nearly pi * r
    assert s.max_threshold == 0.5 and e.max_threshold == 0.25


def test_perfect_map_and_antipodal_map(sphere):
    m = sphere
    v = m.vertices
    antipode = np.argmin(np.linalg.norm(v[:, None] + v[None], axis=-1), axis=1)  # icosphere is symmetric
    truth = np.arange(m.n_vertices)
    perfect = correspondence_error(m, truth, truth)
    assert perfect.auc == 1.0 and perfect.mean_error == 0.0 and np.all(perfect.curve == 1.0)
    worst = correspondence_error(m, antipode, truth, normalization="sqrt_area")
    # pi r / sqrt(4 pi r^2) = sqrt(pi) / 2 > 0.25: no point under the curve's range
    np.testing.assert_allclose(worst.errors, np.sqrt(np.pi) / 2, rtol=0.03)
    assert worst.auc == 0.0


def test_errors_invariant_to_scale_and_flip_aware(sphere):
    m = sphere
    v = m.vertices
    mirror = np.argmin(np.linalg.norm(v[:, None] - (v * [-1, 1, 1])[None], axis=-1), axis=1)
    assert np.allclose(v[mirror], v * [-1, 1, 1])
    truth = np.arange(0, m.n_vertices, 3)
    pred = mirror[truth]  # a map off exactly by the left/right symmetry
    e = correspondence_error(m, pred, truth, symmetric_truth=mirror[truth])
    assert e.auc < 0.8 and e.flip_aware_auc == 1.0
    np.testing.assert_array_equal(e.flip_aware_errors, 0.0)
    big = m.transformed(scale=3.0)
    for norm in ("sqrt_area", "diameter"):
        a = correspondence_error(m, pred, truth, normalization=norm)
        b = correspondence_error(big, pred, truth, normalization=norm)
        np.testing.assert_allclose(b.raw, 3.0 * a.raw, rtol=1e-6)
        np.testing.assert_allclose(b.errors, a.errors, rtol=1e-6, atol=1e-9)


def test_cross_component_uses_euclidean(sphere):
    v, f = sphere.vertices, sphere.faces
    two = Mesh(np.r_[v, v + [10.0, 0, 0]], np.r_[f, f + len(v)], warn=False)
    truth = np.array([0, 1, 2])
    pred = truth + len(v)
    e = correspondence_error(two, pred, truth)
    assert e.n_cross_component == 3
    np.testing.assert_allclose(e.raw, 10.0)


def trapezoid(y, x):
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2)


def test_auc_of_known_curves():
    t = 0.25
    assert curve_auc(np.zeros(10), t) == 1.0
    assert curve_auc(np.full(10, t), t) == 0.0
    e = (np.arange(1000) + 0.5) / 1000 * t  # uniform on [0, T]: the curve is the diagonal, mean 1/2
    assert curve_auc(e, t) == pytest.approx(0.5)
    thr = np.linspace(0, t, 20001)
    np.testing.assert_allclose(cumulative_curve(e, thr), np.clip(np.floor(thr / t * 1000 + 0.5) / 1000, 0, 1), atol=1e-3)
    rng = np.random.default_rng(0)
    e = rng.exponential(0.1, size=500)
    assert curve_auc(e, t) == pytest.approx(trapezoid(cumulative_curve(e, thr), thr) / t, abs=1e-4)
    # the curve counts errors <= threshold
    assert cumulative_curve([0.0, 0.1, 0.2], [0.1]).tolist() == [2 / 3]


def test_summary_averages_pairs(sphere):
    m = sphere
    g = GeodesicDistances(m)
    rng = np.random.default_rng(2)
    truth = np.arange(50)
    rs = [correspondence_error(g, rng.integers(0, m.n_vertices, 50), truth) for _ in range(3)]
    s = summarize_correspondence(rs)
    assert s.n_pairs == 3 and s.auc == pytest.approx(np.mean([r.auc for r in rs]))
    np.testing.assert_allclose(s.curve, np.mean([r.curve for r in rs], axis=0))
    other = correspondence_error(g, truth, truth, normalization="diameter")
    with pytest.raises(ValueError, match="normalizations"):
        summarize_correspondence([rs[0], other])


def test_correspondence_rejects_bad_input(sphere):
    with pytest.raises(ValueError, match="normalization"):
        correspondence_error(sphere, [0], [0], normalization="area")
    with pytest.raises(ValueError, match="outside"):
        correspondence_error(sphere, [sphere.n_vertices], [0])
    with pytest.raises(ValueError, match="equal length"):
        correspondence_error(sphere, [0, 1], [0])


@pytest.mark.data
def test_tosca_ground_truth_and_symmetric_flip(tosca5k):
    from wpot.datasets import tosca_ground_truth
    from wpot.io import load_mesh

    cat1 = load_mesh(tosca5k / "cat1.off")
    src, dst = tosca_ground_truth(tosca5k, "cat0", "cat1")
    _, sym = tosca_ground_truth(tosca5k, "cat0", "cat1", symmetric=True)
    k = slice(0, 5000, 25)  # 200 template points keep the test fast
    g = GeodesicDistances(cat1)
    exact = correspondence_error(g, dst[k], dst[k], symmetric_truth=sym[k])
    assert exact.auc == 1.0
    flipped = correspondence_error(g, sym[k], dst[k], symmetric_truth=sym[k])
    assert flipped.flip_aware_auc == 1.0 and flipped.auc < 0.9
    f = symmetric_flip(g, sym[k], dst[k], sym[k])
    assert f.map_flipped and f.fraction == 1.0 and f.n_lateral > 100  # most of a cat is off the symmetry plane
    assert symmetric_flip(g, dst[k], dst[k], sym[k]).fraction == 0.0


def test_symmetric_flip_on_a_mirrored_sphere(sphere):
    m = sphere
    v = m.vertices
    mirror = np.argmin(np.linalg.norm(v[:, None] - (v * [-1, 1, 1])[None], axis=-1), axis=1)
    truth = np.arange(0, m.n_vertices, 2)
    sym = mirror[truth]
    g = GeodesicDistances(m)
    # lateral points: the great circle from a point to its mirror, 2 r asin(|x| / r), against 0.05 sqrt(4 pi r^2)
    sep = great_circle(m, truth, sym) / np.sqrt(m.area)
    f = symmetric_flip(g, sym, truth, sym)
    clear = np.abs(sep - 0.05) > 0.01  # away from the threshold, where the heat method's error could tip it
    np.testing.assert_array_equal(f.lateral[clear], (sep >= 0.05)[clear])
    assert 0 < f.n_lateral < truth.size
    assert f.fraction == 1.0 and f.map_flipped and f.n_flipped == f.n_lateral
    exact = symmetric_flip(g, truth, truth, sym)
    assert exact.fraction == 0.0 and not exact.map_flipped and not exact.flipped.any()
    # mirror only the points with x > 0: the fraction is the share of lateral points on that side
    half = np.where(v[truth, 0] > 0, sym, truth)
    h = symmetric_flip(g, half, truth, sym)
    np.testing.assert_array_equal(h.flipped, h.lateral & (v[truth, 0] > 0))
    assert h.fraction == pytest.approx(np.mean(v[truth, 0][h.lateral] > 0))
    assert 0.3 < h.fraction < 0.7
    # invariant to scale (the lateral threshold is relative to sqrt(area)) and to relabelling the vertices
    big = symmetric_flip(m.transformed(scale=4.0), half, truth, sym)
    np.testing.assert_array_equal(big.flipped, h.flipped)
    perm = np.random.default_rng(1).permutation(m.n_vertices)
    inv = np.argsort(perm)
    r = symmetric_flip(m.relabelled(perm), inv[half], inv[truth], inv[sym])
    assert r.fraction == pytest.approx(h.fraction, abs=0.01)


def test_symmetric_flip_rejects_bad_input(sphere):
    with pytest.raises(ValueError, match="equal length"):
        symmetric_flip(sphere, [0, 1], [0, 1], [0])
    with pytest.raises(ValueError, match="ratio"):
        symmetric_flip(sphere, [0], [0], [1], ratio=0.0)
    with pytest.raises(ValueError, match="min_separation"):
        symmetric_flip(sphere, [0], [0], [1], min_separation=-1.0)
    with pytest.warns(UserWarning, match="lateral"):
        assert np.isnan(symmetric_flip(sphere, [0, 1], [0, 1], [0, 1]).fraction)


# ----------------------------------------------------------------------------- random draws of k per class
def _separated(sizes, within=1.0, between=10.0):
    """Block distances: ``within`` inside a class, ``between`` across, classes ``c0, c1, ...``."""
    lab = np.repeat([f"c{k}" for k in range(len(sizes))], sizes)
    d = np.where(lab[:, None] == lab[None, :], within, between)
    np.fill_diagonal(d, 0.0)
    return d, lab


def test_classification_draws_perfectly_separated_is_100_percent():
    d, lab = _separated([5, 6, 9])
    r = classification_draws(d, lab, per_class=3, n_draws=20, n_trials=50, seed=1)
    assert r.n_draws == 20 and r.draws.shape == (20, 9)
    np.testing.assert_array_equal(r.one_shot, 1.0)
    np.testing.assert_array_equal(r.leave_one_out, 1.0)
    # every draw: 3 distinct shapes of each class, and the draws differ
    for idx in r.draws:
        assert len(set(idx.tolist())) == 9
        assert [int((lab[idx] == c).sum()) for c in ("c0", "c1", "c2")] == [3, 3, 3]
    assert len({tuple(x) for x in r.draws.tolist()}) > 1
    # a class of exactly per_class shapes (c0: shapes 0-4) is whole in every draw
    whole = classification_draws(d, lab, per_class=5, n_draws=4, n_trials=5).draws
    assert all(set(range(5)) <= set(x) for x in whole.tolist())


def test_classification_draws_one_class_always_confused():
    # queries of class c2 are nearer (0.5) to every c0 shape than to their own class (1): c2 is always wrong,
    # c0 and c1 always right (rows are queries; c0 queries see c2 at 10). Both protocols: 2/3 in every draw.
    d, lab = _separated([4, 4, 4])
    d[np.ix_(lab == "c2", lab == "c0")] = 0.5
    r = classification_draws(d, lab, per_class=3, n_draws=10, n_trials=40, seed=0)
    np.testing.assert_allclose(r.one_shot, 2 / 3)
    np.testing.assert_allclose(r.leave_one_out, 2 / 3)
    assert r.one_shot_std == pytest.approx(0.0, abs=1e-12) and r.leave_one_out_mean == pytest.approx(2 / 3)


def test_classification_draws_score_depends_on_the_drawn_shapes():
    # one bad shape (index 0, class c0) whose nearest shape is in c1; classes of 3, draws of 2 per class.
    # Leave-one-out of a draw = 1 - 1/6 when shape 0 is drawn, 1 otherwise; it is drawn with probability 2/3.
    d, lab = _separated([3, 3, 3])
    d[0, lab == "c1"] = 0.5
    r = classification_draws(d, lab, per_class=2, n_draws=600, n_trials=10, seed=3)
    has_bad = (r.draws == 0).any(axis=1)
    np.testing.assert_allclose(r.leave_one_out, np.where(has_bad, 5 / 6, 1.0))
    assert has_bad.mean() == pytest.approx(2 / 3, abs=0.06)
    assert r.leave_one_out_mean == pytest.approx(1 - (2 / 3) / 6, abs=0.01)
    assert r.leave_one_out_std > 0


def test_classification_draws_is_reproducible_and_checks_its_input():
    d, lab = _separated([4, 5])
    d[0, lab == "c1"] = 0.5
    a = classification_draws(d, lab, per_class=3, n_draws=5, n_trials=20, seed=7)
    b = classification_draws(d, lab, per_class=3, n_draws=5, n_trials=20, seed=7)
    np.testing.assert_array_equal(a.draws, b.draws)
    np.testing.assert_array_equal(a.one_shot, b.one_shot)
    with pytest.raises(ValueError, match="fewer than per_class=5"):
        classification_draws(d, lab, per_class=5)
    with pytest.raises(ValueError, match="per_class must be >= 2"):
        classification_draws(d, lab, per_class=1)
    with pytest.raises(ValueError, match="n_draws"):
        classification_draws(d, lab, per_class=2, n_draws=0)
