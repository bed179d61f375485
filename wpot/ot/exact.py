"""Exact balanced transport by column generation (``method="exact"``, `wpot.ot.solvers.ExactSolver`).

The annealing's limit beta -> infinity is the transport LP (Eq. 6-7): U(beta) - U* ~ N1 N2 / beta. Its
optimal plan has at most N1 + N2 - 1 nonzeros, so the LP is solved on a sparse support S by the dual
simplex method of HiGHS (`highspy`), and S grows until no entry of the whole N1 x N2 cost has a negative
reduced cost:

1. S0 is each row's `INIT_K` cheapest columns (one Warp pass over C), with the north-west-corner plan's
   N1 + N2 - 1 entries, which make the LP on S0 feasible whatever the masses.
2. The LP on S is solved, warm-started from the previous round's basis: the plan x on S and the duals u, v.
3. One Warp pass over all N1 N2 entries (`price_rows`) computes r(k, l) = C(k, l) - u(k) - v(l), each row's
   least r, and its `PRICE_K` most negative entries below -`PRICE_TOL`, which join S. None: stop.

Certificate: for any u, v, the duals u'(k) = u(k) + min(0, min_l r(k, l)) and v are feasible for the dual LP,
so L = sum a u' + sum b v <= U* <= U = sum C x. The last pass gives L over every entry; ``gap_bound`` is
U - L, and the solve has converged when it is <= ``tol`` U + ``atol`` max C.

Costs are computed where the pass needs them (`wpot.ot.kernels.cost_at`), so a `FeatureCost` needs no
N1 x N2 array anywhere: memory is the features and the support, O((N1 + N2) (D + k)). Internally the cost is
C / max C and the masses are scaled to a mean of 1, the units HiGHS's tolerances are meant for.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import warp as wp

from wpot.cost import METRIC_CODES
from wpot.ot import kernels as K
from wpot.ot.options import SolverOptions, check_mode
from wpot.ot.problem import CostInput, TransportProblem, check_balanced, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import BetaStep, OTResult

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["INIT_K", "PRICE_K", "PRICE_TOL", "ColumnGeneration", "solve_exact_problem"]

#: columns per row in the first support (each row's cheapest)
INIT_K = 8
#: most negative entries per row that join the support in each pricing round
PRICE_K = 8
#: an entry prices out when its reduced cost is below -PRICE_TOL (costs divided by max C): ten times HiGHS's
#: dual feasibility tolerance (`_HIGHS_OPTIONS`), so that the LP's own rounding never adds a column
PRICE_TOL = 1e-9
#: presolve off: on the transport LP it costs seconds (3 s at N = 1,000) and the simplex itself 0.1 s
_HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10, "presolve": "off"}
_BIG = 1.0e300


@wp.kernel
def price_rows(
    csrc: Any, n_c: int, u: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64), thresh: wp.float64,
    m: int,
    # outputs: each row's m most negative reduced costs below ``thresh`` (as -r, descending) and their columns
    # (-1 where there are fewer), its least reduced cost and how many entries are below ``thresh``
    neg_r: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32),
    row_min: wp.array(dtype=wp.float64), row_cnt: wp.array(dtype=wp.int32),
):
    """Row k of the pricing pass: r(k, l) = C'(k, l) - u(k) - v(l) over every column l. With u = v = 0 and
    ``thresh`` = +inf it lists each row's m cheapest columns."""
    k = wp.tid()
    for j in range(m):
        neg_r[k, j] = wp.float64(-_BIG)
        idx[k, j] = -1
    worst = wp.float64(-_BIG)
    rmin = wp.float64(_BIG)
    cnt = int(0)
    uk = u[k]
    for l in range(n_c):
        r = K.cost_at(csrc, k, l) - uk - v[l]
        rmin = wp.min(rmin, r)
        if r < thresh:
            cnt += 1
            if -r > worst:
                worst = K.topk_insert(neg_r, idx, k, m, -r, l)
    row_min[k] = rmin
    row_cnt[k] = cnt


@wp.kernel
def gather_cost(csrc: Any, rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
                out: wp.array(dtype=wp.float64)):
    """out[i] = C'(rows[i], cols[i])."""
    i = wp.tid()
    out[i] = K.cost_at(csrc, rows[i], cols[i])


_PRICE = {c: wp.overload(price_rows, {"csrc": c}) for c in (K.DenseCost, K.LazyCost)}
_GATHER = {c: wp.overload(gather_cost, {"csrc": c}) for c in (K.DenseCost, K.LazyCost)}


def cost_source(cost: CostInput):
    """The Warp struct that gives C'(k, l) = C(k, l) / max C in the user's orientation (rows = N1)."""
    if cost.lazy:
        fc = cost.features
        src = K.LazyCost()
        src.A, src.B, src.metric = fc.X, fc.Y, METRIC_CODES[fc.metric]
    else:
        src = K.DenseCost()
        src.C, src.trans = cost.C, 0
    src.inv_scale = wp.float64(1.0 / cost.scale)
    return src


def northwest_corner(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the north-west-corner plan of masses a (N1,), b (N2,) with equal sums: a feasible
    plan on at most N1 + N2 - 1 entries (a staircase from (0, 0) to (N1 - 1, N2 - 1))."""
    ca, cb = np.cumsum(a), np.cumsum(b)
    ca[-1] = cb[-1] = max(ca[-1], cb[-1])
    # the staircase visits (i, j) in the merged order of the two cumulative sums
    ends = np.union1d(ca, cb)
    mids = np.concatenate([[0.0], ends[:-1]]) + 0.5 * np.diff(np.concatenate([[0.0], ends]))
    rows = np.minimum(np.searchsorted(ca, mids, side="right"), len(a) - 1)
    cols = np.minimum(np.searchsorted(cb, mids, side="right"), len(b) - 1)
    return rows, cols


#: bytes per support entry: its row, column and cost here, and HiGHS's column (bounds, cost, two nonzeros,
#: basis status, solution and dual values, and the simplex's work copies)
_BYTES_PER_ENTRY = 160


def support_bytes(n1: int, n2: int) -> int:
    """Bytes of the column generation apart from C and the plan: the pricing pass's lists and the support,
    taken as the first support (INIT_K a row, the north-west corner) and two full rounds of PRICE_K a row (the
    first round adds about PRICE_K a row, the later ones a few in all: 17.4 a row at N = 10,000)."""
    entries = (INIT_K + 2 * PRICE_K) * n1 + n1 + n2
    return _BYTES_PER_ENTRY * entries + 12 * (max(INIT_K, PRICE_K) + 2) * n1 + 64 * (n1 + n2)


@dataclass(frozen=True)
class Round:
    """One pricing round: the LP's objective on the support (normalized units), the support's size, the
    entries priced out (below -PRICE_TOL), the least reduced cost over all N1 N2 entries, seconds in the LP
    and in the pass, and the host-device transfers since the previous round (device-to-host reads are the
    synchronisations on a GPU: the pass's results and the new entries' costs; host-to-device writes: the
    duals and the new entries' indices)."""

    objective: float
    support: int
    violations: int
    min_reduced: float
    t_lp: float
    t_price: float
    n_d2h: int = 0
    n_h2d: int = 0


def _quiet_highs(highspy):
    """A HiGHS model that prints nothing. highspy's constructor enables its callbacks, which logs the HiGHS
    banner before any option can be set; the solver here uses no callback, so the core is built alone and its
    output turned off first."""
    h = highspy.Highs.__new__(highspy.Highs)
    super(highspy.Highs, h).__init__()
    h.setOptionValue("output_flag", False)
    return h


class ColumnGeneration:
    """The column-generation state of one problem: the device arrays of the pricing pass and the HiGHS model
    (its basis carries over from round to round). ``cost`` from `prepare_cost`; ``a``, ``b`` masses scaled
    to a mean of 1 and equal sums."""

    def __init__(self, cost: CostInput, a: np.ndarray, b: np.ndarray, device: str):
        import highspy

        self.cost, self.a, self.b, self.device = cost, a, b, device
        self.n1, self.n2 = cost.n1, cost.n2
        self.src = cost_source(cost)
        self.kernel = _PRICE[self.src._cls]
        self._highspy = highspy
        h = _quiet_highs(highspy)
        for key, val in _HIGHS_OPTIONS.items():
            h.setOptionValue(key, val)
        rhs = np.concatenate([a, b])
        empty_i, empty_f = np.zeros(0, np.int32), np.zeros(0, np.float64)
        h.addRows(self.n1 + self.n2, rhs, rhs, 0, empty_i, empty_i, empty_f)
        self.h = h
        self.rows = np.zeros(0, np.int64)
        self.cols = np.zeros(0, np.int64)
        self.c = np.zeros(0, np.float64)  # C' on the support
        self.n_d2h = self.n_h2d = 0  # host-device transfers (see `Round`)
        self._known = np.zeros(0, np.int64)  # sorted keys row * n2 + col of the support

    # ------------------------------------------------------------------ the pass over all entries
    def price(self, u: np.ndarray, v: np.ndarray, thresh: float, m: int):
        """(candidate rows, candidate columns, row minima, count below thresh) of a pass at duals u, v."""
        d = self.device
        n1, m = self.n1, max(1, min(m, self.n2))
        neg = wp.empty((n1, m), dtype=wp.float64, device=d)
        idx = wp.empty((n1, m), dtype=wp.int32, device=d)
        rmin = wp.empty(n1, dtype=wp.float64, device=d)
        rcnt = wp.empty(n1, dtype=wp.int32, device=d)
        wp.launch(self.kernel, dim=n1, device=d,
                  inputs=[self.src, self.n2, wp.array(u, dtype=wp.float64, device=d),
                          wp.array(v, dtype=wp.float64, device=d), wp.float64(thresh), m, neg, idx, rmin, rcnt])
        self.n_h2d += 2
        self.n_d2h += 3
        cols = idx.numpy()
        ok = cols >= 0
        rows = np.broadcast_to(np.arange(n1)[:, None], cols.shape)[ok]
        return rows.astype(np.int64), cols[ok].astype(np.int64), rmin.numpy(), int(rcnt.numpy().sum())

    def cost_of(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """C'(k, l) of the listed entries (normalized units), computed by the kernels' own cost function."""
        d = self.device
        out = wp.empty(len(rows), dtype=wp.float64, device=d)
        wp.launch(_GATHER[self.src._cls], dim=len(rows), device=d,
                  inputs=[self.src, wp.array(rows.astype(np.int32), dtype=wp.int32, device=d),
                          wp.array(cols.astype(np.int32), dtype=wp.int32, device=d), out])
        self.n_h2d += 2
        self.n_d2h += 1
        return out.numpy()

    # ------------------------------------------------------------------ the LP on the support
    def add(self, rows: np.ndarray, cols: np.ndarray) -> int:
        """Add the entries not yet in the support as LP columns; returns how many were new."""
        key = np.unique(rows * self.n2 + cols)
        key = key[~np.isin(key, self._known, assume_unique=True)]
        if len(key) == 0:
            return 0
        r, c = key // self.n2, key % self.n2
        m = len(key)
        starts = np.arange(0, 2 * m, 2, dtype=np.int32)
        index = np.empty(2 * m, np.int32)
        index[0::2], index[1::2] = r, self.n1 + c
        inf = self._highspy.kHighsInf
        c_rc = self.cost_of(r, c)
        self.h.addCols(m, c_rc, np.zeros(m), np.full(m, inf), 2 * m, starts, index, np.ones(2 * m))
        self.rows = np.concatenate([self.rows, r])
        self.cols = np.concatenate([self.cols, c])
        self.c = np.concatenate([self.c, c_rc])
        self._known = np.union1d(self._known, key)
        return m

    def solve_lp(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Solve the LP on the support: (x on the support, u (N1,), v (N2,), objective)."""
        h = self.h
        h.run()
        status = h.getModelStatus()
        if status != self._highspy.HighsModelStatus.kOptimal:
            raise RuntimeError(f"the transport LP on the sparse support ended with HiGHS status "
                               f"{h.modelStatusToString(status)}; please report this problem")
        sol = h.getSolution()
        x = np.maximum(np.asarray(sol.col_value, dtype=np.float64), 0.0)
        dual = np.asarray(sol.row_dual, dtype=np.float64)
        return x, dual[:self.n1], dual[self.n1:], float(h.getInfo().objective_function_value)


def solve_exact_problem(problem: TransportProblem, options: SolverOptions, *, kind: str = "solve_balanced",
                        on_beta: Callable[[BetaStep], None] | None = None,
                        on_round: Callable[[Round], None] | None = None) -> OTResult:
    """Solve the balanced ``problem`` exactly by column generation (see the module's docstring).

    The result is the LP's optimum: ``beta`` = inf, ``cost`` = ``objective`` = ``free_energy`` = U (the
    entropy term vanishes at beta = inf), one `BetaStep` in ``history`` whose ``gap_bound`` is the certified
    U - L over all entries, ``n_newton`` = ``n_linear`` = 0, ``lam`` = -u and ``mu`` = -v (the sign of
    Eq. 15: C + lam + mu >= 0, = 0 on the plan's support). ``on_round`` gets each pricing round's `Round`."""
    if problem.partial:
        raise ValueError("method='exact' solves balanced transport only (mass_penalty=None); use method='anneal' "
                         "for partial transport")
    dev = resolve_device(problem.device)
    dense = check_mode(problem.cost, options, dev)
    cost = prepare_cost(problem.cost, dev)
    n1, n2 = cost.n1, cost.n2
    a_ = prepare_masses(problem.a, n1, "a")
    b_ = prepare_masses(problem.b, n2, "b")
    total = check_balanced(a_, b_)
    f = max(n1, n2) / total  # masses with mean ~1 (HiGHS's tolerances are absolute)
    a, b = a_ * f, b_ * f
    b *= a.sum() / b.sum()

    cg = ColumnGeneration(cost, a, b, dev)
    zero1, zero2 = np.zeros(n1), np.zeros(n2)
    r0, c0, _, _ = cg.price(zero1, zero2, math.inf, INIT_K)
    nw_r, nw_c = northwest_corner(a, b)
    cg.add(np.concatenate([r0, nw_r]), np.concatenate([c0, nw_c]))
    converged = False
    seen = (0, 0)
    for _ in range(options.max_iter):
        t0 = time.perf_counter()
        x, u, v, obj = cg.solve_lp()
        t1 = time.perf_counter()
        rr, cc, rmin, nviol = cg.price(u, v, -PRICE_TOL, PRICE_K)
        t2 = time.perf_counter()
        rnd = Round(obj, len(cg.rows), nviol, float(rmin.min()), t1 - t0, t2 - t1,
                    cg.n_d2h - seen[0], cg.n_h2d - seen[1])
        seen = (cg.n_d2h, cg.n_h2d)
        if on_round is not None:
            on_round(rnd)
        if options.verbose:
            print(f"  exact: LP {obj:.12g} on {rnd.support} entries, {nviol} priced out (min r {rnd.min_reduced:.2e}), "
                  f"LP {rnd.t_lp:.2f} s, pass {rnd.t_price:.2f} s")
        if nviol == 0 or cg.add(rr, cc) == 0:
            converged = nviol == 0
            break
    # the certificate over every entry, from the last pass
    n_x = len(x)  # the support the last LP was solved on (a last round may have added columns after it)
    primal = float(cg.c[:n_x] @ x)
    lower = float(a @ (u + np.minimum(rmin, 0.0)) + b @ v)
    gap = max(primal - lower, 0.0)
    # tol relative to U, atol a fraction of max C per unit of mass (as the annealing's)
    converged = converged and gap <= options.tol * abs(primal) + options.atol * a.sum()
    unit = cost.scale / f  # normalized objective -> user units
    keep = x > 0
    rows, cols, vals = cg.rows[:n_x][keep], cg.cols[:n_x][keep], x[keep] / f
    mass1 = np.bincount(rows, weights=vals, minlength=n1)
    mass2 = np.bincount(cols, weights=vals, minlength=n2)
    resid = 0.5 * (np.abs(mass1 - a_).sum() + np.abs(mass2 - b_).sum()) / total
    U = primal * unit
    step = BetaStep(beta=math.inf, cost=U, free_energy=U, n_newton=0, n_linear=0, residual=float(resid),
                    gap_bound=gap * unit, objective=U)
    if on_beta is not None:
        on_beta(step)
    if not converged:
        import warnings

        warnings.warn(f"{kind}: the exact solve stopped after max_iter={options.max_iter} pricing rounds with a "
                      f"certified gap of {gap * unit:.3g} (cost units), above tol; increase max_iter", RuntimeWarning,
                      stacklevel=3)
    order = np.lexsort((-vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    start = np.searchsorted(rows, np.arange(n1 + 1))
    rank = np.arange(len(rows)) - start[rows]
    top = rank < options.plan_topk
    counts = np.bincount(rows[top], minlength=n1)
    plan_top = sp.csr_matrix((vals[top], cols[top], np.concatenate([[0], np.cumsum(counts)])), shape=(n1, n2))
    argmax = cols[start[:-1]]
    plan = None
    if dense:
        plan = np.zeros((n1, n2))
        plan[rows, cols] = vals
    return OTResult(plan=plan, plan_top=plan_top, argmax=argmax.astype(np.int64), cost=U, objective=U,
                    free_energy=U, lam=-u * cost.scale, mu=-v * cost.scale, x=0.0, mass1=mass1, mass2=mass2,
                    beta=math.inf, converged=bool(converged), n_newton=0, n_linear=0, history=(step,))
