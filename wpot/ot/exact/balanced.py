"""Exact balanced transport by column generation (``method="exact"``, `wpot.ot.solvers.ExactSolver`).

The annealing's limit beta -> infinity is the transport LP (Eq. 6-7): U(beta) - U* ~ N1 N2 / beta. Its
optimal plan has at most N1 + N2 - 1 nonzeros, so the LP is solved on a sparse support S by the network
simplex method (POT's, on the bipartite graph of S: `ot.emd` with a sparse cost), and S grows until no entry
of the whole N1 x N2 cost has a negative reduced cost:

1. S0 is each row's and each column's `INIT_K` cheapest entries (two Warp passes over C), with the
   north-west-corner plan's N1 + N2 - 1 entries, which make the LP on S0 feasible whatever the masses.
2. The LP on S is solved, warm-started from the previous round's duals: the plan x on S and the duals u, v.
3. One Warp pass over all N1 N2 entries (`price_rows`) computes r(k, l) = C(k, l) - u(k) - v(l), each row's
   least r, and its `PRICE_K` most negative entries below a threshold (-`PRICE_TOL`, or the duals' rounding
   if that is more), which join S. None: stop.

Many problems can share each round's pass in one launch (`solve_exact_batch`, `price_rows_batch`), with the
same results as alone.

Certificate: for any u, v, the duals u'(k) = u(k) + min(0, min_l r(k, l)) and v are feasible for the dual LP,
so L = sum a u' + sum b v <= U* <= U = sum C x. The last pass gives L over every entry; ``gap_bound`` is
U - L, and the solve has converged when it is <= ``tol`` U + ``atol`` max C.

Costs are computed where the pass needs them (`wpot.ot.kernels.cost_at`), so a `FeatureCost` needs no
N1 x N2 array anywhere: memory is the features and the support, O((N1 + N2) (D + k)). Internally the cost is
C / max C and the masses sum to 1.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import warp as wp

from wpot._warp import launch_rows
from wpot.cost import METRIC_CODES
from wpot.ot import kernels as K
from wpot.ot.gram import GramBlocks, gram_blocks, sq_bounds
from wpot.ot.options import SolverOptions, check_mode
from wpot.ot.problem import CostInput, TransportProblem, check_balanced, prepare_cost, prepare_masses, resolve_device
from wpot.ot.result import BetaStep, OTResult

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["INIT_K", "PRICE_K", "PRICE_TOL", "ROUNDING_MARGIN", "ColumnGeneration", "ExactRun", "Round"]

#: entries per row and per column in the first support (each row's and column's cheapest)
INIT_K = 8
#: most negative entries per row that join the support in each pricing round
PRICE_K = 8
#: an entry prices out when its reduced cost is below -PRICE_TOL (costs divided by max C), or below
#: -ROUNDING_MARGIN times the largest |reduced cost| on the LP's own support where that is more: the network
#: simplex's duals are exact only to their rounding, which grows with the problem (its support's reduced costs
#: fall below -PRICE_TOL at large N; the docs' Results page), and support entries listed again crowd new ones out
PRICE_TOL = 1e-11
ROUNDING_MARGIN = 4.0
#: network simplex iterations allowed per LP (POT's default of 1e5 stops early on problems of a few thousand
#: points a side)
_LP_MAX_ITER = 10**9
_BIG = 1.0e300
#: `price_rows_gram` recomputes an entry exactly where its reduced cost's lower bound is below this (normalized
#: units: far above the rounding of C' - u - v, ~1e-16, and far below any reduced cost that matters)
_GRAM_GUARD = wp.constant(wp.float64(1e-12))


@wp.func
def start_row(neg_r: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32), g: int, m: int):
    """Clear row g's kept list; returns a scan's starting (smallest -r kept, row minimum, count)."""
    for j in range(m):
        neg_r[g, j] = wp.float64(-_BIG)
        idx[g, j] = -1
    return wp.float64(-_BIG), wp.float64(_BIG), int(0)


@wp.func
def price_entry(r: wp.float64, l: int, thresh: wp.float64, neg_r: wp.array2d(dtype=wp.float64),
                idx: wp.array2d(dtype=wp.int32), g: int, m: int, worst: wp.float64, rmin: wp.float64, cnt: int):
    """One entry (reduced cost r, column l) of row g's scan: returns the updated (smallest -r kept, row
    minimum, count below ``thresh``)."""
    rmin = wp.min(rmin, r)
    if r < thresh:
        cnt += 1
        if -r > worst:
            worst = K.topk_insert(neg_r, idx, g, m, -r, l)
    return worst, rmin, cnt


@wp.kernel
def price_rows(
    csrc: Any, k0: int, n_c: int, u: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64),
    thresh: wp.float64, m: int,
    # outputs: each row's m most negative reduced costs below ``thresh`` (as -r, descending) and their columns
    # (-1 where there are fewer), its least reduced cost and how many entries are below ``thresh``
    neg_r: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32),
    row_min: wp.array(dtype=wp.float64), row_cnt: wp.array(dtype=wp.int32),
):
    """Row k = k0 + i of the pricing pass: r(k, l) = C'(k, l) - u(k) - v(l) over every column l. With u = v = 0
    and ``thresh`` = +inf it lists each row's m cheapest columns."""
    k = k0 + wp.tid()
    worst, rmin, cnt = start_row(neg_r, idx, k, m)
    uk = u[k]
    for l in range(n_c):
        worst, rmin, cnt = price_entry(K.cost_at(csrc, k, l) - uk - v[l], l, thresh, neg_r, idx, k, m, worst, rmin, cnt)
    row_min[k] = rmin
    row_cnt[k] = cnt


@wp.kernel
def price_rows_batch(
    g0: int, C: wp.array(dtype=wp.float64), off: wp.array(dtype=wp.int64), n1s: wp.array(dtype=wp.int32),
    n2s: wp.array(dtype=wp.int32), inv_scale: wp.array(dtype=wp.float64), trans: int,
    row_prob: wp.array(dtype=wp.int32), row_local: wp.array(dtype=wp.int32),
    u: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64), v_off: wp.array(dtype=wp.int32),
    thresh: wp.array(dtype=wp.float64), m: int,
    neg_r: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32),
    row_min: wp.array(dtype=wp.float64), row_cnt: wp.array(dtype=wp.int32),
):
    """`price_rows` for many problems in one launch: row g = g0 + i of the launch is row ``row_local[g]`` of
    problem ``row_prob[g]``, whose (N1, N2) cost starts at ``off[p]`` of the flat ``C``; with ``trans`` the
    rows are the problems' columns. u is given per launch row, v per problem from ``v_off[p]``, ``thresh``
    per problem. The same operations in the same order as `price_rows` on each problem alone."""
    g = g0 + wp.tid()
    p = row_prob[g]
    k = row_local[g]
    n2 = n2s[p]
    n = n2
    if trans != 0:
        n = n1s[p]
    worst, rmin, cnt = start_row(neg_r, idx, g, m)
    ug = u[g]
    vo = v_off[p]
    base = off[p]
    s = inv_scale[p]
    th = thresh[p]
    for l in range(n):
        e = base + wp.int64(k) * wp.int64(n2) + wp.int64(l)
        if trans != 0:
            e = base + wp.int64(l) * wp.int64(n2) + wp.int64(k)
        worst, rmin, cnt = price_entry(C[e] * s - ug - v[vo + l], l, th, neg_r, idx, g, m, worst, rmin, cnt)
    row_min[g] = rmin
    row_cnt[g] = cnt


@wp.kernel
def gather_cost(csrc: Any, rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
                out: wp.array(dtype=wp.float64)):
    """out[i] = C'(rows[i], cols[i])."""
    i = wp.tid()
    out[i] = K.cost_at(csrc, rows[i], cols[i])


@wp.kernel
def price_rows_gram(
    P: wp.array2d(dtype=wp.float64), k0: int, src: K.LazyCost, n_c: int, a2: wp.array(dtype=wp.float64),
    b2: wp.array(dtype=wp.float64), an: wp.array(dtype=wp.float64), bn: wp.array(dtype=wp.float64),
    err: wp.float64, u: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64), thresh: wp.float64, m: int,
    neg_r: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32),
    row_min: wp.array(dtype=wp.float64), row_cnt: wp.array(dtype=wp.int32),
):
    """`price_rows` for rows k0 + i of a Euclidean `FeatureCost` on the CPU, from a block P of the Gram matrix
    (`wpot.ot.gram.GramBlocks`), which bounds each entry's C'(k, l)^2 from below (no square root is taken).
    Only where the bound could matter is the entry recomputed exactly by `cost_at`: where its reduced cost may
    be below `_GRAM_GUARD` (a candidate, or a negative row minimum) or, with ``thresh`` = +inf, may enter the
    row's top-m list. So the outputs are `price_rows`'s, except row minima >= `_GRAM_GUARD` (then
    `_GRAM_GUARD`, a lower bound). Valid for ``thresh`` <= 0 or +inf."""
    i = wp.tid()
    k = k0 + i
    worst, rmin, cnt = start_row(neg_r, idx, k, m)
    uk = u[k]
    ak2 = a2[k]
    ak = an[k]
    inv2 = src.inv_scale * src.inv_scale
    ug = uk + _GRAM_GUARD
    every = thresh > wp.float64(_BIG)  # thresh = +inf: every entry counts, the top m are wanted
    skipped = int(0)
    for l in range(n_c):
        lo2, hi2 = sq_bounds(P, i, l, ak2, ak, b2, bn, err)
        d2 = lo2 * inv2  # <= C'(k, l)^2
        vl = v[l]
        t = ug + vl  # r < guard  <=>  C' < t
        need = t > wp.float64(0.0) and d2 < t * t
        if every and not need:
            t = uk + vl - worst  # -r > worst  <=>  C' < t
            need = t > wp.float64(0.0) and d2 < t * t
        if need:
            worst, rmin, cnt = price_entry(K.cost_at(src, k, l) - uk - vl, l, thresh, neg_r, idx, k, m, worst,
                                           rmin, cnt)
        else:
            skipped += 1
    if skipped > 0:
        rmin = wp.min(rmin, _GRAM_GUARD)
        if every:
            cnt += skipped
    row_min[k] = rmin
    row_cnt[k] = cnt


_PRICE = {c: wp.overload(price_rows, {"csrc": c}) for c in (K.DenseCost, K.LazyCost)}
_GATHER = {c: wp.overload(gather_cost, {"csrc": c}) for c in (K.DenseCost, K.LazyCost)}


def cost_source(cost: CostInput, transposed: bool = False):
    """The Warp struct that gives C'(k, l) = C(k, l) / max C in the user's orientation (rows = N1), or with
    ``transposed`` C'(l, k) (rows = N2; the metrics are symmetric, so the features just swap)."""
    if cost.lazy:
        fc = cost.features
        src = K.LazyCost()
        src.A, src.B = (fc.Y, fc.X) if transposed else (fc.X, fc.Y)
        src.metric = METRIC_CODES[fc.metric]
    else:
        src = K.DenseCost()
        src.C, src.trans = cost.C, int(transposed)
    src.inv_scale = wp.float64(1.0 / cost.scale)
    return src


def pass_outputs(n_rows: int, m: int, device: str) -> tuple[wp.array, wp.array, wp.array, wp.array]:
    """The output arrays of a pricing pass over ``n_rows`` rows keeping ``m`` entries a row (`price_rows`,
    `price_rows_batch`): -r and columns of the kept entries, each row's minimum and count."""
    return (wp.empty((n_rows, m), dtype=wp.float64, device=device),
            wp.empty((n_rows, m), dtype=wp.int32, device=device),
            wp.empty(n_rows, dtype=wp.float64, device=device),
            wp.empty(n_rows, dtype=wp.int32, device=device))


def candidates(idx: np.ndarray, rmin: np.ndarray, rcnt: np.ndarray, transposed: bool):
    """A pass's (rows, columns) of the listed entries (``idx`` (n, m), -1 where a row lists fewer; with
    ``transposed`` its rows are columns), its row minima and its count below the threshold."""
    ok = idx >= 0
    rows = np.broadcast_to(np.arange(idx.shape[0])[:, None], idx.shape)[ok].astype(np.int64)
    cols = idx[ok].astype(np.int64)
    if transposed:
        rows, cols = cols, rows
    return rows, cols, rmin, int(rcnt.sum())


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


#: bytes per support entry: its row, column, cost and key here, the sparse cost handed to the network simplex
#: (COO) and its graph (arcs with their source, target, cost, flow and state, and the search's work arrays)
_BYTES_PER_ENTRY = 160


def support_bytes(n1: int, n2: int) -> int:
    """Bytes of the column generation apart from C and the plan: the pricing pass's lists and the support,
    taken as the first support (INIT_K a row and a column, the north-west corner) and two full rounds of
    PRICE_K a row (the first round adds about PRICE_K a row, the later ones a few in all)."""
    entries = (INIT_K + 2 * PRICE_K) * n1 + INIT_K * n2 + n1 + n2
    return _BYTES_PER_ENTRY * entries + 12 * (max(INIT_K, PRICE_K) + 2) * max(n1, n2) + 64 * (n1 + n2)


@dataclass(frozen=True)
class Round:
    """One pricing round: the restricted problem's optimum on the support (the LP's, or the partial QP's;
    normalized units), the support's size, the entries priced out (below the threshold, see `PRICE_TOL`), the
    least reduced cost over all N1 N2 entries, seconds in the restricted solve and in the pass, and the
    host-device transfers since the previous round (device-to-host reads are the synchronisations on a GPU:
    the pass's results and the new entries' costs; host-to-device writes: the duals and the new entries'
    indices)."""

    objective: float
    support: int
    violations: int
    min_reduced: float
    t_lp: float
    t_price: float
    n_d2h: int = 0
    n_h2d: int = 0


class ColumnGeneration:
    """The column-generation state of one problem: the support and the device arrays of the pricing pass
    (the restricted problem on the support is the run's: `ExactRun`, `wpot.ot.exact.partial.PartialRun`).
    ``cost`` from `prepare_cost`. ``gram``: run the passes of a matrix-free
    Euclidean cost on the CPU through BLAS (`wpot.ot.gram`; the same results, much faster): None
    (the default) where it applies, True, False, or the `GramBlocks` of the cost's features to use."""

    def __init__(self, cost: CostInput, device: str, *, gram: bool | GramBlocks | None = None):
        self.cost, self.device = cost, device
        self.gram = gram_blocks(cost.features, device, gram)
        self.n1, self.n2 = cost.n1, cost.n2
        self.src = cost_source(cost)
        self.src_t = cost_source(cost, transposed=True)
        self.rows = np.zeros(0, np.int64)
        self.cols = np.zeros(0, np.int64)
        self.c = np.zeros(0, np.float64)  # C' on the support
        self._known = np.zeros(0, np.int64)  # sorted keys row * n2 + col of the support
        self.n_d2h = self.n_h2d = 0  # host-device transfers (see `Round`)

    # ------------------------------------------------------------------ the pass over all entries
    def price(self, u: np.ndarray, v: np.ndarray, thresh: float, m: int, *, transposed: bool = False):
        """One pass at duals u (a row's), v (a column's): (candidate rows, candidate columns, row minima, count
        below ``thresh``), each row's ``m`` most negative reduced costs below ``thresh``. ``transposed``: the
        pass over the columns instead (u, v swapped; the candidates are still returned as (row, column))."""
        d = self.device
        n_rows, n_cols = (self.n2, self.n1) if transposed else (self.n1, self.n2)
        m = max(1, min(m, n_cols))
        neg, idx, rmin, rcnt = pass_outputs(n_rows, m, d)
        src = self.src_t if transposed else self.src
        u_w, v_w = wp.array(u, dtype=wp.float64, device=d), wp.array(v, dtype=wp.float64, device=d)
        if self.gram is not None:
            if not (thresh <= 0.0 or thresh == math.inf):
                raise ValueError(f"price_rows_gram needs thresh <= 0 or inf, got {thresh!r}")
            norms, err = self.gram.norms(transposed), wp.float64(self.gram.err)
            for k0, n, P in self.gram.blocks(transposed):
                launch_rows(lambda lo, hi: wp.launch(
                    price_rows_gram, dim=hi - lo, device=d, inputs=[P[lo:hi], k0 + lo, src, n_cols, *norms, err, u_w,
                                                                    v_w, wp.float64(thresh), m, neg, idx, rmin, rcnt]),
                    n, d, cols=n_cols)
        else:
            launch_rows(lambda lo, hi: wp.launch(_PRICE[src._cls], dim=hi - lo, device=d, inputs=[
                src, lo, n_cols, u_w, v_w, wp.float64(thresh), m, neg, idx, rmin, rcnt]), n_rows, d,
                cols=n_cols)
        self.n_h2d += 2
        self.n_d2h += 3
        return candidates(idx.numpy(), rmin.numpy(), rcnt.numpy(), transposed)

    def reduced(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(S,) the support's reduced costs r = C' - u - v at duals u (N1,), v (N2,)."""
        return self.c - u[self.rows] - v[self.cols]

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
        """Add the entries not yet in the support; returns how many were new."""
        key = np.unique(rows * self.n2 + cols)
        known = self._known  # the support's keys, kept sorted: O(m log S) membership
        pos = np.searchsorted(known, key)
        new = np.ones(len(key), bool) if len(known) == 0 else \
            (pos == len(known)) | (known[np.minimum(pos, len(known) - 1)] != key)
        key, pos = key[new], pos[new]
        if len(key) == 0:
            return 0
        r, c = key // self.n2, key % self.n2
        self.rows = np.concatenate([self.rows, r])
        self.cols = np.concatenate([self.cols, c])
        self.c = np.concatenate([self.c, self.cost_of(r, c)])
        self._known = np.insert(self._known, pos, key)
        return len(key)

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the support entries where ``mask`` (S,) bool is True (in their order)."""
        self.rows, self.cols, self.c = self.rows[mask], self.cols[mask], self.c[mask]
        self._known = np.sort(self.rows * self.n2 + self.cols)


def transport_lp(cg: ColumnGeneration, a: np.ndarray, b: np.ndarray, duals: tuple[np.ndarray, np.ndarray] | None):
    """Solve the transport LP with masses ``a``, ``b`` on ``cg``'s support by POT's network simplex on its
    bipartite graph, warm-started from ``duals`` (the previous round's u, v, or None): (plan rows, columns,
    values (its nonzeros), u (N1,), v (N2,), objective)."""
    import ot

    M = sp.coo_matrix((cg.c, (cg.rows, cg.cols)), shape=(cg.n1, cg.n2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # reported below, as an error
        G, log = ot.emd(a, b, M, numItermax=_LP_MAX_ITER, log=True, potentials_init=duals)
    if log.get("warning"):
        raise RuntimeError(f"the transport LP on the sparse support failed ({log['warning']}); please report "
                           "this problem")
    G = sp.coo_matrix(G)
    u, v = np.asarray(log["u"], dtype=np.float64), np.asarray(log["v"], dtype=np.float64)
    keep = G.data > 0
    return (G.row[keep].astype(np.int64), G.col[keep].astype(np.int64), np.asarray(G.data[keep], np.float64),
            u, v, float(log["cost"]))


def first_of_each(major: np.ndarray, k: int) -> np.ndarray:
    """Mask of the first ``k`` entries of each run of equal values of ``major`` (a pass's candidates: a row's
    are contiguous and listed cheapest first)."""
    if len(major) == 0:
        return np.zeros(0, bool)
    starts = np.flatnonzero(np.concatenate([[True], major[1:] != major[:-1]]))
    first = np.repeat(starts, np.diff(np.concatenate([starts, [len(major)]])))
    return np.arange(len(major)) - first < k


def threshold(reduced_on_support: np.ndarray) -> float:
    """The pricing threshold after a restricted solve (see `PRICE_TOL`): -max(PRICE_TOL, ROUNDING_MARGIN x the
    support's most negative reduced cost), where the restricted problem is optimal up to its duals' rounding."""
    worst = float(np.max(-reduced_on_support, initial=0.0))
    return -max(PRICE_TOL, ROUNDING_MARGIN * worst)


def sparse_plan(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, n1: int, n2: int, plan_topk: int,
                dense: bool) -> tuple[np.ndarray | None, sp.csr_matrix, np.ndarray]:
    """A plan given by its nonzeros (user units, every row listed or not) as `OTResult` holds it: the dense
    (N1, N2) plan when ``dense`` (else None), each row's ``plan_topk`` largest entries (CSR) and each row's
    argmax (int64; 0 for a row with no entry)."""
    order = np.lexsort((-vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    start = np.searchsorted(rows, np.arange(n1 + 1))
    rank = np.arange(len(rows)) - start[rows]
    top = rank < plan_topk
    counts = np.bincount(rows[top], minlength=n1)
    plan_top = sp.csr_matrix((vals[top], cols[top], np.concatenate([[0], np.cumsum(counts)])), shape=(n1, n2))
    has = start[1:] > start[:-1]
    argmax = np.zeros(n1, np.int64)
    argmax[has] = cols[start[:-1][has]]
    plan = None
    if dense:
        plan = np.zeros((n1, n2))
        plan[rows, cols] = vals
    return plan, plan_top, argmax


class ExactRun:
    """One balanced problem's column generation (steps 1-3 of the module's docstring), driven round by round:
    `solve_exact_problem` drives one with its own passes, `solve_exact_batch` many with shared ones.

    ``first_support`` takes the two candidate passes (``init_k`` a row and a column), then while ``active``:
    ``lp`` solves the restricted problem on the support and returns its duals in the pass's convention
    (r = C' - u - v), ``take`` takes the pass at those duals. ``result`` assembles the `OTResult` (and warns,
    saying why the rounds stopped, when the certified gap is above tol). `wpot.ot.exact.partial.PartialRun`
    is the same with the chi^2 problem on the support."""

    #: candidates a row and a column in the first support
    init_k: int = INIT_K
    #: most negative entries a row that join the support in each pricing round
    price_k: int = PRICE_K

    def __init__(self, problem: TransportProblem, options: SolverOptions, kind: str,
                 on_round: Callable[[Round], None] | None = None, *, gram: bool | GramBlocks | None = None):
        if problem.partial:
            raise ValueError(f"ExactRun solves balanced transport (mass_penalty=None), got {problem!r}; partial "
                             "problems are `wpot.ot.exact.partial.PartialRun`'s")
        self._start(problem, options, kind, on_round, gram)
        cost = self.cost
        self.a_ = prepare_masses(problem.a, cost.n1, "a")
        self.b_ = prepare_masses(problem.b, cost.n2, "b")
        self.total = check_balanced(self.a_, self.b_)
        self.a, self.b = self.a_ / self.total, self.b_ / self.total
        self.b *= self.a.sum() / self.b.sum()
        self._duals: tuple[np.ndarray, np.ndarray] | None = None  # the last LP's, its warm start

    def _start(self, problem: TransportProblem, options: SolverOptions, kind: str,
               on_round: Callable[[Round], None] | None, gram: bool | GramBlocks | None) -> None:
        """The state every run shares: the device, the cost, the support and the round counters."""
        self.options, self.kind, self.on_round = options, kind, on_round
        self.device = resolve_device(problem.device)
        self.dense = check_mode(problem.cost, options, self.device)
        self.cost = prepare_cost(problem.cost, self.device)
        self.cg = ColumnGeneration(self.cost, self.device, gram=gram)
        self.active, self.stop, self.n_rounds = True, None, 0
        self._seen = (0, 0)

    def first_support(self, row_pass: tuple, col_pass: tuple) -> None:
        """The first support: the first ``init_k`` of each row's (``row_pass``) and each column's (``col_pass``)
        candidates, given as (rows, columns) pairs listed cheapest first, and the entries the restricted
        problem needs to be feasible (`feasible_entries`)."""
        r_ok, c_ok = first_of_each(row_pass[0], self.init_k), first_of_each(col_pass[1], self.init_k)
        extra_r, extra_c = self.feasible_entries()
        self.cg.add(np.concatenate([row_pass[0][r_ok], col_pass[0][c_ok], extra_r]),
                    np.concatenate([row_pass[1][r_ok], col_pass[1][c_ok], extra_c]))

    def feasible_entries(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, columns) that make the LP on any support feasible: the north-west-corner plan's."""
        return northwest_corner(self.a, self.b)

    def lp(self) -> tuple[np.ndarray, np.ndarray]:
        """Solve the LP on the support; returns its duals (u, v) for the next pass, whose threshold is then
        ``thresh`` (see `PRICE_TOL`)."""
        t0 = time.perf_counter()
        cg = self.cg
        rows, cols, vals, self.u, self.v, self.obj = transport_lp(cg, self.a, self.b, self._duals)
        self._duals = (self.u, self.v)
        self.plan_entries = (rows, cols, vals)
        self.thresh = threshold(cg.reduced(self.u, self.v))
        self.t_lp = time.perf_counter() - t0
        return self.u, self.v

    def take(self, rows: np.ndarray, cols: np.ndarray, rmin: np.ndarray, nviol: int, t_pass: float) -> None:
        """The pass at the last restricted solve's duals: its entries priced out join the support, or the
        solve ends."""
        cg = self.cg
        self.rmin = rmin
        self.n_rounds += 1
        rnd = Round(self.obj, len(cg.rows), nviol, float(rmin.min()), self.t_lp, t_pass,
                    cg.n_d2h - self._seen[0], cg.n_h2d - self._seen[1])
        self._seen = (cg.n_d2h, cg.n_h2d)
        if self.on_round is not None:
            self.on_round(rnd)
        if self.options.verbose:
            print(f"  exact: restricted optimum {self.obj:.12g} on {rnd.support} entries, {nviol} priced out "
                  f"(min r {rnd.min_reduced:.2e}), solve {rnd.t_lp:.2f} s, pass {rnd.t_price:.2f} s")
        take = first_of_each(rows, self.price_k)  # a batch's shared pass may list more a row than this run takes
        if nviol == 0:
            self.active, self.stop = False, "optimal"
        elif cg.add(rows[take], cols[take]) == 0:  # every entry priced out is in the support: the duals' rounding
            self.active, self.stop = False, "rounding"
        elif self.n_rounds >= self.options.max_iter:
            self.active, self.stop = False, "max_iter"

    def converged(self, gap: float, primal: float, unit: float) -> bool:
        """Whether the certified ``gap`` (normalized units) is within tol of ``primal`` (+ atol); warns,
        saying why the rounds stopped, when it is not. ``unit``: normalized -> the user's cost units."""
        # the certificate decides: tol relative to U, atol a fraction of max C per unit of mass (as the
        # annealing's). Where the rounds stopped on entries already in the support (large problems: the
        # restricted solver's duals carry rounding of ~1e-11 of max C), the bound still covers them.
        options = self.options
        if gap <= options.tol * abs(primal) + options.atol:
            return True
        why, fix = ((f"stopped after max_iter={options.max_iter} pricing rounds", "increase max_iter")
                    if self.stop == "max_iter" else
                    ("stopped on entries priced out that are in the support already", "please report this"))
        warnings.warn(f"{self.kind}: the exact solve {why} with a certified gap of {gap * unit:.3g} (cost units), "
                      f"above tol; {fix}", RuntimeWarning, stacklevel=5)
        return False

    def result(self, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """The `OTResult`: the LP's optimum, ``beta`` = inf, ``cost`` = ``objective`` = ``free_energy`` = U (the
        entropy term vanishes at beta = inf), one `BetaStep` in ``history`` whose ``gap_bound`` is the certified
        U - L over all entries, ``n_newton`` = ``n_linear`` = 0, ``lam`` = -u and ``mu`` = -v (the sign of
        Eq. 15: C + lam + mu >= 0, = 0 on the plan's support)."""
        cg, cost, total = self.cg, self.cost, self.total
        (rows, cols, vals), u, v = self.plan_entries, self.u, self.v
        n1, n2 = cost.n1, cost.n2
        # the certificate over every entry, from the last pass: the primal cost of the plan (its entries' costs
        # recomputed, as every cost here, by the kernels' function) against the dual bound
        primal = float(cg.cost_of(rows, cols) @ vals)
        lower = float(self.a @ (u + np.minimum(self.rmin, 0.0)) + self.b @ v)
        gap = max(primal - lower, 0.0)
        unit = cost.scale * total  # normalized objective -> user units
        converged = self.converged(gap, primal, unit)
        vals = vals * total
        mass1 = np.bincount(rows, weights=vals, minlength=n1)
        mass2 = np.bincount(cols, weights=vals, minlength=n2)
        resid = 0.5 * (np.abs(mass1 - self.a_).sum() + np.abs(mass2 - self.b_).sum()) / total
        U = primal * unit
        step = BetaStep(beta=math.inf, cost=U, free_energy=U, n_newton=0, n_linear=0, residual=float(resid),
                        gap_bound=gap * unit, objective=U)
        if on_beta is not None:
            on_beta(step)
        plan, plan_top, argmax = sparse_plan(rows, cols, vals, n1, n2, self.options.plan_topk, self.dense)
        return OTResult(plan=plan, plan_top=plan_top, argmax=argmax, cost=U, objective=U,
                        free_energy=U, lam=-u * cost.scale, mu=-v * cost.scale, x=0.0, mass1=mass1, mass2=mass2,
                        beta=math.inf, converged=bool(converged), n_newton=0, n_linear=0, history=(step,))
