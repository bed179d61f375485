"""Tests of wpot.ot: phi accuracy, schedule, balanced vs POT's exact emd, partial vs an independent QP,
invariances, validation and non-convergence reporting, CPU vs CUDA."""
from __future__ import annotations

import warnings

import numpy as np
import ot
import pytest
import warp as wp

import wpot.ot as wo
from helpers import partial_qp
from wpot.ot import kernels as K
from wpot.ot.anneal.schedule import beta_schedule, relative_change
from helpers import masses, points_cost






# --------------------------------------------------------------------------- phi, phi', g
def test_phi_dphi_g_match_longdouble_reference():
    x = np.concatenate([-np.logspace(-12, 12, 801), [0.0], np.logspace(-12, 12, 801), np.linspace(-3, 3, 1201)])
    xa = wp.array(x, dtype=wp.float64, device="cpu")
    out = [wp.zeros(len(x), dtype=wp.float64, device="cpu") for _ in range(3)]
    wp.launch(K.eval_phi, dim=len(x), inputs=[xa, *out], device="cpu")
    p, dp, g = (o.numpy() for o in out)
    L = np.longdouble
    xl = x.astype(L)
    with np.errstate(all="ignore"):
        em1 = np.expm1(xl)
        ph = 1 / xl - 1 / em1
        dph = -1 / xl**2 + np.exp(xl) / em1**2
        gg = np.log(-np.expm1(-xl) / xl)
    s = np.abs(x) < 0.1  # series reference (longdouble direct forms cancel there)
    xs = xl[s]
    ph[s] = 0.5 - xs / 12 + xs**3 / 720 - xs**5 / 30240 + xs**7 / 1209600
    dph[s] = -L(1) / 12 + xs**2 / 240 - xs**4 / 6048 + xs**6 / 172800
    gg[s] = -xs / 2 + xs**2 / 24 - xs**4 / 2880 + xs**6 / 181440
    big = np.abs(x) > 1e4  # closed asymptotics (e^-|x| negligible)
    ph[big] = np.where(x[big] > 0, 1 / xl[big], 1 + 1 / xl[big])
    dph[big] = -1 / xl[big] ** 2
    xb = xl[big]
    gg[big] = np.where(xb > 0, -np.log(np.abs(xb)), -xb - np.log(np.abs(xb)))
    assert np.all(np.isfinite(p)) and np.all(np.isfinite(dp)) and np.all(np.isfinite(g))
    assert np.all((p > 0) & (p < 1)) and np.all(dp < 0)
    for a, r in ((p, ph), (dp, dph), (g, gg)):
        m = r != 0
        rel = np.abs((a[m] - r[m]) / r[m]).astype(float)
        assert rel.max() < 1e-13
    assert p[np.argmin(np.abs(x))] == 0.5 and abs(dp[np.argmin(np.abs(x))] + 1 / 12) < 1e-16
    # g' = -phi (finite differences of g at moderate x)
    h = 1e-5
    xm = np.linspace(-5, 5, 41)
    xa = wp.array(np.concatenate([xm - h, xm + h]), dtype=wp.float64, device="cpu")
    out = [wp.zeros(2 * len(xm), dtype=wp.float64, device="cpu") for _ in range(3)]
    wp.launch(K.eval_phi, dim=2 * len(xm), inputs=[xa, *out], device="cpu")
    gv = out[2].numpy()
    fd = (gv[len(xm):] - gv[: len(xm)]) / (2 * h)
    xa = wp.array(xm, dtype=wp.float64, device="cpu")
    out = [wp.zeros(len(xm), dtype=wp.float64, device="cpu") for _ in range(3)]
    wp.launch(K.eval_phi, dim=len(xm), inputs=[xa, *out], device="cpu")
    np.testing.assert_allclose(fd, -out[0].numpy(), atol=1e-8)


# --------------------------------------------------------------------------- schedule
def test_beta_schedule_is_geometric_and_bounded():
    b = beta_schedule(2.0, 10.0, 2e5)
    np.testing.assert_allclose(b, [2, 20, 200, 2e3, 2e4, 2e5])
    assert beta_schedule(1.0, 3.0, 2.9).tolist() == [1.0]
    np.testing.assert_array_equal(beta_schedule(1.5, 2.0, 100.0), beta_schedule(1.5, 2.0, 100.0))
    with pytest.raises(ValueError, match="step"):
        beta_schedule(1.0, 1.0, 10.0)
    with pytest.raises(ValueError, match="beta_max"):
        beta_schedule(10.0, 2.0, 1.0)
    assert relative_change(2.0, 1.0) == 0.5 and relative_change(0.0, 0.0) == 0.0


# --------------------------------------------------------------------------- balanced
def _check_balanced(C, a, b, res, rtol=1e-6):
    u0 = ot.emd2(a, b, C, numItermax=10**7)
    assert res.converged
    assert abs(res.cost - u0) <= rtol * abs(u0)
    assert res.cost >= u0 - 1e-12  # a feasible plan costs at least the optimum
    tot = a.sum()
    assert np.abs(res.mass1 - a).sum() <= 1e-6 * tot
    assert np.abs(res.mass2 - b).sum() <= 1e-6 * tot
    assert abs((res.plan * C).sum() - res.cost) <= 1e-12 * max(1.0, abs(res.cost))
    # the history is monotone (U(beta) decreases to U*) and its gap bound holds
    costs = np.array([h.cost for h in res.history])
    assert np.all(np.diff(costs) <= 1e-12 * costs[0])
    assert res.history[-1].gap_bound >= res.cost - u0 - 1e-12
    # balanced: the per-beta objective is the transport cost
    assert all(h.objective == h.cost for h in res.history)


def test_balanced_square_uniform_matches_emd(device):
    C = points_cost(40, 40)
    n = 40
    a = np.full(n, 1 / n)
    res = wo.solve_balanced(C, device=device, method="anneal")
    _check_balanced(C, a, a, res)


def test_balanced_rectangular_nonuniform_matches_emd():
    C = points_cost(30, 45, seed=3) * 7.5  # arbitrary scale
    a, b = masses(30, 1), masses(45, 2)
    res = wo.solve_balanced(C, a, b, device="cpu", method="anneal")
    _check_balanced(C, a, b, res)
    # the same with the roles swapped (the solver eliminates the larger side either way)
    rt = wo.solve_balanced(C.T.copy(), b, a, device="cpu", method="anneal")
    np.testing.assert_allclose(rt.plan, res.plan.T, atol=1e-9 * res.plan.max())
    assert abs(rt.cost - res.cost) <= 1e-9 * res.cost


def test_balanced_planted_permutation_closed_form():
    n = 25
    rng = np.random.default_rng(5)
    perm = rng.permutation(n)
    C = 1.0 + rng.random((n, n))
    C[np.arange(n), perm] = 0.2 * rng.random(n)  # the planted permutation is the unique optimum
    res = wo.solve_balanced(C, device="cpu", method="anneal")
    u_star = C[np.arange(n), perm].sum() / n
    assert abs(res.cost - u_star) <= 1e-6 * u_star
    assert np.array_equal(res.plan.argmax(axis=1), perm)


def test_balanced_invariances():
    C = points_cost(20, 20, seed=7)
    a, b = masses(20, 8), masses(20, 9)
    r = wo.solve_balanced(C, a, b, device="cpu", method="anneal")
    p1, p2 = np.random.default_rng(0).permutation(20), np.random.default_rng(1).permutation(20)
    rp = wo.solve_balanced(C[p1][:, p2], a[p1], b[p2], device="cpu", method="anneal")
    assert abs(rp.cost - r.cost) <= 1e-9 * r.cost
    np.testing.assert_allclose(rp.plan, r.plan[p1][:, p2], atol=1e-9 * r.plan.max())
    rs = wo.solve_balanced(C * 1e5, a, b, device="cpu", method="anneal")
    assert abs(rs.cost - 1e5 * r.cost) <= 1e-9 * rs.cost
    assert abs(rs.beta * 1e5 - r.beta) <= 1e-9 * r.beta
    rt = wo.solve_balanced(C.T.copy(), b, a, device="cpu", method="anneal")
    assert abs(rt.cost - r.cost) <= 1e-9 * r.cost


def test_direct_and_cg_agree_and_warp_input_is_used_in_place():
    C = points_cost(15, 22, seed=4)
    rc = wo.solve_balanced(C, device="cpu", method="anneal")
    rd = wo.solve_balanced(C, device="cpu", linear_solver="direct", method="anneal")
    assert abs(rc.cost - rd.cost) <= 1e-9 * rc.cost
    # a much cruder preconditioner (reused across steps until CG slows) changes the path, not the answer
    r2 = wo.solve_balanced(C, device="cpu", topk=2, method="anneal")
    assert r2.converged and abs(r2.cost - rd.cost) <= 1e-9 * rc.cost
    Cw = wp.array(C, dtype=wp.float64, device="cpu")
    rw = wo.solve_balanced(Cw, device="cpu", method="anneal")
    assert rw.cost == rc.cost
    np.testing.assert_array_equal(Cw.numpy(), C)


def test_balanced_self_transport_has_zero_cost_and_stops():
    X = np.random.default_rng(2).random((20, 3))
    C = np.linalg.norm(X[:, None] - X[None], axis=-1)
    res = wo.solve_balanced(C, device="cpu", method="anneal")
    assert res.converged
    assert res.cost <= 1e-9 * C.max()
    assert np.array_equal(res.plan.argmax(axis=1), np.arange(20))
    assert wo.debiased(res.cost, res.cost, res.cost) == 0.0


def test_cpu_and_cuda_agree(device):
    if device == "cpu":
        pytest.skip("needs a CUDA device to compare with")
    C = points_cost(30, 24, seed=11)
    rc = wo.solve_balanced(C, device="cpu", method="anneal")
    rg = wo.solve_balanced(C, device=device, method="anneal")
    assert abs(rc.cost - rg.cost) <= 1e-10 * rc.cost
    np.testing.assert_allclose(rg.plan, rc.plan, atol=1e-10 * rc.plan.max())
    pc = wo.solve_partial(C, device="cpu")
    pg = wo.solve_partial(C, device=device)
    assert abs(pc.objective - pg.objective) <= 1e-10 * pc.objective


# --------------------------------------------------------------------------- partial
def _partial_checked_by_qp(C, r1, r2, mp):
    """solve_partial's result (the annealing), asserted converged and equal (objective, masses) to the cvxpy QP's
    optimum."""
    res = wo.solve_partial(C, r1, r2, mass_penalty=mp, device="cpu", method="anneal")
    val, m1, m2 = partial_qp(C, r1, r2, mp)
    assert res.converged
    assert abs(res.objective - val) <= 1e-6 * val
    np.testing.assert_allclose(res.mass1, m1, atol=1e-6)
    np.testing.assert_allclose(res.mass2, m2, atol=1e-6)
    return res


@pytest.mark.parametrize("mp", [1.0, 0.01])
def test_partial_matches_independent_qp(mp):
    rng = np.random.default_rng(1)
    C = rng.random((12, 9))
    r1, r2 = masses(12, 3), masses(9, 4)
    res = _partial_checked_by_qp(C, r1, r2, mp)
    assert abs(res.mass1.sum() - 1) < 1e-9
    pen = mp * np.sum((res.mass1 / r1) ** 2) + mp * np.sum((res.mass2 / r2) ** 2)
    assert abs(res.objective - (res.cost + pen)) <= 1e-9 * res.objective
    # the per-beta objective (cost + chi^2 penalty) ends at the result's and exceeds the transport part
    assert abs(res.history[-1].objective - res.objective) <= 1e-12 * res.objective
    assert all(h.objective > h.cost for h in res.history)


def test_partial_huge_penalty_recovers_balanced():
    C = points_cost(16, 16, seed=5)
    rb = wo.solve_balanced(C, device="cpu", method="anneal")
    rp = wo.solve_partial(C, mass_penalty=1e6, device="cpu")
    # uniform rho: masses -> rho^2 / sum rho^2 = uniform, so the transport part -> balanced U*
    np.testing.assert_allclose(rp.mass1, 1 / 16, atol=1e-5)
    assert abs(rp.cost - rb.cost) <= 1e-4 * rb.cost
    # non-uniform rho: masses -> rho^2 / sum(rho^2), not rho
    r1 = masses(16, 6)
    rq = wo.solve_partial(C, r1, None, mass_penalty=1e6, device="cpu")
    np.testing.assert_allclose(rq.mass1, r1**2 / np.sum(r1**2), atol=1e-4)


def _uneven_problem(n, spread, seed):
    """Points in R^3 and log-normal masses (max/min ~ 10^2-10^4, as cell-pooled samples of unevenly meshed
    shapes give, or heavier)."""
    rng = np.random.default_rng(seed)
    X, Y = np.abs(rng.normal(size=(n, 3))), np.abs(rng.normal(size=(n, 3)))
    C = np.linalg.norm(X[:, None] - Y[None], axis=-1)
    a, b = np.exp(spread * rng.normal(size=n)), np.exp(spread * rng.normal(size=n))
    return C, a / a.sum(), b / b.sum()


@pytest.mark.parametrize("spread,seed", [(1.5, 0), (1.5, 1), (2.5, 0)])
def test_balanced_uneven_masses_match_emd(spread, seed):
    # Regression: Newton used to stall at the first beta on such masses (residual stuck at 0.5; converged
    # False and U off by ~100%)
    C, a, b = _uneven_problem(40, spread, seed)
    _check_balanced(C, a, b, wo.solve_balanced(C, a, b, device="cpu", method="anneal"))  # asserts converged and emd's optimum


@pytest.mark.parametrize("seed", [0, 2])
def test_partial_uneven_masses_match_independent_qp(seed):
    # Regression: one point holding ~40% of the mass drove a pivot entry to G ~ 1/2 (beta s ~ 0), where the
    # fraction-to-boundary rule stopped every Newton step short
    C, r1, r2 = _uneven_problem(40, 1.5, seed)
    _partial_checked_by_qp(C, r1, r2, 0.01 * C.mean() / 40)


def test_a_newton_failure_after_a_solved_beta_returns_that_beta_s_solution(monkeypatch):
    # Regression: a failed solve at a late beta (seen at beta 2.5e14 on a cell-pooled TOSCA pair) left its far
    # from feasible iterate as the result (U 12 % below ot.emd's optimum), although the beta before was
    # within 1e-7 of it. Now the result is the last solved beta's, flagged not converged, with a warning.
    ot = pytest.importorskip("ot")
    from wpot.ot.anneal import newton

    C, a, b = _uneven_problem(30, 1.0, 0)
    exact = ot.emd2(a, b, C)
    calls = []
    real = newton.Engine.newton

    def flaky(self, beta, pt):
        calls.append(beta)
        pt, nn, nl, ok = real(self, beta, pt)
        if len(calls) >= 4:  # from the fourth solve on (midpoints too): wreck the duals and report failure
            for arr in (*self.lam, *self.y):
                arr.assign(wp.array(np.random.default_rng(1).normal(size=arr.shape) * 10, dtype=wp.float64, device=arr.device))
            pt = self.evaluate(self.lam, self.y, beta)
            ok = False
        return pt, nn, nl, ok

    monkeypatch.setattr(newton.Engine, "newton", flaky)
    with pytest.warns(RuntimeWarning, match="failed at beta=.*the result is that of the last solved beta"):
        r = wo.solve_balanced(C, a, b, device="cpu", method="anneal")
    assert not r.converged and len(r.history) == 3
    assert r.beta == pytest.approx(r.history[-1].beta) and r.cost == pytest.approx(r.history[-1].cost)
    assert abs(r.cost - exact) <= r.history[-1].gap_bound + 1e-9 * exact
    np.testing.assert_allclose(r.mass1, a, atol=1e-9)
    np.testing.assert_allclose(r.mass2, b, atol=1e-9)


def test_a_beta_step_too_long_for_max_newton_is_split_and_still_reaches_the_optimum():
    # Regression: on real 5,000-vertex WKS pairs (TOSCA cat0-cat1, horse0-dog0) the damped Newton solve from
    # beta 2.5e7 to 2.5e8 (normalized), where the plan turns from spread out to a near-permutation, ran out of
    # max_newton = 100 steps, and the result was beta0's, U 3x the optimum. The same happens here with a
    # smaller max_newton; the failed step is now split at its geometric midpoint from the last solved duals.
    ot = pytest.importorskip("ot")
    rng = np.random.default_rng(3)
    X, Y = rng.random((150, 5)), rng.random((150, 5))
    C = np.sqrt(((X[:, None] - Y[None]) ** 2).sum(-1))
    a = np.full(150, 1 / 150)
    exact = ot.emd2(a, a, C)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning: every beta solved
        r = wo.solve_balanced(C, device="cpu", max_newton=8, method="anneal")
    assert r.converged
    assert abs(r.cost - exact) <= r.history[-1].gap_bound + 1e-9 * exact
    betas = np.array([h.beta for h in r.history])
    steps = betas[1:] / betas[:-1]
    assert np.all(steps > 1) and np.any(steps < 9.99)  # a step of the default 10 was split
    assert np.all(np.isclose(np.log10(steps) * 16, np.round(np.log10(steps) * 16)))  # by halvings in log beta


# --------------------------------------------------------------------------- validation
def test_bad_inputs_raise_value_errors_naming_the_problem():
    C = np.random.default_rng(0).random((5, 6))
    bad = C.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        wo.solve_balanced(bad, device="cpu", method="anneal")
    with pytest.raises(ValueError, match="non-negative"):
        wo.solve_balanced(C - 0.5, device="cpu", method="anneal")
    with pytest.raises(ValueError, match="negative entries"):
        wo.solve_balanced(C, np.array([0.5, -0.1, 0.2, 0.2, 0.2]), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="equal total masses"):
        wo.solve_balanced(C, np.full(5, 0.2), np.full(6, 0.2), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="length 4"):
        wo.solve_balanced(C, np.full(4, 0.25), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="2-D"):
        wo.solve_balanced(np.ones(5), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="empty"):
        wo.solve_balanced(np.zeros((0, 3)), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="float64"):
        wo.solve_balanced(wp.array(C, dtype=wp.float32, device="cpu"), device="cpu", method="anneal")
    with pytest.raises(ValueError, match="linear_solver"):
        wo.solve_balanced(C, device="cpu", linear_solver="lu", method="anneal")
    with pytest.raises(ValueError, match="mass_penalty"):
        wo.solve_partial(C, mass_penalty=0.0, device="cpu")
    with pytest.raises(ValueError, match="zero entries"):
        wo.solve_partial(C, np.array([0.5, 0.0, 0.2, 0.2, 0.1]), device="cpu")
    with pytest.raises(ValueError, match="finite"):
        wo.debiased(1.0, np.nan, 0.0)


def test_non_convergence_is_reported():
    C = points_cost(10, 10)
    with pytest.warns(RuntimeWarning, match="max_iter"):
        res = wo.solve_balanced(C, device="cpu", max_iter=1, method="anneal")
    assert not res.converged and len(res.history) == 1
    with pytest.warns(RuntimeWarning, match="Newton"):
        res = wo.solve_partial(C, device="cpu", max_newton=1, method="anneal")
    assert not res.converged


def test_debiased_eq27():
    assert wo.debiased(3.0, 1.0, 2.0) == 1.5


@pytest.mark.parametrize("mode", ["balanced", "ipm", "partial", "matrix-free"])
def test_strided_gpu_kernels_give_the_row_kernels_solution(mode):
    # GPUs run the passes over W as strided lanes (eval_rows in lanes + eval_combine, schur_prep_cols, the Schur matvec
    # as schur_row_partial / schur_row_delta / schur_col_sweep, recover_finish), the CPU as one thread per
    # row. Forced on the CPU with a lane count that divides neither side, the strided kernels must give the
    # same solution up to rounding (stored W and recomputed W), with the same pivots.
    rng = np.random.default_rng(2)
    X, Y = rng.random((41, 4)), rng.random((29, 4))
    a, b = rng.random(41) + 0.2, rng.random(29) + 0.2
    a, b = a / a.sum(), b / b.sum()
    if mode == "matrix-free":
        def solve(**kw):
            return wo.solve_balanced(wo.FeatureCost(X, Y, metric="l2", device="cpu"), a, b, device="cpu", **kw, method="anneal")
    else:
        C = np.linalg.norm(X[:, None] - Y[None], axis=-1)
        if mode in ("balanced", "ipm"):
            def solve(**kw):
                return wo.solve_balanced(C, a, b, device="cpu", method="anneal" if mode == "balanced" else "ipm", **kw)
        else:
            def solve(**kw):
                return wo.solve_partial(C, a, b, mass_penalty=0.05, device="cpu", **kw)
    ref = solve()
    got = solve(matvec_lanes=5)
    assert got.converged and ref.converged
    assert got.cost == pytest.approx(ref.cost, rel=1e-10)
    np.testing.assert_allclose(got.mass1, ref.mass1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.mass2, ref.mass2, rtol=0, atol=1e-12)
    assert np.array_equal(got.argmax, ref.argmax) and got.n_newton == ref.n_newton


@pytest.mark.parametrize("lanes", [1, 5, 64])
def test_strided_evaluation_pass_matches_the_row_pass_entry_for_entry(lanes):
    # eval_rows in 5 or 64 lanes (GPUs) against one lane (the CPU's row scan), each + eval_combine, at one
    # point, with tied weights in some rows: the same sums, and the same pivot (the largest weight, the first column on ties), tail and s there.
    from wpot.ot.anneal import newton
    from wpot.ot.problem import orient, prepare_cost

    rng = np.random.default_rng(4)
    n1, n2 = 70, 23  # rows = the larger side: no transposition, so C's rows are the solver's
    C = 0.1 + rng.random((n1, n2))
    C[3, [5, 11, 20]] = 0.05  # three tied smallest costs: tied largest weights
    C[7, :] = 0.5  # a constant row: every weight tied
    cost = prepare_cost(C, "cpu")

    def engine(matvec_lanes=None):
        opts = wo.SolverOptions(step=10.0, tol=1e-6, atol=0.0, max_iter=100, max_newton=100, newton_tol=1e-10,
                                linear_solver="cg", cg_rtol=1e-10, cg_max_iter=1000, topk=4, extrapolate=True,
                                matvec_lanes=matvec_lanes, verbose=0).normalized(n1, n2, cost.scale)
        prob = orient(cost, np.full(n1, 1 / n1), np.full(n2, 1 / n2), np.zeros(n1), np.zeros(n2), False, "cpu")
        e = newton.Engine(prob, opts)
        e.init_point(rng_duals.normal(size=prob.n_r) * 0.01, np.full(prob.n_c, 0.3))  # equal y: ties stay ties
        return e

    rng_duals = np.random.default_rng(0)
    ref = engine()
    assert ref.lanes == 0 and not ref.p.trans
    pr = ref.evaluate(ref.lam, ref.y, 40.0)
    rng_duals = np.random.default_rng(0)
    got = engine(lanes)
    assert got.lanes == lanes
    pg = got.evaluate(got.lam, got.y, 40.0)
    for name in ("row_g", "col_g", "row_w", "tail", "row_u", "row_xphi", "s_piv"):
        np.testing.assert_allclose(getattr(got, name).numpy(), getattr(ref, name).numpy(), rtol=1e-13, atol=0,
                                   err_msg=name)
    np.testing.assert_array_equal(got.piv.numpy(), ref.piv.numpy())
    assert pg.merit == pytest.approx(pr.merit, rel=1e-12)
