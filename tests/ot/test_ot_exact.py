"""The exact balanced solver (method="exact", column generation on a sparse support): the optimum of POT's
network simplex and of SciPy's assignment solver, a feasible plan, dual-feasible duals with complementary
slackness over every entry, the same result from a FeatureCost, and its input checks."""
from __future__ import annotations

import math

import numpy as np
import ot
import pytest
from scipy.optimize import linear_sum_assignment

import wpot
import wpot.ot as wo
from wpot.cost import cost_matrix
from wpot.ot.exact.balanced import ColumnGeneration, northwest_corner
from wpot.ot.problem import prepare_cost


def _emd(C, a, b):
    """POT's exact optimum <G, C> (numItermax raised: its default stops early at N ~ 3,400)."""
    G, log = ot.emd(a, b, C, numItermax=10**9, log=True)
    assert not log["warning"], log["warning"]
    return float((G * C).sum())


def _problem(n1, n2, uniform, seed):
    rng = np.random.default_rng(seed)
    C = 3.7 * cost_matrix(rng.random((n1, 6)), rng.random((n2, 6)), metric="l2")
    if uniform:
        return C, np.full(n1, 1 / n1), np.full(n2, 1 / n2)
    a, b = np.exp(1.5 * rng.normal(size=n1)), np.exp(1.5 * rng.normal(size=n2))
    return C, 2.0 * a / a.sum(), 2.0 * b / b.sum()  # total mass 2, masses spread ~10^3


@pytest.mark.parametrize("n1,n2,uniform", [(300, 300, True), (240, 410, False), (500, 130, True), (9, 14, False)])
def test_exact_is_the_optimum_with_a_feasible_plan_and_certified_duals(n1, n2, uniform, device):
    C, a, b = _problem(n1, n2, uniform, seed=n1 + n2)
    r = wo.solve_balanced(C, a, b, method="exact", device=device)
    u = _emd(C, a, b)
    assert r.converged and r.beta == math.inf
    assert abs(r.cost - u) <= 1e-9 * u
    # the plan: nonnegative, exact marginals, its cost is the reported one
    assert r.plan.min() >= 0
    assert np.abs(r.plan.sum(1) - a).sum() <= 1e-9 * a.sum() and np.abs(r.plan.sum(0) - b).sum() <= 1e-9 * a.sum()
    assert abs(float((r.plan * C).sum()) - r.cost) <= 1e-12 * u
    # the duals (Eq. 15's sign): s = C + lam + mu >= 0 on every entry and = 0 where the plan is positive
    s = C + r.lam[:, None] + r.mu[None, :]
    assert s.min() >= -1e-8 * C.max()
    assert np.abs(s[r.plan > 0]).max() <= 1e-8 * C.max()
    # dual objective = primal: the certificate, and the one step of the history
    assert abs(-(a @ r.lam + b @ r.mu) - r.cost) <= 1e-8 * u
    (step,) = r.history
    assert step.beta == math.inf and step.cost == r.cost == r.objective == r.free_energy
    assert 0.0 <= step.gap_bound <= 1e-9 * u
    # plan_top and argmax are read from the plan
    assert np.array_equal(r.argmax, r.plan.argmax(axis=1))
    np.testing.assert_array_equal(r.plan_top.max(axis=1).toarray().ravel(), r.plan.max(axis=1))
    np.testing.assert_allclose(r.mass1, a, rtol=0, atol=1e-12 * a.sum())


def test_exact_equals_the_assignment_optimum():
    """Uniform masses on equal sizes: the optimum is a permutation (Birkhoff), found independently by SciPy's
    Jonker-Volgenant solver; an integer cost has a unique-valued optimum, reached to the last digit."""
    n = 400
    rng = np.random.default_rng(5)
    C = rng.integers(0, 1000, size=(n, n)).astype(np.float64)
    ri, ci = linear_sum_assignment(C)
    best = C[ri, ci].sum() / n
    r = wo.solve_balanced(C, method="exact", device="cpu")
    assert abs(r.cost - best) <= 1e-9 * best
    assert r.converged


def test_exact_reaches_the_optimum_when_the_cheapest_columns_are_shared():
    """Every row's cheapest columns are the same few, so the first support (each row's cheapest columns)
    cannot carry the masses; the north-west corner keeps the LP feasible and pricing finds the optimum."""
    n = 200
    rng = np.random.default_rng(2)
    C = np.tile(np.linspace(0, 1, n), (n, 1)) + 0.01 * rng.random((n, n))
    a = np.full(n, 1 / n)
    r = wo.solve_balanced(C, method="exact", device="cpu")
    assert abs(r.cost - _emd(C, a, a)) <= 1e-9 * r.cost


@pytest.mark.parametrize("seed", range(5))
def test_northwest_corner_is_a_feasible_staircase(seed):
    rng = np.random.default_rng(seed)
    n1, n2 = rng.integers(1, 40, size=2)
    a, b = rng.random(n1) + 0.1, rng.random(n2) + 0.1
    b *= a.sum() / b.sum()
    rows, cols = northwest_corner(a, b)
    assert len(rows) <= n1 + n2 - 1
    assert rows[0] == 0 and cols[0] == 0 and rows[-1] == n1 - 1 and cols[-1] == n2 - 1
    steps = np.stack([np.diff(rows), np.diff(cols)], axis=1)
    assert np.all((steps.sum(1) >= 1) & (steps.min(1) >= 0))  # each step moves right, down or both
    # the plan on those entries: the LP with only these columns is feasible (checked by POT on a cost that
    # forbids every other entry)
    C = np.full((n1, n2), 1e6)
    C[rows, cols] = 0.0
    assert _emd(C, a, b) < 1e-6


def test_pricing_pass_lists_each_rows_cheapest_columns():
    rng = np.random.default_rng(0)
    C = rng.random((50, 70))
    cost = prepare_cost(C, "cpu")
    cg = ColumnGeneration(cost, "cpu")
    rows, cols, rmin, cnt = cg.price(np.zeros(50), np.zeros(70), math.inf, 5)
    assert cnt == 50 * 70
    np.testing.assert_allclose(rmin, C.min(axis=1) / C.max(), rtol=1e-15)
    want = np.argsort(C, axis=1, kind="stable")[:, :5]
    assert np.array_equal(cols.reshape(50, 5), want)
    # below a threshold: only the entries under it, and their count
    u = rng.random(50) * 0.1
    v = rng.random(70) * 0.1
    R = C / C.max() - u[:, None] - v[None, :]
    _, cols2, _, cnt2 = cg.price(u, v, 0.2, 3)
    assert cnt2 == int((R < 0.2).sum())
    assert len(cols2) == int(np.minimum((R < 0.2).sum(1), 3).sum())


@pytest.mark.parametrize("metric", ["wks", "l2"])
def test_exact_matrix_free_equals_stored(metric):
    rng = np.random.default_rng(1)
    X, Y = rng.random((260, 12)), rng.random((200, 12))
    fc = wo.FeatureCost(X, Y, metric=metric, device="cpu")
    r_free = wo.solve_balanced(fc, method="exact", device="cpu")
    r_dense = wo.solve_balanced(cost_matrix(X, Y, metric=metric), method="exact", device="cpu")
    assert r_free.plan is None and r_dense.plan is not None
    assert abs(r_free.cost - r_dense.cost) <= 1e-12 * r_dense.cost
    assert np.array_equal(r_free.argmax, r_dense.argmax)


def test_exact_in_a_comparison_matches_annealing(blob):
    """wpot.compare with method="exact": the distance of the annealing's limit, one history step at inf."""
    other = wpot.Mesh(blob.vertices * np.array([1.25, 1.0, 0.85]), blob.faces)
    kw = dict(signature="wks", max_vertices=80, device="cpu")
    d_exact = wpot.compare(blob, other, method="exact", **kw)
    d_anneal = wpot.compare(blob, other, method="anneal", **kw)
    assert abs(d_exact.distance - d_anneal.distance) <= 1e-6 * abs(d_anneal.distance) + 1e-9
    assert d_exact.history.shape == (1, 2) and d_exact.history[0, 0] == math.inf


def test_exact_sizes_its_memory():
    s = wo.make_solver("exact")
    stored = s.memory_bytes(5000, 5000)
    free = s.memory_bytes(5000, 5000, matrix_free=True, dim=100)
    assert stored >= 2 * 8 * 5000 * 5000  # C and the dense plan
    assert free < 8 * 5000 * 5000  # no N1 x N2 array


def test_exact_says_when_max_iter_stops_it_before_the_optimum():
    C, a, b = _problem(300, 300, True, seed=4)
    with pytest.warns(RuntimeWarning, match="max_iter=1 pricing rounds"):
        r = wo.solve_balanced(C, a, b, method="exact", max_iter=1, device="cpu")
    assert not r.converged and r.history[0].gap_bound > 0
    # the certified bound holds: the optimum lies within it
    u = _emd(C, a, b)
    assert r.cost - r.history[0].gap_bound <= u * (1 + 1e-12) and r.cost >= u * (1 - 1e-12)


def _rounds(C, a, b, check=None):
    """An `ExactRun` driven round by round to its end as `solve_exact_problem` drives it; ``check(run, u, v,
    rows, cols)`` sees each round's duals and candidates."""
    from wpot.ot.exact.balanced import PRICE_K, ExactRun

    run = ExactRun(wo.TransportProblem(C, a, b, device="cpu"), wo.SolverOptions(), "test")
    cg = run.cg
    z1, z2 = np.zeros(cg.n1), np.zeros(cg.n2)
    run.first_support(cg.price(z1, z2, math.inf, 8)[:2], cg.price(z2, z1, math.inf, 8, transposed=True)[:2])
    while run.active:
        u, v = run.lp()
        rows, cols, rmin, nviol = cg.price(u, v, run.thresh, PRICE_K)
        if check is not None:
            check(run, u, v, rows, cols)
        run.take(rows, cols, rmin, nviol, 0.0)
    return run


def test_the_certificate_decides_when_rounding_stops_the_rounds():
    """On large problems the network simplex's duals carry rounding, so entries of the support itself can price
    out below -PRICE_TOL; the rounds then stop (nothing new to add) and the dual bound over every entry decides
    convergence, as it does when nothing prices out."""
    import warnings

    C, a, b = _problem(200, 200, True, seed=5)
    run = _rounds(C, a, b)
    cg = run.cg
    assert run.stop == "optimal"
    # the same last pass, as if two support entries had priced out by rounding
    u, v = run.lp()
    rows, cols, rmin, _ = cg.price(u, v, -1e-11, 8)
    run.active = True
    run.take(cg.rows[:2], cg.cols[:2], rmin, 2, 0.0)
    assert not run.active and run.stop == "rounding"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = run.result()
    assert r.converged and abs(r.cost - _emd(C, a, b)) <= 1e-12 * r.cost


def test_the_threshold_keeps_support_entries_out_of_the_candidates():
    """The pricing threshold sits below the duals' rounding on the support, so a pass lists new entries only."""
    from wpot.ot.exact.balanced import PRICE_TOL

    def check(run, u, v, rows, cols):
        cg = run.cg
        assert run.thresh <= -PRICE_TOL and run.thresh < (cg.c - u[cg.rows] - v[cg.cols]).min()
        known = set(zip(cg.rows.tolist(), cg.cols.tolist()))
        assert not any((r, c) in known for r, c in zip(rows.tolist(), cols.tolist()))

    C, a, b = _problem(400, 350, False, seed=6)
    run = _rounds(C, a, b, check)
    assert run.stop == "optimal" and run.result().converged


def test_each_pricing_round_costs_a_few_transfers():
    """The pass's results and the new entries' costs come back to the host once a round (a GPU's
    synchronisations): 4 device-to-host reads a round, 10 in the first (it includes the first support's row
    and column passes)."""
    from wpot.ot.exact import solve_exact_problem

    C, a, b = _problem(400, 300, False, seed=7)
    rounds = []
    r = solve_exact_problem(wo.TransportProblem(C, a, b, device="cpu"), wo.SolverOptions(), on_round=rounds.append)
    assert r.converged and len(rounds) >= 2 and rounds[-1].violations == 0
    assert rounds[0].n_d2h == 10 and all(x.n_d2h == 4 for x in rounds[1:])
    # the duals, and the new entries' rows and columns
    assert rounds[0].n_h2d == 8 and all(x.n_h2d == 4 for x in rounds[1:])
    assert [x.support for x in rounds] == sorted(x.support for x in rounds)  # the support only grows


@pytest.mark.slow
def test_exact_prints_nothing():
    """A library call is silent (the LP solver's own messages are turned into errors or results)."""
    import subprocess
    import sys

    code = ("import numpy as np, wpot.ot as wo; "
            "wo.solve_balanced(np.random.default_rng(0).random((30, 40)), method='exact', device='cpu')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout + out.stderr == ""


def test_exact_keeps_zero_cost_entries():
    """A point set against itself: the optimum is 0 on the zero-cost diagonal (entries of cost exactly 0 are
    edges of the sparse problem like any other, not missing ones)."""
    X = np.random.default_rng(3).random((150, 5))
    C = cost_matrix(X, X, metric="l2")
    r = wo.solve_balanced(C, method="exact", device="cpu")
    assert r.converged and r.cost == 0.0
    assert np.array_equal(r.argmax, np.arange(150))


def test_a_batch_equals_the_one_problem_solves():
    """Problems of different shapes (both orientations), masses and cost scales, priced in shared launches:
    every result is the one-problem solve's, bit for bit."""
    rng = np.random.default_rng(11)
    problems = []
    for n1, n2 in [(60, 90), (140, 70), (100, 100), (9, 13), (200, 150)]:
        C, a, b = _problem(n1, n2, uniform=bool(rng.integers(2)), seed=int(rng.integers(1000)))
        problems.append(wo.TransportProblem(C * rng.random() * 10, a, b, device="cpu"))
    batch = wo.solve_batch(problems, plan_topk=4)
    assert len(batch) == len(problems)
    for p, r in zip(problems, batch):
        one = wo.make_solver("exact", plan_topk=4).solve(p)
        assert r.converged and r.cost == one.cost and r.history == one.history
        assert np.array_equal(r.plan, one.plan) and np.array_equal(r.lam, one.lam) and np.array_equal(r.mu, one.mu)
        assert (r.plan_top != one.plan_top).nnz == 0
        assert abs(r.cost - _emd(np.asarray(p.cost), p.a, p.b)) <= 1e-9 * r.cost


def test_a_batch_refuses_what_it_cannot_share():
    fc = wo.FeatureCost(np.random.default_rng(0).random((20, 3)), np.random.default_rng(1).random((20, 3)), "l2",
                        device="cpu")
    with pytest.raises(ValueError, match="stored costs"):
        wo.solve_batch([wo.TransportProblem(np.ones((5, 5)), device="cpu"), wo.TransportProblem(fc, device="cpu")])
    assert wo.solve_batch([]) == []
