"""Option handling shared by `solve_balanced` and `solve_partial`."""
from __future__ import annotations

import math
import os

import warp as wp

from wpot.ot.newton import Options
from wpot.ot.problem import FeatureCost
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


#: default number of plan entries kept per row in `OTResult.plan_top`
DEFAULT_PLAN_TOPK = 8


def _host_available_bytes() -> float:
    """MemAvailable of /proc/meminfo (Linux); elsewhere the free physical pages; inf when unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def check_mode(C, linear_solver: str, dense_plan, plan_topk, device: str) -> bool:
    """Options that depend on the cost's mode (``C`` as the caller passed it; checked before any pass over
    it); returns whether to form the dense plan.

    ``dense_plan`` None: the dense plan in stored mode only; True: also in matrix-free mode, refused with a
    ValueError naming the size when the (N1, N2) float64 array does not fit in the memory available (on the
    device and on the host, where it is returned); False: never.
    """
    if not (isinstance(plan_topk, int) and not isinstance(plan_topk, bool) and plan_topk >= 1):
        raise ValueError(f"plan_topk must be an integer >= 1, got {plan_topk!r}")
    if dense_plan not in (None, True, False):
        raise ValueError(f"dense_plan must be None, True or False, got {dense_plan!r}")
    lazy = isinstance(C, FeatureCost)
    if lazy and linear_solver == "direct":
        raise ValueError("linear_solver='direct' is not available with a FeatureCost (matrix-free mode): it "
                         "forms the dense N1 x N2 weight matrix the matrix-free mode exists to avoid; use "
                         "linear_solver='cg'")
    if dense_plan is None:
        return not lazy
    if dense_plan and lazy:
        n1, n2 = C.shape
        need = 8.0 * n1 * n2
        avail = _host_available_bytes()
        dev = wp.get_device(device)
        if dev.is_cuda:
            avail = min(avail, float(dev.free_memory))
        if need > avail:
            raise ValueError(
                f"dense_plan=True needs an (N1, N2) = ({n1}, {n2}) float64 array of {need / 2**30:.2f} "
                f"GiB, more than the {avail / 2**30:.2f} GiB available on {device}; use the result's plan_top "
                "and argmax instead")
    return bool(dense_plan)
