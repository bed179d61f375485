"""Balanced OT by statistical physics (paper Sec. 2.4, Eq. 6-16, Algorithm 1)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from wpot.ot._common import DEFAULT_MAX_NEWTON, DEFAULT_PLAN_TOPK, DEFAULT_TOPK, check_mode, make_options
from wpot.ot.ipm import ipm_start
from wpot.ot.newton import Engine, warn_not_converged
from wpot.ot.problem import check_balanced, orient, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import BetaStep, OTResult
from wpot.ot.schedule import DEFAULT_STEP

#: default relative change of U that stops the annealing (Algorithm 1). Since U(beta) - U* ~ N1 N2 /
#: beta_n, the change over one step of 10 is ~9x the remaining gap: tol = 1e-6 leaves a gap ~1e-7 (measured
#: <= 2e-7 relative to ot.emd on the tests' and benchmark's problems).
DEFAULT_TOL = 1e-6
#: ways to reach the annealing's later betas (see `solve_balanced`)
METHODS = ("anneal", "ipm")
#: annealing also stops when |Delta U| <= atol * max C (needed when U* = 0, e.g. a shape
#: against itself, where the relative change never falls)
DEFAULT_ATOL = 1e-10


def solve_balanced(
    C,
    a=None,
    b=None,
    *,
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
    method: str = "anneal",
    device: str | None = None,
    verbose: bool = False,
) -> OTResult:
    """Balanced optimal transport min_G sum C G, G >= 0, G 1 = a, G^T 1 = b (Eq. 6-7), by annealing.

    At each beta the saddle point of the free energy (Eq. 12) is found by Newton's method on the duals
    (lam, mu) (Eq. 14-16: G = phi(beta (C + lam + mu)), phi(x) = 1/x - 1/(e^x - 1)), warm-started (and
    extrapolated linearly in 1/beta) from the previous beta; beta is multiplied by ``step`` until the
    relative change of U falls below ``tol`` (Algorithm 1).

    Parameters
    ----------
    C : (N1, N2) float64 numpy array or 2-D float64 ``wp.array`` (used without a copy when on ``device``);
        finite, >= 0; or a `FeatureCost` (signatures and a metric: the matrix-free mode, C recomputed inside
        the kernels, memory O((N1 + N2) D + N topk); same results). Results are in C's units.
    a, b : (N1,), (N2,) positive masses with equal sums (default uniform, 1/N). The plan is computed for
        masses normalized to sum 1 and multiplied back by the total.
    beta0, beta_max : first and largest beta in C's units (beta * C dimensionless). Defaults: beta0 =
        N1 N2 / s and beta_max = 1e12 N1 N2 / s, s = max C (the gap U(beta) - U* is
        ~ N1 N2 / beta, so these are scale- and size-free).
    step : beta multiplier (default 10; see `wpot.ot.schedule.DEFAULT_STEP`).
    tol, atol : stop when |dU| <= tol |U_prev| or |dU| <= atol s. Default tol = 1e-6 gives a gap to the
        exact optimum of ~1e-7 relative.
    max_iter : maximum number of betas; max_newton (default 100), newton_tol : Newton iterations per beta and their
        stopping residual (sum of |marginal errors| / (2 total mass)).
    linear_solver : "cg" (PCG on the Schur complement, sparse top-``topk`` preconditioner, default topk = 4;
        the factorization is reused across Newton steps and betas until CG slows down by more than 2
        iterations) or "direct" (dense Cholesky of the Schur complement, O(N^3) per Newton step; for
        comparison).
    cg_rtol, cg_max_iter : CG relative tolerance and cap per Newton step.
    dense_plan : form ``OTResult.plan`` (N1, N2)? None (default): in stored mode only; True: also with a
        `FeatureCost` (ValueError naming the size when it does not fit in memory); False: never.
    plan_topk : entries per row kept in ``OTResult.plan_top`` (default 8).
    method : "anneal" (default): Algorithm 1 from ``beta0``, every grid beta solved (``history`` has them
        all). "ipm": a primal-dual interior-point method (Mehrotra) follows the same path (for N >= ~50 the
        saddle point at beta is the LP central point with G s = 1/beta) from the product plan to the first
        grid beta whose gap bound N1 N2 / beta is <= 1e-3 U, and Algorithm 1 goes on from there (``history``
        starts at that beta; ``n_newton``/``n_linear`` include the interior-point iterations). Same result
        at convergence, 1.5-2x faster at N >= 1000 (`benchmarks/ot_speed.py`); stored cost only (it keeps
        the primal plan, N1 x N2). See `wpot.ot.ipm`.
    device : Warp device (None: Warp's default).

    Returns
    -------
    OTResult (``x`` = 0, ``objective`` = ``cost``). ``converged`` is False, with a RuntimeWarning, when
    the annealing or a Newton solve did not reach its tolerance.
    """
    dev = resolve_device(device)
    dense = check_mode(C, linear_solver, dense_plan, plan_topk, dev)
    cost = prepare_cost(C, dev)
    a_ = prepare_masses(a, cost.n1, "a")
    b_ = prepare_masses(b, cost.n2, "b")
    total = check_balanced(a_, b_)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "ipm" and cost.lazy:
        raise ValueError("method='ipm' keeps the primal plan (N1 x N2) and needs the stored cost matrix; "
                         "use method='anneal' with a FeatureCost (the matrix-free mode)")
    opts = make_options(n1=cost.n1, n2=cost.n2, scale=cost.scale, beta0=beta0, beta_max=beta_max, step=step,
                        tol=tol, atol=atol, max_iter=max_iter, max_newton=max_newton, newton_tol=newton_tol,
                        linear_solver=linear_solver, cg_rtol=cg_rtol, cg_max_iter=cg_max_iter, topk=topk,
                        extrapolate=extrapolate, verbose=verbose)
    prob = orient(cost, a_ / a_.sum(), b_ / b_.sum(), np.zeros(cost.n1), np.zeros(cost.n2), False, dev)
    eng = Engine(prob, opts)
    n_ipm = (0, 0)
    if method == "ipm":
        beta_h, it, lin, _ = ipm_start(eng)
        opts.beta0 = beta_h  # Algorithm 1 goes on from the hand-off beta, at the interior-point duals
        n_ipm = (it, lin)
    else:
        # start: s = C' + n1 n2 / beta0 (a nearly uniform plan)
        eng.init_point(np.zeros(prob.n_r), np.full(prob.n_c, cost.n1 * cost.n2 / opts.beta0))

    def free_energy(e: Engine, pt, beta):
        lam = e.lam[0].numpy() + e.lam[1].numpy()
        y = e.y[0].numpy() + e.y[1].numpy()
        return -(float(lam @ prob.m_r) + float(y @ prob.m_c)) - pt.f_sum / beta

    info = eng.anneal(free_energy)
    info["n_newton"] += n_ipm[0]
    info["n_linear"] += n_ipm[1]
    return _result(eng, info, total, "solve_balanced", partial=False, dense=dense, plan_topk=plan_topk)


def _result(eng: Engine, info: dict, total: float, kind: str, partial: bool, dense: bool, plan_topk: int
            ) -> OTResult:
    p = eng.p
    s = p.scale
    warn_not_converged(kind, info, p.scale)
    hist = tuple(
        BetaStep(beta=r["beta"] / s, cost=r["u"] * s * total, free_energy=r["f"] * s * total, n_newton=r["nn"],
                 n_linear=r["nl"], residual=r["res"], gap_bound=r["gap"] * s * total,
                 objective=r["obj"] * s * total)
        for r in info["raw"]
    )
    plan = eng.plan() * total if dense else None
    top_val, top_idx = eng.plan_top(plan_topk)
    n1, n2 = (p.n_c, p.n_r) if p.trans else (p.n_r, p.n_c)
    kk = top_val.shape[1]
    plan_top = sp.csr_matrix((top_val.reshape(-1) * total, top_idx.reshape(-1).astype(np.int64),
                              np.arange(0, n1 * kk + 1, kk, dtype=np.int64)), shape=(n1, n2))
    argmax = plan.argmax(axis=1) if plan is not None else top_idx[:, 0].astype(np.int64)
    # the exact marginals of the last evaluation (at the final duals and beta)
    rg, cg = eng.row_g.numpy() * total, eng.col_g.numpy() * total
    mass1, mass2 = (cg, rg) if p.trans else (rg, cg)
    lam = (eng.lam[0].numpy() + eng.lam[1].numpy()) * s
    y = (eng.y[0].numpy() + eng.y[1].numpy()) * s
    x = eng.last.x * s if partial else 0.0
    mu = y - x
    if p.trans:
        lam, mu = mu, lam
    last = info["raw"][-1]
    return OTResult(
        plan=plan,
        plan_top=plan_top,
        argmax=argmax.astype(np.int64),
        cost=last["u"] * s * total,
        objective=last["obj"] * s * total,
        free_energy=last["f"] * s * total,
        lam=lam,
        mu=mu,
        x=float(x),
        mass1=mass1.copy(),
        mass2=mass2.copy(),
        beta=last["beta"] / s,
        converged=bool(info["converged"]),
        n_newton=int(info["n_newton"]),
        n_linear=int(info["n_linear"]),
        history=hist,
    )
