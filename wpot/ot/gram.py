"""Passes over a matrix-free Euclidean cost on the CPU through BLAS: the Gram matrix a block of rows at a time.

Warp's CPU backend runs a kernel on one thread without SIMD, so a pass over C(k, l) = ||A(k) - B(l)||
recomputed from D ~ 100 features costs on the order of D times a pass over a stored C. Almost all of that
work is the inner products, which BLAS (NumPy's matmul, every core, SIMD) does many times faster (the docs'
Results page). `GramBlocks` fills one block
P(i, l) = A(k0 + i) . B(l) at a time; a Warp kernel then reads

    ||A(k) - B(l)||^2 = a2(k) + b2(l) - 2 P(i, l),   off by at most err (an(k) + bn(l))^2,

(a2, b2 the squared norms, an, bn the norms, ``err`` = 2 (D + 4) 2^-53: the rounding of the dot product and of
the norms, with a margin of 2), which bounds each entry from below and above. A kernel recomputes exactly,
with the per-pair function every other pass uses (`wpot.ot.kernels.cost_at`), only the few entries whose
bound cannot settle its answer, so its outputs are those of the plain kernel, bit for bit
(`feature_cost_max_gram` here; `wpot.ot.exact.balanced.price_rows_gram`). Memory: one block (64 MiB by default).
"""
from __future__ import annotations

from typing import Iterator

import numpy as np
import warp as wp

from wpot._warp import launch_rows
from wpot.ot import kernels as K

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["GRAM_BLOCK_BYTES", "GramBlocks", "gram_applies", "gram_blocks", "feature_cost_max_gram"]

#: bytes of one block of the Gram matrix
GRAM_BLOCK_BYTES = 64 * 2**20
#: relative error bound of a2 + b2 - 2 A.B per feature, with a margin of 2 (|fl(x.y) - x.y| <= D u |x| |y|)
_ERR_PER_FEATURE = 2.0 * 2.0 ** -53


def gram_applies(features, device) -> bool:
    """Whether passes over ``features`` (a `FeatureCost`, or None for a stored cost) on ``device`` can go
    through `GramBlocks`: a Euclidean cost on the CPU (on a GPU the plain kernels are fast)."""
    return features is not None and features.metric == "l2" and wp.get_device(device).is_cpu


def gram_blocks(features, device, gram: bool | GramBlocks | None = None) -> GramBlocks | None:
    """The `GramBlocks` that passes over ``features`` on ``device`` use, or None for the plain kernels.
    ``gram``: None where `gram_applies`, False never, True always, or the `GramBlocks` to use (a test seam);
    True or a `GramBlocks` where it does not apply is a ValueError (the bound is for the Euclidean metric)."""
    fits = gram_applies(features, device)
    use = fits if gram is None else gram is not False
    if use and not fits:
        raise ValueError("gram needs a FeatureCost with metric='l2' on the CPU")
    if not use:
        return None
    return gram if isinstance(gram, GramBlocks) else GramBlocks(features)


@wp.func
def sq_bounds(P: wp.array2d(dtype=wp.float64), i: int, l: int, ak2: wp.float64, ak: wp.float64,
              b2: wp.array(dtype=wp.float64), bn: wp.array(dtype=wp.float64), err: wp.float64):
    """Lower and upper bounds of ||A(k) - B(l)||^2 from the Gram block (row i of the block is row k)."""
    e = err * (ak + bn[l]) * (ak + bn[l])
    s2 = ak2 + b2[l] - wp.float64(2.0) * P[i, l]
    return wp.max(s2 - e, wp.float64(0.0)), s2 + e


@wp.kernel
def feature_cost_max_gram(P: wp.array2d(dtype=wp.float64), k0: int, src: K.LazyCost, n_c: int,
                          a2: wp.array(dtype=wp.float64), b2: wp.array(dtype=wp.float64),
                          an: wp.array(dtype=wp.float64), bn: wp.array(dtype=wp.float64), err: wp.float64,
                          row_max: wp.array(dtype=wp.float64)):
    """`wpot.ot.kernels.feature_cost_max` for rows k0 + i from the Gram block: an entry is recomputed exactly
    only where its upper bound exceeds the row's running maximum (about log N2 entries a row)."""
    i = wp.tid()
    k = k0 + i
    mx = wp.float64(0.0)
    ak2 = a2[k]
    ak = an[k]
    for l in range(n_c):
        lo2, hi2 = sq_bounds(P, i, l, ak2, ak, b2, bn, err)
        if wp.sqrt(hi2) * src.inv_scale * wp.float64(1.0 + 1e-15) > mx:
            mx = wp.max(mx, K.cost_at(src, k, l))
    row_max[k] = mx


class GramBlocks:
    """The Gram matrix of a Euclidean `FeatureCost` (X (N1, D), Y (N2, D) on the CPU), a block of rows at a
    time. ``blocks(transposed)`` yields (k0, n, P): rows k0 .. k0 + n of P = A B^T in a (h, n_c) ``wp.array``
    that shares its memory with the buffer matmul fills (A, B = X, Y, or Y, X with ``transposed``); the
    buffer is reused, so each block must be consumed (by a CPU launch, which runs at once) before the next.
    ``norms(transposed)`` gives the kernels' (a2, b2, an, bn) and ``err`` the bound's constant."""

    def __init__(self, features, *, block_bytes: int = GRAM_BLOCK_BYTES):
        self.feats = (features.X.numpy(), features.Y.numpy())  # views of the CPU arrays
        sq = [np.einsum("ij,ij->i", f, f) for f in self.feats]
        arr = lambda x: wp.array(x, dtype=wp.float64, device="cpu")  # noqa: E731
        self._sq = [arr(q) for q in sq]
        self._norm = [arr(np.sqrt(q)) for q in sq]
        self.err = _ERR_PER_FEATURE * (self.feats[0].shape[1] + 4)
        self.block_bytes = int(block_bytes)

    def norms(self, transposed: bool = False) -> tuple[wp.array, wp.array, wp.array, wp.array]:
        i, j = (1, 0) if transposed else (0, 1)
        return self._sq[i], self._sq[j], self._norm[i], self._norm[j]

    def blocks(self, transposed: bool = False) -> Iterator[tuple[int, int, wp.array]]:
        A, B = (self.feats[1], self.feats[0]) if transposed else self.feats
        n_r, n_c = A.shape[0], B.shape[0]
        h = max(1, min(n_r, self.block_bytes // (8 * n_c)))
        buf = np.empty((h, n_c))
        P = wp.array(buf, dtype=wp.float64, device="cpu", copy=False)  # the same memory
        for k0 in range(0, n_r, h):
            k1 = min(k0 + h, n_r)
            np.matmul(A[k0:k1], B.T, out=buf[:k1 - k0])
            yield k0, k1 - k0, P

    def row_max(self, src) -> np.ndarray:
        """Each row's max C'(k, l) (``src`` a `LazyCost` of these features), as `feature_cost_max` gives it."""
        out = wp.empty(self.feats[0].shape[0], dtype=wp.float64, device="cpu")
        n_c = self.feats[1].shape[0]
        norms, err = self.norms(), wp.float64(self.err)
        for k0, n, P in self.blocks():
            launch_rows(lambda lo, hi: wp.launch(feature_cost_max_gram, dim=hi - lo, device="cpu",
                                                 inputs=[P[lo:hi], k0 + lo, src, n_c, *norms, err, out]), n, "cpu",
                        cols=n_c)
        return out.numpy()
