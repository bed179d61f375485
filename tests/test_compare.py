"""wpot.comparison: registration (closed form), farthest-point sampling, memory guard, and end-to-end comparisons."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from wpot.comparison import ProblemTooLargeError, choose_cost_mode
from wpot.runs.history import debias_history, history_at
from wpot.maps.registration import Registration, fit_similarity
from wpot.sampling import farthest_point_sampling
from wpot.mesh import Mesh


def torus(n_major: int = 24, n_minor: int = 12, R: float = 2.0, r: float = 0.7, noise: float = 0.0, seed: int = 0) -> Mesh:
    """A closed torus grid mesh (n_major·n_minor vertices), optionally with jittered vertices."""
    u, v = np.meshgrid(np.arange(n_major) * 2 * np.pi / n_major, np.arange(n_minor) * 2 * np.pi / n_minor, indexing="ij")
    x = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], -1).reshape(-1, 3)
    if noise:
        x = x + np.random.default_rng(seed).normal(scale=noise, size=x.shape)
    idx = np.arange(n_major * n_minor).reshape(n_major, n_minor)
    a = idx
    b = np.roll(idx, -1, 0)
    c = np.roll(idx, -1, 1)
    d = np.roll(np.roll(idx, -1, 0), -1, 1)
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return Mesh(x, faces)


# ------------------------------------------------------------------------------------ registration
def _random_similarity(seed: int):
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=seed).as_matrix()
    return float(rng.uniform(0.3, 3.0)), rot, rng.normal(size=3) * 5


@pytest.mark.parametrize("seed", range(5))
def test_fit_similarity_recovers_a_known_transform(seed):
    scale, rot, t = _random_similarity(seed)
    p = np.random.default_rng(100 + seed).normal(size=(40, 3))
    reg = fit_similarity(p, scale * p @ rot.T + t)
    assert reg.scale == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(reg.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(reg.translation, t, atol=1e-11)
    assert reg.rms < 1e-11
    assert np.linalg.det(reg.rotation) == pytest.approx(1.0)


def test_fit_similarity_weights_ignore_zero_weight_outliers():
    scale, rot, t = _random_similarity(7)
    rng = np.random.default_rng(1)
    p = rng.normal(size=(30, 3))
    q = scale * p @ rot.T + t
    q[:5] += rng.normal(scale=10.0, size=(5, 3))  # five gross outliers
    w = np.r_[np.zeros(5), np.ones(25)]
    reg = fit_similarity(p, q, w)
    np.testing.assert_allclose(reg.rotation, rot, atol=1e-10)
    assert reg.scale == pytest.approx(scale, rel=1e-10)
    unweighted = fit_similarity(p, q)
    assert unweighted.rms > 1.0  # the outliers do spoil an unweighted fit


def test_fit_similarity_with_noise_matches_an_independent_optimizer():
    """Against a generic optimizer of the same weighted objective (scale, rotation vector, translation)."""
    from scipy.optimize import minimize

    scale, rot, t = _random_similarity(3)
    rng = np.random.default_rng(5)
    p = rng.normal(size=(50, 3))
    q = scale * p @ rot.T + t + rng.normal(scale=0.05, size=p.shape)
    w = rng.uniform(0.1, 1.0, size=50)
    reg = fit_similarity(p, q, w)

    def f(z):
        r = Rotation.from_rotvec(z[1:4]).as_matrix()
        res = z[0] * p @ r.T + z[4:] - q
        return float(w @ (res**2).sum(1))

    z0 = np.r_[reg.scale, Rotation.from_matrix(reg.rotation).as_rotvec(), reg.translation]
    best = minimize(f, z0 + 0.05, method="BFGS", options={"gtol": 1e-12})
    assert f(z0) <= best.fun * (1 + 1e-8)
    assert reg.rms == pytest.approx(np.sqrt(f(z0) / w.sum()), rel=1e-10)


def test_fit_similarity_never_returns_a_reflection():
    p = np.random.default_rng(2).normal(size=(20, 3))
    mirrored = p * np.array([1.0, 1.0, -1.0])
    reg = fit_similarity(p, mirrored)
    assert np.linalg.det(reg.rotation) == pytest.approx(1.0)
    assert reg.rms > 0.1


def test_registration_apply_inverse_and_matrix_round_trip():
    scale, rot, t = _random_similarity(11)
    reg = Registration(scale, rot, t, 0.0, 3)
    p = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(reg.inverse().apply(reg.apply(p)), p, atol=1e-12)
    h = np.c_[p, np.ones(len(p))] @ reg.matrix.T
    np.testing.assert_allclose(h[:, :3], reg.apply(p), atol=1e-12)
    m = torus(8, 6)
    np.testing.assert_allclose(reg.apply(m).vertices, reg.apply(m.vertices), atol=1e-12)


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.zeros((2, 3)), np.zeros((2, 3))), "at least 3"),
        ((np.zeros((4, 3)), np.zeros((5, 3))), "shape"),
        ((np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)],) * 2, "source points are .*collinear"),
        ((np.random.default_rng(0).normal(size=(5, 3)), np.c_[np.arange(5.0), 2 * np.arange(5.0), np.ones(5)]),
         "target points are .*collinear"),
        ((np.random.default_rng(0).normal(size=(5, 3)), np.tile([0.3, -1.7, 2.9], (5, 1))), "target points coincide"),
        ((np.tile([1e3, 0.1, 0.0], (5, 1)), np.random.default_rng(0).normal(size=(5, 3))), "source points coincide"),
    ],
)
def test_fit_similarity_rejects_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        fit_similarity(*args)


def test_fit_similarity_holds_at_any_size_and_place():
    """The degeneracy checks are relative: a shape a millionth the size, far from the origin, is fitted exactly,
    while the same shape collapsed onto one of its points (a map's images at one vertex) is refused."""
    _, rot, _ = _random_similarity(4)
    rng = np.random.default_rng(4)
    p = rng.normal(size=(8, 3))
    q = 1e-6 * p @ rot.T + np.array([50.0, -20.0, 7.0])
    reg = fit_similarity(p, q)
    assert reg.scale == pytest.approx(1e-6, rel=1e-6)
    np.testing.assert_allclose(reg.rotation, rot, atol=1e-6)
    with pytest.raises(ValueError, match="target points coincide"):
        fit_similarity(p, q[[3] * len(q)] * (1 + 1e-16 * rng.normal(size=q.shape)))


def test_fit_similarity_rejects_negative_weights():
    p = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises(ValueError, match="non-negative"):
        fit_similarity(p, p, [1, 1, -1, 1, 1])


# -------------------------------------------------------------------------------------------- FPS
@pytest.mark.parametrize("metric", ["geodesic", "euclidean"])
def test_fps_spreads_samples_and_extension_map_is_nearest(metric):
    mesh = torus(30, 14, noise=0.02, seed=3)
    k = 40
    s = farthest_point_sampling(mesh, k, metric=metric)
    assert s.indices.shape == (k,) and len(np.unique(s.indices)) == k
    assert s.nearest.shape == (mesh.n_vertices,)
    np.testing.assert_array_equal(s.nearest[s.indices], np.arange(k))
    if metric == "geodesic":
        d = dijkstra(mesh.edge_graph, directed=False, indices=s.indices)  # (k, N)
    else:
        d = cdist(mesh.vertices[s.indices], mesh.vertices)
    # the map sends every vertex to a nearest sample
    np.testing.assert_allclose(d[s.nearest, np.arange(mesh.n_vertices)], d.min(0), atol=1e-12)
    # covering radius, and the farthest-point property: samples are pairwise at least that far apart
    radius = d.min(0).max()
    assert s.radius == pytest.approx(radius, rel=1e-12)
    pair = d[:, s.indices] + np.diag(np.full(k, np.inf))
    assert pair.min() >= radius - 1e-12
    # and the sample is far better spread than a random one of the same size
    rand = np.random.default_rng(0).choice(mesh.n_vertices, k, replace=False)
    d_rand = dijkstra(mesh.edge_graph, directed=False, indices=rand) if metric == "geodesic" else cdist(mesh.vertices[rand], mesh.vertices)
    assert d_rand.min(0).max() > 1.2 * radius


def test_fps_is_independent_of_vertex_order():
    mesh = torus(20, 10, noise=0.03, seed=1)
    perm = np.random.default_rng(4).permutation(mesh.n_vertices)
    s = farthest_point_sampling(mesh, 25)
    s2 = farthest_point_sampling(mesh.relabelled(perm), 25)
    np.testing.assert_array_equal(perm[s2.indices], s.indices)


def test_fps_extend_lifts_per_sample_values():
    mesh = torus(12, 8)
    s = farthest_point_sampling(mesh, 10)
    vals = np.arange(10) * 10
    np.testing.assert_array_equal(s.extend(vals)[s.indices], vals)
    with pytest.raises(ValueError, match="10 rows"):
        s.extend(np.arange(9))


def test_fps_pool_is_the_cell_mean_and_inverts_extend():
    mesh = torus(12, 8)
    s = farthest_point_sampling(mesh, 10)
    assert s.counts.sum() == mesh.n_vertices and s.counts.min() >= 1
    x = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(s.pool(s.extend(x)), x, rtol=1e-14)
    v = np.random.default_rng(1).normal(size=(mesh.n_vertices, 2))
    by_hand = np.array([v[s.nearest == i].mean(0) for i in range(10)])
    np.testing.assert_allclose(s.pool(v), by_hand, rtol=1e-12)
    with pytest.raises(ValueError, match="one per vertex"):
        s.pool(np.zeros(5))


def test_cell_pooling_coarse_grains_the_full_problem_exactly():
    # the design claim behind pooling="cell": with signatures constant on cells, the samples with the cells'
    # sizes as masses have the same optimal transport cost as every vertex with one unit of mass each
    ot = pytest.importorskip("ot")
    from wpot.cost import cost_matrix

    a, b = torus(12, 8), torus(10, 9)
    sa, sb = farthest_point_sampling(a, 12), farthest_point_sampling(b, 15)
    rng = np.random.default_rng(2)
    xa, xb = rng.normal(size=(12, 5)), rng.normal(size=(15, 5))
    full = ot.emd2(np.full(a.n_vertices, 1 / a.n_vertices), np.full(b.n_vertices, 1 / b.n_vertices),
                   cost_matrix(sa.extend(xa), sb.extend(xb), metric="l2", device="cpu"))
    coarse = ot.emd2(sa.counts / a.n_vertices, sb.counts / b.n_vertices,
                     cost_matrix(sa.pool(sa.extend(xa)), sb.pool(sb.extend(xb)), metric="l2", device="cpu"))
    assert coarse == pytest.approx(full, rel=1e-10)


@pytest.mark.parametrize("k", [0, 10_000])
def test_fps_rejects_bad_k(k):
    with pytest.raises(ValueError, match="k must be"):
        farthest_point_sampling(torus(8, 6), k)


# --------------------------------------------------------------------------------- memory and history
def test_a_problem_runs_dense_when_it_fits_else_matrix_free_else_names_max_vertices():
    from wpot.ot import make_solver

    solver = make_solver("auto")
    assert choose_cost_mode(solver, 1_000, 1_000, 100, 24 * 2**30) is False  # a few dense 8 MB arrays: dense
    # 50,000 x 50,000: each dense float64 array is 20 GB, but the signatures are 40 MB: matrix-free
    assert choose_cost_mode(solver, 50_000, 50_000, 100, 24 * 2**30) is True
    assert solver.memory_bytes(50_000, 50_000) > 24 * 2**30 >= solver.memory_bytes(50_000, 50_000, matrix_free=True, dim=100)
    with pytest.raises(ProblemTooLargeError, match="max_vertices"):
        choose_cost_mode(solver, 50_000, 50_000, 100, 2**20)


def test_a_transport_over_every_vertex_of_two_large_meshes_warns_on_a_cpu_naming_max_vertices():
    import warnings

    from wpot.cli import cli_words
    from wpot.comparison import ComparisonWarning, check_transport_size

    with pytest.warns(ComparisonWarning, match="a 60000 x 60000 transport over every vertex .* max_vertices=2000") as w:
        check_transport_size(60_000, 60_000, "cpu")
    assert "--max-vertices 2000 compares" in cli_words(str(w[0].message))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_transport_size(20_000, 20_000, "cpu")  # about a minute: no warning
        check_transport_size(60_000, 60_000, "cuda:0")


def test_history_at_reads_the_last_value_at_or_below_each_beta():
    h = np.array([[1e3, 5.0], [1e4, 4.0], [1e5, 3.5]])
    np.testing.assert_array_equal(history_at(h, np.array([1e2, 1e3, 1e4, 1e6])), [np.nan, 5.0, 4.0, 3.5])
    su = debias_history(np.array([[1e3, 10.0], [1e4, 9.0]]), h, np.array([[1e3, 1.0]]))
    np.testing.assert_allclose(su[:, 1], [10 - 0.5 * (5 + 1), 9 - 0.5 * (4 + 1)])


# ------------------------------------------------------------------------ end to end (solver + WKS)
# Small settings: 300 vertices and 100 eigenpairs/energies (fewer energies widen the WKS Gaussians,
# sigma = 7 delta, and blur the correspondence: 50 energies give a median error of ~5 edge lengths here).
FAST = {"n_eigen": 100, "n_energies": 100}


@pytest.fixture(scope="module")
def pair():
    from wpot.examples import example_pair

    # equal vertex counts: a balanced plan can then put a vertex's whole mass on one vertex (G > 0.9 m1)
    return example_pair(300, seed=1, n_target=300)


@pytest.fixture(scope="module")
def comparer(pair):
    from wpot.comparison import Comparer

    c = Comparer(signature="wks", transport="balanced", **FAST)
    c.fit_energies([pair.source, pair.target])
    return c


@pytest.fixture(scope="module")
def ab(comparer, pair):
    return comparer.compare(pair.source, pair.target)


def _errors(pair, correspondence):
    """Distance (in the source frame, in mean edge lengths) between each source vertex and the surface point
    sampled by the target vertex it was matched to."""
    d = np.linalg.norm(pair.target_in_source_frame[correspondence] - pair.source.vertices, axis=1)
    return d / pair.source.mean_edge_length


def test_correspondence_is_mostly_right(ab, pair):
    assert ab.correspondence.shape == (pair.source.n_vertices,)
    err = _errors(pair, ab.correspondence)
    assert np.median(err) < 1.5
    assert np.mean(err < 3.0) > 0.65


def test_matched_pairs_and_masses_are_consistent_with_the_plan(ab):
    plan = np.asarray(ab.result.plan)
    np.testing.assert_allclose(ab.mass1, plan.sum(1), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(ab.mass2, plan.sum(0), rtol=1e-6, atol=1e-12)
    i, j = ab.matched.T
    assert np.all(plan[i, j] > 0.9 * ab.mass1[i])
    np.testing.assert_allclose(ab.matched_weight, plan[i, j])
    # a row with a matched pair has it at its argmax
    np.testing.assert_array_equal(ab.correspondence[i], j)
    assert len(ab.matched) > 0.5 * len(plan)
    assert ab.distance == pytest.approx(float(ab.result.cost))
    assert ab.history.shape[1] == 2 and ab.history[-1, 1] == pytest.approx(ab.distance, rel=1e-6)


def test_reprs_are_summaries_not_array_dumps(ab, pair, comparer):
    # a notebook shows these: the dataclass default printed every array (19 kB for 150 vertices)
    r = repr(ab)
    assert len(r) < 300 and "\n" not in r, r
    assert f"distance={ab.distance:.6g}" in r and f"matched={len(ab.matched)} pairs" in r
    assert f"{pair.source.n_vertices}->{pair.target.n_vertices} vertices" in r and "converged=True" in r
    assert f"scale {ab.registration.scale:.4g}" in r
    c = repr(comparer)
    assert c.startswith("Comparer(signature='wks', transport='balanced'") and f"energies: {len(comparer.energies)} fitted" in c
    o = repr(ab.result)
    n1, n2 = np.asarray(ab.result.plan).shape
    assert len(o) < 300 and f"OTResult({n1}x{n2}, cost={ab.result.cost:.6g}" in o, o


def test_registration_recovers_the_rigid_motion_between_the_pair(ab, pair):
    reg = ab.registration
    assert reg is not None
    # target = source surface rotated and translated: the fitted similarity is that motion
    angle = np.degrees(Rotation.from_matrix(reg.rotation @ pair.rotation.T).magnitude())
    assert angle < 2.0
    # the robust fit: the wrong matches (pairs pointing across the shape) do not pull the scale below 1, as they
    # pull the least-squares fit of the same pairs
    assert reg.method == "robust" and abs(reg.scale - 1) < 0.02
    plain = fit_similarity(pair.source.vertices[ab.matched[:, 0]], pair.target.vertices[ab.matched[:, 1]], ab.matched_weight)
    assert plain.scale < reg.scale
    assert np.linalg.norm(reg.translation - pair.translation) < 0.02 * pair.source.bounding_box_diagonal
    assert 0.5 < reg.inlier_fraction <= 1 and reg.n_pairs == len(ab.matched)
    assert reg.target_diagonal == pytest.approx(pair.target.bounding_box_diagonal)


def test_distance_to_itself_is_smallest(comparer, pair, ab):
    other = pair.source.transformed(np.diag([1.0, 1.0, 1.0]), scale=1.0)
    blob = Mesh(pair.source.vertices * np.array([1.8, 0.6, 1.0]), pair.source.faces)  # another shape
    d_aa = comparer.compare(pair.source, other).distance
    d_ac = comparer.compare(pair.source, blob).distance
    assert d_aa < 0.2 * ab.distance
    assert ab.distance < d_ac


def test_rigid_motion_of_b_leaves_the_wks_comparison_unchanged(comparer, pair, ab):
    rot = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    moved = pair.target.transformed(rot, np.array([3.0, -2.0, 5.0]))
    c = comparer.compare(pair.source, moved)
    assert c.distance == pytest.approx(ab.distance, rel=1e-8)
    np.testing.assert_array_equal(c.correspondence, ab.correspondence)


def test_size_counts_unless_scale_invariant(comparer, pair):
    # A copy 1.13 times larger (TOSCA's Michael against David): the same form, so area-normalized WKS sees
    # (almost) the same shape, while the paper's WKS at the meshes' own size sees the size difference.
    big = pair.source.transformed(np.eye(3), scale=1.13)
    d_self = comparer.compare(pair.source, pair.source).distance
    d_big = comparer.with_options(energies=None).compare(pair.source, big).distance
    inv = comparer.with_options(scale_invariant=True)
    assert inv.energies is None  # a grid is fitted for one convention: never shared across them
    inv.fit_energies([pair.source, big])
    d_big_inv = inv.compare(pair.source, big).distance
    d_self_inv = inv.compare(pair.source, pair.source).distance
    assert d_big_inv == pytest.approx(d_self_inv, rel=1e-6, abs=1e-9)
    assert d_big > 10 * max(d_self, 1e-3 * pair.source.n_vertices)
    assert comparer.params()["scale_invariant"] is False and inv.params()["scale_invariant"] is True
    with pytest.raises(ValueError, match="scale_invariant must be True or False"):
        comparer.with_options(scale_invariant="yes")


def test_signatures_are_cached_in_memory_and_on_disk(tmp_path, pair, monkeypatch):
    from wpot.comparison import Comparer

    from wpot.signatures._wks import WKS

    calls = []
    orig = WKS.__call__

    def counting(self, mesh):
        calls.append(mesh.fingerprint)
        return orig(self, mesh)

    monkeypatch.setattr(WKS, "__call__", counting)
    c1 = Comparer(cache_dir=tmp_path, **FAST)
    c1.fit_energies([pair.source, pair.target])
    s1 = c1.signatures(pair.source)
    c1.signatures(pair.source)
    assert len(calls) == 1
    c2 = Comparer(cache_dir=tmp_path, energies=c1.energies, **FAST)
    np.testing.assert_array_equal(c2.signatures(pair.source), s1)
    assert len(calls) == 1  # read from disk
    c3 = Comparer(cache_dir=tmp_path, energies=c1.energies[:-1], **FAST)  # another grid: recomputed
    c3.signatures(pair.source)
    assert len(calls) == 2
    # a new version of the signature code invalidates the cached entries (on disk too)
    monkeypatch.setattr(WKS, "version", WKS.version + 1)
    c4 = Comparer(cache_dir=tmp_path, energies=c1.energies, **FAST)
    c4.signatures(pair.source)
    assert len(calls) == 3


def test_max_vertices_subsamples_and_extends_to_every_vertex(comparer, pair):
    from wpot.comparison import Comparer

    c = Comparer(max_vertices=150, energies=comparer.energies, **FAST).compare(pair.source, pair.target)
    assert c.sample_a.n_samples == c.sample_b.n_samples == 150
    assert np.asarray(c.result.plan).shape == (150, 150)
    assert c.correspondence.shape == (pair.source.n_vertices,)
    assert np.isin(c.correspondence, c.sample_b.indices).all()
    assert np.isin(c.matched[:, 0], c.sample_a.indices).all() and np.isin(c.matched[:, 1], c.sample_b.indices).all()
    assert np.median(_errors(pair, c.correspondence)) < 3.0
    assert f"{pair.source.n_vertices}->{pair.target.n_vertices} vertices (transport on 150x150 samples)" in repr(c)


@pytest.mark.filterwarnings("ignore:n_eigen=100 but the mesh has only")  # the 75-vertex quarter below
def test_pooling_feeds_cell_means_and_sizes_to_the_solver(comparer, pair):
    ot = pytest.importorskip("ot")
    from wpot.comparison import Comparer
    from wpot.cost import cost_matrix

    none = Comparer(max_vertices=150, energies=comparer.energies, **FAST)
    assert none.pooling == "none"  # the default: parts against wholes need it (see Comparer)
    cell = none.with_options(pooling="cell")
    sig = cell.signatures(pair.source)
    p, q = cell.points(pair.source), none.points(pair.source)
    np.testing.assert_allclose(p.signatures, p.subsample.pool(sig), rtol=1e-14)
    np.testing.assert_allclose(p.masses, p.subsample.counts / pair.source.n_vertices, rtol=1e-14)
    np.testing.assert_array_equal(q.signatures, sig[q.subsample.indices])
    assert q.masses is None and cell.points(pair.target.transformed(np.eye(3))).masses is not None
    assert Comparer(energies=comparer.energies, **FAST).points(pair.source).masses is None  # no subsample
    # the solver gets those masses: same optimum as POT's exact solver, and the plan's marginals
    r = cell.compare(pair.source, pair.target)
    pb = cell.points(pair.target)
    np.testing.assert_allclose(r.mass1, p.masses, atol=1e-9)
    np.testing.assert_allclose(r.mass2, pb.masses, atol=1e-9)
    exact = ot.emd2(p.masses, pb.masses, cost_matrix(p.signatures, pb.signatures, metric="wks", device="cpu"))
    assert r.distance == pytest.approx(exact, rel=1e-6)
    assert cell.params()["pooling"] == "cell" and comparer.params()["pooling"] is None
    with pytest.raises(ValueError, match="pooling must be one of"):
        Comparer(pooling="max")
    # a quarter against the whole at 60 samples: about 1.3 vertices per cell against 5; warned with "cell" only
    from wpot.mesh import cut

    v = pair.source.vertices
    quarter, _ = cut(pair.source, (v[:, 0] > 0) & (v[:, 2] > 0))
    few = Comparer(max_vertices=60, energies=comparer.energies, **FAST)
    with pytest.warns(UserWarning, match="smoothed unequally"):
        few.with_options(pooling="cell").transport_plan(quarter, pair.source)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        few.transport_plan(quarter, pair.source)
        few.with_options(pooling="cell").transport_plan(pair.target, pair.source)  # two wholes: no warning


@pytest.mark.filterwarnings("ignore:n_eigen=100 but the mesh has only")
def test_vertices_per_sample_gives_a_part_and_its_whole_cells_of_one_size(comparer, pair):
    from wpot.comparison import Comparer
    from wpot.mesh import cut

    v = pair.source.vertices
    quarter, _ = cut(pair.source, (v[:, 0] > 0) & (v[:, 2] > 0))
    dense = Comparer(vertices_per_sample=5, pooling="cell", energies=comparer.energies, **FAST)
    n_q, n_w = quarter.n_vertices, pair.source.n_vertices
    assert dense.n_samples(n_w) == round(n_w / 5) and dense.n_samples(n_q) == round(n_q / 5)
    sq, sw = dense.subsample(quarter), dense.subsample(pair.source)
    assert (sq.n_samples, sw.n_samples) == (round(n_q / 5), round(n_w / 5))
    assert abs(n_q / sq.n_samples - n_w / sw.n_samples) < 0.5  # the same cell size on both
    with warnings.catch_warnings():  # the common count warns here (test above); the common density does not
        warnings.filterwarnings("error", message=".*smoothed unequally")
        r = dense.transport_plan(quarter, pair.source)
    np.testing.assert_allclose(r.mass1, dense.points(quarter).masses, atol=1e-9)
    # max_vertices caps it; a mesh with fewer vertices than one cell's worth keeps 3 samples; never more than N
    assert dense.with_options(max_vertices=40).n_samples(n_w) == 40
    assert dense.with_options(vertices_per_sample=1e6).n_samples(n_w) == 3
    assert Comparer(vertices_per_sample=1, **FAST).subsample(quarter) is None
    # a run key names it only when set, so runs stored before it existed still resume
    assert dense.params()["vertices_per_sample"] == 5.0 and dense.params()["pooling"] == "cell"
    assert "vertices_per_sample" not in comparer.params()
    assert Comparer(**dense.options()).params() == dense.params()
    for bad in (0.5, 0, -2, float("nan"), "x", True):
        with pytest.raises(ValueError, match="vertices_per_sample must be"):
            Comparer(vertices_per_sample=bad)


def test_an_explicit_cache_dir_also_keeps_the_spectra(pair, tmp_path, monkeypatch):
    # Regression: spectra went only to $WPOT_CACHE_DIR, so a Comparer given cache_dir= recomputed every
    # eigendecomposition in each new session (fit_energies over 76 TOSCA shapes: 10+ min instead of 24 s)
    from wpot import spectral
    from wpot.comparison import Comparer

    monkeypatch.delenv("WPOT_CACHE_DIR", raising=False)
    spectral.spectrum_cache.clear()
    calls = []
    real = spectral.LaplaceBeltrami.eigenpairs
    monkeypatch.setattr(spectral.LaplaceBeltrami, "eigenpairs", lambda self, k, **kw: calls.append(k) or real(self, k, **kw))
    meshes = [pair.source, pair.target]
    first = Comparer(cache_dir=tmp_path, **FAST)
    first.fit_energies(meshes)
    sig = first.signatures(pair.source)
    assert len(calls) == 2 and any((tmp_path / "spectrum").rglob("*.npz"))
    spectral.spectrum_cache.clear()
    again = Comparer(cache_dir=tmp_path, **FAST)  # a new session: read back from disk, nothing recomputed
    again.fit_energies(meshes)
    np.testing.assert_array_equal(again.energies, first.energies)
    np.testing.assert_array_equal(again.with_options(mass_penalty=0.1).signatures(pair.source), sig)
    assert len(calls) == 2


def test_a_problem_too_large_for_dense_memory_runs_matrix_free_with_the_same_answer(comparer, pair):
    import wpot.comparison as wc

    dense = wc.Comparer(energies=comparer.energies, **FAST).compare(pair.source, pair.target)
    n1, n2 = pair.source.n_vertices, pair.target.n_vertices
    solver, dim = comparer.solver, comparer.signatures(pair.source).shape[1]
    dense_need, lazy_need = solver.memory_bytes(n1, n2), solver.memory_bytes(n1, n2, matrix_free=True, dim=dim)
    assert lazy_need < dense_need
    # room for the matrix-free problem but not the dense one
    tight = wc.Comparer(energies=comparer.energies, memory_limit=(dense_need + lazy_need) // 2, **FAST)
    lazy = tight.compare(pair.source, pair.target)
    assert dense.result.plan is not None and lazy.result.plan is None  # the matrix-free mode forms no N1 x N2 array
    assert lazy.distance == pytest.approx(dense.distance, rel=1e-9)
    np.testing.assert_array_equal(lazy.correspondence, dense.correspondence)
    np.testing.assert_array_equal(lazy.matched, dense.matched)
    np.testing.assert_allclose(lazy.matched_weight, dense.matched_weight, rtol=1e-9)
    with pytest.raises(ProblemTooLargeError, match="max_vertices"):  # not even the signatures fit
        wc.Comparer(energies=comparer.energies, memory_limit=1000, **FAST).compare(pair.source, pair.target)
    c = wc.Comparer(energies=comparer.energies, max_vertices=120, memory_limit=solver.memory_bytes(120, 120), **FAST)
    assert c.compare(pair.source, pair.target).correspondence.shape == (pair.source.n_vertices,)


def test_partial_distance_is_debiased_and_zero_on_itself():
    from wpot.comparison import Comparer
    from wpot.examples import example_partial

    ex = example_partial(250, seed=2, fraction=0.5)
    c = Comparer(transport="partial", **FAST)
    c.fit_energies([ex.full, ex.part])
    r = c.compare(ex.part, ex.full)
    uaa, ubb = r.self_energies
    assert r.distance == pytest.approx(transport_energy_of(r) - 0.5 * (uaa + ubb), rel=1e-12, abs=1e-15)
    assert c.compare(ex.full, ex.full).distance == pytest.approx(0.0, abs=1e-12)
    assert r.mass1.shape == (ex.part.n_vertices,) and r.mass2.shape == (ex.full.n_vertices,)
    assert r.mass1.sum() == pytest.approx(1.0, rel=1e-6)


def transport_energy_of(c):
    return float(c.result.objective)


def test_balanced_pairs_get_the_exact_lp_and_named_methods_the_annealing(comparer, pair):
    # The default solver ("auto") solves balanced pairs exactly (the annealing's limit); "anneal" and "ipm"
    # give D(beta) along the way. The same optimum every way, within the annealing's certified gap.
    problem = comparer.transport_problem(comparer.points(pair.source), comparer.points(pair.target))
    assert comparer.solver.name == "auto" and comparer.solver.method_for(problem) == "exact"
    exact = comparer.transport_plan(pair.source, pair.target)
    results = {m: comparer.with_options(solver_options={"method": m}).transport_plan(pair.source, pair.target)
               for m in ("anneal", "ipm")}
    assert exact.converged and exact.beta == np.inf and len(exact.history) == 1
    for m, r in results.items():
        assert r.converged and len(r.history) > 1, m
        assert 0 <= r.cost - exact.cost <= r.history[-1].gap_bound + exact.history[0].gap_bound, m
    assert results["ipm"].history[0].beta > results["anneal"].history[0].beta  # ipm's history starts later


def test_ldsift_slab_is_part_of_the_run_key_and_the_signature_cache_key():
    from wpot.comparison import Comparer

    old = Comparer(signature="ldsift", device="cpu", cache_dir=False)
    thin = old.with_options(ldsift_slab=0.25)
    assert old.ldsift_slab == 1.0 and thin.params()["ldsift_slab"] == 0.25
    # slab 1.0 (the default), the only one before the option existed: same run key and signature cache key
    # as then, so stored runs resume and cached signatures are reused
    assert "ldsift_slab" not in old.params() and "slab" not in old.stage.params()
    assert thin.stage.params() != old.stage.params()
    assert Comparer(**thin.options()).params() == thin.params()
    assert "ldsift_slab" not in Comparer(signature="wks", ldsift_slab=0.5).params()  # WKS ignores it
    for bad in (0, -1.0, float("nan"), float("inf"), True, "thin"):
        with pytest.raises(ValueError, match="slab must be"):
            Comparer(signature="ldsift", ldsift_slab=bad)
