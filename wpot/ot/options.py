"""The options of the OT solvers: `SolverOptions` (what a caller sets, in the cost's units) and
`EngineOptions` (the same, checked against a problem and converted to the normalized units the engine
works in)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from wpot._warp import available_memory
from wpot._validate import boolean, integer_at_least, nonnegative_finite, one_of, positive_finite
from wpot.ot.problem import FeatureCost
from wpot.ot.anneal.schedule import DEFAULT_BETA0_PER_N1N2, DEFAULT_BETA_MAX_PER_N1N2, DEFAULT_STEP

__all__ = ["SolverOptions", "EngineOptions", "DEVICE_PRECONDITIONERS", "LINEAR_SOLVERS", "NEWTON_LOOPS"]

#: the linear solvers of the Newton systems (see `SolverOptions.linear_solver`)
LINEAR_SOLVERS = ("cg", "direct")
#: where the Newton steps' vectors live (see `SolverOptions.newton_loop`)
NEWTON_LOOPS = ("host", "device")
#: the device loop's preconditioners (see `SolverOptions.device_preconditioner`)
DEVICE_PRECONDITIONERS = ("multilevel", "fsai")
#: default relative change of U that stops the annealing (Algorithm 1). Since U(beta) - U* ~ N1 N2 /
#: beta_n, the change over one step of 10 is ~9x the remaining gap: tol = 1e-6 leaves a gap ~1e-7 (the gaps to
#: ot.emd on the tests' and the benchmarks' problems: the docs' Results page).
DEFAULT_TOL = 1e-6
#: annealing also stops when |Delta U| <= atol * max C (needed when U* = 0, e.g. a shape against itself,
#: where the relative change never falls)
DEFAULT_ATOL = 1e-10
#: weights kept per row and per column of W for the sparse preconditioner: 4 needs about as many CG iterations
#: as 8 with half the LU fill, 2 needs more (benchmarks/ot_speed.py's problem; the docs' Results page)
DEFAULT_TOPK = 4
#: Newton iterations allowed per beta: the transition from a spread-out plan to a near-permutation takes
#: the most, a few tens of steps where the other betas take a few (the docs' Results page)
DEFAULT_MAX_NEWTON = 100
#: default number of plan entries kept per row in `OTResult.plan_top`
DEFAULT_PLAN_TOPK = 8


@dataclass(frozen=True, kw_only=True)
class SolverOptions:
    """Options of the OT solvers (`wpot.ot.make_solver`, `solve_balanced`, `solve_partial`), keyword-only,
    validated on construction (ValueError naming the option and the value). Betas are in the cost's units
    (beta * C is dimensionless); the solver converts them with the problem's scale s = max C.

    Annealing (Algorithm 1)
    -----------------------
    beta0, beta_max : first and largest beta. Defaults (None): beta0 = N1 N2 / s and beta_max =
        1e12 N1 N2 / s. The gap U(beta) - U* is ~ N1 N2 / beta, so these defaults are free of the cost's
        scale and of the problem's size; the plan at beta0 is nearly uniform.
    step : beta multiplier between annealing steps, a finite number > 1 (default 10: with the 1/beta
        extrapolation of the duals it needs the fewest Newton steps in all; see
        `wpot.ot.anneal.schedule.DEFAULT_STEP`). A step whose Newton solve fails is split in log beta.
    tol, atol : stop when |dU| <= tol |U_prev| or |dU| <= atol s (``atol`` serves U* = 0, e.g. a shape
        against itself). Default tol = 1e-6 leaves a gap to the exact optimum of ~1e-7 relative.
    max_iter : maximum number of betas (default 100).
    extrapolate : warm-start each beta from the previous one's duals extrapolated linearly in 1/beta along
        the tangent d(lam, mu)/d(log beta) (default True; without it every beta starts with a residual of
        ~1 - 1/step).

    Newton's method at each beta (Eq. 14-16 / 25-26)
    ------------------------------------------------
    max_newton : Newton iterations per beta (default 100: the beta where the plan turns from spread out
        to a near-permutation takes the most).
    newton_tol : stopping residual, sum of |marginal errors| / (2 total mass) (default 1e-11).
    linear_solver : "cg" (default: PCG on the Schur complement with a sparse preconditioner built from the
        ``topk`` largest weights per row and column of W, factorized by SuperLU and reused across Newton
        steps and betas until CG slows down by more than 2 iterations) or "direct" (dense Cholesky of the
        Schur complement, O(N^3) per Newton step and an N x N array; for comparison, stored cost only).
    cg_rtol, cg_max_iter : CG relative tolerance and iteration cap per Newton step (defaults 1e-3, 1000).
    topk : weights per row and column of W in the preconditioner (default 4: as few CG iterations as 8
        with half the factorization's fill).
    newton_loop : where the Newton steps run (`wpot.ot.anneal.resident`). "device": every vector stays on the
        device, CG and its preconditioner (of the same sparse Schur approximation, built on the device; see
        ``device_preconditioner``) are kernels, and the host reads one small array per trial point (about one
        synchronisation per Newton step). "host": CG's vectors and the SuperLU preconditioner on the host (a
        transfer each way per CG iteration; fewer CG iterations, which is what counts on the CPU). None
        (default): "device" on a GPU, "host" on the CPU. "device" needs ``linear_solver="cg"``.
    device_preconditioner : the device loop's preconditioner of the sparse Schur approximation P. None
        (default) or "multilevel": a V-cycle over aggregates of P's unknowns with FSAI smoothing on P
        (`wpot.ot.anneal.multilevel`; a full build reads P once). "fsai": FSAI alone (local, so CG needs more
        iterations at high beta, where P's inverse couples far-apart unknowns). Only the device loop has
        one: setting it with ``newton_loop="host"`` or ``linear_solver="direct"`` is an error.
    matvec_lanes : threads per row of the strided kernels that run the passes over W (the Schur matvec,
        the evaluation pass). None (default): the device's choice, strided lanes
        (`wpot.ot.kernels.MATVEC_LANES`) on GPUs, where neighbouring threads then read neighbouring
        entries, and one thread per row (0) on the CPU. 0 forces the row kernels, n >= 1 the strided
        kernels with n lanes on any device (both orders give the same sums up to rounding).

    Output
    ------
    dense_plan : form ``OTResult.plan`` (N1, N2)? None (default): with a stored cost only; True: also with
        a `FeatureCost` (ValueError naming the size when it does not fit in the memory available); False:
        never (``plan_top`` and ``argmax`` are always returned).
    plan_topk : entries per row kept in ``OTResult.plan_top`` (default 8).
    verbose : 0 (default) silent; 1 prints one line per beta and the timers; 2 also every Newton step.
    """

    beta0: float | None = None
    beta_max: float | None = None
    step: float = DEFAULT_STEP
    tol: float = DEFAULT_TOL
    atol: float = DEFAULT_ATOL
    max_iter: int = 100
    max_newton: int = DEFAULT_MAX_NEWTON
    newton_tol: float = 1e-11
    linear_solver: str = "cg"
    cg_rtol: float = 1e-3
    cg_max_iter: int = 1000
    topk: int = DEFAULT_TOPK
    extrapolate: bool = True
    dense_plan: bool | None = None
    plan_topk: int = DEFAULT_PLAN_TOPK
    matvec_lanes: int | None = None
    newton_loop: str | None = None
    device_preconditioner: str | None = None
    verbose: int = 0

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        if self.beta0 is not None:
            put("beta0", positive_finite("beta0", self.beta0))
        if self.beta_max is not None:
            bm = positive_finite("beta_max", self.beta_max)
            put("beta_max", bm)
            if self.beta0 is not None and not (bm >= self.beta0):
                raise ValueError(f"beta_max must be >= beta0, got beta_max={self.beta_max!r}, beta0={self.beta0!r}")
        step = _number(self.step)
        if step is None or not (math.isfinite(step) and step > 1):
            raise ValueError(f"step must be a finite number > 1, got {self.step!r}")
        put("step", step)
        for name in ("tol", "atol", "newton_tol", "cg_rtol"):
            put(name, nonnegative_finite(name, getattr(self, name)))
        for name in ("max_iter", "max_newton", "cg_max_iter", "topk", "plan_topk"):
            put(name, integer_at_least(name, getattr(self, name), 1))
        one_of("linear_solver", self.linear_solver, LINEAR_SOLVERS)
        if self.newton_loop is not None:
            one_of("newton_loop", self.newton_loop, NEWTON_LOOPS)
            if self.newton_loop == "device" and self.linear_solver == "direct":
                raise ValueError("newton_loop='device' needs linear_solver='cg' (the dense direct solve runs on "
                                 "the host); use newton_loop='host' or None with linear_solver='direct'")
        if self.device_preconditioner is not None:
            one_of("device_preconditioner", self.device_preconditioner, DEVICE_PRECONDITIONERS)
            if self.newton_loop == "host" or self.linear_solver == "direct":
                raise ValueError("device_preconditioner is the device loop's; the host loop (newton_loop='host' "
                                 "or linear_solver='direct') factorizes its preconditioner with SuperLU: leave "
                                 "device_preconditioner=None there")
        put("extrapolate", boolean("extrapolate", self.extrapolate))
        if self.dense_plan is not None:
            if not isinstance(self.dense_plan, (bool, np.bool_)):
                raise ValueError(f"dense_plan must be None, True or False, got {self.dense_plan!r}")
            put("dense_plan", bool(self.dense_plan))
        if self.matvec_lanes is not None:
            put("matvec_lanes", integer_at_least("matvec_lanes", self.matvec_lanes, 0))
        if isinstance(self.verbose, (bool, np.bool_)):
            put("verbose", int(self.verbose))
        else:
            put("verbose", integer_at_least("verbose", self.verbose, 0))

    # ------------------------------------------------------------------ copies and dictionaries
    def replace(self, **changes: Any) -> SolverOptions:
        """A copy with ``changes`` applied (validated); TypeError naming an unknown option."""
        unknown = sorted(set(changes) - set(self.names()))
        if unknown:
            raise TypeError(f"unknown solver option(s) {', '.join(map(repr, unknown))}; the options are "
                            f"{', '.join(self.names())}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every option by name (plain Python values: JSON-able)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SolverOptions:
        """Options from a mapping of some or all of them (the rest default); ValueError naming unknown keys."""
        if not isinstance(d, Mapping):
            raise ValueError(f"solver options must be a mapping of option names to values, got {type(d).__name__}")
        unknown = sorted(set(d) - set(cls.names()), key=str)
        if unknown:
            raise ValueError(f"unknown solver option(s) {', '.join(map(repr, unknown))}; the options are "
                             f"{', '.join(cls.names())}")
        return cls(**dict(d))

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The option names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    # ------------------------------------------------------------------ the engine's view
    def normalized(self, n1: int, n2: int, scale: float) -> EngineOptions:
        """The options of an ``n1 x n2`` problem whose cost the solver divides by ``scale`` (max C): betas
        converted to normalized units (beta_n = beta * scale; defaults from N1 N2) and checked there."""
        nn = float(n1) * float(n2)
        b0 = DEFAULT_BETA0_PER_N1N2 * nn if self.beta0 is None else float(self.beta0) * scale
        bm = DEFAULT_BETA_MAX_PER_N1N2 * nn if self.beta_max is None else float(self.beta_max) * scale
        if not (math.isfinite(b0) and b0 > 0):
            raise ValueError(f"beta0 must be a positive finite number, got {self.beta0!r}")
        if not (bm >= b0):
            raise ValueError(f"beta_max must be >= beta0, got beta_max={self.beta_max!r}, beta0={self.beta0!r}")
        return EngineOptions(beta0=b0, beta_max=bm, step=self.step, tol=self.tol, atol=self.atol,
                             max_iter=self.max_iter, max_newton=self.max_newton, newton_tol=self.newton_tol,
                             linear_solver=self.linear_solver, cg_rtol=self.cg_rtol, cg_max_iter=self.cg_max_iter,
                             topk=self.topk, extrapolate=self.extrapolate, matvec_lanes=self.matvec_lanes,
                             newton_loop=self.newton_loop,
                             device_preconditioner=self.device_preconditioner or DEVICE_PRECONDITIONERS[0],
                             verbose=self.verbose)


def _number(value: Any) -> float | None:
    if isinstance(value, (bool, np.bool_, str)):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


@dataclass(frozen=True, kw_only=True)
class EngineOptions:
    """`SolverOptions` for one problem, as the engine (`wpot.ot.anneal.newton.Engine`) and the annealing loop
    (`wpot.ot.anneal.loop`) read them: betas in normalized units (the cost divided by its max), checked.
    Built by `SolverOptions.normalized`; ``atol`` is a fraction of the cost scale in both."""

    beta0: float
    beta_max: float
    step: float
    tol: float
    atol: float
    max_iter: int
    max_newton: int
    newton_tol: float
    linear_solver: str
    cg_rtol: float
    cg_max_iter: int
    topk: int
    extrapolate: bool
    matvec_lanes: int | None
    newton_loop: str | None
    device_preconditioner: str
    verbose: int


def check_mode(C, options: SolverOptions, device: str) -> bool:
    """The options that depend on the cost's mode (``C`` as the caller passed it: checked before any pass
    over it); returns whether to form the dense plan.

    ``linear_solver="direct"`` needs the stored cost. ``dense_plan`` None: the dense plan in stored mode
    only; True: also in matrix-free mode, refused with a ValueError naming the size when the (N1, N2) float64
    array does not fit in the memory available (on the device and on the host, where it is returned);
    False: never.
    """
    lazy = isinstance(C, FeatureCost)
    if lazy and options.linear_solver == "direct":
        raise ValueError("linear_solver='direct' is not available with a FeatureCost (matrix-free mode): it "
                         "forms the dense N1 x N2 weight matrix the matrix-free mode exists to avoid; use "
                         "linear_solver='cg'")
    if options.dense_plan is None:
        return not lazy
    if options.dense_plan and lazy:
        n1, n2 = C.shape
        need = 8.0 * n1 * n2
        avail = available_memory(device, host_too=True)
        if need > avail:
            raise ValueError(
                f"dense_plan=True needs an (N1, N2) = ({n1}, {n2}) float64 array of {need / 2**30:.2f} "
                f"GiB, more than the {avail / 2**30:.2f} GiB available on {device}; use the result's plan_top "
                "and argmax instead")
    return options.dense_plan
