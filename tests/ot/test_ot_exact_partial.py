"""Exact partial transport (method="exact", the default: the chi^2 QP at beta = infinity by column generation,
`wpot.ot.exact.partial`) against an independent dense QP, the annealing's limit, closed forms and its own
certificate."""
from __future__ import annotations

import math

import numpy as np
import ot
import pytest

import wpot
import wpot.ot as wo
from helpers import partial_qp
from wpot.cost import cost_matrix


def _cost(n1, n2, d=3, seed=0):
    rng = np.random.default_rng(seed)
    X, Y = rng.normal(size=(n1, d)), rng.normal(size=(n2, d)) + 0.3
    return np.linalg.norm(X[:, None] - Y[None], axis=-1)


def _rho(n, seed):
    return np.random.default_rng(seed).random(n) + 0.3


@pytest.mark.parametrize("n1, n2, mp", [(40, 30, 1e-3), (30, 45, 0.05), (36, 36, 3.0)])
def test_exact_partial_is_the_qp_optimum_with_kkt_duals(n1, n2, mp):
    C = 7.0 * _cost(n1, n2, seed=n1 + n2)
    r1, r2 = _rho(n1, 1), _rho(n2, 2)
    res = wo.solve_partial(C, r1, r2, mass_penalty=mp, device="cpu")
    r1, r2 = r1 / r1.sum(), r2 / r2.sum()
    val, m1, m2 = partial_qp(C, r1, r2, mp)
    assert res.converged and res.beta == math.inf and len(res.history) == 1
    assert abs(res.objective - val) <= 1e-9 * val
    np.testing.assert_allclose(res.mass1, m1, atol=1e-8)
    np.testing.assert_allclose(res.mass2, m2, atol=1e-8)
    # the certified bound holds and is tight
    gap = res.history[0].gap_bound
    assert res.objective - gap <= val * (1 + 1e-12) and gap <= 1e-9 * val
    # the plan: nonnegative, its sums the masses, total 1; objective = cost + penalty (Eq. 17)
    P = res.plan
    assert P.min() >= 0 and abs(P.sum() - 1) < 1e-12
    np.testing.assert_allclose(P.sum(1), res.mass1, atol=1e-15)
    a1, a2 = mp / r1**2, mp / r2**2
    assert abs(res.cost - (P * C).sum()) <= 1e-12 * res.cost
    assert abs(res.objective - (res.cost + a1 @ res.mass1**2 + a2 @ res.mass2**2)) <= 1e-12 * res.objective
    # the duals (Eq. 26's sign): C + lam + mu + x >= 0 everywhere, = 0 where the plan is positive; Eq. 25 at
    # beta = infinity: m1 = lam / (2 alpha1), m2 = mu / (2 alpha2)
    R = C + res.lam[:, None] + res.mu[None, :] + res.x
    assert R.min() >= -1e-9 * C.max()
    assert np.abs(R[P > 0]).max() <= 1e-7 * C.max()
    np.testing.assert_allclose(res.lam / (2 * a1), res.mass1, atol=1e-8)
    np.testing.assert_allclose(res.mu / (2 * a2), res.mass2, atol=1e-8)


def test_exact_partial_is_the_annealings_limit():
    C = _cost(60, 45, seed=3)
    for mp in (1e-3, 0.3):
        e = wo.solve_partial(C, mass_penalty=mp, device="cpu")
        a = wo.solve_partial(C, mass_penalty=mp, device="cpu", method="anneal")
        assert a.objective >= e.objective - e.history[0].gap_bound  # the annealing's plan is feasible
        assert abs(a.objective - e.objective) <= 1e-6 * e.objective
        np.testing.assert_allclose(e.mass1, a.mass1, atol=1e-6)
        # the same matches, including the rows that send (almost) nothing: there the exact solver names the
        # entry of least reduced cost, the annealing's largest entry
        assert np.mean(e.argmax == a.argmax) >= 0.95
        assert 0 < np.sum(e.mass1 == 0) or mp > 0.1


def test_limits_of_the_penalty_are_the_closed_forms():
    """A huge penalty fixes the masses at rho^2 / sum rho^2 (the penalty's minimizer under sum m = 1): the
    transport part is then the balanced optimum between those masses (network simplex). With non-uniform rho
    the QP's objective is ~1e9 while the transport part is ~1: the shifted formulation keeps it solvable."""
    C = _cost(25, 20, seed=7)
    r1, r2 = _rho(25, 4), _rho(20, 5)
    w1, w2 = r1**2 / np.sum(r1**2), r2**2 / np.sum(r2**2)
    res = wo.solve_partial(C, r1, r2, mass_penalty=1e6, device="cpu")
    assert res.converged
    np.testing.assert_allclose(res.mass1, w1, atol=1e-8)
    np.testing.assert_allclose(res.mass2, w2, atol=1e-8)
    G, log = ot.emd(w1, w2, C, numItermax=10**8, log=True)
    assert not log["warning"]
    assert abs(res.cost - (G * C).sum()) <= 1e-6 * res.cost


def test_exact_partial_says_when_max_iter_stops_it_and_its_bound_still_holds():
    C = _cost(220, 180, d=6, seed=9)
    mp = 0.02
    full = wo.solve_partial(C, mass_penalty=mp, device="cpu")
    rounds = []
    from wpot.ot.exact import solve_exact_problem

    solve_exact_problem(wo.TransportProblem(C, mass_penalty=mp, device="cpu"), wo.SolverOptions(),
                        on_round=rounds.append)
    assert len(rounds) >= 2 and rounds[0].violations > 0  # the first support lacks entries of the optimum
    with pytest.warns(RuntimeWarning, match="max_iter=1 pricing rounds"):
        r = wo.solve_partial(C, mass_penalty=mp, device="cpu", max_iter=1)
    assert not r.converged and r.history[0].gap_bound > 0
    assert r.objective - r.history[0].gap_bound <= full.objective * (1 + 1e-12) <= r.objective * (1 + 1e-12)


def test_pruned_support_stays_near_the_optimal_face_and_rows_with_no_mass_name_their_least_reduced_cost():
    # random points in R^20: each row's few cheapest entries form a graph whose factorization fills; the rounds
    # keep the support near the optimal plan's (a forest: at most N1 + N2 - 1 entries) and the result exact
    from wpot.ot.exact import solve_exact_problem
    from wpot.ot.exact.partial import least_of_each

    rng = np.random.default_rng(4)
    C = cost_matrix(rng.random((300, 20)), rng.random((240, 20)), metric="l2")
    mp = 0.01 * C.mean() / 300
    rounds = []
    res = solve_exact_problem(wo.TransportProblem(C, mass_penalty=mp, device="cpu"), wo.SolverOptions(),
                              on_round=rounds.append)
    assert res.converged and len(rounds) >= 2
    assert max(r.support for r in rounds[1:]) <= 1.5 * (300 + 240)
    R = C + res.lam[:, None] + res.mu[None, :] + res.x
    assert R.min() >= -1e-9 * C.max()
    empty = res.mass1 == 0
    assert empty.sum() > 20  # a partial plan: rows that send nothing
    # such a row's correspondence is the annealing's limit: its least reduced cost over every column
    np.testing.assert_array_equal(res.argmax[empty], np.argmin(R[empty], axis=1))
    # least_of_each: one entry a row, its least r
    rows, r = np.array([2, 0, 2, 0, 1]), np.array([0.5, 0.3, 0.1, 0.7, 0.2])
    np.testing.assert_array_equal(least_of_each(rows, r), [False, True, True, False, True])


@pytest.mark.parametrize("metric", ["l2", "wks"])
def test_exact_partial_matrix_free_equals_stored(metric):
    rng = np.random.default_rng(1)
    X, Y = rng.random((160, 10)), rng.random((130, 10))
    rho1 = rng.random(160) + 0.5
    kw = dict(mass_penalty=0.05, device="cpu")
    free = wo.solve_partial(wo.FeatureCost(X, Y, metric=metric, device="cpu"), rho1, None, **kw)
    dense = wo.solve_partial(cost_matrix(X, Y, metric=metric), rho1, None, **kw)
    assert free.plan is None and dense.plan is not None
    assert abs(free.objective - dense.objective) <= 1e-12 * dense.objective
    assert np.array_equal(free.argmax, dense.argmax)
    np.testing.assert_allclose(free.mass1, dense.mass1, atol=1e-14)


def test_exact_partial_is_symmetric_under_transposition():
    C = _cost(50, 35, seed=11)
    r1, r2 = _rho(50, 1), _rho(35, 2)
    a = wo.solve_partial(C, r1, r2, mass_penalty=0.01, device="cpu")
    b = wo.solve_partial(C.T.copy(), r2, r1, mass_penalty=0.01, device="cpu")
    assert abs(a.objective - b.objective) <= 1e-10 * a.objective
    np.testing.assert_allclose(a.mass1, b.mass2, atol=1e-9)
    np.testing.assert_allclose(a.lam, b.mu, atol=1e-8 * C.max())


def test_a_batch_of_balanced_and_partial_problems_equals_the_one_problem_solves():
    rng = np.random.default_rng(12)
    problems = []
    for i, (n1, n2) in enumerate([(40, 60), (70, 35), (9, 13), (50, 50)]):
        C = _cost(n1, n2, seed=20 + i) * rng.random() * 10
        a, b = _rho(n1, i), _rho(n2, i + 7)
        problems.append(wo.TransportProblem(C, a / a.sum(), b / b.sum(), device="cpu",
                                            mass_penalty=None if i % 2 else 0.05))
    batch = wo.solve_batch(problems, plan_topk=4)
    for p, r in zip(problems, batch):
        one = wo.make_solver("exact", plan_topk=4).solve(p)
        assert r.converged and r.objective == one.objective and r.history == one.history
        assert np.array_equal(r.plan, one.plan) and np.array_equal(r.lam, one.lam) and r.x == one.x
        assert (r.plan_top != one.plan_top).nnz == 0


def test_partial_comparison_distance_is_the_annealings(blob):
    """wpot.compare with partial transport: the exact solver's D(inf) (default) equals the annealing's."""
    other = wpot.Mesh(blob.vertices * np.array([1.25, 1.0, 0.85]), blob.faces)
    kw = dict(signature="wks", transport="partial", max_vertices=80, device="cpu")
    d_exact = wpot.compare(blob, other, **kw)
    d_anneal = wpot.compare(blob, other, method="anneal", **kw)
    assert abs(d_exact.distance - d_anneal.distance) <= 1e-6 * (abs(d_anneal.distance) + sum(d_anneal.self_energies))
    assert d_exact.history.shape == (1, 2) and d_exact.history[0, 0] == math.inf
    np.testing.assert_allclose(d_exact.mass1, d_anneal.mass1, atol=1e-5)
