"""Exact transport at the annealing's limit beta -> infinity, by column generation (``method="exact"``).

- `wpot.ot.exact.balanced`: the transport LP by POT's network simplex on a growing sparse support, the Warp
  pricing passes over every entry, and the optimality certificate (`ExactRun`);
- `wpot.ot.exact.partial`: the partial chi^2 problem, a convex QP, by Clarabel's interior-point method on the
  same kind of support (`PartialRun`);
- `wpot.ot.exact.solve`: the drivers, one problem (`solve_exact_problem`) or a batch sharing each round's
  pricing launch (`solve_exact_batch`).
"""
from __future__ import annotations

from wpot.ot.exact.balanced import ExactRun, Round, support_bytes
from wpot.ot.exact.partial import PartialRun, qp_bytes
from wpot.ot.exact.solve import exact_run, solve_exact_batch, solve_exact_problem

__all__ = ["ExactRun", "PartialRun", "Round", "exact_run", "qp_bytes", "solve_exact_batch", "solve_exact_problem",
           "support_bytes"]
