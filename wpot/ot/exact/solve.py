"""The exact solves' drivers: one problem (`solve_exact_problem`) or many sharing each round's pricing launch
(`solve_exact_batch`, `BatchPricer`), balanced (`wpot.ot.exact.balanced.ExactRun`) or partial
(`wpot.ot.exact.partial.PartialRun`): the rounds of column generation described in `wpot.ot.exact.balanced`."""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import warp as wp

from wpot._warp import launch_rows
from wpot.ot.exact.balanced import ExactRun, Round, candidates, pass_outputs, price_rows_batch
from wpot.ot.exact.partial import PartialRun
from wpot.ot.gram import GramBlocks
from wpot.ot.options import SolverOptions
from wpot.ot.problem import TransportProblem
from wpot.ot.result import BetaStep, OTResult


def exact_run(problem: TransportProblem, options: SolverOptions, kind: str,
              on_round: Callable[[Round], None] | None = None, *, gram: bool | GramBlocks | None = None) -> ExactRun:
    """The run of ``problem``: `ExactRun` (balanced) or `wpot.ot.exact.partial.PartialRun` (partial)."""
    if problem.partial:
        return PartialRun(problem, options, kind, on_round, gram=gram)
    return ExactRun(problem, options, kind, on_round, gram=gram)


def solve_exact_problem(problem: TransportProblem, options: SolverOptions, *, kind: str = "solve_balanced",
                        on_beta: Callable[[BetaStep], None] | None = None,
                        on_round: Callable[[Round], None] | None = None,
                        gram: bool | GramBlocks | None = None) -> OTResult:
    """Solve ``problem`` exactly by column generation (see the module's docstring; balanced: `ExactRun.result`,
    partial: `wpot.ot.exact.partial.PartialRun.result`). ``on_round`` gets each pricing round's `Round`;
    ``gram`` as in `ColumnGeneration`."""
    run = exact_run(problem, options, kind, on_round, gram=gram)
    cg = run.cg
    z1, z2 = np.zeros(cg.n1), np.zeros(cg.n2)
    run.first_support(cg.price(z1, z2, math.inf, run.init_k)[:2],
                      cg.price(z2, z1, math.inf, run.init_k, transposed=True)[:2])
    while run.active:
        u, v = run.lp()
        t0 = time.perf_counter()
        rows, cols, rmin, nviol = cg.price(u, v, run.thresh, run.price_k)
        run.take(rows, cols, rmin, nviol, time.perf_counter() - t0)
    return run.result(on_beta)


class BatchPricer:
    """The pricing passes of many problems (stored costs, one device; balanced or partial) in one launch of
    `price_rows_batch`: their costs (the caller's C, scaled in the kernel) are copied once into one flat device
    array, and
    each launch covers the rows (or columns) of the problems asked for. Counts its host-device transfers
    (``n_d2h``, ``n_h2d``: per launch, whatever the number of problems)."""

    def __init__(self, runs: list[ExactRun]):
        if any(r.cost.lazy for r in runs):
            raise ValueError("solve_exact_batch needs stored costs (arrays), not FeatureCost; solve matrix-free "
                             "problems one at a time")
        devices = {r.device for r in runs}
        if len(devices) != 1:
            raise ValueError(f"solve_exact_batch needs every problem on one device, got {sorted(devices)}")
        self.device = d = devices.pop()
        self.runs = runs
        sizes = np.array([r.cost.n1 * r.cost.n2 for r in runs], dtype=np.int64)
        self.off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        flat = wp.empty(int(sizes.sum()), dtype=wp.float64, device=d)
        for r, o, n in zip(runs, self.off, sizes):
            wp.copy(flat, r.cost.C.flatten(), dest_offset=int(o), count=int(n))
        self.C = flat
        self.n1 = np.array([r.cost.n1 for r in runs], dtype=np.int32)
        self.n2 = np.array([r.cost.n2 for r in runs], dtype=np.int32)
        self.inv_scale = np.array([1.0 / r.cost.scale for r in runs])
        self.n_d2h = self.n_h2d = 0

    def price(self, which: list[int], us: list[np.ndarray], vs: list[np.ndarray], thresh: float | list[float],
              m: int, *, transposed: bool = False) -> list[tuple]:
        """`ColumnGeneration.price` of the problems ``which`` (indices into the runs), at their duals ``us``,
        ``vs`` and thresholds ``thresh`` (one, or one per problem), in one launch; one (rows, columns, row minima,
        count) per problem."""
        d = self.device
        n_rows = (self.n2 if transposed else self.n1)[which]
        n_cols = (self.n1 if transposed else self.n2)[which]
        m = max(1, min(m, int(n_cols.min())))
        prob = np.repeat(np.arange(len(which), dtype=np.int32), n_rows)
        local = np.concatenate([np.arange(n, dtype=np.int32) for n in n_rows])
        v_off = np.concatenate([[0], np.cumsum(n_cols)[:-1]]).astype(np.int32)
        g = len(prob)
        neg, idx, rmin, rcnt = pass_outputs(g, m, d)
        arr = lambda x, t: wp.array(x, dtype=t, device=d)  # noqa: E731
        ins = [self.C, arr(self.off[which], wp.int64), arr(self.n1[which], wp.int32), arr(self.n2[which], wp.int32),
               arr(self.inv_scale[which], wp.float64), int(transposed), arr(prob, wp.int32), arr(local, wp.int32),
               arr(np.concatenate(us), wp.float64), arr(np.concatenate(vs), wp.float64), arr(v_off, wp.int32),
               arr(np.broadcast_to(np.asarray(thresh, np.float64), (len(which),)).copy(), wp.float64), m, neg, idx,
               rmin, rcnt]
        launch_rows(lambda lo, hi: wp.launch(price_rows_batch, dim=hi - lo, device=d, inputs=[lo, *ins]), g, d,
                    cols=int(n_cols.max()))
        self.n_h2d += 9
        self.n_d2h += 3
        idx_h, rmin_h, rcnt_h = idx.numpy(), rmin.numpy(), rcnt.numpy()
        bounds = np.concatenate([[0], np.cumsum(n_rows)])
        return [candidates(idx_h[s:e], rmin_h[s:e], rcnt_h[s:e], transposed) for s, e in zip(bounds[:-1], bounds[1:])]


def solve_exact_batch(problems: list[TransportProblem], options: SolverOptions | None = None) -> list[OTResult]:
    """Solve many problems (balanced or partial, stored costs of any sizes, one device) exactly, their pricing
    passes in shared launches: one launch a round for every problem still running, so that a GPU is kept busy
    by small problems; the restricted problems are solved on the host. Each result equals
    `solve_exact_problem`'s on the problem alone (the same passes, in the same order: bit for bit)."""
    options = SolverOptions() if options is None else options
    runs = [exact_run(p, options, "solve_exact_batch") for p in problems]
    if not runs:
        return []
    pricer = BatchPricer(runs)
    everyone = list(range(len(runs)))
    z1 = [np.zeros(r.cg.n1) for r in runs]
    z2 = [np.zeros(r.cg.n2) for r in runs]
    init_k = max(r.init_k for r in runs)  # each run takes its own first init_k of the lists
    rows_pass = pricer.price(everyone, z1, z2, math.inf, init_k)
    cols_pass = pricer.price(everyone, z2, z1, math.inf, init_k, transposed=True)
    for r, rp, cp in zip(runs, rows_pass, cols_pass):
        r.first_support(rp[:2], cp[:2])
    while True:
        active = [i for i, r in enumerate(runs) if r.active]
        if not active:
            break
        duals = [runs[i].lp() for i in active]
        t0 = time.perf_counter()
        passes = pricer.price(active, [u for u, _ in duals], [v for _, v in duals], [runs[i].thresh for i in active],
                              max(runs[i].price_k for i in active))  # each run takes its own first price_k a row
        t_pass = (time.perf_counter() - t0) / len(active)
        for i, (rows, cols, rmin, nviol) in zip(active, passes):
            runs[i].take(rows, cols, rmin, nviol, t_pass)
    return [r.result() for r in runs]
