"""Warp kernels of the statistical-physics OT solver (float64 throughout).

Notation (internal, see `wpot.ot.problem`): the solver works on an oriented, normalized problem with
``n_r`` "rows" (the side that is eliminated in the Schur complement, the larger one) and ``n_c``
"columns". The reduced cost of entry (k, l) is

    s(k, l) = C'(k, l) + lam(k) + y(l),          C' = C / max C,

with ``lam`` and ``y`` stored in double-double (hi + lo) so that ``s`` keeps full relative precision
when C' + lam + y cancels (at beta = 1e14, s ~ 1e-11 while C' ~ 1). The plan is
G(k, l) = phi(beta * s(k, l)) (paper Eq. 15 / 26) and the Hessian weights are
W(k, l) = beta * |phi'(beta * s(k, l))|.

Every read of the cost matrix goes through the single `cost_at` function, so that a matrix-free mode
(the cost computed from signatures inside the kernel) only needs another `cost_at`.
"""
from __future__ import annotations

import warp as wp

import wpot._warp  # noqa: F401  (quiet Warp start-up, shared by every module)

wp.set_module_options({"enable_backward": False})

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
def cost_at(C: wp.array2d(dtype=wp.float64), k: int, l: int, trans: int, inv_scale: wp.float64) -> wp.float64:
    """The single place where the cost matrix is read: C'(k, l) in the solver's orientation."""
    if trans != 0:
        return C[l, k] * inv_scale
    return C[k, l] * inv_scale


@wp.func
def reduced_cost(c: wp.float64, lh: wp.float64, ll: wp.float64, yh: wp.float64, yl: wp.float64) -> wp.float64:
    """s = c + (lh + ll) + (yh + yl) with the cancellation c + lh + yh done error-free."""
    t = c + lh
    e1 = two_sum_err(c, lh, t)
    u = t + yh
    e2 = two_sum_err(t, yh, u)
    return u + ((e1 + e2) + (ll + yl))


@wp.kernel
def eval_rows(
    C: wp.array2d(dtype=wp.float64),
    trans: int,
    inv_scale: wp.float64,
    n_c: int,
    beta: wp.float64,
    lam_hi: wp.array(dtype=wp.float64),
    lam_lo: wp.array(dtype=wp.float64),
    y_hi: wp.array(dtype=wp.float64),
    y_lo: wp.array(dtype=wp.float64),
    # outputs
    W: wp.array2d(dtype=wp.float64),
    row_g: wp.array(dtype=wp.float64),
    col_g: wp.array(dtype=wp.float64),
    row_w: wp.array(dtype=wp.float64),
    piv: wp.array(dtype=wp.int32),
    tail: wp.array(dtype=wp.float64),
    row_u: wp.array(dtype=wp.float64),
    row_xphi: wp.array(dtype=wp.float64),
    s_piv: wp.array(dtype=wp.float64),
):
    """One pass over row k: G = phi(beta s), its row sum (and column sums, atomically), W = beta |phi'|
    (stored), W's row sum, argmax (pivot), the row sum without the pivot (``tail``, accumulated without
    cancellation), the pivot's s, sum G C' (U) and sum x phi(x) (beta x duality gap)."""
    k = wp.tid()
    lh = lam_hi[k]
    ll = lam_lo[k]
    sg = _ZERO
    su = _ZERO
    sx = _ZERO
    wmax = wp.float64(-1.0)
    wrest = _ZERO
    p = int(0)
    sp = _ZERO
    for l in range(n_c):
        c = cost_at(C, k, l, trans, inv_scale)
        x = beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l])
        gw = phi_w(x)
        g = gw[0]
        w = beta * gw[1]
        sg += g
        wp.atomic_add(col_g, l, g)
        W[k, l] = w
        if w > wmax:
            if wmax > _ZERO:
                wrest += wmax
            wmax = w
            p = l
            sp = x / beta
        else:
            wrest += w
        su += g * c
        sx += x * g
    row_g[k] = sg
    piv[k] = p
    tail[k] = wrest
    row_w[k] = wrest + wmax
    row_u[k] = su
    row_xphi[k] = sx
    s_piv[k] = sp


@wp.kernel
def free_rows(
    C: wp.array2d(dtype=wp.float64),
    trans: int,
    inv_scale: wp.float64,
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
        c = cost_at(C, k, l, trans, inv_scale)
        x = beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l])
        sf += gfun(x)
        ws = phi_w(x)[1] * x
        sws += ws
        wp.atomic_add(col_ws, l, ws)
    row_f[k] = sf
    row_ws[k] = sws


@wp.kernel
def schur_prep(
    W: wp.array2d(dtype=wp.float64),
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
    for j in range(topk):
        top_val[k, j] = wp.float64(-1.0)
        top_idx[k, j] = -1
    tmin = wp.float64(-1.0)
    for l in range(n_c):
        w = W[k, l]
        rest = ek - w
        if l == p:
            rest = tail[k] + b[k]
        wp.atomic_add(diag_s, l, w * rest / ek)
        wp.atomic_add(wtg, l, w * gk)
        if topk > 0 and w > tmin:
            # insertion into the descending list top_val[k, :]
            j = topk - 1
            while j > 0 and top_val[k, j - 1] < w:
                top_val[k, j] = top_val[k, j - 1]
                top_idx[k, j] = top_idx[k, j - 1]
                j -= 1
            top_val[k, j] = w
            top_idx[k, j] = l
            tmin = top_val[k, topk - 1]


@wp.kernel
def schur_prep_topk(
    W: wp.array2d(dtype=wp.float64),
    n_c: int,
    topk: int,
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """Row k's ``topk`` largest W entries alone (the selection part of `schur_prep`)."""
    k = wp.tid()
    for j in range(topk):
        top_val[k, j] = wp.float64(-1.0)
        top_idx[k, j] = -1
    tmin = wp.float64(-1.0)
    for l in range(n_c):
        w = W[k, l]
        if w > tmin:
            j = topk - 1
            while j > 0 and top_val[k, j - 1] < w:
                top_val[k, j] = top_val[k, j - 1]
                top_idx[k, j] = top_idx[k, j - 1]
                j -= 1
            top_val[k, j] = w
            top_idx[k, j] = l
            tmin = top_val[k, topk - 1]


@wp.kernel
def col_topk(
    W: wp.array2d(dtype=wp.float64),
    n_r: int,
    piv: wp.array(dtype=wp.int32),
    topk: int,
    top_val: wp.array2d(dtype=wp.float64),
    top_idx: wp.array2d(dtype=wp.int32),
):
    """Column l's ``topk`` largest W entries among rows whose pivot is not l."""
    l = wp.tid()
    for j in range(topk):
        top_val[l, j] = wp.float64(-1.0)
        top_idx[l, j] = -1
    tmin = wp.float64(-1.0)
    for k in range(n_r):
        w = W[k, l]
        if w > tmin and piv[k] != l:
            j = topk - 1
            while j > 0 and top_val[l, j - 1] < w:
                top_val[l, j] = top_val[l, j - 1]
                top_idx[l, j] = top_idx[l, j - 1]
                j -= 1
            top_val[l, j] = w
            top_idx[l, j] = k
            tmin = top_val[l, topk - 1]


@wp.func
def row_dot_diff(W: wp.array2d(dtype=wp.float64), k: int, n_c: int, v: wp.array(dtype=wp.float64),
                 vp: wp.float64) -> wp.float64:
    """sum_l W(k, l) (v(l) - vp) with four independent accumulators (the single-accumulator loop is
    bound by the latency of the additions on the CPU backend)."""
    a0 = _ZERO
    a1 = _ZERO
    a2 = _ZERO
    a3 = _ZERO
    n4 = n_c - n_c % 4
    for l in range(0, n4, 4):
        a0 += W[k, l] * (v[l] - vp)
        a1 += W[k, l + 1] * (v[l + 1] - vp)
        a2 += W[k, l + 2] * (v[l + 2] - vp)
        a3 += W[k, l + 3] * (v[l + 3] - vp)
    for l in range(n4, n_c):
        a0 += W[k, l] * (v[l] - vp)
    return (a0 + a1) + (a2 + a3)


@wp.kernel
def schur_matvec(
    W: wp.array2d(dtype=wp.float64),
    n_c: int,
    piv: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.float64),
):
    """out += S_W v with S_W = D2 - W^T E1^-1 W, E1 = D1 + diag(b), computed without cancellation:
    delta(k) = (sum_l W(k,l) (v(l) - v(p)) - b(k) v(p)) / E1(k),  out(l) += W(k,l) ((v(l) - v(p)) - delta(k)),
    p = piv(k) the row's largest weight. ``out`` must be zeroed (or hold the other terms) beforehand."""
    k = wp.tid()
    vp = v[piv[k]]
    acc = row_dot_diff(W, k, n_c, v, vp)
    delta = (acc - b[k] * vp) / e1[k]
    for l in range(n_c):
        wp.atomic_add(out, l, W[k, l] * ((v[l] - vp) - delta))


@wp.kernel
def recover_rows(
    W: wp.array2d(dtype=wp.float64),
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
    acc = row_dot_diff(W, k, n_c, dy, vp)
    d_a[k] = -vp
    d_b[k] = (-g1[k] - acc + b[k] * vp) / e1[k]


@wp.kernel
def dd_axpy(
    hi: wp.array(dtype=wp.float64),
    lo: wp.array(dtype=wp.float64),
    alpha: wp.float64,
    d_a: wp.array(dtype=wp.float64),
    d_b: wp.array(dtype=wp.float64),
    out_hi: wp.array(dtype=wp.float64),
    out_lo: wp.array(dtype=wp.float64),
):
    """(out_hi + out_lo) = (hi + lo) + alpha d_a + alpha d_b in double-double arithmetic."""
    i = wp.tid()
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
    C: wp.array2d(dtype=wp.float64),
    trans: int,
    inv_scale: wp.float64,
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
        c = cost_at(C, k, l, trans, inv_scale)
        g = phi(beta * reduced_cost(c, lh, ll, y_hi[l], y_lo[l]))
        if trans != 0:
            G[l, k] = g
        else:
            G[k, l] = g


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
