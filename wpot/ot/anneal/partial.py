"""Partial (unbalanced) OT by statistical physics (paper Sec. 2.5, Eq. 17-26, Algorithm 1).

    min_{G >= 0, m1, m2}  sum C G + sum_k alpha1(k) m1(k)^2 + sum_l alpha2(l) m2(l)^2
    s.t. G 1 = m1, G^T 1 = m2, sum G = 1,       alpha_i = mass_penalty / rho_i^2   (Eq. 17-18).

At each beta the saddle point of F (Eq. 23) in (lam, mu, x) is found by Newton's method (Eq. 25-26:
H = phi(beta (C + lam + mu + x)), sum_l H = lam / (2 alpha1), sum_k H = mu / (2 alpha2), sum H = 1); x is
eliminated in closed form. Callers use `wpot.ot.solve_partial` or a solver of `wpot.ot.make_solver`.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from wpot.ot.anneal.loop import anneal
from wpot.ot.anneal.newton import Engine
from wpot.ot.options import SolverOptions, check_mode
from wpot.ot.problem import TransportProblem, orient, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import BetaStep, OTResult, beta_step, build_result


def solve_partial_problem(problem: TransportProblem, options: SolverOptions, *, kind: str = "solve_partial",
                          on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
    """Solve the partial ``problem`` (``mass_penalty`` given; ``a``, ``b`` are the reference measures rho1,
    rho2, normalized to sum 1) by Algorithm 1. ``kind`` names the caller in warnings; ``on_beta`` gets each
    solved beta's `BetaStep` as it is solved."""
    if not problem.partial:
        raise ValueError(f"solve_partial_problem needs a mass_penalty, got {problem!r}")
    mass_penalty = problem.mass_penalty
    dev = resolve_device(problem.device)
    dense = check_mode(problem.cost, options, dev)
    cost = prepare_cost(problem.cost, dev)
    r1 = prepare_masses(problem.a, cost.n1, "rho1")
    r2 = prepare_masses(problem.b, cost.n2, "rho2")
    r1, r2 = r1 / r1.sum(), r2 / r2.sum()
    opts = options.normalized(cost.n1, cost.n2, cost.scale)
    # 1/(2 alpha') with alpha' = alpha / scale (normalized costs)
    b1 = cost.scale * r1 * r1 / (2.0 * mass_penalty)
    a2 = cost.scale * r2 * r2 / (2.0 * mass_penalty)
    prob = orient(cost, np.zeros(cost.n1), np.zeros(cost.n2), b1, a2, True, dev)
    eng = Engine(prob, opts)
    # start from the masses of the large-penalty limit, with s >= n1 n2 / beta0 everywhere
    m_r = prob.b_r / prob.b_r.sum()  # b ~ rho^2: the masses rho^2 / sum rho^2
    m_c = prob.a_c / prob.a_c.sum()
    lam0 = m_r / prob.b_r
    mu0 = m_c / prob.a_c
    x0 = cost.n1 * cost.n2 / opts.beta0 - lam0.min() - mu0.min()
    eng.init_point(lam0, mu0 + x0)

    def free_energy(e: Engine, pt, beta):
        sums = e.dual_sums(pt)
        return -pt.x - 0.5 * sums.b_lam2 - 0.5 * sums.a_mu2 - pt.f_sum / beta

    hook = None if on_beta is None else (lambda r: on_beta(beta_step(r, cost.scale, 1.0)))
    out = anneal(eng, free_energy, on_beta=hook)
    return build_result(eng, out, 1.0, kind, partial=True, dense=dense, plan_topk=options.plan_topk)
