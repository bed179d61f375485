"""Pairwise shape comparison: signatures → samples → cost → transport → distance, correspondence, matches.

`Comparer` composes the stages of a comparison, each behind a small protocol with its options in one
frozen dataclass, all described by one `wpot.config.ComparisonConfig`:

* a **signature** (`wpot.signatures`: WKS §2.3 with the cost of Eq. 29, LD-SIFT §2.2 with L2, HKS, or any
  registered one), computed once per shape and cached in memory and on disk; signatures that are fitted
  to a dataset (WKS's energy grid, paper §3.2) are fitted once and shared by every shape;
* a **sampler** (`wpot.sampling`): every vertex, or farthest-point samples with their cells;
* a **transport solver** (`wpot.ot`): balanced (Eq. 6–16) or partial (Eq. 17–26) statistical-physics
  transport, at β = ∞ exactly or annealed in β (Algorithm 1), by the solver the configuration names.

What belongs to a comparison stays here: the cost between the two point sets (dense, or recomputed in the
solver's kernels when the dense problem does not fit the device's memory), the relative mass penalty of
partial transport (`solver_mass_penalty`), the distance (U for balanced transport; SU of Eq. 27 for partial,
from the self-comparisons, cached per shape), the correspondence (the argmax of each plan row, §4.1.3), the
matched pairs ``G(i, j) > 0.9·m1(i)`` and the similarity registration fitted to them (§5.1,
`wpot.maps.registration`).

`compare` is the one-shot function; for many pairs, build one `Comparer`.
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from wpot import _validate
from wpot.config import _all_signature_keywords, ComparisonConfig, DEFAULT_MASS_PENALTY, PENALTY_SCALES, TRANSPORTS
from wpot.mesh import Mesh
from wpot.progress import as_progress
from wpot.maps.registration import area_scale, fit_similarity, fit_similarity_robust, Registration
from wpot.sampling import FarthestPointSampler, Points, Subsample, farthest_point_sampling
from wpot._warp import available_memory, resolve_device
from wpot.cache import Cache
from wpot.cost import cost_matrix, cost_mean, NearestCosts
from wpot.maps.locate import check_part, locate_part
from wpot.maps.retrieval import (CALIBRATED_THICKNESS, SIZE_SPREAD, CalibrationRecord, RetrievalCalibration,
                                 RetrievalWarning, calibration_of, calibration_parts, library_digest, rank_classes,
                                 retrieval_options, retrieval_sample, size_spread)
from wpot.signatures._frames import common_edge
from wpot.ot import debiased, FeatureCost, make_solver, TransportProblem
from wpot.runs.history import debias_history
from wpot.signatures import get_signature, Signature
from wpot.signatures._spectral import MIN_EIGENPAIRS, SpectralOptions, SpectralSignature
from wpot.spectral import spectrum_cache

__all__ = [
    "DEFAULT_MASS_PENALTY",
    "PENALTY_SCALES",
    "TRANSPORTS",
    "Comparison",
    "ComparisonWarning",
    "Comparer",
    "ComparisonConfig",
    "ProblemTooLargeError",
    "Registration",
    "Subsample",
    "Points",
    "compare",
    "farthest_point_sampling",
    "fit_similarity",
    "cost_scale",
    "solver_mass_penalty",
    "choose_cost_mode",
    "check_mesh_size",
    "min_vertices",
]

#: fraction of the device's free memory a solve may plan to use (`Comparer`'s default ``memory_limit``)
MEMORY_FRACTION = 0.8
#: signatures kept in a `Comparer`'s memory cache, by shapes and bytes (the disk cache has no bound); the count of
#: entries allows for two cached pieces a shape (`wpot.signatures.base.Signature.pieces`)
MAX_CACHED_SHAPES = 128
MAX_CACHED_BYTES = 2 << 30


class ProblemTooLargeError(ValueError):
    """The transport problem does not fit in the chosen device's memory, even matrix-free (use ``max_vertices``)."""


# ----------------------------------------------------------------------------------------- mass penalty
def cost_scale(C: Any) -> float:
    """The cost scale ``s(C)`` of the relative mass penalty: the mean of ``C`` over all pairs.

    It is the transport cost of the independent plan ``ρ1 ⊗ ρ2`` (the β → 0 limit of the annealing), scales
    linearly with ``C``, and does not change when points are duplicated (and barely when they are
    resampled), which is what makes the relative penalty scale- and size-free. ``C`` is an (N1, N2)
    NumPy array, a float64 ``wp.array``, or a `wpot.ot.FeatureCost` (one pass, nothing stored).
    """

    if isinstance(C, FeatureCost):

        return cost_mean(C.X, C.Y, metric=C.metric, device=C.device)
    if hasattr(C, "numpy") and not isinstance(C, np.ndarray):
        C = C.numpy()
    c = np.asarray(C, dtype=np.float64)
    if c.ndim != 2 or c.size == 0:
        raise ValueError(f"the cost matrix must be a non-empty (N1, N2) array, got shape {c.shape}")
    return float(c.mean())


def solver_mass_penalty(C: Any, mass_penalty: float, *, penalty_scale: str = "relative") -> float:
    """The factor ``a`` handed to `wpot.ot.solve_partial`, whose χ² penalty is ``α_i(k) = a / ρ_i(k)²`` (Eq. 17).

    ``penalty_scale="paper"`` returns ``mass_penalty`` itself: ``mass_penalty = 1`` is exactly the paper's
    ``α = 1/ρ²`` (§2.5). ``penalty_scale="relative"`` (the default of `Comparer`) returns

        a = κ · s(C) / N̄,     s(C) = mean_{k,l} C(k, l) (`cost_scale`),   N̄ = √(N1 N2),   κ = mass_penalty.

    Why. Compare uses uniform references ρ_i = 1/N_i. Write the masses as densities ``w_i = m_i / ρ_i``
    (``E_ρ[w] = 1``). The penalty of side i is then ``Σ_k a N_i² m_i(k)² = a N_i · E_ρi[w_i²]``, and
    ``E_ρ[w²] = 1 + χ²(m‖ρ)`` (Pearson). With the paper's ``a = 1`` it is ``N_i (1 + χ²)``: putting all
    the mass uniformly on a fraction f of the points costs ``N_i (1/f − 1)``, which grows with N and is
    compared with transport costs ``Σ C G`` of the order of ``s(C)``, in whatever unit the signature
    distance has. With ``a = κ s / N̄`` the objective becomes

        U = Σ C G + κ s(C) [ (N1/N̄) E_ρ1[w1²] + (N2/N̄) E_ρ2[w2²] ],

    so (for N1 = N2, or when both sides are resampled together)

    * scaling C by λ scales U by λ: the plan and masses do not change (scale-free);
    * duplicating every point (or resampling both shapes at another density) leaves the densities w, the
      transport cost and s(C) unchanged: the plan is the same up to the splitting (size-free);
    * κ alone sets the trade-off: concentrating side i on a fraction f costs ``κ (1/f − 1)`` mean costs.
      Closed form: if a fraction f of B costs 0 to every point of A and the rest costs c, the mass
      B's fraction receives is ``q = min(1, f + f / (2κ))``; it takes all the mass once ``κ ≤ f / (2(1 − f))``.
      In general a region whose cost is lower by Δ receives ``f + f(1 − f) Δ / (2 κ s)``.

    κ → ∞ is balanced transport with the reference masses; κ → 0 collapses onto the cheapest pairs.
    When N1 ≠ N2 the solver's single factor cannot give both sides the weight κ s exactly; the geometric
    mean N̄ weights side i by ``√(N_i / N_j)`` (symmetric in A and B, exact when N1 = N2).

    Raises
    ------
    ValueError : unknown ``penalty_scale``, ``mass_penalty`` not positive and finite, or (relative) a cost
        matrix with zero mean (every signature identical: there is no cost scale).
    """
    _validate.one_of("penalty_scale", penalty_scale, PENALTY_SCALES)
    mp = _validate.positive_finite("mass_penalty", mass_penalty)
    if penalty_scale == "paper":
        return mp
    n1, n2 = (int(x) for x in C.shape)
    s = cost_scale(C)
    if not s > 0:
        raise ValueError(
            f"the relative mass penalty needs a cost matrix with a positive mean, got mean {s!r} for a {n1} x {n2} "
            "cost (all signatures identical?); use penalty_scale='paper' to give the factor directly"
        )
    return mp * s / math.sqrt(n1 * n2)

# ----------------------------------------------------------------------------------------------- memory
def choose_cost_mode(solver: Any, n1: int, n2: int, dim: int, budget_bytes: float) -> bool:
    """Whether an ``n1 × n2`` problem with ``dim``-dimensional signatures must run matrix-free.

    False (dense: the cost matrix is stored, the fastest mode) when ``solver.memory_bytes(n1, n2)`` fits
    in ``budget_bytes``; True (`wpot.ot.FeatureCost`: the cost recomputed in the kernels, no N1 × N2
    array, the plan returned as its top entries per row) when only the matrix-free need fits.

    Raises
    ------
    ProblemTooLargeError : neither fits; the message names ``max_vertices``.
    ValueError : the dense mode does not fit and ``solver`` cannot run matrix-free.
    """
    dense = solver.memory_bytes(n1, n2)
    if dense <= budget_bytes:
        return False
    lazy = solver.memory_bytes(n1, n2, matrix_free=True, dim=dim)
    if lazy <= budget_bytes:
        return True
    k = max(3, int(math.sqrt(budget_bytes / max(1.0, dense / (float(n1) * float(n2))))))
    raise ProblemTooLargeError(
        f"a {n1} x {n2} comparison needs about {dense / 2**30:.2f} GiB for the dense transport and "
        f"{lazy / 2**30:.2f} GiB matrix-free, but the budget is {budget_bytes / 2**30:.2f} GiB; pass max_vertices "
        f"(at most about {k} here for the dense mode) to subsample both meshes by farthest-point sampling"
    )


#: above this many pairs of points (20,000 a side), a transport over every vertex warns on a CPU device
#: (`check_transport_size`; the exact solver's times by size: the docs' Results page, §1)
LARGE_TRANSPORT_PAIRS = 20_000 ** 2


class ComparisonWarning(UserWarning):
    """A comparison that will run, but not as the caller likely expects (e.g. for hours)."""


def check_transport_size(n1: int, n2: int, device: str) -> None:
    """Warn (`ComparisonWarning`) when an ``n1 × n2`` transport on a CPU ``device`` exceeds
    `LARGE_TRANSPORT_PAIRS`, naming ``max_vertices``: a large mesh compared vertex by vertex runs for hours."""
    if str(device).startswith("cpu") and n1 * n2 > LARGE_TRANSPORT_PAIRS:
        warnings.warn(f"a {n1} x {n2} transport over every vertex can take an hour or more on a CPU; max_vertices=2000 "
                      "compares 2000 farthest-point samples of each mesh instead, and the correspondence still covers "
                      "every vertex", ComparisonWarning, stacklevel=3)


# ------------------------------------------------------------------------------------------- mesh size
#: the fewest vertices of a mesh in a comparison: three points to sample (`SamplerOptions.max_vertices`) and
#: three matched pairs to fit a registration
MIN_VERTICES = 3


def min_vertices(config: ComparisonConfig) -> tuple[int, str]:
    """The fewest vertices a mesh may have in a comparison with ``config``, and why (for the error message)."""
    title = get_signature(config.signature).title
    if not isinstance(config.signature_options, SpectralOptions):
        return MIN_VERTICES, f"a comparison needs at least {MIN_VERTICES} points to sample and to match"
    n_eigen = config.signature_options.n_eigen
    need = max(MIN_VERTICES, min(int(n_eigen), MIN_EIGENPAIRS))
    return need, (f"{title} takes min(n_eigen, N) Laplace-Beltrami eigenpairs from a mesh of N vertices and needs "
                  f"at least {need} of them (n_eigen={n_eigen})")


def check_mesh_size(mesh: Mesh, config: ComparisonConfig, name: str = "mesh") -> None:
    """A `ValueError` naming ``name`` when ``mesh`` has too few vertices for ``config`` (`min_vertices`), raised
    before any spectrum or transport is computed."""
    need, why = min_vertices(config)
    if mesh.n_vertices < need:
        raise ValueError(f"{name} has only {mesh.n_vertices} vertices, too few to compare: {why}")


def fit_phase(stage: Any) -> str:
    """The progress name of fitting ``stage`` to a dataset: "spectra" for a spectral signature (its fit inputs are
    the shapes' spectra, the long part), else "fitting <title>"."""

    return "spectra" if isinstance(stage, SpectralSignature) else f"fitting {stage.title}"


def _fit_step(stage: Any, label: str, mesh: Mesh) -> str:
    """The progress line of one mesh's share of fitting a signature (for a spectral signature, its spectrum)."""

    if isinstance(stage, SpectralSignature):
        o = stage.options
        size = (f"{mesh.n_vertices} vertices, through a simplified copy of {o.copy_vertices}"
                if o.copies(mesh.n_vertices) else f"{mesh.n_vertices} vertices")
        return f"Laplace-Beltrami spectrum of {label} ({size}, {min(int(stage.options.n_eigen), mesh.n_vertices)} eigenpairs)"
    return f"fitting {stage.title} to {label} ({mesh.n_vertices} vertices)"


# ----------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Comparison:
    """The comparison of shape A with shape B.

    Attributes
    ----------
    distance : U at convergence (balanced, Eq. 6) or SU (partial, Eq. 27, with the self-comparisons)
    correspondence : (N_A,) int64, for each vertex of A the vertex of B with the largest plan entry in its
        row (when subsampled: the row of A's nearest sample, and B's sampled vertex)
    matched : (K, 2) int64 pairs (i in A, j in B) with ``G(i, j) > 0.9·m1(i)`` (vertex indices of the full
        meshes). With balanced transport and uniform masses, a vertex of A (mass 1/N_A) fits in one vertex of
        B (mass 1/N_B) only when N_B ≤ N_A / 0.9, so between meshes of quite different sizes few or no pairs
        match (the paper's Fig. 1 contrast); partial transport adapts the masses.
    matched_weight : (K,) float64, the plan entries ``G(i, j)`` of the matched pairs
    mass1 : (n_A,) float64, the mass each (sampled) vertex of A sends, ``Σ_l G(k, l)`` (uniform for balanced)
    mass2 : (n_B,) float64, the mass each (sampled) vertex of B receives
    registration : similarity transform taking A onto B fitted to the matched pairs (§5.1) by
        `wpot.maps.registration.fit_similarity_robust` (wrong matches are left out as outliers: its ``inliers``
        mask and ``rms`` over them), or None when fewer than 3 non-collinear pairs matched. With balanced
        transport its scale is the two shapes' size ratio (`wpot.maps.registration.area_scale`, sqrt of the area
        ratio) and only the rotation and translation are fitted: a scale fitted to the pairs follows the pose
        (even between same-size TOSCA poses with the true correspondence; the docs' Results page). With partial transport the
        scale is fitted too (``scale_from`` says which)
    result : the solver's `OTResult` for A vs B (on the sampled vertices when subsampled)
    self_energies : (U(A, A), U(B, B)) for partial transport, else None
    history : (n_β, 2) float64, columns β and D(β): U_β (balanced) or SU_β (partial) at each annealing β
    sample_a, sample_b : the `Subsample` of each mesh, or None when not subsampled
    confidence : (N_A,) float64 in [0, 1], per vertex of A (through its sample): the share of its sample's
        reference mass that the plan sends to the matched vertex, ``G(k, j*) / ρ_k`` (ρ: A's masses scaled to
        the plan's total; capped at 1). Near 1: the sample goes whole to one place; near 0: it is spread out,
        or (partial transport) left unmatched. It ranks the correspondence's matches by trust
    received : (N_B,) float64, per vertex of B (through its sample): the mass its sample receives over its
        reference mass (1 everywhere for balanced transport); `region` thresholds it
    """

    distance: float
    correspondence: np.ndarray
    matched: np.ndarray
    matched_weight: np.ndarray
    mass1: np.ndarray
    mass2: np.ndarray
    registration: Registration | None
    result: Any
    signature: str
    transport: str
    self_energies: tuple[float, float] | None = None
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    sample_a: Subsample | None = None
    sample_b: Subsample | None = None
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    received: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def region(self, threshold: float = 0.5) -> np.ndarray:
        """(N_B,) bool, the vertices of B that A matched: those whose sample receives at least ``threshold``
        times its reference mass (`received`). With partial transport of a part into a whole, the part's place
        in the whole; with balanced transport, all of B."""
        if not (isinstance(threshold, (int, float)) and np.isfinite(threshold) and threshold >= 0):
            raise ValueError(f"threshold must be a finite number >= 0, got {threshold!r}")
        return self.received >= threshold

    def __repr__(self) -> str:
        # a summary for notebooks: the dataclass default would print every array, the OT result's included
        sizes = f"{len(self.correspondence)}->{len(self.sample_b.nearest) if self.sample_b is not None else len(self.mass2)} vertices"
        if self.sample_a is not None or self.sample_b is not None:
            sizes += f" (transport on {len(self.mass1)}x{len(self.mass2)} samples)"
        reg = "none" if self.registration is None else (
            f"scale {self.registration.scale:.4g}, rms {self.registration.rms:.4g} on {self.registration.n_pairs} pairs")
        return (f"Comparison({self.signature}, {self.transport}, {sizes}, distance={self.distance:.6g}, "
                f"converged={bool(getattr(self.result, 'converged', False))}, matched={len(self.matched)} pairs, "
                f"registration: {reg})")


# --------------------------------------------------------------------------------------------- comparer
def solve_with_progress(solver: Any, problem: Any, progress: Any) -> Any:
    """Solve ``problem`` with ``solver``; with ``progress`` shown live (a terminal, a notebook), a bar counts the
    solved betas and shows the last β and U."""
    method = solver.method_for(problem) if hasattr(solver, "method_for") else solver.name
    if not progress.live or method == "exact":  # the exact LP has one beta (infinity): nothing to count
        return solver.solve(problem)
    progress.break_line()  # the transport stage's line: the bar goes below it
    bar = progress.bar(None, "annealing", "beta")
    try:
        def step(s: Any) -> None:
            bar.set_postfix_str(f"beta {s.beta:.3g}, U {s.cost:.9g}", refresh=False)
            bar.update()

        return solver.solve(problem, on_beta=step)
    finally:
        bar.refresh()  # the last beta and U drawn at least once: tqdm redraws at most every 0.1 s
        bar.close()


class SignatureSource:
    """One signature stage and its caches: each shape's signatures computed once (in memory, and on disk under a
    cache folder) and the state fitted to a dataset (WKS's energy grid, HKS's times), shared by every shape.

    ``stage`` is the configured `wpot.signatures.Signature` (replaced, not changed, when its state is set or
    fitted); ``signature_cache`` holds the signatures (or their pieces), ``spectrum_cache`` the eigenpairs."""

    def __init__(self, stage: Signature, signature_cache: Cache, spectrum_cache: Cache) -> None:
        self.stage, self.signature_cache, self.spectrum_cache = stage, signature_cache, spectrum_cache

    @property
    def energies(self) -> np.ndarray | None:
        """The WKS energy grid (n_energies,) float64, or None until fitted (or for a signature without one)."""
        st = self.stage.state()
        return None if not st or "energies" not in st else np.asarray(st["energies"], dtype=np.float64)

    def set_state(self, state: dict[str, Any] | None) -> None:
        """Set the fitted state (`Signature.with_state`)."""
        self.stage = self.stage.with_state(state)

    def fit(self, meshes: Sequence[Mesh], *, labels: Sequence[str] | None = None, progress: Any = None) -> None:
        """Fit the stage to ``meshes``, reported on ``progress`` (a `wpot.progress.Progress`): a signature with a
        fit of its own in one step, a pair a line per mesh (``labels`` names them), a dataset as a bar."""
        meshes, progress = list(meshes), as_progress(progress)
        stage = self.stage
        if stage.needs_fit and type(stage).fit is not Signature.fit:  # a signature with its own fit
            with progress.stage(f"fitting {stage.title} to {len(meshes)} shapes"):
                stage.fit(meshes)
        elif stage.needs_fit and len(meshes) <= 2:  # a pair: a line per mesh
            names = list(labels) if labels is not None else [f"shape {k}" for k in range(len(meshes))]
            inputs = []
            for name, m in zip(names, meshes):
                with progress.stage(_fit_step(stage, name, m)):
                    inputs.append(stage.fit_input(m))
            stage.fit_from(inputs)
        elif stage.needs_fit:  # a dataset: a bar
            bar = progress.bar(len(meshes), fit_phase(stage), "shape")
            inputs = []
            try:
                for m in meshes:
                    inputs.append(stage.fit_input(m))
                    bar.update()
            finally:
                bar.close()
            stage.fit_from(inputs)

    def signatures(self, mesh: Mesh) -> np.ndarray:
        """Per-vertex signatures of the full mesh, (N, d) float64, read-only.

        Cached by mesh content and the signature's parameters (`wpot.cache.Cache`, namespace "signatures"): in
        memory, and on disk under ``cache_dir`` (or ``$WPOT_CACHE_DIR``); a signature made of pieces
        (`wpot.signatures.base.Signature.pieces`, e.g. LD-SIFT with its thickness column) is cached piece by
        piece. A signature fitted to a dataset (WKS) must be fitted first (`fit`, ``energies=``, or
        `Comparer.compare`, which fits it to its pair).
        """
        stage, cache = self.stage, self.signature_cache
        keys = stage.pieces()
        got = {name: cache.get(mesh.fingerprint, params) for name, params in keys.items()}
        missing = [name for name, entry in got.items() if entry is None]
        if missing:
            for name, value in stage.compute_pieces(mesh, missing).items():
                got[name] = cache.put(mesh.fingerprint, keys[name], {"signature": value})
        sig = stage.assemble({name: entry["signature"] for name, entry in got.items()})
        sig.setflags(write=False)  # a cached piece already is; an assembled array is new
        if sig.shape[0] != mesh.n_vertices:
            raise ValueError(f"signature rows ({sig.shape[0]}) do not match the mesh's {mesh.n_vertices} vertices")
        return sig


class Comparer:
    """A comparison session: one configuration, signatures cached per shape, fitted signature state shared.

    Parameters
    ----------
    config : a `wpot.config.ComparisonConfig`; or leave it out and give the flat keywords below
    signature : one of the registered signatures (`wpot.signatures.signature_names()`): "wks" (default;
        intrinsic, §2.3; cost Eq. 29), "ldsift" (extrinsic, §2.2; L2) or "hks" (intrinsic, heat kernel)
    transport : one of `wpot.config.TRANSPORTS`: "balanced" (default; Eq. 6–16) or "partial" (Eq. 17–26,
        for a shape against a part of another)
    max_vertices, vertices_per_sample, fps_metric, pooling : the sampler's options (`wpot.sampling.SamplerOptions`;
        by default every vertex is used)
    mass_penalty, penalty_scale : partial transport's χ² penalty. With ``penalty_scale="relative"`` (default)
        ``mass_penalty`` is κ in ``α(k) = κ · mean(C) / (√(N1 N2) ρ(k)²)``: spreading all of a side's mass on
        a fraction f of its points costs κ (1/f − 1) mean costs, whatever the cost's unit and the number of
        points (`solver_mass_penalty`); default `DEFAULT_MASS_PENALTY`. ``penalty_scale="paper"``:
        ``α(k) = mass_penalty / ρ(k)²``, exactly Eq. 17 for ``mass_penalty=1``.
    solver_options : the transport solver: ``method`` ("auto", default, or "exact": the exact limit β = ∞,
        the transport LP for balanced transport and the χ² QP for partial transport, whose history is D(∞)
        alone; "anneal", and "ipm" for balanced transport, which also record D(β) along the annealing) and
        any `wpot.ot.SolverOptions` (``tol``, ``max_newton``, ...)
    match_ratio : a pair (i, j) is matched when ``G(i, j) > match_ratio · m1(i)`` (paper: 0.9)
    **signature options : those of the chosen signature, e.g. ``n_eigen``, ``n_energies``,
        ``scale_invariant`` (WKS, HKS), ``ldsift_K``, ``ldsift_resolution``, ``ldsift_slab`` (LD-SIFT),
        ``hks_n_times``; options of other signatures are ignored
    device : Warp device for signatures, cost and solver; None is Warp's default, resolved once here
    cache_dir : folder for the on-disk signature and spectrum caches (content-keyed npz, `wpot.cache.Cache`);
        None uses ``$WPOT_CACHE_DIR`` when set (else memory only); False keeps them in memory only
    energies : a fixed WKS energy grid (n_energies,) shared by all shapes (shorthand for
        ``signature_state={"energies": energies}``)
    signature_state : the fitted state of the signature (`Signature.state`); when None it is fitted by
        `fit` (a dataset) or, for a lone pair, by `compare` to the two shapes
    memory_limit : bytes a transport problem may use on the device (None: `MEMORY_FRACTION` of its free
        memory). A problem whose dense form does not fit runs matrix-free (`choose_cost_mode`).
    progress : report the steps of `compare` and `fit` (spectra, signatures, sampling, transport), each with
        its time: True (on standard error; in Jupyter `tqdm.auto` shows the bars as widgets), False (default:
        nothing), or a `wpot.progress.Progress`
    """

    def __init__(
        self,
        config: ComparisonConfig | None = None,
        *,
        device: str | None = None,
        cache_dir: str | Path | None | bool = None,
        energies: ArrayLike | None = None,
        signature_state: dict[str, Any] | None = None,
        memory_limit: float | None = None,
        progress: Any = False,
        **keywords: Any,
    ) -> None:
        if config is None:
            config = ComparisonConfig.from_keywords(**keywords)
        elif keywords:
            raise TypeError(f"give either config or keywords, not both (got {sorted(keywords)})")
        elif not isinstance(config, ComparisonConfig):
            raise TypeError(f"config must be a wpot.ComparisonConfig, got {type(config).__name__}")
        if energies is not None:
            if signature_state is not None:
                raise ValueError("give either energies or signature_state, not both")
            signature_state = {"energies": energies}
        self._setup(config, device, cache_dir, signature_state, memory_limit, None)
        self.progress = as_progress(progress)

    def _setup(self, config: ComparisonConfig, device: str | None, cache_dir: Any, signature_state: Any,
               memory_limit: float | None, caches: tuple[Any, Any] | None) -> None:
        """Build the stages; ``caches`` = (signature cache, spectrum cache) to share another comparer's."""
        self.config = config
        self.device = _resolve_device(device)
        self.cache_dir = cache_dir
        self.memory_limit = None if memory_limit is None else _validate.positive_finite("memory_limit", memory_limit)
        if caches is None:
            caches = (Cache("signatures", max_entries=2 * MAX_CACHED_SHAPES, max_bytes=MAX_CACHED_BYTES,
                            cache_dir=cache_dir),
                      _spectrum_cache(cache_dir))
        stage = get_signature(config.signature)(config.signature_options, device=self.device, spectrum_cache=caches[1],
                                                state=signature_state)
        self.source = SignatureSource(stage, *caches)
        self.sampler = FarthestPointSampler(config.sampler)
        self.solver = make_solver(config.method, **dict(config.solver_options))
        self._self_energies: dict[tuple[str, str], tuple[float, np.ndarray]] = {}

    # ------------------------------------------------------------------------------ settings
    @property
    def signature(self) -> str:
        return self.config.signature

    @property
    def transport(self) -> str:
        return self.config.transport

    def __getattr__(self, name: str) -> Any:
        # the flat settings (mass_penalty, max_vertices, n_eigen, ldsift_slab, ...) read from the configuration
        if name.startswith("_") or name in ("config", "source", "progress"):
            raise AttributeError(name)
        kw = self.config.keywords()
        if name in kw:
            return kw[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def params(self) -> dict[str, Any]:
        """Every setting that changes a distance, as JSON-able values (`ComparisonConfig.run_key`)."""
        return self.config.run_key()

    def options(self) -> dict[str, Any]:
        """The constructor keywords that rebuild this `Comparer` (``Comparer(**c.options())``)."""
        return dict(self.config.keywords(), device=self.device, cache_dir=self.cache_dir,
                    signature_state=self.stage.state(), memory_limit=self.memory_limit)

    def __repr__(self) -> str:
        # one line for notebooks: the run key's settings, the device, and the fitted state (e.g. WKS's grid)
        settings = ", ".join(f"{k}={v!r}" for k, v in self.params().items() if v is not None and v != {})
        state = ""
        if self.stage.needs_fit:
            st = self.stage.state() or {}
            state = "".join(f", {k}: {len(st[k])} fitted" if k in st else f", {k}: none yet" for k in self.stage.state_keys)
        return f"Comparer({settings}, device={self.device!r}{state})"

    def with_options(self, **changes: Any) -> "Comparer":
        """A new `Comparer` with some settings changed (e.g. ``mass_penalty`` in a sweep).

        It shares this one's signature and spectrum caches (keyed by content and parameters, so always
        safe) unless ``cache_dir`` changes, the fitted signature state unless the signature's options change
        (or ``energies`` / ``signature_state`` is given), and the farthest-point samples when ``fps_metric``
        is unchanged. Self-comparisons (Eq. 27) are not shared: they depend on every setting.
        """
        return _derived(self, changes)

    # ------------------------------------------------------------------------------ signatures
    @property
    def stage(self) -> Signature:
        """The configured signature with its fitted state (`SignatureSource.stage`)."""
        return self.source.stage

    @property
    def energies(self) -> np.ndarray | None:
        """The WKS energy grid (n_energies,) float64, or None until fitted (or for a signature without one)."""
        return self.source.energies

    @energies.setter
    def energies(self, value: ArrayLike | None) -> None:
        self._refit(lambda: self.source.set_state(None if value is None else {"energies": value}))

    def _refit(self, change: Callable[[], None]) -> None:
        """Apply ``change`` to the signature's state; the self-comparisons (Eq. 27) go when the signatures change."""
        old = self.source.stage.key()
        change()
        if self.source.stage.key() != old:
            self._self_energies.clear()

    def fit(self, meshes: Sequence[Mesh], *, labels: Sequence[str] | None = None) -> None:
        """Fit the signature to a dataset (WKS's energy grid, HKS's times: one for every shape, paper §3.2).

        With ``progress``, each mesh's share (for WKS and HKS its spectrum, the long part) is reported: a line per
        mesh for a pair (``labels`` names them; default: their positions), a bar for more."""
        self._refit(lambda: self.source.fit(meshes, labels=labels, progress=self.progress))

    def fit_energies(self, meshes: Sequence[Mesh]) -> np.ndarray:
        """WKS: build one energy grid from the spectra of all ``meshes`` (`wpot.wks_energies`), keep it, return it."""
        if self.signature != "wks":
            raise ValueError(f"fit_energies is for WKS; the {self.signature!r} signature is fitted by fit(meshes)")
        self.fit(meshes)
        return self.energies

    def signatures(self, mesh: Mesh) -> np.ndarray:
        """Per-vertex signatures of the full mesh, (N, d) float64, read-only (`SignatureSource.signatures`)."""
        return self.source.signatures(mesh)

    # ------------------------------------------------------------------------------ sampling
    def n_samples(self, n_vertices: int) -> int:
        """How many points stand for a mesh of ``n_vertices`` vertices (`SamplerOptions.n_samples`)."""
        return self.config.sampler.n_samples(n_vertices)

    def subsample(self, mesh: Mesh) -> Subsample | None:
        """The farthest-point sample used for ``mesh`` (None when every vertex is used)."""
        return self.sampler.subsample(mesh)

    def points(self, mesh: Mesh) -> Points:
        """What the transport sees of ``mesh``: every vertex, or its farthest-point samples."""
        return self.sampler.points(mesh, self.signatures(mesh))

    def _reported_points(self, mesh: Mesh, label: str) -> Points:
        """`points`, with the signatures and the sampling reported as two steps."""
        with self.progress.stage(f"{self.stage.title} signatures of {label} ({mesh.n_vertices} vertices)"):
            sig = self.signatures(mesh)
        k = self.n_samples(mesh.n_vertices)
        if k >= mesh.n_vertices:
            return self.sampler.points(mesh, sig)
        with self.progress.stage(f"farthest-point sampling of {label}: {k} of {mesh.n_vertices} vertices"):
            return self.sampler.points(mesh, sig)

    # ------------------------------------------------------------------------------ transport
    def _budget(self) -> float:
        return self.memory_limit if self.memory_limit is not None else MEMORY_FRACTION * available_memory(self.device)

    def transport_problem(self, pa: Points, pb: Points) -> Any:
        """The `wpot.ot.TransportProblem` between two point sets: the cost (dense, or a `FeatureCost` when the
        dense problem does not fit the memory budget, `choose_cost_mode`), the masses, and for partial
        transport the solver's mass-penalty factor (`solver_mass_penalty`)."""
        n1, n2 = len(pa.signatures), len(pb.signatures)
        metric = self.stage.metric
        if choose_cost_mode(self.solver, n1, n2, pa.signatures.shape[1], self._budget()):
            cost = FeatureCost(pa.signatures, pb.signatures, metric, device=self.device)
        else:
            cost = cost_matrix(pa.signatures, pb.signatures, metric=metric, device=self.device)
        a = None
        if self.transport == "partial":
            a = solver_mass_penalty(cost, self.config.mass_penalty, penalty_scale=self.config.penalty_scale)
        return TransportProblem(cost, pa.masses, pb.masses, mass_penalty=a, device=self.device)

    def transport_plan(self, mesh_a: Mesh, mesh_b: Mesh) -> Any:
        """Solve the transport between the (sampled) signatures of A and B; returns the solver's `OTResult`."""
        self.sampler.check_cells(mesh_a, mesh_b)
        return self.solver.solve(self.transport_problem(self.points(mesh_a), self.points(mesh_b)))

    def self_transport(self, mesh: Mesh) -> Any:
        """Solve ``mesh`` against itself (the self-comparison of Eq. 27); returns the `OTResult`, not cached."""
        p = self.points(mesh)
        return self.solver.solve(self.transport_problem(p, p))

    def self_energy(self, mesh: Mesh) -> tuple[float, np.ndarray]:
        """U(A, A) and its per-β history ((n_β, 2) float64), for Eq. 27; cached per shape (the plan is not kept)."""
        key = (mesh.fingerprint, self.stage.key())
        r = self._self_energies.get(key)
        if r is None:
            res = self.self_transport(mesh)
            r = (float(res.objective), res.energy_history)
            self._self_energies[key] = r
        return r

    def _fit_to_pair(self, mesh_a: Mesh, mesh_b: Mesh, labels: tuple[str, str]) -> None:
        """Fit a signature that needs fitting and is not fitted yet to the two meshes of a lone pair."""
        if self.stage.needs_fit and not self.stage.fitted:
            self.fit([mesh_a, mesh_b], labels=list(labels))

    def compare(self, mesh_a: Mesh, mesh_b: Mesh) -> "Comparison":
        """Compare A with B; see `Comparison`. A signature that needs fitting and is not fitted yet is fitted
        to A and B."""
        for name, m in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
            if not isinstance(m, Mesh):
                raise TypeError(f"{name} must be a wpot.Mesh, got {type(m).__name__}")
            check_mesh_size(m, self.config, name)
        self._fit_to_pair(mesh_a, mesh_b, ("A", "B"))
        self.sampler.check_cells(mesh_a, mesh_b)
        pa, pb = self._reported_points(mesh_a, "A"), self._reported_points(mesh_b, "B")
        what = "every vertex" if pa.subsample is None and pb.subsample is None else "farthest-point samples"
        check_transport_size(len(pa.signatures), len(pb.signatures), self.device)
        with self.progress.stage(f"{self.transport} transport on {what}, {len(pa.signatures)} x {len(pb.signatures)}"):
            res = solve_with_progress(self.solver, self.transport_problem(pa, pb), self.progress)
        hist = res.energy_history
        self_e = None
        distance = float(res.objective)  # U (Eq. 6): for balanced transport the objective is the cost
        if self.transport == "partial":
            with self.progress.stage("self-comparison of A (Eq. 27)"):
                uaa, haa = self.self_energy(mesh_a)
            with self.progress.stage("self-comparison of B (Eq. 27)"):
                ubb, hbb = self.self_energy(mesh_b)
            distance = float(debiased(distance, uaa, ubb))
            self_e = (uaa, ubb)
            hist = debias_history(hist, haa, hbb)
        return _assemble(res, pa.subsample, pb.subsample, mesh_a, mesh_b, distance, self_e, hist, self.config,
                         (pa.masses, pb.masses))

    def nearest_signature_distance(self, part: Mesh, whole: Mesh) -> float:
        """The mean, over the vertices of ``part``, of the cost from its signature to the nearest signature of
        ``whole`` (`wpot.cost.nearest_costs`): how well the whole explains each vertex of the part, whatever
        their places. Asymmetric, no transport, no map (`retrieve` ranks classes from the same costs)."""
        self._fit_to_pair(part, whole, ("part", "whole"))
        return float(self.nearest_costs(part, [whole]).mean())

    def nearest_costs(self, part: Mesh, wholes: Sequence[Mesh]) -> np.ndarray:
        """(N, M) float64: for each of the part's N vertices and each of the M wholes, the cost from the vertex's
        signature to the nearest signature of the whole (`wpot.cost.nearest_costs`); column j's mean is
        `nearest_signature_distance` ``(part, wholes[j])``. What `retrieve` ranks classes from. A signature that
        needs fitting (WKS) must be fitted first (`fit`)."""
        return library_costs(self, part, wholes)

    def retrieve(self, part: Mesh, wholes: Sequence[Mesh], labels: Sequence[str], *, options: Any = None,
                 calibration: Any = None) -> Any:
        """Rank the classes of a library of whole shapes for ``part`` (`wpot.maps.retrieval.rank_classes`) from each
        vertex's cost to the nearest signature of each whole (`nearest_costs`, on the part's `retrieval_sample`),
        standardised per vertex, a class scored by the union of its nearest members. ``labels``: each whole's class;
        ``options``: a `wpot.maps.retrieval.RetrievalOptions`; ``calibration``: the library's own probability
        (`calibrate_retrieval`), else the shipped one. Returns a `wpot.maps.retrieval.ClassRanking`."""
        return retrieve(self, part, wholes, labels, options, calibration)

    def calibrate_retrieval(self, wholes: Sequence[Mesh], labels: Sequence[str], *, n_parts: int = 100, seed: int = 0,
                            options: Any = None, record: str | Path | None = None) -> Any:
        """`retrieve`'s probability fitted to this library (`wpot.maps.retrieval.RetrievalCalibration`): ``n_parts``
        parts cut from its wholes, each looked up among the others, and saved to a ``record`` file to resume from."""
        return calibrate_retrieval(self, wholes, labels, n_parts=n_parts, seed=seed, options=options, record=record)

    def locate(self, part: Mesh, whole: Mesh, *, options: Any = None, landmarks: Any = None) -> Any:
        """Locate ``part`` in ``whole`` (another pose, say) and map every vertex of it (`wpot.maps.locate.locate_part`):
        this comparer's signatures propose the matches, geodesic consistency chooses among them. ``options``: a
        `wpot.maps.locate.LocateOptions` (``edge="whole"``: LD-SIFT at the whole's edge length for both meshes;
        ``scale="fit"`` or a number, with LD-SIFT at a set edge length: the part described again at the whole's
        scale); ``landmarks``: (L, 2) vertices (part, whole) known to match. Returns a `wpot.maps.locate.PartMap`."""
        self._fit_to_pair(part, whole, ("part", "whole"))
        return locate(self, part, whole, options, landmarks)


def locate(comparer: "Comparer", part: Mesh, whole: Mesh, options: Any, landmarks: Any = None) -> Any:
    """`Comparer.locate` (after the comparer is fitted to the pair). LD-SIFT at a set edge length sees a part at its
    own size, so a part whose scale is given (a number other than 1) or fitted is described again at the whole's
    scale (grown by it) and located from those signatures, at scale 1; the result reports the scale."""
    c = locating_comparer(comparer, whole, options)
    sw = c.signatures(whole)

    def at(mesh: Mesh, opt: Any) -> Any:
        return locate_part(mesh, whole, c.signatures(mesh), sw, metric=comparer.stage.metric, options=opt,
                           landmarks=landmarks, device=comparer.device)

    def grown(s: float) -> Any:  # the part at the whole's scale, located at scale 1; the result says s
        return dataclasses.replace(at(part.transformed(scale=s), dataclasses.replace(options, scale=1.0)), scale=s)

    sized = c.config.signature == "ldsift" and c.config.signature_options.edge is not None
    scale = None if options is None else options.scale
    if sized and scale not in ("same", "fit", None) and float(scale) != 1.0:  # given: no first pass
        return grown(float(scale))
    pm = at(part, options)
    return grown(pm.scale) if sized and scale == "fit" and pm.scale != 1.0 else pm


def retrieve(comparer: "Comparer", part: Mesh, wholes: Sequence[Mesh], labels: Sequence[str], options: Any,
             calibration: Any = None) -> Any:
    """`Comparer.retrieve`."""
    wholes = list(wholes)
    if len(wholes) != len(labels):
        raise ValueError(f"wholes and labels must be of one length, got {len(wholes)} wholes and {len(labels)} labels")
    if calibration is not None and not isinstance(calibration, RetrievalCalibration):
        raise TypeError(f"calibration must be a RetrievalCalibration (Comparer.calibrate_retrieval), got "
                        f"{type(calibration).__name__}")
    if wholes:
        check_part(part, max(wholes, key=lambda w: w.area), RetrievalWarning, "the library's largest whole")
        _warn_size_spread(wholes, labels, stacklevel=4)
    sample = retrieval_sample(part, options)
    rows, weights = (None, None) if sample is None else (sample.indices, sample.counts)
    if (options is None or options.edge == "library") and wholes:
        comparer = at_common_edge(comparer, wholes)
    costs = library_costs(comparer, part, wholes, rows=rows)
    ranking = rank_classes(costs, labels, weights=weights, options=options)
    if calibration is None:
        return _as_calibrated(ranking, comparer.config)
    differ = calibration_differences(calibration, comparer.config, options)
    if differ:
        raise ValueError("calibration was fitted with other settings than this lookup's: " + "; ".join(differ)
                         + ". Fit it again with these (Comparer.calibrate_retrieval)")
    if calibration.library and calibration.library != library_digest(wholes, labels):
        warnings.warn(f"calibration was fitted on another library than these {len(wholes)} wholes (other meshes or "
                      "classes): its probability is that library's. Fit one on this library "
                      "(Comparer.calibrate_retrieval)", RetrievalWarning, stacklevel=3)
    return dataclasses.replace(ranking, calibrated=True, coefficients=calibration.coefficients)


def calibration_differences(calibration: RetrievalCalibration, config: ComparisonConfig, options: Any) -> list[str]:
    """What differs between the settings ``calibration`` was fitted with and a lookup's (its comparer's
    ``config``, its `wpot.maps.retrieval.RetrievalOptions`): empty when it applies."""
    return [f"{what} {mine} (calibrated with {theirs})" for what, mine, theirs in (
        ("options", retrieval_options(options), calibration.options),
        ("signature", signature_key(config), calibration.signature)) if mine != theirs]


def _warn_size_spread(wholes: Sequence[Mesh], labels: Sequence[str], stacklevel: int) -> None:
    """Warn (`RetrievalWarning`) when two wholes of one class differ in size by more than `SIZE_SPREAD`."""
    spread = size_spread(wholes, labels)
    if spread is not None and spread[1] > SIZE_SPREAD:
        warnings.warn(f"the library's wholes of class {spread[0]!r} differ in size by up to {spread[1]:.2f} "
                      "times (square root of area): retrieve reads size, so a part may be taken for another "
                      "class's member of its size. Were the shapes scaled one by one? Bring each class to one "
                      "scale, and the parts with the shapes they come from, or with LD-SIFT describe each mesh at "
                      "its own (RetrievalOptions(edge='own'))",
                      RetrievalWarning, stacklevel=stacklevel)


def signature_key(config: ComparisonConfig) -> str:
    """The signature and its options, as text, less LD-SIFT's edge length (which `Comparer.retrieve` sets from
    each library): what a `wpot.maps.retrieval.RetrievalCalibration` was fitted with."""
    opts = config.signature_options
    if config.signature == "ldsift":
        opts = dataclasses.replace(opts, edge=None)
    return f"{config.signature} {opts!r}"


def calibrate_retrieval(comparer: "Comparer", wholes: Sequence[Mesh], labels: Sequence[str], *, n_parts: int,
                        seed: int, options: Any, record: str | Path | None = None) -> RetrievalCalibration:
    """`Comparer.calibrate_retrieval`: each part of `wpot.maps.retrieval.calibration_parts` ranked by `retrieve`
    among the library less its whole (every lookup at the whole library's edge length, so the library is described
    once), then `wpot.maps.retrieval.calibration_of` on the margins and outcomes. With ``record`` (a file), each
    lookup is saved as it is made and a rerun resumes from them (`wpot.maps.retrieval.CalibrationRecord`)."""
    wholes, labels, options = list(wholes), [str(x) for x in labels], retrieval_options(options)
    parts = calibration_parts(wholes, labels, n_parts, seed=seed)
    _warn_size_spread(wholes, labels, stacklevel=4)
    if options.edge == "library":
        comparer = at_common_edge(comparer, wholes)
    key, library = signature_key(comparer.config), library_digest(wholes, labels)
    done = None if record is None else CalibrationRecord(record, {
        "n_parts": len(parts), "seed": seed, "options": dataclasses.asdict(options),
        "signature": key, "library": library})
    found = {} if done is None else dict(done.done)
    # the first lookup describes the library, with its progress; the others read it from the shared cache, quietly
    quiet = comparer.with_options()
    quiet.progress = as_progress(False)
    lookup = comparer
    bar = comparer.progress.bar(len(parts), "retrieval calibration: parts of the library looked up", "part",
                                initial=len(found))
    try:
        for k, (j, part) in enumerate(parts):
            if k in found:
                continue
            others = [i for i in range(len(wholes)) if i != j]
            with warnings.catch_warnings():  # said once above
                warnings.simplefilter("ignore", RetrievalWarning)
                r = retrieve(lookup, part, [wholes[i] for i in others], [labels[i] for i in others], options)
            lookup = quiet
            found[k] = (r.margin, r.label == labels[j])
            if done is not None:
                done.add(k, *found[k])
            bar.update()
    finally:
        bar.close()
    margins, right = zip(*(found[k] for k in range(len(parts))))
    return calibration_of(margins, right, options, key, library)


def locating_comparer(comparer: "Comparer", whole: Mesh, options: Any) -> "Comparer":
    """The comparer whose signatures `Comparer.locate` reads: ``comparer``, or with ``options.edge == "whole"`` its
    copy at the whole's edge length (`at_common_edge`). ValueError when the whole's edge length is asked of a
    comparer whose signature is not LD-SIFT, on which it would change nothing."""
    if options is None or getattr(options, "edge", None) != "whole":
        return comparer
    if comparer.config.signature != "ldsift":
        raise ValueError(f"LocateOptions(edge='whole') sets LD-SIFT's edge length; this comparer uses "
                         f"signature={comparer.config.signature!r}, on which it would change nothing")
    return at_common_edge(comparer, [whole])


def at_common_edge(comparer: "Comparer", meshes: Sequence[Mesh]) -> "Comparer":
    """``comparer``, or for LD-SIFT with its edge length unset a copy (`Comparer.with_options`, sharing its caches)
    with the edge set to ``meshes``' `wpot.signatures._frames.common_edge`: every mesh it then describes, whatever
    its density, is seen at one scale (what `Comparer.retrieve` does with its library)."""
    if comparer.config.signature != "ldsift" or comparer.config.signature_options.edge is not None:
        return comparer
    return comparer.with_options(ldsift_edge=common_edge(meshes))


def _as_calibrated(ranking: Any, config: ComparisonConfig) -> Any:
    """``ranking`` (a `wpot.maps.retrieval.ClassRanking`), marked as not calibrated unless its costs came from the
    signature its probability was calibrated with: LD-SIFT at its defaults (any common edge length), its thickness
    column at `wpot.maps.retrieval.CALIBRATED_THICKNESS`."""
    opts = config.signature_options
    calibrated = (config.signature == "ldsift"
                  and dataclasses.replace(opts, edge=None) == type(opts)(thickness=CALIBRATED_THICKNESS))
    return ranking if calibrated or not ranking.calibrated else dataclasses.replace(ranking, calibrated=False)


def _derived(base: "Comparer", changes: dict[str, Any]) -> "Comparer":
    """`Comparer.with_options`: a new comparer from ``base`` with ``changes``, sharing what stays valid."""
    own = {"device", "cache_dir", "energies", "signature_state", "memory_limit"}

    unknown = sorted(set(changes) - own - set(base.config.keywords()) - _all_signature_keywords())
    if unknown:
        raise ValueError(f"unknown Comparer options {unknown}; known: {sorted(set(base.config.keywords()) | own)}")
    config = base.config.replace(**{k: v for k, v in changes.items() if k not in own})
    kw = {"device": base.device, "cache_dir": base.cache_dir, "memory_limit": base.memory_limit}
    kw.update({k: v for k, v in changes.items() if k in own})
    if "energies" in kw:
        kw["signature_state"] = None if kw.pop("energies") is None else {"energies": changes["energies"]}
    if "energies" not in changes and "signature_state" not in changes and \
            config.signature == base.config.signature and config.signature_options == base.config.signature_options:
        kw["signature_state"] = base.stage.state()
    new = Comparer.__new__(Comparer)
    same_dir = kw["cache_dir"] == base.cache_dir
    new._setup(config, kw["device"], kw["cache_dir"], kw.get("signature_state"), kw["memory_limit"],
               (base.source.signature_cache, base.source.spectrum_cache) if same_dir else None)
    if new.config.sampler.fps_metric == base.config.sampler.fps_metric:
        new.sampler.share_samples_with(base.sampler)
    new.progress = base.progress
    return new


def library_costs(comparer: "Comparer", part: Mesh, wholes: Sequence[Mesh], *, rows: np.ndarray | None = None
                  ) -> np.ndarray:
    """`Comparer.nearest_costs`: (N, M) float64, each of the part's N vertices' cost to the nearest signature of each
    of the M wholes; with ``rows`` (n,) vertex indices, (n, M) for those vertices only."""
    wholes = list(wholes)
    if not wholes:
        raise ValueError("wholes must hold at least one mesh")
    if comparer.stage.needs_fit and not comparer.stage.fitted:
        raise ValueError(f"{comparer.signature} needs fitting: call fit(wholes) first")
    with comparer.progress.stage(f"{comparer.stage.title} signatures of the part ({part.n_vertices} vertices)"):
        sig = comparer.signatures(part)
    if rows is not None:
        sig = sig[rows]

    costs_to = NearestCosts(sig, metric=comparer.stage.metric, device=comparer.device)

    def costs(w: Mesh) -> np.ndarray:
        return costs_to(comparer.signatures(w))[1]

    if len(wholes) == 1:
        return costs(wholes[0])[:, None]
    # a library: a step per whole (its signatures, computed or read from the cache, and its costs)
    bar = comparer.progress.bar(len(wholes), f"{comparer.stage.title} signatures of the library", "shape")
    cols = []
    try:
        for w in wholes:
            cols.append(costs(w))
            bar.update()
    finally:
        bar.close()
    return np.column_stack(cols)


def _matched_pairs(res: Any, m1: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and values of the plan entries above ``ratio · m1`` (row-major order), from the dense plan
    or, when it was not formed, from each row's top entries (an entry above ratio · m1 with ratio > 1/(top k)
    is always among them)."""
    if res.plan is not None:
        plan = np.asarray(res.plan, dtype=np.float64)
        ii, jj = np.nonzero(plan > ratio * m1[:, None])
        return ii, jj, plan[ii, jj]
    top = res.plan_top.tocoo()
    keep = top.data > ratio * m1[top.row]
    ii, jj, vv = top.row[keep].astype(np.int64), top.col[keep].astype(np.int64), top.data[keep]
    order = np.lexsort((jj, ii))
    return ii[order], jj[order], vv[order]


def _reference(masses: np.ndarray | None, n: int, total: float) -> np.ndarray:
    """(n,) reference masses (uniform when ``masses`` is None) scaled to sum to ``total``."""
    m = np.ones(n) if masses is None else np.asarray(masses, dtype=np.float64)
    return m * (total / m.sum())


def _assemble(res, sub_a, sub_b, mesh_a, mesh_b, distance, self_e, hist, config: ComparisonConfig,
              masses: tuple[np.ndarray | None, np.ndarray | None]) -> Comparison:
    m1 = np.asarray(res.mass1, dtype=np.float64)
    m2 = np.asarray(res.mass2, dtype=np.float64)
    rows_best = np.asarray(res.argmax, dtype=np.int64)
    total = float(m1.sum())
    best = np.asarray(res.plan_top.max(axis=1).toarray()).ravel()  # each row's largest entry, G(k, j*)
    conf = np.minimum(best / _reference(masses[0], len(m1), total), 1.0)
    recv = m2 / _reference(masses[1], len(m2), total)
    n_b = len(m2)
    ia = np.arange(len(m1)) if sub_a is None else sub_a.indices
    jb = np.arange(n_b) if sub_b is None else sub_b.indices
    corr_sampled = jb[rows_best]
    correspondence = corr_sampled if sub_a is None else sub_a.extend(corr_sampled)
    ii, jj, weight = _matched_pairs(res, m1, config.match_ratio)
    matched = np.stack([ia[ii], jb[jj]], axis=1).astype(np.int64)
    registration = None
    if len(matched) >= 3:

        # balanced transport matches the whole shapes: their size ratio is the scale. With partial transport the
        # matched regions come from the received masses, too loosely for a size ratio (far off on the
        # quickstart's part; the docs' Results page), so the scale is fitted there
        scale = area_scale(mesh_a, mesh_b) if config.transport == "balanced" else None
        try:
            # robust: the wrong matches (pairs pointing across the shape) would pull a least-squares fit in
            registration = fit_similarity_robust(mesh_a.vertices[matched[:, 0]], mesh_b.vertices[matched[:, 1]],
                                                 weight, scale=scale).with_target(mesh_b)
        except ValueError:
            registration = None  # degenerate (collinear) matches; documented as None
    return Comparison(
        distance=float(distance),
        correspondence=correspondence.astype(np.int64),
        matched=matched,
        matched_weight=weight,
        mass1=m1,
        mass2=m2,
        registration=registration,
        result=res,
        signature=config.signature,
        transport=config.transport,
        self_energies=self_e,
        history=hist,
        sample_a=sub_a,
        sample_b=sub_b,
        confidence=conf if sub_a is None else sub_a.extend(conf),
        received=recv if sub_b is None else sub_b.extend(recv),
    )


def _spectrum_cache(cache_dir: Any) -> Any:
    """The spectrum cache for a `Comparer`'s ``cache_dir``: the process-wide one (``$WPOT_CACHE_DIR``) for None,
    else one under that folder (memory only for False), as for the signatures."""
    if cache_dir is None:
        return True

    return Cache("spectrum", max_entries=spectrum_cache.max_entries, max_bytes=spectrum_cache.max_bytes, cache_dir=cache_dir)


def _resolve_device(device: str | None) -> str:

    return str(resolve_device(device))


def compare(mesh_a: Mesh, mesh_b: Mesh, *, config: ComparisonConfig | None = None, device: str | None = None,
            progress: Any = False, **options: Any) -> Comparison:
    """Compare two meshes by statistical-physics optimal transport of their vertex signatures.

    One-shot form of `Comparer`. For many pairs, build one `Comparer`, so that signatures are computed once
    per shape and every shape shares one fitted state (WKS's energy grid).

    Parameters
    ----------
    mesh_a, mesh_b : the two shapes (`wpot.Mesh`, e.g. from `wpot.load_mesh`); the correspondence maps A to B
    signature : one of the registered signatures (`wpot.signatures.signature_names()`): "wks" (default; wave
        kernel, intrinsic), "ldsift" (depth images + SIFT, extrinsic) or "hks" (heat kernel, intrinsic)
    transport : one of `wpot.config.TRANSPORTS`: "balanced" (default; all mass matched) or "partial"
        (a shape against a part of another)
    max_vertices, mass_penalty, solver_options, the signature's options (``n_eigen``, ...), ... : every other
        keyword of `Comparer`, which describes them all; or ``config``, a `wpot.ComparisonConfig`
    device : Warp device ("cpu", "cuda", "cuda:0"); None is Warp's default
    progress : ``True`` reports each step with its time (`wpot.progress`)

    Returns
    -------
    Comparison : distance (U or SU, Eq. 27), correspondence (N_A,), matched pairs, masses, registration,
        and the solver's `OTResult`.
    """
    return Comparer(config, device=device, progress=progress, **options).compare(mesh_a, mesh_b)
