"""Balanced OT by statistical physics (paper Sec. 2.4, Eq. 6-16, Algorithm 1).

min_G sum C G, G >= 0, G 1 = a, G^T 1 = b (Eq. 6-7). At each beta the saddle point of the free energy
(Eq. 12) is found by Newton's method on the duals (lam, mu) (Eq. 14-16: G = phi(beta (C + lam + mu)),
phi(x) = 1/x - 1/(e^x - 1)), warm-started (and extrapolated linearly in 1/beta) from the previous beta;
beta is multiplied by ``step`` until the relative change of U falls below ``tol`` (Algorithm 1). The
annealing starts at beta0 from a nearly uniform plan, or at a later beta from the interior-point start
(`wpot.ot.anneal.ipm`). Callers use `wpot.ot.solve_balanced` or a solver of `wpot.ot.make_solver`.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from wpot.ot.anneal.loop import anneal
from wpot.ot.anneal.ipm import ipm_start
from wpot.ot.anneal.newton import Engine
from wpot.ot.options import SolverOptions, check_mode
from wpot.ot.problem import TransportProblem, check_balanced, orient, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import BetaStep, OTResult, beta_step, build_result


def solve_balanced_problem(problem: TransportProblem, options: SolverOptions, *, interior_point: bool = False,
                           kind: str = "solve_balanced", on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
    """Solve the balanced ``problem`` (``mass_penalty`` None) by Algorithm 1, from beta0 or, with
    ``interior_point``, from the hand-off beta of the interior-point start (stored cost only). ``kind``
    names the caller in warnings; ``on_beta`` gets each solved beta's `BetaStep` as it is solved."""
    if problem.partial:
        raise ValueError(f"solve_balanced_problem needs a balanced problem (mass_penalty=None), got {problem!r}")
    if interior_point and problem.matrix_free:
        raise ValueError("method='ipm' keeps the primal plan (N1 x N2) and needs the stored cost matrix; "
                         "use method='anneal' with a FeatureCost (the matrix-free mode)")
    dev = resolve_device(problem.device)
    dense = check_mode(problem.cost, options, dev)
    cost = prepare_cost(problem.cost, dev)
    a_ = prepare_masses(problem.a, cost.n1, "a")
    b_ = prepare_masses(problem.b, cost.n2, "b")
    total = check_balanced(a_, b_)
    opts = options.normalized(cost.n1, cost.n2, cost.scale)
    prob = orient(cost, a_ / a_.sum(), b_ / b_.sum(), np.zeros(cost.n1), np.zeros(cost.n2), False, dev)
    eng = Engine(prob, opts)
    n_ipm = (0, 0)
    beta0 = None
    if interior_point:
        # Algorithm 1 goes on from the hand-off beta, at the interior-point duals
        beta0, it, lin, _ = ipm_start(eng)
        n_ipm = (it, lin)
    else:
        # start: s = C' + n1 n2 / beta0 (a nearly uniform plan)
        eng.init_point(np.zeros(prob.n_r), np.full(prob.n_c, cost.n1 * cost.n2 / opts.beta0))

    def free_energy(e: Engine, pt, beta):
        sums = e.dual_sums(pt)
        return -(sums.lam_m + sums.y_m) - pt.f_sum / beta

    hook = None if on_beta is None else (lambda r: on_beta(beta_step(r, cost.scale, total)))
    out = anneal(eng, free_energy, beta0=beta0, on_beta=hook).add_work(*n_ipm)
    return build_result(eng, out, total, kind, partial=False, dense=dense, plan_topk=options.plan_topk)
