"""Looking a part up in a labelled library of whole shapes: which class is the part from?

`Comparer.nearest_signature_distance` scores one whole: the mean, over the part's vertices, of the cost from
each vertex's signature to the nearest signature of the whole. Taking the class of the nearest whole fails in
one way on TOSCA (`benchmarks/part_retrieval.py`): a part cut from a pose that two other classes share (TOSCA's
three humans all have a neutral pose 0) is taken for one of them, because LD-SIFT is extrinsic and one pose of
two bodies looks more alike than two poses of one body. The vertices where the pose differs (a hand, an elbow)
then cost much more in every pose of the part's own class than in the other class's pose 0, and they decide
the mean. `rank_classes` scores a class from the same per-vertex costs in two steps that take that weight
away from them:

1. **Standardised per vertex** (``standardize``): each vertex's costs to the library's wholes become z-scores
   over the library, so that every vertex weighs the same, whether its costs spread widely (a vertex the pose
   moves) or hardly (a vertex every whole explains equally well, or none does, such as one on the part's cut).
2. **A class as the union of its nearest members** (``k_nearest``): a vertex's cost to a class is its least
   cost over the class's ``k_nearest`` members nearest to the part (by their mean), so a part whose arm is
   posed as in one pose of its class and whose hand as in another is explained by the two together. A class's
   score is the mean of these costs over the part's vertices; the smallest score ranks first. ``k_nearest``
   stays small because a class with more members would otherwise gain from its size alone, and every class is
   scored by the union of the same number of members: ``k_nearest``, or the smallest class's size when that is
   smaller (the least of three costs is lower than the least of two even when no member fits).

`ClassRanking.probability` turns the margin between the first two classes into the chance that the first is
right: a logistic shipped as `CALIBRATION` (fitted on TOSCA), or one fitted to a user's own library
(`RetrievalCalibration`: parts cut from its wholes by `calibration_parts`, each looked up among the others).

With LD-SIFT (`benchmarks/part_retrieval.py`: parts cut from TOSCA 5k poses, each against the 75 other shapes)
the two steps together rank the true class first more often than the nearest whole's class from the same costs,
on each of three part sets, and each step alone gains less (the docs' Results page: Parts looked up in a library
of whole shapes).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from wpot import _validate
from wpot.mesh import Mesh, MeshWarning, cut
from wpot.sampling import Subsample, farthest_point_sampling

__all__ = ["RetrievalWarning", "RetrievalOptions", "ClassRanking", "rank_classes", "CALIBRATION", "MARGIN_DOUBT",
           "CALIBRATED_THICKNESS", "probability_of", "retrieval_sample", "SIZE_SPREAD", "size_spread",
           "RetrievalCalibration", "fit_logistic", "calibration_of", "calibration_parts", "PART_FRACTIONS",
           "CalibrationRecord", "library_digest", "MIN_PART_VERTICES",
           "retrieval_options"]

#: (intercept, slope) of `ClassRanking.probability`, ``1 / (1 + exp(-(intercept + slope · margin)))``: a logistic
#: regression of "the first class is right" on the margin, fitted on the development parts of
#: `benchmarks/retrieval_calibration.py` (TOSCA parts cut from the library's own meshes; LD-SIFT at its defaults,
#: one edge length, the library's; the default options) and measured on its check parts (parts meshed apart, and
#: FAUST's people: the docs' Results page)
CALIBRATION = (-0.920, 24.943)
#: the LD-SIFT thickness weight `CALIBRATION` was fitted with (LD-SIFT at its other defaults): 0, without the
#: column; `Comparer.retrieve` marks a ranking made with other signatures as not calibrated
CALIBRATED_THICKNESS = 0.0
#: the values of `RetrievalOptions.edge`
EDGES = ("library", "own")
#: the fixed rule that `ClassRanking.probability` replaces: a margin below this was called doubtful
MARGIN_DOUBT = 0.12
#: `Comparer.retrieve` warns when two wholes of one class differ in size (√area) by more than this factor:
#: TOSCA's poses of a class agree within it, FAUST's 5k people (scaled one by one) do not (the docs' Results page)
SIZE_SPREAD = 1.1


#: the share of its whole's area that each part `calibration_parts` cuts takes, drawn uniformly between these
PART_FRACTIONS = (0.1, 0.6)
#: `calibration_parts` keeps parts of at least this many vertices
MIN_PART_VERTICES = 20


def probability_of(margin: float, coefficients: tuple[float, float] = CALIBRATION) -> float:
    """The calibrated probability that a ranking whose margin is ``margin`` has the right first class: the logistic
    ``1 / (1 + exp(-(intercept + slope · margin)))`` of ``coefficients`` (default the shipped `CALIBRATION`); 1
    for an infinite margin."""
    if np.isinf(margin):
        return 1.0
    return float(1.0 / (1.0 + np.exp(-(coefficients[0] + coefficients[1] * float(margin)))))


def fit_logistic(x: ArrayLike, y: ArrayLike, *, prior: tuple[float, float] = (0.0, 0.0),
                 weight: tuple[float, float] = (0.0, 1e-3), n_iter: int = 100) -> tuple[float, float]:
    """(intercept, slope) of ``P(y = 1) = 1 / (1 + exp(-(a + b x)))``: the maximum of the log-likelihood of the
    outcomes ``y`` (N,) in {0, 1} at ``x`` (N,), less ``½ Σ weight_i (coefficient_i − prior_i)²``, by Newton's
    method. The default, a small ridge on the slope, keeps the fit finite when the set is separable but not when
    every outcome is the same: then (NaN, NaN) unless the intercept has a weight, which holds it near its prior."""
    x, y = np.asarray(x, dtype=np.float64).ravel(), np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape or not len(y) or not np.isfinite(x).all():
        raise ValueError(f"x and y must be finite and of one nonzero length, got {len(x)} and {len(y)}")
    if y.min() == y.max() and weight[0] <= 0:
        return float("nan"), float("nan")
    a0, lam = np.asarray(prior, dtype=np.float64), np.diag(np.asarray(weight, dtype=np.float64))
    a = a0.copy()
    X = np.stack([np.ones_like(x), x], axis=1)
    for _ in range(n_iter):
        p = 1.0 / (1.0 + np.exp(-(X @ a)))
        step = np.linalg.solve((X * (p * (1 - p))[:, None]).T @ X + lam, X.T @ (y - p) - lam @ (a - a0))
        a = a + step
        if np.abs(step).max() < 1e-10:
            break
    return float(a[0]), float(a[1])


class RetrievalWarning(UserWarning):
    """A part that cannot be a part of any whole of the library (larger than all of them), or a library whose
    wholes of one class differ in size."""


def size_spread(wholes: Sequence[Mesh], labels: Sequence[str]) -> tuple[str, float] | None:
    """The class whose wholes differ most in size, and the ratio of its largest √area to its smallest; None when
    no class has two wholes. Signatures that see size (LD-SIFT at one edge length for the library, WKS at the
    meshes' own size) then also see whatever scaled a class's members apart."""
    by: dict[str, list[float]] = {}
    for w, label in zip(wholes, labels):
        by.setdefault(str(label), []).append(float(np.sqrt(w.area)))
    spread = [(name, max(r) / min(r)) for name, r in by.items() if len(r) > 1 and min(r) > 0]
    return max(spread, key=lambda x: x[1]) if spread else None


@dataclass(frozen=True)
class RetrievalOptions:
    """Options of `rank_classes` (the module docstring says what each does).

    k_nearest : a class's score takes each vertex's least cost over this many of its members, those nearest to
        the part by their mean cost; the smallest class's size instead when that is smaller, for every class
        alike; 1 scores a class by its nearest member alone
    standardize : turn each vertex's costs into z-scores over the library's wholes first
    max_points : a part of more vertices stands for this many of them (`retrieval_sample`: Euclidean
        farthest-point samples, each weighing its cell's vertex count), so the cost of a lookup stops growing
        with the part's size and a densely meshed part counts its area, not its vertices; None: every vertex
    edge : for LD-SIFT in `Comparer.retrieve`, when the comparer leaves its edge length unset
        (`wpot.signatures.LDSIFTOptions.edge`): ``"library"`` (default) one edge length for the part and every
        whole, the library's (`wpot.signatures._frames.common_edge`), so that a part meshed at another density
        sees the images its whole does; ``"own"``: each mesh's own, the paper's Eq. 1
    """

    k_nearest: int = 3
    standardize: bool = True
    max_points: int | None = 1500
    edge: str = "library"

    def __post_init__(self) -> None:
        _validate.integer_at_least("k_nearest", self.k_nearest, 1)
        _validate.boolean("standardize", self.standardize)
        if self.max_points is not None:
            object.__setattr__(self, "max_points", _validate.integer_at_least("max_points", self.max_points, 3))
        _validate.one_of("edge", self.edge, EDGES)


def retrieval_options(options: RetrievalOptions | None) -> RetrievalOptions:
    """``options``, or the defaults for None; TypeError naming anything else."""
    o = RetrievalOptions() if options is None else options
    if not isinstance(o, RetrievalOptions):
        raise TypeError(f"options must be a RetrievalOptions, got {type(o).__name__}")
    return o


def retrieval_sample(part: Mesh, options: RetrievalOptions | None = None) -> Subsample | None:
    """The points that stand for ``part`` in `rank_classes`: None (every vertex) up to ``options.max_points``
    vertices, else that many Euclidean farthest-point samples (`wpot.sampling.farthest_point_sampling`); pass
    their ``indices`` to pick the costs' rows and their ``counts`` as ``weights``. Deterministic for a mesh."""
    o = retrieval_options(options)
    if o.max_points is None or part.n_vertices <= o.max_points:
        return None
    return farthest_point_sampling(part, o.max_points, metric="euclidean")


@dataclass(frozen=True)
class ClassRanking:
    """The library's classes ranked for one part (`rank_classes`).

    Attributes
    ----------
    classes : (C,) the classes, best first
    scores : (C,) float64, their scores in the same order, ascending (the unit of the costs, or z-scores with
        ``standardize``)
    members : (C,) for each class in that order, the indices (into the library) of the members that scored it,
        nearest first
    whole_costs : (M,) float64, each whole's mean per-vertex cost (`Comparer.nearest_signature_distance`; a
        weighted mean with `rank_classes`'s ``weights``)
    calibrated : whether the ranking was made as `probability` was calibrated: the default options, and (when
        `Comparer.retrieve` made it) LD-SIFT at its defaults (its thickness column at `CALIBRATED_THICKNESS`, none);
        or the options and signature of the `RetrievalCalibration` given to `Comparer.retrieve`
    coefficients : (intercept, slope) of `probability`'s logistic: the shipped `CALIBRATION`, or a library's own
        (`RetrievalCalibration`)
    """

    classes: tuple[str, ...]
    scores: np.ndarray
    members: tuple[tuple[int, ...], ...]
    whole_costs: np.ndarray
    calibrated: bool = False
    coefficients: tuple[float, float] = CALIBRATION

    @property
    def label(self) -> str:
        """The best class."""
        return self.classes[0]

    @property
    def margin(self) -> float:
        """The second class's score less the first's (inf with one class): how sure the ranking is: on the
        TOSCA 5k part sets (`benchmarks/part_retrieval.py`) the misses lay among the parts with the smallest
        margins (the docs' Results page)."""
        return float(self.scores[1] - self.scores[0]) if len(self.scores) > 1 else float("inf")

    @property
    def probability(self) -> float:
        """The chance that `label` is the part's class, from the margin (`probability_of` with ``coefficients``).
        The shipped calibration was fitted on parts of TOSCA shapes looked up in a library of TOSCA's other poses
        with LD-SIFT at its defaults (`benchmarks/retrieval_calibration.py`), so it is a guide for libraries like
        that one; a library unlike it (FAUST's people as distributed, scaled one by one, where it is too sure)
        calls for its own (`Comparer.calibrate_retrieval`). NaN for a ranking made otherwise (``calibrated`` False: other options
        or signatures), whose margins are on another scale."""
        return probability_of(self.margin, self.coefficients) if self.calibrated else float("nan")

    def rank(self, label: str) -> int:
        """1-based rank of class ``label`` (1 = best)."""
        if label not in self.classes:
            raise ValueError(f"class {label!r} is not in the library; it has {sorted(self.classes)}")
        return self.classes.index(label) + 1

    def __repr__(self) -> str:
        top = ", ".join(f"{c} {s:.3g}" for c, s in zip(self.classes[:3], self.scores[:3]))
        more = ", ..." if len(self.classes) > 3 else ""
        return (f"ClassRanking({len(self.classes)} classes: {top}{more}; margin {self.margin:.3g}, probability "
                f"{self.probability:.2f})")


def rank_classes(costs: ArrayLike, labels: Sequence[str], *, weights: ArrayLike | None = None,
                 options: RetrievalOptions | None = None) -> ClassRanking:
    """Rank the classes of a library of whole shapes for one part.

    Parameters
    ----------
    costs : (N, M) for each of the part's N vertices and each of the library's M wholes, the cost from the
        vertex's signature to the nearest signature of the whole (`wpot.cost.nearest_costs`); finite
    labels : (M,) the class of each whole
    weights : (N,) nonnegative, not all zero: what each vertex weighs in the means over the part (e.g. a
        farthest-point sample's cell sizes, `retrieval_sample`); None: every vertex the same. A row of weight
        w counts as w copies of it.
    options : `RetrievalOptions` (default: standardised, ``k_nearest=3``); its ``max_points`` is for the caller
        (`retrieval_sample`): the rows given here are all used
    """
    o = retrieval_options(options)
    c = np.asarray(costs, dtype=np.float64)
    labels = [str(x) for x in labels]
    if c.ndim != 2 or c.shape[0] == 0 or c.shape[1] == 0:
        raise ValueError(f"costs must be a non-empty (n_vertices, n_wholes) array, got shape {c.shape}")
    if len(labels) != c.shape[1]:
        raise ValueError(f"labels must have one class per whole: costs has {c.shape[1]} wholes, labels "
                         f"{len(labels)}")
    if not np.isfinite(c).all():
        raise ValueError("costs must be finite")
    if len(set(labels)) < 2:
        raise ValueError(f"labels name one class ({labels[0]!r}): a ranking needs a library of at least two "
                         "classes (a part's class cannot be told from a library that holds one)")
    if weights is None:
        w = np.full(c.shape[0], 1.0 / c.shape[0])
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (c.shape[0],):
            raise ValueError(f"weights must have one entry per row of costs ({c.shape[0]}), got shape {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise ValueError("weights must be finite and nonnegative, and not all zero")
        w = w / w.sum()
    whole_costs = w @ c
    z = c
    if o.standardize:
        sd = c.std(axis=1, keepdims=True)
        z = np.divide(c - c.mean(axis=1, keepdims=True), sd, out=np.zeros_like(c), where=sd > 0)
    means = w @ z
    names = sorted(set(labels))
    lab = np.asarray(labels)
    # the same number of members for every class, so that none gains from its size alone
    k = min(o.k_nearest, min(int(np.sum(lab == name)) for name in names))
    scores, members = [], []
    for name in names:
        cols = np.flatnonzero(lab == name)
        cols = cols[np.argsort(means[cols], kind="stable")[:k]]
        scores.append(float(w @ z[:, cols].min(axis=1)))
        members.append(tuple(int(j) for j in cols))
    order = np.argsort(scores, kind="stable")
    return ClassRanking(tuple(names[i] for i in order), np.asarray(scores)[order],
                        tuple(members[i] for i in order), whole_costs, calibrated=o == RetrievalOptions())


@dataclass(frozen=True)
class RetrievalCalibration:
    """`ClassRanking.probability` fitted to one library (`Comparer.calibrate_retrieval`): parts cut from its own
    wholes (`calibration_parts`), each looked up among the other wholes, and a logistic regression of "the first
    class is right" on the ranking's margin (`fit_logistic`), held near the shipped `CALIBRATION` by a weak prior
    (`calibration_of`), so that a library on which every part is right still gets a finite fit.

    Attributes
    ----------
    intercept, slope : the logistic's coefficients (`probability_of`)
    n_parts, n_right : how many parts were looked up, and how many of them came out right
    options : the `RetrievalOptions` the parts were ranked with; `Comparer.retrieve` uses the calibration only
        with these
    signature : the signature the parts were described with (`wpot.comparison.signature_key`), likewise
    library : the library's content (`library_digest`); `Comparer.retrieve` warns when it is used with another
        library ("" leaves it unchecked)
    """

    intercept: float
    slope: float
    n_parts: int
    n_right: int
    options: RetrievalOptions
    signature: str
    library: str = ""

    def __post_init__(self) -> None:
        for name in ("intercept", "slope"):
            object.__setattr__(self, name, _validate.finite(name, getattr(self, name)))
        for name, least in (("n_parts", 1), ("n_right", 0)):
            object.__setattr__(self, name, _validate.integer_at_least(name, getattr(self, name), least))
        if self.n_right > self.n_parts:
            raise ValueError(f"n_right ({self.n_right}) cannot exceed n_parts ({self.n_parts})")
        if not isinstance(self.options, RetrievalOptions):
            raise TypeError(f"options must be a RetrievalOptions, got {type(self.options).__name__}")
        for name in ("signature", "library"):
            if not isinstance(getattr(self, name), str):
                raise TypeError(f"{name} must be a str, got {type(getattr(self, name)).__name__}")

    @property
    def coefficients(self) -> tuple[float, float]:
        """(intercept, slope)."""
        return (self.intercept, self.slope)

    def probability(self, margin: float) -> float:
        """The chance that a ranking of margin ``margin`` has the right first class."""
        return probability_of(margin, self.coefficients)

    def to_json(self) -> str:
        """The calibration as JSON text (`from_json` reads it back): keep it beside the library."""
        return json.dumps(dataclasses.asdict(self), indent=1)

    @classmethod
    def from_json(cls, text: str) -> "RetrievalCalibration":
        """Read `to_json`'s text; ValueError naming what is missing or wrong."""
        try:
            d = json.loads(text)
            d["options"] = RetrievalOptions(**d["options"])
            return cls(**d)
        except (json.JSONDecodeError, TypeError, KeyError) as e:
            raise ValueError(f"not a RetrievalCalibration's JSON: {e}") from None


def library_digest(wholes: Sequence[Mesh], labels: Sequence[str]) -> str:
    """A content key of a labelled library: SHA-1 of its (mesh `wpot.Mesh.fingerprint`, class) pairs, sorted, so
    that the order of the wholes does not count."""
    h = hashlib.sha1()
    for fingerprint, label in sorted((w.fingerprint, str(x)) for w, x in zip(wholes, labels)):
        h.update(f"{fingerprint} {label}\n".encode())
    return h.hexdigest()


def calibration_of(margins: ArrayLike, right: ArrayLike, options: RetrievalOptions | None, signature: str,
                   library: str = "") -> RetrievalCalibration:
    """The `RetrievalCalibration` of parts whose rankings had ``margins`` (N,) and came out ``right`` (N,) or not:
    `fit_logistic` held near the shipped `CALIBRATION` by a weak prior, of unit weight on the intercept and on the
    slope times the margins' root mean square (a change of one in the logit at a typical margin costs as much as
    one in the intercept)."""
    m, y = np.asarray(margins, dtype=np.float64), np.asarray(right, dtype=bool)
    if m.shape != y.shape or not len(m) or not np.isfinite(m).all():
        raise ValueError(f"margins must be finite and one per outcome, got {m.shape} and {y.shape}")
    rms2 = max(float(np.mean(m ** 2)), 1e-12)
    a, b = fit_logistic(m, y, prior=CALIBRATION, weight=(1.0, rms2))
    return RetrievalCalibration(a, b, len(m), int(y.sum()), retrieval_options(options), signature, library)


def calibration_parts(wholes: Sequence[Mesh], labels: Sequence[str], n_parts: int, *, seed: int = 0
                      ) -> list[tuple[int, Mesh]]:
    """``n_parts`` parts cut from a library's wholes, for `Comparer.calibrate_retrieval`: (the whole's index, the
    part). The wholes are drawn class by class in turn (so that every class counts alike), among the classes of
    at least two wholes (a part of a class of one cannot be looked up once its whole is left out). Parts alternate
    between two cuts, each taking a share of the whole's area drawn uniformly in `PART_FRACTIONS`: the vertices
    within a Euclidean ball around a random vertex (a head, a hand, a disc), and those on one side of a plane of
    random direction (a cut); the largest connected piece is kept. Deterministic for a seed."""
    labels = [str(x) for x in labels]
    if len(labels) != len(wholes):
        raise ValueError(f"wholes and labels must be of one length, got {len(wholes)} and {len(labels)}")
    n_parts = _validate.integer_at_least("n_parts", n_parts, 1)
    by: dict[str, list[int]] = {}
    for i, label in enumerate(labels):
        by.setdefault(label, []).append(i)
    classes = sorted(c for c, members in by.items() if len(members) > 1)
    if not classes:
        raise ValueError("no class has two wholes: a part cut from a whole cannot be looked up once that whole is "
                         "left out, so there is nothing to calibrate on")
    rng = np.random.default_rng(seed)
    out: list[tuple[int, Mesh]] = []
    start = int(rng.integers(len(classes)))
    for _ in range(20 * n_parts):
        if len(out) == n_parts:
            break
        j = int(rng.choice(by[classes[(start + len(out)) % len(classes)]]))
        mesh = wholes[j]
        v, areas = mesh.vertices, mesh.vertex_areas
        if len(out) % 2 == 0:  # a ball around a random vertex
            height = np.linalg.norm(v - v[rng.integers(mesh.n_vertices)], axis=1)
        else:  # one side of a plane of random direction
            d = rng.normal(size=3)
            height = v @ (d / np.linalg.norm(d))
        order = np.argsort(height, kind="stable")
        share = np.cumsum(areas[order]) / areas.sum()
        keep = order[:int(np.searchsorted(share, rng.uniform(*PART_FRACTIONS))) + 1]
        try:
            with warnings.catch_warnings():  # the pieces a cut leaves are dropped here
                warnings.simplefilter("ignore", MeshWarning)
                part, _ = cut(mesh, keep)
                part, _ = part.cleaned(keep_largest_component=True)
        except ValueError:
            continue
        if part.n_vertices >= MIN_PART_VERTICES:
            out.append((j, part))
    if len(out) < n_parts:
        raise ValueError(f"the wholes are too coarse to cut parts from: {len(out)} of {n_parts} parts had "
                         f"{MIN_PART_VERTICES} vertices or more")
    return out


class CalibrationRecord:
    """The lookups of `Comparer.calibrate_retrieval` so far, in a JSON-lines file, so that a stopped calibration
    resumes: a first line with its settings (``header``: the parts' count and seed, the options, the signature and
    the library's content), then one line per part looked up (its index, margin and outcome). A file of other
    settings is refused by name; a last line cut short by a stop is dropped and looked up again."""

    def __init__(self, path: str | Path, header: dict) -> None:
        self.path, self.done = Path(path), {}
        if self.path.exists() and self.path.stat().st_size:
            lines = self.path.read_text().splitlines()
            try:
                found = json.loads(lines[0])
            except json.JSONDecodeError:
                raise ValueError(f"record {self.path}: not a retrieval calibration's record") from None
            if found != header:
                differ = sorted(k for k in set(found) | set(header) if found.get(k) != header.get(k))
                raise ValueError(f"record {self.path} holds the lookups of another calibration (its "
                                 f"{', '.join(differ)} differ): give another file, or delete it to start again")
            good = 1
            for line in lines[1:]:
                try:
                    d = json.loads(line)
                    self.done[int(d["part"])] = (float(d["margin"]), bool(d["right"]))
                except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                    break  # cut short by a stop: looked up again
                good += 1
            self.path.write_text("".join(x + "\n" for x in lines[:good]))
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.write_text(json.dumps(header) + "\n")

    def add(self, part: int, margin: float, right: bool) -> None:
        """Record part ``part``'s lookup (appended at once)."""
        self.done[part] = (float(margin), bool(right))
        with open(self.path, "a") as f:
            f.write(json.dumps({"part": part, "margin": float(margin), "right": bool(right)}) + "\n")
