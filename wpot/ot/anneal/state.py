"""The annealing's state records, shared by the Newton engine (`wpot.ot.anneal.newton`) and its host and
device Newton loops (`wpot.ot.anneal.host`, `wpot.ot.anneal.resident`): a point's values, the dual sums, a dual
snapshot and the engine's timers and work counts."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp


@dataclass
class Timers:
    """Seconds spent per phase of one `Engine`'s solve and its work counts (``as_dict`` is what benchmarks print).

    n_factor counts preconditioner builds (SuperLU factorizations; in the device loop, full FSAI builds),
    n_refit the device loop's refits on the last pattern and n_build_sync the synchronisations inside Warp's
    set-up of its full builds (`wpot.ot.anneal.resident.BUILD_SYNCS` each);
    n_newton counts Newton steps (`Engine.newton`'s and the interior-point iterations: `OTResult.n_newton`);
    n_d2h / n_h2d count the device-to-host reads (`Engine.to_host`) and host-to-device writes
    (`Engine.to_device`) of device arrays, the transfers (and, for reads, synchronisations) a GPU makes.
    """

    eval: float = 0.0
    prep: float = 0.0
    precond: float = 0.0
    cg: float = 0.0
    direct: float = 0.0
    other: float = 0.0
    n_eval: int = 0
    n_matvec: int = 0
    n_factor: int = 0
    n_refit: int = 0
    n_build_sync: int = 0
    n_free: int = 0
    n_newton: int = 0
    n_d2h: int = 0
    n_h2d: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Point:
    """Values at one (lam, y): the marginal residuals g1 (n_r,), g2 (n_c,) and the scalar sums.

    From `Engine.evaluate`, g1 and g2 are host copies in the host loop and None in the device loop (they
    stay on the device). As the right-hand side of `Engine.direction` they may be numpy arrays, Warp arrays
    on the solve device, or None for those of the last evaluation."""

    g1: np.ndarray | wp.array | None
    g2: np.ndarray | wp.array | None
    merit: float
    residual: float
    u: float = math.nan
    f_sum: float = math.nan
    xphi: float = math.nan
    x: float = 0.0
    sums: DualSums | None = None  # set by `Engine.free_pass` (host loop) or `Engine.free_values` (device loop)


@dataclass(frozen=True)
class DualSums:
    """Sums over the duals and marginals at a solved point (normalized units), for the free energy (Eq. 12 /
    23) and the partial penalty: lam . m_r, y . m_c, sum b lam^2, sum a mu^2 with mu = y - x, and
    penalty = sum m1^2 / (2 b) + sum m2^2 / (2 a) with m the marginals (0 for balanced transport)."""

    lam_m: float
    y_m: float
    b_lam2: float
    a_mu2: float
    penalty: float


@dataclass(frozen=True)
class DualSnapshot:
    """A copy of the duals (lam, y), each a (hi, lo) pair of float64 device arrays (see `Engine.snapshot`)."""

    lam: tuple[wp.array, wp.array]
    y: tuple[wp.array, wp.array]
