"""The annealing loop of Algorithm 1 over an `Engine`'s public step API (shared by balanced and partial).

beta goes up the geometric grid `wpot.ot.anneal.schedule.beta_schedule` (from ``beta0``, or from the hand-off
beta of the interior-point start); at each beta the saddle point is found by `Engine.newton`, warm-started
by a tangent predictor (the duals extrapolated linearly in 1/beta). The loop stops when the relative
change of U falls below ``tol`` (or |dU| below ``atol``). Per beta: one pass for the predictor (two or
more when it is rejected), the Newton steps, one pass for F and the tangent's right-hand side
(`Engine.free_pass`) and one tangent solve.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import warnings
from dataclasses import dataclass
from typing import Callable

from wpot.ot.anneal.newton import Engine
from wpot.ot.anneal.state import DualSnapshot, Point
from wpot.ot.anneal.schedule import beta_schedule, relative_change

__all__ = ["AnnealOutcome", "anneal", "warn_not_converged", "MIN_SPLIT_STEP"]

#: a beta step that fails (max_newton reached) is split at its geometric midpoint, down to this ratio
#: (10 ** (1/16): four halvings of the default step in log beta)
MIN_SPLIT_STEP = 10.0 ** (1.0 / 16.0)

#: free_energy(engine, point, beta) -> F at the solved point (normalized units), Eq. 12 or Eq. 23
FreeEnergy = Callable[[Engine, Point, float], float]


@dataclass(frozen=True)
class AnnealOutcome:
    """What `anneal` reached, in normalized units.

    records : one dict per solved beta: beta, u (U), obj (U plus the partial penalty), f (F), nn, nl
        (Newton and linear iterations), res (residual), gap (gap bound), ok (Newton converged)
    converged : stopped by tol/atol with every Newton solve converged; stopped : stopped by tol/atol;
    newton_ok : every recorded Newton solve converged; n_newton, n_linear : totals (including failed and
    split steps, and any work added by the caller, e.g. the interior-point start)
    failed_beta : the beta whose Newton solve failed with no shorter step left (None otherwise)
    beta, point : the final beta and the evaluated `Point` there; the engine's duals are those of it
    """

    records: tuple[dict, ...]
    converged: bool
    stopped: bool
    newton_ok: bool
    n_newton: int
    n_linear: int
    failed_beta: float | None
    beta: float
    point: Point

    def add_work(self, n_newton: int, n_linear: int) -> AnnealOutcome:
        """The same outcome with iterations spent before the annealing (the interior-point start) added."""
        return dataclasses.replace(self, n_newton=self.n_newton + n_newton, n_linear=self.n_linear + n_linear)


def _tangent(eng: Engine, pt: Point) -> Callable[[], int]:
    """d(lam, y)/d(log beta) at the solved point ``pt`` (device state at it, after `Engine.free_pass`), left
    in the engine's direction arrays for `_predict`; skipped when the extrapolation is off or the point is
    not accurate enough. Returns a function that gives its linear iterations, to be called after the
    predictor's evaluation (whose read brings them, in the device loop) and before the next direction."""
    o = eng.o
    if o.extrapolate and pt.residual <= o.newton_tol * 1e3:
        # direction() solves J d = -g: with g = (row, column sums of W s), d = d(lam, y)/d(log beta)
        result = eng.direction_later(Point(eng.row_ws, eng.col_ws, 0.0, 0.0))
        return lambda: result()[0]
    return lambda: 0


def _refresh_tangent(eng: Engine, beta: float) -> Callable[[], int]:
    """Re-evaluate the (restored) duals at ``beta`` and recompute the tangent there (a failed Newton solve
    overwrote the device state and the direction arrays). Returns `_tangent`'s function."""
    pt = eng.evaluate(eng.lam, eng.y, beta)
    eng.free_pass(eng.lam, eng.y, beta, pt)
    return _tangent(eng, pt)


def _predict(eng: Engine, beta: float, beta_prev: float) -> Point:
    """Tangent predictor: (lam, y) + alpha d(lam, y)/d(log beta) with alpha = 1 - 1/q, i.e. linear in
    1/beta (exact when the duals behave like v* + a/beta). Without it the plan's entries (~ 1/(beta s))
    all shrink by q and the residual is ~ 1 - 1/q; the prediction is kept at once when its residual is
    below half of that, otherwise it is compared with the unmoved point and halved (3 times at most).
    Returns the evaluated point; the device state is left at it."""
    q = beta / beta_prev
    alpha = 1.0 - 1.0 / q
    eng.trial(alpha)
    tp = eng.evaluate(eng.lam_t, eng.y_t, beta)
    if tp.residual <= 0.5 * alpha:
        eng.accept()
        return tp
    pt = eng.evaluate(eng.lam, eng.y, beta)
    for _ in range(3):
        alpha *= 0.5
        eng.trial(alpha)
        tp = eng.evaluate(eng.lam_t, eng.y_t, beta)
        if tp.merit < pt.merit:
            eng.accept()
            return tp
    return eng.evaluate(eng.lam, eng.y, beta)


def anneal(eng: Engine, free_energy: FreeEnergy, *, beta0: float | None = None,
           on_beta: Callable[[dict], None] | None = None) -> AnnealOutcome:
    """Algorithm 1 from the engine's current duals: the betas ``beta0`` (default: the options' beta0),
    x step, ... up to beta_max (normalized units), at most max_iter of them. ``on_beta`` is called with each
    solved beta's record (as `AnnealOutcome.records` holds them) as soon as it is solved (progress reports).

    A Newton solve that fails after a solved beta goes back to that beta's duals and reaches the failed
    beta through the geometric midpoint (down to `MIN_SPLIT_STEP`); with no shorter step left, the result is
    the last solved beta's (``failed_beta`` says which one failed)."""
    o = eng.o
    betas = beta_schedule(o.beta0 if beta0 is None else beta0, o.step, o.beta_max)
    raw: list[dict] = []
    solved: list[float] = []  # the solved betas (each gets a record)
    # the last solved beta, point and counts, whose record waits for the free-energy sums: in the device loop
    # they come with the next read (the next beta's first evaluation)
    pending: tuple | None = None

    def record(beta: float, pt: Point, nn: int, nl: int, ok: bool) -> None:
        eng.free_values(pt)
        obj = pt.u + eng.dual_sums(pt).penalty
        fe = free_energy(eng, pt, beta)
        rec = dict(beta=beta, u=pt.u, obj=obj, f=fe, nn=nn, nl=nl, res=pt.residual, gap=pt.xphi / beta, ok=ok)
        raw.append(rec)
        if on_beta is not None:
            on_beta(rec)
        if o.verbose:
            print(f"  beta={beta:.3e} U={pt.u:.12g} res={pt.residual:.2e} newton={nn} cg={nl} "
                  f"gap<={pt.xphi / beta:.2e} t_eval={eng.t.eval:.2f}s")

    all_newton_ok = True
    stopped = False
    u_prev = None
    n_newton_tot = n_lin_tot = 0
    n_tangent = lambda: 0  # noqa: E731  (the last tangent's linear iterations, counted when the predictor uses it)
    good: DualSnapshot | None = None  # the duals at the last beta whose Newton solve converged
    failed_beta = None
    final_beta, final_pt = math.nan, None
    targets = list(betas)
    while targets:
        beta = targets.pop(0)
        if len(solved) >= o.max_iter:
            break
        if solved and o.extrapolate:
            pt = _predict(eng, beta, solved[-1])
            n_lin_tot += n_tangent()
        else:
            pt = eng.evaluate(eng.lam, eng.y, beta)
        if pending is not None:
            record(*pending)
            pending = None
        pt, nn, nl, ok = eng.newton(beta, pt)
        if not ok and good is not None:
            # a failed solve after a solved beta (good holds that beta's duals, raw[-1] its record): its
            # iterate can be far from feasible, so go back to the solved duals
            n_newton_tot += nn
            n_lin_tot += nl
            eng.restore(good)
            beta_prev = solved[-1]
            if beta / beta_prev > MIN_SPLIT_STEP:
                # the step was too long for max_newton damped steps (as on real 5k-vertex WKS pairs at the
                # plan's spread-to-permutation transition): reach beta through the geometric midpoint
                n_tangent = _refresh_tangent(eng, beta_prev)
                targets[:0] = [math.sqrt(beta_prev * beta), beta]
                continue
            # no shorter step left (a failed step can leave U far off while the previous beta was within the
            # tolerance of the optimum; the docs' Results page): end at the last solved beta
            failed_beta = beta
            all_newton_ok = False
            beta = beta_prev
            pt = eng.evaluate(eng.lam, eng.y, beta)
            eng.free_pass(eng.lam, eng.y, beta, pt)
            final_beta, final_pt = beta, pt
            break
        # the device state (W, marginals, ...) is that of the current point: add F and W s
        eng.free_pass(eng.lam, eng.y, beta, pt)
        n_tangent = _tangent(eng, pt)
        all_newton_ok &= ok
        n_newton_tot += nn
        n_lin_tot += nl
        pending = (beta, pt, nn, nl, ok)
        solved.append(beta)
        final_beta, final_pt = beta, pt
        if ok:
            good = eng.snapshot(into=good)
        if u_prev is not None and ok:
            # Algorithm 1 on the transport cost U (for the partial problem the penalty would mask it)
            if relative_change(u_prev, pt.u) < o.tol or abs(pt.u - u_prev) <= o.atol:
                stopped = True
                break
        u_prev = pt.u
    if pending is not None:
        record(*pending)
    if o.verbose:
        print("  timers:", {k: round(v, 3) if isinstance(v, float) else v for k, v in eng.t.as_dict().items()})
    return AnnealOutcome(records=tuple(raw), converged=stopped and all_newton_ok, stopped=stopped,
                         newton_ok=all_newton_ok, n_newton=n_newton_tot, n_linear=n_lin_tot,
                         failed_beta=failed_beta, beta=final_beta, point=final_pt)


def _stacklevel_outside_ot() -> int:
    """The `warnings.warn` stacklevel, seen from the caller of this function, of the first frame outside
    the ``wpot.ot`` package (the user's call, however deep the solver's layers are)."""
    def inside(frame) -> bool:
        name = frame.f_globals.get("__name__", "")
        return name == "wpot.ot" or name.startswith("wpot.ot.")

    frame, level = sys._getframe(2), 2
    while frame is not None and inside(frame):
        frame, level = frame.f_back, level + 1
    return level


def warn_not_converged(kind: str, out: AnnealOutcome) -> None:
    """A RuntimeWarning saying why the annealing did not converge and what to change (nothing if it did)."""
    if out.converged:
        return
    if out.failed_beta is not None:
        last = out.records[-1]
        msg = (f"{kind}: the Newton solve failed at beta={out.failed_beta:.3g} (normalized); the result is that "
               f"of the last solved beta={last['beta']:.3g}, whose U is optimal to within its gap bound "
               f"{last['gap']:.2g} (normalized units) but which did not meet tol; increase max_newton or cg_max_iter, "
               "or try linear_solver='direct'")
    elif not out.newton_ok:
        msg = (f"{kind}: a Newton solve did not reach its tolerance (see result.history residuals); "
               "increase max_newton, use a smaller step, or try linear_solver='direct'")
    else:
        msg = (f"{kind}: annealing stopped before the relative change of U fell below tol "
               f"(reached beta={out.records[-1]['beta'] if out.records else float('nan'):.3g} normalized); "
               "increase max_iter or beta_max, or loosen tol")
    warnings.warn(msg, RuntimeWarning, stacklevel=_stacklevel_outside_ot())
