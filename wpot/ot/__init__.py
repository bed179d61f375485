"""Statistical-physics optimal transport (Koehl & Orland 2023, Sec. 2.4, 2.5, 3.3) in Warp.

`solve_balanced` (Eq. 6-16) and `solve_partial` (Eq. 17-26, Pearson chi^2 mass penalty) anneal the
inverse temperature beta (Algorithm 1) and solve each saddle point by Newton's method, the linear
systems by CG on a Schur complement with a sparse factorized preconditioner (or a dense direct solve).
Balanced transport is by default solved at its limit beta -> infinity, the transport LP, exactly, by column
generation (`wpot.ot.exact.balanced`). The same solvers as objects: a `TransportProblem` solved by a
`TransportSolver` of `make_solver` ("auto", "exact", "anneal", "ipm": an interior-point start),
configured by `SolverOptions`.
Pass a `FeatureCost` (two signature arrays and a metric) instead of C for the matrix-free mode: C is
recomputed inside the kernels and no N1 x N2 array is formed.
"""
from __future__ import annotations

from wpot.ot.options import SolverOptions
from wpot.ot.problem import FeatureCost, TransportProblem
from wpot.ot.result import BetaStep, OTResult, debiased
from wpot.ot.anneal.schedule import beta_schedule
from wpot.ot.solvers import SOLVERS, TransportSolver, make_solver, solve_balanced, solve_batch, solve_partial

__all__ = ["BetaStep", "FeatureCost", "OTResult", "SOLVERS", "SolverOptions", "TransportProblem",
           "TransportSolver", "beta_schedule", "debiased", "make_solver", "solve_balanced", "solve_batch",
           "solve_partial"]
