"""The host Newton loop (``newton_loop="host"``, the default on the CPU and with ``linear_solver="direct"``).

The length-N vectors of a Newton step come to the host (zero-copy views on "cpu", transfers elsewhere,
each counted by `wpot.ot.anneal.newton.Engine.to_host` / ``to_device``): an evaluation's marginal residuals
g1 (n_r,), g2 (n_c,) and their norms, and the Schur system S dy = -g2 + W^T E1^-1 g1 (`wpot.ot.anneal.linear`),
solved by CG on the host with the sparse preconditioner P factorized by SuperLU (or by a dense direct solve).
Each CG iteration uploads its vector and reads the matvec S_W v back from the device kernels; the kernels
over W are those of `wpot.ot.anneal.schur.SchurSolver`.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Callable

import numpy as np
import warp as wp

from wpot.ot.anneal import linear
from wpot.ot.anneal.schur import SchurSolver, step_alpha
from wpot.ot.anneal.state import Point

if TYPE_CHECKING:  # pragma: no cover
    from wpot.ot.anneal.newton import Engine

__all__ = ["HostSolver"]

class HostSolver(SchurSolver):
    """The `wpot.ot.anneal.schur.NewtonSolver` of the host loop (see the module docstring)."""

    def __init__(self, eng: Engine):
        super().__init__(eng)
        self._mv_view = np.asarray(eng.mv) if eng._host else None  # zero-copy, for zeroing it

    # ------------------------------------------------------------------ evaluation
    def _x_of_y(self, y: np.ndarray) -> float:
        """Partial: the scalar x eliminated in closed form, x = (a . y - 1) / sum(a) (then sum m2 = 1)."""
        p = self.e.p
        if not p.partial:
            return 0.0
        return (float(p.a_c @ y) - 1.0) / self.e.a_sum

    def point(self, lam, y, full: bool) -> Point:
        """The marginal residuals g1 = m_r + b lam - G 1, g2 = m_c + a (y - x) - G^T 1 (Eq. 14 / 25) as host
        arrays, their 2-norm (the merit) and half their 1-norm (the residual), and, with ``full``, U and the
        gap sum, from the sums the engine's evaluation pass left on the device."""
        e, p = self.e, self.e.p
        rg, cg = e.to_host(e.row_g), e.to_host(e.col_g)
        lam_h = e.to_host(lam[0]) + e.to_host(lam[1])
        y_h = e.to_host(y[0]) + e.to_host(y[1])
        x = self._x_of_y(y_h)
        tgt1 = p.m_r + p.b_r * lam_h
        tgt2 = p.m_c + p.a_c * (y_h - x)
        g1 = tgt1 - rg
        g2 = tgt2 - cg
        merit = float(np.sqrt(g1 @ g1 + g2 @ g2))
        res = 0.5 * float(np.abs(g1).sum() + np.abs(g2).sum())
        pt = Point(g1, g2, merit, res, x=x)
        if full:
            pt.u = float(e.to_host(e.row_u).sum())
            pt.xphi = float(e.to_host(e.row_xphi).sum())
        return pt

    def free_sums(self, lam, y, pt: Point) -> None:
        """Sum g into ``pt.f_sum`` and ``pt``'s `DualSums`, read now (at these duals and marginals: the caller
        may move on before it asks)."""
        e = self.e
        pt.f_sum = float(e.to_host(e.row_f).sum())
        pt.sums = None
        e.dual_sums(pt)

    def free_values(self, pt: Point) -> Point:
        """``pt`` (`free_sums` filled it in)."""
        return pt

    def read_scalars(self, arr: wp.array) -> np.ndarray:
        """A copy of the small device array ``arr`` on the host (one read)."""
        return self.e.to_host(arr).copy()

    # ------------------------------------------------------------------ the Newton step
    def step_start(self, beta: float, pt: Point, rtol: float,
                   min_x: float) -> tuple[Callable[[], tuple[int, bool]], float]:
        """The Newton direction at ``pt`` (CG to ``rtol``) and its first trial step length: 90 % of the way to
        s = 0 on the rows' pivots whose step d_b is negative, among those with beta s > ``min_x``."""
        e = self.e
        counts = self.direction_later(pt, rtol)
        db = e.to_host(e.d_b)
        spv = e.to_host(e.s_piv)
        neg = (db < 0) & (spv * beta > min_x)
        limit = math.inf
        if np.any(neg):
            limit = float(np.min(spv[neg] / -db[neg]))
        return counts, step_alpha(limit)

    def first_factor(self, last: float) -> float:
        """1: each line search starts at the full first trial step."""
        return 1.0

    def trial(self, factor: float, limit: float) -> None:
        """The trial duals at ``factor * limit`` x the direction."""
        self.e.trial(factor * limit)

    def step_length(self, limit: float) -> float:
        """``limit`` (known on the host since `step_start`)."""
        return limit

    # ------------------------------------------------------------------ the Newton direction
    def direction_later(self, pt: Point, rtol: float | None = None) -> Callable[[], tuple[int, bool]]:
        """`solve` now; the function returns its (linear iterations, converged)."""
        res = self.solve(pt, rtol)
        return lambda: res

    def solve(self, pt: Point, rtol: float | None = None) -> tuple[int, bool]:
        """Solve the Newton system for the residuals of ``pt`` (see `Point`) at the last evaluated point: the
        right-hand side -g2 + W^T E1^-1 g1 and S_W's diagonal on the device, CG (or the direct solve) on the
        host, dlam = d_a + d_b and dy = dy_a left on the device. Returns (linear iterations, converged)."""
        e, p, o, t = self.e, self.e.p, self.e.o, self.e.t
        t0 = time.perf_counter()
        self._select_weights()
        g1 = self._host_vec(pt.g1)
        g2 = self._host_vec(pt.g2)
        e1 = e.to_host(e.row_w) + p.b_r
        e.to_device(e.e1, e1)
        e.to_device(e.g1, g1)
        cg = o.linear_solver != "direct"
        fresh = cg and (self._M is None or self._M_fresh_needed)
        self._prep(e.g1, fresh)
        rhs = -g2 + e.to_host(e.wtg)
        data = linear.SchurData(e.to_host(e.diag_s).copy(), e1, e.to_host(e.piv).copy(), p.a_c, not p.partial)
        t.prep += time.perf_counter() - t0
        n_lin, ok = 0, True
        if o.linear_solver == "direct":
            t0 = time.perf_counter()
            dy = linear.direct_solve(e.to_host(e.W), data, rhs)
            t.direct += time.perf_counter() - t0
            n_lin = 1
        else:
            if fresh:
                self._build_preconditioner(data)
            t0 = time.perf_counter()
            rtol = o.cg_rtol if rtol is None else max(rtol, o.cg_rtol)
            dy, info = linear.pcg(self._matvec, rhs, self._M, rtol=rtol, max_iter=o.cg_max_iter, gauge=not p.partial)
            t.cg += time.perf_counter() - t0
            n_lin, ok = info.iterations, info.converged
            self._after_solve(fresh, n_lin, ok)
            if not fresh and not ok:
                # and re-solve now, with a fresh preconditioner (and row top-k)
                self._row_topk()
                self._build_preconditioner(data)
                t0 = time.perf_counter()
                dy, info = linear.pcg(self._matvec, rhs, self._M, rtol=o.cg_rtol, max_iter=o.cg_max_iter,
                                      gauge=not p.partial)
                t.cg += time.perf_counter() - t0
                n_lin += info.iterations
                ok = info.converged
                self._M_iters = info.iterations
        t0 = time.perf_counter()
        e.to_device(e.dy_a, dy)
        self._recover(e.g1)
        t.other += time.perf_counter() - t0
        return n_lin, ok

    def _host_vec(self, v) -> np.ndarray:
        """A right-hand side as a host array (a device array is read)."""
        return self.e.to_host(v) if isinstance(v, wp.array) else v

    def _matvec(self, v: np.ndarray) -> np.ndarray:
        """S v (n_c,) on the host: S_W v by the device kernels, plus the partial rank-one term a v - a (a . v) / sum a."""
        e, p = self.e, self.e.p
        e.to_device(e.v, v)
        if e._host:  # a zero-copy view of the device array
            self._mv_view[:] = 0.0
        else:
            e.mv.zero_()
        launches = self.matvec_launches()
        if len(launches) > 1:
            e.delta.zero_()
        for cmd in launches:
            cmd.launch()
        out = e.to_host(e.mv).copy()
        if p.partial:
            a = p.a_c
            out += a * v - a * (float(a @ v) / e.a_sum)
        e.t.n_matvec += 1
        return out

    def _build_preconditioner(self, data: linear.SchurData) -> None:
        """Top-k selection per column (Warp), assembly and SuperLU factorization of the sparse approximation P."""
        e, p = self.e, self.e.p
        t0 = time.perf_counter()
        self._col_topk()
        P = linear.assemble_sparse_schur(data, e.to_host(e.top_val), e.to_host(e.top_idx),
                                         e.to_host(e.ctop_val), e.to_host(e.ctop_idx))
        self._M = linear.SchurPreconditioner(P, p.a_c, not p.partial)
        self._M_fresh_needed = False
        e.t.precond += time.perf_counter() - t0
        e.t.n_factor += 1
