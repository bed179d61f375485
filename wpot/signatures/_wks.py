"""Wave kernel signatures (Aubry et al. 2011; paper §2.3, Eq. 5, and §3.2).

For a vertex x and log-energy e,

    WKS(x, e) = C_e Σ_k φ_k(x)² exp(−(e − log E_k)² / (2σ²)),   C_e = 1 / Σ_k exp(−(e − log E_k)² / (2σ²)),

over the nonzero eigenvalues E_k of the Laplace–Beltrami operator (`wpot.spectral`), with Aubry's
Gaussian (the paper's Eq. 5 drops the square of (e − log E_k); we use the square).

Size (``scale_invariant``)
--------------------------
By default (``scale_invariant=False``) the operator is the paper's ``L = M⁻¹W`` of the mesh at its own size
(§3.2 normalizes nothing): E_k scale as 1/length² and φ_k² as 1/area, so two shapes of the same form but
different sizes get different signatures. That is what separates TOSCA's David from Michael, which share
one template and differ mainly in size: one-shot 1-NN over the 76 shapes of ``tosca_isometric_5k`` is
clearly better at the meshes' own size than area-normalized (the docs' Results page). It is also what partial matching needs: a part keeps its size, not the whole's. With
``scale_invariant=True`` the spectrum is that of the mesh scaled to area 1, so a shape and any scaled copy
get the same WKS; use it when meshes come in unrelated units. Meshes must then share one unit of length.

Energy grid (paper §3.2) and our reading of its circular δ
----------------------------------------------------------
The paper sets e_min = log E_1 + 2σ, e_max = log E_K − 2σ, δ = (e_max − e_min)/M and σ = 7δ, which is
circular (δ depends on e_min, e_max, which depend on σ). We take **pyFM's reading**: δ is computed from
the *unshrunk* range, ``δ = (log E_K − log E_1) / M``, ``σ = 7δ``, and the M energies are
``linspace(log E_1 + 2σ, log E_K − 2σ, M)``. It is the widely used implementation, so signatures can
be checked against it. (The exact solution of the circular definition would be a slightly smaller δ.)

One grid for a comparison
-------------------------
Eq. 29 compares WKS values energy by energy, so both shapes must use the same energies
(paper §3.2). `wks_energies` builds one grid for a set of spectra from the common part of their
spectra: ``log E_1 = max_s log E_1(s)`` and ``log E_K = min_s log E_K(s)``, so every energy lies inside
every shape's computed spectrum. For one spectrum it is exactly the grid above.

`WKS` is the registered signature (`wpot.signatures.base`): options n_eigen, n_energies, scale_invariant, and
the shared grid as its fitted state.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike

from wpot.mesh import Mesh
from wpot.cache import Cache
from wpot.spectral import Spectrum
from wpot._validate import integer_at_least
from wpot.signatures.base import option, register_signature
from wpot.signatures._spectral import SpectralOptions, SpectralSignature, check_eigenpairs, mesh_spectrum, positive_evals, spectrum_summary

__all__ = ["VERSION", "wks", "wks_energies", "wks_from_eigenpairs", "wks_weights", "sigma_of_grid", "EnergyGrid", "SIGMA_PER_DELTA",
           "WKSWarning", "WKS", "WKSOptions", "spectrum_summary"]

#: bumped whenever this module's output changes; part of the signature cache keys (`WKS.params`)
VERSION = 2
#: σ = 7δ (paper §3.2)
SIGMA_PER_DELTA = 7.0
#: e_min = log E_1 + 2σ, e_max = log E_K − 2σ (paper §3.2)
MARGIN_SIGMAS = 2.0


#: `wks_energies` warns when the shapes' shared log-eigenvalue band is below this fraction of the narrowest
#: shape's own band. Datasets of one kind at their own size share well above it, a part among wholes (HEAD)
#: less; one mesh in cm among meshes in mm shifts its band by log(100) = 4.6, most of a band's width, and falls
#: below it (the shares measured at k = 500: the docs' Results page).
MIN_SHARED_BAND = 0.35


class WKSWarning(UserWarning):
    """WKS settings that are legal but unusual (fewer eigenpairs than asked, energies off the spectrum)."""


class EnergyGrid(NamedTuple):
    """A shared WKS energy grid: ``energies`` (M,) float64 log-energies, increasing, and ``sigma``."""

    energies: np.ndarray
    sigma: float


def check_scale_invariant(scale_invariant: object) -> bool:
    """``scale_invariant`` as a bool; a `ValueError` for anything but True or False (e.g. the string "yes")."""
    if not isinstance(scale_invariant, (bool, np.bool_)):
        raise ValueError(f"scale_invariant must be True or False, got {scale_invariant!r}")
    return bool(scale_invariant)


def _wks_spectrum(spectrum: Spectrum, scale_invariant: bool) -> Spectrum:
    """The spectrum WKS uses: area-normalized, or at the mesh's own size (see the module docstring)."""
    return spectrum.rescaled(normalized=check_scale_invariant(scale_invariant))


def wks_energies(spectra: Spectrum | Iterable[Spectrum], *, n_energies: int = 200, scale_invariant: bool = False) -> EnergyGrid:
    """One WKS energy grid shared by a set of shapes (paper §3.2; see the module docstring).

    Parameters
    ----------
    spectra : one `Spectrum` or several (all shapes of a comparison or a dataset).
    n_energies : M, the number of energies (paper: 200).
    scale_invariant : the grid for the area-normalized spectra (True) or for the meshes at their own size
        (False, default); it must match the ``scale_invariant`` of the `wks` calls that use it.

    Returns
    -------
    `EnergyGrid` (energies (M,) float64, sigma): ``δ = (log E_K − log E_1)/M``, ``σ = 7δ``,
    ``energies = linspace(log E_1 + 2σ, log E_K − 2σ, M)``, where ``E_1`` is the largest of the
    shapes' first nonzero eigenvalues and ``E_K`` the smallest of their largest eigenvalues.
    """
    if isinstance(spectra, Spectrum):
        spectra = [spectra]
    spectra = list(spectra)
    if not spectra:
        raise ValueError("wks_energies needs at least one Spectrum, got none")
    for s in spectra:
        if not isinstance(s, Spectrum):
            raise TypeError(f"wks_energies expects wpot.spectral.Spectrum objects, got {type(s).__name__}")
    spectra = [_wks_spectrum(s, scale_invariant) for s in spectra]
    min_m = int(2 * MARGIN_SIGMAS * SIGMA_PER_DELTA)  # 28: below, the 2σ margins cross (σ = 7R/M)
    if isinstance(n_energies, bool) or not isinstance(n_energies, (int, np.integer)) or n_energies <= min_m:
        raise ValueError(
            f"n_energies must be an integer > {min_m} (with σ = 7δ and 2σ margins the §3.2 grid is empty "
            f"otherwise; paper: 200), got {n_energies!r}"
        )
    lo = max(float(np.log(positive_evals(s, "a WKS")[0])) for s in spectra)
    hi = min(float(np.log(positive_evals(s, "a WKS")[-1])) for s in spectra)
    if not hi > lo:
        raise ValueError(
            f"the spectra do not overlap: the largest first eigenvalue exp({lo:.3g}) is above the smallest "
            f"last eigenvalue exp({hi:.3g}); compute more eigenpairs"
            + ("" if scale_invariant else ", or check that the meshes share one unit of length (or use scale_invariant=True)")
        )
    narrowest = min(float(np.log(positive_evals(s, "a WKS")[-1] / positive_evals(s, "a WKS")[0])) for s in spectra)
    if (hi - lo) < MIN_SHARED_BAND * narrowest:
        areas = [s.area for s in spectra]
        warnings.warn(
            f"the shapes' spectra share only {(hi - lo) / narrowest:.0%} of their log-eigenvalue band (the energy grid "
            f"spans exp({lo:.3g})..exp({hi:.3g})), so WKS sees a narrow range of scales and matches less well"
            + (f". Their areas range over {min(areas):.4g}..{max(areas):.4g} (x{max(areas) / min(areas):.3g}): if the "
               "meshes are not in one unit of length, pass scale_invariant=True (CLI --scale-invariant); "
               "otherwise compute more eigenpairs (n_eigen)" if not scale_invariant else
               "; compute more eigenpairs (n_eigen)"),
            WKSWarning,
            stacklevel=2,
        )
    delta = (hi - lo) / int(n_energies)
    sigma = SIGMA_PER_DELTA * delta
    energies = np.linspace(lo + MARGIN_SIGMAS * sigma, hi - MARGIN_SIGMAS * sigma, int(n_energies))
    energies.setflags(write=False)
    return EnergyGrid(energies, float(sigma))


def sigma_of_grid(energies: ArrayLike) -> float:
    """σ of a grid built by `wks_energies`, recovered from the grid alone.

    The grid spans ``e_M − e_1 = R − 4σ`` with ``σ = 7R/M``, so ``σ = 7 (e_M − e_1) / (M − 28)``.
    Defined for evenly spaced, increasing grids with M > 28; otherwise pass ``sigma`` explicitly.
    """
    e = np.asarray(energies, dtype=np.float64)
    m = e.size
    if e.ndim != 1 or m <= SIGMA_PER_DELTA * 2 * MARGIN_SIGMAS or not np.all(np.isfinite(e)):
        raise ValueError(
            f"cannot infer sigma from an energy grid of shape {e.shape} (needs a finite 1-D grid of more than "
            f"{int(SIGMA_PER_DELTA * 2 * MARGIN_SIGMAS)} energies); pass sigma (from wks_energies)"
        )
    step = np.diff(e)
    span = e[-1] - e[0]
    if not (span > 0 and np.allclose(step, span / (m - 1), rtol=1e-9, atol=0)):
        raise ValueError("cannot infer sigma: energies are not an evenly spaced increasing grid; pass sigma")
    return float(SIGMA_PER_DELTA * span / (m - SIGMA_PER_DELTA * 2 * MARGIN_SIGMAS))


def wks_from_eigenpairs(evals: ArrayLike, evecs: ArrayLike, energies: ArrayLike, sigma: float) -> np.ndarray:
    """The WKS (Eq. 5) as a pure function of eigenpairs and an energy grid.

    Parameters
    ----------
    evals : (K,) float64, strictly positive eigenvalues E_k (the zero eigenvalue(s) already removed).
    evecs : (N, K) float64, their eigenvectors φ_k (M-orthonormal).
    energies : (M,) float64 log-energies e.
    sigma : σ > 0, the Gaussian width in log-energy.

    Returns
    -------
    (N, M) float64, ``WKS[x, m] = C_m Σ_k φ_k(x)² exp(−(e_m − log E_k)²/(2σ²))``: the squared eigenvectors
    times `wks_weights`.
    """
    ev, vec, e = check_eigenpairs(evals, evecs, energies, "energies")
    return np.square(vec) @ wks_weights(ev, e, sigma)


def wks_weights(evals: ArrayLike, energies: ArrayLike, sigma: float) -> np.ndarray:
    """(K, M) float64: the weight of each squared eigenvector φ_k² in the WKS at each energy,
    ``C_m exp(−(e_m − log E_k)²/(2σ²))`` (`wks_from_eigenpairs`; the WKS is linear in the φ_k², so whatever is
    linear in a descriptor can be computed once per φ_k² and weighed). ``evals`` (K,) strictly positive,
    ``energies`` (M,). Computed with the weights of each energy rescaled by their largest value (which C_m cancels
    exactly), so an energy far from every eigenvalue gives finite values (the nearest eigenvalue's), never NaN."""
    ev, e = np.asarray(evals, dtype=np.float64), np.asarray(energies, dtype=np.float64)
    sigma = float(sigma)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive finite number, got {sigma}")
    log_e = np.log(ev)
    if e.min() < log_e[0] - 3 * sigma or e.max() > log_e[-1] + 3 * sigma:
        warnings.warn(
            f"energies [{e.min():.3g}, {e.max():.3g}] reach more than 3 sigma outside the log-spectrum "
            f"[{log_e.min():.3g}, {log_e.max():.3g}]; WKS there only reflects the extreme eigenpairs. "
            "Build the grid with wks_energies from the same spectra.",
            WKSWarning,
            stacklevel=3,
        )
    expo = -((e[None, :] - log_e[:, None]) ** 2) / (2.0 * sigma * sigma)  # (K, M)
    expo -= expo.max(axis=0, keepdims=True)
    g = np.exp(expo)  # (K, M), column max = 1
    return g / g.sum(axis=0, keepdims=True)  # C_e


def wks(
    mesh_or_spectrum: Mesh | Spectrum,
    *,
    n_eigen: int = 500,
    n_energies: int = 200,
    energies: ArrayLike | None = None,
    sigma: float | None = None,
    scale_invariant: bool = False,
    cache: "Cache | bool" = True,
) -> np.ndarray:
    """Wave kernel signature of every vertex (paper Eq. 5, parameters of §3.2).

    Parameters
    ----------
    mesh_or_spectrum : a `Mesh` (its spectrum is computed, or read from the cache) or a `Spectrum` from
        `wpot.eigenpairs` (then ``n_eigen`` is not used).
    n_eigen : number of eigenpairs including the zero one(s) (paper: 500). A mesh with fewer vertices
        uses all N eigenpairs, with a `WKSWarning`.
    n_energies : M, the number of energies when the grid is built here (paper: 200).
    energies, sigma : a shared grid from `wks_energies`. Needed whenever two shapes' signatures are
        compared (Eq. 29 assumes the same energies). Without ``energies``, the grid of this shape alone
        is used. With ``energies`` but no ``sigma``, σ is recovered from the grid (`sigma_of_grid`,
        exact for grids made by `wks_energies`).
    scale_invariant : False (default, the paper): the spectrum of the mesh at its own size, so size
        matters; True: of the mesh scaled to area 1. A shared grid must come from `wks_energies` with the
        same value. See the module docstring.
    cache : where a mesh's spectrum is cached, as in `wpot.eigenpairs` (True: the process-wide cache, on disk
        under ``$WPOT_CACHE_DIR``; a `wpot.cache.Cache`; False: none).

    Returns
    -------
    (N, M) float64, nonnegative; the zero eigenvalue(s) (one per connected component) are excluded.
    """
    spectrum = mesh_spectrum(mesh_or_spectrum, n_eigen, cache, "wks", WKSWarning)
    spectrum = _wks_spectrum(spectrum, scale_invariant)
    if energies is None:
        if sigma is not None:
            raise ValueError(f"sigma={sigma!r} was given without energies; pass both (from wks_energies) or neither")
        energies, sigma = wks_energies(spectrum, n_energies=n_energies, scale_invariant=scale_invariant)
    elif sigma is None:
        sigma = sigma_of_grid(energies)
    ev = positive_evals(spectrum, "a WKS")
    return wks_from_eigenpairs(ev, spectrum.nonzero_evecs, energies, sigma)


# ---------------------------------------------------------------------------------------------- the registered signature
#: the smallest number of energies with a non-empty §3.2 grid (σ = 7δ and 2σ margins)
MIN_ENERGIES = int(2 * MARGIN_SIGMAS * SIGMA_PER_DELTA) + 1


@dataclass(frozen=True)
class WKSOptions(SpectralOptions):
    """Settings of `WKS` (paper §3.2): ``n_eigen`` and ``scale_invariant`` (`SpectralOptions`), and

    Attributes
    ----------
    n_energies : M, the energies of the grid (paper: 200); more than 28 (`wks_energies`).
    """

    n_energies: int = option(200, keyword="n_energies", flag="--n-energies", help="energies (default {default})")

    def __post_init__(self) -> None:
        super().__post_init__()
        try:
            n_energies = integer_at_least("n_energies", self.n_energies, MIN_ENERGIES)
        except ValueError:
            raise ValueError(
                f"n_energies must be an integer > {MIN_ENERGIES - 1} (with σ = 7δ and 2σ margins the §3.2 grid is empty "
                f"otherwise; paper: 200), got {self.n_energies!r}"
            ) from None
        object.__setattr__(self, "n_energies", n_energies)


@register_signature
class WKS(SpectralSignature):
    """The wave kernel signature (paper §2.3, Eq. 5) as a registered `Signature`: (N, n_energies) per mesh,
    compared by Eq. 29 (``metric="wks"``).

    Its state is the energy grid shared by every shape of a comparison or dataset (§3.2): ``{"energies": (M,)}``,
    given as ``state`` or fitted by `fit` / `fit_from` (`wks_energies` over the shapes' spectra). `fit_input` is
    a shape's `Spectrum` without eigenvectors, computed with ``min(n_eigen, N)`` eigenpairs through
    `wpot.spectral.eigenpairs` and the instance's ``spectrum_cache``, so the eigenvectors wait in that cache for
    the signature itself. σ is recovered from the grid (`sigma_of_grid`).
    """

    name = "wks"
    title = "WKS"
    metric = "wks"
    version = VERSION
    Options = WKSOptions
    state_keys = ("energies",)

    @classmethod
    def check_state(cls, state: Mapping[str, Any]) -> dict[str, np.ndarray]:
        out = super().check_state(state)
        e = out["energies"]
        if e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError(f"energies must be a finite increasing grid of at least 2 values, got {e.size} values")
        return out

    @property
    def energies(self) -> np.ndarray | None:
        """The shared energy grid (M,) float64, read-only, or None until fitted."""
        return self.state_array("energies")

    def fit_from(self, inputs: Sequence[Spectrum]) -> None:
        """Fit the grid to these spectra (`wks_energies` with this instance's ``n_energies`` and ``scale_invariant``)."""
        o = self.options
        self.set_state({"energies": wks_energies(list(inputs), n_energies=o.n_energies, scale_invariant=o.scale_invariant).energies})

    def evaluate(self, mesh: Mesh) -> np.ndarray:
        """(N, n_energies) float64, `wks` of ``mesh`` on the fitted grid."""
        o = self.options
        return np.asarray(wks(mesh, n_eigen=o.n_eigen, n_energies=o.n_energies, energies=self.energies,
                              scale_invariant=o.scale_invariant, cache=self.spectrum_cache), dtype=np.float64)
