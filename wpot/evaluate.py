"""Evaluation of the paper's experiments (§4): classification from a distance matrix, and geodesic errors of
correspondences.

Classification (Tables 1-4)
    * `one_shot_1nn`: pick one random training shape per class, classify every other shape by its nearest
      training shape, repeat ``n_trials`` times (Table 1: 10,000 trials, mean accuracy).
    * `leave_one_out_1nn` / `leave_one_out_levels`: each shape takes the label of its nearest other shape, at
      every label level of a CSV (Tables 2-4: genera, families, superfamilies).
    * `classification_draws`: both of the above on many random subsets of a fixed size per class drawn from a
      larger set's matrix (TOSCA8: six per class, and the paper does not say which six).
    The distance from query ``i`` to shape ``j`` is ``distances[i, j]`` (row = query). Ties at the smallest
    distance are split: a query whose nearest shapes tie earns the fraction of them that carry its label,
    which is the expected score under a random tie-break (never a hidden bias toward low indices).

Correspondence (Table 5, Fig. 6)
    For a predicted correspondent ``y_k`` and the true one ``z_k`` on the target shape Y, the geodesic error is
    ``d_Y(y_k, z_k)``, computed by the heat method (potpourri3d; Crane et al. 2013) from the true points only
    (`GeodesicDistances` caches one distance row per source vertex). It is normalized either by
    ``sqrt(area(Y))`` (the paper's Eq. in §4.1.3, "sqrt_area"), by the geodesic diameter of Y ("diameter",
    estimated by farthest-point sweeps, a property of Y alone), or as in the official SHREC'19 evaluation code
    ("shrec19": the largest distance between a true and a predicted point of the pair). The cumulative curve
    is the fraction of points with error <= t; its AUC is the mean of the curve over ``[0, max_threshold]``,
    computed exactly as ``mean(max(0, 1 - e / max_threshold))``.
    `symmetric_flip` counts the points whose prediction lands on the left/right mirror of the truth (TOSCA
    ``.sym.vts``), the typical failure of intrinsic methods on symmetric shapes.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from wpot.mesh import Mesh

__all__ = [
    "OneShotClassification",
    "format_percent",
    "LeaveOneOut",
    "one_shot_1nn",
    "leave_one_out_1nn",
    "leave_one_out_levels",
    "ClassificationDraws",
    "classification_draws",
    "PartRetrieval",
    "part_retrieval",
    "GeodesicDistances",
    "CorrespondenceError",
    "CorrespondenceSummary",
    "NORMALIZATIONS",
    "DEFAULT_MAX_THRESHOLD",
    "correspondence_error",
    "cumulative_curve",
    "curve_auc",
    "summarize_correspondence",
    "SymmetricFlip",
    "symmetric_flip",
    "DEFAULT_FLIP_SEPARATION",
    "DEFAULT_FLIP_RATIO",
]


# ============================================================================ classification
def _check_distances(distances: ArrayLike, labels: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] != d.shape[1]:
        raise ValueError(f"distances must be a square (n, n) matrix, got shape {d.shape}")
    lab = np.asarray(labels)
    if lab.shape != (d.shape[0],):
        raise ValueError(f"labels must have shape ({d.shape[0]},) to match distances, got {lab.shape}")
    bad = ~np.isfinite(d)
    np.fill_diagonal(bad, False)  # the diagonal is never used
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"distances has {int(bad.sum())} NaN or infinite off-diagonal entries (first: [{i}, {j}] = {d[i, j]}); "
            "finish or drop the missing pairs before classifying"
        )
    classes, code = np.unique(lab, return_inverse=True)
    return d, lab, classes, code.astype(np.int64)


def _tie_shares(dq: np.ndarray) -> np.ndarray:
    """For distances ``dq`` (..., K) to K candidates: each candidate's share (..., K) of the vote, 1/m for each
    of the m candidates tied at the smallest distance, 0 for the others."""
    tie = dq == dq.min(axis=-1, keepdims=True)
    return tie / tie.sum(-1, keepdims=True)


def _tie_credit(dq: np.ndarray, correct: np.ndarray) -> np.ndarray:
    """Score of each query given its distances ``dq`` (..., K) to K candidates and ``correct`` (..., K) bool:
    the fraction of the nearest (tied) candidates that are correct."""
    return (_tie_shares(dq) * correct).sum(-1)


def format_percent(fraction: float, decimals: int = 1) -> str:
    """``fraction`` as a percentage with ``decimals`` decimals, or with as many more as it takes (up to 4) for
    a value short of 100 % (or above 0 %) not to print as 100 % (or 0 %): 0.9998 gives "99.98%", and anything
    closer still gives "99.9999%" (or "0.0001%"). Accuracies reported to users go through this."""
    if decimals < 0:
        raise ValueError(f"decimals must be >= 0, got {decimals}")
    v = 100 * float(fraction)
    for dec in range(decimals, max(decimals, 4) + 1):
        text = f"{v:.{dec}f}"
        if not (0 < fraction < 1) or float(text) not in (0.0, 100.0):
            return text + "%"
    return ("99.9999" if fraction > 0.5 else "0.0001") + "%"


@dataclass(frozen=True)
class OneShotClassification:
    """1-NN with one random training shape per class (paper Table 1).

    ``accuracies`` ((n_trials,) float64) holds, per trial, the fraction of the test shapes (all shapes but the
    C training ones) classified correctly; ``mean`` and ``std`` summarize it (``std`` is the spread over
    trials, not the error of the mean, which is ``std / sqrt(n_trials)``).

    ``confusion`` ((C, C) float64, rows and columns in the order of ``classes``): ``confusion[a, b]`` is the
    fraction of the test queries of class ``a``, over all trials, that were given class ``b`` (ties split as
    everywhere here). Each row sums to 1 (a class with a single shape is never tested: its row is NaN); its diagonal is the per-class accuracy (`class_accuracy`), and
    ``mean`` is the diagonal weighted by each class's test count ``n_a - 1``.
    """

    mean: float
    std: float
    accuracies: np.ndarray = field(repr=False)
    n_trials: int
    seed: int | None
    classes: tuple[str, ...]
    confusion: np.ndarray = field(repr=False)

    @property
    def standard_error(self) -> float:
        return self.std / np.sqrt(self.n_trials)

    @property
    def class_accuracy(self) -> dict[str, float]:
        """One-shot accuracy of each class's test queries (the diagonal of ``confusion``)."""
        return {c: float(self.confusion[k, k]) for k, c in enumerate(self.classes)}


def one_shot_1nn(
    distances: ArrayLike,
    labels: ArrayLike,
    *,
    n_trials: int = 10_000,
    seed: int | None = 0,
    chunk: int = 512,
) -> OneShotClassification:
    """1-NN classification with one random training shape per class, repeated ``n_trials`` times (Table 1).

    Parameters
    ----------
    distances : (n, n) float64; ``distances[i, j]`` is the distance from query ``i`` to training shape ``j``.
    labels : (n,) class labels.
    n_trials : number of random training sets.
    seed : seed of `numpy.random.default_rng` (None: fresh entropy).
    chunk : trials evaluated together (memory ~ n * chunk * C floats).
    """
    d, _, classes, code = _check_distances(distances, labels)
    n, c = len(d), len(classes)
    if n_trials < 1:
        raise ValueError(f"n_trials must be >= 1, got {n_trials}")
    if c < 2:
        raise ValueError(f"classification needs at least 2 classes, got {c}: {classes.tolist()}")
    if n == c:
        raise ValueError(f"every class has a single shape ({n} shapes, {c} classes): no shape is left to test")
    rng = np.random.default_rng(seed)
    members = [np.nonzero(code == k)[0] for k in range(c)]
    # (n_trials, C): the training shape of each class in each trial
    train = np.stack([m[rng.integers(0, len(m), size=n_trials)] for m in members], axis=1)
    onehot = code[:, None] == np.arange(c)[None, :]  # (n, C)
    acc = np.empty(n_trials)
    votes = np.zeros((n, c))  # per query: summed share of each predicted class over the trials it was tested in
    for s in range(0, n_trials, chunk):
        tr = train[s : s + chunk]  # (t, C)
        t = len(tr)
        share = _tie_shares(d[:, tr])  # (n, t, C): the share of each class among the nearest training shapes
        is_test = np.ones((t, n), dtype=bool)
        is_test[np.arange(t)[:, None], tr] = False
        share *= is_test.T[:, :, None]
        acc[s : s + t] = (share * onehot[:, None, :]).sum((0, 2)) / (n - c)
        votes += share.sum(1)
    tested = n_trials * (np.bincount(code, minlength=c) - 1)  # a class of one shape is never tested: NaN row
    with np.errstate(invalid="ignore", divide="ignore"):
        confusion = (onehot.T.astype(np.float64) @ votes) / tested[:, None]
    return OneShotClassification(float(acc.mean()), float(acc.std()), acc, n_trials, seed, tuple(classes.tolist()), confusion)


@dataclass(frozen=True)
class LeaveOneOut:
    """Leave-one-out 1-NN classification (paper Tables 2-4).

    ``score`` ((n,) float64) is 1 when a shape's nearest other shape has its label, 0 when not, and the
    fraction of correct ones when several nearest shapes tie; ``nearest`` ((n,) int64) is the first nearest
    shape; ``accuracy`` is the mean score.
    """

    accuracy: float
    score: np.ndarray = field(repr=False)
    nearest: np.ndarray = field(repr=False)
    n_groups: int

    @property
    def n_correct(self) -> float:
        return float(self.score.sum())


def leave_one_out_1nn(distances: ArrayLike, labels: ArrayLike) -> LeaveOneOut:
    """Each shape takes the label of its nearest other shape (``distances[i, j]``, j != i)."""
    d, _, classes, code = _check_distances(distances, labels)
    if len(d) < 2:
        raise ValueError(f"leave-one-out needs at least 2 shapes, got {len(d)}")
    d = d.copy()
    np.fill_diagonal(d, np.inf)
    score = _tie_credit(d, code[:, None] == code[None, :])
    return LeaveOneOut(float(score.mean()), score, np.argmin(d, axis=1), len(classes))


def leave_one_out_levels(distances: ArrayLike, levels: Mapping[str, ArrayLike]) -> dict[str, LeaveOneOut]:
    """`leave_one_out_1nn` at every label level (e.g. ``{"genus": ..., "family": ...}`` from a label CSV)."""
    if not levels:
        raise ValueError("levels is empty: give at least one label level")
    return {name: leave_one_out_1nn(distances, lab) for name, lab in levels.items()}


@dataclass(frozen=True)
class ClassificationDraws:
    """One-shot and leave-one-out 1-NN accuracies on random subsets of ``per_class`` shapes per class.

    ``one_shot[k]`` (mean over that draw's one-shot trials) and ``leave_one_out[k]`` are the accuracies of draw
    ``k``, whose shapes are ``draws[k]`` ((C * per_class,) int64 indices into the full matrix, class by class
    in the order of ``classes``). ``*_mean`` / ``*_std`` summarize them over draws (the spread that the
    choice of shapes causes, not an error of the mean).
    """

    one_shot: np.ndarray = field(repr=False)
    leave_one_out: np.ndarray = field(repr=False)
    draws: np.ndarray = field(repr=False)
    per_class: int
    n_trials: int
    seed: int | None
    classes: tuple[str, ...]

    @property
    def n_draws(self) -> int:
        return len(self.draws)

    @property
    def one_shot_mean(self) -> float:
        return float(self.one_shot.mean())

    @property
    def one_shot_std(self) -> float:
        return float(self.one_shot.std())

    @property
    def leave_one_out_mean(self) -> float:
        return float(self.leave_one_out.mean())

    @property
    def leave_one_out_std(self) -> float:
        return float(self.leave_one_out.std())


def classification_draws(
    distances: ArrayLike,
    labels: ArrayLike,
    *,
    per_class: int,
    n_draws: int = 200,
    seed: int | None = 0,
    n_trials: int = 1000,
) -> ClassificationDraws:
    """`one_shot_1nn` and `leave_one_out_1nn` on ``n_draws`` random subsets of ``per_class`` shapes per class.

    A benchmark defined as "k shapes of each class" without saying which (TOSCA8) can be scored over the
    choices instead of on one of them: each draw takes ``per_class`` shapes of every class uniformly without
    replacement from ``distances`` (the matrix of all shapes, row = query) and scores the sub-matrix of those
    shapes alone. A class with exactly ``per_class`` shapes is in every draw whole; one with fewer is an error.

    Parameters
    ----------
    distances : (n, n) float64 over the full set; labels : (n,) its classes.
    per_class : shapes drawn per class (>= 2, so that leave-one-out has a same-class neighbour to find).
    n_draws : number of random subsets. seed : `numpy.random.default_rng` seed for the draws and, through it,
        for each draw's one-shot trials (None: fresh entropy).
    n_trials : one-shot trials per draw.
    """
    d, _, classes, code = _check_distances(distances, labels)
    if per_class < 2:
        raise ValueError(f"per_class must be >= 2, got {per_class}")
    if n_draws < 1:
        raise ValueError(f"n_draws must be >= 1, got {n_draws}")
    members = [np.nonzero(code == k)[0] for k in range(len(classes))]
    short = {str(c): len(m) for c, m in zip(classes, members) if len(m) < per_class}
    if short:
        raise ValueError(f"these classes have fewer than per_class={per_class} shapes: {short}")
    rng = np.random.default_rng(seed)
    draws = np.empty((n_draws, len(classes) * per_class), dtype=np.int64)
    one_shot = np.empty(n_draws)
    loo = np.empty(n_draws)
    for k in range(n_draws):
        idx = np.concatenate([np.sort(rng.choice(m, per_class, replace=False)) for m in members])
        draws[k] = idx
        sub, lab = d[np.ix_(idx, idx)], code[idx]
        one_shot[k] = one_shot_1nn(sub, lab, n_trials=n_trials, seed=int(rng.integers(2**63))).mean
        loo[k] = leave_one_out_1nn(sub, lab).accuracy
    return ClassificationDraws(one_shot, loo, draws, per_class, n_trials, seed, tuple(classes.tolist()))


@dataclass(frozen=True)
class PartRetrieval:
    """Which full shape each part (e.g. a HEAD head) is nearest to (paper §4.2).

    ``nearest[part]`` is the name of the nearest full shape (``distances[part, full]``, first one on ties);
    ``class_accuracy`` the fraction of parts whose nearest full shape has the parent's class, and
    ``parent_accuracy`` the fraction whose nearest full shape is the very shape they were cut from.
    """

    nearest: dict[str, str]
    class_accuracy: float
    parent_accuracy: float


def part_retrieval(
    distances: ArrayLike, names: Sequence[str], labels: ArrayLike, parent: Mapping[str, str]
) -> PartRetrieval:
    """Nearest full shape of every part.

    Parameters
    ----------
    distances : (n, n) over all shapes (parts and full shapes), row = query.
    names : (n,) shape names; labels : (n,) their classes (a part is compared through its parent's class).
    parent : part name -> name of the full shape it was cut from; the full shapes are the names that are not
        parts.
    """
    names = list(names)
    d, lab, _, _ = _check_distances(distances, labels)
    if len(names) != len(d):
        raise ValueError(f"names must have {len(d)} entries to match distances, got {len(names)}")
    pos = {n: k for k, n in enumerate(names)}
    missing = [f"{p}->{f}" for p, f in parent.items() if p not in pos or f not in pos]
    if missing or not parent:
        raise ValueError(f"parent must map parts to full shapes that are all in names; not found: {missing[:5]}")
    full = np.array([k for k, n in enumerate(names) if n not in parent])
    if full.size == 0:
        raise ValueError("every shape is a part: there is no full shape to retrieve")
    nearest, ok_class, ok_parent = {}, [], []
    for part, par in parent.items():
        i = pos[part]
        j = int(full[np.argmin(d[i, full])])
        nearest[part] = names[j]
        ok_class.append(lab[j] == lab[pos[par]])
        ok_parent.append(j == pos[par])
    return PartRetrieval(nearest, float(np.mean(ok_class)), float(np.mean(ok_parent)))


# ============================================================================ geodesics
class GeodesicDistances:
    """Geodesic distances on one mesh by the heat method (potpourri3d), cached per source vertex.

    The heat-method solver is factored once; every requested source vertex costs one solve (with the
    stored factors, no new factorization) and one stored (N,) float32 row, so evaluating many maps onto the same target shape
    reuses the rows of its ground-truth points. Distances between different connected components are
    undefined for the heat method; they are reported as ``inf`` by `from_sources`.

    Parameters
    ----------
    mesh : the surface (Y).
    t_coef : heat-method time step as a multiple of the squared mean edge length (potpourri3d's default 1.0;
        smaller is sharper but less smooth).
    """

    def __init__(self, mesh: Mesh, *, t_coef: float = 1.0) -> None:
        import potpourri3d as pp3d

        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
        if not t_coef > 0:
            raise ValueError(f"t_coef must be positive, got {t_coef}")
        self.mesh = mesh
        self.t_coef = float(t_coef)
        self._solver = pp3d.MeshHeatMethodDistanceSolver(mesh.vertices, mesh.faces, t_coef=self.t_coef)
        self._rows: dict[int, np.ndarray] = {}
        self._labels = mesh.component_labels
        self._multi = mesh.n_components > 1
        self._diameter: float | None = None

    def _row(self, s: int) -> np.ndarray:
        r = self._rows.get(s)
        if r is None:
            r = np.asarray(self._solver.compute_distance(int(s)), dtype=np.float32)
            if self._multi:
                r = np.where(self._labels == self._labels[s], r, np.float32(np.inf))
            r.setflags(write=False)
            self._rows[s] = r
        return r

    def from_sources(self, sources: ArrayLike) -> np.ndarray:
        """(S, N) float32 distances from each source vertex to every vertex."""
        src = self._check(sources, "sources")
        if src.size == 0:
            return np.empty((0, self.mesh.n_vertices), dtype=np.float32)
        return np.stack([self._row(int(s)) for s in src])

    def pairwise(self, sources: ArrayLike, targets: ArrayLike) -> np.ndarray:
        """(K,) float64 distances ``d(sources[k], targets[k])``, computed from the unique sources only."""
        s = self._check(sources, "sources")
        t = self._check(targets, "targets")
        if s.shape != t.shape:
            raise ValueError(f"sources and targets must have the same shape, got {s.shape} and {t.shape}")
        uniq, inv = np.unique(s, return_inverse=True)
        rows = self.from_sources(uniq)
        return rows[inv, t].astype(np.float64)

    def diameter(self, *, n_sweeps: int = 4) -> float:
        """Estimated geodesic diameter: repeated farthest-point sweeps, starting from the vertex farthest from
        the centroid; the largest distance found (a lower bound, exact on a sphere or a convex planar patch).
        Over all components when there are several."""
        if self._diameter is None:
            v = self.mesh.vertices
            best = 0.0
            for comp in np.unique(self._labels[self.mesh.referenced]):
                idx = np.nonzero(self._labels == comp)[0]
                s = int(idx[np.argmax(np.linalg.norm(v[idx] - v[idx].mean(0), axis=1))])
                for _ in range(n_sweeps):
                    r = self._row(s)
                    far = int(idx[np.argmax(r[idx])])
                    best = max(best, float(r[far]))
                    if far == s:
                        break
                    s = far
            self._diameter = best
        return self._diameter

    def _check(self, idx: ArrayLike, what: str) -> np.ndarray:
        a = np.asarray(idx)
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{what} must be integer vertex indices, got dtype {a.dtype}")
        a = a.astype(np.int64).ravel()
        n = self.mesh.n_vertices
        if a.size and (a.min() < 0 or a.max() >= n):
            bad = a[(a < 0) | (a >= n)]
            raise ValueError(f"{what} holds vertex indices outside [0, {n - 1}]: {bad[:10].tolist()}")
        return a


# ============================================================================ correspondence errors
NORMALIZATIONS = ("sqrt_area", "diameter", "shrec19")
#: threshold range of the cumulative curve and its AUC, per normalization (SHREC'19 plots 0..0.5 of the
#: diameter; errors normalized by sqrt(area) are about 1.5-2x larger, 0..0.25 is the range customarily shown)
DEFAULT_MAX_THRESHOLD = {"sqrt_area": 0.25, "diameter": 0.5, "shrec19": 0.5}


def cumulative_curve(errors: ArrayLike, thresholds: ArrayLike) -> np.ndarray:
    """(T,) fraction of ``errors`` that are <= each threshold."""
    e = np.sort(np.asarray(errors, dtype=np.float64).ravel())
    if e.size == 0:
        raise ValueError("errors is empty")
    return np.searchsorted(e, np.asarray(thresholds, dtype=np.float64), side="right") / e.size


def curve_auc(errors: ArrayLike, max_threshold: float) -> float:
    """Mean of the cumulative error curve over ``[0, max_threshold]``: the exact integral
    ``(1/T) int_0^T P(e <= t) dt = mean(max(0, 1 - e/T))`` (1 for a perfect map, 0 when every error >= T)."""
    if not max_threshold > 0:
        raise ValueError(f"max_threshold must be positive, got {max_threshold}")
    e = np.asarray(errors, dtype=np.float64).ravel()
    if e.size == 0:
        raise ValueError("errors is empty")
    return float(np.mean(np.clip(1.0 - e / max_threshold, 0.0, 1.0)))


@dataclass(frozen=True)
class CorrespondenceError:
    """Normalized geodesic errors of one predicted correspondence against the ground truth.

    ``errors`` ((K,) float64) = ``raw[k] / scale`` with ``raw[k] = d_Y(predicted[k], truth[k])``;
    ``curve`` ((T,) float64) is `cumulative_curve` at ``thresholds`` (0 .. ``max_threshold``), and ``auc`` its
    mean over that range (`curve_auc`). When a symmetric ground truth was given, ``flip_aware_errors`` is the
    per-point smaller of the errors against the truth and against its left/right mirror, with its own
    ``flip_aware_auc`` (a map that is off only by the symmetry scores high there but not in ``auc``).
    ``n_cross_component`` counts points whose prediction lies on another connected component than the truth:
    their raw error is the Euclidean distance (as in the SHREC'19 code).
    """

    errors: np.ndarray = field(repr=False)
    raw: np.ndarray = field(repr=False)
    normalization: str
    scale: float
    thresholds: np.ndarray = field(repr=False)
    curve: np.ndarray = field(repr=False)
    max_threshold: float
    auc: float
    mean_error: float
    flip_aware_errors: np.ndarray | None = field(default=None, repr=False)
    flip_aware_auc: float | None = None
    n_cross_component: int = 0


def _geodesic_errors(geo: GeodesicDistances, predicted: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, int]:
    raw = geo.pairwise(truth, predicted)
    cross = ~np.isfinite(raw)
    if cross.any():
        v = geo.mesh.vertices
        raw[cross] = np.linalg.norm(v[predicted[cross]] - v[truth[cross]], axis=1)
    return raw, int(cross.sum())


def correspondence_error(
    target: Mesh | GeodesicDistances,
    predicted: ArrayLike,
    truth: ArrayLike,
    *,
    normalization: str = "sqrt_area",
    max_threshold: float | None = None,
    n_thresholds: int = 501,
    symmetric_truth: ArrayLike | None = None,
) -> CorrespondenceError:
    """Normalized geodesic error of a correspondence on the target shape Y (paper §4.1.3, Table 5, Fig. 6).

    Parameters
    ----------
    target : Y, or a `GeodesicDistances` on Y (pass the same one for every map onto Y to reuse its rows).
    predicted : (K,) int, the predicted vertex of Y for each evaluated point (for a map ``m`` from X and
        ground truth pairs ``(src, dst)``: ``m[src]``).
    truth : (K,) int, the true vertex of Y for each evaluated point (``dst``).
    normalization : "sqrt_area" (the paper: d / sqrt(area(Y))), "diameter" (d / estimated geodesic diameter of
        Y, `GeodesicDistances.diameter`), or "shrec19" (d / the largest distance between a true and a
        predicted point of this pair, what the official SHREC'19 code divides by).
    max_threshold : upper end of the curve and of the AUC range (default `DEFAULT_MAX_THRESHOLD`).
    n_thresholds : points of the curve (0 .. max_threshold; 501 as in the SHREC'19 code).
    symmetric_truth : (K,) int, optional left/right-mirrored truth (TOSCA ``.sym.vts``) for the flip-aware
        error.
    """
    geo = target if isinstance(target, GeodesicDistances) else GeodesicDistances(target)
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
    pred = geo._check(predicted, "predicted")
    true = geo._check(truth, "truth")
    if pred.shape != true.shape or pred.size == 0:
        raise ValueError(f"predicted and truth must be non-empty and of equal length, got {pred.size} and {true.size}")
    if max_threshold is None:
        max_threshold = DEFAULT_MAX_THRESHOLD[normalization]
    if not max_threshold > 0:
        raise ValueError(f"max_threshold must be positive, got {max_threshold}")
    if n_thresholds < 2:
        raise ValueError(f"n_thresholds must be >= 2, got {n_thresholds}")
    raw, n_cross = _geodesic_errors(geo, pred, true)
    if normalization == "sqrt_area":
        scale = float(np.sqrt(geo.mesh.area))
    elif normalization == "diameter":
        scale = geo.diameter()
    else:  # shrec19: max over (unique truth) x (unique predicted), finite entries
        rows = geo.from_sources(np.unique(true))[:, np.unique(pred)]
        scale = float(rows[np.isfinite(rows)].max()) if np.isfinite(rows).any() else 0.0
        if scale == 0.0:  # every prediction equals its truth at a single point: no length scale
            scale = geo.diameter()
    if not scale > 0:
        raise ValueError(f"cannot normalize: the {normalization} scale of the target is {scale}")
    err = raw / scale
    thr = np.linspace(0.0, max_threshold, n_thresholds)
    flip = flip_auc = None
    if symmetric_truth is not None:
        sym = geo._check(symmetric_truth, "symmetric_truth")
        if sym.shape != true.shape:
            raise ValueError(f"symmetric_truth must have shape {true.shape}, got {sym.shape}")
        flip = np.minimum(err, _geodesic_errors(geo, pred, sym)[0] / scale)
        flip_auc = curve_auc(flip, max_threshold)
    return CorrespondenceError(err, raw, normalization, scale, thr, cumulative_curve(err, thr), float(max_threshold),
                               curve_auc(err, max_threshold), float(err.mean()), flip, flip_auc, n_cross)


@dataclass(frozen=True)
class CorrespondenceSummary:
    """Curves of several pairs averaged with equal weight per pair (as the SHREC'19 code does).

    ``curve`` ((T,) float64) at ``thresholds``; ``auc`` = mean of the per-pair AUCs (= the AUC of the mean
    curve); ``auc_std`` their spread; ``mean_error`` the mean of per-pair mean errors.
    """

    thresholds: np.ndarray = field(repr=False)
    curve: np.ndarray = field(repr=False)
    auc: float
    auc_std: float
    mean_error: float
    n_pairs: int
    normalization: str
    max_threshold: float
    flip_aware_auc: float | None = None


def summarize_correspondence(results: Sequence[CorrespondenceError]) -> CorrespondenceSummary:
    """Average `CorrespondenceError` results of several pairs (same normalization and thresholds)."""
    if not results:
        raise ValueError("results is empty")
    r0 = results[0]
    for r in results[1:]:
        if r.normalization != r0.normalization or not np.array_equal(r.thresholds, r0.thresholds):
            raise ValueError(
                f"cannot average results with different normalizations or thresholds: {r0.normalization!r} "
                f"(max {r0.max_threshold}, {r0.thresholds.size} points) vs {r.normalization!r} "
                f"(max {r.max_threshold}, {r.thresholds.size} points)"
            )
    aucs = np.array([r.auc for r in results])
    flips = [r.flip_aware_auc for r in results]
    flip = float(np.mean(flips)) if all(f is not None for f in flips) else None
    if flip is None and any(f is not None for f in flips):
        warnings.warn("only some results carry a flip-aware AUC; the summary leaves it out", stacklevel=2)
    return CorrespondenceSummary(r0.thresholds, np.mean([r.curve for r in results], axis=0), float(aucs.mean()),
                                 float(aucs.std()), float(np.mean([r.mean_error for r in results])), len(results),
                                 r0.normalization, r0.max_threshold, flip)


# ============================================================================ symmetric flips
#: points whose truth and mirrored truth are closer than this (times sqrt(area(Y))) lie near the symmetry
#: plane, where a flip cannot be told from a correct match; they are left out of the flip fraction
DEFAULT_FLIP_SEPARATION = 0.05
#: a point is flipped when d(prediction, mirror) < DEFAULT_FLIP_RATIO * d(prediction, truth)
DEFAULT_FLIP_RATIO = 0.5


@dataclass(frozen=True)
class SymmetricFlip:
    """Points of a correspondence that are off by the target's left/right symmetry.

    With ``z_k`` the true correspondent of point k on Y, ``z'_k`` its mirror (TOSCA ``.sym.vts``) and ``y_k``
    the prediction, point k is *lateral* when ``d_Y(z_k, z'_k) >= min_separation * sqrt(area(Y))`` (near the
    symmetry plane the two coincide and nothing can be judged), and a lateral point is *flipped* when
    ``d_Y(y_k, z'_k) < ratio * d_Y(y_k, z_k)`` (clearly nearer the mirror than the truth: a random error is
    rarely that close to the mirror).

    Attributes
    ----------
    fraction : flipped / lateral points (NaN when no point is lateral).
    map_flipped : ``fraction > 0.5``: most of the map is the mirror image (a "flipped pair").
    n_lateral, n_flipped : counts.
    lateral, flipped : (K,) bool per point (``flipped`` implies ``lateral``).
    min_separation, ratio : the settings used.
    """

    fraction: float
    map_flipped: bool
    n_lateral: int
    n_flipped: int
    lateral: np.ndarray = field(repr=False)
    flipped: np.ndarray = field(repr=False)
    min_separation: float = DEFAULT_FLIP_SEPARATION
    ratio: float = DEFAULT_FLIP_RATIO


def symmetric_flip(
    target: Mesh | GeodesicDistances,
    predicted: ArrayLike,
    truth: ArrayLike,
    symmetric_truth: ArrayLike,
    *,
    min_separation: float = DEFAULT_FLIP_SEPARATION,
    ratio: float = DEFAULT_FLIP_RATIO,
) -> SymmetricFlip:
    """Which predicted correspondents are the left/right mirror of the truth (see `SymmetricFlip`).

    Parameters
    ----------
    target : Y, or a `GeodesicDistances` on Y (the rows of ``truth`` and ``symmetric_truth`` are reused, so
        pass the one `correspondence_error` used).
    predicted, truth, symmetric_truth : (K,) int vertices of Y: prediction, true correspondent and its
        mirror for each evaluated point.
    min_separation : lateral-point threshold on ``d_Y(truth, mirror) / sqrt(area(Y))`` (>= 0).
    ratio : flip threshold on ``d_Y(pred, mirror) / d_Y(pred, truth)``, in (0, 1].

    Distances between connected components are Euclidean, as in `correspondence_error`.
    """
    geo = target if isinstance(target, GeodesicDistances) else GeodesicDistances(target)
    if not (np.isfinite(min_separation) and min_separation >= 0):
        raise ValueError(f"min_separation must be a finite number >= 0, got {min_separation!r}")
    if not 0 < ratio <= 1:
        raise ValueError(f"ratio must be in (0, 1], got {ratio!r}")
    pred = geo._check(predicted, "predicted")
    true = geo._check(truth, "truth")
    sym = geo._check(symmetric_truth, "symmetric_truth")
    if pred.size == 0 or pred.shape != true.shape or sym.shape != true.shape:
        raise ValueError(
            f"predicted, truth and symmetric_truth must be non-empty and of equal length, got {pred.size}, "
            f"{true.size} and {sym.size}"
        )
    sep, _ = _geodesic_errors(geo, sym, true)  # d(truth, mirror), from the truth rows
    to_truth, _ = _geodesic_errors(geo, pred, true)
    to_mirror, _ = _geodesic_errors(geo, pred, sym)
    lateral = sep >= min_separation * np.sqrt(geo.mesh.area)
    if min_separation == 0:
        lateral &= sym != true
    flipped = lateral & (to_mirror < ratio * to_truth)
    n_lat, n_flip = int(lateral.sum()), int(flipped.sum())
    if n_lat == 0:
        warnings.warn(
            "no evaluated point is lateral (every truth lies within min_separation of its mirror): the flip "
            "fraction is NaN; check symmetric_truth or lower min_separation",
            stacklevel=2,
        )
        frac = float("nan")
    else:
        frac = n_flip / n_lat
    return SymmetricFlip(frac, bool(frac > 0.5), n_lat, n_flip, lateral, flipped, float(min_separation), float(ratio))
