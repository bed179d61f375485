"""Linear solvers for the Newton system in Schur-complement form.

The Newton system of the (negated, convex) free energy in (lam, y) is

    [ E1   W  ] [dlam]   [-g1]      E1 = diag(row sums of W) + diag(b),
    [ W^T  E2 ] [dy  ] = [-g2],     E2 = diag(column sums of W) + diag(a) - a a^T / sum(a),

with W = beta |phi'(beta s)| (a bipartite, signless-Laplacian structure; singular along (1, -1) in the
balanced case, b = a = 0). The rows (diagonal block) are eliminated:

    S dy = -g2 + W^T E1^-1 g1,     S = E2 - W^T E1^-1 W,

and S (a graph Laplacian on the columns plus the partial terms) is applied matrix-free by
`kernels.schur_matvec` in a cancellation-free form that pivots each row on its largest weight. This is
what keeps the solve accurate at beta = 1e14, where W spans 25+ orders of magnitude: the full system's
small eigenvalues (the "rotations" of nearly matched pairs) are lost to rounding, S's are not.

Solvers: preconditioned CG on S with a sparse approximation of S built from the top-k weights per row
and per column of W (exact diagonal), factorized by SuperLU (symmetric mode, no pivoting) and reused
across Newton steps and betas until CG with it slows down (see `wpot.ot.anneal.schur.REFRESH_EXTRA_CG`); or a dense direct
(Cholesky) solve of S, formed with BLAS, as the paper does (LU) for comparison.
The balanced gauge is fixed by dy(last) = 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass
class SchurData:
    """Host-side (numpy) pieces of S at one Newton point (length n_c or n_r arrays)."""

    diag_w: np.ndarray  # (n_c,) diagonal of S_W = D2 - W^T E1^-1 W
    e1: np.ndarray  # (n_r,)
    piv: np.ndarray  # (n_r,) int
    a: np.ndarray  # (n_c,) partial column terms (zeros: balanced)
    gauge: bool  # balanced: fix dy[-1] = 0


def assemble_sparse_schur(data: SchurData, row_val, row_idx, col_val, col_idx) -> sp.csc_matrix:
    """Sparse approximation P of S_W + diag(a) from selected weights (top-k per row and per column).

    Every selected entry W(k,l), l != piv(k), gives an edge (piv(k), l) of weight W(k,l) W(k,piv)/E1(k);
    pairs of row-selected non-pivot entries give edges of weight W(k,l1) W(k,l2)/E1(k) (rows split
    between several partners). The diagonal is S_W's exact diagonal, so P is diagonally dominant.
    """
    n_r, kk = row_val.shape
    n_c = data.diag_w.shape[0]
    e1 = data.e1
    piv = data.piv.astype(np.int64)
    wpiv = row_val[:, 0]  # the largest weight of each row is its pivot's
    ii, jj, ww = [], [], []
    # pivot <-> other entries of the row's top-k
    rows = np.repeat(np.arange(n_r), kk - 1)
    idx = row_idx[:, 1:].reshape(-1).astype(np.int64)
    val = row_val[:, 1:].reshape(-1)
    ok = idx >= 0
    rows, idx, val = rows[ok], idx[ok], val[ok]
    ii.append(piv[rows])
    jj.append(idx)
    ww.append(val * wpiv[rows] / e1[rows])
    # pairs among a row's non-pivot top entries (second order unless the row is split)
    for j1 in range(1, kk):
        for j2 in range(j1 + 1, kk):
            l1, l2 = row_idx[:, j1].astype(np.int64), row_idx[:, j2].astype(np.int64)
            ok = (l1 >= 0) & (l2 >= 0)
            w = row_val[:, j1] * row_val[:, j2] / e1
            big = ok & (w > 1e-3 * (row_val[:, 1] * wpiv / e1))
            if np.any(big):
                ii.append(l1[big])
                jj.append(l2[big])
                ww.append(w[big])
    # column top-k entries (rows whose pivot is another column)
    kc = col_val.shape[1]
    cols = np.repeat(np.arange(n_c), kc)
    rk = col_idx.reshape(-1).astype(np.int64)
    cv = col_val.reshape(-1)
    ok = rk >= 0
    cols, rk, cv = cols[ok], rk[ok], cv[ok]
    # drop entries already taken from the row lists
    in_row = np.zeros(cols.shape, dtype=bool)
    for j in range(kk):
        in_row |= row_idx[rk, j] == cols
    keep = ~in_row
    ii.append(piv[rk[keep]])
    jj.append(cols[keep])
    ww.append(cv[keep] * wpiv[rk[keep]] / e1[rk[keep]])
    i = np.concatenate(ii)
    j = np.concatenate(jj)
    w = np.concatenate(ww)
    off = i != j
    i, j, w = i[off], j[off], w[off]
    A = sp.coo_matrix((np.concatenate([-w, -w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n_c, n_c))
    A = A.tocsr()
    A.sum_duplicates()
    A = A + sp.diags(data.diag_w + data.a)
    return A.tocsc()


#: relative diagonal shift of the preconditioner's sparse Schur approximation when it is exactly singular
SINGULAR_SHIFT = 1e-8


def _factor(P: sp.csc_matrix):
    return spla.splu(P, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


class SchurPreconditioner:
    """z = M^-1 r with M = P - a a^T / sum(a) (Sherman-Morrison), P factorized by SuperLU.
    Balanced: P's last row/column are dropped (gauge dy[-1] = 0) and z[-1] = 0."""

    def __init__(self, P: sp.csc_matrix, a: np.ndarray, gauge: bool):
        n = P.shape[0]
        self.n = n
        self.gauge = gauge
        if gauge:
            P = P[: n - 1, : n - 1]
        # P is symmetric and diagonally dominant (SPD once the gauge is fixed): no pivoting is needed, and
        # a symmetric elimination keeps the minimum-degree ordering's fill
        P = sp.csc_matrix(P)
        self.shifted = False
        try:
            self.lu = _factor(P)
        except RuntimeError:
            # exactly singular: the sparsified couplings fell apart into pieces, and a piece that does not
            # hold the gauge has a singular (Laplacian) block. Any SPD M is a valid preconditioner, so shift
            # the diagonal a little; CG on the exact Schur complement stays exact.
            d = np.abs(P.diagonal())
            scale = float(d.mean()) if d.size and d.mean() > 0 else 1.0
            self.lu = _factor(P + sp.diags(SINGULAR_SHIFT * np.maximum(d, scale)))
            self.shifted = True
        self.sm = None
        if np.any(a > 0):
            A = float(a.sum())
            pa = self.lu.solve(a)
            den = A - float(a @ pa)
            # M = P - a a^T/A is SPD only when den > 0; when rounding eats den, P alone is used
            if den > 1e-12 * A:
                self.sm = (pa, den, a)

    def __call__(self, r: np.ndarray) -> np.ndarray:
        if self.gauge:
            z = np.zeros_like(r)
            z[:-1] = self.lu.solve(r[:-1])
            return z
        z = self.lu.solve(r)
        if self.sm is not None:
            pa, den, a = self.sm
            z = z + pa * (float(a @ z) / den)
        return z


@dataclass
class CGInfo:
    iterations: int
    residual: float  # final ||r|| / ||rhs||
    converged: bool


def pcg(matvec, rhs: np.ndarray, precond, *, rtol: float, max_iter: int, gauge: bool = False
        ) -> tuple[np.ndarray, CGInfo]:
    """Preconditioned conjugate gradients from x0 = 0 (host vectors of length n_c; the O(N^2)
    matvec runs in Warp). Stops at ||r|| <= rtol ||rhs||. With ``gauge`` the last unknown is fixed
    to 0 (the preconditioner returns z[-1] = 0) and the last equation is left out of the norms."""
    x = np.zeros_like(rhs)
    r = rhs.copy()
    m = slice(0, rhs.shape[0] - 1) if gauge else slice(None)
    nb = float(np.linalg.norm(rhs[m]))
    if nb == 0.0:
        return x, CGInfo(0, 0.0, True)
    z = precond(r)
    p = z.copy()
    rz = float(r @ z)
    it = 0
    rel = 1.0
    while it < max_iter:
        q = matvec(p)
        pq = float(p @ q)
        if not pq > 0:
            break
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        it += 1
        rel = float(np.linalg.norm(r[m])) / nb
        if rel <= rtol:
            return x, CGInfo(it, rel, True)
        z = precond(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, CGInfo(it, rel, rel <= rtol)


def direct_solve(W: np.ndarray, data: SchurData, rhs: np.ndarray) -> np.ndarray:
    """Dense Cholesky solve of S dy = rhs with S formed exactly: off-diagonal -W^T E1^-1 W (BLAS, sums of
    positive terms), the cancellation-free diagonal from the kernel, and the partial terms."""
    Wn = W / np.sqrt(data.e1)[:, None]
    S = -(Wn.T @ Wn)
    del Wn
    np.fill_diagonal(S, data.diag_w)
    if np.any(data.a > 0):
        S += np.diag(data.a) - np.outer(data.a, data.a) / data.a.sum()
    if data.gauge:
        dy = np.zeros_like(rhs)
        c = sla.cho_factor(S[:-1, :-1], lower=True, check_finite=False)
        dy[:-1] = sla.cho_solve(c, rhs[:-1], check_finite=False)
        return dy
    c = sla.cho_factor(S, lower=True, check_finite=False)
    return sla.cho_solve(c, rhs, check_finite=False)
