"""Similarity registration of matched point pairs (paper §5.1, Fig. 1): a transform ``x ↦ s R x + t``.

* `fit_similarity` is the exact weighted least-squares fit (Umeyama 1991). Every pair pulls on it, so the
  wrong matches of a correspondence (pairs that point across the shape) shrink the scale toward the two
  centroids: on the demo (one surface, B only rigidly moved) its scale falls well short of 1 (the docs'
  Results page: Registration).
* `fit_similarity_robust` is the fit `wpot.Comparer` stores: least median of squares over minimal 3-pair
  samples, then least squares over the pairs it finds consistent (the inliers); wrong matches, up to
  about half of the pairs, do not pull on it.

* `area_scale` is the size ratio of two shapes (or of two regions), sqrt of the area ratio. Between two poses
  of one body no fitted scale is their size ratio, so for balanced transport the `wpot.Comparer` gives this
  one to `fit_similarity_robust` (``scale=``), which then fits the rotation and translation.

`Registration` is the result of both fits.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from itertools import combinations
from math import comb

import numpy as np
from scipy.stats import chi2
from numpy.typing import ArrayLike

from wpot.mesh import Mesh

__all__ = ["Registration", "area_scale", "fit_similarity", "fit_similarity_robust"]


@dataclass(frozen=True, eq=False)
class Registration:
    """A similarity transform ``x ↦ scale · R x + t`` (paper §5.1, Fig. 1).

    Attributes
    ----------
    scale : float, > 0
    rotation : (3, 3) float64, a proper rotation (det = +1)
    translation : (3,) float64
    rms : weighted root-mean-square residual ``|scale·R·p + t − q|`` over the pairs the transform was fitted
        to (for `fit_similarity_robust`: over its inliers), in the target's units (mesh units of B)
    n_pairs : number of point pairs given to the fit
    n_inliers : number of them the transform was fitted to (= n_pairs for the least-squares fit)
    inliers : (n_pairs,) bool, which pairs those are, in the order given (None: all of them)
    method : ``"least-squares"`` (`fit_similarity`) or ``"robust"`` (`fit_similarity_robust`)
    scale_from : ``"fit"`` (the scale was fitted to the pairs) or ``"given"`` (it was given, e.g. `area_scale`'s
        size ratio, and only the rotation and translation were fitted)
    target_edge_length, target_diagonal : the mean edge length and bounding-box diagonal of the target mesh
        (B, when `wpot.Comparer` fitted it; None when fitted to bare points), which `rms_text` quotes the rms
        against, so that a residual can be read without knowing the mesh's units
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    rms: float
    n_pairs: int
    n_inliers: int | None = None
    inliers: np.ndarray | None = None
    method: str = "least-squares"
    scale_from: str = "fit"
    target_edge_length: float | None = None
    target_diagonal: float | None = None

    def __post_init__(self) -> None:
        if self.n_inliers is None:
            object.__setattr__(self, "n_inliers", int(self.n_pairs))

    @property
    def inlier_fraction(self) -> float:
        """n_inliers / n_pairs."""
        return self.n_inliers / self.n_pairs if self.n_pairs else float("nan")

    @property
    def rotation_degrees(self) -> float:
        """The angle of the rotation, in degrees."""
        return float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1.0) / 2.0, -1.0, 1.0))))

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

    def with_target(self, mesh: Mesh) -> "Registration":
        """This registration with ``mesh``'s mean edge length and bounding-box diagonal recorded (the target's:
        the rms is in its units), for `rms_text`."""
        return dataclasses.replace(self, target_edge_length=float(mesh.mean_edge_length),
                                   target_diagonal=float(mesh.bounding_box_diagonal))

    def rms_text(self) -> str:
        """The rms with its unit and, when the target's sizes are known, relative to them, e.g.
        ``"0.73 (mesh units; 0.9 mean edge lengths of B; 0.3 % of B's bounding-box diagonal)"``."""
        parts = ["mesh units"]
        if self.target_edge_length:
            parts.append(f"{self.rms / self.target_edge_length:.2g} mean edge lengths of B")
        if self.target_diagonal:
            parts.append(f"{100 * self.rms / self.target_diagonal:.2g} % of B's bounding-box diagonal")
        return f"{self.rms:.4g} ({'; '.join(parts)})"

    def __repr__(self) -> str:
        fitted = f"n_pairs={self.n_pairs}" if self.n_inliers == self.n_pairs else \
            f"n_inliers={self.n_inliers} of n_pairs={self.n_pairs}"
        return (f"Registration(scale={self.scale:.6g}, rotation={self.rotation_degrees:.3g} deg, "
                f"translation={np.array2string(self.translation, precision=4)}, rms={self.rms:.4g}, {fitted})")

    def inverse(self) -> "Registration":
        """The inverse transform ``y ↦ (1/scale) Rᵀ (y − t)`` (rms expressed in the source's units, whose sizes
        are not known here: the target's are dropped)."""
        rt = self.rotation.T
        return dataclasses.replace(self, scale=1.0 / self.scale, rotation=rt,
                                   translation=-(rt @ self.translation) / self.scale, rms=self.rms / self.scale,
                                   target_edge_length=None, target_diagonal=None)


def _validated(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    return p, q, w


#: a point set whose spread is below this fraction of its coordinates' size coincides (numerically), and one whose
#: second principal spread is below this fraction of its first lies on a line: neither determines a rotation
_RANK_TOL = 1e-9


def _undetermined(name: str, x: np.ndarray, w: np.ndarray) -> str | None:
    """Why the points ``x`` (n, 3) with weights ``w`` (n,), summing to 1, cannot determine a rotation (they
    coincide or lie on a line, up to rounding), or None when they can. ``name`` names them in the reason."""
    spread = np.linalg.svd((x - w @ x) * np.sqrt(w)[:, None], compute_uv=False)
    if spread[0] <= _RANK_TOL * max(float(np.abs(x).max()), np.finfo(float).tiny):
        return f"the {name} points coincide (numerically)"
    if spread[1] <= _RANK_TOL * spread[0]:
        return f"the {name} points are (numerically) collinear"
    return None


def _umeyama(p: np.ndarray, q: np.ndarray, w: np.ndarray, with_scale: bool
             ) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted least-squares (scale, rotation, translation) for validated p, q (n, 3) and w (n,) ≥ 0. Raises
    ValueError, naming the point set, when the source or the target points coincide or lie on a line: the
    cross-covariance of a target collapsed to one point is rounding noise, whose SVD would give an arbitrary
    rotation."""
    w = w / w.sum()
    for name, x in (("source", p), ("target", q)):
        if (why := _undetermined(name, x, w)) is not None:
            raise ValueError(f"{why}; a rotation is not determined")
    mp = w @ p
    mq = w @ q
    pc = p - mp
    qc = q - mq
    cov = (qc * w[:, None]).T @ pc  # Σ w q p^T, (3, 3)
    u, d, vt = np.linalg.svd(cov)
    var_p = float(w @ np.einsum("ij,ij->i", pc, pc))
    if d[1] <= 1e-12 * max(d[0], np.finfo(float).tiny):
        raise ValueError(f"the pairs do not determine a rotation (the cross-covariance's singular values are "
                         f"{d.tolist()}: the source and target spreads are at right angles)")
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float((d * sign).sum() / var_p) if with_scale else 1.0
    if scale <= 0:
        raise ValueError(f"the best similarity has a non-positive scale ({scale}); the pairs are inconsistent")
    return scale, rot, mq - scale * rot @ mp


def _sq_residuals(p: np.ndarray, q: np.ndarray, scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    res = scale * p @ rot.T + trans - q
    return np.einsum("ij,ij->i", res, res)


def fit_similarity(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None, *, with_scale: bool = True) -> Registration:
    """Weighted least-squares similarity transform taking ``source`` onto ``target`` (Umeyama 1991).

    Minimizes ``Σ w_i |s · R p_i + t − q_i|²`` over rotations R (det +1, no reflections), scales s > 0
    (fixed to 1 when ``with_scale`` is false) and translations t, in closed form from the SVD of the
    weighted cross-covariance. Every pair pulls on it: see `fit_similarity_robust` for pairs that include
    wrong matches.

    Parameters
    ----------
    source, target : (n, 3) float64, corresponding points p_i and q_i
    weights : (n,) non-negative, default uniform

    Raises
    ------
    ValueError : mismatched shapes, negative or all-zero weights, fewer than 3 points, or source or target points
        that (numerically) coincide or lie on a line, for which the rotation is not determined (the message
        names which).
    """
    p, q, w = _validated(source, target, weights)
    scale, rot, trans = _umeyama(p, q, w, with_scale)
    rms = float(np.sqrt((w / w.sum()) @ _sq_residuals(p, q, scale, rot, trans)))
    return Registration(scale, rot, trans, rms, len(p))


def _triples(candidates: np.ndarray, prob: np.ndarray, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(S, 3) int: every triple of ``candidates`` when there are at most ``n_samples`` of them, else
    ``n_samples`` random ones (each pair drawn with probability ``prob``), repeats within a triple dropped."""
    m = len(candidates)
    if comb(m, 3) <= n_samples:
        return candidates[np.array(list(combinations(range(m), 3)), dtype=np.int64).reshape(-1, 3)]
    idx = rng.choice(m, size=(n_samples, 3), p=prob)
    idx = idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])]
    return candidates[idx]


def _minimal_fits(p3: np.ndarray, q3: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Umeyama fits of S triples at once: p3, q3 (S, 3, 3) (triple, point, coordinate) → scale (S,), rotation
    (S, 3, 3), translation (S, 3) and a (S,) bool mask of the triples whose fit is determined (not collinear,
    positive scale)."""
    mp, mq = p3.mean(1), q3.mean(1)
    pc, qc = p3 - mp[:, None], q3 - mq[:, None]
    cov = np.einsum("sni,snj->sij", qc, pc) / 3.0
    u, d, vt = np.linalg.svd(cov)
    var_p = np.einsum("sni,sni->s", pc, pc) / 3.0
    sign = np.ones((len(p3), 3))
    sign[np.linalg.det(u) * np.linalg.det(vt) < 0, 2] = -1.0
    rot = (u * sign[:, None, :]) @ vt
    size_q = np.abs(q3).max(axis=(1, 2))
    var_q = np.einsum("sni,sni->s", qc, qc) / 3.0  # a target triple at one point: noise, not a rotation
    ok = (var_p > 0) & (d[:, 1] > 1e-9 * np.maximum(d[:, 0], np.finfo(float).tiny))
    ok &= np.sqrt(var_q) > _RANK_TOL * np.maximum(size_q, np.finfo(float).tiny)
    scale = np.where(ok, (d * sign).sum(1) / np.where(var_p > 0, var_p, 1.0), 0.0) if with_scale else np.ones(len(p3))
    ok &= scale > 0
    trans = mq - scale[:, None] * np.einsum("sij,sj->si", rot, mp)
    return scale, rot, trans, ok


#: hypotheses scored per block (a block holds block x n squared residuals)
_BLOCK = 64


def area_scale(mesh_a: Mesh, mesh_b: Mesh, mask_a: ArrayLike | None = None, mask_b: ArrayLike | None = None) -> float:
    """The size ratio of B to A, sqrt(area of B's region / area of A's region), the regions given as (N,) bool
    vertex masks (None: the whole mesh; a vertex stands for its `Mesh.vertex_areas`).

    Between two poses of one body the scale of a similarity fitted to corresponding points is not their size
    ratio: a least-squares fit shrinks with the pose change (even on same-size TOSCA pairs fitted to their true
    correspondence), a fit of the points' spread (Horn's symmetric scale) follows it, while sqrt(area ratio)
    stays close to 1 there (the docs' Results page: Registration). Raises ValueError when a region has no area."""
    out = []
    for name, mesh, mask in (("A", mesh_a, mask_a), ("B", mesh_b, mask_b)):
        va = mesh.vertex_areas
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (mesh.n_vertices,):
                raise ValueError(f"mask_{name.lower()} must be an ({mesh.n_vertices},) bool mask, "
                                 f"got shape {mask.shape}")
            va = va[mask]
        area = float(va.sum())
        if not area > 0:
            raise ValueError(f"the region of {name} has no area")
        out.append(area)
    return float(np.sqrt(out[1] / out[0]))


def fit_similarity_robust(
    source: ArrayLike,
    target: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    with_scale: bool = True,
    scale: float | None = None,
    n_samples: int = 500,
    seed: int = 0,
    quantile: float = 0.5,
    confidence: float = 0.9,
) -> Registration:
    """Similarity transform taking ``source`` onto ``target`` that wrong pairs (up to about half) do not pull on.

    Method: least median of squares (LMedS; Rousseeuw 1984) over minimal samples, then least squares on the
    inliers, repeated until the inliers stop changing:

    1. ``n_samples`` triples of pairs (each pair drawn with probability ∝ its weight; every triple when there
       are fewer), each fitted exactly (`fit_similarity` of 3 pairs, all at once by a batched SVD);
    2. the hypothesis with the smallest median squared residual over all pairs wins (it needs no threshold,
       so no knowledge of the mesh's units or noise, and it breaks down only past 50 % wrong pairs);
    3. the noise σ (per coordinate) is estimated from that median (``|r|²/σ² ~ χ²₃``, median 2.366); pairs with
       ``|r|²`` below the χ²₃ quantile ``confidence`` times σ² are the inliers, and the transform is refitted to
       them by weighted least squares; step 3 repeats (σ from the new fit's median) until the inlier set is
       fixed (at most 20 times).

    ``confidence`` is 0.9 (``|r|² ≤ 6.25 σ²``), not the 0.99 that Gaussian noise would suggest: between two
    poses of a body the residuals of correct pairs have no clean Gaussian core, and wrong matches that stay
    near the surface (left/right mirrored ones) sit in their tail (`benchmarks/registration.py` compares the
    cutoffs; the docs' Results page has its figures).

    Why this and not IRLS with a Tukey or Cauchy loss: IRLS starts from the least-squares fit, which the wrong
    matches have already pulled in (its scale well below the true one on the demo and on TOSCA), and from there a redescending loss
    can settle on that wrong minimum; a minimal-sample search needs no starting point. Why the median and
    not RANSAC's inlier count: the count needs a threshold in mesh units, the median does not. The final step
    is least squares, so with exact pairs among gross outliers the transform is recovered exactly.

    Deterministic: the samples come from ``numpy.random.default_rng(seed)``, drawn from the pairs in an
    order that depends only on their distances to the weighted centroids (so relabelling the pairs or moving
    either point set rigidly gives the same samples). Cost: O(n_samples · n).

    Parameters
    ----------
    source, target : (n, 3) float64, corresponding points p_i and q_i (n ≥ 3)
    weights : (n,) non-negative, default uniform; they weight the sampling and the final fit (a pair of weight
        0 is never sampled and never fitted to, but is still classified as an inlier or not)
    with_scale : False fixes the scale to 1 (a rigid fit)
    scale : a known scale (e.g. `area_scale`'s size ratio): only the rotation and translation are fitted, to
        ``scale`` · source (``scale_from="given"``); overrides ``with_scale``
    n_samples : number of random triples (every triple when C(n, 3) is at most this)
    seed : seed of the sampling
    quantile : the order statistic of the squared residuals minimized in step 2 and giving σ in step 3 (0.5: the
        median; lower tolerates more wrong pairs, 1 − quantile of them, with a noisier σ)
    confidence : the χ²₃ probability that sets the inlier cutoff in step 3 (see above)

    Returns
    -------
    `Registration` with ``method="robust"``, ``n_inliers`` and ``inliers`` ((n,) bool), and ``rms`` the weighted
    rms residual over the inliers.

    Raises
    ------
    ValueError : as `fit_similarity` (shapes, weights, fewer than 3 pairs, collinear points), or no sampled
        triple determines a transform, or n_samples < 1, or quantile or confidence outside (0, 1).
    """
    if scale is not None:
        if isinstance(scale, bool) or not isinstance(scale, (int, float, np.floating)) or not (
                math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive finite number (or None), got {scale!r}")
        p, q, w = _validated(source, target, weights)
        rigid = fit_similarity_robust(float(scale) * p, q, w, with_scale=False, n_samples=n_samples, seed=seed,
                                      quantile=quantile, confidence=confidence)
        return dataclasses.replace(rigid, scale=float(scale), scale_from="given")
    p, q, w = _validated(source, target, weights)
    for name, v in (("quantile", quantile), ("confidence", confidence)):
        if not 0.0 < float(v) < 1.0:
            raise ValueError(f"{name} must be in (0, 1), got {v!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    wn = w / w.sum()
    fitted = _canonical_positive(p, q, w, wn)  # the median is taken over the pairs that carry weight
    k = min(len(fitted) - 1, max(0, int(np.ceil(quantile * len(fitted))) - 1))
    cur = _least_median_fit(p, q, w, fitted, k, int(n_samples), seed, with_scale)
    inl, cur = _inlier_refit(p, q, w, wn, fitted, k, cur, with_scale, float(chi2.ppf(quantile, 3)),
                             float(chi2.ppf(confidence, 3)))
    r2 = _sq_residuals(p, q, *cur)
    wi = w * inl
    rms = float(np.sqrt((wi @ r2) / wi.sum())) if wi.sum() > 0 else float("nan")
    inl = inl.copy()
    inl.setflags(write=False)
    return Registration(cur[0], cur[1], cur[2], rms, len(p), n_inliers=int(inl.sum()), inliers=inl,
                        method="robust")


def _canonical_positive(p: np.ndarray, q: np.ndarray, w: np.ndarray, wn: np.ndarray) -> np.ndarray:
    """The pairs of positive weight, in a canonical order invariant to relabelling and to rigid motions (and
    scalings) of either point set: by distance to the weighted centroids."""
    rp = np.linalg.norm(p - wn @ p, axis=1)
    rq = np.linalg.norm(q - wn @ q, axis=1)
    order = np.lexsort((w, rq / max(rq.max(), np.finfo(float).tiny), rp / max(rp.max(), np.finfo(float).tiny)))
    return order[w[order] > 0]


def _least_median_fit(p: np.ndarray, q: np.ndarray, w: np.ndarray, fitted: np.ndarray, k: int, n_samples: int,
                      seed: int, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Steps 1-2 of `fit_similarity_robust`: of the exact fits to ``n_samples`` random triples of the ``fitted``
    pairs, the one whose k-th smallest squared residual over those pairs is least: (scale, rotation (3, 3),
    translation (3,))."""
    rng = np.random.default_rng(seed)
    tri = _triples(fitted, w[fitted] / w[fitted].sum(), n_samples, rng)
    if len(tri) == 0:
        raise ValueError("no triple of distinct pairs with positive weight could be sampled")
    scale, rot, trans, ok = _minimal_fits(p[tri], q[tri], with_scale)
    if not ok.any():
        raise ValueError(
            f"none of the {len(tri)} sampled triples of pairs determines a transform: the source or target "
            "points are (numerically) collinear or coincident, or the pairs are inconsistent"
        )
    scale, rot, trans = scale[ok], rot[ok], trans[ok]
    best, best_med = -1, np.inf
    for s in range(0, len(scale), _BLOCK):
        sl = slice(s, s + _BLOCK)
        res = scale[sl, None, None] * np.einsum("sij,nj->sni", rot[sl], p[fitted]) + trans[sl, None, :] - q[fitted]
        med = np.partition(np.einsum("sni,sni->sn", res, res), k, axis=1)[:, k]
        i = int(np.argmin(med))
        if med[i] < best_med:
            best, best_med = s + i, float(med[i])
    return float(scale[best]), rot[best], trans[best]


def _inlier_refit(p: np.ndarray, q: np.ndarray, w: np.ndarray, wn: np.ndarray, fitted: np.ndarray, k: int,
                  cur: tuple, with_scale: bool, chi2_q: float, chi2_cut: float) -> tuple[np.ndarray, tuple]:
    """Step 3 of `fit_similarity_robust`: σ from the k-th smallest squared residual (``|r|²/σ² ~ χ²₃``: ``chi2_q``
    is the χ²₃ quantile of that order), the inliers below ``chi2_cut`` σ², least squares on them, until the
    inliers are fixed (at most 20 times). Returns (inliers (n,) bool, the transform)."""
    # a floor for σ, so that exact pairs (residuals of rounding size) are inliers
    size = float(np.sqrt(wn @ np.einsum("ij,ij->i", q - wn @ q, q - wn @ q)))
    floor2 = (1e-9 * max(size, np.finfo(float).tiny)) ** 2
    inl = None
    for _ in range(20):
        r2 = _sq_residuals(p, q, *cur)
        sigma2 = max(float(np.partition(r2[fitted], k)[k]) / chi2_q, floor2)
        new = r2 <= chi2_cut * sigma2
        if inl is not None and np.array_equal(new, inl):
            break
        if np.count_nonzero(new & (w > 0)) < 3:
            break
        try:
            fit = _umeyama(p[new], q[new], w[new], with_scale)
        except ValueError:
            break
        inl, cur = new, fit
    if inl is None:  # the minimal fit's own inliers were degenerate: keep that fit and its inliers
        inl = new
    return inl, cur
