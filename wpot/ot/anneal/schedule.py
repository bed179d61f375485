"""The beta annealing schedule of Algorithm 1 as pure functions (testable alone).

The solver works on a cost normalized to max 1 (``beta_n = beta * scale``). For these problems the
mean-field plan has every entry in the 1/x tail of phi, so the gap U(beta) - U* is very nearly
N1 * N2 / beta_n (in units of max C). Defaults are therefore expressed through N1 * N2.
"""
from __future__ import annotations

import math

import numpy as np

#: default multiplicative step of beta. With the 1/beta extrapolation of the duals, 10 needs a few Newton steps
#: per beta, except at the one or two betas where the plan goes from spread out to a near-permutation (damped
#: steps), and fewer Newton steps in all than sqrt(10) or 10**0.25 (the paper's and the authors' code's values;
#: benchmarks/ot_speed.py, figures on the docs' Results page).
DEFAULT_STEP = 10.0
#: default first beta, in units of N1*N2 / max(C): the plan is then close to uniform and Newton from
#: the uniform start converges in a few steps
DEFAULT_BETA0_PER_N1N2 = 1.0
#: default cap on beta in units of N1*N2 / max(C): the gap scale N1*N2/beta is then 1e-12 of max(C)
DEFAULT_BETA_MAX_PER_N1N2 = 1e12


def beta_schedule(beta0: float, step: float, beta_max: float) -> np.ndarray:
    """The betas of Algorithm 1: beta0, beta0*step, beta0*step^2, ..., the last one <= beta_max.

    beta0 > 0, step > 1, beta_max >= beta0; returns a (K,) float64 array (K >= 1).
    """
    beta0, step, beta_max = float(beta0), float(step), float(beta_max)
    if not (math.isfinite(beta0) and beta0 > 0):
        raise ValueError(f"beta0 must be a positive finite number, got {beta0}")
    if not (math.isfinite(step) and step > 1):
        raise ValueError(f"step must be a finite number > 1, got {step}")
    if not (beta_max >= beta0):
        raise ValueError(f"beta_max must be >= beta0, got beta_max={beta_max}, beta0={beta0}")
    n = int(math.floor(math.log(beta_max / beta0) / math.log(step) + 1e-9)) + 1
    return beta0 * step ** np.arange(n, dtype=np.float64)


def relative_change(u_prev: float, u_cur: float) -> float:
    """|U(beta_k) - U(beta_{k-1})| / |U(beta_{k-1})| (Algorithm 1, step 4); inf when U(beta_{k-1}) = 0."""
    if u_prev == 0.0:
        return 0.0 if u_cur == 0.0 else math.inf
    return abs(u_cur - u_prev) / abs(u_prev)
