"""Result types of the OT solvers (frozen dataclasses; the return type never depends on a flag) and their
assembly from a solved `wpot.ot.anneal.newton.Engine`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from wpot.ot.anneal.loop import AnnealOutcome, warn_not_converged
from wpot.ot.anneal.newton import Engine


@dataclass(frozen=True)
class BetaStep:
    """One annealing step (Algorithm 1), everything in the user's units.

    beta : inverse temperature (user's cost units: beta * C is dimensionless)
    cost : U(beta) = sum_kl G(k,l) C(k,l), the transport part (Eq. 6 / first term of Eq. 17)
    free_energy : F at the saddle point (Eq. 12 balanced, Eq. 23 partial)
    n_newton, n_linear : Newton iterations and linear (CG) iterations spent at this beta
    residual : marginal residual at the end of the Newton solve, sum of |row-sum errors| and
        |column-sum errors| divided by 2 x total mass (relative, dimensionless)
    gap_bound : certified bound on U(beta) - U* (user units; the duality gap (1/beta) sum x phi(x),
        valid whenever every plan entry is < 1/2 of its marginal, always the case for N >= 3); for the
        partial problem the same quantity bounds the gap of the objective
    objective : the full objective at this beta (user units): ``cost`` plus the chi^2 mass penalties
        sum alpha1 m1^2 + sum alpha2 m2^2 of the plan's marginals (Eq. 17); equal to ``cost`` for balanced
        transport. It is the per-beta counterpart of `OTResult.objective`.
    """

    beta: float
    cost: float
    free_energy: float
    n_newton: int
    n_linear: int
    residual: float
    gap_bound: float = float("nan")
    objective: float = float("nan")


@dataclass(frozen=True)
class OTResult:
    """Solution of a balanced (Eq. 6-16) or partial (Eq. 17-26) OT problem by annealing.

    plan : (N1, N2) float64, the mean-field plan G = phi(beta (C + lam + mu [+ x])) at the final beta
        (Eq. 15 / 26), or None when not formed: by default in the matrix-free mode (a `FeatureCost`;
        ``dense_plan=True`` asks for it where it fits), or with ``dense_plan=False``
    plan_top : scipy.sparse.csr_matrix (N1, N2), each row's ``plan_topk`` (default 8) largest entries of
        the plan (the same values as ``plan``), in both modes
    argmax : (N1,) int64, each row's largest plan entry (its column; the first one on ties, as
        ``plan.argmax(axis=1)``), in both modes
    cost : U = sum G C (user's units), Eq. 6 (balanced) or the transport part of Eq. 17 (partial)
    objective : the minimized objective: = cost (balanced); cost + sum alpha1 m1^2 + sum alpha2 m2^2 (partial)
    free_energy : F at the saddle point, Eq. 12 / Eq. 23 (user's units)
    lam : (N1,) float64, mu : (N2,) float64, x : float (0.0 for balanced) -- the dual variables in user's
        units (balanced: one gauge is free; ours is whatever the solve reached)
    mass1 : (N1,) float64 row sums of the plan; mass2 : (N2,) float64 column sums (exact sums over all
        entries, computed by the solver's last evaluation pass, in both modes)
    beta : final inverse temperature (user's units); converged : annealing stopped by `tol` with every
        Newton solve converged; n_newton, n_linear : totals; history : one `BetaStep` per beta
    energy_history : (property) the (beta, objective) pairs of ``history`` as an (n_beta, 2) array
    """

    plan: np.ndarray | None
    plan_top: sp.csr_matrix
    argmax: np.ndarray
    cost: float
    objective: float
    free_energy: float
    lam: np.ndarray
    mu: np.ndarray
    x: float
    mass1: np.ndarray
    mass2: np.ndarray
    beta: float
    converged: bool
    n_newton: int
    n_linear: int
    history: tuple[BetaStep, ...]

    @property
    def energy_history(self) -> np.ndarray:
        """(n_beta, 2) float64: each annealing step's (beta, objective) from ``history`` (user's units; the
        objective is the transport cost for balanced transport), e.g. to plot the annealing."""
        return np.array([(h.beta, h.objective) for h in self.history], dtype=np.float64).reshape(-1, 2)

    def __repr__(self) -> str:
        # a summary: the dataclass default would print every array (the plan alone is N1 x N2)
        return (f"OTResult({len(self.mass1)}x{len(self.mass2)}, cost={self.cost:.6g}, objective={self.objective:.6g}, "
                f"free_energy={self.free_energy:.6g}, beta={self.beta:.3g}, converged={self.converged}, "
                f"n_beta={len(self.history)}, n_newton={self.n_newton}, n_linear={self.n_linear}, "
                f"mass={self.mass1.sum():.6g}->{self.mass2.sum():.6g}, plan={'stored' if self.plan is not None else 'top-k only'})")


def debiased(u12, u11, u22, *, strict: bool = True):
    """Debiased transport cost SU (paper Eq. 27): ``u12 - 0.5 (u11 + u22)``.

    The one implementation of Eq. 27: `wpot.Comparer` (a pair's distance), `wpot.runs.history.debias_history`
    (SU at every β) and the run store's SQL (`wpot.runs.store.RunStore`) all call it. Works the same for U and
    for the free energy F.

    Scalars give a float and, with ``strict`` (default), non-finite input raises ValueError. Arrays (with
    ``strict=False``) are combined element-wise, NaN where an input is NaN (a β at which a self-comparison
    has no value yet).
    """
    if not strict:
        return np.asarray(u12, dtype=np.float64) - 0.5 * (np.asarray(u11, dtype=np.float64) + np.asarray(u22, dtype=np.float64))
    vals = (float(u12), float(u11), float(u22))
    if not all(np.isfinite(v) for v in vals):
        raise ValueError(f"debiased needs finite values, got u12={u12}, u11={u11}, u22={u22}")
    return vals[0] - 0.5 * (vals[1] + vals[2])


def beta_step(r: dict, scale: float, total: float) -> BetaStep:
    """One annealing record (normalized units, `wpot.ot.anneal.loop.AnnealOutcome.records`) in the user's units."""
    return BetaStep(beta=r["beta"] / scale, cost=r["u"] * scale * total, free_energy=r["f"] * scale * total,
                    n_newton=r["nn"], n_linear=r["nl"], residual=r["res"], gap_bound=r["gap"] * scale * total,
                    objective=r["obj"] * scale * total)


def build_result(eng: Engine, out: AnnealOutcome, total: float, kind: str, *, partial: bool, dense: bool,
                 plan_topk: int) -> OTResult:
    """The `OTResult` of a finished annealing (``out``) on ``eng``, in the user's units and orientation:
    costs x scale x ``total`` (the mass the problem was normalized by), betas / scale, the duals x scale.
    ``dense``: also form the (N1, N2) plan. Warns (RuntimeWarning, `wpot.ot.anneal.loop.warn_not_converged`)
    when the annealing did not converge."""
    p = eng.p
    s = p.scale
    warn_not_converged(kind, out)
    hist = tuple(beta_step(r, s, total) for r in out.records)
    plan = None
    if dense:
        plan = eng.plan(out.beta)
        plan *= total  # in place: no second (N1, N2) array
    top_val, top_idx = eng.plan_top(out.beta, plan_topk)
    n1, n2 = (p.n_c, p.n_r) if p.trans else (p.n_r, p.n_c)
    kk = top_val.shape[1]
    plan_top = sp.csr_matrix((top_val.reshape(-1) * total, top_idx.reshape(-1).astype(np.int64),
                              np.arange(0, n1 * kk + 1, kk, dtype=np.int64)), shape=(n1, n2))
    argmax = plan.argmax(axis=1) if plan is not None else top_idx[:, 0].astype(np.int64)
    # the exact marginals of the last evaluation (at the final duals and beta)
    rg, cg = eng.to_host(eng.row_g) * total, eng.to_host(eng.col_g) * total
    mass1, mass2 = (cg, rg) if p.trans else (rg, cg)
    lam = (eng.to_host(eng.lam[0]) + eng.to_host(eng.lam[1])) * s
    y = (eng.to_host(eng.y[0]) + eng.to_host(eng.y[1])) * s
    x = out.point.x * s if partial else 0.0
    mu = y - x
    if p.trans:
        lam, mu = mu, lam
    last = out.records[-1]
    return OTResult(
        plan=plan,
        plan_top=plan_top,
        argmax=argmax.astype(np.int64),
        cost=last["u"] * s * total,
        objective=last["obj"] * s * total,
        free_energy=last["f"] * s * total,
        lam=lam,
        mu=mu,
        x=float(x),
        mass1=mass1.copy(),
        mass2=mass2.copy(),
        beta=last["beta"] / s,
        converged=bool(out.converged),
        n_newton=int(out.n_newton),
        n_linear=int(out.n_linear),
        history=hist,
    )
