"""Similarity registration of matched point pairs (paper §5.1, Fig. 1): a transform ``x ↦ s R x + t``.

`fit_similarity` is the weighted least-squares fit (Umeyama 1991) that `wpot.Comparer` applies to a
comparison's matched pairs; `Registration` is its result.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from wpot.mesh import Mesh

__all__ = ["Registration", "fit_similarity"]


@dataclass(frozen=True)
class Registration:
    """A similarity transform ``x ↦ scale · R x + t`` (paper §5.1, Fig. 1).

    Attributes
    ----------
    scale : float, > 0
    rotation : (3, 3) float64, a proper rotation (det = +1)
    translation : (3,) float64
    rms : weighted root-mean-square residual ``|scale·R·s + t − d|`` over the fitted pairs
    n_pairs : number of point pairs it was fitted to
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    rms: float
    n_pairs: int

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous matrix of the transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def apply(self, x: Mesh | ArrayLike) -> Mesh | np.ndarray:
        """Transform a mesh (returns a new `Mesh`) or points ``(n, 3)`` (returns ``(n, 3)`` float64)."""
        if isinstance(x, Mesh):
            return x.transformed(self.rotation, self.translation, self.scale)
        p = np.asarray(x, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (n, 3), got {p.shape}")
        return self.scale * p @ self.rotation.T + self.translation

    def __repr__(self) -> str:
        angle = float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1.0) / 2.0, -1.0, 1.0))))
        return (f"Registration(scale={self.scale:.6g}, rotation={angle:.3g} deg, "
                f"translation={np.array2string(self.translation, precision=4)}, rms={self.rms:.4g}, "
                f"n_pairs={self.n_pairs})")

    def inverse(self) -> "Registration":
        """The inverse transform ``y ↦ (1/scale) Rᵀ (y − t)`` (rms expressed in the source's units)."""
        rt = self.rotation.T
        return Registration(1.0 / self.scale, rt, -(rt @ self.translation) / self.scale, self.rms / self.scale, self.n_pairs)


def fit_similarity(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None, *, with_scale: bool = True) -> Registration:
    """Weighted least-squares similarity transform taking ``source`` onto ``target`` (Umeyama 1991).

    Minimizes ``Σ w_i |s · R p_i + t − q_i|²`` over rotations R (det +1, no reflections), scales s > 0
    (fixed to 1 when ``with_scale`` is false) and translations t, in closed form from the SVD of the
    weighted cross-covariance.

    Parameters
    ----------
    source, target : (n, 3) float64, corresponding points p_i and q_i
    weights : (n,) non-negative, default uniform

    Raises
    ------
    ValueError : mismatched shapes, negative or all-zero weights, fewer than 3 points, or points that are
        (numerically) collinear, for which the rotation is not determined.
    """
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or q.shape != p.shape:
        raise ValueError(f"source and target must both have shape (n, 3), got {p.shape} and {q.shape}")
    n = len(p)
    if n < 3:
        raise ValueError(f"a similarity transform needs at least 3 point pairs, got {n}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be finite, non-negative and not all zero (sum {w.sum()!r}, min {w.min()!r})")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("source and target must be finite")
    w = w / w.sum()
    mp = w @ p
    mq = w @ q
    pc = p - mp
    qc = q - mq
    cov = (qc * w[:, None]).T @ pc  # Σ w q p^T, (3, 3)
    u, d, vt = np.linalg.svd(cov)
    var_p = float(w @ np.einsum("ij,ij->i", pc, pc))
    if var_p <= 0 or d[1] <= 1e-12 * max(d[0], np.finfo(float).tiny):
        raise ValueError(
            f"the source points are (numerically) collinear or coincident (singular values {d.tolist()}); "
            "a rotation is not determined"
        )
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float((d * sign).sum() / var_p) if with_scale else 1.0
    if scale <= 0:
        raise ValueError(f"the best similarity has a non-positive scale ({scale}); the pairs are inconsistent")
    trans = mq - scale * rot @ mp
    res = scale * p @ rot.T + trans - q
    rms = float(np.sqrt(w @ np.einsum("ij,ij->i", res, res)))
    return Registration(scale, rot, trans, rms, n)

