"""Class retrieval of a part from a labelled library (`wpot.maps.retrieval.rank_classes`, `Comparer.retrieve`)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from wpot.maps.retrieval import ClassRanking, RetrievalOptions, rank_classes


def _costs(seed: int = 0, n: int = 40, m: int = 7) -> tuple[np.ndarray, list[str]]:
    rng = np.random.default_rng(seed)
    return rng.uniform(1.0, 3.0, size=(n, m)), ["a", "b", "a", "c", "b", "a", "c"][:m]


def test_nearest_member_alone_is_the_nearest_whole():
    """k_nearest=1 without standardising: a class's score is its nearest member's mean cost."""
    c, labels = _costs()
    r = rank_classes(c, labels, options=RetrievalOptions(k_nearest=1, standardize=False))
    means = c.mean(axis=0)
    expect = {k: min(means[j] for j in range(len(labels)) if labels[j] == k) for k in set(labels)}
    assert list(r.classes) == sorted(expect, key=expect.get)
    np.testing.assert_allclose(r.scores, [expect[k] for k in r.classes])
    np.testing.assert_allclose(r.whole_costs, means)
    assert r.label == r.classes[0] and labels[r.members[0][0]] == r.label


def test_standardised_ranking_ignores_each_vertex_offset_and_spread():
    """z-scores per vertex: adding a constant to a vertex's costs or scaling them does not change the ranking."""
    c, labels = _costs(1)
    rng = np.random.default_rng(2)
    c2 = c * rng.uniform(0.1, 10.0, size=(len(c), 1)) + rng.uniform(-5.0, 5.0, size=(len(c), 1))
    r1, r2 = rank_classes(c, labels), rank_classes(c2, labels)
    assert r1.classes == r2.classes and r1.members == r2.members
    np.testing.assert_allclose(r1.scores, r2.scores, atol=1e-12)


def test_standardised_every_vertex_weighs_the_same():
    """Whole a explains nine vertices of ten a little better than b; the tenth (a vertex the pose moved) much
    worse. The raw mean follows the tenth vertex (b: 1.09 against a: 1.4); the z-scores follow the nine."""
    c = np.column_stack([np.r_[np.full(9, 1.0), 5.0], np.r_[np.full(9, 1.1), 1.0]])
    raw = rank_classes(c, ["a", "b"], options=RetrievalOptions(standardize=False))
    z = rank_classes(c, ["a", "b"])
    assert raw.classes == ("b", "a") and np.allclose(raw.scores, [1.09, 1.4])
    assert z.classes == ("a", "b") and np.allclose(z.scores, [-0.8, 0.8])


def test_a_class_is_the_union_of_its_nearest_members():
    """Class a's two members each explain half of the part; class b's two members each explain all of it
    fairly. By its nearest member a loses (mean 1.5 against 1.2); as the union of two it wins (1.0)."""
    n = 10
    c = np.empty((n, 4))
    c[:, 0] = np.r_[np.full(5, 1.0), np.full(5, 2.0)]  # a, first half
    c[:, 1] = np.r_[np.full(5, 2.0), np.full(5, 1.0)]  # a, second half
    c[:, 2:] = 1.2  # b
    labels = ["a", "a", "b", "b"]
    one = rank_classes(c, labels, options=RetrievalOptions(k_nearest=1, standardize=False))
    two = rank_classes(c, labels, options=RetrievalOptions(k_nearest=2, standardize=False))
    assert one.classes == ("b", "a") and np.allclose(one.scores, [1.2, 1.5])
    assert two.classes == ("a", "b") and np.allclose(two.scores, [1.0, 1.2])
    assert sorted(two.members[0]) == [0, 1] and two.rank("b") == 2
    assert two.margin == pytest.approx(0.2) and one.margin == pytest.approx(0.3)
    with pytest.raises(ValueError, match="labels name one class"):  # one class: no answer to give, not a sure one
        rank_classes(c[:, :2], labels[:2])
    # with b down to one member, every class is scored by its nearest member alone
    three = rank_classes(c[:, :3], labels[:3], options=RetrievalOptions(k_nearest=2, standardize=False))
    assert three.classes == ("b", "a") and np.allclose(three.scores, [1.2, 1.5])
    with pytest.raises(ValueError, match="'z' is not in the library"):
        two.rank("z")


def test_no_class_gains_from_its_size_alone():
    """Costs that no whole explains better than another (independent draws): the least of three costs is lower
    than the least of two, so were a class of three members scored by all three and a class of two by both,
    the larger would come first for almost every part (5 % of 200 parts went to the smaller). Scored by two
    members each, the smaller comes first for about a third: the larger still picks its two nearest of three,
    as the nearest whole's class favours a larger class."""
    rng = np.random.default_rng(3)
    labels = ["big", "big", "big", "small", "small"]
    firsts = [rank_classes(rng.normal(size=(50, 5)), labels).label for _ in range(200)]
    assert 0.25 < firsts.count("small") / len(firsts) < 0.6
    r = rank_classes(rng.normal(size=(50, 5)), labels, options=RetrievalOptions(k_nearest=3))
    assert all(len(m) == 2 for m in r.members)


@pytest.mark.parametrize("kwargs, match", [
    (dict(costs=np.ones((3, 2)), labels=["a"]), "one class per whole"),
    (dict(costs=np.ones(3), labels=["a"]), "n_vertices, n_wholes"),
    (dict(costs=np.full((3, 2), np.nan), labels=["a", "b"]), "finite"),
    (dict(costs=np.ones((3, 2)), labels=["a", "a"]), "at least two classes"),
    (dict(costs=np.ones((3, 2)), labels=["a", "b"], options={"k_nearest": 2}), "RetrievalOptions"),
])
def test_bad_input_is_named(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        rank_classes(**kwargs)


def test_a_row_of_weight_w_counts_as_w_copies():
    """``weights``: integer weights give the ranking of the costs with each row repeated that many times; a
    common factor changes nothing; zero weight drops a row."""
    c, labels = _costs(5)
    w = np.random.default_rng(6).integers(0, 4, size=len(c))
    w[0] = 2
    r = rank_classes(c, labels, weights=w)
    ref = rank_classes(np.repeat(c, w, axis=0), labels)
    assert r.classes == ref.classes and r.members == ref.members
    np.testing.assert_allclose(r.scores, ref.scores, rtol=1e-12)
    np.testing.assert_allclose(r.whole_costs, ref.whole_costs, rtol=1e-12)
    np.testing.assert_allclose(rank_classes(c, labels, weights=3.5 * w).scores, r.scores, rtol=1e-12)
    for bad in (np.ones(len(c) - 1), np.zeros(len(c)), -np.ones(len(c)), np.full(len(c), np.nan)):
        with pytest.raises(ValueError, match="weights"):
            rank_classes(c, labels, weights=bad)


def test_a_large_part_stands_for_its_farthest_point_samples():
    """`retrieval_sample`: None up to ``max_points`` vertices; above, ``max_points`` distinct vertices whose
    cells (their counts) cover the part once; the same sample on every call."""
    import wpot
    from wpot.maps.retrieval import retrieval_sample

    part = wpot.example_mesh(400, seed=7)
    assert retrieval_sample(part, RetrievalOptions(max_points=None)) is None
    assert retrieval_sample(part, RetrievalOptions(max_points=part.n_vertices)) is None
    s = retrieval_sample(part, RetrievalOptions(max_points=50))
    assert len(np.unique(s.indices)) == 50 and s.counts.sum() == part.n_vertices and s.counts.min() >= 1
    np.testing.assert_array_equal(s.indices, retrieval_sample(part, RetrievalOptions(max_points=50)).indices)
    with pytest.raises(TypeError, match="RetrievalOptions"):
        retrieval_sample(part, {"max_points": 50})


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="max_points"):
        RetrievalOptions(max_points=2)
    with pytest.raises(ValueError, match="edge"):
        RetrievalOptions(edge="mine")
    with pytest.raises(ValueError, match="k_nearest"):
        RetrievalOptions(k_nearest=0)
    with pytest.raises((ValueError, TypeError), match="standardize"):
        RetrievalOptions(standardize="yes")


def test_comparer_retrieve_agrees_with_the_cost_matrix():
    """`Comparer.retrieve` scores from the same costs as the signatures' cost matrix, and its whole costs are
    `nearest_signature_distance`."""
    import wpot
    from wpot.cost import cost_matrix

    from wpot.comparison import at_common_edge
    from wpot.signatures._frames import common_edge

    base = wpot.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    wholes = [wpot.example_mesh(300, seed=s) for s in (1, 2, 3)]
    part = wpot.cut(wpot.example_mesh(300, seed=4), np.arange(150))[0]
    labels = ["x", "y", "x"]
    r = base.retrieve(part, wholes, labels)
    assert isinstance(r, ClassRanking)
    # LD-SIFT at one edge length, the library's, for the part and every whole (RetrievalOptions.edge="library")
    c = at_common_edge(base, wholes)
    assert c.config.signature_options.edge == common_edge(wholes) and base.config.signature_options.edge is None
    costs = np.column_stack([cost_matrix(c.signatures(part), c.signatures(w), metric="l2").min(axis=1)
                             for w in wholes])
    ref = rank_classes(costs, labels)
    assert r.classes == ref.classes
    np.testing.assert_allclose(r.scores, ref.scores, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r.whole_costs, [c.nearest_signature_distance(part, w) for w in wholes], rtol=1e-9)
    # LD-SIFT at its defaults is what the probability was calibrated on; with the thickness column it is not:
    # NaN, not a number on another scale
    assert ref.calibrated and r.calibrated and r.probability == pytest.approx(ref.probability)
    with warnings.catch_warnings():  # the half-mesh part shows little of its thickness, and says so
        warnings.simplefilter("ignore", UserWarning)
        t = base.with_options(ldsift_thickness=2.0).retrieve(part, wholes, labels)
    assert not t.calibrated and np.isnan(t.probability) and not np.allclose(t.whole_costs, r.whole_costs)
    with pytest.raises(ValueError, match="wholes and labels must be of one length"):
        c.retrieve(part, wholes, labels[:2])
    # each mesh at its own edge lengths (the paper's): the costs of the comparer as it was given
    own = base.retrieve(part, wholes, labels, options=RetrievalOptions(edge="own"))
    mine = np.column_stack([cost_matrix(base.signatures(part), base.signatures(w), metric="l2").min(axis=1)
                            for w in wholes])
    np.testing.assert_allclose(own.scores, rank_classes(mine, labels).scores, rtol=1e-5, atol=1e-6)
    assert not np.allclose(own.whole_costs, r.whole_costs)
    # a part of more than max_points vertices: the same ranking as rank_classes on its sample's rows, weighted
    from wpot.maps.retrieval import retrieval_sample

    few = RetrievalOptions(max_points=40)
    s = retrieval_sample(part, few)
    small = c.retrieve(part, wholes, labels, options=few)
    ref = rank_classes(costs[s.indices], labels, weights=s.counts, options=few)
    assert small.classes == ref.classes
    np.testing.assert_allclose(small.scores, ref.scores, rtol=1e-5, atol=1e-6)


def test_a_part_larger_than_every_whole_is_named():
    import wpot
    from wpot.maps.retrieval import RetrievalWarning

    c = wpot.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    wholes = [wpot.example_mesh(300, seed=s) for s in (1, 2)]
    big = wpot.Mesh(2.0 * wpot.example_mesh(300, seed=4).vertices, wpot.example_mesh(300, seed=4).faces, name="big.off")
    with pytest.warns(RetrievalWarning, match=r"big\.off: the part's area is \d\.\d+ times that of the library's "
                                              r"largest whole.*different scales"):
        c.retrieve(big, wholes, ["x", "y"])
    part = wpot.cut(wpot.example_mesh(300, seed=4), np.arange(150))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrievalWarning)
        c.retrieve(part, wholes, ["x", "y"])


def test_a_class_whose_wholes_differ_in_size_is_named():
    """A library whose members of one class were scaled apart (a data set normalised shape by shape): retrieve
    reads size, and says which class and how much, naming the option that describes each mesh at its own."""
    import wpot
    from wpot.maps.retrieval import SIZE_SPREAD, RetrievalWarning, size_spread

    c = wpot.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    wholes = [wpot.example_mesh(300, seed=s) for s in (1, 2, 3)]
    part = wpot.cut(wpot.example_mesh(300, seed=4), np.arange(150))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrievalWarning)
        c.retrieve(part, wholes, ["x", "y", "x"])
    shrunk = [wholes[0], wholes[1], wholes[2].transformed(scale=0.8)]
    name, ratio = size_spread(shrunk, ["x", "y", "x"])
    assert name == "x" and ratio == pytest.approx(np.sqrt(wholes[0].area / shrunk[2].area)) and ratio > SIZE_SPREAD
    with pytest.warns(RetrievalWarning, match=r"class 'x' differ in size by up to 1\.2\d times.*edge='own'"):
        c.retrieve(part, shrunk, ["x", "y", "x"])
    assert size_spread(wholes[:2], ["x", "y"]) is None  # one whole a class: nothing to compare


def test_probability_grows_with_the_margin_and_needs_the_calibrated_options():
    """`ClassRanking.probability` is the calibrated logistic of the margin: in (0, 1), increasing with the margin,
    1 for the infinite margin of a ranking without a second class; NaN for options it was not calibrated for."""
    from wpot.maps.retrieval import CALIBRATION, probability_of

    assert CALIBRATION[1] > 0  # a larger margin is never less sure
    m = np.linspace(0.0, 1.0, 11)
    p = np.array([probability_of(x) for x in m])
    assert np.all((p > 0) & (p < 1)) and np.all(np.diff(p) > 0) and probability_of(float("inf")) == 1.0
    c, labels = _costs(3)
    r = rank_classes(c, labels)
    assert r.calibrated and r.probability == pytest.approx(probability_of(r.margin))
    other = rank_classes(c, labels, options=RetrievalOptions(k_nearest=1))
    assert not other.calibrated and np.isnan(other.probability)


def _penalised_log_likelihood(a, x, y, prior, weight):
    z = a[0] + a[1] * x
    return float(np.sum(y * z - np.logaddexp(0.0, z)) - 0.5 * np.sum(np.asarray(weight) * (a - prior) ** 2))


@pytest.mark.parametrize("prior,weight", [((0.0, 0.0), (0.0, 1e-3)), ((-0.9, 25.0), (1.0, 0.04))])
def test_fit_logistic_agrees_with_a_general_optimiser(prior, weight):
    """Newton's fit is the maximum of the penalised log-likelihood that scipy's BFGS finds from scratch, and on
    many outcomes drawn from a known logistic it lands near that logistic."""
    from scipy.optimize import minimize

    from wpot.maps.retrieval import fit_logistic

    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 0.4, 2000)
    y = (rng.uniform(size=x.size) < 1.0 / (1.0 + np.exp(-(-1.0 + 15.0 * x)))).astype(float)
    a = np.array(fit_logistic(x, y, prior=prior, weight=weight))
    ref = minimize(lambda c: -_penalised_log_likelihood(c, x, y, np.array(prior), weight), np.zeros(2),
                   method="BFGS", options={"gtol": 1e-9}).x
    np.testing.assert_allclose(a, ref, rtol=1e-4, atol=1e-4)
    assert abs(a[0] + 1.0) < 0.3 and abs(a[1] - 15.0) < 2.5


def test_fit_logistic_when_every_outcome_is_the_same():
    """All right: no maximum without a prior on the intercept (NaN, as said), a finite one with it, surer than
    the prior at the data; bad input is named."""
    from wpot.maps.retrieval import CALIBRATION, fit_logistic, probability_of

    x = np.linspace(0.0, 0.3, 50)
    assert np.isnan(fit_logistic(x, np.ones_like(x))).all()
    a = fit_logistic(x, np.ones_like(x), prior=CALIBRATION, weight=(1.0, float(np.mean(x ** 2))))
    assert np.isfinite(a).all()
    assert all(probability_of(v, a) > probability_of(v) for v in x)
    with pytest.raises(ValueError, match="x and y must be finite and of one nonzero length"):
        fit_logistic(x, np.ones(3))


def _library():
    import wpot

    wholes = [wpot.example_mesh(300, seed=s) for s in (1, 2, 3, 4, 5)]
    return wholes, ["x", "y", "x", "y", "z"]


def test_calibration_parts_are_drawn_class_by_class_and_cut_as_said():
    """Parts of classes of two or more wholes only, classes in turn, connected, no larger than PART_FRACTIONS
    allows; the same for a seed; a library without a class of two wholes is refused."""
    from wpot.maps.retrieval import PART_FRACTIONS, calibration_parts

    wholes, labels = _library()
    parts = calibration_parts(wholes, labels, 8, seed=3)
    assert len(parts) == 8
    classes = [labels[j] for j, _ in parts]
    assert "z" not in classes and all(a != b for a, b in zip(classes, classes[1:]))
    for j, p in parts:
        assert p.n_components == 1 and 20 <= p.n_vertices < wholes[j].n_vertices
        assert p.area <= PART_FRACTIONS[1] * wholes[j].area + 1e-9
    again = calibration_parts(wholes, labels, 8, seed=3)
    assert all(j == k and np.array_equal(p.vertices, q.vertices) for (j, p), (k, q) in zip(parts, again))
    with pytest.raises(ValueError, match="no class has two wholes"):
        calibration_parts(wholes[:3], ["x", "y", "z"], 4)
    import trimesh

    import wpot

    ico = trimesh.creation.icosphere(subdivisions=0)  # 12 vertices: no part reaches MIN_PART_VERTICES
    coarse = [wpot.Mesh(ico.vertices * s, ico.faces) for s in (1.0, 1.1)]
    with pytest.raises(ValueError, match="too coarse to cut parts from: 0 of 3 parts"):
        calibration_parts(coarse, ["x", "x"], 3)


def test_retrieval_calibration_round_trips_and_checks_its_fields():
    from wpot.maps.retrieval import RetrievalCalibration

    cal = RetrievalCalibration(-0.5, 12.0, 40, 31, RetrievalOptions(k_nearest=2), "ldsift ...")
    assert RetrievalCalibration.from_json(cal.to_json()) == cal
    assert cal.probability(0.1) == pytest.approx(1.0 / (1.0 + np.exp(-(-0.5 + 1.2))))
    with pytest.raises(ValueError, match="not a RetrievalCalibration's JSON"):
        RetrievalCalibration.from_json('{"intercept": 1}')
    with pytest.raises(ValueError, match="n_right .* cannot exceed n_parts"):
        RetrievalCalibration(0.0, 1.0, 3, 4, RetrievalOptions(), "s")
    with pytest.raises(ValueError, match="slope must be a finite number"):
        RetrievalCalibration(0.0, float("nan"), 3, 2, RetrievalOptions(), "s")


def test_comparer_calibrates_retrieval_on_its_library():
    """`Comparer.calibrate_retrieval`: its counts are those of the parts of `calibration_parts` looked up among
    the other wholes, its coefficients `calibration_of` their margins; `retrieve` with it gives that logistic's
    probability, and refuses a calibration made with other options or another signature."""
    import wpot
    from wpot.maps.retrieval import calibration_of, calibration_parts

    c = wpot.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    wholes, labels = _library()
    cal = c.calibrate_retrieval(wholes, labels, n_parts=4, seed=1)
    margins, right = [], []
    for j, part in calibration_parts(wholes, labels, 4, seed=1):
        keep = [i for i in range(len(wholes)) if i != j]
        # the lookups of the calibration see the whole library's edge length, not the four wholes'
        r = c.with_options(ldsift_edge=wpot.signatures._frames.common_edge(wholes)).retrieve(
            part, [wholes[i] for i in keep], [labels[i] for i in keep])
        margins.append(r.margin)
        right.append(r.label == labels[j])
    assert (cal.n_parts, cal.n_right) == (4, sum(right))
    ref = calibration_of(margins, right, None, cal.signature)
    assert cal.coefficients == pytest.approx(ref.coefficients)
    part = wpot.cut(wpot.example_mesh(300, seed=6), np.arange(150))[0]
    r = c.retrieve(part, wholes, labels, calibration=cal)
    assert r.calibrated and r.probability == pytest.approx(cal.probability(r.margin))
    with pytest.raises(ValueError, match=r"other settings.*options RetrievalOptions\(k_nearest=1"):
        c.retrieve(part, wholes, labels, calibration=cal, options=RetrievalOptions(k_nearest=1))
    with pytest.raises(ValueError, match=r"other settings.*signature ldsift .*thickness=2\.0"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            c.with_options(ldsift_thickness=2.0).retrieve(part, wholes, labels, calibration=cal)
    with pytest.raises(TypeError, match="calibration must be a RetrievalCalibration"):
        c.retrieve(part, wholes, labels, calibration=(0.0, 1.0))
    with pytest.raises(TypeError, match="options must be a RetrievalOptions, got str"):
        c.calibrate_retrieval(wholes, labels, n_parts=2, options="library")
    # the library it was fitted on, in any order: silent; another library: said, the probability still given
    from wpot.maps.retrieval import RetrievalWarning

    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrievalWarning)
        c.retrieve(part, wholes[::-1], labels[::-1], calibration=cal)
    with pytest.warns(RetrievalWarning, match="fitted on another library than these 4 wholes"):
        other = c.retrieve(part, wholes[:4], labels[:4], calibration=cal)
    assert other.probability == pytest.approx(cal.probability(other.margin))


def test_a_stopped_calibration_resumes_from_its_record(tmp_path):
    """With ``record``, every lookup is saved as it is made: a calibration stopped midway (here: its record cut
    after two lookups, the last line half written) resumes with the parts left, and gives what an unbroken one
    gives; a record of other settings is refused, naming what differs."""
    import json

    import wpot

    c = wpot.Comparer(signature="ldsift", device="cpu", cache_dir=False)
    wholes, labels = _library()
    rec = tmp_path / "cal.jsonl"
    whole_run = c.calibrate_retrieval(wholes, labels, n_parts=4, seed=2, record=rec)
    lines = rec.read_text().splitlines()
    assert len(lines) == 5 and json.loads(lines[0])["n_parts"] == 4
    assert sorted(json.loads(x)["part"] for x in lines[1:]) == [0, 1, 2, 3]
    assert c.calibrate_retrieval(wholes, labels, n_parts=4, seed=2, record=rec) == whole_run  # all read back
    rec.write_text("\n".join(lines[:3]) + "\n" + lines[3][:9])  # stopped while writing the third lookup
    resumed = c.calibrate_retrieval(wholes, labels, n_parts=4, seed=2, record=rec)
    assert resumed == whole_run
    after = rec.read_text().splitlines()  # the two lookups kept, not made again; the two left appended
    assert after[:3] == lines[:3] and len(after) == 5
    assert sorted(json.loads(x)["part"] for x in after[1:]) == [0, 1, 2, 3]
    with pytest.raises(ValueError, match=r"holds the lookups of another calibration \(its seed differ\)"):
        c.calibrate_retrieval(wholes, labels, n_parts=4, seed=3, record=rec)
    with pytest.raises(ValueError, match=r"its library differ"):
        c.calibrate_retrieval(wholes[:4] + [wholes[4].transformed(scale=1.01)], labels, n_parts=4, seed=2,
                              record=rec)


def test_a_library_calibration_serves_other_signatures():
    """The shipped probability holds for LD-SIFT only (NaN for WKS); a calibration fitted with the WKS comparer
    gives its rankings a probability, its own logistic of the margin."""
    import wpot

    wholes, labels = _library()
    c = wpot.Comparer(signature="wks", device="cpu", cache_dir=False, n_eigen=30, n_energies=40)
    c.fit(wholes)
    part = wpot.cut(wpot.example_mesh(300, seed=6), np.arange(150))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the smallest parts have fewer vertices than n_eigen
        cal = c.calibrate_retrieval(wholes, labels, n_parts=4)
        plain, mine = c.retrieve(part, wholes, labels), c.retrieve(part, wholes, labels, calibration=cal)
    assert cal.signature.startswith("wks ") and np.isnan(plain.probability)
    assert mine.calibrated and mine.probability == pytest.approx(cal.probability(mine.margin))
    assert mine.classes == plain.classes
