"""What the spectral signatures (WKS, HKS) share: the checks of their eigenpairs, and fitting a grid
(WKS's energies, HKS's times) to a dataset from the shapes' eigenvalues.

`SpectralSignature` is the base of a registered signature computed from Laplace–Beltrami eigenpairs
(`wpot.spectral.eigenpairs`, through the instance's spectrum cache, so every spectral signature of an
all-vs-all reads the same cached spectra): its `fit_input` is a shape's eigenvalues, and a subclass says in
`fit_from` how a grid follows from them.

A mesh of more than ``max_vertices`` vertices (`wpot.spectral.SPECTRAL_MAX_VERTICES`) is seen through a simplified
copy of that many (`wpot.simplify`): its eigenvalues are the copy's, and its signatures the copy's, blended to every
vertex at its closest point of the copy (`wpot.simplify.Simplified.interpolate`). The eigenpairs a spectral
signature uses are a surface's lowest frequencies, which the copy keeps, while their cost grows faster than the
vertex count.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from wpot._validate import boolean, integer_at_least
from wpot.mesh import Mesh
from wpot.signatures.base import Signature, SignatureOptions, option
from wpot.spectral import SPECTRAL_MAX_VERTICES, Spectrum, eigenpairs

__all__ = ["ZERO_EVAL_RTOL", "SpectralOptions", "SpectralSignature", "check_eigenpairs", "mesh_spectrum",
           "positive_evals", "spectrum_summary"]

#: an eigenvalue below this fraction of the largest one is numerically zero (a null-space pair)
ZERO_EVAL_RTOL = 1e-9


def positive_evals(spectrum: Spectrum, what: str) -> np.ndarray:
    """The nonzero eigenvalues of ``spectrum`` (at least 2, the first clearly nonzero); ``what`` names the
    signature in the message ("a WKS")."""
    ev = spectrum.nonzero_evals
    if ev.size < 2:
        raise ValueError(
            f"{what} needs at least 2 nonzero eigenvalues, got {ev.size} (k={spectrum.k}, n_zero={spectrum.n_zero})"
        )
    if ev[0] <= ZERO_EVAL_RTOL * abs(ev[-1]):
        raise ValueError(
            f"the first nonzero eigenvalue is {ev[0]:.3g}, numerically zero (n_zero={spectrum.n_zero}); the mesh probably has "
            "more connected components than recorded, or degenerate triangles"
        )
    return ev


def check_eigenpairs(evals: ArrayLike, evecs: ArrayLike, grid: ArrayLike, grid_name: str
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``evals`` (K,) strictly positive, ``evecs`` (N, K) and a signature's ``grid`` (M,) (its energies or
    times), all finite, as float64 arrays; ValueError naming what is wrong otherwise."""
    ev = np.asarray(evals, dtype=np.float64)
    vec = np.asarray(evecs, dtype=np.float64)
    g = np.asarray(grid, dtype=np.float64)
    if ev.ndim != 1 or ev.size < 1:
        raise ValueError(f"evals must be a non-empty (K,) array, got shape {ev.shape}")
    if vec.ndim != 2 or vec.shape[1] != ev.size:
        raise ValueError(f"evecs must have shape (N, {ev.size}) to match evals, got {vec.shape}")
    if g.ndim != 1 or g.size < 1:
        raise ValueError(f"{grid_name} must be a non-empty (M,) array, got shape {g.shape}")
    if not np.all(np.isfinite(ev)) or not np.all(np.isfinite(vec)) or not np.all(np.isfinite(g)):
        raise ValueError(f"evals, evecs and {grid_name} must be finite (got NaN or inf)")
    if np.any(ev <= ZERO_EVAL_RTOL * np.abs(ev).max()):
        raise ValueError(
            "evals must be strictly positive, not numerically zero (exclude the zero eigenvalue(s) first, e.g. "
            f"Spectrum.nonzero_evals); got min {ev.min():.3g} with max {ev.max():.3g}"
        )
    return ev, vec, g


def mesh_spectrum(mesh_or_spectrum: Mesh | Spectrum, n_eigen: int, cache: Any, what: str,
                  warning: type[Warning]) -> Spectrum:
    """The spectrum a signature function (`wpot.wks`, `wpot.hks`) works on: a given `Spectrum` as it is, or
    ``n_eigen`` eigenpairs of a `Mesh` (all N, with a ``warning``, when it has fewer vertices) through
    `wpot.spectral.eigenpairs` and ``cache``. ``what`` names the function in the TypeError."""
    if isinstance(mesh_or_spectrum, Spectrum):
        return mesh_or_spectrum
    if not isinstance(mesh_or_spectrum, Mesh):
        raise TypeError(f"{what} expects a wpot.Mesh or a wpot.spectral.Spectrum, got {type(mesh_or_spectrum).__name__}")
    mesh = mesh_or_spectrum
    k = integer_at_least("n_eigen", n_eigen, 1)
    if k > mesh.n_vertices:
        warnings.warn(
            f"n_eigen={k} but the mesh has only {mesh.n_vertices} vertices: using all {mesh.n_vertices} eigenpairs",
            warning,
            stacklevel=3,
        )
        k = mesh.n_vertices
    return eigenpairs(mesh, k=k, cache=cache)


def spectrum_summary(spectrum: Spectrum) -> Spectrum:
    """``spectrum`` without its eigenvectors (a (1, k) zero placeholder): what a grid over a dataset needs
    (`wks_energies`, `wpot.signatures.hks.hks_times`), small enough to send back from a worker process."""
    s = spectrum
    return Spectrum(evals=s.evals, evecs=np.zeros((1, s.k)), area=s.area, n_zero=s.n_zero, solver=s.solver,
                    fingerprint=s.fingerprint, normalized=s.normalized)


#: the smallest nonzero ``spectral_max_vertices``: a smaller copy loses the shape's detail
MIN_COPY_VERTICES = 1000

#: the fewest Laplace-Beltrami eigenpairs a spectral signature (WKS, HKS) takes: ``n_eigen`` below it is refused,
#: and a mesh with fewer vertices than ``min(n_eigen, MIN_EIGENPAIRS)`` cannot be compared
#: (`wpot.comparison.min_vertices`). Below this, every vertex's signature is a mix of a handful of eigenfunctions, and
#: the spectrum's top lies in another band than a full mesh's, so the shared grid fails with a message about units of
#: length (or, worse, fits and gives a meaningless distance).
MIN_EIGENPAIRS = 10


@dataclass(frozen=True)
class SpectralOptions(SignatureOptions):
    """The options every spectral signature has (a subclass adds its grid's size).

    Attributes
    ----------
    n_eigen : Laplace–Beltrami eigenpairs, the zero one(s) included (paper: 500); at least `MIN_EIGENPAIRS`. A mesh
        with fewer vertices uses all of them. One value serves every spectral
        signature, so they share one cached spectrum.
    scale_invariant : False: the meshes at their own size (the paper; size counts); True: scaled to area 1.
    max_vertices : a mesh of more vertices is seen through a simplified copy of this many (the module docstring),
        or of ``2 n_eigen`` when that is more (`copy_vertices`); 0: every mesh as it is. Keys carry it only when
        not at its default.
    """

    n_eigen: int = option(500, keyword="n_eigen", flag="--n-eigen", help="Laplace-Beltrami eigenpairs (default {default})")
    scale_invariant: bool = option(
        False, keyword="scale_invariant", flag="--scale-invariant",
        help="scale every mesh to area 1 first, so size does not count (default: meshes at their own size, as in the "
             "paper; then all meshes must share one unit of length)",
    )

    max_vertices: int = option(
        SPECTRAL_MAX_VERTICES, keyword="spectral_max_vertices", flag="--spectral-max-vertices", key_omit_default=True,
        help="meshes of more vertices get their spectral signature on a simplified copy of this many, blended back "
             "to every vertex (default {default}; 0: always on the mesh itself)",
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_eigen", integer_at_least("n_eigen", self.n_eigen, MIN_EIGENPAIRS))
        object.__setattr__(self, "scale_invariant", boolean("scale_invariant", self.scale_invariant))
        n = integer_at_least("spectral_max_vertices", self.max_vertices, 0)
        if 0 < n < MIN_COPY_VERTICES:
            raise ValueError(f"spectral_max_vertices must be 0 (off) or at least {MIN_COPY_VERTICES}, got {n}")
        object.__setattr__(self, "max_vertices", n)

    @property
    def copy_vertices(self) -> int:
        """The size of the simplified copy a larger mesh is seen through: ``max_vertices``, raised to ``2 n_eigen``
        so that the copy resolves the eigenpairs asked; 0 when off."""
        return max(self.max_vertices, 2 * self.n_eigen) if self.max_vertices else 0

    def copies(self, n_vertices: int) -> bool:
        """Whether a mesh of ``n_vertices`` vertices is seen through a simplified copy (of `copy_vertices`)."""
        return 0 < self.copy_vertices < n_vertices


class SpectralSignature(Signature):
    """A signature computed from ``options.n_eigen`` Laplace–Beltrami eigenpairs and fitted to a dataset
    from the shapes' eigenvalues (`fit_input`; the subclass's `fit_from` builds its grid from them)."""

    needs_fit = True

    def copy_of(self, mesh: Mesh) -> Any:
        """The `wpot.simplify.Simplified` copy ``mesh`` is seen through, or None when it is seen as it is (at most
        `SpectralOptions.copy_vertices` vertices, or ``max_vertices`` 0). `wpot.simplify` keeps its last copies, so
        fitting and evaluating a mesh simplify it once."""
        if not self.options.copies(mesh.n_vertices):
            return None
        from wpot.simplify import simplify  # imports Warp: only for large meshes

        return simplify(mesh, self.options.copy_vertices, device=self.device)

    def spectral_mesh(self, mesh: Mesh) -> Mesh:
        """The mesh whose spectrum stands for ``mesh``'s: its simplified copy (`copy_of`), or itself."""
        s = self.copy_of(mesh)
        return mesh if s is None else s.coarse

    def fit_input(self, mesh: Any) -> Spectrum:
        """The eigenvalues of ``mesh`` (a `Spectrum` with a placeholder for the eigenvectors, `spectrum_summary`),
        from ``min(n_eigen, N)`` eigenpairs of `spectral_mesh` through the instance's spectrum cache, where the
        eigenvectors wait for the signature itself."""
        if not isinstance(mesh, Mesh):
            raise TypeError(f"fit_input expects a wpot.Mesh, got {type(mesh).__name__}")
        m = self.spectral_mesh(mesh)
        # a mesh with fewer vertices than n_eigen uses all its eigenpairs, as the signature itself does
        s = eigenpairs(m, min(self.options.n_eigen, m.n_vertices), cache=self.spectrum_cache)
        return spectrum_summary(s)

    def __call__(self, mesh: Mesh) -> np.ndarray:
        """(N, d) float64 signatures of every vertex of ``mesh``: `evaluate` on the mesh, or on its simplified copy
        and blended to every vertex (`copy_of`)."""
        self.check_fitted()
        s = self.copy_of(mesh)
        return self.evaluate(mesh) if s is None else s.interpolate(self.evaluate(s.coarse))

    def evaluate(self, mesh: Mesh) -> np.ndarray:
        """(N, d) float64 signatures of the vertices of ``mesh`` itself, by the fitted state."""
        raise NotImplementedError
