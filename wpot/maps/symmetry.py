"""A shape's left/right (reflective) symmetry, and maps made to keep orientation with it.

* `reflection_symmetry`: the self-map that exchanges a shape's left and right. Each vertex is sent to the
  vertex of the most similar WKS signature that is not near it (its mirror image has the same WKS), and
  ZoomOut makes that map consistent; it is kept only when it reverses orientation (score below
  ``-min_score``, `wpot.maps.orientation.orientation_score`) and moves the shape (it is not the identity).
  WKS cannot tell the mirror from a self-map that keeps orientation, and at ZoomOut's first resolutions
  neither can the spectrum: on a body whose limbs are posed apart, plain ZoomOut can settle on a half turn
  (left to right *and* front to back, a near-isometry of a torso that keeps orientation) however close it
  starts to the mirror. So when plain ZoomOut finds no mirror, it runs again with its rounds up to
  k = `ORIENTED_K` also asking that each vertex's image carry the negatives of its
  `wpot.maps.fmap.pseudoscalars` (``⟨n, ∇f × ∇g⟩`` for pairs of WKS functions f, g at `PSEUDO_ENERGIES`): the
  mirror turns them around, a half turn does not. Only then: where plain ZoomOut finds a mirror, the guided
  rounds find one nearer the truth, but with that mirror `locate`'s choice of side, a near-tie in signature
  cost for some parts, takes their mirror side (the docs' Results page, §6).
* `keep_orientation`: the vertices where a map is mirrored (`wpot.maps.orientation.local_orientation`) are sent
  where the map sends their mirror images (A's symmetry, else B's), the result is refined (ZoomOut), and the
  better-scoring map is returned.

The symmetry is cached per mesh content (memory, and disk under ``$WPOT_CACHE_DIR``), so an all-against-all
detects it once per shape.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike

from wpot._validate import integer_at_least, one_of, vertex_map
from wpot.cache import Cache
from wpot.maps.orientation import LOCAL_RADIUS, map_score, orientation_terms, spread, terms_score
from wpot.cost import nearest_rows
from wpot.maps.fmap import SpectralOperators, pseudoscalars
from wpot.maps.zoom import ZOOMOUT_K_START, ZOOMOUT_SAMPLES, ZOOMOUT_STEP, Refiner, spectral_basis, spectrum_size
from wpot.mesh import Mesh, winding
from wpot.signatures import wks
from wpot.spectral import eigenpairs

__all__ = ["EXCLUSION", "MIN_SCORE", "ORIENTED_K", "PSEUDO_ENERGIES", "SYMMETRY_K_END", "Symmetry", "keep_orientation",
           "reflection_symmetry", "symmetry_cache"]

#: symmetry maps, keyed by mesh content and the detection settings
symmetry_cache = Cache("symmetry", max_entries=128, max_bytes=64 << 20)
#: a self-map counts as a reflection when its orientation score is below -MIN_SCORE
MIN_SCORE = 0.3
#: candidate mirror partners lie at least this far (times sqrt(area)) from the vertex
EXCLUSION = 0.1
#: ZoomOut's last resolution for the symmetry map (`reflection_symmetry`'s ``k_end``)
SYMMETRY_K_END = 200
#: when plain ZoomOut finds no mirror, the second try's rounds up to this resolution also match the pseudoscalars
#: (the module docstring); from the next on, plain ZoomOut. On FAUST's pose 8, plain ZoomOut started from the true
#: mirror keeps it from k = 50 and leaves it from k = 10 (the docs' Results page, §6)
ORIENTED_K = 50
#: the WKS energies (of `_signature`'s 100, low to high) whose pairs give the pseudoscalars: five spread over the
#: lower half, where the signature describes the body's large parts rather than the mesh's detail
PSEUDO_ENERGIES = (5, 15, 25, 35, 45)
#: version of the detection, part of the cache key
_VERSION = 6


@dataclass(frozen=True)
class Symmetry:
    """A shape's left/right symmetry (`reflection_symmetry`).

    Attributes
    ----------
    map : (N,) int64, the mirror vertex of each vertex (an involution up to the mesh's sampling).
    score : its `orientation_score` against itself (near -1: it reverses orientation).
    displacement : mean distance from a vertex to its mirror image, over sqrt(area).
    residual : how far the map is from an isometry: ``||C Λ - Λ C|| / ||C Λ||`` for its functional map C on
        the first 10 non-constant eigenfunctions (eigenvalues Λ); 0 for an exact symmetry. Only a weak test:
        a reversing self-map that ZoomOut finds on a surface without symmetry scores nearly as low as the
        symmetry of a mirror-symmetric shape (the docs' Results page).
    """

    map: np.ndarray
    score: float
    displacement: float
    residual: float


def _signature(spec) -> np.ndarray:
    """WKS on 100 energies, each energy scaled to unit RMS (the mirror test compares shapes of the signature,
    not its magnitude)."""
    sig = wks(spec, n_energies=100)
    return sig / np.maximum(np.sqrt((sig * sig).mean(axis=0, keepdims=True)), 1e-300)


def _commutator_residual(mesh: Mesh, spec, t: np.ndarray, k: int = 10) -> float:
    mass = mesh.voronoi_areas
    lo = spec.n_zero
    phi, lam = spec.evecs[:, lo:lo + k], spec.evals[lo:lo + k]
    c = (phi * (mass / mass.sum())[:, None]).T @ phi[t]
    return float(np.linalg.norm(c * (lam[:, None] - lam[None, :])) / np.linalg.norm(c * lam[None, :]))


def _mirror_candidates(mesh: Mesh, sig: np.ndarray, exclusion: float, block: int = 1024) -> np.ndarray:
    """For each vertex, the vertex of the nearest signature among those farther than ``exclusion`` sqrt(area)."""
    v = mesh.vertices
    r2 = (exclusion * np.sqrt(mesh.area)) ** 2
    ss = np.einsum("ij,ij->i", sig, sig)
    vv = np.einsum("ij,ij->i", v, v)
    out = np.empty(mesh.n_vertices, dtype=np.int64)
    for s in range(0, mesh.n_vertices, block):
        d = ss[None, :] - 2.0 * (sig[s:s + block] @ sig.T)
        near = (vv[None, :] - 2.0 * (v[s:s + block] @ v.T) + vv[s:s + block, None]) < r2
        d[near] = np.inf
        out[s:s + block] = np.argmin(d, axis=1)
    return out


def _reversing_rounds(mesh: Mesh, sig: np.ndarray, t: np.ndarray, k_end: int) -> np.ndarray:
    """ZoomOut's rounds k = `ZOOMOUT_K_START`, ..., ``k_end`` (step `ZOOMOUT_STEP`) on every vertex of a connected
    mesh, each vertex mapped to the one whose spectral embedding (carried by the round's functional map) is
    nearest *and* whose pseudoscalars are nearest the negatives of its own (the module docstring). The two
    parts weigh alike: the pseudoscalars are scaled to unit RMS and their block to the embedding's √k.
    ``sig`` (N, 100) `_signature`; ``t`` (N,) the start map; the basis is the ZoomOut rounds' that follow
    (`wpot.maps.zoom.spectral_basis`). Returns (N,) int64."""
    h = pseudoscalars(mesh, sig[:, list(PSEUDO_ENERGIES)])
    h /= np.maximum(np.sqrt((h * h).mean(axis=0, keepdims=True)), 1e-300)
    ops = SpectralOperators(mesh, spectral_basis(mesh, None), k_end)
    phi = ops.phi
    for k in range(ZOOMOUT_K_START, k_end + 1, ZOOMOUT_STEP):
        fmap = ops.pinv[:k] @ phi[t, :k]
        w = np.sqrt(k / h.shape[1])
        t = nearest_rows(np.hstack([phi[:, :k], w * h]), np.hstack([phi[:, :k] @ fmap.T, -w * h]))[0]
    return t


def reflection_symmetry(mesh: Mesh, *, n_eigen: int | None = None, min_score: float = MIN_SCORE,
                        exclusion: float = EXCLUSION, k_end: int = SYMMETRY_K_END, oriented_k: int = ORIENTED_K,
                        cache: bool = True) -> Symmetry | None:
    """The self-map exchanging left and right of a mirror-symmetric shape, or None when none is found.

    Parameters
    ----------
    mesh : the shape (one connected, consistently wound surface)
    n_eigen : eigenpairs for the WKS and ZoomOut (the vertex count when fewer); default
        `wpot.maps.zoomout.spectrum_size` (500, WKS's, from 5,000 vertices up, so that a WKS comparison's cached
        spectrum serves). Whatever else is cached, the result depends on the mesh and these options alone
    min_score : the map must score below ``-min_score`` (`orientation_score` of the mesh against itself)
    exclusion : a vertex's mirror candidate lies at least this far from it, times sqrt(area)
    k_end : ZoomOut's last spectral resolution for the self-map (`wpot.zoomout`, which starts at 10; fewer
        when ``spectrum_size`` gives fewer eigenpairs)
    oriented_k : when plain ZoomOut finds no mirror, a second try whose rounds up to this resolution also match
        the pseudoscalars (the module docstring; at most ``k_end``); below `ZOOMOUT_K_START` (e.g. 0), no second
        try
    cache : reuse (and store) the result in `symmetry_cache`

    Returns
    -------
    `Symmetry`, or None when the detected self-map does not reverse orientation or barely moves the shape, or
    the mesh's winding cannot be read. A shape with no mirror symmetry may still get a smooth reversing
    self-map that is far from an isometry: its ``residual`` says so (`keep_orientation` only uses a flip that
    scores better than the map it replaces).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    n_eigen = spectrum_size(mesh.n_vertices) if n_eigen is None else integer_at_least("n_eigen", n_eigen, 2)
    k_end = integer_at_least("k_end", k_end, 10)
    oriented_k = integer_at_least("oriented_k", oriented_k, 0)
    params = {"n_eigen": int(n_eigen), "min_score": float(min_score), "exclusion": float(exclusion),
              "k_end": int(k_end), "oriented_k": oriented_k, "version": _VERSION}
    if cache:
        hit = symmetry_cache.get(mesh.fingerprint, params)
        if hit is not None:
            if not bool(hit["found"]):
                return None
            return Symmetry(np.array(hit["map"]), float(hit["score"]), float(hit["displacement"]),
                            float(hit["residual"]))
    found = None
    if winding(mesh) != 0 and mesh.n_vertices >= 8:
        spec = eigenpairs(mesh, min(n_eigen, mesh.n_vertices))  # from the spectrum cache when it is there
        sig = _signature(spec)
        cand = _mirror_candidates(mesh, sig, exclusion)
        ke = min(k_end, spectrum_size(mesh.n_vertices))
        if ke < ZOOMOUT_K_START:
            raise ValueError(f"k_start must be <= k_end, got k_start={ZOOMOUT_K_START}, k_end={ke}")
        refine = Refiner(mesh, mesh, None, ZOOMOUT_SAMPLES)

        def mirror(sym: np.ndarray) -> Symmetry | None:
            score = map_score(mesh, mesh, sym)
            disp = float(np.linalg.norm(mesh.vertices[sym] - mesh.vertices, axis=1).mean() / np.sqrt(mesh.area))
            if score < -min_score and disp > 0.5 * exclusion:
                return Symmetry(sym, score, disp, _commutator_residual(mesh, spec, sym))
            return None

        found = mirror(refine(cand, ZOOMOUT_K_START, ke, ZOOMOUT_STEP))
        if found is None and mesh.n_components == 1 and oriented_k >= ZOOMOUT_K_START:  # (one spectrum)
            k_done = ZOOMOUT_K_START + (min(oriented_k, ke) - ZOOMOUT_K_START) // ZOOMOUT_STEP * ZOOMOUT_STEP
            sym = _reversing_rounds(mesh, sig, cand, k_done)
            found = mirror(refine(sym, min(k_done + ZOOMOUT_STEP, ke), ke, ZOOMOUT_STEP) if k_done < ke else sym)
    if cache:
        entry = {"found": found is not None}
        if found is not None:
            entry.update(map=found.map, score=found.score, displacement=found.displacement,
                         residual=found.residual)
        symmetry_cache.put(mesh.fingerprint, params, entry)
    return found


def keep_orientation(mesh_a: Mesh, mesh_b: Mesh, correspondence: ArrayLike,
                     refine: Callable[[np.ndarray], np.ndarray] | None = None, *, symmetry_of: str = "a"
                     ) -> tuple[np.ndarray, float, bool]:
    """A map A -> B that keeps orientation.

    Where the map reverses orientation (`local_orientation` < 0: the whole map, or a symmetric part of it such
    as both legs), those vertices of A are sent where the map sends their mirror images under A's symmetry
    (``t[S_A(i)]``; with no symmetry found on A, B's: ``S_B(t[i])``); the result is passed through ``refine``
    (e.g. ZoomOut, which also smooths the seams) and kept when its `orientation_score` is higher.
    ``symmetry_of="b"`` uses B's symmetry only: for a part A of a whole B, whose own symmetry (a limb's, a
    head's) need not be the whole's left/right.

    Returns
    -------
    (map (N_A,) int64, its orientation score, whether it was changed).
    """
    one_of("symmetry_of", symmetry_of, ("a", "b"))
    t = vertex_map("correspondence", correspondence, mesh_a.n_vertices, mesh_b.n_vertices)
    terms = orientation_terms(mesh_a, mesh_b, t)  # once: the score and where the map is mirrored
    score = float("nan") if terms is None else terms_score(*terms)
    if np.isnan(score):
        return t, score, False
    wrong = spread(mesh_a, *terms, LOCAL_RADIUS) < 0
    if not wrong.any():
        return t, score, False
    sym = reflection_symmetry(mesh_a) if symmetry_of == "a" else None
    if sym is not None:
        flipped = np.where(wrong, t[sym.map], t)
    else:
        sym = reflection_symmetry(mesh_b)
        if sym is None:
            return t, score, False
        flipped = np.where(wrong, sym.map[t], t)
    if refine is not None:
        flipped = np.asarray(refine(flipped), dtype=np.int64)
    score2 = map_score(mesh_a, mesh_b, flipped)
    if score2 > score:
        return flipped, score2, True
    return t, score, False
