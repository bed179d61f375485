"""The interior-point start of the balanced solver (method="ipm"): the same optimum as POT's exact emd and as
plain annealing, exact betas in the history from the hand-off on, and its input checks."""
from __future__ import annotations

import numpy as np
import ot
import pytest

import wpot.ot as wo
from helpers import masses, points_cost
from wpot.cost import cost_matrix
from wpot.ot.anneal.ipm import HANDOFF, handoff_beta


def _points(n, d=8, seed=0):
    return np.random.default_rng(seed).random((n, d))


def _emd(C, a, b):
    G = ot.emd(a, b, C, numItermax=10**7)
    return float((G * C).sum())


@pytest.mark.parametrize("n1,n2,uniform", [(120, 120, True), (90, 140, False), (150, 70, True), (12, 9, False)])
def test_ipm_matches_emd_and_marginals(n1, n2, uniform):
    C = 3.7 * points_cost(n1, n2, seed=n1)  # any cost scale
    a = np.full(n1, 1 / n1) if uniform else masses(n1, 1)
    b = np.full(n2, 1 / n2) if uniform else masses(n2, 2)
    r = wo.solve_balanced(C, a, b, method="ipm", device="cpu")
    u = _emd(C, a, b)
    assert r.converged
    assert abs(r.cost - u) <= 1e-6 * u
    assert np.abs(r.plan.sum(1) - a).sum() <= 1e-6 and np.abs(r.plan.sum(0) - b).sum() <= 1e-6


def test_ipm_planted_permutation():
    n = 100
    rng = np.random.default_rng(3)
    perm = rng.permutation(n)
    C = rng.random((n, n)) + 1.0
    C[np.arange(n), perm] = rng.random(n) * 0.1  # the permutation is the unique optimum
    r = wo.solve_balanced(C, method="ipm", device="cpu")
    assert np.array_equal(r.argmax, perm)
    assert abs(r.cost - C[np.arange(n), perm].sum() / n) <= 1e-6 * r.cost


def test_ipm_and_annealing_reach_the_same_solution():
    C = points_cost(160, 130, seed=7)
    ra = wo.solve_balanced(C, device="cpu", method="anneal")
    ri = wo.solve_balanced(C, method="ipm", device="cpu")
    assert ra.converged and ri.converged
    assert abs(ri.cost - ra.cost) <= 1e-8 * ra.cost
    # the history from the hand-off on is Algorithm 1's: same betas and U as annealing at those betas
    hist_a = {round(np.log10(h.beta), 6): h for h in ra.history}
    assert len(ri.history) < len(ra.history)
    for h in ri.history:
        ha = hist_a[round(np.log10(h.beta), 6)]
        assert abs(h.cost - ha.cost) <= 1e-9 * ha.cost
    # the first recorded beta is the hand-off: its gap bound is at most HANDOFF x U (and the one before is not)
    h0 = ri.history[0]
    assert h0.gap_bound <= 1.05 * HANDOFF * h0.cost
    assert ri.n_newton > sum(h.n_newton for h in ri.history)  # the interior-point iterations are counted


def test_ipm_zero_optimum_self_comparison():
    # a point set against itself: U* = 0 (the hand-off beta is capped by beta_max, the annealing stops on atol)
    X = _points(80, d=6, seed=4)
    C = np.linalg.norm(X[:, None] - X[None], axis=-1)
    r = wo.solve_balanced(C, method="ipm", device="cpu")
    ra = wo.solve_balanced(C, device="cpu", method="anneal")
    assert r.converged
    assert r.cost <= 1e-8 * C.mean() and abs(r.cost - ra.cost) <= 1e-9 * C.max()
    assert np.array_equal(r.argmax, np.arange(80))


def test_handoff_beta_is_the_first_grid_beta_below_the_gap():
    b = handoff_beta(2.0, 10.0, 100, 50, 0.3, handoff=1e-3)
    assert 100 * 50 / b <= 1e-3 * 0.3 < 100 * 50 / (b / 10)
    assert np.isclose(np.log10(b / 2.0), round(np.log10(b / 2.0)))


def test_ipm_rejects_the_matrix_free_mode_and_unknown_methods():
    X, Y = _points(30, d=5), _points(40, d=5, seed=9)
    with pytest.raises(ValueError, match="ipm"):
        wo.solve_balanced(wo.FeatureCost(X, Y, metric="l2", device="cpu"), method="ipm", device="cpu")
    with pytest.raises(ValueError, match="method"):
        wo.solve_balanced(cost_matrix(X, Y, metric="l2"), method="simplex", device="cpu")
