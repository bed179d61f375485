"""The matrix-free mode of the OT solver (issue 7): `wpot.ot.FeatureCost` against the stored-C mode on
``cost_matrix(X, Y, metric)`` (same kernels, so the same numbers), the sparse plan outputs, the memory
claim (no N1 x N2 array in the engine) and input validation."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import warp as wp

import wpot.ot as wo
from wpot.cost import cost_matrix
from wpot.ot.anneal.newton import Engine
from wpot.ot.problem import orient, prepare_cost


def _features(n1, n2, d, seed, metric):
    rng = np.random.default_rng(seed)
    X, Y = rng.random((n1, d)), rng.random((n2, d))
    if metric == "wks":  # nonnegative, spread over decades like WKS values, with some 0/0 terms
        X, Y = X**3, Y**3
        X[0, :2] = 0.0
        Y[1, :2] = 0.0
    return X, Y


def _rel(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def _assert_same(rl: wo.OTResult, rs: wo.OTResult):
    """The matrix-free result ``rl`` equals the stored-mode result ``rs`` (to 1e-10 relative)."""
    for name in ("cost", "objective", "free_energy", "x", "beta"):
        assert abs(getattr(rl, name) - getattr(rs, name)) <= 1e-10 * max(1.0, abs(getattr(rs, name))), name
    for name in ("lam", "mu", "mass1", "mass2"):
        assert _rel(getattr(rl, name), getattr(rs, name)) <= 1e-10, name
    assert np.array_equal(rl.argmax, rs.argmax)
    assert rl.n_newton == rs.n_newton and rl.converged == rs.converged


def _assert_same_sparse(r0: wo.OTResult, r1: wo.OTResult, exact: bool):
    """Two runs' sparse plans: the same entries (indices), with equal values (``exact``) or to 1e-10."""
    assert np.array_equal(r0.plan_top.indptr, r1.plan_top.indptr)
    assert np.array_equal(r0.plan_top.indices, r1.plan_top.indices) and np.array_equal(r0.argmax, r1.argmax)
    if exact:
        np.testing.assert_array_equal(r0.plan_top.data, r1.plan_top.data)
    else:
        np.testing.assert_allclose(r0.plan_top.data, r1.plan_top.data, rtol=1e-10, atol=1e-12 * r1.plan_top.data.max())


def _check_sparse_plan(res: wo.OTResult, dense: np.ndarray, k: int):
    """plan_top holds each row's k largest entries of the dense plan, with their exact values."""
    n1, n2 = dense.shape
    P = res.plan_top
    assert sp.isspmatrix_csr(P) and P.shape == (n1, n2)
    kk = min(k, n2)
    assert np.array_equal(np.diff(P.indptr), np.full(n1, kk))
    rows = np.repeat(np.arange(n1), kk)
    np.testing.assert_array_equal(P.data, dense[rows, P.indices])  # the plan's own entries, bit for bit
    # they are the k largest of each row: the smallest kept >= the largest left out
    kept = np.zeros_like(dense, dtype=bool)
    kept[rows, P.indices] = True
    smallest_kept = np.where(kept, dense, np.inf).min(axis=1)
    largest_left = np.where(kept, -np.inf, dense).max(axis=1)
    assert np.all(smallest_kept >= largest_left)
    assert np.array_equal(res.argmax, dense.argmax(axis=1)) and res.argmax.dtype == np.int64
    np.testing.assert_allclose(res.mass1, dense.sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(res.mass2, dense.sum(axis=0), rtol=1e-12)


@pytest.mark.parametrize("metric", ["l2", "l1", "wks"])
@pytest.mark.parametrize("shape", [(60, 60), (45, 70), (70, 45)])
def test_balanced_matrix_free_equals_stored(metric, shape, device):
    n1, n2 = shape
    X, Y = _features(n1, n2, 9, seed=n1 + 7 * n2, metric=metric)
    a = np.random.default_rng(3).random(n1) + 0.5
    b = np.random.default_rng(4).random(n2) + 0.5
    b *= a.sum() / b.sum()
    rs = wo.solve_balanced(cost_matrix(X, Y, metric=metric, device=device), a, b, device=device, method="anneal")
    rl = wo.solve_balanced(wo.FeatureCost(X, Y, metric, device=device), a, b, device=device, dense_plan=True,
                           plan_topk=5, method="anneal")
    _assert_same(rl, rs)
    np.testing.assert_allclose(rl.plan, rs.plan, rtol=1e-10, atol=1e-12 * rs.plan.max())
    _check_sparse_plan(rs, rs.plan, 8)
    _check_sparse_plan(rl, rl.plan, 5)
    # sanity of the shared solution: marginals met
    np.testing.assert_allclose(rl.mass1, a, rtol=1e-6)
    # default: no dense plan in matrix-free mode, the same sparse one (bit for bit on the CPU; on CUDA the
    # atomic column sums add in a varying order, so two runs agree to rounding: 9 of 9 differed on an H100)
    r0 = wo.solve_balanced(wo.FeatureCost(X, Y, metric, device=device), a, b, device=device, plan_topk=5, method="anneal")
    assert r0.plan is None
    _assert_same_sparse(r0, rl, exact=device == "cpu")


@pytest.mark.parametrize("metric", ["l2", "wks"])
@pytest.mark.parametrize("shape", [(50, 50), (40, 64), (64, 40)])
def test_partial_matrix_free_equals_stored(metric, shape, device):
    n1, n2 = shape
    X, Y = _features(n1, n2, 6, seed=3 * n1 + n2, metric=metric)
    rho1 = np.random.default_rng(5).random(n1) + 0.5
    kw = dict(mass_penalty=0.3, device=device, method="anneal")
    rs = wo.solve_partial(cost_matrix(X, Y, metric=metric, device=device), rho1, None, **kw)
    rl = wo.solve_partial(wo.FeatureCost(X, Y, metric, device=device), rho1, None, dense_plan=True, **kw)
    _assert_same(rl, rs)
    np.testing.assert_allclose(rl.plan, rs.plan, rtol=1e-10, atol=1e-12 * rs.plan.max())
    _check_sparse_plan(rl, rl.plan, 8)
    assert rs.objective > rs.cost  # the penalty term is there, and the same in both modes


def test_larger_problem_l1_stays_equal():
    """N ~ 120, d = 16: more Newton steps and preconditioner rebuilds, still the same iterates."""
    X, Y = _features(120, 100, 16, seed=11, metric="l1")
    rs = wo.solve_balanced(cost_matrix(X, Y, metric="l1"), device="cpu", method="anneal")
    rl = wo.solve_balanced(wo.FeatureCost(X, Y, "l1", device="cpu"), device="cpu", method="anneal")
    _assert_same(rl, rs)
    assert rl.plan is None and rl.plan_top.shape == (120, 100)
    # the sparse plan's top entries are the stored mode's plan entries
    _check_sparse_plan(rl, rs.plan, 8)


def test_engine_allocates_nothing_quadratic():
    n1, n2 = 37, 53
    X, Y = _features(n1, n2, 5, seed=2, metric="l2")
    for lazy in (True, False):
        cost = prepare_cost(wo.FeatureCost(X, Y, "l2", device="cpu") if lazy else cost_matrix(X, Y, metric="l2"), "cpu")
        assert cost.lazy == lazy and cost.scale == pytest.approx(cost_matrix(X, Y, metric="l2").max(), rel=0, abs=0)
        opts = wo.SolverOptions(step=10.0, tol=1e-6, atol=1e-10, max_iter=5, max_newton=20, newton_tol=1e-11,
                                linear_solver="cg", cg_rtol=1e-3, cg_max_iter=100, topk=4, extrapolate=True,
                                verbose=0).normalized(n1, n2, cost.scale)
        prob = orient(cost, np.full(n1, 1 / n1), np.full(n2, 1 / n2), np.zeros(n1), np.zeros(n2), False, "cpu")
        eng = Engine(prob, opts)
        sizes = []
        for v in vars(eng).values():
            arrs = v if isinstance(v, list) else [v]
            sizes += [a.size for a in arrs if isinstance(a, wp.array)]
        sizes += [a.size for a in (cost.C,) if isinstance(a, wp.array)]
        if lazy:
            assert max(sizes) < n1 * n2 / 4  # O(N k) only (top-k lists, vectors)
            assert cost.C is None
        else:
            assert n1 * n2 in sizes  # the stored mode does keep W (and C)


def test_bad_input_is_named(device):
    X, Y = _features(20, 30, 4, seed=0, metric="wks")
    with pytest.raises(ValueError, match="same signature length"):
        wo.FeatureCost(X, Y[:, :3], "l2", device=device)
    bad = X.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="X contains NaN"):
        wo.FeatureCost(bad, Y, "l2", device=device)
    with pytest.raises(ValueError, match="Y has negative entries"):
        wo.FeatureCost(X, Y - 0.5, "wks", device=device)
    wo.FeatureCost(X, Y - 0.5, "l2", device=device)  # negative values are fine for l2
    with pytest.raises(ValueError, match="metric must be one of"):
        wo.FeatureCost(X, Y, "cosine", device=device)
    fc = wo.FeatureCost(X, Y, "wks", device=device)
    with pytest.raises(ValueError, match="linear_solver='direct'.*matrix-free"):
        wo.solve_balanced(fc, device=device, linear_solver="direct", method="anneal")
    with pytest.raises(ValueError, match="linear_solver='direct'"):
        wo.solve_partial(fc, device=device, linear_solver="direct")
    with pytest.raises(ValueError, match="plan_topk"):
        wo.solve_balanced(fc, device=device, plan_topk=0, method="anneal")
    with pytest.raises(ValueError, match="dense_plan"):
        wo.solve_balanced(fc, device=device, dense_plan="yes", method="anneal")
    with pytest.raises(AttributeError, match="immutable"):
        fc.metric = "l2"
    assert fc.shape == (20, 30)
    np.testing.assert_array_equal(fc.dense(), cost_matrix(X, Y, metric="wks", device=device))


def test_dense_plan_that_does_not_fit_is_refused():
    # 2e5 x 2e5 float64 = 298 GiB: refused before any work (X, Y themselves are small)
    X = np.zeros((200_000, 1))
    fc = wo.FeatureCost(X, X, "l1", device="cpu")
    with pytest.raises(ValueError, match=r"dense_plan=True needs .*\(200000, 200000\).* GiB"):
        wo.solve_balanced(fc, device="cpu", dense_plan=True, method="anneal")


def test_feature_cost_on_another_device_is_named():
    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("needs two Warp devices (cpu and cuda)")
    X, Y = _features(10, 12, 3, seed=0, metric="l2")
    fc = wo.FeatureCost(X, Y, "l2", device="cpu")
    with pytest.raises(ValueError, match="FeatureCost is on device cpu"):
        wo.solve_balanced(fc, device="cuda", method="anneal")


def test_stored_mode_dense_plan_false_keeps_sparse_outputs():
    X, Y = _features(30, 40, 4, seed=9, metric="l2")
    C = cost_matrix(X, Y, metric="l2")
    r = wo.solve_balanced(C, device="cpu", method="anneal")
    r0 = wo.solve_balanced(C, device="cpu", dense_plan=False, method="anneal")
    assert r0.plan is None and (r0.plan_top != r.plan_top).nnz == 0 and np.array_equal(r0.argmax, r.argmax)
    assert r0.cost == r.cost
