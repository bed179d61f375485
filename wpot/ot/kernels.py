"""Warp kernels of the statistical-physics OT solver (float64 throughout).

Notation (internal, see `wpot.ot.problem`): the solver works on an oriented, normalized problem with
``n_r`` "rows" (the side that is eliminated in the Schur complement, the larger one) and ``n_c``
"columns". The reduced cost of entry (k, l) is

    s(k, l) = C'(k, l) + lam(k) + y(l),          C' = C / max C,

with ``lam`` and ``y`` stored in double-double (hi + lo) so that ``s`` keeps full relative precision
when C' + lam + y cancels (at beta = 1e14, s ~ 1e-11 while C' ~ 1). The plan is
G(k, l) = phi(beta * s(k, l)) (paper Eq. 15 / 26) and the Hessian weights are
W(k, l) = beta * |phi'(beta * s(k, l))|.

Two modes share every kernel body (generic kernels, overloaded once per mode at the end of this file):

* stored: the cost is a dense (N1, N2) array (`DenseCost`) and the weights W are stored (`DenseW`) by
  `eval_rows` and read back by the Schur kernels;
* matrix-free: the cost is computed from the two signature arrays (`LazyCost`, the per-pair
  functions of `wpot.cost`) and each weight is recomputed where it is read (`LazyW`: the features, beta
  and the duals of the point `eval_rows` last evaluated), exactly as `eval_rows` computes it. No N1 x N2
  array exists; each pass over W costs a pass over the features instead.

Every read of C goes through `cost_at(src, k, l)` and every read (write) of W through
`weight_at(src, k, l)` (`put_weight`), overloaded per mode.
"""
from __future__ import annotations

from typing import Any

import warp as wp

import wpot._warp  # noqa: F401  (quiet Warp start-up, shared by every module)
from wpot.cost import pair_cost

# no fused multiply-add (Warp's default on CUDA): the double-double sums below are error-free only when
# each product is rounded on its own (fusing C * inv_scale into c + lam breaks two_sum_err: on a GPU the
# plan's row sums drift off the marginals at high beta), and every kernel must round alike
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

f64 = wp.float64

# cut-off below which phi, phi' and g use their Taylor series
_SERIES_CUT = wp.constant(wp.float64(0.5))
_ZERO = wp.constant(wp.float64(0.0))
_ONE = wp.constant(wp.float64(1.0))
_HALF = wp.constant(wp.float64(0.5))

# phi(x) = 1/2 - x/12 + x^3/720 - x^5/30240 + x^7/1209600 - x^9/47900160 + 691 x^11/1307674368000
#          - x^13/74724249600 + 3617 x^15/10670622842880000 ...   (from the Bernoulli numbers)
_P1 = wp.constant(wp.float64(-1.0 / 12.0))
_P3 = wp.constant(wp.float64(1.0 / 720.0))
_P5 = wp.constant(wp.float64(-1.0 / 30240.0))
_P7 = wp.constant(wp.float64(1.0 / 1209600.0))
_P9 = wp.constant(wp.float64(-1.0 / 47900160.0))
_P11 = wp.constant(wp.float64(691.0 / 1307674368000.0))
_P13 = wp.constant(wp.float64(-1.0 / 74724249600.0))
_P15 = wp.constant(wp.float64(3617.0 / 10670622842880000.0))
# g(x) = log((1 - e^-x) / x) = -x/2 + x^2/24 - x^4/2880 + x^6/181440 - x^8/9676800 + x^10/479001600
#        - 691 x^12/15692092416000 + x^14/1046139494400 ...  (g' = -phi)
_G2 = wp.constant(wp.float64(1.0 / 24.0))
_G4 = wp.constant(wp.float64(-1.0 / 2880.0))
_G6 = wp.constant(wp.float64(1.0 / 181440.0))
_G8 = wp.constant(wp.float64(-1.0 / 9676800.0))
_G10 = wp.constant(wp.float64(1.0 / 479001600.0))
_G12 = wp.constant(wp.float64(-691.0 / 15692092416000.0))
_G14 = wp.constant(wp.float64(1.0 / 1046139494400.0))


@wp.func
def phi(x: wp.float64) -> wp.float64:
    """phi(x) = 1/x - 1/(e^x - 1) (paper Eq. 16): the mean of a truncated exponential on [0, 1].

    In (0, 1), decreasing, phi(0) = 1/2, phi(x) ~ 1/x for x -> +inf and 1 + 1/x for x -> -inf.
    Series for |x| < 1/2, overflow-free closed forms (exp of -|x| only) elsewhere.
    """
    ax = wp.abs(x)
    if ax < _SERIES_CUT:
        x2 = x * x
        p = _P15
        p = p * x2 + _P13
        p = p * x2 + _P11
        p = p * x2 + _P9
        p = p * x2 + _P7
        p = p * x2 + _P5
        p = p * x2 + _P3
        p = p * x2 + _P1
        return _HALF + x * p
    e = wp.exp(-ax)  # in (0, e^-1/2]
    # 1/(e^x - 1) = e^-x / (1 - e^-x) for x > 0, and = -1/(1 - e^x) = -1 - e^x/(1 - e^x) for x < 0
    q = e / (_ONE - e)
    if x > _ZERO:
        return _ONE / x - q
    return _ONE + _ONE / x + q


@wp.func
def dphi(x: wp.float64) -> wp.float64:
    """phi'(x) = -1/x^2 + e^x / (e^x - 1)^2, in [-1/12, 0); ~ -1/x^2 for |x| -> inf."""
    ax = wp.abs(x)
    if ax < _SERIES_CUT:
        x2 = x * x
        # derivative of the phi series
        p = wp.float64(15.0) * _P15
        p = p * x2 + wp.float64(13.0) * _P13
        p = p * x2 + wp.float64(11.0) * _P11
        p = p * x2 + wp.float64(9.0) * _P9
        p = p * x2 + wp.float64(7.0) * _P7
        p = p * x2 + wp.float64(5.0) * _P5
        p = p * x2 + wp.float64(3.0) * _P3
        return _P1 + x2 * p
    e = wp.exp(-ax)
    d = _ONE - e
    # e^x/(e^x-1)^2 is even in x: e^-|x| / (1 - e^-|x|)^2
    return e / (d * d) - _ONE / (x * x)


_TAIL = wp.constant(wp.float64(40.0))


@wp.func
def phi_w(x: wp.float64) -> wp.vec2d:
    """(phi(x), -phi'(x)) sharing one exp; for |x| > 40 the pure tails 1/x (+1), 1/x^2 (e^-40 * 40 < 2e-16)."""
    ax = wp.abs(x)
    if ax > _TAIL:
        r = _ONE / x
        if x > _ZERO:
            return wp.vec2d(r, r * r)
        return wp.vec2d(_ONE + r, r * r)
    if ax < _SERIES_CUT:
        return wp.vec2d(phi(x), -dphi(x))
    e = wp.exp(-ax)
    d = _ONE - e
    q = e / d
    r = _ONE / x
    w = r * r - e / (d * d)
    if x > _ZERO:
        return wp.vec2d(r - q, w)
    return wp.vec2d(_ONE + r + q, w)


@wp.func
def gfun(x: wp.float64) -> wp.float64:
    """g(x) = log((1 - e^-x) / x) (the summand of Eq. 12 / 23), g' = -phi; overflow-free."""
    ax = wp.abs(x)
    if ax < _SERIES_CUT:
        x2 = x * x
        p = _G14
        p = p * x2 + _G12
        p = p * x2 + _G10
        p = p * x2 + _G8
        p = p * x2 + _G6
        p = p * x2 + _G4
        p = p * x2 + _G2
        return -_HALF * x + x2 * p
    # x > 0: log(1 - e^-x) - log x ;  x < 0: |x| + log(1 - e^-|x|) - log|x|
    r = -wp.log(ax)
    if ax <= _TAIL:  # beyond, log(1 - e^-|x|) ~ -e^-40 is below rounding
        r = r + wp.log(_ONE - wp.exp(-ax))
    if x < _ZERO:
        r = r + ax
    return r


@wp.func
def two_sum_err(a: wp.float64, b: wp.float64, s: wp.float64) -> wp.float64:
    """Exact rounding error of s = fl(a + b) (Knuth's TwoSum)."""
    bb = s - a
    return (a - (s - bb)) + (b - bb)


@wp.func
def reduced_cost(c: wp.float64, lh: wp.float64, ll: wp.float64, yh: wp.float64, yl: wp.float64) -> wp.float64:
    """s = c + (lh + ll) + (yh + yl) with the cancellation c + lh + yh done error-free."""
    t = c + lh
    e1 = two_sum_err(c, lh, t)
    u = t + yh
    e2 = two_sum_err(t, yh, u)
    return u + ((e1 + e2) + (ll + yl))


# --------------------------------------------------------------------------- cost and weight sources
@wp.struct
class DenseCost:
    """Stored mode: the user's (N1, N2) cost matrix, read transposed when ``trans`` (rows = user's columns)."""

    C: wp.array2d(dtype=wp.float64)
    trans: int
    inv_scale: wp.float64


@wp.struct
class LazyCost:
    """Matrix-free mode: signatures of the solver's rows (A, (n_r, D)) and columns (B, (n_c, D)), already
    oriented (the metrics are symmetric bit for bit, so no ``trans`` is needed), a `wpot.cost.METRIC_CODES` code."""

    A: wp.array2d(dtype=wp.float64)
    B: wp.array2d(dtype=wp.float64)
    metric: int
    inv_scale: wp.float64


@wp.func
def cost_at(src: DenseCost, k: int, l: int) -> wp.float64:
    """C'(k, l) = C(k, l) / max C in the solver's orientation, from the stored matrix."""
    if src.trans != 0:
        return src.C[l, k] * src.inv_scale
    return src.C[k, l] * src.inv_scale


@wp.func
def cost_at(src: LazyCost, k: int, l: int) -> wp.float64:  # noqa: F811  (Warp overload)
    """C'(k, l) computed from the signatures (the same per-pair function as `wpot.cost.cost_matrix`)."""
    return pair_cost(src.metric, src.A, k, src.B, l) * src.inv_scale


@wp.struct
class DenseW:
    """Stored mode: the Hessian weights W (n_r, n_c), written by `eval_rows`."""

    W: wp.array2d(dtype=wp.float64)


@wp.struct
class NoW:
    """Matrix-free mode, as `eval_rows`' weight sink: the weights are not stored."""

    unused: int


@wp.struct
class LazyW:
    """Matrix-free mode: W(k, l) recomputed from the cost, beta and the duals (double-double) of the point
    that `eval_rows` last evaluated."""

    cost: LazyCost
    beta: wp.float64
    lam_hi: wp.array(dtype=wp.float64)
    lam_lo: wp.array(dtype=wp.float64)
    y_hi: wp.array(dtype=wp.float64)
    y_lo: wp.array(dtype=wp.float64)


@wp.func
def weight_at(src: DenseW, k: int, l: int) -> wp.float64:
    return src.W[k, l]


@wp.func
def weight_at(src: LazyW, k: int, l: int) -> wp.float64:  # noqa: F811  (Warp overload)
    """beta |phi'(beta s(k, l))|, the same operations as in `eval_rows` (same value to the last bit)."""
    c = cost_at(src.cost, k, l)
    x = src.beta * reduced_cost(c, src.lam_hi[k], src.lam_lo[k], src.y_hi[l], src.y_lo[l])
    return src.beta * phi_w(x)[1]


@wp.func
def put_weight(dst: DenseW, k: int, l: int, w: wp.float64):
    dst.W[k, l] = w


@wp.func
def put_weight(dst: NoW, k: int, l: int, w: wp.float64):  # noqa: F811  (Warp overload)
    return


@wp.func
def topk_insert(val: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32), r: int, topk: int,
                w: wp.float64, i: int) -> wp.float64:
    """Insert (w, i) into row r of the descending top-``topk`` list (w > the list's minimum); returns the new
    minimum. Ties keep the earlier index first."""
    j = topk - 1
    while j > 0 and val[r, j - 1] < w:
        val[r, j] = val[r, j - 1]
        idx[r, j] = idx[r, j - 1]
        j -= 1
    val[r, j] = w
    idx[r, j] = i
    return val[r, topk - 1]


@wp.func
def topk_clear(val: wp.array2d(dtype=wp.float64), idx: wp.array2d(dtype=wp.int32), r: int, topk: int):
    for j in range(topk):
        val[r, j] = wp.float64(-1.0)
        idx[r, j] = -1


# --------------------------------------------------------------------------- passes over C / W
@wp.func
def track_pivot(w: wp.float64, l: int, wmax: wp.float64, wrest: wp.float64, p: int):
    """One entry of a row's pivot scan: returns (largest weight, sum of the others, its column). Each weight
    is added to ``wrest`` once it is known not to be the largest, so the rest is summed without
    cancellation (E1 - W(k, pivot) = tail + b)."""
    if w > wmax:
        if wmax > _ZERO:
            wrest += wmax
        return w, wrest, l
    return wmax, wrest + w, p


@wp.kernel
def free_rows(
    csrc: Any,
    n_c: int,
    beta: wp.float64,
    lam_hi: wp.array(dtype=wp.float64),
    lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64),
    y_lo: wp.array(dtype=wp.float64),
    # outputs
    row_f: wp.array(dtype=wp.float64),
    row_ws: wp.array(dtype=wp.float64),
    col_ws: wp.array(dtype=wp.float64),
):
    """Once per beta, at the saddle point: sum_l g(beta s) (for F, Eq. 12 / 23) and the row and column
    sums of W s = beta |phi'(x)| s = |phi'(x)| x (right-hand side of the tangent d(lam, y)/d(log beta)).
    ``col_ws`` must be zeroed beforehand."""
    k = wp.tid()
    lh = lam_hi[k]
    ll = lam_lo[k]
    sf = _ZERO
    sws = _ZERO
    for l in range(n_c):
        c = cost_at(csrc, k, l)
        x = beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l])
        sf += gfun(x)
        ws = phi_w(x)[1] * x
        sws += ws
        wp.atomic_add(col_ws, l, ws)
    row_f[k] = sf
    row_ws[k] = sws


@wp.kernel
def schur_prep(
    wsrc: Any,
    n_c: int,
    piv: wp.array(dtype=wp.int32),
    tail: wp.array(dtype=wp.float64),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    g1: wp.array(dtype=wp.float64),
    topk: int,
    # outputs
    diag_s: wp.array(dtype=wp.float64),
    wtg: wp.array(dtype=wp.float64),
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """Row k's contributions to the Schur complement S = E2 - W^T E1^-1 W onto the columns:
    diag(S_W)(l) += W(k,l) (E1(k) - W(k,l)) / E1(k) (the pivot term uses tail + b: no cancellation),
    wtg(l) += W(k,l) g1(k) / E1(k) (for the right-hand side), and row k's ``topk`` largest W entries
    (``topk`` = 0: no selection, when the preconditioner is not rebuilt)."""
    k = wp.tid()
    p = piv[k]
    ek = e1[k]
    gk = g1[k] / ek
    topk_clear(top_val, top_idx, k, topk)
    tmin = wp.float64(-1.0)
    for l in range(n_c):
        w = weight_at(wsrc, k, l)
        rest = ek - w
        if l == p:
            rest = tail[k] + b[k]
        wp.atomic_add(diag_s, l, w * rest / ek)
        wp.atomic_add(wtg, l, w * gk)
        if topk > 0 and w > tmin:
            tmin = topk_insert(top_val, top_idx, k, topk, w, l)


@wp.kernel
def schur_prep_topk(
    wsrc: Any,
    n_c: int,
    topk: int,
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """Row k's ``topk`` largest W entries alone (the selection part of `schur_prep`)."""
    k = wp.tid()
    topk_clear(top_val, top_idx, k, topk)
    tmin = wp.float64(-1.0)
    for l in range(n_c):
        w = weight_at(wsrc, k, l)
        if w > tmin:
            tmin = topk_insert(top_val, top_idx, k, topk, w, l)


@wp.kernel
def col_topk(
    wsrc: Any,
    n_r: int,
    piv: wp.array(dtype=wp.int32),
    topk: int,
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """Column l's ``topk`` largest W entries among rows whose pivot is not l."""
    l = wp.tid()
    topk_clear(top_val, top_idx, l, topk)
    tmin = wp.float64(-1.0)
    for k in range(n_r):
        if piv[k] != l:
            w = weight_at(wsrc, k, l)
            if w > tmin:
                tmin = topk_insert(top_val, top_idx, l, topk, w, k)


@wp.func
def row_dot_diff(wsrc: Any, k: int, n_c: int, v: wp.array(dtype=wp.float64), vp: wp.float64) -> wp.float64:
    """sum_l W(k, l) (v(l) - vp) with four independent accumulators (the single-accumulator loop is
    bound by the latency of the additions on the CPU backend)."""
    a0 = _ZERO
    a1 = _ZERO
    a2 = _ZERO
    a3 = _ZERO
    n4 = n_c - n_c % 4
    for l in range(0, n4, 4):
        a0 += weight_at(wsrc, k, l) * (v[l] - vp)
        a1 += weight_at(wsrc, k, l + 1) * (v[l + 1] - vp)
        a2 += weight_at(wsrc, k, l + 2) * (v[l + 2] - vp)
        a3 += weight_at(wsrc, k, l + 3) * (v[l + 3] - vp)
    for l in range(n4, n_c):
        a0 += weight_at(wsrc, k, l) * (v[l] - vp)
    return (a0 + a1) + (a2 + a3)


@wp.kernel
def schur_matvec(
    wsrc: Any,
    n_c: int,
    piv: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.float64),
):
    """out += S_W v with S_W = D2 - W^T E1^-1 W, E1 = D1 + diag(b), computed without cancellation:
    delta(k) = (sum_l W(k,l) (v(l) - v(p)) - b(k) v(p)) / E1(k),  out(l) += W(k,l) ((v(l) - v(p)) - delta(k)),
    p = piv(k) the row's largest weight. ``out`` must be zeroed (or hold the other terms) beforehand.
    (Matrix-free: each weight is computed twice, once per sweep.)"""
    k = wp.tid()
    vp = v[piv[k]]
    acc = row_dot_diff(wsrc, k, n_c, v, vp)
    delta = (acc - b[k] * vp) / e1[k]
    for l in range(n_c):
        wp.atomic_add(out, l, weight_at(wsrc, k, l) * ((v[l] - vp) - delta))


#: lanes per row (per column) of the strided Schur matvec kernels below: the GPU then runs n * LANES
#: threads, each reading every LANES-th entry, so that neighbouring threads read neighbouring entries
MATVEC_LANES = 64


@wp.kernel
def schur_row_partial(
    wsrc: Any,
    n_c: int,
    lanes: int,
    piv: wp.array(dtype=wp.int32),
    v: wp.array(dtype=wp.float64),
    acc: wp.array(dtype=wp.float64),
):
    """Strided first sweep of `schur_matvec` for many-core devices: lane j of row k adds
    sum_{l = j, j + lanes, ...} W(k, l) (v(l) - v(p)) to ``acc[k]`` (zeroed beforehand)."""
    k, j = wp.tid()
    vp = v[piv[k]]
    a = _ZERO
    for l in range(j, n_c, lanes):
        a += weight_at(wsrc, k, l) * (v[l] - vp)
    wp.atomic_add(acc, k, a)


@wp.kernel
def schur_row_delta(
    piv: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
    acc: wp.array(dtype=wp.float64),
):
    """delta(k) = (acc(k) - b(k) v(p)) / E1(k), in place of ``acc`` (see `schur_matvec`)."""
    k = wp.tid()
    acc[k] = (acc[k] - b[k] * v[piv[k]]) / e1[k]


@wp.kernel
def schur_col_sweep(
    wsrc: Any,
    n_r: int,
    lanes: int,
    piv: wp.array(dtype=wp.int32),
    v: wp.array(dtype=wp.float64),
    delta: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.float64),
):
    """Strided second sweep of `schur_matvec`: lane j of column l adds
    sum_{k = j, j + lanes, ...} W(k, l) ((v(l) - v(p_k)) - delta(k)) to ``out[l]``."""
    j, l = wp.tid()  # l fastest: a warp reads one row's neighbouring entries
    vl = v[l]
    a = _ZERO
    for k in range(j, n_r, lanes):
        a += weight_at(wsrc, k, l) * ((vl - v[piv[k]]) - delta[k])
    wp.atomic_add(out, l, a)


@wp.kernel
def recover_finish(
    piv: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    g1: wp.array(dtype=wp.float64),
    dy: wp.array(dtype=wp.float64),
    acc: wp.array(dtype=wp.float64),
    d_a: wp.array(dtype=wp.float64),
    d_b: wp.array(dtype=wp.float64),
):
    """`recover_rows` from the strided row sums ``acc`` of `schur_row_partial` (with v = dy)."""
    k = wp.tid()
    vp = dy[piv[k]]
    d_a[k] = -vp
    d_b[k] = (-g1[k] - acc[k] + b[k] * vp) / e1[k]


@wp.kernel
def schur_prep_cols(
    wsrc: Any,
    n_r: int,
    lanes: int,
    piv: wp.array(dtype=wp.int32),
    tail: wp.array(dtype=wp.float64),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    g1: wp.array(dtype=wp.float64),
    diag_s: wp.array(dtype=wp.float64),
    wtg: wp.array(dtype=wp.float64),
):
    """`schur_prep` without the top-k selection, as strided column lanes (see `schur_col_sweep`): lane j of
    column l adds its rows' terms of diag(S_W)(l) and wtg(l) (``diag_s``, ``wtg`` zeroed beforehand)."""
    j, l = wp.tid()
    ds = _ZERO
    wg = _ZERO
    for k in range(j, n_r, lanes):
        w = weight_at(wsrc, k, l)
        ek = e1[k]
        rest = ek - w
        if l == piv[k]:
            rest = tail[k] + b[k]
        ds += w * rest / ek
        wg += w * (g1[k] / ek)
    wp.atomic_add(diag_s, l, ds)
    wp.atomic_add(wtg, l, wg)


@wp.kernel
def eval_rows(
    csrc: Any,
    wdst: Any,
    n_c: int,
    lanes: int,
    beta: wp.float64,
    lam_hi: wp.array(dtype=wp.float64),
    lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64),
    y_lo: wp.array(dtype=wp.float64),
    # outputs
    col_g: wp.array(dtype=wp.float64),
    lane_f: wp.array3d(dtype=wp.float64),
    lane_p: wp.array2d(dtype=wp.int32),
):
    """One pass over C at a point, in ``lanes`` strided lanes per row (1 on the CPU, which streams the row;
    many on GPUs, so that neighbouring threads read neighbouring entries). Lane j of row k scans columns
    j, j + lanes, ...: G = phi(beta s) (column sums added atomically), W = beta |phi'| (stored into ``wdst``
    in stored mode), and leaves lane_f[k, j] = (sum G, sum G C' (U), sum x phi(x) (beta x duality gap),
    largest W, sum of the other W (without cancellation), s at the largest) and lane_p[k, j] = the largest
    W's column. `eval_combine` reduces the lanes of each row."""
    k, j = wp.tid()
    lh = lam_hi[k]
    ll = lam_lo[k]
    sg = _ZERO
    su = _ZERO
    sx = _ZERO
    wmax = wp.float64(-1.0)
    wrest = _ZERO
    p = int(-1)
    sp = _ZERO
    for l in range(j, n_c, lanes):
        c = cost_at(csrc, k, l)
        x = beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l])
        gw = phi_w(x)
        g = gw[0]
        w = beta * gw[1]
        sg += g
        wp.atomic_add(col_g, l, g)
        put_weight(wdst, k, l, w)
        wmax, wrest, p = track_pivot(w, l, wmax, wrest, p)
        if p == l:
            sp = x / beta
        su += g * c
        sx += x * g
    lane_f[k, j, 0] = sg
    lane_f[k, j, 1] = su
    lane_f[k, j, 2] = sx
    lane_f[k, j, 3] = wmax
    lane_f[k, j, 4] = wrest
    lane_f[k, j, 5] = sp
    lane_p[k, j] = p


@wp.kernel
def eval_combine(
    lanes: int,
    lane_f: wp.array3d(dtype=wp.float64),
    lane_p: wp.array2d(dtype=wp.int32),
    # outputs
    row_g: wp.array(dtype=wp.float64),
    row_w: wp.array(dtype=wp.float64),
    piv: wp.array(dtype=wp.int32),
    tail: wp.array(dtype=wp.float64),
    row_u: wp.array(dtype=wp.float64),
    row_xphi: wp.array(dtype=wp.float64),
    s_piv: wp.array(dtype=wp.float64),
):
    """Row k of `eval_rows` from its lanes: G's row sum, U, sum x phi, the pivot = the largest W (the smallest
    column on ties, as one lane's scan), its s, the rest of the row's W (``tail``, summed without
    cancellation) and W's row sum = tail + the pivot's W. With one lane each value is that lane's, exactly."""
    k = wp.tid()
    sg = _ZERO
    su = _ZERO
    sx = _ZERO
    best = int(0)
    for j in range(lanes):
        sg += lane_f[k, j, 0]
        su += lane_f[k, j, 1]
        sx += lane_f[k, j, 2]
        pj = lane_p[k, j]
        if pj >= 0:
            wj = lane_f[k, j, 3]
            wb = lane_f[k, best, 3]
            pb = lane_p[k, best]
            if pb < 0 or wj > wb or (wj == wb and pj < pb):
                best = j
    rest = _ZERO
    for j in range(lanes):
        if lane_p[k, j] >= 0:
            rest += lane_f[k, j, 4]
            if j != best and lane_f[k, j, 3] > _ZERO:
                rest += lane_f[k, j, 3]
    wmax = lane_f[k, best, 3]
    row_g[k] = sg
    piv[k] = lane_p[k, best]
    tail[k] = rest
    row_w[k] = rest + wmax
    row_u[k] = su
    row_xphi[k] = sx
    s_piv[k] = lane_f[k, best, 5]


@wp.kernel
def recover_rows(
    wsrc: Any,
    n_c: int,
    piv: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    g1: wp.array(dtype=wp.float64),
    dy: wp.array(dtype=wp.float64),
    d_a: wp.array(dtype=wp.float64),
    d_b: wp.array(dtype=wp.float64),
):
    """Back-substitution dlam = E1^-1 (-g1 - W dy), returned as d_a + d_b with d_a = -dy(p) (which
    cancels exactly against the pivot column's dy in the reduced cost) and d_b the small remainder."""
    k = wp.tid()
    p = piv[k]
    vp = dy[p]
    acc = row_dot_diff(wsrc, k, n_c, dy, vp)
    d_a[k] = -vp
    d_b[k] = (-g1[k] - acc + b[k] * vp) / e1[k]


@wp.kernel
def dd_axpy(
    hi: wp.array(dtype=wp.float64),
    lo: wp.array(dtype=wp.float64),
    steps: wp.array(dtype=wp.float64),
    slot: int,
    coef: wp.float64,
    factor: wp.float64,
    d_a: wp.array(dtype=wp.float64),
    d_b: wp.array(dtype=wp.float64),
    out_hi: wp.array(dtype=wp.float64),
    out_lo: wp.array(dtype=wp.float64),
):
    """(out_hi + out_lo) = (hi + lo) + alpha d_a + alpha d_b in double-double arithmetic, with the step
    length alpha = factor min(1, coef steps[slot]) (computed on the device: ``steps[slot]`` = 1e300 gives
    alpha = factor)."""
    i = wp.tid()
    alpha = factor * wp.min(_ONE, coef * steps[slot])
    h = hi[i]
    a = alpha * d_a[i]
    s = h + a
    e = two_sum_err(h, a, s)
    bb = alpha * d_b[i]
    s2 = s + bb
    e = e + two_sum_err(s, bb, s2) + lo[i]
    t = s2 + e
    out_lo[i] = e - (t - s2)
    out_hi[i] = t


@wp.kernel
def plan_kernel(
    csrc: Any,
    trans: int,
    n_c: int,
    beta: wp.float64,
    lam_hi: wp.array(dtype=wp.float64),
    lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64),
    y_lo: wp.array(dtype=wp.float64),
    G: wp.array2d(dtype=wp.float64),
):
    """The plan G = phi(beta s) in the user's orientation ((N1, N2): transposed back when ``trans``)."""
    k = wp.tid()
    lh = lam_hi[k]
    ll = lam_lo[k]
    for l in range(n_c):
        c = cost_at(csrc, k, l)
        g = phi(beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l]))
        if trans != 0:
            G[l, k] = g
        else:
            G[k, l] = g


@wp.kernel
def plan_topk(
    csrc: Any,
    trans: int,
    n_r: int,
    n_c: int,
    beta: wp.float64,
    lam_hi: wp.array(dtype=wp.float64),
    lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64),
    y_lo: wp.array(dtype=wp.float64),
    topk: int,
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """User row i's ``topk`` largest plan entries G(i, j) = phi(beta s) (the values `plan_kernel` writes)
    and their user column indices, in descending order (ties: smaller index first, as numpy's argmax).
    One thread per user row: a row of the solver (``trans`` = 0) or a column (``trans`` = 1)."""
    i = wp.tid()
    topk_clear(top_val, top_idx, i, topk)
    tmin = wp.float64(-1.0)
    n = n_c
    if trans != 0:
        n = n_r
    for j in range(n):
        k = i
        l = j
        if trans != 0:
            k = j
            l = i
        g = phi(beta * reduced_cost(cost_at(csrc, k, l), lam_hi[k], lam_lo[k], y_hi[l], y_lo[l]))
        if g > tmin:
            tmin = topk_insert(top_val, top_idx, i, topk, g, j)


@wp.kernel
def feature_cost_max(csrc: LazyCost, n_c: int, row_max: wp.array(dtype=wp.float64)):
    """Row maxima of the (unscaled when inv_scale = 1) cost computed from the signatures (no C stored)."""
    k = wp.tid()
    mx = _ZERO
    for l in range(n_c):
        mx = wp.max(mx, cost_at(csrc, k, l))
    row_max[k] = mx


@wp.kernel
def cost_stats(
    C: wp.array2d(dtype=wp.float64),
    n2: int,
    row_min: wp.array(dtype=wp.float64),
    row_max: wp.array(dtype=wp.float64),
    row_bad: wp.array(dtype=wp.int32),
):
    """Per-row min, max and count of non-finite entries of C (validation without a host copy)."""
    k = wp.tid()
    mn = C[k, 0]
    mx = C[k, 0]
    bad = int(0)
    for l in range(n2):
        c = C[k, l]
        if wp.isnan(c) or wp.isinf(c):
            bad += 1
        else:
            mn = wp.min(mn, c)
            mx = wp.max(mx, c)
    row_min[k] = mn
    row_max[k] = mx
    row_bad[k] = bad


@wp.kernel
def eval_phi(x: wp.array(dtype=wp.float64), out_phi: wp.array(dtype=wp.float64),
             out_dphi: wp.array(dtype=wp.float64), out_g: wp.array(dtype=wp.float64)):
    """phi, phi' and g on a vector (for tests and diagnostics)."""
    i = wp.tid()
    out_phi[i] = phi(x[i])
    out_dphi[i] = dphi(x[i])
    out_g[i] = gfun(x[i])


# --------------------------------------------------------------------------- one instance per mode
#: (generic kernel, struct type of its source argument) -> the concrete instance; launch it through `variant`
#: (a generic kernel launched directly infers every argument's type, Python floats as float32)
_VARIANTS = {}
for _c, _w in ((DenseCost, DenseW), (LazyCost, NoW)):
    _VARIANTS[(eval_rows, _c)] = wp.overload(eval_rows, {"csrc": _c, "wdst": _w})
for _c in (DenseCost, LazyCost):
    for _k in (free_rows, plan_kernel, plan_topk):
        _VARIANTS[(_k, _c)] = wp.overload(_k, {"csrc": _c})
for _w in (DenseW, LazyW):
    for _k in (schur_prep, schur_prep_topk, col_topk, schur_matvec, schur_row_partial, schur_col_sweep,
               schur_prep_cols, recover_rows):
        _VARIANTS[(_k, _w)] = wp.overload(_k, {"wsrc": _w})


def variant(kernel: wp.Kernel, src) -> wp.Kernel:
    """The instance of a generic kernel of this module for the source struct ``src`` (its first argument)."""
    return _VARIANTS[(kernel, src._cls)]
