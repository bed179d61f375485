"""The Schur-complement side of a Newton direction, shared by the host and the device Newton loops, and the
interface (`NewtonSolver`) through which `wpot.ot.anneal.newton.Engine` drives either loop.

At the engine's last evaluated point the Newton system of Eq. 14-16 (balanced) or Eq. 25-26 (partial) is
solved in Schur-complement form (`wpot.ot.anneal.linear`): the rows are eliminated, S dy = -g2 + W^T E1^-1 g1
is solved on the n_c columns, and dlam = d_a + d_b is recovered row by row. Both loops run the same kernels
(`wpot.ot.kernels`) for the parts that touch W: S_W's diagonal and W^T E1^-1 g1 (`SchurSolver._prep`), the
top-k weights per row and column of W from which the sparse preconditioner P is built, the matvec S_W v
(`SchurSolver.matvec_launches`) and the back-substitution (`SchurSolver._recover`). They differ in where the
length-N vectors live and where the CG recurrences and the preconditioner run:

* `wpot.ot.anneal.host.HostSolver` (``newton_loop="host"``): on the host; CG with P factorized by SuperLU,
  or a dense direct solve (``linear_solver="direct"``);
* `wpot.ot.anneal.resident.DeviceSolver` (``newton_loop="device"``): on the device; CG as kernels with P
  approximately inverted by FSAI (in a multilevel V-cycle), one host read per trial point.

The engine picks one from the options when it is built and holds it as ``Engine.solver``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np
import warp as wp

from wpot.ot import kernels as K
from wpot.ot.anneal.state import Point

if TYPE_CHECKING:  # pragma: no cover
    from wpot.ot.anneal.newton import Engine

__all__ = ["LIMIT_FRACTION", "NewtonSolver", "REFRESH_EXTRA_CG", "SchurSolver", "step_alpha"]

#: a preconditioner is reused (across Newton steps and betas) until a CG solve with it takes more than
#: this many iterations beyond the count of its first solve (or a full Newton step with it gains less than
#: 4x); it is then rebuilt at the next Newton point (in the host loop at once, with a re-solve, when CG failed)
REFRESH_EXTRA_CG = 2
#: a Newton step's first trial stops this fraction of the way to its step limit (the nearest s = 0 on a
#: row's pivot, see `wpot.ot.anneal.newton.Engine.newton`)
LIMIT_FRACTION = 0.9


def step_alpha(limit: float) -> float:
    """The Newton step's first trial length for a step limit: min(1, `LIMIT_FRACTION` x ``limit``) (what
    `wpot.ot.anneal.newton.Engine.trial_from` computes on the device from a limit there)."""
    return min(1.0, LIMIT_FRACTION * limit)


class NewtonSolver(Protocol):
    """The loop-specific half of `wpot.ot.anneal.newton.Engine`'s Newton steps: the reads of an evaluation,
    the Newton direction and the first trial step. ``lam``, ``y`` are (hi, lo) pairs of device arrays."""

    def point(self, lam, y, full: bool) -> Point:
        """The `Point` (residuals and sums) at the duals the engine's evaluation pass just saw."""

    def free_sums(self, lam, y, pt: Point) -> None:
        """After the engine's free-energy pass at ``pt``: sum g and the `DualSums`, or their later read."""

    def free_values(self, pt: Point) -> Point:
        """``pt`` with the sums `free_sums` started (reading them when they have not been read yet)."""

    def read_scalars(self, arr: wp.array) -> np.ndarray:
        """A small device array to the host, in one read."""

    def direction_later(self, pt: Point, rtol: float | None) -> Callable[[], tuple[int, bool]]:
        """Solve the Newton system for ``pt``'s residuals; the function returns (linear iterations, converged)."""

    def step_start(self, beta: float, pt: Point, rtol: float,
                   min_x: float) -> tuple[Callable[[], tuple[int, bool]], float]:
        """The Newton direction at ``pt`` and the first trial step length (NaN: it stays on the device)."""

    def first_factor(self, last: float) -> float:
        """The line search's first fraction of the first trial step, given the last accepted one (``last``)."""

    def trial(self, factor: float, limit: float) -> None:
        """The trial duals at ``factor`` x the first trial step (``limit`` from `step_start`)."""

    def step_length(self, limit: float) -> float:
        """The first trial step length, known once the first trial point has been read."""

    def preconditioner_reused(self) -> bool:
        """Whether the next direction reuses the current preconditioner."""

    def invalidate_preconditioner(self) -> None:
        """Rebuild the preconditioner at the next direction."""


class SchurSolver:
    """The Schur-complement kernels and the preconditioner reuse rule that `HostSolver` and `DeviceSolver`
    share, over the arrays of the engine ``e`` (the weights W, the row pivots, E1, S_W's diagonal, the
    top-k lists, the matvec's ``v`` / ``mv`` and the direction d_a, d_b, dy_a)."""

    def __init__(self, eng: Engine):
        self.e = eng
        self._wsrc = None  # the W source of the current direction's kernels (`_select_weights`)
        self._matvec_cmd = None  # the recorded matvec launches for that source
        self._M = None  # the sparse preconditioner, reused across Newton steps and betas while it works
        self._M_iters = 0  # CG iterations of its first solve
        self._M_fresh_needed = False

    # ------------------------------------------------------------------ preconditioner reuse
    def preconditioner_reused(self) -> bool:
        """Whether the next direction reuses the current preconditioner (there is one, and it is not stale)."""
        return self._M is not None and not self._M_fresh_needed

    def invalidate_preconditioner(self) -> None:
        """Rebuild the preconditioner at the next Newton direction."""
        self._M_fresh_needed = True

    def _after_solve(self, fresh: str | bool, n_lin: int, ok: bool) -> None:
        """The reuse rule: a fresh preconditioner's count is the reference; a reused one that failed or took
        more than `REFRESH_EXTRA_CG` iterations beyond it has gone stale and is rebuilt at the next point."""
        if fresh:
            self._M_iters = n_lin
        elif not ok or n_lin > self._M_iters + REFRESH_EXTRA_CG:
            self._M_fresh_needed = True

    # ------------------------------------------------------------------ kernels over W
    def _select_weights(self) -> None:
        """The W source of this point's Schur kernels (matrix-free: its duals' buffers alternate, so the
        matvec is recorded again)."""
        e = self.e
        if e.lazy:
            if e.o.linear_solver == "direct":
                raise ValueError("linear_solver='direct' needs the dense weight matrix, which the matrix-free "
                                 "mode does not store; use linear_solver='cg'")
            self._wsrc = e.weights()
            self._matvec_cmd = None
        else:
            self._wsrc = e._wsink

    def _prep(self, g1: wp.array, fresh: bool) -> None:
        """S_W's diagonal and W^T E1^-1 g1 (into the engine's ``diag_s``, ``wtg``), and the rows' top-k when
        the preconditioner is rebuilt (``fresh``)."""
        e, p = self.e, self.e.p
        e.diag_s.zero_()
        e.wtg.zero_()
        if e.lanes:
            wp.launch(K.variant(K.schur_prep_cols, self._wsrc), dim=(e.lanes, p.n_c),
                      inputs=[self._wsrc, p.n_r, e.lanes, e.piv, e.tail, e.e1, e.b, g1, e.diag_s, e.wtg],
                      device=p.device)
            if fresh:
                self._row_topk()
        else:
            wp.launch(K.variant(K.schur_prep, self._wsrc), dim=p.n_r,
                      inputs=[self._wsrc, p.n_c, e.piv, e.tail, e.e1, e.b, g1, e.kk if fresh else 0],
                      outputs=[e.diag_s, e.wtg, e.top_val, e.top_idx], device=p.device)

    def _row_topk(self) -> None:
        """Each row's top-k weights of W (into the engine's ``top_val``, ``top_idx``)."""
        e, p = self.e, self.e.p
        wp.launch(K.variant(K.schur_prep_topk, self._wsrc), dim=p.n_r, inputs=[self._wsrc, p.n_c, e.kk],
                  outputs=[e.top_val, e.top_idx], device=p.device)

    def _col_topk(self) -> None:
        """Each column's top weights of W off the rows' pivots (into the engine's ``ctop_val``, ``ctop_idx``)."""
        e, p = self.e, self.e.p
        wp.launch(K.variant(K.col_topk, self._wsrc), dim=p.n_c,
                  inputs=[self._wsrc, p.n_r, e.piv, e.ctop_val.shape[1]],
                  outputs=[e.ctop_val, e.ctop_idx], device=p.device)

    def _recover(self, g1: wp.array) -> None:
        """dlam = d_a + d_b from dy (the engine's ``dy_a``): the back-substitution of the eliminated rows."""
        e, p = self.e, self.e.p
        if e.lanes:
            e.delta.zero_()
            wp.launch(K.variant(K.schur_row_partial, self._wsrc), dim=(p.n_r, e.lanes),
                      inputs=[self._wsrc, p.n_c, e.lanes, e.piv, e.dy_a, e.delta], device=p.device)
            wp.launch(K.recover_finish, dim=p.n_r, inputs=[e.piv, e.e1, e.b, g1, e.dy_a, e.delta],
                      outputs=[e.d_a, e.d_b], device=p.device)
        else:
            wp.launch(K.variant(K.recover_rows, self._wsrc), dim=p.n_r,
                      inputs=[self._wsrc, p.n_c, e.piv, e.e1, e.b, g1, e.dy_a],
                      outputs=[e.d_a, e.d_b], device=p.device)

    def matvec_launches(self) -> list:
        """The recorded launches of one Schur matvec, mv += S_W v (the engine's ``v``, ``mv``, and ``delta``
        zeroed first when there is more than one launch), for the current W source; recorded once per source:
        only the arrays' contents change between calls."""
        if self._matvec_cmd is None:
            self._matvec_cmd = self._record_matvec()
        return self._matvec_cmd

    def _record_matvec(self) -> list:
        """The launches of one Schur matvec (mv += S_W v). The CPU runs one thread per row, streaming its
        row of W (`K.schur_matvec`); a GPU would then run only n_r threads, each reading a strided column
        of W, and serialize on atomics into ``mv``. There the two sweeps are split into strided lanes
        (`K.schur_row_partial`, `K.schur_row_delta`, `K.schur_col_sweep`): n * MATVEC_LANES threads whose
        neighbours read neighbouring entries. Both orders compute the same sums up to rounding."""
        e, p, w, d = self.e, self.e.p, self._wsrc, self.e.p.device
        if not e.lanes:
            return [wp.launch(K.variant(K.schur_matvec, w), dim=p.n_r,
                              inputs=[w, p.n_c, e.piv, e.e1, e.b, e.v, e.mv], device=d, record_cmd=True)]
        lanes = e.lanes
        return [
            wp.launch(K.variant(K.schur_row_partial, w), dim=(p.n_r, lanes),
                      inputs=[w, p.n_c, lanes, e.piv, e.v, e.delta], device=d, record_cmd=True),
            wp.launch(K.schur_row_delta, dim=p.n_r, inputs=[e.piv, e.e1, e.b, e.v, e.delta],
                      device=d, record_cmd=True),
            wp.launch(K.variant(K.schur_col_sweep, w), dim=(lanes, p.n_c),
                      inputs=[w, p.n_r, lanes, e.piv, e.v, e.delta, e.mv], device=d, record_cmd=True),
        ]
