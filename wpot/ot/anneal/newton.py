"""The solver state of one OT problem and Newton's method at fixed beta (shared by balanced and partial).

State lives in preallocated Warp arrays on the solve device; the O(N1 N2) work (phi, phi', row and
column sums, U, F, Schur matvecs) runs in `wpot.ot.kernels`. The Newton steps run in one of two loops
(`EngineOptions.newton_loop`), each a `wpot.ot.anneal.schur.NewtonSolver` that the `Engine` picks once and
holds as ``solver``: the host loop (`wpot.ot.anneal.host.HostSolver`, the default on "cpu") handles the
length-N vectors on the host (zero-copy views on "cpu"), where the CG recurrences and the SuperLU
preconditioner run; the device loop (`wpot.ot.anneal.resident.DeviceSolver`, the default on a GPU) keeps them
on the device and reads one small array per trial point. Every read of a device array goes through
`Engine.to_host` and every write of host data through `Engine.to_device`, which count them (`Timers.n_d2h`,
`Timers.n_h2d`): on a GPU each is a transfer, and each read waits for the device (a synchronisation); the
counts are the same on every device.

Two modes (`wpot.ot.kernels`): stored (a dense C, and the Hessian weights W stored by the evaluation
pass) and matrix-free (C from the signatures, W recomputed where it is read: no N1 x N2 array; each pass
over W then costs a pass over the features).

Cost per Newton step: one pass over C (`kernels.eval_rows`, at the trial point), one pass over W for the
Schur right-hand side and diagonal, one per CG iteration (two sweeps of a row) and one for the
back-substitution. The sparse preconditioner (top-k selection in Warp, then SuperLU or FSAI) is the expensive
part at large N and is reused across Newton steps and betas while CG converges about as fast as with a fresh
one (`wpot.ot.anneal.schur.REFRESH_EXTRA_CG`).

The `Engine`'s public step API (`evaluate`, `direction`, `direction_later`, `trial`, `trial_from`,
`accept`, `newton`, `free_pass`, `free_values`, `dual_sums`, `snapshot`/`restore`, `invalidate_preconditioner`,
`plan`, `plan_top`, `to_host`/`to_device`, `read_scalars`) is what the annealing loop (`wpot.ot.anneal.loop`)
and the interior-point start (`wpot.ot.anneal.ipm`) drive.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import warp as wp

from wpot.cost import METRIC_CODES
from wpot.ot import kernels as K
from wpot.ot.anneal.host import HostSolver
from wpot.ot.anneal.resident import DeviceSolver
from wpot.ot.anneal.schur import NewtonSolver
from wpot.ot.anneal.state import DualSnapshot, DualSums, Point, Timers
from wpot.ot.options import EngineOptions
from wpot.ot.problem import Internal

#: forcing term of the inexact Newton steps (Eisenstat-Walker style): CG stops at a relative residual of
#: min(CG_LOOSE, residual), but never tighter than ``cg_rtol``. Far from the solution (the damped steps of the
#: transition betas) a rough direction does as well as an accurate one
CG_LOOSE = 0.1
#: the fraction-to-zero step rule applies to pivots with beta s above this (see `Engine.newton`)
FTB_MIN_X = 1.0


def _cost_source(prob: Internal, inv_scale: float) -> tuple:
    """The evaluation kernels' cost source and W sink for ``prob``, and W: stored, a `kernels.DenseCost` over
    C and a `kernels.DenseW` over a new (n_r, n_c) float64 W; matrix-free, a `kernels.LazyCost` over the
    (oriented) signatures, `kernels.NoW` and None (W is recomputed where it is read, `Engine.weights`)."""
    if prob.cost.lazy:
        fc = prob.cost.features
        csrc = K.LazyCost()
        csrc.A, csrc.B = (fc.Y, fc.X) if prob.trans else (fc.X, fc.Y)
        csrc.metric = METRIC_CODES[fc.metric]
        csrc.inv_scale = wp.float64(inv_scale)
        return csrc, K.NoW(), None
    csrc = K.DenseCost()
    csrc.C, csrc.trans, csrc.inv_scale = prob.cost.C, prob.trans, wp.float64(inv_scale)
    wsink = K.DenseW()
    wsink.W = wp.zeros((prob.n_r, prob.n_c), dtype=wp.float64, device=prob.device)
    return csrc, wsink, wsink.W


class Engine:
    """Preallocated solver state for one internal problem (see `wpot.ot.problem.Internal`) and options
    (`wpot.ot.options.EngineOptions`, never changed once the engine holds them).

    The duals lam (n_r,), y (n_c,) are double-double pairs (``lam[0] + lam[1]``: hi, lo) on the device;
    a trial point goes to a second pair of buffers (`trial`) and becomes the current one by a swap
    (`accept`). Each evaluation (`evaluate`) leaves the device state (the weights W, the marginals, ...)
    at the point it evaluated; `direction` solves the Newton system there (through ``solver``, the host or
    the device loop).
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
        self.csrc, self._wsink, self.W = _cost_source(prob, self.inv_scale)
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
        # strided lanes on GPUs (see `SchurSolver._record_matvec`); one thread per row on the CPU (unless the options
        # say otherwise)
        if opts.matvec_lanes is None:
            self.lanes = 0 if self._host else K.MATVEC_LANES
        else:
            self.lanes = opts.matvec_lanes
        self.eval_lanes = self.lanes or 1  # `K.eval_rows` runs one lane per row on the CPU
        self.lane_f = wp.zeros((n_r, self.eval_lanes, 6), dtype=wp.float64, device=d)
        self.lane_p = wp.zeros((n_r, self.eval_lanes), dtype=wp.int32, device=d)
        self._w_point = None  # (lam, y, beta) of the last evaluation: the point W belongs to
        loop = opts.newton_loop
        if loop is None:
            loop = "host" if self._host or opts.linear_solver != "cg" else "device"
        #: the Newton loop: the linear solves and the loop-specific reads (`wpot.ot.anneal.schur.NewtonSolver`)
        self.solver: NewtonSolver = DeviceSolver(self) if loop == "device" else HostSolver(self)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, lam, y, beta: float, full: bool = True) -> Point:
        """One pass over C at the duals (``lam``, ``y``: (hi, lo) pairs, e.g. ``self.lam`` or the trial
        ``self.lam_t``) and ``beta``: stores W (stored mode) and the row and column sums on the device and
        returns the marginal residuals (and, with ``full``, U and the gap sum; the device loop always
        returns them, and no host residual vectors)."""
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
        pt = self.solver.point(lam, y, full)
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
        self.solver.free_sums(lam, y, pt)
        self.t.eval += time.perf_counter() - t0
        self.t.n_free += 1

    def free_values(self, pt: Point) -> Point:
        """``pt`` with sum g and its `DualSums` after `free_pass` (the last one, at ``pt``): in the device loop
        from the first read of the device's scalars since then, or from one now."""
        return self.solver.free_values(pt)

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

    # ------------------------------------------------------------------ W, for the Newton direction
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

    # ------------------------------------------------------------------ the Newton step
    def direction(self, pt: Point, rtol: float | None = None) -> tuple[int, bool]:
        """Solve the Newton system for the residuals of ``pt`` (see `Point`) at the last evaluated point;
        leaves dlam = d_a + d_b and dy = dy_a on the device. Returns (linear iterations, linear solve
        converged); in the device loop that costs one read (`direction_later` alone costs none)."""
        return self.solver.direction_later(pt, rtol)()

    def direction_later(self, pt: Point, rtol: float | None = None) -> Callable[[], tuple[int, bool]]:
        """`direction`, with its (linear iterations, converged) from the returned function, to be called
        before the second direction after it. In the device loop nothing is read now: the counts come with
        the next read of the device's scalars (an evaluation, `read_scalars`), or the function reads them."""
        return self.solver.direction_later(pt, rtol)

    def invalidate_preconditioner(self) -> None:
        """Rebuild the preconditioner at the next Newton direction (the weights it was built from no longer
        describe the problem, e.g. after the interior-point start)."""
        self.solver.invalidate_preconditioner()

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
        return self.solver.read_scalars(arr)

    def accept(self) -> None:
        """The trial duals become the current ones (the buffers are swapped, nothing is copied)."""
        self.lam, self.lam_t = self.lam_t, self.lam
        self.y, self.y_t = self.y_t, self.y

    def newton(self, beta: float, pt: Point) -> tuple[Point, int, int, bool]:
        """Newton's method with backtracking on the residual norm ||g||_2 (accurate at any beta: the
        marginal sums are sums of positive terms). Returns (point, newton iterations, linear iterations,
        converged).

        Each direction is solved to a relative residual of min(`CG_LOOSE`, residual). Its first trial step
        is cut to 90 % of the way to s = 0 on each row's pivot entry (its reduced cost moves by d_b
        exactly), for pivots in phi's 1/x tail (beta s > `FTB_MIN_X`): there the linear model overshoots
        (G ~ 1/(beta s)). s = 0 is not a bound (phi is smooth, G < 1): a pivot already near it is left to
        the line search, otherwise every step would stop 90% of the way and the iteration stall.

        In the device loop each trial point costs one host read (its evaluation's sums; the first also
        brings the direction's CG count and step limit), and the line search starts at
        `wpot.ot.anneal.resident.STEP_GROWTH` times the last accepted step of this call (at most the full
        step), since a halving costs an evaluation and a read."""
        solver = self.solver
        n_newton = n_lin = 0
        last = 1.0  # the last accepted step, as a fraction of its first trial
        while pt.residual > self.o.newton_tol:
            if n_newton >= self.o.max_newton:
                return pt, n_newton, n_lin, False
            reused = solver.preconditioner_reused()
            counts, limit = solver.step_start(beta, pt, min(CG_LOOSE, pt.residual), FTB_MIN_X)
            n_newton += 1
            self.t.n_newton += 1
            factor = solver.first_factor(last)
            alpha, accepted = 1.0, False
            for j in range(60):
                solver.trial(factor, limit)
                tp = self.evaluate(self.lam_t, self.y_t, beta, full=True)
                if j == 0:  # in the device loop, the read that came with this evaluation brought these
                    k_lin, _ = counts()
                    limit = solver.step_length(limit)
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
                solver.invalidate_preconditioner()
            pt = tp
        return pt, n_newton, n_lin, True

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
