"""The object interface of wpot.ot: `SolverOptions`, `TransportProblem`, the solver registry (`make_solver`,
"anneal" / "ipm" / "auto"), `memory_bytes`, `OTResult.energy_history`, and the function forms' keywords."""
from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

import wpot.ot as wo
from helpers import masses, points_cost


# --------------------------------------------------------------------------- SolverOptions
def test_solver_options_defaults_are_the_function_forms_defaults():
    o = wo.SolverOptions()
    assert o.to_dict() == dict(beta0=None, beta_max=None, step=10.0, tol=1e-6, atol=1e-10, max_iter=100, max_newton=100,
                               newton_tol=1e-11, linear_solver="cg", cg_rtol=1e-3, cg_max_iter=1000, topk=4,
                               extrapolate=True, dense_plan=None, plan_topk=8, matvec_lanes=None, newton_loop=None,
                               device_preconditioner=None,
                               verbose=0)
    # the function forms carry no copy of the defaults: every option comes from SolverOptions
    for fn in (wo.solve_balanced, wo.solve_partial):
        params = set(inspect.signature(fn).parameters)
        assert not params & set(wo.SolverOptions.names())
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.tol = 1.0


@pytest.mark.parametrize("kw,match", [
    (dict(tol=-1.0), "tol must be a finite number >= 0"),
    (dict(atol=float("nan")), "atol must be a finite number >= 0"),
    (dict(max_iter=0), "max_iter must be an integer >= 1"),
    (dict(max_newton=2.5), "max_newton must be an integer >= 1"),
    (dict(topk=True), "topk must be an integer >= 1"),
    (dict(plan_topk=0), "plan_topk"),
    (dict(linear_solver="lu"), "linear_solver must be one of"),
    (dict(step=1.0), "step must be a finite number > 1"),
    (dict(beta0=0.0), "beta0 must be a positive finite number"),
    (dict(beta0=10.0, beta_max=1.0), "beta_max must be >= beta0"),
    (dict(dense_plan="yes"), "dense_plan must be None, True or False"),
    (dict(extrapolate="no"), "extrapolate must be True or False"),
    (dict(matvec_lanes=-1), "matvec_lanes must be an integer >= 0"),
    (dict(verbose=-1), "verbose must be an integer >= 0"),
])
def test_solver_options_are_validated_naming_the_option(kw, match):
    with pytest.raises(ValueError, match=match):
        wo.SolverOptions(**kw)
    with pytest.raises(ValueError, match=match):  # replace validates too
        wo.SolverOptions().replace(**kw)


def test_solver_options_replace_and_dict_round_trip():
    o = wo.SolverOptions(tol=1e-8, max_iter=7, verbose=True, matvec_lanes=0)
    assert o.verbose == 1 and o.matvec_lanes == 0
    assert o.replace(topk=2) == wo.SolverOptions(tol=1e-8, max_iter=7, verbose=1, matvec_lanes=0, topk=2)
    assert wo.SolverOptions.from_dict(o.to_dict()) == o
    assert wo.SolverOptions.from_dict({"tol": 1e-8}) == wo.SolverOptions(tol=1e-8)
    with pytest.raises(ValueError, match=r"unknown solver option\(s\) 'bogus', 'method'; the options are beta0, "):
        wo.SolverOptions.from_dict({"tol": 1e-8, "method": "ipm", "bogus": 1})
    with pytest.raises(TypeError, match="'bogus'"):
        o.replace(bogus=1)


def test_normalized_options_convert_betas_and_are_frozen():
    e = wo.SolverOptions().normalized(30, 40, 2.5)
    assert e.beta0 == 30 * 40 and e.beta_max == 1e12 * 30 * 40  # defaults in units of N1 N2 / max C
    e = wo.SolverOptions(beta0=3.0, beta_max=3e6).normalized(30, 40, 2.5)
    assert e.beta0 == 3.0 * 2.5 and e.beta_max == 3e6 * 2.5
    with pytest.raises(dataclasses.FrozenInstanceError):
        e.beta0 = 1.0
    with pytest.raises(ValueError, match="beta_max must be >= beta0"):  # the default beta0 N1 N2 / s is above it
        wo.SolverOptions(beta_max=1.0).normalized(30, 40, 1.0)


# --------------------------------------------------------------------------- TransportProblem
def test_transport_problem():
    C = np.ones((3, 5))
    p = wo.TransportProblem(C)
    assert not p.partial and not p.matrix_free and p.shape == (3, 5) and p.mass_penalty is None
    q = wo.TransportProblem(C, np.ones(3), None, mass_penalty=2, device="cpu")
    assert q.partial and q.mass_penalty == 2.0 and isinstance(q.mass_penalty, float)
    fc = wo.FeatureCost(np.zeros((4, 2)), np.zeros((6, 2)), "l2", device="cpu")
    assert wo.TransportProblem(fc).matrix_free and wo.TransportProblem(fc).shape == (4, 6)
    for bad in (0.0, -1.0, float("inf"), True):
        with pytest.raises(ValueError, match="mass_penalty must be a positive finite number"):
            wo.TransportProblem(C, mass_penalty=bad)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.cost = None
    assert "3x5" in repr(q) and "partial" in repr(q)


# --------------------------------------------------------------------------- solvers
def test_registry_and_make_solver():
    assert set(wo.SOLVERS) == {"anneal", "ipm", "auto", "exact"}
    for name, cls in wo.SOLVERS.items():
        s = wo.make_solver(name, tol=1e-7)
        assert isinstance(s, cls) and isinstance(s, wo.TransportSolver) and s.name == name
        assert s.options == wo.SolverOptions(tol=1e-7)
    base = wo.SolverOptions(tol=1e-7, topk=2)
    assert wo.make_solver("anneal", base, topk=3).options == wo.SolverOptions(tol=1e-7, topk=3)
    with pytest.raises(ValueError, match=r"method must be one of \('anneal', 'ipm', 'auto', 'exact'\), got 'simplex'"):
        wo.make_solver("simplex")
    with pytest.raises(TypeError, match="'bogus'"):
        wo.make_solver("anneal", bogus=1)
    with pytest.raises(TypeError, match="SolverOptions"):
        wo.make_solver("anneal", {"tol": 1e-7})


def test_function_forms_refuse_unknown_keywords():
    C = points_cost(6, 7)
    with pytest.raises(TypeError, match=r"solve_balanced\(\) got an unexpected keyword argument 'tolerance'"):
        wo.solve_balanced(C, device="cpu", tolerance=1e-3, method="anneal")
    with pytest.raises(TypeError, match=r"solve_partial\(\) got an unexpected keyword argument 'tolerance'"):
        wo.solve_partial(C, device="cpu", tolerance=1e-3)
    with pytest.raises(ValueError, match="method='ipm' solves balanced transport only"):
        wo.solve_partial(C, device="cpu", method="ipm")


def _same(r1: wo.OTResult, r2: wo.OTResult):
    for name in ("cost", "objective", "free_energy", "x", "beta", "converged", "n_newton", "n_linear", "history"):
        assert getattr(r1, name) == getattr(r2, name), name
    for name in ("plan", "argmax", "lam", "mu", "mass1", "mass2"):
        np.testing.assert_array_equal(getattr(r1, name), getattr(r2, name), err_msg=name)


def test_solvers_give_the_function_forms_results_bit_for_bit():
    C = points_cost(30, 45, seed=3)
    a, b = masses(30, 1), masses(45, 2)
    opts = wo.SolverOptions(tol=1e-7, topk=3)
    rb = wo.solve_balanced(C, a, b, device="cpu", tol=1e-7, topk=3, method="anneal")
    _same(wo.make_solver("anneal", opts).solve(wo.TransportProblem(C, a, b, device="cpu")), rb)
    _same(wo.solve_balanced(C, a, b, device="cpu", options=opts, method="anneal"), rb)
    _same(wo.solve_balanced(C, a, b, device="cpu", options=wo.SolverOptions(topk=3), tol=1e-7, method="anneal"), rb)
    ri = wo.solve_balanced(C, a, b, method="ipm", device="cpu")
    _same(wo.make_solver("ipm").solve(wo.TransportProblem(C, a, b, device="cpu")), ri)
    _same(wo.make_solver("auto").solve(wo.TransportProblem(C, a, b, device="cpu")), wo.solve_balanced(C, a, b, device="cpu"))
    _same(wo.make_solver("exact").solve(wo.TransportProblem(C, a, b, device="cpu")), wo.solve_balanced(C, a, b, device="cpu"))
    rp = wo.solve_partial(C, a, b, mass_penalty=0.3, device="cpu", method="anneal")
    _same(wo.make_solver("anneal").solve(wo.TransportProblem(C, a, b, mass_penalty=0.3, device="cpu")), rp)
    re = wo.solve_partial(C, a, b, mass_penalty=0.3, device="cpu")
    _same(wo.make_solver("auto").solve(wo.TransportProblem(C, a, b, mass_penalty=0.3, device="cpu")), re)
    _same(wo.make_solver("exact").solve(wo.TransportProblem(C, a, b, mass_penalty=0.3, device="cpu")), re)


def test_ipm_refuses_partial_and_matrix_free_problems():
    C = points_cost(8, 9)
    with pytest.raises(ValueError, match="ipm.*balanced"):
        wo.make_solver("ipm").solve(wo.TransportProblem(C, mass_penalty=1.0, device="cpu"))
    fc = wo.FeatureCost(np.random.default_rng(0).random((8, 3)), np.random.default_rng(1).random((9, 3)), "l2",
                        device="cpu")
    with pytest.raises(ValueError, match="ipm"):
        wo.make_solver("ipm").solve(wo.TransportProblem(fc, device="cpu"))
    with pytest.raises(TypeError, match="TransportProblem"):
        wo.make_solver("anneal").solve(C)


def test_auto_picks_the_exact_solver_for_balanced_and_partial_transport():
    auto = wo.make_solver("auto")
    big = np.zeros((2000, 2005))  # zero pages: only the shape is read
    assert auto.method_for(wo.TransportProblem(big)) == "exact"
    assert auto.method_for(wo.TransportProblem(big, mass_penalty=1.0)) == "exact"
    fc = wo.FeatureCost(np.zeros((20, 1)), np.zeros((20, 1)), "l1", device="cpu")
    assert auto.method_for(wo.TransportProblem(fc)) == "exact"
    assert auto.method_for(wo.TransportProblem(fc, mass_penalty=1.0)) == "exact"


# --------------------------------------------------------------------------- memory_bytes
def test_memory_bytes_counts_the_quadratic_arrays():
    n1, n2 = 3000, 2000
    nn = 8 * n1 * n2
    anneal, ipm, auto, exact = (wo.make_solver(m) for m in ("anneal", "ipm", "auto", "exact"))
    no_plan = wo.make_solver("anneal", dense_plan=False).memory_bytes(n1, n2)
    assert no_plan > 2 * nn  # C's device copy and W, + the vectors and the preconditioner
    assert anneal.memory_bytes(n1, n2) == no_plan + nn  # + the dense plan
    assert ipm.memory_bytes(n1, n2) > no_plan + 2 * nn  # + the primal plan and the reduced costs
    assert exact.memory_bytes(n1, n2) < no_plan + nn  # C and the plan, no W
    for kw in ({}, {"matrix_free": True, "dim": 10}):  # auto: the exact solver's
        assert auto.memory_bytes(n1, n2, **kw) == exact.memory_bytes(n1, n2, **kw)
    # matrix-free: no (N1, N2) term unless the dense plan is asked for; the features count
    mf = anneal.memory_bytes(n1, n2, matrix_free=True, dim=100)
    assert 8 * (n1 + n2) * 100 < mf < 1.25 * nn  # features, vectors, both loops' preconditioners; stored: C + W
    assert anneal.memory_bytes(n1, n2, matrix_free=True, dim=200) == mf + 8 * (n1 + n2) * 100
    assert wo.make_solver("anneal", dense_plan=True).memory_bytes(n1, n2, matrix_free=True, dim=100) == mf + nn
    assert anneal.memory_bytes(10 * n1, 10 * n2, matrix_free=True, dim=100) < 0.5 * 100 * nn  # below the dense
    # each Newton loop counts its own preconditioner; the device's choice (None) counts both
    host, device = (wo.make_solver("anneal", newton_loop=x).memory_bytes(n1, n2) for x in ("host", "device"))
    from wpot.ot.anneal.resident import FSAI_ROW, device_loop_bytes
    dl = device_loop_bytes(n1, n2, 4, 4)
    assert dl > 2 * 12 * n2 * FSAI_ROW  # FSAI's factor and its transpose at least
    assert anneal.memory_bytes(n1, n2) == host + dl
    assert anneal.memory_bytes(n1, n2) > device + 10 * n2  # the host loop's LU factor, not built by the device loop
    # the direct solver's dense Schur complement
    assert wo.make_solver("anneal", linear_solver="direct").memory_bytes(n1, n2) > anneal.memory_bytes(n1, n2)
    with pytest.raises(ValueError, match="ipm"):
        ipm.memory_bytes(n1, n2, matrix_free=True, dim=10)
    with pytest.raises(ValueError, match="n1 must be an integer >= 1"):
        anneal.memory_bytes(0, 5)


# --------------------------------------------------------------------------- results
def test_energy_history_is_beta_and_objective_per_step():
    C = points_cost(20, 25, seed=2)
    r = wo.solve_balanced(C, device="cpu", method="anneal")
    e = r.energy_history
    assert e.shape == (len(r.history), 2) and e.dtype == np.float64
    np.testing.assert_array_equal(e[:, 0], [h.beta for h in r.history])
    np.testing.assert_array_equal(e[:, 1], [h.cost for h in r.history])  # balanced: objective == cost, bit for bit
    p = wo.solve_partial(C, device="cpu", method="anneal")
    np.testing.assert_array_equal(p.energy_history[:, 1], [h.objective for h in p.history])
    assert p.energy_history[-1, 1] == pytest.approx(p.objective, rel=1e-12)


@pytest.mark.parametrize("method, penalty", [("anneal", None), ("ipm", None), ("auto", None), ("exact", None),
                                             ("auto", 0.05), ("anneal", 0.05)])
def test_on_beta_reports_each_solved_beta_as_the_history_records_it(method, penalty):
    rng = np.random.default_rng(3)
    C = rng.random((40, 30))
    seen = []
    solver = wo.make_solver(method)
    problem = wo.TransportProblem(C, mass_penalty=penalty, device="cpu")
    r = solver.solve(problem, on_beta=seen.append)
    exact = method in ("exact", "auto")  # the LP or the QP: beta = inf alone
    assert r.converged and len(seen) == len(r.history) and (len(seen) == 1 if exact else len(seen) >= 2)
    assert tuple(seen) == r.history  # the same BetaStep values, in the user's units, in order
    assert solver.solve(problem).cost == r.cost  # reporting changes nothing
