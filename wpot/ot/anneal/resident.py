"""The device Newton loop (``newton_loop="device"``, the default on a GPU): no host round trip per CG iteration.

`wpot.ot.anneal.newton.Engine` runs its Newton steps through one of two `wpot.ot.anneal.schur.NewtonSolver`
strategies, picked from ``SolverOptions.newton_loop`` when it is built:

* "host" (`wpot.ot.anneal.host.HostSolver`): the length-N vectors go to the host, where the CG recurrences
  and the SuperLU preconditioner run; every CG iteration writes and reads a vector.
* "device" (`DeviceSolver`, this module): every vector stays on the device. An evaluation reduces the marginal
  residuals and U into a few scalars in a kernel; the right-hand side, the preconditioner, CG and the
  back-substitution are kernels; the fraction-to-zero step and the trial point read the step length from
  the device. The host reads one small array per trial point (`DeviceLoop.scal`: the evaluation's sums and
  the last solve's CG count, residual and step limit), so a Newton step whose first trial is accepted
  costs one synchronisation.

`DeviceLoop` holds the loop's device buffers and runs its kernels; `DeviceSolver` drives it for the engine
(the preconditioner's reuse, refit and rebuild rules, the line search's first step).

CG runs under ``wp.capture_while``: on a GPU with conditional graph nodes (CUDA 12.4+) the whole loop is
one captured graph that stops itself on the device; on the CPU the condition is read from host memory
(no transfer). Without conditional nodes a GPU reads the condition each iteration, counted as a transfer.
(`DeviceLoop.captured` says which; Warp captures on the CPU too, where the tests run the captured loop.)

The preconditioner is the sparse approximation P of the Schur complement that the host loop factorizes
(`wpot.ot.anneal.linear.assemble_sparse_schur`: the top-k weights per row and column of W, the exact diagonal),
assembled on the device by `sparse_schur_rows` / `sparse_schur_cols` into a Warp BSR matrix and
approximately inverted by Warp's FSAI (factorized sparse approximate inverse, M^-1 = G^T G, built row by
row on the device; applying it is two sparse products, no triangular solve), by default inside a multilevel
V-cycle over aggregates of P's unknowns (`wpot.ot.anneal.multilevel`, ``SolverOptions.device_preconditioner``):
FSAI is local, and at high beta P's inverse couples far-apart unknowns. CG then needs more iterations than
with the host loop's SuperLU factors of P, fewer with the V-cycle than with FSAI alone (the Results page of
the documentation has the figures).
When the host loop would refactorize, the device loop first refits: P's new values on the last build's
pattern (`bsr_set_from_triplets(..., topology="masked")`), FSAI refitted on its supports (`FSAI.update`) and the
V-cycle's coarse levels recomputed from P: kernels only, no host read (`Timers.n_refit`). A full build
(`Timers.n_factor`) selects FSAI's supports on the device too (``defer_pattern``: the first `FSAI.update`
selects them), which synchronises 3 times inside Warp (`BUILD_SYNCS`: P's entry count and the selection's
ready flag, 2 reads counted on the CPU build, and a stream synchronisation on CUDA, where FSAI's eager set-up
would read 5 times), and the V-cycle's aggregation reads P once (through `Engine.to_host`, so counted in
``Timers.n_d2h``). It runs first, again when a refit does not serve (`REFIT_SLOWDOWN`), and at least every
`FULL_BUILD_EVERY` rebuilds.

The balanced gauge dy(last) = 0 is kept by a zero right-hand side and matvec output there and an identity
row in P; the partial rank-one term of S (-a a^T / sum a) is applied in the matvec and left out of P.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Callable

import numpy as np
import warp as wp
import warp.sparse as wsp
from warp.optim.linear import FSAI

from wpot.ot.anneal.linear import SINGULAR_SHIFT
from wpot.ot.anneal.multilevel import Multilevel, multilevel_bytes
from wpot.ot.anneal.schur import LIMIT_FRACTION, REFRESH_EXTRA_CG, SchurSolver, step_alpha
from wpot.ot.anneal.state import DualSums, Point

if TYPE_CHECKING:  # pragma: no cover
    from wpot.ot.anneal.newton import Engine

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["BUILD_SYNCS", "DeviceLoop", "DeviceSolver", "FSAI_ROW", "device_loop_bytes"]

#: scalar entries per row of the FSAI factor G (more entries: fewer CG iterations, a costlier build and apply)
FSAI_ROW = 32

#: synchronisations of one full preconditioner build inside Warp: FSAI's constructor reads P's entry count
#: and its first update the ready flag of the support selection (2 reads counted on the CPU build;
#: tests/ot/test_ot_resident.py bounds them), and the constructor synchronises the stream on CUDA
BUILD_SYNCS = 3
#: at least every this many rebuilds of the preconditioner is a full one (a new pattern): a refit on an old
#: pattern can serve far worse than a fresh build without exceeding the reuse rule (the interior point on
#: unequal masses)
FULL_BUILD_EVERY = 6
#: a stale preconditioner is refitted on its last pattern (no host read) while CG with the refit needs at
#: most this many times the count of its last full build (+ `wpot.ot.anneal.schur.REFRESH_EXTRA_CG`);
#: otherwise the next rebuild is a full one (`BUILD_SYNCS` synchronisations inside Warp)
REFIT_SLOWDOWN = 2.0
#: a Newton line search starts at this multiple of the last accepted step of its call (at most the full step),
#: since each halving costs an evaluation and a read; 1.0 would let no step grow
STEP_GROWTH = 1.5

# slots of `DeviceLoop.scal`: the evaluation's sums (zeroed by each evaluation) ...
_G2, _L1, _U, _XPHI, _AY = 0, 1, 2, 3, 4
N_EVAL = 5
# ... the last solve's results: step limit (fraction to zero), CG iterations, converged ...
_LIMIT, _IT, _OK = 5, 6, 7
# ... `DeviceLoop.free_sums`: sum g, lam . m_r, y . m_c, sum b lam^2, sum a mu^2, sum m^2 / (2 alpha') ...
_F, _LM, _YM, _BL2, _AM2, _PEN = 8, 9, 10, 11, 12, 13
# ... and the solve before the last one's CG results (two directions between reads: the interior point's)
_IT0, _OK0 = 14, 15
N_SCAL = 16
# slots of `DeviceLoop.cg`: r.z, p.q, r.r (masked), r.z new, ||rhs||^2, a.p, rtol^2
_RZ, _PQ, _RR, _RZN, _NB2, _AP, _TOL2 = 0, 1, 2, 3, 4, 5, 6
N_CG = 7
_SHIFT = wp.constant(wp.float64(SINGULAR_SHIFT))


# --------------------------------------------------------------------------- evaluation
@wp.kernel
def residual_rows(m_r: wp.array(dtype=wp.float64), b_r: wp.array(dtype=wp.float64),
                  lam_hi: wp.array(dtype=wp.float64), lam_lo: wp.array(dtype=wp.float64),
                  row_g: wp.array(dtype=wp.float64), row_u: wp.array(dtype=wp.float64),
                  row_xphi: wp.array(dtype=wp.float64), g1: wp.array(dtype=wp.float64),
                  scal: wp.array(dtype=wp.float64)):
    """g1 = m_r + b lam - (row sums of G) (Eq. 14 / 25), and its squared and absolute sums, U and the
    gap sum into ``scal``."""
    k = wp.tid()
    g = (m_r[k] + b_r[k] * (lam_hi[k] + lam_lo[k])) - row_g[k]
    g1[k] = g
    wp.atomic_add(scal, _G2, g * g)
    wp.atomic_add(scal, _L1, wp.abs(g))
    wp.atomic_add(scal, _U, row_u[k])
    wp.atomic_add(scal, _XPHI, row_xphi[k])


@wp.kernel
def a_dot_y(a_c: wp.array(dtype=wp.float64), y_hi: wp.array(dtype=wp.float64),
            y_lo: wp.array(dtype=wp.float64), scal: wp.array(dtype=wp.float64)):
    """Partial: a . y into ``scal`` (for x = (a . y - 1) / sum a, the eliminated scalar)."""
    l = wp.tid()
    wp.atomic_add(scal, _AY, a_c[l] * (y_hi[l] + y_lo[l]))


@wp.kernel
def residual_cols(m_c: wp.array(dtype=wp.float64), a_c: wp.array(dtype=wp.float64),
                  y_hi: wp.array(dtype=wp.float64), y_lo: wp.array(dtype=wp.float64),
                  col_g: wp.array(dtype=wp.float64), inv_asum: wp.float64, partial: int,
                  g2: wp.array(dtype=wp.float64), scal: wp.array(dtype=wp.float64)):
    """g2 = m_c + a (y - x) - (column sums of G), and its squared and absolute sums into ``scal``."""
    l = wp.tid()
    x = wp.float64(0.0)
    if partial != 0:
        x = (scal[_AY] - wp.float64(1.0)) * inv_asum
    g = (m_c[l] + a_c[l] * ((y_hi[l] + y_lo[l]) - x)) - col_g[l]
    g2[l] = g
    wp.atomic_add(scal, _G2, g * g)
    wp.atomic_add(scal, _L1, wp.abs(g))


@wp.kernel
def free_sums_rows(row_f: wp.array(dtype=wp.float64), lam_hi: wp.array(dtype=wp.float64),
                   lam_lo: wp.array(dtype=wp.float64), m_r: wp.array(dtype=wp.float64),
                   b_r: wp.array(dtype=wp.float64), row_g: wp.array(dtype=wp.float64), partial: int,
                   scal: wp.array(dtype=wp.float64)):
    """Row terms of `wpot.ot.anneal.state.DualSums` and sum g."""
    k = wp.tid()
    lam = lam_hi[k] + lam_lo[k]
    wp.atomic_add(scal, _F, row_f[k])
    wp.atomic_add(scal, _LM, lam * m_r[k])
    wp.atomic_add(scal, _BL2, b_r[k] * (lam * lam))
    if partial != 0:
        wp.atomic_add(scal, _PEN, wp.float64(0.5) * (row_g[k] * row_g[k] / b_r[k]))


@wp.kernel
def free_sums_cols(y_hi: wp.array(dtype=wp.float64), y_lo: wp.array(dtype=wp.float64), x: wp.float64,
                   m_c: wp.array(dtype=wp.float64), a_c: wp.array(dtype=wp.float64),
                   col_g: wp.array(dtype=wp.float64), partial: int, scal: wp.array(dtype=wp.float64)):
    """Column terms of `wpot.ot.anneal.state.DualSums`."""
    l = wp.tid()
    y = y_hi[l] + y_lo[l]
    mu = y - x
    wp.atomic_add(scal, _YM, y * m_c[l])
    wp.atomic_add(scal, _AM2, a_c[l] * (mu * mu))
    if partial != 0:
        wp.atomic_add(scal, _PEN, wp.float64(0.5) * (col_g[l] * col_g[l] / a_c[l]))


# --------------------------------------------------------------------------- Newton system
@wp.kernel
def sum_into(v: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, 0, v[i])


@wp.kernel
def add_vec(a: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = a[i] + b[i]


@wp.kernel
def schur_rhs(g2: wp.array(dtype=wp.float64), wtg: wp.array(dtype=wp.float64), gauge: int,
              rhs: wp.array(dtype=wp.float64)):
    """rhs = -g2 + W^T E1^-1 g1 (0 on the gauge column)."""
    l = wp.tid()
    r = -g2[l] + wtg[l]
    if gauge != 0 and l == rhs.shape[0] - 1:
        r = wp.float64(0.0)
    rhs[l] = r


@wp.func
def put_edge(rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
             slot: int, i: int, j: int, w: wp.float64, skip: int):
    """Two triplets (i, j, -w), (j, i, -w) of P at ``slot``; an edge on the node ``skip`` (the gauge
    column, or -1) or a zero weight becomes two explicit zeros on the diagonal (pruned by the assembly)."""
    if i == j or w == wp.float64(0.0) or i == skip or j == skip:
        rows[slot] = i
        cols[slot] = i
        vals[slot] = wp.float64(0.0)
        rows[slot + 1] = j
        cols[slot + 1] = j
        vals[slot + 1] = wp.float64(0.0)
    else:
        rows[slot] = i
        cols[slot] = j
        vals[slot] = -w
        rows[slot + 1] = j
        cols[slot + 1] = i
        vals[slot + 1] = -w


@wp.kernel
def sparse_schur_rows(top_val: wp.array2d(dtype=wp.float64), top_idx: wp.array2d(dtype=wp.int32),
                      piv: wp.array(dtype=wp.int32), e1: wp.array(dtype=wp.float64), skip: int,
                      rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
                      vals: wp.array(dtype=wp.float64)):
    """Row k's edges of P (`wpot.ot.anneal.linear.assemble_sparse_schur`): pivot <-> each other entry of its
    top-k, W(k,l) W(k,p) / E1(k), and pairs of its non-pivot top entries, W(k,l1) W(k,l2) / E1(k), where
    that is above 1e-3 of the first pivot edge. Slots: 2 per pair (l1 < l2 of the top-k list)."""
    k = wp.tid()
    kk = top_val.shape[1]
    per_row = kk * (kk - 1)
    ek = e1[k]
    p = piv[k]
    wpiv = top_val[k, 0]
    first = top_val[k, 1] * wpiv / ek
    slot = k * per_row
    for j in range(1, kk):
        l = int(top_idx[k, j])
        w = wp.float64(0.0)
        if l >= 0:
            w = top_val[k, j] * wpiv / ek
        else:
            l = p
        put_edge(rows, cols, vals, slot, p, l, w, skip)
        slot += 2
    for j1 in range(1, kk):
        for j2 in range(j1 + 1, kk):
            l1 = int(top_idx[k, j1])
            l2 = int(top_idx[k, j2])
            w = wp.float64(0.0)
            if l1 >= 0 and l2 >= 0:
                w = top_val[k, j1] * top_val[k, j2] / ek
                if not (w > wp.float64(1.0e-3) * first):
                    w = wp.float64(0.0)
            if l1 < 0 or l2 < 0:
                l1 = p
                l2 = p
            put_edge(rows, cols, vals, slot, l1, l2, w, skip)
            slot += 2


@wp.kernel
def sparse_schur_cols(ctop_val: wp.array2d(dtype=wp.float64), ctop_idx: wp.array2d(dtype=wp.int32),
                      top_val: wp.array2d(dtype=wp.float64), top_idx: wp.array2d(dtype=wp.int32),
                      piv: wp.array(dtype=wp.int32), e1: wp.array(dtype=wp.float64),
                      diag: wp.array(dtype=wp.float64), a_c: wp.array(dtype=wp.float64),
                      dsum: wp.array(dtype=wp.float64),
                      skip: int, base: int,
                      rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
                      vals: wp.array(dtype=wp.float64)):
    """Column l's edges of P: each of its top rows k (pivoting elsewhere) not already in row k's top-k list
    gives (piv(k), l) with weight W(k,l) W(k,piv) / E1(k); and P's diagonal, diag(S_W)(l) + a(l), at least
    `SINGULAR_SHIFT` x the mean diagonal (``dsum`` / n_c; 1 if that is 0), and 1 on the gauge column ``skip``.
    (A column whose rows all pivot on it has a zero row in S: P's diagonal there is 0, which FSAI refuses.)
    Slots from ``base``: 2 per column entry, then one diagonal."""
    l = wp.tid()
    kc = ctop_val.shape[1]
    kk = top_val.shape[1]
    slot = base + l * (2 * kc + 1)
    for j in range(kc):
        k = int(ctop_idx[l, j])
        w = wp.float64(0.0)
        p = l
        if k >= 0:
            p = int(piv[k])
            w = ctop_val[l, j] * top_val[k, 0] / e1[k]
            for i in range(kk):
                if int(top_idx[k, i]) == l:
                    w = wp.float64(0.0)
        put_edge(rows, cols, vals, slot, p, l, w, skip)
        slot += 2
    d = diag[l] + a_c[l]
    floor = _SHIFT * dsum[0] / wp.float64(diag.shape[0])
    if not (floor > wp.float64(0.0)):
        floor = wp.float64(1.0)
    if not (d > floor):
        d = wp.max(d, floor)
    if l == skip:
        d = wp.float64(1.0)
    rows[slot] = l
    cols[slot] = l
    vals[slot] = d


# --------------------------------------------------------------------------- CG on the device
@wp.kernel
def norm_dot(r: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.float64), cg: wp.array(dtype=wp.float64),
             slot_rr: int, slot_rz: int):
    """r . r and r . z into ``cg`` (||rhs||^2 and the first r . z when r = rhs)."""
    i = wp.tid()
    wp.atomic_add(cg, slot_rr, r[i] * r[i])
    wp.atomic_add(cg, slot_rz, r[i] * z[i])


@wp.kernel
def cg_first(cg: wp.array(dtype=wp.float64), tol2: wp.float64, scal: wp.array(dtype=wp.float64)):
    """A new solve: its tolerance; the previous solve's results move to the slots of the one before."""
    cg[_TOL2] = tol2
    scal[_IT0] = scal[_IT]
    scal[_OK0] = scal[_OK]


@wp.kernel
def cg_go(cg: wp.array(dtype=wp.float64), cond: wp.array(dtype=wp.int32), scal: wp.array(dtype=wp.float64)):
    """The first condition: iterate unless the right-hand side is 0."""
    if cg[_NB2] > wp.float64(0.0):
        cond[0] = 1
        scal[_OK] = wp.float64(0.0)
    else:
        cond[0] = 0
        scal[_OK] = wp.float64(1.0)
    scal[_IT] = wp.float64(0.0)


@wp.kernel
def cg_condition(cg: wp.array(dtype=wp.float64), it: wp.array(dtype=wp.int32), max_iter: int,
                 cond: wp.array(dtype=wp.int32), scal: wp.array(dtype=wp.float64)):
    """Go on while ||r||^2 > rtol^2 ||rhs||^2, below ``max_iter`` and p.q > 0 (else CG broke down); the count
    and convergence into ``scal``. Resets the sums of the next iteration."""
    nb2 = cg[_NB2]
    rr = cg[_RR]
    rel2 = wp.float64(0.0)
    if nb2 > wp.float64(0.0):
        rel2 = rr / nb2
    ok = rel2 <= cg[_TOL2]
    go = int(0)
    if not ok and it[0] < max_iter and cg[_PQ] > wp.float64(0.0):
        go = 1
    cond[0] = go
    scal[_IT] = wp.float64(it[0])
    scal[_OK] = wp.where(ok, wp.float64(1.0), wp.float64(0.0))
    cg[_PQ] = wp.float64(0.0)
    cg[_AP] = wp.float64(0.0)


@wp.kernel
def dot_into(a: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64), cg: wp.array(dtype=wp.float64),
             slot: int):
    i = wp.tid()
    wp.atomic_add(cg, slot, a[i] * b[i])


@wp.kernel
def matvec_finish(q: wp.array(dtype=wp.float64), a_c: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64),
                  cg: wp.array(dtype=wp.float64), inv_asum: wp.float64, partial: int, gauge: int):
    """q += a p - a (a . p) / sum a (partial), q(last) = 0 (balanced gauge)."""
    l = wp.tid()
    if partial != 0:
        q[l] = q[l] + (a_c[l] * p[l] - a_c[l] * (cg[_AP] * inv_asum))
    if gauge != 0 and l == q.shape[0] - 1:
        q[l] = wp.float64(0.0)


@wp.kernel
def cg_update(cg: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64), q: wp.array(dtype=wp.float64),
              x: wp.array(dtype=wp.float64), r: wp.array(dtype=wp.float64)):
    """x += alpha p, r -= alpha q with alpha = r.z / p.q (nothing when p.q <= 0: CG breaks down)."""
    i = wp.tid()
    pq = cg[_PQ]
    if pq > wp.float64(0.0):
        alpha = cg[_RZ] / pq
        x[i] = x[i] + alpha * p[i]
        r[i] = r[i] - alpha * q[i]


@wp.kernel
def cg_count(cg: wp.array(dtype=wp.float64), it: wp.array(dtype=wp.int32)):
    """One more iteration, unless CG broke down (p.q <= 0: nothing was updated)."""
    if cg[_PQ] > wp.float64(0.0):
        it[0] = it[0] + 1


@wp.kernel
def cg_direction(cg: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64)):
    """p = z + (r.z new / r.z) p."""
    i = wp.tid()
    rz = cg[_RZ]
    beta = wp.float64(0.0)
    if rz != wp.float64(0.0):
        beta = cg[_RZN] / rz
    p[i] = z[i] + beta * p[i]


@wp.kernel
def cg_shift(cg: wp.array(dtype=wp.float64)):
    """r.z <- r.z new; the sums of r for the next iteration start at 0."""
    cg[_RZ] = cg[_RZN]
    cg[_RZN] = wp.float64(0.0)
    cg[_RR] = wp.float64(0.0)


# --------------------------------------------------------------------------- step
@wp.kernel
def step_limit(d_b: wp.array(dtype=wp.float64), s_piv: wp.array(dtype=wp.float64), beta: wp.float64,
               min_x: wp.float64, scal: wp.array(dtype=wp.float64)):
    """min over rows of s_piv / -d_b where d_b < 0 and beta s_piv > ``min_x`` (`Engine.newton`'s fraction
    to s = 0), into scal (set to 1e300 beforehand)."""
    k = wp.tid()
    db = d_b[k]
    s = s_piv[k]
    if db < wp.float64(0.0) and s * beta > min_x:
        wp.atomic_min(scal, _LIMIT, s / -db)


#: the slot of `DeviceLoop.scal` that holds the step limit of `step_limit` (read by `Engine.trial_from`)
LIMIT_SLOT = _LIMIT


def device_loop_bytes(n_r: int, n_c: int, kk: int, kc: int, multilevel: bool = True) -> int:
    """Device bytes a `DeviceLoop` adds to its engine (n_r rows, n_c columns, ``kk`` / ``kc`` top weights per
    row / column): its vectors, the triplets of P and P itself (an upper bound: duplicates are summed),
    FSAI's factor, transpose and set-up work (`FSAI_ROW` entries a row), and with ``multilevel`` the V-cycle's
    levels (`wpot.ot.anneal.multilevel.multilevel_bytes`)."""
    f64, i32 = 8, 4
    vectors = f64 * (2 * n_r + 5 * n_c + N_SCAL + N_CG)
    n_trip = n_r * kk * (kk - 1) + n_c * (2 * kc + 1)
    triplets = (2 * i32 + f64) * n_trip
    bsr = (i32 + f64) * n_trip + i32 * (n_c + 1)
    # G, its transpose and the support selection's columns, ranks, values and candidates (`FSAI_ROW` a row)
    fsai = (5 * i32 + 4 * f64) * n_c * FSAI_ROW + 2 * f64 * n_c
    levels = multilevel_bytes(n_c, n_trip) if multilevel else 0
    return vectors + triplets + bsr + fsai + levels


class DeviceLoop:
    """The device buffers of one `Engine`'s device-resident Newton steps (see the module docstring)."""

    def __init__(self, eng: Engine):
        self.e = eng
        p = eng.p
        d = p.device
        self.device = wp.get_device(d)
        z = lambda n: wp.zeros(n, dtype=wp.float64, device=d)  # noqa: E731
        self.m_r, self.m_c, self.a_c = z(p.n_r), z(p.n_c), z(p.n_c)
        for dst, src in ((self.m_r, p.m_r), (self.m_c, p.m_c), (self.a_c, p.a_c)):
            eng.to_device(dst, src)
        self.inv_asum = wp.float64(1.0 / eng.a_sum if eng.a_sum > 0 else 0.0)
        self.gauge = int(not p.partial)
        self.g1, self.g2 = z(p.n_r), z(p.n_c)
        self.scal = z(N_SCAL)
        self.last = np.zeros(N_SCAL)  # the last read of ``scal``
        # CG: the solution is the engine's dy_a, p and q are its matvec input and output (v, mv)
        self.r, self.z = z(p.n_c), z(p.n_c)
        self.cg = z(N_CG)
        self.it = wp.zeros(1, dtype=wp.int32, device=d)
        self.cond = wp.zeros(1, dtype=wp.int32, device=d)
        self.M: FSAI | None = None
        self.ml: Multilevel | None = None  # the V-cycle around M (device_preconditioner="multilevel")
        self.refit_ok = False  # whether the next rebuild may refit the last pattern
        self.n_refits = 0  # refits since the last full build
        kk, kc = eng.kk, eng.ctop_val.shape[1]
        self.row_slots = p.n_r * kk * (kk - 1)
        n_trip = self.row_slots + p.n_c * (2 * kc + 1)
        self.t_rows = wp.zeros(n_trip, dtype=wp.int32, device=d)
        self.t_cols = wp.zeros(n_trip, dtype=wp.int32, device=d)
        self.t_vals = wp.zeros(n_trip, dtype=wp.float64, device=d)
        self.P = wsp.bsr_zeros(p.n_c, p.n_c, wp.float64, device=d)
        self.dsum = z(1)
        #: CG as a captured graph (GPUs with conditional graph nodes; a test seam on the CPU, where Warp
        #: captures too)
        self.captured = self.device.is_cuda and wp.is_conditional_graph_supported()
        self.n_reads = 0  # reads of ``scal``
        self._stage = None  # ``scal`` and another small array, for one read of both
        self.n_solves = 0
        self.n_captures = 0
        self._graph = None  # the captured CG loop, and the (preconditioner, matvec launches) it was captured for
        self._graph_for = (None, None)
        self._launches = None

    # ------------------------------------------------------------------ evaluation
    def point(self, lam, y) -> Point:
        """The residuals g1, g2 (left in ``self.g1``, ``self.g2``) and the sums at the point the engine's
        evaluation pass just saw; reads ``scal`` (one synchronisation) into a `Point` without host vectors."""

        e, p, d = self.e, self.e.p, self.e.p.device
        self.scal[:N_EVAL].zero_()
        wp.launch(residual_rows, dim=p.n_r, inputs=[self.m_r, e.b, lam[0], lam[1], e.row_g, e.row_u, e.row_xphi,
                                                   self.g1, self.scal], device=d)
        if p.partial:
            wp.launch(a_dot_y, dim=p.n_c, inputs=[self.a_c, y[0], y[1], self.scal], device=d)
        wp.launch(residual_cols, dim=p.n_c, inputs=[self.m_c, self.a_c, y[0], y[1], e.col_g, self.inv_asum,
                                                   int(p.partial), self.g2, self.scal], device=d)
        s = self.read()
        x = (s[_AY] - 1.0) * float(self.inv_asum) if p.partial else 0.0
        return Point(None, None, float(np.sqrt(s[_G2])), 0.5 * float(s[_L1]), u=float(s[_U]),
                     xphi=float(s[_XPHI]), x=x)

    def read(self, extra: wp.array | None = None) -> np.ndarray:
        """``scal`` to the host (one synchronisation), kept as ``last``; with ``extra`` (a small float64 array on
        the device) both in the same read, and ``extra``'s copy is returned."""
        if extra is None:
            self.last = self.e.to_host(self.scal).copy()
            self.n_reads += 1
            return self.last
        n = extra.shape[0]
        if self._stage is None or self._stage.shape[0] != N_SCAL + n:
            self._stage = wp.empty(N_SCAL + n, dtype=wp.float64, device=self.e.p.device)
        wp.copy(self._stage, self.scal, 0, 0, N_SCAL)
        wp.copy(self._stage, extra, N_SCAL, 0, n)
        both = self.e.to_host(self._stage).copy()
        self.last = both[:N_SCAL]
        self.n_reads += 1
        return both[N_SCAL:]

    def free_sums(self, lam, y, x: float) -> None:
        """Sum g and the `wpot.ot.anneal.state.DualSums` at the duals ``lam``, ``y``, the partial scalar ``x`` and
        the last evaluation, after `kernels.free_rows`, into ``scal`` (`free_values` reads them)."""
        e, p, d = self.e, self.e.p, self.e.p.device
        self.scal[_F:_PEN + 1].zero_()
        wp.launch(free_sums_rows, dim=p.n_r, inputs=[e.row_f, lam[0], lam[1], self.m_r, e.b, e.row_g,
                                                    int(p.partial), self.scal], device=d)
        wp.launch(free_sums_cols, dim=p.n_c, inputs=[y[0], y[1], x, self.m_c, self.a_c, e.col_g, int(p.partial),
                                                    self.scal], device=d)

    def free_values(self):
        """(sum g, `wpot.ot.anneal.state.DualSums`) of the last `free_sums`, from the last read of ``scal``."""

        s = self.last
        return float(s[_F]), DualSums(float(s[_LM]), float(s[_YM]), float(s[_BL2]), float(s[_AM2]), self.penalty())

    def penalty(self) -> float:
        """The partial penalty of the last `free_sums` (from the last read)."""
        return float(self.last[_PEN])

    def cg_result(self, back: int = 0) -> tuple[int, bool]:
        """(CG iterations, converged) of the last solve (``back`` = 1: the one before), from the last read."""
        if back == 0:
            return int(self.last[_IT]), bool(self.last[_OK])
        return int(self.last[_IT0]), bool(self.last[_OK0])

    def step_limit(self, beta: float, min_x: float) -> None:
        """The Newton step's limit (`step_limit`) for the last direction, into ``scal`` (no read)."""
        self.scal[_LIMIT:_LIMIT + 1].fill_(1e300)
        wp.launch(step_limit, dim=self.e.p.n_r, inputs=[self.e.d_b, self.e.s_piv, beta, min_x, self.scal],
                  device=self.e.p.device)

    def limit(self) -> float:
        """The step limit of the last `step_limit`, from the last read of ``scal``."""
        return float(self.last[_LIMIT])

    # ------------------------------------------------------------------ Newton direction
    def set_residual(self, pt: Point) -> None:
        """The residuals the next direction solves for: ``pt``'s (host arrays are uploaded, device arrays
        copied), or, when ``pt`` has none, those of the last evaluation (already in ``g1``, ``g2``)."""
        for dst, src in ((self.g1, pt.g1), (self.g2, pt.g2)):
            if src is None:
                continue
            if isinstance(src, wp.array):
                wp.copy(dst, src)
            else:
                self.e.to_device(dst, np.asarray(src, dtype=np.float64))

    def rebuild_preconditioner(self) -> bool:
        """A new preconditioner at this point: a refit (`refit_preconditioner`, no host read) when the last
        one's pattern still serves (``refit_ok``) and fewer than `FULL_BUILD_EVERY` - 1 refits followed the
        last full build, else a full build. Returns whether it was a full build."""
        if self.M is not None and self.refit_ok and self.n_refits < FULL_BUILD_EVERY - 1:
            self.refit_preconditioner()
            self.n_refits += 1
            return False
        self.build_preconditioner()
        self.n_refits = 0
        return True

    def _assemble(self) -> None:
        """The triplets of P from the top-k selections (rows: ``eng.top_*``, columns: ``eng.ctop_*``, both at
        this point) and S_W's diagonal."""
        e, p, d = self.e, self.e.p, self.e.p.device
        skip = p.n_c - 1 if self.gauge else -1
        wp.launch(sparse_schur_rows, dim=p.n_r, inputs=[e.top_val, e.top_idx, e.piv, e.e1, skip],
                  outputs=[self.t_rows, self.t_cols, self.t_vals], device=d)
        self.dsum.zero_()
        wp.launch(sum_into, dim=p.n_c, inputs=[e.diag_s, self.dsum], device=d)
        wp.launch(sparse_schur_cols, dim=p.n_c,
                  inputs=[e.ctop_val, e.ctop_idx, e.top_val, e.top_idx, e.piv, e.e1, e.diag_s, self.a_c, self.dsum,
                          skip, self.row_slots], outputs=[self.t_rows, self.t_cols, self.t_vals], device=d)

    def build_preconditioner(self) -> None:
        """P assembled into a new sparsity pattern and FSAI on it, its supports selected on the device by the
        first update (the same factor as FSAI's eager set-up, in `BUILD_SYNCS` synchronisations, not 6)."""
        self._assemble()
        wsp.bsr_set_from_triplets(self.P, self.t_rows, self.t_cols, self.t_vals)
        self.M = FSAI(self.P, max_row_size=FSAI_ROW, reuse_pattern=True, regularize_refit=True,
                      validate_topology=False, defer_pattern=True)
        self.M.update(self.P)
        if self.e.o.device_preconditioner == "multilevel":
            self.ml = Multilevel(self.P, self.M, self.e.to_host)
        self.refit_ok = True

    def refit_preconditioner(self) -> None:
        """P's new values on the last build's pattern (entries outside it are dropped: P stays diagonally
        dominant) and FSAI refitted on its supports: kernels only, no host read. (The engine's reuse rule sets
        ``refit_ok`` False after a refit that does not serve: the next rebuild is a full one.)"""
        self._assemble()
        wsp.bsr_set_from_triplets(self.P, self.t_rows, self.t_cols, self.t_vals, topology="masked")
        self.M.update(self.P)
        if self.ml is not None:
            self.ml.refit()

    def apply_preconditioner(self) -> None:
        """z = M^-1 r."""
        if self.ml is not None:
            self.ml.apply(self.r, self.z)
        else:
            self.M.matvec(self.r, self.z, self.z, 1.0, 0.0)

    def solve(self, rtol: float, max_iter: int, launches: list) -> None:
        """CG on S dy = rhs (rhs in ``r``) from dy = 0, into the engine's ``dy_a``, with the Schur matvec's
        recorded ``launches`` (`wpot.ot.anneal.schur.SchurSolver.matvec_launches`); no host read (see the
        module docstring). Its count, residual and convergence land in ``scal``."""
        e, p, d = self.e, self.e.p, self.e.p.device
        self.n_solves += 1
        e.dy_a.zero_()
        self.cg.zero_()
        self.it.zero_()
        wp.launch(cg_first, dim=1, inputs=[self.cg, wp.float64(rtol * rtol), self.scal], device=d)
        self.apply_preconditioner()
        wp.launch(norm_dot, dim=p.n_c, inputs=[self.r, self.z, self.cg, _NB2, _RZ], device=d)
        wp.copy(e.v, self.z)
        wp.launch(cg_go, dim=1, inputs=[self.cg, self.cond, self.scal], device=d)
        self._launches = launches
        if self.captured:
            # one graph per preconditioner and matvec (a refit changes only their arrays' contents)
            if self._graph is None or self._graph_for[0] is not self.M or self._graph_for[1] is not self._launches:
                with wp.ScopedCapture(device=d) as capture:
                    wp.capture_while(self.cond, self._iteration, max_iter=max_iter)
                self._graph, self._graph_for = capture.graph, (self.M, self._launches)
                self.n_captures += 1
            wp.capture_launch(self._graph)
        elif self.device.is_cuda:  # no conditional graph nodes: read the condition each iteration
            while e.to_host(self.cond)[0]:
                self._iteration(max_iter)
        else:  # the condition is in host memory
            wp.capture_while(self.cond, self._iteration, max_iter=max_iter)

    def _iteration(self, max_iter: int) -> None:
        """One CG iteration, all on the device."""
        e, p, d = self.e, self.e.p, self.e.p.device
        e.mv.zero_()
        if len(self._launches) > 1:
            e.delta.zero_()
        for cmd in self._launches:
            cmd.launch()
        if p.partial:
            wp.launch(dot_into, dim=p.n_c, inputs=[self.a_c, e.v, self.cg, _AP], device=d)
        wp.launch(matvec_finish, dim=p.n_c, inputs=[e.mv, self.a_c, e.v, self.cg, self.inv_asum, int(p.partial),
                                                   self.gauge], device=d)
        wp.launch(dot_into, dim=p.n_c, inputs=[e.v, e.mv, self.cg, _PQ], device=d)
        wp.launch(cg_update, dim=p.n_c, inputs=[self.cg, e.v, e.mv, e.dy_a, self.r], device=d)
        self.apply_preconditioner()
        wp.launch(norm_dot, dim=p.n_c, inputs=[self.r, self.z, self.cg, _RR, _RZN], device=d)
        wp.launch(cg_count, dim=1, inputs=[self.cg, self.it], device=d)
        wp.launch(cg_direction, dim=p.n_c, inputs=[self.cg, self.z, e.v], device=d)
        wp.launch(cg_condition, dim=1, inputs=[self.cg, self.it, max_iter, self.cond, self.scal], device=d)
        wp.launch(cg_shift, dim=1, inputs=[self.cg], device=d)


class DeviceSolver(SchurSolver):
    """The `wpot.ot.anneal.schur.NewtonSolver` of the device loop: drives a `DeviceLoop` (``dev``) for its
    engine (see the module docstring)."""

    def __init__(self, eng: Engine):
        super().__init__(eng)
        self.dev = DeviceLoop(eng)
        self._free_pending = None  # (point, reads of ``dev.scal``) of the last `free_sums`

    # ------------------------------------------------------------------ evaluation
    def point(self, lam, y, full: bool) -> Point:
        """The `Point` at the last evaluation (`DeviceLoop.point`: one read; U and the gap sum always come)."""
        return self.dev.point(lam, y)

    def free_sums(self, lam, y, pt: Point) -> None:
        """Sum g and ``pt``'s `DualSums` into the device's scalars; they come with the next read of them
        (`free_values`), and until then ``pt.f_sum`` is NaN."""
        self.dev.free_sums(lam, y, pt.x)
        pt.f_sum, pt.sums = math.nan, None
        self._free_pending = (pt, self.dev.n_reads)

    def free_values(self, pt: Point) -> Point:
        """``pt`` with sum g and its `DualSums` after `free_sums` (the last one, at ``pt``): from the first
        read of the device's scalars since then, or from one now."""
        if not math.isnan(pt.f_sum):
            return pt
        at, reads = self._free_pending
        if at is not pt:
            raise RuntimeError("free_values: the last free_pass was not at this point")
        if self.dev.n_reads == reads:
            self.dev.read()
        pt.f_sum, pt.sums = self.dev.free_values()
        return pt

    def read_scalars(self, arr: wp.array) -> np.ndarray:
        """``arr`` (a small device array) to the host in one read with the device's scalars (the last
        directions' CG counts)."""
        return self.dev.read(arr)

    # ------------------------------------------------------------------ the Newton step
    def step_start(self, beta: float, pt: Point, rtol: float,
                   min_x: float) -> tuple[Callable[[], tuple[int, bool]], float]:
        """The Newton direction at the last evaluation (its residuals are on the device) and its step limit
        (`step_limit`, rows with beta s > ``min_x``) left on the device; the length is NaN here."""
        counts = self.direction_later(Point(None, None, 0.0, 0.0), rtol)
        self.dev.step_limit(beta, min_x)
        return counts, math.nan

    def first_factor(self, last: float) -> float:
        """`STEP_GROWTH` x the last accepted fraction of this call's line search, at most 1."""
        return min(1.0, STEP_GROWTH * last)

    def trial(self, factor: float, limit: float) -> None:
        """The trial duals at ``factor`` x min(1, `LIMIT_FRACTION` x the step limit on the device) (no read)."""
        self.e.trial_from(self.dev.scal, LIMIT_SLOT, LIMIT_FRACTION, factor)

    def step_length(self, limit: float) -> float:
        """The first trial's step length, from the step limit that came with the last read."""
        return step_alpha(self.dev.limit())

    # ------------------------------------------------------------------ the Newton direction
    def direction_later(self, pt: Point, rtol: float | None = None) -> Callable[[], tuple[int, bool]]:
        """`solve` (no read); the returned function gives its (linear iterations, converged) from the next
        read of the device's scalars (an evaluation, `read_scalars`), or reads them. It must be called before
        the second direction after this one."""
        fresh = self.solve(pt, rtol)
        dev, t = self.dev, self.e.t
        reads, solves = dev.n_reads, dev.n_solves

        def result() -> tuple[int, bool]:
            back = dev.n_solves - solves
            if back > 1:
                raise RuntimeError("direction_later: two more directions were solved before this one's counts "
                                   "were read")
            if dev.n_reads == reads:
                dev.read()
            n_lin, ok = dev.cg_result(back)
            t.n_matvec += n_lin
            self._after_solve(fresh, n_lin, ok)
            return n_lin, ok
        return result

    def solve(self, pt: Point, rtol: float | None) -> str | bool:
        """The Newton direction with no host read: right-hand side, preconditioner (when it is rebuilt), CG
        and back-substitution as kernels; CG's count and convergence land in ``dev.scal``. Returns how the
        preconditioner was rebuilt ("build", "refit"), or False when it was reused."""
        e, p, o, t, dev = self.e, self.e.p, self.e.o, self.e.t, self.dev
        t0 = time.perf_counter()
        self._select_weights()
        dev.set_residual(pt)
        wp.launch(add_vec, dim=p.n_r, inputs=[e.row_w, e.b, e.e1], device=p.device)
        fresh = self._M is None or self._M_fresh_needed
        self._prep(dev.g1, fresh)
        wp.launch(schur_rhs, dim=p.n_c, inputs=[dev.g2, e.wtg, dev.gauge, dev.r], device=p.device)
        t.prep += time.perf_counter() - t0
        if fresh:
            t0 = time.perf_counter()
            self._col_topk()
            if dev.rebuild_preconditioner():
                t.n_factor += 1
                t.n_build_sync += BUILD_SYNCS
                fresh = "build"
            else:
                t.n_refit += 1
                fresh = "refit"
            self._M = dev.M
            self._M_fresh_needed = False
            t.precond += time.perf_counter() - t0
        t0 = time.perf_counter()
        dev.solve(o.cg_rtol if rtol is None else max(rtol, o.cg_rtol), o.cg_max_iter, self.matvec_launches())
        t.cg += time.perf_counter() - t0
        t0 = time.perf_counter()
        self._recover(dev.g1)
        t.other += time.perf_counter() - t0
        return fresh

    def _after_solve(self, fresh: str | bool, n_lin: int, ok: bool) -> None:
        """The reuse rule (`wpot.ot.anneal.schur.SchurSolver._after_solve`), and after a refit: a refit that
        failed or needed more than `REFIT_SLOWDOWN` x the last full build's count (+ `REFRESH_EXTRA_CG`) is
        replaced by a full build at the next point, and the refits stop until then."""
        if fresh == "refit":
            if not ok or n_lin > REFIT_SLOWDOWN * self._M_iters + REFRESH_EXTRA_CG:
                self.dev.refit_ok = False
                self._M_fresh_needed = True
        else:
            super()._after_solve(fresh, n_lin, ok)
