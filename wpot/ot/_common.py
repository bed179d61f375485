"""Option handling shared by `solve_balanced` and `solve_partial`."""
from __future__ import annotations

import math

from wpot.ot.newton import Options
from wpot.ot.schedule import DEFAULT_BETA0_PER_N1N2, DEFAULT_BETA_MAX_PER_N1N2

LINEAR_SOLVERS = ("cg", "direct")
#: weights kept per row and per column of W for the sparse preconditioner. Measured at N = 1000
#: (benchmarks/ot_speed.py problem): 4 needs about as many CG iterations as 8 (508 vs 484 in all; 5 per
#: solve at high beta) with half the LU fill (SuperLU time 42 vs 80 ms); 2 needs ~30% more
DEFAULT_TOPK = 4
#: Newton iterations allowed per beta: the transition from a spread-out plan to a near-permutation takes
#: the most (measured: 29 at N = 1000 and 50 at N = 3400 for the step of 10; 1-6 at the other betas)
DEFAULT_MAX_NEWTON = 100


def make_options(*, n1: int, n2: int, scale: float, beta0, beta_max, step, tol, atol, max_iter, max_newton,
                 newton_tol, linear_solver, cg_rtol, cg_max_iter, topk, extrapolate, verbose) -> Options:
    """Validate the keyword options and convert betas from user units to normalized units (x scale)."""
    if linear_solver not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {linear_solver!r}")
    for name, v in (("tol", tol), ("atol", atol), ("newton_tol", newton_tol), ("cg_rtol", cg_rtol)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    for name, v in (("max_iter", max_iter), ("max_newton", max_newton), ("cg_max_iter", cg_max_iter), ("topk", topk)):
        if not (isinstance(v, int) and v >= 1):
            raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
    nn = float(n1) * float(n2)
    b0 = DEFAULT_BETA0_PER_N1N2 * nn if beta0 is None else float(beta0) * scale
    bm = DEFAULT_BETA_MAX_PER_N1N2 * nn if beta_max is None else float(beta_max) * scale
    if not (math.isfinite(b0) and b0 > 0):
        raise ValueError(f"beta0 must be a positive finite number, got {beta0!r}")
    if not (bm >= b0):
        raise ValueError(f"beta_max must be >= beta0, got beta_max={beta_max!r}, beta0={beta0!r}")
    if not (math.isfinite(float(step)) and float(step) > 1):
        raise ValueError(f"step must be a finite number > 1, got {step!r}")
    return Options(beta0=b0, beta_max=bm, step=float(step), tol=float(tol), atol=float(atol), max_iter=max_iter,
                   max_newton=max_newton, newton_tol=float(newton_tol), linear_solver=linear_solver,
                   cg_rtol=float(cg_rtol), cg_max_iter=cg_max_iter, topk=topk, extrapolate=bool(extrapolate),
                   verbose=int(verbose))
