"""Passes over a matrix-free Euclidean cost through BLAS (`wpot.ot.gram`): the Gram blocks are A B^T, and the
exact solver's pricing passes and max C give what the plain Warp kernels give, bit for bit, also where
a2 + b2 - 2 A.B cancels (equal and nearly equal points, features far from the origin)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

import wpot.ot as wo
from wpot.ot import kernels as K
from wpot.ot.exact import solve_exact_problem
from wpot.ot.exact.balanced import ColumnGeneration
from wpot.ot.gram import GramBlocks, gram_applies
from wpot.ot.options import SolverOptions
from wpot.ot.problem import TransportProblem, _prepare_features, prepare_cost


def _features(n1, n2, d, seed, offset=0.0):
    """Random points, a few of them shared by both sides and a few a hair apart (1e-9: the squared distance
    cancels to nothing in a2 + b2 - 2 A.B), optionally moved far from the origin (more cancellation)."""
    rng = np.random.default_rng(seed)
    X, Y = rng.random((n1, d)), rng.random((n2, d))
    Y[:7] = X[:7]
    Y[7:12] = X[7:12] + 1e-9 * rng.normal(size=(5, d))
    return X + offset, Y + offset


def test_blocks_are_the_gram_matrix_in_pieces():
    X, Y = _features(37, 23, 5, seed=0)
    fc = wo.FeatureCost(X, Y, metric="l2", device="cpu")
    g = GramBlocks(fc, block_bytes=8 * 23 * 10)  # 10 rows a block: 4 blocks, the last one short
    for transposed, (A, B) in ((False, (X, Y)), (True, (Y, X))):
        seen = []
        for k0, n, P in g.blocks(transposed):
            np.testing.assert_allclose(P.numpy()[:n], A[k0:k0 + n] @ B.T, rtol=1e-13)
            seen.append((k0, n))
        # 8 * 23 * 10 bytes: 10 rows of 23 columns (4 blocks, the last short), or 6 rows of 37
        assert seen[0] == (0, 6 if transposed else 10) and sum(n for _, n in seen) == len(A)
    assert gram_applies(fc, "cpu")
    assert not gram_applies(wo.FeatureCost(np.abs(X), np.abs(Y), metric="wks", device="cpu"), "cpu")


@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_max_cost_equals_the_plain_kernel(offset):
    X, Y = _features(120, 90, 17, seed=1, offset=offset)
    fc = wo.FeatureCost(X, Y, metric="l2", device="cpu")
    plain = _prepare_features(fc, "cpu", gram=False)
    gram = _prepare_features(fc, "cpu", gram=True)
    assert gram.c_max == plain.c_max and gram.scale == plain.scale
    src = K.LazyCost()
    src.A, src.B, src.metric, src.inv_scale = fc.X, fc.Y, 1, wp.float64(1.0)
    rows = GramBlocks(fc, block_bytes=8 * 90 * 16).row_max(src)
    np.testing.assert_array_equal(rows, _plain_row_max(fc))


def _plain_row_max(fc):
    src = K.LazyCost()
    src.A, src.B, src.metric, src.inv_scale = fc.X, fc.Y, 1, wp.float64(1.0)
    out = wp.zeros(fc.shape[0], dtype=wp.float64, device="cpu")
    wp.launch(K.feature_cost_max, dim=fc.shape[0], inputs=[src, fc.shape[1], out], device="cpu")
    return out.numpy()


@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_pricing_passes_equal_the_plain_kernel(offset):
    X, Y = _features(150, 110, 9, seed=2, offset=offset)
    fc = wo.FeatureCost(X, Y, metric="l2", device="cpu")
    cost = prepare_cost(fc, "cpu")
    plain = ColumnGeneration(cost, "cpu", gram=False)
    gram = ColumnGeneration(cost, "cpu", gram=GramBlocks(fc, block_bytes=8 * 150 * 13))
    assert plain.gram is None and gram.gram is not None
    rng = np.random.default_rng(3)
    C = np.sqrt(((X[:, None] - Y[None]) ** 2).sum(-1)) / cost.scale
    # duals that make some entries exactly tight (r = 0 to rounding) and some negative
    u = rng.random(150) * 0.3
    v = np.min(C - u[:, None], axis=0)  # every column has a tight entry, no negative one
    v[::4] += 0.05  # a quarter of the columns now price out somewhere
    for transposed in (False, True):
        uu, vv = (v, u) if transposed else (u, v)
        for thresh, m in ((math.inf, 5), (-1e-11, 4), (0.0, 3)):
            p = plain.price(uu, vv, thresh, m, transposed=transposed)
            g = gram.price(uu, vv, thresh, m, transposed=transposed)
            assert np.array_equal(p[0], g[0]) and np.array_equal(p[1], g[1]) and p[3] == g[3]
            neg = p[2] < 0  # row minima agree where they are negative; elsewhere both are >= 0
            assert np.array_equal(p[2][neg], g[2][neg]) and (g[2][~neg] >= 0).all()


@pytest.mark.parametrize("n1,n2,offset", [(300, 260, 0.0), (180, 240, 50.0)])
def test_exact_solve_through_gram_blocks_equals_the_plain_kernels(n1, n2, offset):
    X, Y = _features(n1, n2, 24, seed=n1, offset=offset)
    rng = np.random.default_rng(4)
    a, b = np.exp(rng.normal(size=n1)), np.exp(rng.normal(size=n2))
    a, b = a / a.sum(), b / b.sum()
    fc = wo.FeatureCost(X, Y, metric="l2", device="cpu")
    prob = TransportProblem(fc, a, b, device="cpu")
    r_plain = solve_exact_problem(prob, SolverOptions(), gram=False)
    r_gram = solve_exact_problem(prob, SolverOptions(), gram=GramBlocks(fc, block_bytes=8 * n2 * 64))
    assert r_plain.converged and r_gram.converged
    assert r_gram.cost == r_plain.cost and r_gram.history[0].gap_bound == r_plain.history[0].gap_bound
    assert np.array_equal(r_gram.lam, r_plain.lam) and np.array_equal(r_gram.mu, r_plain.mu)
    assert (r_gram.plan_top != r_plain.plan_top).nnz == 0
    # and the default picks the Gram blocks for this cost on the CPU
    assert wo.solve_balanced(fc, a, b, method="exact", device="cpu").cost == r_plain.cost


def test_gram_refuses_a_cost_it_cannot_serve():
    rng = np.random.default_rng(5)
    fc = wo.FeatureCost(rng.random((20, 4)), rng.random((30, 4)), metric="l1", device="cpu")
    with pytest.raises(ValueError, match="metric='l2'"):
        ColumnGeneration(prepare_cost(fc, "cpu"), "cpu", gram=True)
