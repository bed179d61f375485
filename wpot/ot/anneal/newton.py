"""The solver state of one OT problem and Newton's method at fixed beta (shared by balanced and partial).

State lives in preallocated Warp arrays on the solve device; the O(N1 N2) work (phi, phi', row and
column sums, U, F, Schur matvecs) runs in `wpot.ot.kernels`. The Newton steps run in one of two loops
(`EngineOptions.newton_loop`): the host loop handles the length-N vectors on the host (zero-copy views on
"cpu"), where the CG recurrences and the SuperLU preconditioner run; the device loop (`wpot.ot.anneal.resident`,
the default on a GPU) keeps them on the device and reads one small array per trial point. Every read of
a device array goes through `Engine.to_host` and every write of host data through `Engine.to_device`, which
count them (`Timers.n_d2h`, `Timers.n_h2d`): on a GPU each is a transfer, and each read waits for the
device (a synchronisation); the counts are the same on every device.

Two modes (`wpot.ot.kernels`): stored (a dense C, and the Hessian weights W stored by the evaluation
pass) and matrix-free (C from the signatures, W recomputed where it is read: no N1 x N2 array; each pass
over W then costs a pass over the features).

Cost per Newton step: one pass over C (`kernels.eval_rows`, at the trial point), one pass over W for the
Schur right-hand side and diagonal, one per CG iteration (two sweeps of a row) and one for the
back-substitution. The sparse preconditioner (top-k selection in Warp, SuperLU) is the expensive part at
large N and is reused across Newton steps and betas while CG converges about as fast as with a fresh
one (`REFRESH_EXTRA_CG`).

The `Engine`'s public step API (`evaluate`, `direction`, `direction_later`, `trial`, `trial_from`,
`accept`, `newton`, `free_pass`, `dual_sums`, `snapshot`/`restore`, `invalidate_preconditioner`, `plan`,
`plan_top`, `to_host`/`to_device`, `read_scalars`) is what the annealing loop (`wpot.ot.anneal.loop`) and the
interior-point start (`wpot.ot.anneal.ipm`) drive.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import warp as wp

from wpot.cost import METRIC_CODES
from wpot.ot import kernels as K
from wpot.ot.anneal import linear
from wpot.ot.anneal import resident
from wpot.ot.options import EngineOptions
from wpot.ot.problem import Internal
from wpot.ot.anneal.resident import DeviceLoop
from wpot.ot.anneal.state import DualSnapshot, DualSums, Point, Timers

#: a preconditioner is reused (across Newton steps and betas) until a CG solve with it takes more than
#: this many iterations beyond the count of its first solve (or a full Newton step with it gains less than
#: 4x); it is then rebuilt at the next Newton point (at once, with a re-solve, when CG failed). Measured
#: at N = 1000: 20 factorizations instead of 74, 513 CG iterations instead of 246
REFRESH_EXTRA_CG = 2
#: the device loop refits a stale FSAI preconditioner on its last pattern (no host read) while CG with the
#: refit needs at most this many times the count of its last full build (+ REFRESH_EXTRA_CG); a full build
#: synchronises `resident.BUILD_SYNCS` times inside Warp. Measured at N = 1,000 (random R^8 points), full
#: builds / CG iterations: 1.0: 8 / 637 (annealing), 5 / 455 (ipm); 2.0: 5 / 676, 4 / 491; 3.0: 4 / 711, 4 / 491
REFIT_SLOWDOWN = 2.0
#: forcing term of the inexact Newton steps (Eisenstat-Walker style): CG stops at a relative residual of
#: min(CG_LOOSE, residual), but never tighter than ``cg_rtol``. Far from the solution (the damped steps of the
#: transition betas) a rough direction does as well as an accurate one
CG_LOOSE = 0.1
#: in the device loop a Newton line search starts at this multiple of the last accepted step of its call (at
#: most the full step), since each halving costs a read. Annealing, synchronisations per Newton step / Newton
#: steps / CG iterations with 2.0 and 1.5: TOSCA cat0-cat1 WKS cost at 1,500 samples 2.19 / 212 / 2,319 and
#: 1.94 / 225 / 2,417; random points, unequal masses, N = 500: 1.96 / 258 / 9,678 and 1.78 / 287 / 10,775 (the
#: total synchronisations fall or stay: 464 against 437, 506 against 511); 1.0 lets no step grow (1,747
#: Newton steps on the TOSCA pair at 600 samples, against 120)
STEP_GROWTH = 1.5
#: the fraction-to-zero step rule applies to pivots with beta s above this (see `Engine.newton`)
FTB_MIN_X = 1.0


class Engine:
    """Preallocated solver state for one internal problem (see `wpot.ot.problem.Internal`) and options
    (`wpot.ot.options.EngineOptions`, never changed once the engine holds them).

    The duals lam (n_r,), y (n_c,) are double-double pairs (``lam[0] + lam[1]``: hi, lo) on the device;
    a trial point goes to a second pair of buffers (`trial`) and becomes the current one by a swap
    (`accept`). Each evaluation (`evaluate`) leaves the device state (the weights W, the marginals, ...)
    at the point it evaluated; `direction` solves the Newton system there.
    """

    def __init__(self, prob: Internal, opts: EngineOptions):
        self.p = prob
        self.o = opts
        d = prob.device
        n_r, n_c = prob.n_r, prob.n_c
        z = lambda n, dt=wp.float64: wp.zeros(n, dtype=dt, device=d)  # noqa: E731
        self.lam = [z(n_r), z(n_r)]  # hi, lo
        self.y = [z(n_c), z(n_c)]
        self.lam_t = [z(n_r), z(n_r)]
        self.y_t = [z(n_c), z(n_c)]
        self.lazy = prob.cost.lazy
        self.inv_scale = 1.0 / prob.scale
        if self.lazy:  # matrix-free: the cost from the (oriented) signatures, W recomputed where read
            fc = prob.cost.features
            self.csrc = K.LazyCost()
            self.csrc.A, self.csrc.B = (fc.Y, fc.X) if prob.trans else (fc.X, fc.Y)
            self.csrc.metric = METRIC_CODES[fc.metric]
            self.csrc.inv_scale = wp.float64(self.inv_scale)
            self.W = None
            self._wsink = K.NoW()
        else:
            self.csrc = K.DenseCost()
            self.csrc.C, self.csrc.trans, self.csrc.inv_scale = prob.cost.C, prob.trans, wp.float64(self.inv_scale)
            self.W = wp.zeros((n_r, n_c), dtype=wp.float64, device=d)
            self._wsink = K.DenseW()
            self._wsink.W = self.W
        self._w_point = None  # (lam, y, beta) of the last evaluation: the point W belongs to
        self.row_g, self.col_g = z(n_r), z(n_c)
        self.row_w, self.tail = z(n_r), z(n_r)
        self.piv = z(n_r, wp.int32)
        self.row_u, self.row_f, self.row_xphi, self.s_piv = z(n_r), z(n_r), z(n_r), z(n_r)
        self.row_ws, self.col_ws = z(n_r), z(n_c)
        self.e1, self.b, self.g1 = z(n_r), z(n_r), z(n_r)
        self.diag_s, self.wtg = z(n_c), z(n_c)
        kk = max(2, min(opts.topk, n_c))
        self.kk = kk
        self.top_val = wp.zeros((n_r, kk), dtype=wp.float64, device=d)
        self.top_idx = wp.zeros((n_r, kk), dtype=wp.int32, device=d)
        kc = max(1, min(opts.topk, n_r))
        self.ctop_val = wp.zeros((n_c, kc), dtype=wp.float64, device=d)
        self.ctop_idx = wp.zeros((n_c, kc), dtype=wp.int32, device=d)
        self.v, self.mv = z(n_c), z(n_c)
        self._no_limit = wp.full(1, 1e300, dtype=wp.float64, device=d)  # `trial`'s step: alpha itself
        self.delta = z(n_r)  # the row sweep's sums, then delta(k), of the strided matvec
        self.d_a, self.d_b = z(n_r), z(n_r)
        self.dy_a, self.zero_c = z(n_c), z(n_c)
        self.t = Timers()
        self._host = wp.get_device(d).is_cpu
        self.to_device(self.b, prob.b_r)
        self.a_sum = float(prob.a_c.sum())
        # strided lanes on GPUs (see `_record_matvec`); one thread per row on the CPU (unless the options
        # say otherwise)
        if opts.matvec_lanes is None:
            self.lanes = 0 if self._host else K.MATVEC_LANES
        else:
            self.lanes = opts.matvec_lanes
        self.eval_lanes = self.lanes or 1  # `K.eval_rows` runs one lane per row on the CPU
        self.lane_f = wp.zeros((n_r, self.eval_lanes, 6), dtype=wp.float64, device=d)
        self.lane_p = wp.zeros((n_r, self.eval_lanes), dtype=wp.int32, device=d)
        self._mv_view = np.asarray(self.mv) if self._host else None  # zero-copy, for zeroing it
        self._matvec_cmd = None
        self._M = None  # the sparse preconditioner, reused across Newton steps and betas while it works
        self._M_iters = 0
        self._M_fresh_needed = False
        self._free_pending = None  # (point, reads of the device's scalars) of the last free_pass
        loop = opts.newton_loop
        if loop is None:
            loop = "host" if self._host or opts.linear_solver != "cg" else "device"
        #: the device-resident Newton loop (`wpot.ot.anneal.resident`), or None for the host loop
        self.dev = DeviceLoop(self) if loop == "device" else None

    # ------------------------------------------------------------------ evaluation
    def _x_of_y(self, y: np.ndarray) -> float:
        """Partial: the scalar x eliminated in closed form, x = (a . y - 1) / sum(a) (then sum m2 = 1)."""
        if not self.p.partial:
            return 0.0
        return (float(self.p.a_c @ y) - 1.0) / self.a_sum

    def evaluate(self, lam, y, beta: float, full: bool = True) -> Point:
        """One pass over C at the duals (``lam``, ``y``: (hi, lo) pairs, e.g. ``self.lam`` or the trial
        ``self.lam_t``) and ``beta``: stores W (stored mode) and the row and column sums on the device and
        returns the marginal residuals (and, with ``full``, U and the gap sum)."""
        t0 = time.perf_counter()
        p = self.p
        self.col_g.zero_()
        wp.launch(K.variant(K.eval_rows, self.csrc), dim=(p.n_r, self.eval_lanes),
                  inputs=[self.csrc, self._wsink, p.n_c, self.eval_lanes, beta, lam[0], lam[1], y[0], y[1]],
                  outputs=[self.col_g, self.lane_f, self.lane_p], device=p.device)
        wp.launch(K.eval_combine, dim=p.n_r, inputs=[self.eval_lanes, self.lane_f, self.lane_p],
                  outputs=[self.row_g, self.row_w, self.piv, self.tail, self.row_u, self.row_xphi, self.s_piv],
                  device=p.device)
        self._w_point = (lam[0], lam[1], y[0], y[1], beta)
        if self.dev is not None:
            pt = self.dev.point(lam, y)
            self.t.eval += time.perf_counter() - t0
            self.t.n_eval += 1
            return pt
        rg, cg = self.to_host(self.row_g), self.to_host(self.col_g)
        lam_h = self.to_host(lam[0]) + self.to_host(lam[1])
        y_h = self.to_host(y[0]) + self.to_host(y[1])
        x = self._x_of_y(y_h)
        tgt1 = p.m_r + p.b_r * lam_h
        tgt2 = p.m_c + p.a_c * (y_h - x)
        g1 = tgt1 - rg
        g2 = tgt2 - cg
        merit = float(np.sqrt(g1 @ g1 + g2 @ g2))
        res = 0.5 * float(np.abs(g1).sum() + np.abs(g2).sum())
        pt = Point(g1, g2, merit, res, x=x)
        if full:
            pt.u = float(self.to_host(self.row_u).sum())
            pt.xphi = float(self.to_host(self.row_xphi).sum())
        self.t.eval += time.perf_counter() - t0
        self.t.n_eval += 1
        return pt

    def free_pass(self, lam, y, beta: float, pt: Point):
        """At the saddle point of a beta (the point of the last evaluation, ``pt``): sum g (into
        ``pt.f_sum``) and the row/column sums of W s. In the device loop sum g and ``pt.sums`` come with the
        next read of the device's scalars: `free_values` fills them in (until then ``pt.f_sum`` is NaN)."""
        t0 = time.perf_counter()
        p = self.p
        self.col_ws.zero_()
        wp.launch(K.variant(K.free_rows, self.csrc), dim=p.n_r,
                  inputs=[self.csrc, p.n_c, beta, lam[0], lam[1], y[0], y[1]],
                  outputs=[self.row_f, self.row_ws, self.col_ws], device=p.device)
        if self.dev is not None:
            self.dev.free_sums(lam, y, pt.x)
            pt.f_sum, pt.sums = math.nan, None
            self._free_pending = (pt, self.dev.n_reads)
        else:
            pt.f_sum = float(self.to_host(self.row_f).sum())
            pt.sums = None
            self.dual_sums(pt)  # at these duals and marginals (the caller may move on before it asks)
        self.t.eval += time.perf_counter() - t0
        self.t.n_free += 1

    def free_values(self, pt: Point) -> Point:
        """``pt`` with sum g and its `DualSums` after `free_pass` (the last one, at ``pt``): in the device loop
        from the first read of the device's scalars since then, or from one now."""
        if self.dev is None or not math.isnan(pt.f_sum):
            return pt
        at, reads = self._free_pending
        if at is not pt:
            raise RuntimeError("free_values: the last free_pass was not at this point")
        if self.dev.n_reads == reads:
            self.dev.read()
        pt.f_sum, pt.sums = self.dev.free_values()
        return pt

    def dual_sums(self, pt: Point) -> DualSums:
        """The `DualSums` at ``pt`` (those `free_pass` / `free_values` set, or, when there are none, read here
        at the current duals and the last evaluation)."""
        if pt.sums is not None:
            return pt.sums
        p = self.p
        lam = self.to_host(self.lam[0]) + self.to_host(self.lam[1])
        y = self.to_host(self.y[0]) + self.to_host(self.y[1])
        mu = y - pt.x
        pt.sums = DualSums(float(lam @ p.m_r), float(y @ p.m_c), float(p.b_r @ (lam * lam)),
                           float(p.a_c @ (mu * mu)), self.penalty())
        return pt.sums

    # ------------------------------------------------------------------ Newton direction
    def weights(self):
        """The source of W at the last evaluated point: the stored array, or (matrix-free) a `kernels.LazyW`
        over the features, beta and the duals of that point (those arrays are not written until the
        next evaluation: the trial point goes to the other buffer)."""
        if not self.lazy:
            return self._wsink
        lh, ll, yh, yl, beta = self._w_point
        src = K.LazyW()
        src.cost = self.csrc
        src.beta = wp.float64(beta)
        src.lam_hi, src.lam_lo, src.y_hi, src.y_lo = lh, ll, yh, yl
        return src

    # ------------------------------------------------------------------ host <-> device
    def to_host(self, arr: wp.array) -> np.ndarray:
        """The device array ``arr`` as a numpy array: a zero-copy view on "cpu", elsewhere a copy that waits
        for the device (a synchronisation). The solver reads device arrays only through here, so that
        ``t.n_d2h`` counts the reads a GPU run makes."""
        self.t.n_d2h += 1
        return arr.numpy()

    def to_device(self, dst: wp.array, src: np.ndarray) -> None:
        """Host data ``src`` -> the device array ``dst`` (same shape): a copy into its zero-copy view on
        "cpu", an upload (``assign``) elsewhere. The solver writes host data only through here, so that
        ``t.n_h2d`` counts the uploads a GPU run makes."""
        self.t.n_h2d += 1
        if self._host:
            np.asarray(dst)[:] = src
        else:
            dst.assign(src)

    def _matvec(self, v: np.ndarray) -> np.ndarray:
        p = self.p
        self.to_device(self.v, v)
        if self._host:  # a zero-copy view of the device array
            self._mv_view[:] = 0.0
        else:
            self.mv.zero_()
        launches = self.matvec_launches()
        if len(launches) > 1:
            self.delta.zero_()
        for cmd in launches:
            cmd.launch()
        out = self.to_host(self.mv).copy()
        if p.partial:
            a = p.a_c
            out += a * v - a * (float(a @ v) / self.a_sum)
        self.t.n_matvec += 1
        return out

    def matvec_launches(self) -> list:
        """The recorded launches of one Schur matvec, mv += S_W v (``v``, ``mv``, and ``delta`` zeroed first
        when there is more than one launch), for the current W source; recorded once per source: only the
        arrays' contents change between calls."""
        if self._matvec_cmd is None:
            self._matvec_cmd = self._record_matvec()
        return self._matvec_cmd

    def _record_matvec(self) -> list:
        """The launches of one Schur matvec (mv += S_W v). The CPU runs one thread per row, streaming its
        row of W (`K.schur_matvec`); a GPU would then run only n_r threads, each reading a strided column
        of W, and serialize on atomics into ``mv``. There the two sweeps are split into strided lanes
        (`K.schur_row_partial`, `K.schur_row_delta`, `K.schur_col_sweep`): n * MATVEC_LANES threads whose
        neighbours read neighbouring entries. Both orders compute the same sums up to rounding."""
        p, w, d = self.p, self._wsrc, self.p.device
        if not self.lanes:
            return [wp.launch(K.variant(K.schur_matvec, w), dim=p.n_r,
                              inputs=[w, p.n_c, self.piv, self.e1, self.b, self.v, self.mv], device=d, record_cmd=True)]
        lanes = self.lanes
        return [
            wp.launch(K.variant(K.schur_row_partial, w), dim=(p.n_r, lanes),
                      inputs=[w, p.n_c, lanes, self.piv, self.v, self.delta], device=d, record_cmd=True),
            wp.launch(K.schur_row_delta, dim=p.n_r, inputs=[self.piv, self.e1, self.b, self.v, self.delta],
                      device=d, record_cmd=True),
            wp.launch(K.variant(K.schur_col_sweep, w), dim=(lanes, p.n_c),
                      inputs=[w, p.n_r, lanes, self.piv, self.v, self.delta, self.mv], device=d, record_cmd=True),
        ]

    def direction(self, pt: Point, rtol: float | None = None) -> tuple[int, bool]:
        """Solve the Newton system for the residuals of ``pt`` (see `Point`) at the last evaluated point;
        leaves dlam = d_a + d_b and dy = dy_a on the device. Returns (linear iterations, linear solve
        converged); in the device loop that costs one read (`_direction_device` alone costs none)."""
        if self.dev is not None:
            return self.direction_later(pt, rtol)()
        p = self.p
        t0 = time.perf_counter()
        self._select_weights()
        g1 = self._host_vec(pt.g1)
        g2 = self._host_vec(pt.g2)
        e1 = self.to_host(self.row_w) + p.b_r
        self.to_device(self.e1, e1)
        self.to_device(self.g1, g1)
        cg = self.o.linear_solver != "direct"
        fresh = cg and (self._M is None or self._M_fresh_needed)
        self._prep(self.g1, fresh)
        rhs = -g2 + self.to_host(self.wtg)
        data = linear.SchurData(self.to_host(self.diag_s).copy(), e1, self.to_host(self.piv).copy(), p.a_c,
                                not p.partial)
        self.t.prep += time.perf_counter() - t0
        n_lin, ok = 0, True
        if self.o.linear_solver == "direct":
            t0 = time.perf_counter()
            dy = linear.direct_solve(self.to_host(self.W), data, rhs)
            self.t.direct += time.perf_counter() - t0
            n_lin = 1
        else:
            if fresh:
                self._build_preconditioner(data)
            t0 = time.perf_counter()
            rtol = self.o.cg_rtol if rtol is None else max(rtol, self.o.cg_rtol)
            dy, info = linear.pcg(self._matvec, rhs, self._M, rtol=rtol,
                                  max_iter=self.o.cg_max_iter, gauge=not p.partial)
            self.t.cg += time.perf_counter() - t0
            n_lin, ok = info.iterations, info.converged
            self._after_solve(fresh, n_lin, ok)
            if not fresh and not ok:
                # and re-solve now, with a fresh preconditioner (and row top-k)
                self._row_topk()
                self._build_preconditioner(data)
                t0 = time.perf_counter()
                dy, info = linear.pcg(self._matvec, rhs, self._M, rtol=self.o.cg_rtol,
                                      max_iter=self.o.cg_max_iter, gauge=not p.partial)
                self.t.cg += time.perf_counter() - t0
                n_lin += info.iterations
                ok = info.converged
                self._M_iters = info.iterations
        t0 = time.perf_counter()
        self.to_device(self.dy_a, dy)
        self._recover(self.g1)
        self.t.other += time.perf_counter() - t0
        return n_lin, ok

    def direction_later(self, pt: Point, rtol: float | None = None) -> Callable[[], tuple[int, bool]]:
        """`direction`, with its (linear iterations, converged) from the returned function, to be called
        before the second direction after it. In the device loop nothing is read now: the counts come with
        the next read of the device's scalars (an evaluation, `read_scalars`), or the function reads them."""
        if self.dev is None:
            res = self.direction(pt, rtol)
            return lambda: res
        fresh = self._direction_device(pt, rtol)
        dev = self.dev
        reads, solves = dev.n_reads, dev.n_solves

        def result() -> tuple[int, bool]:
            back = dev.n_solves - solves
            if back > 1:
                raise RuntimeError("direction_later: two more directions were solved before this one's counts "
                                   "were read")
            if dev.n_reads == reads:
                dev.read()
            n_lin, ok = dev.cg_result(back)
            self.t.n_matvec += n_lin
            self._after_solve(fresh, n_lin, ok)
            return n_lin, ok
        return result

    def _direction_device(self, pt: Point, rtol: float | None) -> str | bool:
        """`direction` in the device loop, with no host read: right-hand side, preconditioner (when it is
        rebuilt), CG and back-substitution as kernels; CG's count and convergence land in ``dev.scal``.
        Returns how the preconditioner was rebuilt ("build", "refit"), or False when it was reused."""
        p, dev = self.p, self.dev
        t0 = time.perf_counter()
        self._select_weights()
        dev.set_residual(pt)
        wp.launch(resident.add_vec, dim=p.n_r, inputs=[self.row_w, self.b, self.e1], device=p.device)
        fresh = self._M is None or self._M_fresh_needed
        self._prep(dev.g1, fresh)
        wp.launch(resident.schur_rhs, dim=p.n_c, inputs=[dev.g2, self.wtg, dev.gauge, dev.r], device=p.device)
        self.t.prep += time.perf_counter() - t0
        if fresh:
            t0 = time.perf_counter()
            self._col_topk()
            if dev.rebuild_preconditioner():
                self.t.n_factor += 1
                self.t.n_build_sync += resident.BUILD_SYNCS
                fresh = "build"
            else:
                self.t.n_refit += 1
                fresh = "refit"
            self._M = dev.M
            self._M_fresh_needed = False
            self.t.precond += time.perf_counter() - t0
        t0 = time.perf_counter()
        dev.solve(self.o.cg_rtol if rtol is None else max(rtol, self.o.cg_rtol), self.o.cg_max_iter)
        self.t.cg += time.perf_counter() - t0
        t0 = time.perf_counter()
        self._recover(dev.g1)
        self.t.other += time.perf_counter() - t0
        return fresh

    def _after_solve(self, fresh: str | bool, n_lin: int, ok: bool) -> None:
        """The reuse rule: a fresh preconditioner's count is the reference; a reused one that failed or took
        more than `REFRESH_EXTRA_CG` iterations beyond it has gone stale and is rebuilt at the next point.
        In the device loop a rebuild first refits the last pattern; a refit that fails or needs more than
        `REFIT_SLOWDOWN` x the last full build's count (+ `REFRESH_EXTRA_CG`) is replaced by a full build at
        the next point, and the refits stop until then."""
        if fresh == "refit":
            if not ok or n_lin > REFIT_SLOWDOWN * self._M_iters + REFRESH_EXTRA_CG:
                self.dev.refit_ok = False
                self._M_fresh_needed = True
        elif fresh:
            self._M_iters = n_lin
        elif not ok or n_lin > self._M_iters + REFRESH_EXTRA_CG:
            self._M_fresh_needed = True

    def _host_vec(self, v) -> np.ndarray:
        """A right-hand side as a host array (a device array is read)."""
        return self.to_host(v) if isinstance(v, wp.array) else v

    def _select_weights(self) -> None:
        """The W source of this point's Schur kernels (matrix-free: its duals' buffers alternate, so the
        matvec is recorded again)."""
        if self.lazy:
            if self.o.linear_solver == "direct":
                raise ValueError("linear_solver='direct' needs the dense weight matrix, which the matrix-free "
                                 "mode does not store; use linear_solver='cg'")
            self._wsrc = self.weights()
            self._matvec_cmd = None
        else:
            self._wsrc = self._wsink

    def _prep(self, g1: wp.array, fresh: bool) -> None:
        """S_W's diagonal and W^T E1^-1 g1 (into ``diag_s``, ``wtg``), and the rows' top-k when the
        preconditioner is rebuilt (``fresh``)."""
        p = self.p
        self.diag_s.zero_()
        self.wtg.zero_()
        if self.lanes:
            wp.launch(K.variant(K.schur_prep_cols, self._wsrc), dim=(self.lanes, p.n_c),
                      inputs=[self._wsrc, p.n_r, self.lanes, self.piv, self.tail, self.e1, self.b, g1,
                              self.diag_s, self.wtg], device=p.device)
            if fresh:
                self._row_topk()
        else:
            wp.launch(K.variant(K.schur_prep, self._wsrc), dim=p.n_r,
                      inputs=[self._wsrc, p.n_c, self.piv, self.tail, self.e1, self.b, g1, self.kk if fresh else 0],
                      outputs=[self.diag_s, self.wtg, self.top_val, self.top_idx], device=p.device)

    def _row_topk(self) -> None:
        p = self.p
        wp.launch(K.variant(K.schur_prep_topk, self._wsrc), dim=p.n_r, inputs=[self._wsrc, p.n_c, self.kk],
                  outputs=[self.top_val, self.top_idx], device=p.device)

    def _col_topk(self) -> None:
        p = self.p
        wp.launch(K.variant(K.col_topk, self._wsrc), dim=p.n_c,
                  inputs=[self._wsrc, p.n_r, self.piv, self.ctop_val.shape[1]],
                  outputs=[self.ctop_val, self.ctop_idx], device=p.device)

    def _recover(self, g1: wp.array) -> None:
        """dlam = d_a + d_b from dy (``dy_a``): the back-substitution of the eliminated rows."""
        p = self.p
        if self.lanes:
            self.delta.zero_()
            wp.launch(K.variant(K.schur_row_partial, self._wsrc), dim=(p.n_r, self.lanes),
                      inputs=[self._wsrc, p.n_c, self.lanes, self.piv, self.dy_a, self.delta], device=p.device)
            wp.launch(K.recover_finish, dim=p.n_r, inputs=[self.piv, self.e1, self.b, g1, self.dy_a, self.delta],
                      outputs=[self.d_a, self.d_b], device=p.device)
        else:
            wp.launch(K.variant(K.recover_rows, self._wsrc), dim=p.n_r,
                      inputs=[self._wsrc, p.n_c, self.piv, self.e1, self.b, g1, self.dy_a],
                      outputs=[self.d_a, self.d_b], device=p.device)

    def _build_preconditioner(self, data: linear.SchurData):
        """Top-k selection per column (Warp), assembly and factorization of the sparse approximation."""
        p = self.p
        t0 = time.perf_counter()
        self._col_topk()
        P = linear.assemble_sparse_schur(data, self.to_host(self.top_val), self.to_host(self.top_idx),
                                         self.to_host(self.ctop_val), self.to_host(self.ctop_idx))
        self._M = linear.SchurPreconditioner(P, p.a_c, not p.partial)
        self._M_fresh_needed = False
        self.t.precond += time.perf_counter() - t0
        self.t.n_factor += 1

    def invalidate_preconditioner(self) -> None:
        """Rebuild the preconditioner at the next Newton direction (the weights it was built from no longer
        describe the problem, e.g. after the interior-point start)."""
        self._M_fresh_needed = True

    def trial(self, alpha: float) -> None:
        """The trial duals (``lam_t``, ``y_t``) = current + ``alpha`` x the last `direction`."""
        self.trial_from(self._no_limit, 0, 1.0, alpha)

    def trial_from(self, steps: wp.array, slot: int, coef: float = 1.0, factor: float = 1.0) -> None:
        """`trial` with a step length computed on the device, alpha = factor min(1, coef steps[slot]) (no read)."""
        p = self.p
        for (hi, lo), d_a, d_b, (out_hi, out_lo), n in ((self.lam, self.d_a, self.d_b, self.lam_t, p.n_r),
                                                         (self.y, self.dy_a, self.zero_c, self.y_t, p.n_c)):
            wp.launch(K.dd_axpy, dim=n, inputs=[hi, lo, steps, slot, coef, factor, d_a, d_b],
                      outputs=[out_hi, out_lo], device=p.device)

    def read_scalars(self, arr: wp.array) -> np.ndarray:
        """A small device array to the host, in one read that also brings the device loop's scalars (the last
        directions' CG counts) when there is one."""
        if self.dev is not None:
            return self.dev.read(arr)
        return self.to_host(arr).copy()

    def accept(self) -> None:
        """The trial duals become the current ones (the buffers are swapped, nothing is copied)."""
        self.lam, self.lam_t = self.lam_t, self.lam
        self.y, self.y_t = self.y_t, self.y

    def newton(self, beta: float, pt: Point) -> tuple[Point, int, int, bool]:
        """Newton's method with backtracking on the residual norm ||g||_2 (accurate at any beta: the
        marginal sums are sums of positive terms). Returns (point, newton iterations, linear iterations,
        converged).

        In the device loop each trial point costs one host read (its evaluation's sums; the first also
        brings the direction's CG count and step limit), and the line search starts at `STEP_GROWTH` times
        the last accepted step of this call (at most the full step), since a halving costs an evaluation and
        a read."""
        n_newton = n_lin = 0
        last = 1.0  # the last accepted step, as a fraction of its first trial
        while pt.residual > self.o.newton_tol:
            if n_newton >= self.o.max_newton:
                return pt, n_newton, n_lin, False
            reused = self._M is not None and not self._M_fresh_needed
            counts, limit = self._step_start(beta, pt)
            n_newton += 1
            self.t.n_newton += 1
            factor = 1.0 if self.dev is None else min(1.0, STEP_GROWTH * last)
            alpha, accepted = 1.0, False
            for j in range(60):
                if self.dev is None:
                    self.trial(factor * limit)
                else:
                    self.trial_from(self.dev.scal, resident.LIMIT_SLOT, resident.LIMIT_FRACTION, factor)
                tp = self.evaluate(self.lam_t, self.y_t, beta, full=True)
                if j == 0:  # in the device loop, the read that came with this evaluation brought these
                    k_lin, _ = counts()
                    if self.dev is not None:
                        limit = resident.step_alpha(self.dev.limit())
                alpha = factor * limit
                if tp.merit <= (1.0 - 1e-4 * alpha) * pt.merit:
                    accepted = True
                    break
                factor *= 0.5
            n_lin += k_lin
            if not accepted:
                # no decrease possible at working precision: keep the best point we have
                pt = self.evaluate(self.lam, self.y, beta, full=True)
                return pt, n_newton, n_lin, pt.residual <= self.o.newton_tol
            self.accept()
            last = factor
            if self.o.verbose > 1:
                print(f"    newton {n_newton}: alpha={alpha:.3g} merit {pt.merit:.3e} -> {tp.merit:.3e} "
                      f"res {tp.residual:.2e} cg={k_lin}")
            if reused and alpha == 1.0 and tp.merit > 0.25 * pt.merit:
                # a full step that gained little: the reused preconditioner may have steered CG (stopped at
                # its relative tolerance) to a poor direction; rebuild it at the next step
                self._M_fresh_needed = True
            pt = tp
        return pt, n_newton, n_lin, True

    def _step_start(self, beta: float, pt: Point) -> tuple[Callable[[], tuple[int, bool]], float]:
        """The Newton direction at ``pt`` (the last evaluated point) and the first trial step: returns (the
        direction's `direction_later` function, first step length); in the device loop the step length
        comes with the first trial's read (NaN here, the step limit left on the device).

        The step is cut to 90 % of the way to s = 0 on each row's pivot entry (its reduced cost moves by
        d_b exactly), for pivots in phi's 1/x tail (beta s > FTB_MIN_X): there the linear model overshoots
        (G ~ 1/(beta s)). s = 0 is not a bound (phi is smooth, G < 1): a pivot already near it is left to
        the line search, otherwise every step would stop 90% of the way and the iteration stall."""
        rtol = min(CG_LOOSE, pt.residual)
        if self.dev is not None:
            counts = self.direction_later(Point(None, None, 0.0, 0.0), rtol)
            self.dev.step_limit(beta, FTB_MIN_X)
            return counts, math.nan
        counts = self.direction_later(pt, rtol)
        db = self.to_host(self.d_b)
        spv = self.to_host(self.s_piv)
        neg = (db < 0) & (spv * beta > FTB_MIN_X)
        limit = math.inf
        if np.any(neg):
            limit = float(np.min(spv[neg] / -db[neg]))
        return counts, resident.step_alpha(limit)

    # ------------------------------------------------------------------ duals
    def init_point(self, lam0: np.ndarray, y0: np.ndarray):
        """Set the duals to (lam0 (n_r,), y0 (n_c,)) (normalized units, the engine's orientation)."""
        self.to_device(self.lam[0], lam0)
        self.lam[1].zero_()
        self.to_device(self.y[0], y0)
        self.y[1].zero_()

    def snapshot(self, into: DualSnapshot | None = None) -> DualSnapshot:
        """A copy of the current duals, into ``into``'s arrays when given (no allocation)."""
        if into is None:
            return DualSnapshot(tuple(wp.clone(a) for a in self.lam), tuple(wp.clone(a) for a in self.y))
        for s, t in zip((*self.lam, *self.y), (*into.lam, *into.y)):
            wp.copy(t, s)
        return into

    def restore(self, snap: DualSnapshot) -> None:
        """Copy the duals of ``snap`` back into the current ones."""
        for s, t in zip((*snap.lam, *snap.y), (*self.lam, *self.y)):
            wp.copy(t, s)

    # ------------------------------------------------------------------ values and outputs
    def penalty(self) -> float:
        """Partial: sum alpha1' m1^2 + sum alpha2' m2^2 (normalized units) with m = the marginals of the last
        evaluation; 0 for balanced transport."""
        if not self.p.partial:
            return 0.0
        m1 = self.to_host(self.row_g)
        m2 = self.to_host(self.col_g)
        return float(0.5 * np.sum(m1 * m1 / self.p.b_r) + 0.5 * np.sum(m2 * m2 / self.p.a_c))

    def plan(self, beta: float) -> np.ndarray:
        """The dense plan (N1, N2) in the user's orientation at ``beta`` and the current duals (normalized:
        multiply by the total mass). On the CPU it is a view of the device array."""
        p = self.p
        shape = (p.n_c, p.n_r) if p.trans else (p.n_r, p.n_c)
        G = wp.zeros(shape, dtype=wp.float64, device=p.device)
        wp.launch(K.variant(K.plan_kernel, self.csrc), dim=p.n_r,
                  inputs=[self.csrc, p.trans, p.n_c, beta, self.lam[0], self.lam[1], self.y[0],
                          self.y[1]], outputs=[G], device=p.device)
        return self.to_host(G)

    def plan_top(self, beta: float, topk: int) -> tuple[np.ndarray, np.ndarray]:
        """Each user row's ``topk`` largest plan entries at ``beta`` and the current duals ((N1, topk)
        float64, descending) and their column indices ((N1, topk) int32), computed in one pass without
        forming the plan."""
        p = self.p
        n1, n2 = (p.n_c, p.n_r) if p.trans else (p.n_r, p.n_c)
        kk = min(int(topk), n2)
        val = wp.zeros((n1, kk), dtype=wp.float64, device=p.device)
        idx = wp.zeros((n1, kk), dtype=wp.int32, device=p.device)
        wp.launch(K.variant(K.plan_topk, self.csrc), dim=n1,
                  inputs=[self.csrc, p.trans, p.n_r, p.n_c, beta, self.lam[0], self.lam[1], self.y[0],
                          self.y[1], kk], outputs=[val, idx], device=p.device)
        return self.to_host(val), self.to_host(idx)
