"""Input validation and the internal (normalized, oriented) form of an OT problem."""
from __future__ import annotations

import math
from dataclasses import KW_ONLY, dataclass
from typing import Any

import numpy as np
import warp as wp

from wpot._validate import positive_finite
from wpot._warp import launch_rows, resolve_device as _resolve_device
from wpot.cost import METRIC_CODES, cost_matrix, prepare_signatures
from wpot.ot import kernels as K
from wpot.ot.gram import gram_blocks


def resolve_device(device) -> str:
    """``None`` -> Warp's default device; otherwise the named device (checked once, `wpot._warp`)."""
    return str(_resolve_device(device))


class FeatureCost:
    """A cost matrix given by two signature arrays and a metric, for the matrix-free mode of the solvers:
    ``C(i, j) = metric(X[i], Y[j])`` is recomputed inside the solver's kernels and never stored, so memory
    is O((N1 + N2) D) instead of O(N1 N2). Pass it wherever a cost matrix is accepted
    (`solve_balanced`, `solve_partial`); results agree with passing ``cost_matrix(X, Y, metric=metric)``
    (the same iterates, equal to the last bit). The price is time: every pass over C or over the Hessian
    weights recomputes the D-term sums (a CG matvec, two of them), so on the single-threaded CPU backend passes
    and matvecs are one to two orders of magnitude slower than in stored mode. The exact solver's passes over an
    ``"l2"`` cost on the CPU take the inner products from BLAS instead (`wpot.ot.gram`, the same results): there
    the mode costs little more than the stored one. Timings: the docs' Results page. The mode is for GPUs and
    for sizes where C does not fit in memory.

    Parameters
    ----------
    X : (N1, D), Y : (N2, D) signatures (NumPy array-like or float64 ``wp.array`` on ``device``), finite;
        nonnegative for ``"wks"``. Validated (and copied to ``device`` as float64) like `wpot.cost.cost_matrix`.
    metric : ``"wks"`` (paper Eq. 29, sum_d |(a - b) / (a + b)|, 0/0 terms count 0; the default, as in
        `wpot.cost.cost_matrix`), ``"l2"`` (Euclidean) or ``"l1"``.
    device : Warp device the arrays live on (None: Warp's default); the solve must use the same device.

    Immutable: ``X``, ``Y`` ((N, D) float64 wp.arrays), ``metric``, ``device`` (str), ``shape`` (N1, N2).
    """

    __slots__ = ("X", "Y", "metric", "device")

    def __init__(self, X, Y, metric: str = "wks", *, device=None):
        dev = _resolve_device(device)
        a, b = prepare_signatures(X, Y, metric, dev, names=("X", "Y"))
        object.__setattr__(self, "X", a)
        object.__setattr__(self, "Y", b)
        object.__setattr__(self, "metric", metric)
        object.__setattr__(self, "device", str(dev))

    def __setattr__(self, name, value):
        raise AttributeError(f"FeatureCost is immutable (cannot set {name!r})")

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.X.shape[0]), int(self.Y.shape[0])

    def dense(self) -> np.ndarray:
        """The (N1, N2) float64 cost matrix (`wpot.cost.cost_matrix`), where it fits in memory."""
        return cost_matrix(self.X, self.Y, metric=self.metric, device=self.device)

    def __repr__(self) -> str:
        n1, n2 = self.shape
        return f"FeatureCost(N1={n1}, N2={n2}, D={self.X.shape[1]}, metric={self.metric!r}, device={self.device!r})"


@dataclass(frozen=True)
class TransportProblem:
    """One OT problem, as the caller states it (validated by the solver, except ``mass_penalty``).

    cost : (N1, N2) cost matrix (array-like, finite, >= 0; or a 2-D float64 ``wp.array``, used without a
        copy when on the solve device), or a `FeatureCost` (the matrix-free mode: C recomputed inside the
        kernels, memory O((N1 + N2) D); the same results).
    a, b : (N1,), (N2,) positive masses (None: uniform). Balanced: equal sums; the plan is computed for
        masses normalized to sum 1 and multiplied back by the total. Partial: the reference measures
        rho1, rho2 (normalized to sum 1).
    mass_penalty : None for balanced transport (Eq. 6-7); a positive finite number for partial transport
        with the Pearson chi^2 penalty alpha_i = mass_penalty / rho_i^2 (Eq. 17; 1 is the paper's).
    device : Warp device of the solve (None: Warp's default).
    """

    cost: Any
    a: Any = None
    b: Any = None
    _: KW_ONLY
    mass_penalty: float | None = None
    device: str | None = None

    def __post_init__(self):
        if self.mass_penalty is not None:
            object.__setattr__(self, "mass_penalty", positive_finite("mass_penalty", self.mass_penalty))

    @property
    def partial(self) -> bool:
        """True for partial transport (a mass penalty is given)."""
        return self.mass_penalty is not None

    @property
    def matrix_free(self) -> bool:
        """True when the cost is a `FeatureCost` (no N1 x N2 array is stored)."""
        return isinstance(self.cost, FeatureCost)

    @property
    def shape(self) -> tuple[int, ...]:
        """(N1, N2), the cost's shape (as given: the solver checks that it is 2-D)."""
        if isinstance(self.cost, (FeatureCost, wp.array)):
            return tuple(int(n) for n in self.cost.shape)
        return tuple(int(n) for n in np.shape(self.cost))

    def __repr__(self) -> str:
        kind = "balanced" if self.mass_penalty is None else f"partial, mass_penalty={self.mass_penalty!r}"
        mode = "matrix-free" if self.matrix_free else "stored"
        return f"TransportProblem({'x'.join(map(str, self.shape))}, {kind}, {mode} cost, device={self.device!r})"


@dataclass(frozen=True)
class CostInput:
    """The validated cost and its scale max C (the solver works on C / max C: results are then invariant to
    a scaling of C). Stored mode: ``C`` a 2-D float64 wp.array on the solve device (the caller's, never
    copied when it already is one). Matrix-free mode: ``C`` is None and ``features`` the `FeatureCost`."""

    C: wp.array | None
    n1: int
    n2: int
    scale: float
    c_max: float
    features: FeatureCost | None = None

    @property
    def lazy(self) -> bool:
        """True in matrix-free mode (no N1 x N2 array anywhere)."""
        return self.features is not None


def _prepare_features(fc: FeatureCost, device: str, *, gram: bool | None = None) -> CostInput:
    """Matrix-free cost: check the device and find max C by a Warp pass over the rows (nothing stored); for a
    Euclidean cost on the CPU, through BLAS (`wpot.ot.gram`, the same value; ``gram`` as in
    `wpot.ot.gram.gram_blocks`)."""
    if fc.device != device:
        raise ValueError(f"FeatureCost is on device {fc.device}, expected {device} (pass device= to one of them)")
    n1, n2 = fc.shape
    src = K.LazyCost()
    src.A, src.B, src.metric, src.inv_scale = fc.X, fc.Y, METRIC_CODES[fc.metric], wp.float64(1.0)
    blocks = gram_blocks(fc, device, gram)
    if blocks is not None:
        cmax = float(blocks.row_max(src).max())
    else:
        rmax = wp.zeros(n1, dtype=wp.float64, device=device)

        def rows(lo: int, hi: int) -> None:
            part = K.LazyCost()
            part.A, part.B, part.metric, part.inv_scale = fc.X[lo:hi], fc.Y, src.metric, src.inv_scale
            wp.launch(K.feature_cost_max, dim=hi - lo, inputs=[part, n2, rmax[lo:hi]], device=device)

        launch_rows(rows, n1, device, cols=n2)
        cmax = float(rmax.numpy().max())
    if not math.isfinite(cmax):
        raise ValueError(f"the {fc.metric!r} cost of the signatures overflows (max C = {cmax}); rescale them")
    return CostInput(None, n1, n2, 1.0 if cmax <= 0 else cmax, cmax, fc)


def prepare_cost(C, device: str) -> CostInput:
    """Validate C ((N1, N2), finite, >= 0) and bring it to ``device`` as float64 (no copy if it already is);
    a `FeatureCost` gives the matrix-free mode."""
    if isinstance(C, FeatureCost):
        return _prepare_features(C, device)
    if isinstance(C, wp.array):
        if C.ndim != 2:
            raise ValueError(f"cost matrix must be 2-D (N1, N2), got a wp.array of shape {C.shape}")
        if C.dtype != wp.float64:
            raise ValueError(f"cost matrix wp.array must be float64, got {wp.types.type_repr(C.dtype)}")
        if str(C.device) != device:
            raise ValueError(f"cost matrix is on device {C.device}, expected {device} (pass device=)")
        if not C.is_contiguous:
            raise ValueError("cost matrix wp.array must be contiguous")
        Cw = C
    else:
        try:
            Cn = np.asarray(C, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"cost matrix must be a numeric (N1, N2) array, got {type(C).__name__}") from exc
        if Cn.ndim != 2:
            raise ValueError(f"cost matrix must be 2-D (N1, N2), got shape {Cn.shape}")
        # on the CPU the solver reads the caller's array in place (it never writes C): no second N1 x N2 copy
        Cw = wp.array(np.ascontiguousarray(Cn), dtype=wp.float64, device=device, copy=not device.startswith("cpu"))
    n1, n2 = int(Cw.shape[0]), int(Cw.shape[1])
    if n1 == 0 or n2 == 0:
        raise ValueError(f"cost matrix is empty, got shape {(n1, n2)}")
    rmin = wp.zeros(n1, dtype=wp.float64, device=device)
    rmax = wp.zeros(n1, dtype=wp.float64, device=device)
    rbad = wp.zeros(n1, dtype=wp.int32, device=device)
    wp.launch(K.cost_stats, dim=n1, inputs=[Cw, n2, rmin, rmax, rbad], device=device)
    nbad = int(rbad.numpy().sum())
    if nbad:
        raise ValueError(f"cost matrix has {nbad} non-finite (NaN or inf) entries")
    cmin, cmax = float(rmin.numpy().min()), float(rmax.numpy().max())
    if cmin < 0:
        raise ValueError(f"cost matrix must be non-negative, got min(C) = {cmin}")
    scale = 1.0 if cmax <= 0 else cmax
    return CostInput(Cw, n1, n2, scale, cmax)


def prepare_masses(m, n: int, name: str, default_uniform: bool = True) -> np.ndarray:
    """(n,) float64 strictly positive finite masses (uniform 1/n when ``m`` is None)."""
    if m is None:
        return np.full(n, 1.0 / n)
    if isinstance(m, wp.array):
        m = m.numpy()
    a = np.asarray(m, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    if a.shape[0] != n:
        raise ValueError(f"{name} has length {a.shape[0]}, but the cost matrix needs {n}")
    if a.size == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite entries: {a[~np.isfinite(a)][:5]}")
    if np.any(a < 0):
        raise ValueError(f"{name} has negative entries: {a[a < 0][:5]}")
    if np.any(a == 0):
        raise ValueError(
            f"{name} has {int(np.sum(a == 0))} zero entries (of {n}); remove those points from the problem"
        )
    return a


def check_balanced(a: np.ndarray, b: np.ndarray, rtol: float = 1e-9) -> float:
    """The common total mass of a and b; ValueError when the sums differ (relative rtol)."""
    sa, sb = float(a.sum()), float(b.sum())
    if abs(sa - sb) > rtol * max(sa, sb):
        raise ValueError(f"balanced OT needs equal total masses, got sum(a) = {sa!r} and sum(b) = {sb!r}")
    return 0.5 * (sa + sb)


@dataclass
class Internal:
    """The oriented, normalized problem the engine solves.

    Rows (size n_r >= n_c) are eliminated in the Schur complement; ``trans`` says whether the rows are
    the user's columns. Costs are C' = C / scale. Balanced: fixed masses m_r, m_c (sum 1), b = a = 0.
    Partial: m = 0, b_r = 1/(2 alpha_r'), a_c = 1/(2 alpha_c') with alpha' = alpha / scale.
    """

    cost: CostInput
    trans: int
    n_r: int
    n_c: int
    m_r: np.ndarray
    m_c: np.ndarray
    b_r: np.ndarray
    a_c: np.ndarray
    partial: bool
    device: str

    @property
    def scale(self) -> float:
        return self.cost.scale


def orient(cost: CostInput, m1, m2, b1, a2, partial: bool, device: str) -> Internal:
    """Put the larger side first (it is eliminated: each of its points tends to a single partner)."""
    trans = 1 if cost.n1 < cost.n2 else 0
    if trans:
        return Internal(cost, 1, cost.n2, cost.n1, m2, m1, a2, b1, partial, device)
    return Internal(cost, 0, cost.n1, cost.n2, m1, m2, b1, a2, partial, device)
