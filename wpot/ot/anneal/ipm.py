"""A primal-dual interior-point start for balanced annealing (``method="ipm"``).

For the balanced problem with N1, N2 >= ~50, every entry of the mean-field plan sits in the tail of phi
(G <= max mass <= 1/50 means x = beta s >= 50, where phi(x) = 1/x to rounding), so the saddle point at
beta is the point of the transport LP's central path with G(k, l) s(k, l) = 1/beta, s = C + lam + mu:
annealing beta is path following with the barrier parameter 1/beta. Newton's method on the duals alone
(`wpot.ot.anneal.newton.Engine.newton`) needs many damped steps at the one or two betas where the plan goes
from spread out to a near-permutation (the docs' Results page). Mehrotra's predictor-corrector method,
which keeps G as a variable of its own, crosses that region in a few iterations.

`ipm_start` runs it from the product plan to the barrier 1/beta_h of the first beta of the annealing grid
at which the certified gap N1 N2 / beta_h is below ``handoff`` x U; the annealing of Algorithm 1 then
goes on from beta_h with the usual Newton solves of Eq. 14-16 (so every recorded beta is solved exactly,
and the stopping rule is the paper's). The Newton systems are those of the dual solver with weights
W = G / s instead of beta |phi'(beta s)| (equal on the central path), so the Schur-complement CG,
its preconditioner and the cancellation-free kernels are shared.

Per iteration: one pass that updates G and forms s, W and the residuals, two Newton solves (affine and
corrector, one preconditioner), and one pass for each direction's steps to the boundary (the affine one
also gives mu_aff for any step and the corrector's right-hand side for any target).
The primal G and the reduced costs s are two more N1 x N2 float64 arrays (stored-cost mode only).
"""
from __future__ import annotations

import math
import time

import numpy as np
import warp as wp

from wpot.ot import kernels as K
from wpot.ot.anneal.newton import Engine
from wpot.ot.anneal.state import Point

# no fused multiply-add: the same rounding on every device as wpot.ot.kernels (see there)
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

#: the annealing takes over at the first grid beta with N1 N2 / beta <= HANDOFF * U (relative gap bound),
#: from where the Newton solves need only a few steps (the docs' Results page)
HANDOFF = 1e-3
#: fraction of the step to the boundary (G > 0, s > 0)
ETA = 0.99
#: the annealing takes over once the central plan's marginals at the hand-off beta are this close (relative
#: L1) to the target masses
CENTERED = 1e-5
#: iterations allowed before the annealing takes over regardless (its Newton solves then finish the centring)
MAX_IPM_ITER = 60


@wp.func
def dual_change(d_a: wp.array(dtype=wp.float64), d_b: wp.array(dtype=wp.float64), dy: wp.array(dtype=wp.float64),
                k: int, l: int) -> wp.float64:
    """ds(k, l) = dlam(k) + dy(l) for dlam = d_a + d_b with d_a = -dy(pivot): the pivot's ds is d_b exactly."""
    return (d_a[k] + dy[l]) + d_b[k]


@wp.func
def pd_step(g: wp.float64, s: wp.float64, dsa: wp.float64, ds: wp.float64, mu_t: wp.float64, corr: int) -> wp.float64:
    """dG of the primal-dual direction with dual change ``ds`` (G ds + s dG = T): dG = T/s - G - (G/s) ds,
    T = mu_t, minus dG_aff ds_aff when ``corr`` (Mehrotra's corrector; dG_aff = -G - (G/s) dsa)."""
    t = mu_t
    if corr != 0:
        t = t + (g + g / s * dsa) * dsa
    return t / s - g - g / s * ds


@wp.kernel
def ipm_eval(
    csrc: K.DenseCost, n_c: int,
    lam_hi: wp.array(dtype=wp.float64), lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64), y_lo: wp.array(dtype=wp.float64),
    G: wp.array2d(dtype=wp.float64), S: wp.array2d(dtype=wp.float64),
    # the update of G first (upd = 1; S holds the old point's s): corrector direction, affine direction,
    # target, step
    upd: int,
    d_a: wp.array(dtype=wp.float64), d_b: wp.array(dtype=wp.float64), dy: wp.array(dtype=wp.float64),
    a_a: wp.array(dtype=wp.float64), a_b: wp.array(dtype=wp.float64), a_y: wp.array(dtype=wp.float64),
    sc: wp.array(dtype=wp.float64),
    # outputs
    W: wp.array2d(dtype=wp.float64), row_g: wp.array(dtype=wp.float64), col_g: wp.array(dtype=wp.float64),
    row_w: wp.array(dtype=wp.float64), piv: wp.array(dtype=wp.int32), tail: wp.array(dtype=wp.float64),
    row_u: wp.array(dtype=wp.float64), row_gs: wp.array(dtype=wp.float64), row_smin: wp.array(dtype=wp.float64),
    row_r: wp.array(dtype=wp.float64), col_r: wp.array(dtype=wp.float64),
):
    """Row k: (when ``upd``) G += alpha_p dG for the step just taken (dG from the old point's s, in S; its
    target mu_t and primal step alpha_p in ``sc``), then
    at the new duals s (stored in S) and W = G / s (stored), its sum, pivot (largest) and the rest (``tail``) as in `kernels.eval_rows`;
    the primal row sums (column sums atomically), sum G C' (U), sum G s (complementarity), min s, and the
    row and column sums of 1/s (mu times them are the marginals of the central plan at barrier mu)."""
    k = wp.tid()
    mu_t = sc[_MUT]
    alpha_p = sc[_AP]
    lh = lam_hi[k]
    ll = lam_lo[k]
    sg = wp.float64(0.0)
    su = wp.float64(0.0)
    sgs = wp.float64(0.0)
    smin = wp.float64(1.0e300)
    sr = wp.float64(0.0)
    wmax = wp.float64(-1.0)
    wrest = wp.float64(0.0)
    p = int(0)
    for l in range(n_c):
        c = K.cost_at(csrc, k, l)
        g = G[k, l]
        if upd != 0:
            g = g + alpha_p * pd_step(g, S[k, l], dual_change(a_a, a_b, a_y, k, l), dual_change(d_a, d_b, dy, k, l),
                                      mu_t, 1)
            G[k, l] = g
        s = K.reduced_cost(c, lh, ll, y_hi[l], y_lo[l])
        S[k, l] = s
        w = g / s
        W[k, l] = w
        sg += g
        wp.atomic_add(col_g, l, g)
        wmax, wrest, p = K.track_pivot(w, l, wmax, wrest, p)
        su += g * c
        sgs += g * s
        smin = wp.min(smin, s)
        r = wp.float64(1.0) / s
        sr += r
        wp.atomic_add(col_r, l, r)
    row_r[k] = sr
    row_g[k] = sg
    piv[k] = p
    tail[k] = wrest
    row_w[k] = wrest + wmax
    row_u[k] = su
    row_gs[k] = sgs
    row_smin[k] = smin


@wp.kernel
def ipm_ratio(
    n_c: int, G: wp.array2d(dtype=wp.float64), S: wp.array2d(dtype=wp.float64),
    d_a: wp.array(dtype=wp.float64), d_b: wp.array(dtype=wp.float64), dy: wp.array(dtype=wp.float64),
    a_a: wp.array(dtype=wp.float64), a_b: wp.array(dtype=wp.float64), a_y: wp.array(dtype=wp.float64),
    sc: wp.array(dtype=wp.float64), corr: int,
    # outputs: step to the boundary for s and for G; with corr = 0 (the affine direction) also the sums
    # that give mu_aff for any steps and the corrector's right-hand side for any target (cols atomically)
    row_rs: wp.array(dtype=wp.float64), row_rg: wp.array(dtype=wp.float64),
    row_m: wp.array2d(dtype=wp.float64), col_m: wp.array(dtype=wp.float64),
):
    """Row k for a direction (dlam = d_a + d_b, dy) at the point `ipm_eval` last saw (its s in S; the
    corrector's target mu_t in ``sc``, T = 0 for the affine direction): min over
    ds < 0 of s / -ds and over dG < 0 of G / -dG. Affine (corr = 0, T = 0): row_m[k] = (sum dG s, sum G ds,
    sum dG ds, sum dG ds / s) and col_m[l] += dG ds / s over the column (the sums of 1/s come from `ipm_eval`)."""
    k = wp.tid()
    mu_t = wp.float64(0.0)
    if corr != 0:
        mu_t = sc[_MUT]
    rs = wp.float64(1.0e300)
    rg = wp.float64(1.0e300)
    m0 = wp.float64(0.0)
    m1 = wp.float64(0.0)
    m2 = wp.float64(0.0)
    m3 = wp.float64(0.0)
    for l in range(n_c):
        s = S[k, l]
        g = G[k, l]
        ds = dual_change(d_a, d_b, dy, k, l)
        dsa = wp.float64(0.0)
        if corr != 0:
            dsa = dual_change(a_a, a_b, a_y, k, l)
        dg = pd_step(g, s, dsa, ds, mu_t, corr)
        if ds < wp.float64(0.0):
            rs = wp.min(rs, -s / ds)
        if dg < wp.float64(0.0):
            rg = wp.min(rg, -g / dg)
        if corr == 0:
            q = dg * ds
            m0 += dg * s
            m1 += g * ds
            m2 += q
            m3 += q / s
            wp.atomic_add(col_m, l, q / s)
    row_rs[k] = rs
    row_rg[k] = rg
    if corr == 0:
        row_m[k, 0] = m0
        row_m[k, 1] = m1
        row_m[k, 2] = m2
        row_m[k, 3] = m3


# slots of `_IPM.sc`, the iteration's scalars on the device: the evaluation's sums (sum G s, U, min s, the
# primal residual and the residual of the central marginals at the target, both L1), the steps to the
# boundary (s, G), the affine sums, the target mu_t and the steps taken (primal, dual)
_GS, _U, _SMIN, _R1, _RC, _RS, _RG, _M0, _M1, _M2, _M3, _MUT, _AP, _AD = range(14)
N_SC = 14


@wp.kernel
def ipm_row_sums(m_r: wp.array(dtype=wp.float64), row_g: wp.array(dtype=wp.float64),
                 row_gs: wp.array(dtype=wp.float64), row_u: wp.array(dtype=wp.float64),
                 row_smin: wp.array(dtype=wp.float64), row_r: wp.array(dtype=wp.float64), mu_f: wp.float64,
                 sc: wp.array(dtype=wp.float64)):
    """The rows' part of the evaluation's scalars (see `ipm_eval`'s outputs)."""
    k = wp.tid()
    wp.atomic_add(sc, _GS, row_gs[k])
    wp.atomic_add(sc, _U, row_u[k])
    wp.atomic_min(sc, _SMIN, row_smin[k])
    wp.atomic_add(sc, _R1, wp.abs(m_r[k] - row_g[k]))
    wp.atomic_add(sc, _RC, wp.abs(m_r[k] - mu_f * row_r[k]))


@wp.kernel
def ipm_col_sums(m_c: wp.array(dtype=wp.float64), col_g: wp.array(dtype=wp.float64),
                 col_r: wp.array(dtype=wp.float64), mu_f: wp.float64, sc: wp.array(dtype=wp.float64)):
    l = wp.tid()
    wp.atomic_add(sc, _R1, wp.abs(m_c[l] - col_g[l]))
    wp.atomic_add(sc, _RC, wp.abs(m_c[l] - mu_f * col_r[l]))


@wp.kernel
def ipm_ratio_sums(row_rs: wp.array(dtype=wp.float64), row_rg: wp.array(dtype=wp.float64),
                   row_m: wp.array2d(dtype=wp.float64), corr: int, sc: wp.array(dtype=wp.float64)):
    """The steps to the boundary (minima over rows) and, for the affine direction, the sums of row_m."""
    k = wp.tid()
    wp.atomic_min(sc, _RS, row_rs[k])
    wp.atomic_min(sc, _RG, row_rg[k])
    if corr == 0:
        for i in range(4):
            wp.atomic_add(sc, _M0 + i, row_m[k, i])


@wp.kernel
def ipm_target(sc: wp.array(dtype=wp.float64), nn: wp.float64, mu_f: wp.float64):
    """Mehrotra's target from the affine direction's steps and sums: mu_aff (the complementarity after the
    affine steps), sigma = (mu_aff / mu)^3, mu_t = max(sigma mu, mu_f)."""
    ad = wp.min(wp.float64(1.0), sc[_RS])
    ap = wp.min(wp.float64(1.0), sc[_RG])
    mu = sc[_GS] / nn
    mu_aff = (mu * nn + ap * sc[_M0] + ad * sc[_M1] + ap * ad * sc[_M2]) / nn
    sigma = wp.min(wp.float64(1.0), wp.max(wp.float64(0.0), mu_aff / mu))
    sc[_MUT] = wp.max(sigma * sigma * sigma * mu, mu_f)


@wp.kernel
def ipm_steps(sc: wp.array(dtype=wp.float64), eta: wp.float64):
    """The steps taken: ``eta`` of the way to the boundary, at most 1."""
    sc[_AD] = wp.min(wp.float64(1.0), eta * sc[_RS])
    sc[_AP] = wp.min(wp.float64(1.0), eta * sc[_RG])


@wp.kernel
def ipm_rhs(m: wp.array(dtype=wp.float64), sum_r: wp.array(dtype=wp.float64), sum_m: wp.array(dtype=wp.float64),
            corr: int, sc: wp.array(dtype=wp.float64), g: wp.array(dtype=wp.float64)):
    """g = m - (mu_t sum 1/s - [corr] sum dG_aff ds_aff / s) over a row (column): the Newton residual of the
    rows (columns) for the target mu_t in ``sc``."""
    i = wp.tid()
    t = sc[_MUT] * sum_r[i]
    if corr != 0:
        t = t - sum_m[i]
    g[i] = m[i] - t


class _IPM:
    """The interior-point iteration on an `Engine`'s (oriented, normalized, balanced) problem. Its scalars
    (sums, minima, steps, target) stay on the device in ``sc``; the host reads them once an iteration, with
    the evaluation (`Engine.read_scalars`), and the Newton directions' counts come with that read."""

    def __init__(self, eng: Engine):
        self.e = eng
        p = eng.p
        d = p.device
        z = lambda n: wp.zeros(n, dtype=wp.float64, device=d)  # noqa: E731
        self.G = wp.empty((p.n_r, p.n_c), dtype=wp.float64, device=d)
        eng.to_device(self.G, np.outer(p.m_r, p.m_c))  # the product plan: feasible
        self.S = wp.zeros((p.n_r, p.n_c), dtype=wp.float64, device=d)  # reduced costs at the last evaluation
        self.row_gs, self.row_smin, self.row_r, self.col_r = z(p.n_r), z(p.n_r), z(p.n_r), z(p.n_c)
        self.row_rs, self.row_rg = z(p.n_r), z(p.n_r)
        self.row_m = wp.zeros((p.n_r, 4), dtype=wp.float64, device=d)
        self.col_m = wp.zeros(p.n_c, dtype=wp.float64, device=d)
        self.a_a, self.a_b, self.a_y = z(p.n_r), z(p.n_r), z(p.n_c)
        self.m_r, self.m_c = z(p.n_r), z(p.n_c)
        eng.to_device(self.m_r, p.m_r)
        eng.to_device(self.m_c, p.m_c)
        self.g1, self.g2 = z(p.n_r), z(p.n_c)  # right-hand sides of the Newton systems
        self.sc = z(N_SC)
        self.upd = False  # a step whose G update is pending (done by the next eval)
        self.mu_f = 0.0  # the barrier target of the current run
        self.pending: list = []  # `Engine.direction_later` results not yet counted
        self.n_lin = 0
        self.u = math.nan  # U at the last evaluation

    def eval(self) -> tuple[float, float, float, float, float]:
        """(Pending G update, then) W and the sums at the current point; one read. Returns (mu, U, primal
        residual, min s, residual of the central marginals at the target mu_f = mu_f sum 1/s)."""
        e, p = self.e, self.e.p
        e.col_g.zero_()
        self.col_r.zero_()
        wp.launch(ipm_eval, dim=p.n_r,
                  inputs=[e.csrc, p.n_c, e.lam[0], e.lam[1], e.y[0], e.y[1], self.G, self.S, int(self.upd),
                          e.d_a, e.d_b, e.dy_a, self.a_a, self.a_b, self.a_y, self.sc],
                  outputs=[e.W, e.row_g, e.col_g, e.row_w, e.piv, e.tail, e.row_u, self.row_gs, self.row_smin,
                           self.row_r, self.col_r],
                  device=p.device)
        self.upd = False
        self.sc[_GS:_RC + 1].zero_()
        self.sc[_SMIN:_SMIN + 1].fill_(1e300)
        wp.launch(ipm_row_sums, dim=p.n_r, inputs=[self.m_r, e.row_g, self.row_gs, e.row_u, self.row_smin, self.row_r,
                                                  self.mu_f, self.sc], device=p.device)
        wp.launch(ipm_col_sums, dim=p.n_c, inputs=[self.m_c, e.col_g, self.col_r, self.mu_f, self.sc], device=p.device)
        v = e.read_scalars(self.sc)
        self._collect()
        self.u = float(v[_U])
        return float(v[_GS]) / (p.n_r * p.n_c), self.u, 0.5 * float(v[_R1]), float(v[_SMIN]), 0.5 * float(v[_RC])

    def _collect(self) -> None:
        """Count the linear iterations of the directions solved since the last read."""
        for result in self.pending:
            self.n_lin += result()[0]
        self.pending.clear()

    def _ratio(self, corr: bool) -> None:
        """Steps to the boundary (s, G) for the engine's current direction (and the affine sums), into ``sc``."""
        e, p = self.e, self.e.p
        if not corr:
            self.col_m.zero_()
        wp.launch(ipm_ratio, dim=p.n_r,
                  inputs=[p.n_c, self.G, self.S, e.d_a, e.d_b, e.dy_a, self.a_a, self.a_b, self.a_y, self.sc,
                          int(corr)],
                  outputs=[self.row_rs, self.row_rg, self.row_m, self.col_m], device=p.device)
        self.sc[_RS:_RG + 1].fill_(1e300)
        if not corr:
            self.sc[_M0:_M3 + 1].zero_()
        wp.launch(ipm_ratio_sums, dim=p.n_r, inputs=[self.row_rs, self.row_rg, self.row_m, int(corr), self.sc],
                  device=p.device)

    def _step(self) -> None:
        """Take the engine's current direction (target mu_t in ``sc``, corrector from the affine arrays): the
        dual step now, the primal one in the next `eval`; both ETA of the way to the boundary at most."""
        self._ratio(True)
        wp.launch(ipm_steps, dim=1, inputs=[self.sc, ETA], device=self.e.p.device)
        self.e.trial_from(self.sc, _AD)
        self.e.accept()
        self.upd = True

    def _solve(self, corr: bool, rtol: float) -> None:
        """Newton direction for the target mu_t in ``sc`` (with the corrector term when ``corr``), left in the
        engine's d_a, d_b, dy_a; J has the weights W = G/s."""
        e, p = self.e, self.e.p
        for m, sum_r, sum_m, g in ((self.m_r, self.row_r, self.row_m[:, 3], self.g1),
                                   (self.m_c, self.col_r, self.col_m, self.g2)):
            wp.launch(ipm_rhs, dim=g.shape[0], inputs=[m, sum_r, sum_m, int(corr), self.sc, g], device=p.device)
        self.pending.append(e.direction_later(Point(self.g1, self.g2, 0.0, 0.0), rtol=rtol))

    def _show(self, n_it: int, what: str) -> None:
        v = self.e.read_scalars(self.sc)
        print(f"    ipm {n_it}{what}: mu_t*beta_h={v[_MUT] / self.mu_f:.3g} steps d={v[_AD]:.2f} p={v[_AP]:.2f}")

    def run(self, beta_h: float, verbose: int) -> tuple[int, int]:
        """Mehrotra iterations to the barrier 1/beta_h; returns (iterations, linear iterations). The last
        evaluation (W, sums) is that of the current point, unless MAX_IPM_ITER stopped it."""
        e, p = self.e, self.e.p
        d = p.device
        self.mu_f = mu_f = 1.0 / beta_h
        n_it = 0
        lin0 = self.n_lin
        while n_it < MAX_IPM_ITER:
            mu, u, res, smin, res_c = self.eval()
            if mu <= 1.2 * mu_f:
                # centering at the target (the central plan's marginals are mu_f sum 1/s): Newton on them with
                # the primal-dual weights, until they are close enough for the dual Newton of the annealing
                if res_c <= CENTERED:
                    break
                self.sc[_MUT:_MUT + 1].fill_(mu_f)
                self._solve(False, rtol=1e-2)
                for a in (self.a_a, self.a_b, self.a_y):  # no corrector term: T = mu_f (also in the G update)
                    a.zero_()
                self._step()
                n_it += 1
                if verbose > 1:
                    self._show(n_it, f" (centering, residual of the central marginals {res_c:.1e})")
                continue
            if not smin > 0:  # the fraction to the boundary keeps s > 0; this guards against rounding
                raise FloatingPointError(f"interior-point start: a reduced cost became {smin:.3g}")
            # affine direction (T = 0): sum_l (G/s) ds = -m_r on the rows, i.e. J d = -g with g = m
            self.pending.append(e.direction_later(Point(self.m_r, self.m_c, 0.0, 0.0), rtol=0.1))
            wp.copy(self.a_a, e.d_a)
            wp.copy(self.a_b, e.d_b)
            wp.copy(self.a_y, e.dy_a)
            self._ratio(False)
            wp.launch(ipm_target, dim=1, inputs=[self.sc, float(p.n_r * p.n_c), mu_f], device=d)
            # corrector, T = mu_t - dG_aff ds_aff: rows sum_l (G/s) ds = sum_l T/s - m_r -> g1 = m_r - sum T/s
            self._solve(True, rtol=1e-2)
            self._step()
            n_it += 1
            if verbose > 1:
                self._show(n_it, f": mu*beta_h={mu / mu_f:.3g} res={res:.1e} U={u:.9g}")
        self._collect()
        return n_it, self.n_lin - lin0


def handoff_beta(beta0: float, step: float, n_r: int, n_c: int, u: float, handoff: float = HANDOFF) -> float:
    """The first grid beta (beta0 step^j) with n_r n_c / beta <= handoff * u (u > 0; else beta0 step^12)."""
    if not (u > 0):
        return beta0 * step ** 12
    j = max(0, math.ceil(math.log(n_r * n_c / (handoff * u * beta0)) / math.log(step) - 1e-12))
    return beta0 * step ** j


def ipm_start(eng: Engine) -> tuple[float, int, int, float]:
    """Run the interior-point iteration on a fresh balanced `Engine` and leave its duals at the barrier of
    the hand-off beta, where the annealing goes on (`wpot.ot.anneal.loop.anneal` with ``beta0=beta_h``).
    Returns (beta_h (normalized), iterations, linear iterations, seconds)."""
    t0 = time.perf_counter()
    o, p = eng.o, eng.p
    ipm = _IPM(eng)
    eng.init_point(np.zeros(p.n_r), np.ones(p.n_c))
    _, u0, *_ = ipm.eval()
    # the optimum is below the product plan's U; aim at the gap with respect to a quarter of it, then
    # re-aim once U is known better
    beta_h = min(handoff_beta(o.beta0, o.step, p.n_r, p.n_c, 0.25 * u0), o.beta_max)
    n_it, n_lin = ipm.run(beta_h, o.verbose)
    # (U* = 0, e.g. a shape against itself: the re-aimed beta is capped by beta_max)
    beta_h2 = min(handoff_beta(o.beta0, o.step, p.n_r, p.n_c, ipm.u), o.beta_max)
    if beta_h2 > beta_h:
        k2, l2 = ipm.run(beta_h2, o.verbose)
        n_it, n_lin, beta_h = n_it + k2, n_lin + l2, beta_h2
    eng.t.n_newton += n_it  # the interior-point iterations are Newton steps (as `OTResult.n_newton` counts them)
    eng.invalidate_preconditioner()  # it was built from the interior-point weights
    del ipm  # frees G
    return beta_h, n_it, n_lin, time.perf_counter() - t0
