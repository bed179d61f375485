"""Laplace–Beltrami operator of a triangle mesh and its smallest eigenpairs (paper §3.2).

Conventions
-----------
* ``W`` is the cotangent **stiffness** matrix, positive semidefinite:
  ``W[i, j] = -(cot α_ij + cot β_ij) / 2`` for an edge (i, j) (one cotangent on a boundary edge, which is
  the natural Neumann condition), ``W[i, i] = -Σ_j W[i, j]``. So every row sums to zero and
  ``xᵀ W x = ½ Σ_edges w_ij (x_i − x_j)² ≥ 0``. It is the *negative* of libigl's ``cotmatrix`` (which is
  negative semidefinite).
* ``M`` is the diagonal (lumped) Voronoi mass matrix of libigl (mixed Voronoi areas, Meyer et al. 2003),
  whose diagonal sums to the surface area.
* The eigenproblem is ``W φ = λ M φ`` (``L = M⁻¹W``, paper §3.2), eigenvalues ``0 = λ_0 ≤ λ_1 ≤ …``, and
  eigenvectors M-orthonormal: ``Φᵀ M Φ = I``.
* `eigenpairs` works on the **area-normalized** mesh (total area 1), so eigenvalues of different shapes
  are comparable: ``λ(normalized) = area · λ(original)``. ``W`` is scale invariant, so only ``M`` changes.
  `Spectrum.rescaled` gives the spectrum of the mesh at its own size (what WKS uses by default), exactly.

Solvers (chosen by `choose_solver`, always reported in `Spectrum.solver`; never swapped silently)
------------------------------------------------------------------------------------------------
* ``"dense"``: ``scipy.linalg.eigh`` of ``A = M^{-1/2} W M^{-1/2}`` with ``subset_by_index`` and
  ``driver="evr"``, then ``φ = M^{-1/2} v`` (paper §3.2). Cost ~ N³, nearly independent of k.
* ``"lanczos"``: ARPACK (``scipy.sparse.linalg.eigsh``) in shift-invert mode around a small negative
  shift σ, with the sparse LU factorization of ``W − σM`` computed once and reused (`LaplaceBeltrami`
  keeps it across calls). Cost ~ N·k² (orthogonalization) plus the solves.
* ``"sliced"``: spectrum slicing, shift-invert Lanczos runs of ``SLICE_PAIRS`` = 60 eigenpairs around
  shifts that walk up the spectrum (`LaplaceBeltrami._sliced`). Cost ~ N·k·m plus one factorization a run.

All factorizations are symmetric, without pivoting (SuperLU's partial pivoting adds much fill and makes
solves several times slower on these matrices); inside the spectrum, where ``W − σM`` is indefinite, a test solve
checks the accuracy (refined, or refactorized with pivoting, when it falls short).

``"auto"`` uses dense when ``N ≤ max(DENSE_MIN_N, DENSE_RATIO · k)`` or when ``k ≥ N − 1`` (ARPACK
needs k < N − 1), else Lanczos for ``k ≤ LANCZOS_MAX_PAIRS`` and sliced above (timings with k = 500,
`benchmarks/signatures.py`: the docs' Results page). On large meshes the time is about half ARPACK's own
work (reorthogonalization against the Lanczos basis, memory bound) and half the sparse triangular solves, one
per Lanczos step.
"""
from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from wpot.cache import Cache
from wpot.mesh import Mesh, named

__all__ = [
    "laplace_beltrami",
    "eigenpairs",
    "cached_eigenpairs",
    "LaplaceBeltrami",
    "Spectrum",
    "SpectralWarning",
    "choose_solver",
    "spectrum_cache",
    "SPECTRAL_MAX_VERTICES",
]

#: "auto" picks the dense solver at or below this many vertices, whatever k
DENSE_MIN_N = 300
#: ... and also whenever N <= DENSE_RATIO * k (dense cost ~N³ vs sliced Lanczos ~N k m: they tie near N ≈ 5k)
DENSE_RATIO = 4.0
#: shift of the shift-invert Lanczos, in units of the area-normalized spectrum (λ_1 ≈ 10..50 for
#: shapes of area 1); negative so that W − σM is positive definite even with the zero eigenvalue(s)
DEFAULT_SHIFT = -1e-2
#: a computed eigenvalue counts as zero when below this fraction of the first nonzero one
ZERO_RTOL = 1e-6
#: the spectral steps (WKS and HKS signatures, `wpot.zoomout`) see a mesh of more vertices through a simplified copy
#: of this many (`wpot.simplify`), where the spectra stay affordable on a laptop CPU (their times at 10,000 and
#: 60,000 vertices: the docs' Results page, §6)
SPECTRAL_MAX_VERTICES = 10_000

Solver = Literal["auto", "dense", "lanczos", "sliced"]
SOLVERS = ("auto", "dense", "lanczos", "sliced")

#: process-wide cache of spectra (memory; also on disk when $WPOT_CACHE_DIR is set)
spectrum_cache = Cache("spectrum", max_entries=16, max_bytes=1 << 30)


class SpectralWarning(UserWarning):
    """The spectrum is usable but suspicious (several components, unexpected zero eigenvalues, ...)."""


def _frozen_copy(x) -> np.ndarray:
    """``x`` as a read-only float64 array: a copy, unless it is one already whose memory nothing can write (a
    cached spectrum's arrays are handed out so; copying 500 eigenvectors at every use costs more than most uses)."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64 and not x.flags.writeable and (
            x.base is None or (isinstance(x.base, np.ndarray) and not x.base.flags.writeable)):
        return x
    out = np.array(x, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Spectrum:
    """The k smallest eigenpairs of the area-normalized mesh, ``W φ = λ M φ``.

    Attributes
    ----------
    evals : (k,) float64, ascending; the first ``n_zero`` are the (numerically) zero eigenvalues.
    evecs : (N, k) float64, M-orthonormal for the area-normalized mass ``M / area``.
    area : surface area of the original (un-normalized) mesh.
    n_zero : number of zero eigenvalues = number of connected components. WKS excludes them.
    solver : ``"dense"`` or ``"lanczos"``: which solver produced this result.
    fingerprint : `Mesh.fingerprint` of the source mesh ("" when built by hand).
    seconds : wall time of the eigensolve that produced it (also when read back from the cache).
    from_cache : True when this result was read from the cache instead of computed.
    normalized : True (what `eigenpairs` returns) for the area-normalized mesh; False for the mesh at its own size
        (`rescaled`).
    """

    evals: np.ndarray
    evecs: np.ndarray
    area: float
    n_zero: int = 1
    solver: str = "dense"
    fingerprint: str = ""
    seconds: float = 0.0
    from_cache: bool = False
    normalized: bool = True

    @classmethod
    def _checked(cls, **fields: Any) -> "Spectrum":
        """A spectrum of arrays checked before (read back from the cache, where they were stored from a checked
        spectrum, or a slice of one) and read-only: built without `__post_init__`'s pass over every entry, which
        a refinement that reads a cached spectrum several times would otherwise repeat each time."""
        out = object.__new__(cls)
        defaults = {f.name: f.default for f in dataclasses.fields(cls)}
        for name, default in defaults.items():
            value = fields.pop(name, default)
            if value is dataclasses.MISSING:
                raise TypeError(f"Spectrum._checked needs {name}")
            object.__setattr__(out, name, value)
        if fields:
            raise TypeError(f"Spectrum has no field {sorted(fields)[0]!r}")
        for name in ("evals", "evecs"):
            if getattr(out, name).flags.writeable:
                raise ValueError(f"Spectrum._checked takes read-only arrays; {name} is writeable")
        return out

    def __post_init__(self) -> None:
        ev, vec = _frozen_copy(self.evals), _frozen_copy(self.evecs)
        if ev.ndim != 1 or vec.ndim != 2 or vec.shape[1] != ev.shape[0]:
            raise ValueError(f"evals must be (k,) and evecs (N, k); got {ev.shape} and {vec.shape}")
        if not (np.all(np.isfinite(ev)) and np.all(np.isfinite(vec))):
            raise ValueError("eigenpairs contain NaN or inf")
        if not (0 <= int(self.n_zero) <= ev.size):
            raise ValueError(f"n_zero must be in [0, {ev.size}], got {self.n_zero}")
        object.__setattr__(self, "evals", ev)
        object.__setattr__(self, "evecs", vec)
        object.__setattr__(self, "n_zero", int(self.n_zero))
        object.__setattr__(self, "area", float(self.area))

    @property
    def k(self) -> int:
        return int(self.evals.size)

    @property
    def n_vertices(self) -> int:
        return int(self.evecs.shape[0])

    def rescaled(self, *, normalized: bool) -> "Spectrum":
        """This spectrum for the area-normalized mesh (``normalized=True``, what `eigenpairs` returns) or for the
        mesh at its own size (``normalized=False``: ``λ / area`` and ``φ / √area``, φ M-orthonormal for the
        un-normalized mass ``M``). At its own size the eigenvalues carry the shape's size (they scale as
        1/length²), as with the paper's operator ``L = M⁻¹W`` (§3.2), which does not normalize the area.
        Returns ``self`` when it already is in the asked form."""
        if bool(normalized) == self.normalized:
            return self
        f = self.area if normalized else 1.0 / self.area
        return Spectrum(
            evals=self.evals * f, evecs=self.evecs * np.sqrt(f), area=self.area, n_zero=self.n_zero,
            solver=self.solver, fingerprint=self.fingerprint, seconds=self.seconds, from_cache=self.from_cache,
            normalized=bool(normalized),
        )

    def first(self, k: int) -> "Spectrum":
        """The first ``k`` eigenpairs (all of them when there are fewer): the spectrum a smaller solve gives,
        e.g. for descriptors meant for a coarse basis. Returns ``self`` when nothing is dropped."""
        k = int(k)
        if k < 1:
            raise ValueError(f"k must be a positive integer, got {k}")
        if k >= self.k:
            return self
        return Spectrum._checked(**{**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)},
                                    "evals": self.evals[:k], "evecs": self.evecs[:, :k],
                                    "n_zero": min(self.n_zero, k)})

    @property
    def nonzero_evals(self) -> np.ndarray:
        """(k − n_zero,) the eigenvalues WKS uses."""
        return self.evals[self.n_zero :]

    @property
    def nonzero_evecs(self) -> np.ndarray:
        """(N, k − n_zero) their eigenvectors."""
        return self.evecs[:, self.n_zero :]

    def __repr__(self) -> str:
        return (
            f"Spectrum(N={self.n_vertices}, k={self.k}, n_zero={self.n_zero}, solver={self.solver!r}, "
            f"evals=[{self.evals[0]:.3g} .. {self.evals[-1]:.4g}], area={self.area:.4g})"
        )


# ---------------------------------------------------------------------------------------- operator
def laplace_beltrami(mesh: Mesh) -> tuple[sp.csr_matrix, sp.dia_matrix]:
    """Cotangent stiffness ``W`` and Voronoi mass ``M`` of ``mesh`` (libigl), paper §3.2.

    Parameters
    ----------
    mesh : a `Mesh` (not area-normalized here; see `LaplaceBeltrami` for that).

    Returns
    -------
    W : (N, N) scipy CSR float64, symmetric positive semidefinite, rows summing to zero
        (the negative of ``igl.cotmatrix``); boundary edges carry one cotangent (Neumann).
    M : (N, N) scipy DIA float64, diagonal Voronoi (mixed) areas; ``M.diagonal().sum() == mesh.area``.

    Raises
    ------
    ValueError : when the matrices contain NaN/inf (degenerate triangles) — repair with `Mesh.cleaned`.
    """
    import igl  # local import: libigl is a heavy module

    if not isinstance(mesh, Mesh):
        raise TypeError(f"laplace_beltrami expects a wpot.Mesh, got {type(mesh).__name__}")
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    L = igl.cotmatrix(v, f)
    W = sp.csr_matrix(-L, dtype=np.float64)
    W.sum_duplicates()
    W.sort_indices()
    mass = mesh.voronoi_areas
    if not np.all(np.isfinite(W.data)) or not np.all(np.isfinite(mass)):
        bad = int(np.count_nonzero(~np.isfinite(mass))) + int(np.count_nonzero(~np.isfinite(W.data)))
        raise ValueError(
            f"the cotangent Laplacian has {bad} NaN/inf entries (degenerate triangles: "
            f"{mesh.degenerate_faces.size}); repair the mesh with Mesh.cleaned()"
        )
    M = sp.dia_matrix((mass[None, :], [0]), shape=(mesh.n_vertices, mesh.n_vertices))
    return W, M


def choose_solver(n_vertices: int, k: int) -> str:
    """The solver ``"auto"`` picks for N vertices and k eigenpairs (see the module docstring)."""
    if k >= n_vertices - 1 or n_vertices <= max(DENSE_MIN_N, DENSE_RATIO * k):
        return "dense"
    return "lanczos" if k <= LANCZOS_MAX_PAIRS else "sliced"


@dataclass(eq=False)
class LaplaceBeltrami:
    """Cached Laplace–Beltrami set-up for one mesh (potpourri3d style): W, M, area, and the LU
    factorization of ``W − σ M`` reused by every Lanczos call with the same shift.

    Parameters
    ----------
    mesh : the shape. Its mass matrix is divided by ``mesh.area`` (area normalization).

    Attributes
    ----------
    W : (N, N) CSR, PSD stiffness (scale invariant).
    M : (N, N) DIA, Voronoi mass of the area-normalized mesh (diagonal sums to 1).
    mass : (N,) its diagonal.
    area : the original surface area.
    """

    mesh: Mesh
    W: sp.csr_matrix = field(init=False, repr=False)
    M: sp.dia_matrix = field(init=False, repr=False)
    mass: np.ndarray = field(init=False, repr=False)
    area: float = field(init=False)
    n_zero: int = field(init=False)
    _lu: dict = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        mesh = self.mesh
        if not isinstance(mesh, Mesh):
            raise TypeError(f"LaplaceBeltrami expects a wpot.Mesh, got {type(mesh).__name__}")
        W, M = laplace_beltrami(mesh)
        mass = M.diagonal()
        zero = np.nonzero(mass <= 0)[0]
        if zero.size:
            raise ValueError(
                f"{zero.size} vertices have zero mass (unreferenced vertices or only degenerate triangles), "
                f"e.g. vertices {zero[:10].tolist()}: the eigenproblem W φ = λ M φ is singular. "
                "Repair the mesh with Mesh.cleaned()."
            )
        self.area = float(mass.sum())
        self.mass = mass / self.area
        self.mass.setflags(write=False)
        self.W = W
        self.M = sp.dia_matrix((self.mass[None, :], [0]), shape=W.shape)
        self.n_zero = int(mesh.n_components)

    @property
    def n_vertices(self) -> int:
        return self.W.shape[0]

    def factorization(self, shift: float = DEFAULT_SHIFT):
        """The (cached) SuperLU factorization of ``W − shift·M`` (CSC), for a negative shift (positive definite).

        Symmetric mode without pivoting keeps the minimum-degree ordering's fill, several times less than with
        SuperLU's default partial pivoting, and its solves are that much faster (figures: the docs' Results
        page)."""
        key = float(shift)
        lu = self._lu.get(key)
        if lu is None:
            lu = _splu_symmetric((self.W - key * sp.diags(self.mass)).tocsc())
            self._lu[key] = lu
        return lu

    def _shift_inverse(self, sigma: float) -> sla.LinearOperator:
        """x -> (W − σM)⁻¹ x for any σ (the shift-invert operator of one slice, not cached). Inside the spectrum
        the matrix is indefinite: the symmetric factorization (no pivoting) is used when a test solve is accurate
        to 1e-10, else with one step of iterative refinement, else SuperLU with partial pivoting (much slower
        solves)."""
        if sigma < 0:
            lu = self.factorization(sigma)
            return sla.LinearOperator(self.W.shape, matvec=lu.solve, dtype=np.float64)
        A = (self.W - sigma * sp.diags(self.mass)).tocsc()
        b = np.random.default_rng(1).standard_normal(A.shape[0])
        try:
            lu = _splu_symmetric(A)
        except RuntimeError:  # an exactly zero pivot
            lu = None

        def refined(r: np.ndarray) -> np.ndarray:
            x = lu.solve(r)
            return x + lu.solve(r - A @ x)

        if lu is not None:
            for solve in (lu.solve, refined):
                if np.linalg.norm(b - A @ solve(b)) <= 1e-10 * np.linalg.norm(b):
                    return sla.LinearOperator(A.shape, matvec=solve, dtype=np.float64)
        lu = sla.splu(A, permc_spec="MMD_AT_PLUS_A")
        return sla.LinearOperator(A.shape, matvec=lu.solve, dtype=np.float64)

    def eigenpairs(
        self,
        k: int = 500,
        *,
        solver: Solver = "auto",
        shift: float = DEFAULT_SHIFT,
        tol: float = 0.0,
        ncv: int | None = None,
        per_slice: int | None = None,
    ) -> Spectrum:
        """The k smallest eigenpairs of ``W φ = λ M φ`` (area-normalized), uncached.

        Parameters
        ----------
        k : number of eigenpairs, ``1 ≤ k ≤ N``.
        solver : ``"auto"``, ``"dense"``, ``"lanczos"`` or ``"sliced"`` (see module docstring).
        shift : Lanczos shift σ < 0 (area-normalized units).
        tol : ARPACK relative tolerance (0 = machine precision).
        ncv : ARPACK Lanczos basis size of ``"lanczos"`` (default ``min(N − 1, max(2k + 1, 20))`` as in scipy).
        per_slice : eigenpairs per shift-invert run of ``"sliced"`` (default `SLICE_PAIRS`).

        Returns
        -------
        `Spectrum` with ``solver`` naming the solver actually used.
        """
        n = self.n_vertices
        k = _check_k(k, n)
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(repr(x) for x in SOLVERS)}, got {solver!r}")
        used = choose_solver(n, k) if solver == "auto" else solver
        t0 = time.perf_counter()
        if used == "dense":
            evals, evecs = self._dense(k)
        else:
            if k >= n - 1:
                raise ValueError(
                    f"solver={used!r} needs k < N - 1 (ARPACK), got k={k} for N={n} vertices; use solver='dense'"
                )
            if not shift < 0:
                raise ValueError(f"shift must be negative (W - shift*M must be positive definite), got {shift}")
            if used == "sliced":
                evals, evecs = self._sliced(k, shift=shift, tol=tol, per_slice=per_slice)
            else:
                evals, evecs = self._lanczos(k, shift=shift, tol=tol, ncv=ncv)
        seconds = time.perf_counter() - t0
        n_zero = _check_zero_eigenvalues(evals, self.n_zero, self.mesh.name)
        return Spectrum(
            evals=evals,
            evecs=evecs,
            area=self.area,
            n_zero=n_zero,
            solver=used,
            fingerprint=self.mesh.fingerprint,
            seconds=seconds,
        )

    def _dense(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        d = 1.0 / np.sqrt(self.mass)
        A = (sp.diags(d) @ self.W @ sp.diags(d)).toarray()
        A = 0.5 * (A + A.T)
        w, v = la.eigh(A, subset_by_index=[0, k - 1], driver="evr", overwrite_a=True, check_finite=False)
        return w, v * d[:, None]

    def _lanczos(self, k: int, *, shift: float, tol: float, ncv: int | None) -> tuple[np.ndarray, np.ndarray]:
        n = self.n_vertices
        lu = self.factorization(shift)
        op = sla.LinearOperator((n, n), matvec=lu.solve, dtype=np.float64)
        # Guard band: ARPACK can return a wrong member of a degenerate cluster at the END of the requested
        # range (seen on a sphere, multiplicity 9 at l = 4, in about one run in ten). Asking for a few more
        # pairs and keeping the k smallest makes the returned range complete. A fixed start vector makes the
        # result reproducible run to run (the default v0 is random).
        k_ask = min(n - 2, k + max(GUARD_MIN, int(GUARD_FRACTION * k)))
        if ncv is None:
            ncv = min(n - 1, max(2 * k_ask + 1, 20))
        v0 = np.random.default_rng(0).standard_normal(n)
        w, v = sla.eigsh(self.W, k=k_ask, M=self.M.tocsr(), sigma=shift, which="LM", OPinv=op, tol=tol, ncv=ncv, v0=v0)
        order = np.argsort(w)[:k]
        w, v = w[order], v[:, order]
        # ARPACK returns M-orthonormal vectors; re-normalize columns exactly (cheap, diagonal M)
        v = v / np.sqrt(np.einsum("ik,ik,i->k", v, v, self.mass))[None, :]
        return w, v


    def _sliced(self, k: int, *, shift: float, tol: float, per_slice: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Spectrum slicing: shift-invert Lanczos runs of ``per_slice`` eigenpairs each, around shifts that walk up
        the spectrum, instead of one run of k. A run of m pairs costs ~N m² (orthogonalization) plus one sparse
        factorization, so k/m runs cost ~N k m, a fraction of one run's ~N k² at k = 500.

        A run around σ returns the m eigenvalues nearest σ, so every eigenvalue nearer σ than its farthest one has
        been returned, and a gap between two of them is a gap of the spectrum. Each run keeps its pairs from the
        previous cut up to a new cut placed in the widest gap of the top quarter of its new range (a near-degenerate
        cluster is never split between two runs, whose vectors would not be orthogonal). The next shift is placed
        from the local density so that the next run reaches back past the cut; a run that does not may have
        missed an eigenvalue, and is redone with its shift moved down (and with twice the pairs after two misses,
        for clusters larger than a run)."""
        n = self.n_vertices
        m_req = SLICE_PAIRS if per_slice is None else int(per_slice)
        if m_req < 2:
            raise ValueError(f"per_slice must be an integer >= 2, got {per_slice!r}")
        k_ask = min(n - 2, k + max(GUARD_MIN, int(GUARD_FRACTION * k)))
        M = self.M.tocsr()
        v0 = np.random.default_rng(0).standard_normal(n)
        vals: list[np.ndarray] = []
        vecs: list[np.ndarray] = []
        got, cut, sigma, m, misses = 0, -np.inf, float(shift), min(m_req, n - 2), 0
        for _ in range(4 * (k_ask // max(1, m_req)) + 32):
            if got >= k_ask:
                break
            w, v = sla.eigsh(self.W, k=m, M=M, sigma=sigma, which="LM", OPinv=self._shift_inverse(sigma), tol=tol,
                             ncv=min(n - 1, max(int(1.5 * m), m + 20)), v0=v0)
            order = np.argsort(w)
            w, v = w[order], v[:, order]
            # every eigenvalue strictly nearer σ than the farthest returned one (distance r) has been returned:
            # the spectrum is known on the open interval (σ - r, σ + r), except that the farthest one's cluster
            # may be incomplete
            r = float(np.abs(w - sigma).max())
            inner = np.abs(w - sigma) < r * (1.0 - SLICE_CLUSTER)
            if got and not cut > sigma - r * (1.0 - SLICE_CLUSTER):
                # the known interval does not reach back past the cut: an eigenvalue between them may be missing.
                # Shift down and run again (with twice the pairs after two misses: a cluster larger than the run)
                sigma -= (sigma - r - cut) + SLICE_OVERLAP * r
                misses += 1
                if misses % 2 == 0:
                    m = min(2 * m, n - 2)
                continue
            misses = 0
            # the cut goes in the widest gap of the top quarter of the new known range (its top end, σ + r, bounds
            # a real gap above the last inner eigenvalue), so no cluster is split between two runs
            base = max(cut, sigma - r)
            points = np.append(w[inner & (w >= base)], sigma + r)
            top = points[points >= base + (1.0 - SLICE_GAP_SPAN) * (sigma + r - base)]
            if top.size < 2:
                top = points
            if top.size >= 2:
                j = int(np.argmax(np.diff(top)))
                new_cut = 0.5 * (top[j] + top[j + 1])
            else:
                new_cut = 0.5 * (base + sigma + r)
            keep = inner & (w >= cut) & (w < new_cut)
            vals.append(w[keep])
            vecs.append(v[:, keep])
            got += int(keep.sum())
            # the next run: m pairs at this run's density span 2 r_next
            density = max(w.size - 1, 1) / max(float(w[-1] - w[0]), 1e-300)
            r_next = 0.5 * m / density
            cut, sigma = new_cut, new_cut + (1.0 - SLICE_OVERLAP) * r_next
        else:  # pragma: no cover - the loop bound is generous
            raise RuntimeError(f"spectrum slicing found {got} of {k_ask} eigenpairs; use solver='lanczos'")
        w = np.concatenate(vals)
        v = np.concatenate(vecs, axis=1)
        order = np.argsort(w)[:k]
        w, v = w[order], v[:, order]
        v = v / np.sqrt(np.einsum("ik,ik,i->k", v, v, self.mass))[None, :]
        return w, v


def _splu_symmetric(A: sp.csc_matrix):
    """SuperLU of a symmetric matrix in symmetric mode, no pivoting, ordered by minimum degree on A + Aᵀ at
    every size: COLAMD, at best a little faster to factorize on the largest meshes, leaves more fill and solves
    no faster (the docs' Results page)."""
    return sla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


#: "auto" uses one Lanczos run up to this many eigenpairs, spectrum slicing above
LANCZOS_MAX_PAIRS = 100
#: eigenpairs per shift-invert run of the "sliced" solver. Fewer pairs a run: less orthogonalization, more runs
#: and factorizations. At k = 500, 60 was faster than 100 from 5,000 to 80,000 vertices (the docs' Results page)
SLICE_PAIRS = 60
#: a run's range is planned to start this fraction of its radius below the previous cut (the density is estimated)
SLICE_OVERLAP = 0.2
#: eigenvalues within this relative distance of a run's farthest one count as its cluster
SLICE_CLUSTER = 1e-6
#: the cut goes in the widest gap between a run's trusted eigenvalues in this top fraction of its new range
SLICE_GAP_SPAN = 0.25
#: extra Lanczos pairs computed beyond k and discarded (max of the two), see `LaplaceBeltrami._lanczos`
GUARD_MIN = 8
GUARD_FRACTION = 0.05


def _check_k(k: int, n: int) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise ValueError(f"k must be an integer, got {k!r}")
    k = int(k)
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    if k > n:
        raise ValueError(f"k={k} eigenpairs requested but the mesh has only N={n} vertices (k must be <= N)")
    return k


def _check_zero_eigenvalues(evals: np.ndarray, n_components: int, name: str | None = None) -> int:
    """Number of zero eigenvalues: the number of components, checked against the computed values (warnings start
    with the mesh's ``name`` when it has one)."""
    nz = min(n_components, evals.size)
    if n_components > 1:
        warnings.warn(named(
            name, f"the mesh has {n_components} connected components, so the eigenvalue 0 repeats {n_components} "
            "times; those eigenpairs are excluded from WKS. Signatures of disconnected pieces are not "
            "comparable with those of a connected shape; consider Mesh.cleaned(keep_largest_component=True)."),
            SpectralWarning,
            stacklevel=4,
        )
    if nz < evals.size:
        scale = abs(evals[nz])
        small = np.abs(evals[:nz])
        if scale == 0 or np.any(small > ZERO_RTOL * scale) or abs(evals[nz]) <= ZERO_RTOL * max(abs(evals[-1]), 1.0):
            warnings.warn(named(
                name, f"expected {nz} zero eigenvalue(s) (one per component), but the computed spectrum starts "
                f"{np.array2string(evals[: nz + 2], precision=3)}; the mesh may be badly conditioned "
                "(near-degenerate triangles, nearly disconnected parts)."),
                SpectralWarning,
                stacklevel=4,
            )
    return nz


def _cache_slot(mesh: Mesh, k: int, cache: Cache | bool, solver: str, shift: float, tol: float
                ) -> tuple[Cache, str, dict[str, Any]]:
    """The cache, the solver that ``solver`` resolves to, and the cache parameters of `eigenpairs`."""
    store = spectrum_cache if cache is True else cache
    if not isinstance(store, Cache):
        raise TypeError(f"cache must be True, False or a wpot.cache.Cache, got {type(cache).__name__}")
    used = choose_solver(mesh.n_vertices, k) if solver == "auto" else solver
    return store, used, {"k": k, "solver": used, "shift": float(shift), "tol": float(tol), "normalized": True}


def _cached(store: Cache, mesh: Mesh, params: dict[str, Any]) -> Spectrum | None:
    entry = store.get(mesh.fingerprint, params)
    if entry is None:
        return None
    # no SpectralWarning here: it was given when this spectrum was computed, and a warning per use would repeat
    # it for every pair of an all-vs-all (`eigenpairs`, Warns)
    return Spectrum._checked(
        evals=entry["evals"],
        evecs=entry["evecs"],
        area=float(entry["area"]),
        n_zero=int(entry["n_zero"]),
        solver=str(entry["solver"]),
        fingerprint=mesh.fingerprint,
        seconds=float(entry["seconds"]),
        from_cache=True,
    )


def cached_eigenpairs(
    mesh: Mesh, k: int = 500, *, solver: Solver = "auto", shift: float = DEFAULT_SHIFT, tol: float = 0.0,
    cache: Cache | bool = True,
) -> Spectrum | None:
    """What `eigenpairs` with these arguments would read from the cache, or None when it would have to compute
    (it computes nothing). Lets a caller reuse a larger spectrum computed earlier, e.g. WKS's 500 eigenpairs."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"cached_eigenpairs expects a wpot.Mesh, got {type(mesh).__name__}")
    if cache is False:
        return None
    store, _, params = _cache_slot(mesh, _check_k(k, mesh.n_vertices), cache, solver, shift, tol)
    return _cached(store, mesh, params)


def eigenpairs(
    mesh: Mesh,
    k: int = 500,
    *,
    solver: Solver = "auto",
    shift: float = DEFAULT_SHIFT,
    tol: float = 0.0,
    cache: Cache | bool = True,
) -> Spectrum:
    """The k smallest eigenpairs of the area-normalized Laplace–Beltrami problem ``W φ = λ M φ``.

    Parameters
    ----------
    mesh : the shape (N vertices). It must have no zero-mass (unreferenced) vertex.
    k : number of eigenpairs (including the zero one(s)), ``1 ≤ k ≤ N``; paper: 500.
    solver : ``"auto"`` (by size, see `choose_solver`), ``"dense"`` or ``"lanczos"``; the result's
        ``solver`` field says which one ran.
    shift, tol : Lanczos shift (negative) and ARPACK tolerance.
    cache : True uses the process-wide `spectrum_cache` (memory, plus disk under ``$WPOT_CACHE_DIR``);
        a `Cache` instance uses that one; False computes afresh. The key is the mesh content and
        (k, solver, shift, tol), so an all-vs-all computes each spectrum once.

    Returns
    -------
    `Spectrum`: evals (k,), evecs (N, k) M-orthonormal, area, n_zero, solver.

    Warns
    -----
    `SpectralWarning` when the mesh has several components (repeated zero eigenvalue), or when the computed
    spectrum does not start with one zero per component. Only when the spectrum is computed, not when it is read
    from the cache: once per mesh and cache entry, however many comparisons use it (the number of components
    stays in ``Spectrum.n_zero``; `wpot.io.load_mesh` also warns about components when it reads the file).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"eigenpairs expects a wpot.Mesh, got {type(mesh).__name__}")
    k = _check_k(k, mesh.n_vertices)
    if cache is False:
        return LaplaceBeltrami(mesh).eigenpairs(k, solver=solver, shift=shift, tol=tol)
    store, used, params = _cache_slot(mesh, k, cache, solver, shift, tol)
    found = _cached(store, mesh, params)
    if found is not None:
        return found
    s = LaplaceBeltrami(mesh).eigenpairs(k, solver=used, shift=shift, tol=tol)
    store.put(
        mesh.fingerprint,
        params,
        {"evals": s.evals, "evecs": s.evecs, "area": s.area, "n_zero": s.n_zero, "solver": s.solver, "seconds": s.seconds},
    )
    return s
