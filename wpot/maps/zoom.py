"""The ZoomOut iteration (Melzi et al. 2019) between two meshes: at growing spectral resolution k, the functional
map of the current point map, then the point map of that functional map (see `wpot.maps.zoomout` for the method
and its public entry point, `zoomout`). Meshes of several components are refined component by component."""
from __future__ import annotations

from typing import Callable

import numpy as np

from wpot.cache import Cache
from wpot.maps.fmap import SpectralOperators, point_map
from wpot.mesh import Mesh
from wpot.sampling import farthest_point_sampling
from wpot.spectral import eigenpairs

__all__ = ["Refiner", "ZOOMOUT_K_START", "ZOOMOUT_MIN_EIGEN", "ZOOMOUT_N_EIGEN", "ZOOMOUT_SAMPLES", "ZOOMOUT_STEP", "positive_int", "spectral_basis",
           "spectrum_size"]

#: the most eigenpairs `spectrum_size` gives a mesh: the WKS default, so that on meshes of 5,000 vertices and
#: more the spectrum a WKS comparison computed (and cached) serves
ZOOMOUT_N_EIGEN = 500
#: the fewest (the vertex count when smaller)
ZOOMOUT_MIN_EIGEN = 100
#: default first spectral resolution and step of the rounds (`wpot.maps.zoomout.zoomout`'s ``k_start``, ``step``)
ZOOMOUT_K_START = 10
ZOOMOUT_STEP = 5
#: default vertices per mesh in the rounds before the last (farthest-point samples; the last round maps every
#: vertex): on TOSCA's 5,000-vertex shapes, the accuracy of every vertex in every round in much less time
#: (the docs' Results page)
ZOOMOUT_SAMPLES = 2000
#: the rounds' farthest-point samples, keyed by mesh content and their count: an all-against-all samples each
#: shape once
sample_cache = Cache("zoomout_samples", max_entries=256, max_bytes=32 << 20)


def spectrum_size(n_vertices: int) -> int:
    """Eigenpairs that `zoomout` and `wpot.maps.symmetry.reflection_symmetry` read for a mesh of ``n_vertices``:
    a tenth of the vertices, at least `ZOOMOUT_MIN_EIGEN` and at most `ZOOMOUT_N_EIGEN` (never more than the
    vertices). An eigenfunction beyond about N/10 has a wavelength of a few edges, which the mesh resolves
    poorly: on meshes of about 800 vertices, WKS descriptors from 500 eigenpairs lose the left/right symmetry
    that 100 find. The count depends on the mesh alone, never on what a cache holds, so results do not depend
    on which comparisons ran before."""
    n = int(n_vertices)
    return min(n, max(ZOOMOUT_MIN_EIGEN, min(ZOOMOUT_N_EIGEN, n // 10)))


def positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


class Refiner:
    """ZoomOut rounds between two meshes with fixed ``n_eigen`` and ``samples`` (see `wpot.maps.zoomout.zoomout`):
    ``refiner(t, k_start, k_end, step)`` refines the map t (N_A,) int64 from k_start to k_end and returns the new
    (N_A,) int64 map, component by component when a mesh has several. For two connected meshes, `points`,
    `coarse` and `full` split that into the rounds on the samples and the last map of every vertex, so that
    several maps can be brought to one resolution and compared before any maps every vertex."""

    def __init__(self, mesh_a: Mesh, mesh_b: Mesh, n_eigen: int | None, samples: int | None):
        self.mesh_a, self.mesh_b, self.n_eigen, self.samples = mesh_a, mesh_b, n_eigen, samples
        self._bases: dict[int, np.ndarray] = {}  # each mesh's eigenvectors, read once
        self._factors: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # `coarse`'s fits on A's points, by k

    def with_samples(self, samples: int | None) -> "Refiner":
        """This refiner on ``samples`` samples a mesh (itself when that is its own count), sharing the bases it
        has read."""
        if samples == self.samples:
            return self
        other = Refiner(self.mesh_a, self.mesh_b, self.n_eigen, samples)
        other._bases = self._bases
        return other

    def sample(self, mesh: Mesh) -> np.ndarray | None:
        """(samples,) int64 farthest-point samples (Euclidean) of ``mesh``, or None when every vertex is used."""
        if self.samples is None or self.samples >= mesh.n_vertices:
            return None
        params = {"samples": self.samples, "metric": "euclidean"}
        return sample_cache.get_or_compute(mesh.fingerprint, params, lambda: {
            "indices": farthest_point_sampling(mesh, self.samples, metric="euclidean").indices})["indices"]

    def points(self, mesh: Mesh) -> np.ndarray:
        """The vertices of ``mesh`` that `coarse` maps: its samples, or every vertex."""
        s = self.sample(mesh)
        return np.arange(mesh.n_vertices) if s is None else s

    def _phi(self, mesh: Mesh, k: int) -> np.ndarray:
        if id(mesh) not in self._bases:
            self._bases[id(mesh)] = spectral_basis(mesh, self.n_eigen).evecs
        return self._bases[id(mesh)][:, :k]

    def coarse(self, init: np.ndarray, k0: int, k1: int, dk: int) -> tuple[np.ndarray, np.ndarray]:
        """The rounds k0, k0 + dk, ..., k1 on the `points` of two connected meshes: ``init`` (n_A,) maps A's
        points to vertices of B. Returns the (k1, k1) functional map fitted (least squares) at k1, and A's points
        mapped by it onto B's."""
        a, b = self.points(self.mesh_a), self.points(self.mesh_b)
        phi_a, phi_b = np.ascontiguousarray(self._phi(self.mesh_a, k1)[a]), self._phi(self.mesh_b, k1)
        if k1 not in self._factors:  # several maps brought to one k1 share it
            self._factors[k1] = _least_squares(phi_a)
        fmap = _sample_rounds(phi_a, phi_b, init, b, _schedule(k0, k1, dk), self._factors[k1])
        return fmap, b[point_map(phi_a, phi_b[b], fmap)]

    def full(self, fmap: np.ndarray) -> np.ndarray:
        """(N_A,) int64: every vertex of A mapped by the (k, k) functional map ``fmap``."""
        k = fmap.shape[0]
        return point_map(self._phi(self.mesh_a, k), self._phi(self.mesh_b, k), fmap)

    def __call__(self, init: np.ndarray, k0: int, k1: int, dk: int) -> np.ndarray:
        a, b = self.mesh_a, self.mesh_b
        if a.n_components == 1 and b.n_components == 1:
            return _zoom(a, b, init, k0, k1, dk, self.n_eigen, sample=self.sample)
        return _zoom_components(a, b, init, k0, k1, dk, self.n_eigen, self.sample)


def spectral_basis(mesh: Mesh, n_eigen: int | None):
    """The eigenpairs ZoomOut uses: ``n_eigen``, by default `spectrum_size`, from the spectrum cache when they
    are there. Always that many, whatever else is cached (a larger cached spectrum would change the WKS
    descriptors of `wpot.maps.zoomout`'s oriented candidate and with them the map)."""
    return eigenpairs(mesh, spectrum_size(mesh.n_vertices) if n_eigen is None else n_eigen)


def _schedule(k_start: int, k_end: int, step: int) -> list[int]:
    ks = list(range(k_start, k_end + 1, step))
    if ks[-1] != k_end:
        ks.append(k_end)
    return ks


def _least_squares(phi_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Qᵀ, R⁻¹)`` of the QR factorization of ``phi_a`` (n, K), which serve the least-squares fits of
    `_sample_rounds` at every k ≤ K: the first k columns of phi_a are Q[:, :k] R[:k, :k], and the leading k × k
    block of R⁻¹ is the inverse of R's leading block (R is upper triangular)."""
    q, r = np.linalg.qr(phi_a)
    # numpy's own LAPACK: a call into SciPy's (a second OpenBLAS with its own threads) leaves those threads
    # competing with numpy's for the rounds' products that follow
    return np.ascontiguousarray(q.T), np.linalg.inv(r)


def _sample_rounds(phi_a: np.ndarray, phi_b: np.ndarray, ts: np.ndarray, sb: np.ndarray, ks: list[int],
                   factors: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """ZoomOut rounds on samples. ``phi_a`` (n_A, K): A's basis at its samples; ``phi_b`` (N_B, K): B's at every
    vertex; ``ts`` (n_A,): the samples' images (vertices of B); ``sb``: B's samples. At each k of ``ks``, the
    (k, k) functional map fitted to the samples' map by least squares, and but for the last k the samples
    mapped by it onto B's samples. ``factors``: `_least_squares` of ``phi_a[:, :ks[-1]]`` when the caller has
    it. Returns the last functional map."""
    phi_a, at_sb = np.ascontiguousarray(phi_a[:, :ks[-1]]), np.ascontiguousarray(phi_b[sb, :ks[-1]])
    # one factorization serves every k, and each round is two small products (small BLAS calls are slow when
    # threaded)
    qt, r_inv = _least_squares(phi_a) if factors is None else factors
    for n, k in enumerate(ks):
        fmap = r_inv[:k, :k] @ (qt[:k] @ phi_b[ts, :k])
        if n < len(ks) - 1:
            ts = sb[point_map(phi_a[:, :k], at_sb[:, :k], fmap)]
    return fmap


def _zoom(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray, k_start: int, k_end: int, step: int, n_eigen: int | None,
          valid: np.ndarray | None = None, sample: Callable[[Mesh], np.ndarray | None] | None = None
          ) -> np.ndarray:
    """ZoomOut between two connected meshes: t (N_A,) int64 → (N_A,) int64. ``valid`` (N_A,) bool, optional:
    the vertices of A whose map enters the first functional map (the others' entries of t are ignored).
    ``sample``: a mesh's sampled vertices (or None: every vertex); with both meshes sampled, the rounds before
    the last map only the samples onto each other, and fit the functional map to them by least squares; the
    last round maps every vertex with that fit, and once more with the fit to every vertex."""
    ops_a, ops_b = (SpectralOperators(m, spectral_basis(m, n_eigen), k_end) for m in (mesh_a, mesh_b))
    phi_a, phi_b = ops_a.phi, ops_b.phi
    ks = _schedule(k_start, k_end, step)
    sa, sb = (None, None) if sample is None else (sample(mesh_a), sample(mesh_b))
    if sa is not None and sb is not None and len(ks) > 1:
        if valid is not None:
            sa = sa[valid[sa]]
        fmap = _sample_rounds(phi_a[sa], phi_b, t[sa], sb, ks)
        t, ks, valid = point_map(phi_a, phi_b, fmap), ks[-1:], None
    weighted_a = ops_a.pinv.T  # Φ_A^T (M_A / area) = the pseudo-inverse of Φ_A
    first = weighted_a if valid is None else weighted_a * valid[:, None]
    t = np.where(valid, t, 0) if valid is not None else t
    for n, k in enumerate(ks):
        fmap = (first if n == 0 else weighted_a)[:, :k].T @ phi_b[t, :k]  # (k, k): B's coefficients -> A's
        t = point_map(phi_a[:, :k], phi_b[:, :k], fmap)
    return t


def _component(mesh: Mesh, labels: np.ndarray, c: int) -> tuple[Mesh, np.ndarray]:
    """Component ``c`` of ``mesh`` as a mesh of its own, and its vertices' indices (n_c,) in ``mesh``."""
    idx = np.nonzero(labels == c)[0]
    local = np.full(mesh.n_vertices, -1, dtype=np.int64)
    local[idx] = np.arange(idx.size)
    return Mesh(mesh.vertices[idx], local[mesh.faces[labels[mesh.faces[:, 0]] == c]]), idx


def _zoom_components(mesh_a: Mesh, mesh_b: Mesh, t: np.ndarray, k_start: int, k_end: int, step: int,
                     n_eigen: int | None, sample: Callable[[Mesh], np.ndarray | None] | None = None) -> np.ndarray:
    """ZoomOut component by component (see the module docstring): each component of A against the component of
    B that most of its vertices map to."""
    la, lb = mesh_a.component_labels, mesh_b.component_labels
    out = t.copy()
    parts_b: dict[int, tuple[Mesh, np.ndarray]] = {}
    for ca in np.unique(la):
        sub_a, ia = _component(mesh_a, la, int(ca))
        cb = int(np.argmax(np.bincount(lb[t[ia]])))
        if cb not in parts_b:
            parts_b[cb] = _component(mesh_b, lb, cb)
        sub_b, ib = parts_b[cb]
        n_loc = min(ia.size, ib.size)
        if n_loc < 3 or sub_a.n_faces == 0 or sub_b.n_faces == 0:
            continue
        local_b = np.full(mesh_b.n_vertices, -1, dtype=np.int64)
        local_b[ib] = np.arange(ib.size)
        t_loc = local_b[t[ia]]
        # each component's own spectrum: `spectrum_size` of its vertices (the whole mesh's may be larger)
        ke = min(k_end, spectrum_size(min(sub_a.n_vertices, sub_b.n_vertices)) if n_eigen is None
                 else min(n_eigen, n_loc))
        out[ia] = ib[_zoom(sub_a, sub_b, t_loc, min(k_start, ke), ke, step,
                           None if n_eigen is None else min(n_eigen, n_loc), valid=t_loc >= 0, sample=sample)]
    return out
