"""Exact partial transport (the chi^2 problem of Eq. 17-18 at beta = infinity) by column generation.

    min_{G >= 0, m1, m2}  sum C G + sum_k alpha1(k) m1(k)^2 + sum_l alpha2(l) m2(l)^2
    s.t. G 1 = m1, G^T 1 = m2, sum G = 1,       alpha_i = mass_penalty / rho_i^2,

the limit of the annealing of `wpot.ot.anneal.partial` (its D(infinity)). The plan of this convex QP is sparse (for
its own marginals it is a transport LP's vertex: at most N1 + N2 - 1 nonzeros), so, as for balanced transport
(`wpot.ot.exact.balanced`), the problem is solved on a support S that Warp pricing passes over all N1 N2 entries grow:

1. S0 is each row's and each column's `INIT_K` cheapest entries (any nonempty S is feasible: the masses
   are free).
2. The QP on S is solved by an interior-point method (Clarabel, sparse LDL) in the variables G on S and
   d_i = m_i - w_i, the masses' offsets from w_i = (1 / alpha_i) / sum(1 / alpha_i), the penalty's own
   minimizer under sum m_i = 1: as sum d_i = 0, sum alpha_i m_i^2 = sum alpha_i d_i^2 + c_i with the constant
   c_i = 1 / sum(1 / alpha_i), so the QP's objective stays of the size of the costs even when the penalty is
   huge (unshifted, mass_penalty = 1e6 stalls the method). It gives the plan on S and the duals z1 (N1,),
   z2 (N2,), z3 of the constraints G 1 - d1 = w1, G^T 1 - d2 = w2, sum G = 1, with z1 = 2 alpha1 d1,
   z2 = 2 alpha2 d2 and r(k, l) = C(k, l) + z1(k) + z2(l) + z3 >= 0 on S. (Eq. 26's duals are lam = z1 + 2 c1,
   mu = z2 + 2 c2, x = z3 - 2 (c1 + c2): the same r.)
3. Entries of S whose reduced cost is above `PRUNE_R` leave it (each row keeps its least): they carry no
   mass at the optimum of S, which stays in S, so the rounds' objectives still never increase.
4. One pass (the balanced solver's `price_rows`, at u = -(z1 + z3), v = -z2) lists the entries with
   r < 0, each row's `PRICE_K` most negative of which join S. None: stop.

Certificate (shifted form; the constants c1 + c2 cancel): for any z1, z2, z3 with r >= 0 everywhere the
Lagrangian gives the lower bound L = -w1.z1 - w2.z2 - z3 - sum z1^2 / (4 alpha1) - sum z2^2 / (4 alpha2) <= the
optimum, and z1'(k) = z1(k) - min(0, min_l r(k, l)) makes any duals feasible; the last pass gives those row
minima. The upper bound is the objective of the plan itself (its entries >= 0, renormalized to sum 1, with
m1, m2 its marginals): ``gap_bound`` = U - L.

The interior-point method factorizes a matrix with the bipartite graph of S, whose fill grows with the
graph's cycles: a forest (the optimal plan's support is one) fills nothing, and for random points in R^100
each row's and column's two cheapest entries already form a graph that separates badly. So S is kept close to
the optimal face: one candidate a row and a column to start, `PRICE_K` a row per round, and the entries far
from the face pruned (step 3): a solve on the optimal face is far faster than on each row's and column's 2
cheapest entries, and the whole solve takes less time and memory than with more candidates and no pruning.
Timings: the docs' Results page (`benchmarks/table6.py`, `benchmarks/scale.py`).
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import scipy.sparse as sp

from wpot.ot.exact.balanced import ExactRun, Round, sparse_plan, threshold
from wpot.ot.gram import GramBlocks
from wpot.ot.options import SolverOptions
from wpot.ot.problem import TransportProblem, prepare_masses
from wpot.ot.result import BetaStep, OTResult

__all__ = ["INIT_K", "PRICE_K", "PRUNE_R", "PartialRun", "restricted_qp"]

#: candidates a row and a column in the first support. The interior-point method's factorization grows with
#: the support's cycles (a QP solve's time roughly doubles with each doubling of the candidates a row; the
#: docs' Results page), and the rounds bring in what the first support lacks
INIT_K = 1
#: most negative entries a row that join the support in each pricing round (the balanced solver's network
#: simplex takes 8, `wpot.ot.exact.balanced.PRICE_K`; here each one may close a cycle of the factorized graph)
PRICE_K = 2
#: support entries whose reduced cost (normalized units: costs over max C) is above this leave the support
#: after each solve; far above the pricing threshold (~1e-11), so that an entry pruned comes back only when
#: the duals have moved that much (at 5,000 points a side, 1e-6 made the rounds cycle)
PRUNE_R = 1e-3
#: the interior-point method's tolerances (absolute and relative gap, feasibility): the certificate, not
#: these, decides convergence; they only need to make the duals good enough to price with
_QP_TOL = 1e-11
#: an interior-point plan is positive on every entry of the support: x r ~ the final barrier parameter. An
#: entry whose reduced cost is above `_FACE_R` (normalized units) is outside the optimal face, and one below
#: `_ZERO_REL` of the largest is a residue: both are set to 0 (the certificate is computed on the plan
#: returned, so this cannot hide an error)
_FACE_R = 1e-7
_ZERO_REL = 1e-12
#: Clarabel's settings tried in turn while it stops short of the tolerance (InsufficientProgress), which it did on
#: a few small supports with its own defaults: shorter steps towards the cone's boundary, then no equilibration
#: (the shifted problem is of unit size already)
_QP_RETRIES = ({}, {"max_step_fraction": 0.9}, {"max_step_fraction": 0.9, "equilibrate_enable": False})


def restricted_qp(c: np.ndarray, rows: np.ndarray, cols: np.ndarray, alpha1: np.ndarray, alpha2: np.ndarray,
                  w1: np.ndarray, w2: np.ndarray):
    """The chi^2 problem in the shifted form (the module's step 2) restricted to the entries (``rows``,
    ``cols``) with costs ``c`` (S,), penalties ``alpha1`` (N1,), ``alpha2`` (N2,) and offsets ``w1``, ``w2``:
    (plan values on the entries (S,), z1 (N1,), z2 (N2,), z3), solved by Clarabel. Variables x = (G on S,
    d1, d2); the constraints G 1 - d1 = w1, G^T 1 - d2 = w2, sum G = 1 (zero cone) and G >= 0 (nonnegative
    cone)."""
    import clarabel

    n1, n2, s = len(alpha1), len(alpha2), len(c)
    e = np.arange(s)
    P = sp.diags(np.concatenate([np.zeros(s), 2.0 * alpha1, 2.0 * alpha2])).tocsc()
    q = np.concatenate([c, np.zeros(n1 + n2)])
    A = sp.vstack([
        sp.hstack([sp.csr_matrix((np.ones(s), (rows, e)), shape=(n1, s)), -sp.identity(n1), sp.csr_matrix((n1, n2))]),
        sp.hstack([sp.csr_matrix((np.ones(s), (cols, e)), shape=(n2, s)), sp.csr_matrix((n2, n1)), -sp.identity(n2)]),
        sp.hstack([sp.csr_matrix(np.ones((1, s))), sp.csr_matrix((1, n1 + n2))]),
        sp.hstack([-sp.identity(s), sp.csr_matrix((s, n1 + n2))]),
    ]).tocsc()
    b = np.concatenate([w1, w2, [1.0], np.zeros(s)])
    cones = [clarabel.ZeroConeT(n1 + n2 + 1), clarabel.NonnegativeConeT(s)]
    for retry in _QP_RETRIES:
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = _QP_TOL
        for name, value in retry.items():
            setattr(settings, name, value)
        sol = clarabel.DefaultSolver(P, q, A, b, cones, settings).solve()
        status = str(sol.status)
        if status.endswith("Solved"):  # Solved or AlmostSolved; the certificate judges either
            break
    else:
        raise RuntimeError(f"the partial transport QP on the sparse support failed (Clarabel: {status}); please "
                           "report this problem")
    x, z = np.asarray(sol.x, np.float64), np.asarray(sol.z, np.float64)
    return x[:s], z[:n1], z[n1:n1 + n2], float(z[n1 + n2])


class PartialRun(ExactRun):
    """One partial problem's column generation (see the module's docstring), driven round by round as
    `ExactRun` (the same passes, rounds and drivers: `wpot.ot.exact.solve_exact_problem`,
    `wpot.ot.exact.solve_exact_batch`), with the chi^2 QP on the support and its certificate."""

    init_k = INIT_K
    price_k = PRICE_K

    def __init__(self, problem: TransportProblem, options: SolverOptions, kind: str,
                 on_round: Callable[[Round], None] | None = None, *, gram: bool | GramBlocks | None = None):
        if not problem.partial:
            raise ValueError(f"PartialRun needs a mass_penalty, got {problem!r}")
        self._start(problem, options, kind, on_round, gram)
        cost = self.cost
        r1 = prepare_masses(problem.a, cost.n1, "rho1")
        r2 = prepare_masses(problem.b, cost.n2, "rho2")
        r1, r2 = r1 / r1.sum(), r2 / r2.sum()
        # alpha_i = mass_penalty / rho_i^2 (Eq. 18), divided by max C with the costs (normalized units)
        self.alpha1 = problem.mass_penalty / (r1 * r1) / cost.scale
        self.alpha2 = problem.mass_penalty / (r2 * r2) / cost.scale
        # the penalty's minimizers w_i under sum m_i = 1 and its values there c_i (the shift of step 2)
        self.c1, self.c2 = 1.0 / np.sum(1.0 / self.alpha1), 1.0 / np.sum(1.0 / self.alpha2)
        self.w1, self.w2 = self.c1 / self.alpha1, self.c2 / self.alpha2

    def feasible_entries(self) -> tuple[np.ndarray, np.ndarray]:
        """None needed: the masses are free, so the QP on any nonempty support is feasible."""
        return np.zeros(0, np.int64), np.zeros(0, np.int64)

    def lp(self) -> tuple[np.ndarray, np.ndarray]:
        """Solve the QP on the support; returns the pass's duals u = -(z1 + z3), v = -z2 (r = C' - u - v)."""
        t0 = time.perf_counter()
        cg = self.cg
        self.g, self.z1, self.z2, self.z3 = restricted_qp(cg.c, cg.rows, cg.cols, self.alpha1, self.alpha2,
                                                          self.w1, self.w2)
        self.obj = self._objective(cg.c, np.maximum(self.g, 0.0), cg.rows, cg.cols)[1] + self.c1 + self.c2
        self.u, self.v = -(self.z1 + self.z3), -self.z2
        self.r = cg.reduced(self.u, self.v)  # on the QP's support (later rounds may add entries after it)
        self.thresh = threshold(self.r)
        keep = (self.r <= PRUNE_R) | least_of_each(cg.rows, self.r)
        if not keep.all():
            cg.keep(keep)
            self.g, self.r = self.g[keep], self.r[keep]
        self.t_lp = time.perf_counter() - t0
        return self.u, self.v

    def _objective(self, c: np.ndarray, g: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[float, float]:
        """The transport part sum C G and the shifted objective (without c1 + c2) of the plan ``g`` on the
        entries (``rows``, ``cols``) with costs ``c``, its masses its marginals."""
        d1 = np.bincount(rows, weights=g, minlength=self.cost.n1) - self.w1
        d2 = np.bincount(cols, weights=g, minlength=self.cost.n2) - self.w2
        transport = float(c @ g)
        return transport, transport + float(self.alpha1 @ (d1 * d1)) + float(self.alpha2 @ (d2 * d2))

    def result(self, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """The `OTResult`: the QP's optimum at ``beta`` = inf; ``cost`` = sum C G, ``objective`` (Eq. 17) =
        ``free_energy`` (the entropy term vanishes at beta = inf); one `BetaStep` whose ``gap_bound`` is the
        certified U - L over all entries; ``lam`` = z1, ``mu`` = z2, ``x`` = z3 (Eq. 26's sign: C + lam + mu + x
        >= 0, = 0 where the plan is positive); ``mass1``, ``mass2`` the plan's marginals; ``argmax`` of a row
        with no mass: its entry of least reduced cost over every column (the annealing's largest entry in the limit)."""
        cost = self.cost
        n1, n2 = cost.n1, cost.n2
        s = len(self.g)  # the QP's support: the first s entries (a stop on max_iter has added more since)
        s_rows, s_cols, s_c, r = self.cg.rows[:s], self.cg.cols[:s], self.cg.c[:s], self.r
        g = np.maximum(self.g, 0.0)
        g[(g < _ZERO_REL * g.max()) | (r > _FACE_R)] = 0.0
        g /= g.sum()
        keep = g > 0
        rows, cols, vals = s_rows[keep], s_cols[keep], g[keep]
        m1 = np.bincount(rows, weights=vals, minlength=n1)
        m2 = np.bincount(cols, weights=vals, minlength=n2)
        transport, shifted = self._objective(s_c[keep], vals, rows, cols)
        z1 = self.z1 - np.minimum(self.rmin, 0.0)  # feasible for every entry (the last pass's row minima)
        lower = (-float(self.w1 @ z1) - float(self.w2 @ self.z2) - self.z3
                 - float(np.sum(z1 * z1 / (4.0 * self.alpha1))) - float(np.sum(self.z2 ** 2 / (4.0 * self.alpha2))))
        gap = max(shifted - lower, 0.0)
        primal = shifted + self.c1 + self.c2
        unit = cost.scale
        converged = self.converged(gap, primal, unit)
        U, obj = transport * unit, primal * unit
        # the QP's residual as the annealing's (Eq. 25: sum_l H = lam / (2 alpha1), sum_k H = mu / (2 alpha2))
        resid = 0.5 * float(np.abs(np.bincount(s_rows, weights=self.g, minlength=n1) - self.w1
                                   - self.z1 / (2.0 * self.alpha1)).sum()
                            + np.abs(np.bincount(s_cols, weights=self.g, minlength=n2) - self.w2
                                     - self.z2 / (2.0 * self.alpha2)).sum())
        step = BetaStep(beta=math.inf, cost=U, free_energy=obj, n_newton=0, n_linear=0, residual=resid,
                        gap_bound=gap * unit, objective=obj)
        if on_beta is not None:
            on_beta(step)
        plan, plan_top, argmax = sparse_plan(rows, cols, vals, n1, n2, self.options.plan_topk, self.dense)
        empty = m1 == 0.0
        if empty.any():  # the annealing's largest entry of such a row is in the limit its least reduced cost over
            # every column, which the support may not hold: one pass at the final duals lists it (one a row)
            argmax[empty] = self.cg.price(self.u, self.v, math.inf, 1)[1][empty]
        lam, mu, x = self.z1 + 2.0 * self.c1, self.z2 + 2.0 * self.c2, self.z3 - 2.0 * (self.c1 + self.c2)
        return OTResult(plan=plan, plan_top=plan_top, argmax=argmax, cost=U, objective=obj, free_energy=obj,
                        lam=lam * unit, mu=mu * unit, x=x * unit, mass1=m1, mass2=m2,
                        beta=math.inf, converged=bool(converged), n_newton=0, n_linear=0, history=(step,))


def least_of_each(rows: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Mask (S,) of each row's entry of least ``r`` among the entries (``rows`` (S,), ``r`` (S,))."""
    order = np.lexsort((r, rows))  # each row's entries, least r first
    sorted_rows = rows[order]
    mask = np.zeros(len(rows), bool)
    mask[order[np.concatenate([[True], sorted_rows[1:] != sorted_rows[:-1]])]] = True
    return mask


#: peak bytes per support entry of a QP solve (the KKT matrix, its LDL factor and the method's vectors):
#: the largest growth of the resident set over `restricted_qp` measured (LD-SIFT and WKS at 3,400 x 3,400; the
#: docs' Results page), with a margin
_QP_BYTES_PER_ENTRY = 1536


def qp_bytes(n1: int, n2: int) -> int:
    """Peak bytes of the partial column generation's QP solves apart from C and the plan, for a support of the
    first candidates (`INIT_K` a row and a column) and one full round of `PRICE_K` a row (the rounds after the
    first support add less than one entry a row)."""
    entries = INIT_K * (n1 + n2) + PRICE_K * n1
    return _QP_BYTES_PER_ENTRY * entries + 64 * (n1 + n2)
