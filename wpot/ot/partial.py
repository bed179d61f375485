"""Partial (unbalanced) OT by statistical physics (paper Sec. 2.5, Eq. 17-26, Algorithm 1)."""
from __future__ import annotations

import math

import numpy as np

from wpot.ot._common import DEFAULT_MAX_NEWTON, DEFAULT_PLAN_TOPK, DEFAULT_TOPK, check_mode, make_options
from wpot.ot.balanced import DEFAULT_ATOL, DEFAULT_TOL, _result
from wpot.ot.newton import Engine
from wpot.ot.problem import orient, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import OTResult
from wpot.ot.schedule import DEFAULT_STEP


def solve_partial(
    C,
    rho1=None,
    rho2=None,
    *,
    mass_penalty: float = 1.0,
    beta0: float | None = None,
    beta_max: float | None = None,
    step: float = DEFAULT_STEP,
    tol: float = DEFAULT_TOL,
    atol: float = DEFAULT_ATOL,
    max_iter: int = 100,
    max_newton: int = DEFAULT_MAX_NEWTON,
    newton_tol: float = 1e-11,
    linear_solver: str = "cg",
    cg_rtol: float = 1e-3,
    cg_max_iter: int = 1000,
    topk: int = DEFAULT_TOPK,
    extrapolate: bool = True,
    dense_plan: bool | None = None,
    plan_topk: int = DEFAULT_PLAN_TOPK,
    device: str | None = None,
    verbose: bool = False,
) -> OTResult:
    """Partial OT with a Pearson chi^2 mass penalty (Eq. 17-18), by annealing:

        min_{G >= 0, m1, m2}  sum C G + sum_k alpha1(k) m1(k)^2 + sum_l alpha2(l) m2(l)^2
        s.t. G 1 = m1, G^T 1 = m2, sum G = 1,       alpha_i = mass_penalty / rho_i^2.

    ``mass_penalty = 1`` is exactly the paper's formulation. At each beta the saddle point of F
    (Eq. 23) in (lam, mu, x) is found by Newton's method (Eq. 25-26: H = phi(beta (C + lam + mu + x)),
    sum_l H = lam / (2 alpha1), sum_k H = mu / (2 alpha2), sum H = 1); x is eliminated in closed form.

    Note: as mass_penalty grows the masses tend to rho^2 / sum rho^2 (the minimizer of the penalty under
    sum m = 1), not to rho: a huge mass_penalty recovers the balanced problem with those masses (the
    same as rho when rho is uniform).

    Parameters are those of `solve_balanced` (same defaults and units; ``C`` may be a `FeatureCost` for the
    matrix-free mode, ``dense_plan`` and ``plan_topk`` choose the returned plan), with rho1 (N1,), rho2 (N2,)
    positive reference measures (default uniform; normalized to sum 1) instead of a, b.

    Returns OTResult with ``mass1``, ``mass2`` the plan's marginals (sum 1 together), ``cost`` the
    transport part sum C G, ``objective`` Eq. 17 (cost + penalty), ``free_energy`` Eq. 23, ``x``.
    """
    if not (isinstance(mass_penalty, (int, float)) and math.isfinite(mass_penalty) and mass_penalty > 0):
        raise ValueError(f"mass_penalty must be a positive finite number, got {mass_penalty!r}")
    dev = resolve_device(device)
    dense = check_mode(C, linear_solver, dense_plan, plan_topk, dev)
    cost = prepare_cost(C, dev)
    r1 = prepare_masses(rho1, cost.n1, "rho1")
    r2 = prepare_masses(rho2, cost.n2, "rho2")
    r1, r2 = r1 / r1.sum(), r2 / r2.sum()
    opts = make_options(n1=cost.n1, n2=cost.n2, scale=cost.scale, beta0=beta0, beta_max=beta_max, step=step,
                        tol=tol, atol=atol, max_iter=max_iter, max_newton=max_newton, newton_tol=newton_tol,
                        linear_solver=linear_solver, cg_rtol=cg_rtol, cg_max_iter=cg_max_iter, topk=topk,
                        extrapolate=extrapolate, verbose=verbose)
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
        lam = e.lam[0].numpy() + e.lam[1].numpy()
        mu = e.y[0].numpy() + e.y[1].numpy() - pt.x
        return (-pt.x - 0.5 * float(prob.b_r @ (lam * lam)) - 0.5 * float(prob.a_c @ (mu * mu))
                - pt.f_sum / beta)

    info = eng.anneal(free_energy)
    return _result(eng, info, 1.0, "solve_partial", partial=True, dense=dense, plan_topk=plan_topk)
