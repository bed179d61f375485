"""Functional maps fitted from descriptors, with an orientation-aware term (Ovsjanikov et al. 2012; Ren et al.
2018), as the start of an orientation-keeping ZoomOut (`wpot.zoomout`).

A functional map C (k × k) carries a function on B, given by its coefficients b in B's first k Laplace–Beltrami
eigenfunctions (g ≈ Φ_B b), to its pull-back on A: g ∘ T ≈ Φ_A (C b), for a vertex map T: A → B. It is the
same (k, k) matrix ZoomOut computes from a point map (`wpot.maps.zoomout`). Here it is fitted without any point map,
from functions that a near-isometry carries over (descriptors f_A ≈ f_B ∘ T, WKS on a shared energy grid), by
linear least squares in its k² entries over four terms, each zero for an exact isometry's map:

* descriptors: ``‖C B − A‖²``, with A, B (k × p) the coefficients of the p descriptors on each shape;
* Laplacian commutativity: ``‖C Λ_B − Λ_A C‖²`` (Λ the first k eigenvalues, over the larger k-th one);
* descriptor commutativity: ``Σ_f ‖C M_B^f − M_A^f C‖²``, with ``M^f = Φᵀ M diag(f) Φ`` the product by f in
  the basis (a map that carries f over carries the products by f);
* orientation: ``Σ_f ‖C O_B^f − O_A^f C‖²``, with ``O^f`` the operator ``g ↦ ⟨n, ∇f × ∇g⟩`` in the basis.
  This is the term that tells left from right: WKS and the other three terms are intrinsic, so they are
  satisfied as well by the map composed with a left/right symmetry, whereas a mirror map turns the
  orientation operator around (``C O_B^f = −O_A^f C``). It needs both surfaces consistently wound with
  a readable outside (`wpot.mesh.winding`); the normals are taken outward on both.

Each operator pair (and the descriptor coefficients) is scaled to a unit mean Frobenius norm, so the weights
are relative and independent of the meshes' size and sampling; the defaults (k = 30, 50 WKS descriptors,
weights 1, 0.1, 1, 1) are those of pyfmaps' quickstart (its scores on the TOSCA test pairs: the docs'
Results page, correspondence). The point map of C is read as in ZoomOut (`point_map`).

The coefficients and both operator families are linear in the descriptor (`DescriptorTerms`), and a WKS
descriptor is a weighted sum of the squared eigenfunctions φ_i² (`wpot.signatures.wks_weights`). So a shape's
terms for its φ_i² (`squared_eigenfunction_terms`, K × k × k per operator family, computed once per shape and
cached) give the terms of the WKS descriptors on any shared energy grid by small products: in an all-against-all
no pair goes back to the faces.
"""
from __future__ import annotations

from dataclasses import dataclass

import hashlib

import numpy as np

from wpot.cache import Cache
from wpot.cost import nearest_rows
from wpot.mesh import NO_OUTSIDE, Mesh, winding

__all__ = ["DescriptorTerms", "FmapEnergy", "SpectralOperators", "squared_eigenfunction_terms", "terms_cache",
           "functional_map", "point_map", "pseudoscalars", "FMAP_K", "FMAP_DESCRIPTORS", "FMAP_SPECTRUM",
           "FMAP_WEIGHTS"]

#: default spectral resolution of the fitted functional map
FMAP_K = 30
#: default number of WKS descriptors (every second one of a 2x finer grid, as pyfmaps does)
FMAP_DESCRIPTORS = 50
#: eigenpairs the descriptors of `wpot.zoomout`'s first functional-map candidate are computed from (the second
#: uses all of them): energies beyond them carry detail a k = 30 basis cannot hold. Chosen on FAUST pairs outside
#: its test list against 200 (pyfmaps') and 500 (WKS's), checked on TOSCA pairs (the docs' Results page)
FMAP_SPECTRUM = 100
#: bytes of one block of the orientation operators' per-face products (faces x descriptors x k floats)
_BLOCK_BYTES = 64 << 20


def point_map(phi_a: np.ndarray, phi_b: np.ndarray, fmap: np.ndarray) -> np.ndarray:
    """The vertex map A -> B of a functional map: each vertex of A goes to the vertex of B whose spectral
    embedding, carried by ``fmap``, is nearest: ``T(i) = argmin_j ‖Φ_A(i) − Φ_B(j) Cᵀ‖``.

    phi_a (N_A, k), phi_b (N_B, k): the bases; fmap (k, k), B's coefficients to A's. Returns (N_A,) int64
    (`nearest_rows`)."""
    return nearest_rows(phi_a, phi_b @ fmap.T)[0]


def _hat_gradients(mesh: Mesh, normals: np.ndarray) -> list[np.ndarray]:
    """The gradients (F, 3) of the hat functions of each face's three corners, on the mesh scaled to area 1;
    ``normals`` (F, 3) the unit face normals that orient each face's edges. The gradient of corner a's hat
    function is n × (edge b → c) / (2 area), the edge opposite a taken counter-clockwise about n; a degenerate
    face has none (zeros)."""
    v = mesh.vertices / np.sqrt(mesh.area)
    f = mesh.faces
    area2 = 2.0 * mesh.face_areas / mesh.area
    ok = area2 > 0
    inv = np.where(ok, 1.0 / np.where(ok, area2, 1.0), 0.0)
    return [np.cross(normals, v[f[:, c]] - v[f[:, b]]) * inv[:, None] for b, c in ((1, 2), (2, 0), (0, 1))]


def _face_gradients(faces: np.ndarray, hats: list[np.ndarray], values: np.ndarray) -> np.ndarray:
    """(F, 3, m) per-face gradients of the piecewise-linear vertex functions ``values`` (N, m), from the hat
    functions' gradients ``hats`` of the same F ``faces`` (`_hat_gradients`)."""
    grad = np.zeros((len(faces), 3, values.shape[1]))
    for a, hat in enumerate(hats):
        grad += hat[:, :, None] * values[faces[:, a]][:, None, :]
    return grad


def pseudoscalars(mesh: Mesh, values: np.ndarray) -> np.ndarray:
    """(N, p(p−1)/2): for each pair i < j of the vertex functions ``values`` (N, p), ``⟨n, ∇f_i × ∇f_j⟩`` with n
    the outward normal, per face (the mesh scaled to area 1), then averaged onto the vertices by face area.

    The orientation operator's integrand, read pointwise: an isometry that carries every f_i to itself carries
    these functions to themselves when it keeps orientation, and to their negatives when it reverses it (a
    left/right reflection). So they tell a mirror map from a map that keeps orientation, which the f_i alone
    (intrinsic, like WKS) cannot. Raises ValueError on a mesh whose outside cannot be read."""
    side = winding(mesh)
    if side == 0:
        raise ValueError(f"pseudoscalars need a closed, consistently wound surface: this mesh {NO_OUTSIDE}")
    values = np.asarray(values, dtype=np.float64)
    normals = mesh.face_normals * side
    grad = _face_gradients(mesh.faces, _hat_gradients(mesh, normals), values)  # (F, 3, p)
    i, j = np.triu_indices(values.shape[1], k=1)
    per_face = np.einsum("fc,fcq->fq", normals, np.cross(grad[:, :, i], grad[:, :, j], axis=1))
    share = per_face * (mesh.face_areas / 3.0)[:, None]  # each corner's third, as `Mesh.vertex_areas` counts it
    out = np.zeros((mesh.n_vertices, len(i)))
    for c in range(3):
        np.add.at(out, mesh.faces[:, c], share)
    return out / np.maximum(mesh.vertex_areas, 1e-300)[:, None]


@dataclass(frozen=True)
class DescriptorTerms:
    """What the functional-map terms need of p descriptors on one shape (`SpectralOperators.terms`). Each is
    linear in the descriptors, so the terms of weighted sums of descriptors are the same sums of theirs
    (`combined`): the WKS is a weighted sum of squared eigenfunctions (`wpot.signatures.wks_weights`), whose
    terms can be computed once per shape and weighed for any energy grid.

    Attributes
    ----------
    coefficients : (k, p) the descriptors' coefficients in the basis
    multiplication : (p, k, k) the product by each descriptor in the basis
    orientation : (p, k, k) the operator ``g ↦ ⟨n, ∇f × ∇g⟩`` of each descriptor, or None when not asked for
    """

    coefficients: np.ndarray
    multiplication: np.ndarray
    orientation: np.ndarray | None = None

    def combined(self, weights: np.ndarray) -> "DescriptorTerms":
        """The terms of the q descriptors ``descriptors @ weights``, weights (p, q)."""
        w = np.asarray(weights, dtype=np.float64)
        k = self.coefficients.shape[0]

        def stack(ops: np.ndarray) -> np.ndarray:
            return (w.T @ ops.reshape(len(ops), k * k)).reshape(-1, k, k)

        return DescriptorTerms(self.coefficients @ w, stack(self.multiplication),
                               None if self.orientation is None else stack(self.orientation))


class SpectralOperators:
    """One mesh's first k eigenpairs and what the functional-map terms need of them, computed once.

    Parameters
    ----------
    mesh : the shape: one connected surface, consistently wound (`wpot.mesh.winding` ≠ 0) when the
        orientation operators are asked for
    spectrum : its `wpot.Spectrum` (area-normalized eigenpairs, at least k)
    k : spectral resolution

    Attributes
    ----------
    phi : (N, k) eigenfunctions, M-orthonormal for the mass over the area
    evals : (k,) their eigenvalues
    pinv : (k, N) ``Φᵀ M / area``, the coefficients of a vertex function
    """

    def __init__(self, mesh: Mesh, spectrum, k: int) -> None:

        if spectrum.evecs.shape[1] < k:
            raise ValueError(f"the spectrum has {spectrum.evecs.shape[1]} eigenpairs, fewer than k={k}")
        self.mesh = mesh
        self.phi = np.ascontiguousarray(spectrum.evecs[:, :k])
        self.evals = np.asarray(spectrum.evals[:k], dtype=np.float64)
        mass = mesh.voronoi_areas
        self.pinv = (self.phi * (mass / mass.sum())[:, None]).T
        self._face_terms: tuple | None = None  # what `orientation` needs of the mesh and basis

    def coefficients(self, values: np.ndarray) -> np.ndarray:
        """(k, m) coefficients of the vertex functions ``values`` (N, m)."""
        return self.pinv @ values

    def multiplication(self, values: np.ndarray) -> np.ndarray:
        """(m, k, k): for each function f of ``values`` (N, m), the product by f in the basis, ``Φᵀ M diag(f) Φ``
        (M over the area)."""
        values = np.asarray(values, dtype=np.float64)
        n, k = self.phi.shape
        out = np.zeros((values.shape[1], k * k))
        block = max(1, _BLOCK_BYTES // (8 * k * k))
        for s in range(0, n, block):  # Σ_v f(v) [M/area Φ](v, k) Φ(v, l), by blocks of vertices
            e = min(s + block, n)
            out += values[s:e].T @ (self.pinv.T[s:e, :, None] * self.phi[s:e, None, :]).reshape(e - s, k * k)
        return out.reshape(-1, k, k)

    def terms(self, values: np.ndarray, *, orientation: bool = True) -> DescriptorTerms:
        """`DescriptorTerms` of the vertex functions ``values`` (N, p): their `coefficients`, `multiplication`
        and, when asked, `orientation` operators."""
        return DescriptorTerms(self.coefficients(values), self.multiplication(values),
                               self.orientation(values) if orientation else None)

    def orientation(self, values: np.ndarray) -> np.ndarray:
        """(m, k, k): for each function f of ``values`` (N, m), the operator ``g ↦ ⟨n, ∇f × ∇g⟩`` in the basis,
        with n the outward normal (per face, integrated over the faces: each face gives a third of its area to
        each corner). Entry (k, l) is ``Σ_faces ⟨n × ∇f, ∇φ_l⟩ ∫φ_k``, both gradients constant on a face; the
        faces go by blocks of `_BLOCK_BYTES` (faces × m × k floats). Raises ValueError on a mesh
        whose outside cannot be read."""
        mesh = self.mesh
        side = winding(mesh)
        if side == 0:
            raise ValueError(f"the orientation operators need a closed, consistently wound surface: this mesh "
                             f"{NO_OUTSIDE}")
        if self._face_terms is None:
            normals = mesh.face_normals * side
            share = mesh.face_areas / mesh.area / 3.0
            corners = self.phi[mesh.faces].sum(axis=1) * share[:, None]  # ∫φ_k over each face, (F, k)
            hats = _hat_gradients(mesh, normals)
            self._face_terms = (normals, hats, corners, _face_gradients(mesh.faces, hats, self.phi))
        normals, hats, corners, grad_phi = self._face_terms  # ∇φ_l: (F, 3, k)
        values = np.asarray(values, dtype=np.float64)
        k, m, f = self.phi.shape[1], values.shape[1], mesh.faces
        out = np.zeros((k, m * k))
        block = max(1, _BLOCK_BYTES // (8 * m * k))
        for s in range(0, len(f), block):
            e = min(s + block, len(f))
            grad_f = _face_gradients(f[s:e], [h[s:e] for h in hats], values)  # (faces, 3, m)
            rot = np.cross(normals[s:e, :, None], grad_f, axis=1)  # n × ∇f
            g = np.matmul(rot.transpose(0, 2, 1), grad_phi[s:e])  # ⟨n × ∇f, ∇φ_l⟩, (faces, m, k)
            out += corners[s:e].T @ g.reshape(e - s, m * k)
        return out.reshape(k, m, k).transpose(1, 0, 2)


#: each shape's `DescriptorTerms` of its squared eigenfunctions (`squared_eigenfunction_terms`), keyed by its
#: content, k and a digest of its eigenpairs: an all-against-all computes them once per shape
terms_cache = Cache("fmap_terms", max_entries=64, max_bytes=256 << 20)


def squared_eigenfunction_terms(ops: SpectralOperators, spectrum) -> DescriptorTerms:
    """`DescriptorTerms` (with the orientation operators) of the squared eigenfunctions φ_i² of the nonzero
    eigenpairs of ``spectrum`` (a `wpot.Spectrum` of ``ops``' mesh, area-normalized), (N, K) as descriptors.
    Every WKS descriptor of the shape is their weighted sum (`wpot.signatures.wks_weights`), so
    ``terms.combined(weights)`` gives its terms for any energy grid at the cost of a few small products.
    Cached in `terms_cache` (memory, and disk under ``$WPOT_CACHE_DIR``)."""
    spectrum = spectrum.rescaled(normalized=True)
    vec = spectrum.nonzero_evecs
    # the eigenpairs' digest: their eigenvalues and about a hundred rows of each basis (two spectra of one mesh
    # that agree there are the same), a few hundred kB to hash rather than the whole (N, K)
    step = max(1, len(vec) // 100)
    h = hashlib.sha1(np.ascontiguousarray(spectrum.evals))
    for rows in (vec[::step], ops.phi[::step]):
        h.update(np.ascontiguousarray(rows))
    params = {"k": ops.phi.shape[1], "n_functions": vec.shape[1], "eigenpairs": h.hexdigest()[:16], "version": 2}

    def compute() -> dict[str, np.ndarray]:
        t = ops.terms(np.square(vec))
        return {"coefficients": t.coefficients, "multiplication": t.multiplication, "orientation": t.orientation}

    e = terms_cache.get_or_compute(ops.mesh.fingerprint, params, compute)
    return DescriptorTerms(e["coefficients"], e["multiplication"], e["orientation"])


def _normalized(xs: np.ndarray, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Operator pairs (m, k, k) each, each pair scaled to a unit mean Frobenius norm."""
    s = 0.5 * (np.linalg.norm(xs, axis=(1, 2)) + np.linalg.norm(qs, axis=(1, 2)))
    s = np.where(s > 0, s, 1.0)[:, None, None]
    return xs / s, qs / s


def _commutator_normal(xs: np.ndarray, qs: np.ndarray, out: np.ndarray, weight: float) -> None:
    """Add ``weight Σ_f Lᵀ L`` to ``out`` (k², k²), for the linear maps ``L(C) = C X_f − Q_f C`` on vec(C)
    (column-major).

    With ``vec(C X) = (Xᵀ ⊗ I) vec C`` and ``vec(Q C) = (I ⊗ Q) vec C``:
    ``LᵀL = (X Xᵀ) ⊗ I + I ⊗ (QᵀQ) − X ⊗ Q − Xᵀ ⊗ Qᵀ``; the last two are one matrix product, read in two orders.
    A single pair of diagonal operators (the Laplacian's eigenvalues) gives a diagonal ``(x_a − q_i)²``."""
    m, k, _ = xs.shape
    h4, d = out.reshape(k, k, k, k), np.arange(k)  # h4[a, i, c, j] = out[(a, i), (c, j)], a view
    if m == 1 and not (np.any(xs[0] - np.diag(np.diag(xs[0]))) or np.any(qs[0] - np.diag(np.diag(qs[0])))):
        x, q = np.diag(xs[0]), np.diag(qs[0])
        out[d[:, None] * k + d, d[:, None] * k + d] += weight * (x[:, None] - q[None, :]) ** 2
        return
    h4[:, d, :, d] += weight * np.einsum("fab,fcb->ac", xs, xs)  # (X Xᵀ) ⊗ I, without forming it
    h4[d, :, d, :] += weight * np.einsum("fba,fbc->ac", qs, qs)  # + I ⊗ (QᵀQ)
    # Σ_f x_f ⊗ q_f: [(a, b), (c, e)] = Σ_f x[a, b] q[c, e], entry [(a, c), (b, e)] of X ⊗ Q and [(b, a), (e, c)]
    # of Xᵀ ⊗ Qᵀ
    prod = (xs.reshape(m, k * k).T @ qs.reshape(m, k * k)).reshape(k, k, k, k)
    prod *= weight
    h4 -= prod.transpose(0, 2, 1, 3)
    h4 -= prod.transpose(1, 3, 0, 2)


def _descriptors(values, name: str, ops: SpectralOperators) -> np.ndarray:
    """``values`` as an (N, p) float64 array of vertex functions of ``ops``' mesh; ValueError naming it otherwise."""
    d = np.asarray(values, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] != ops.phi.shape[0]:
        raise ValueError(f"{name} must be ({ops.phi.shape[0]}, p) vertex descriptors, got shape {d.shape}")
    return d


#: the terms' default weights (pyfmaps' quickstart): descriptors, Laplacian commutativity, descriptor
#: commutativity, orientation
FMAP_WEIGHTS = {"descr": 1.0, "lap": 0.1, "dcomm": 1.0, "orient": 1.0}


class FmapEnergy:
    """The four terms of the module docstring for one pair of shapes, prepared once: `fit` gives their
    least-squares minimizer, `terms` their values at any functional map (e.g. that of a point map, to tell
    which of several maps the descriptors and the orientation support best).

    Parameters
    ----------
    ops_a, ops_b : the two shapes' `SpectralOperators`, at the same k
    desc_a, desc_b : (N_A, p) and (N_B, p) descriptors, column f of one corresponding to column f of the other
        (e.g. WKS on one shared energy grid), or their `DescriptorTerms` (computed by ``ops_a.terms``, or combined
        from such terms; with the orientation operators unless w_orient = 0)
    w_descr, w_lap, w_dcomm, w_orient : the terms' weights (nonnegative; w_orient = 0 drops the orientation
        term and then needs no readable outside)
    """

    def __init__(self, ops_a: SpectralOperators, ops_b: SpectralOperators, desc_a: np.ndarray, desc_b: np.ndarray,
                 *, w_descr: float = FMAP_WEIGHTS["descr"], w_lap: float = FMAP_WEIGHTS["lap"],
                 w_dcomm: float = FMAP_WEIGHTS["dcomm"], w_orient: float = FMAP_WEIGHTS["orient"]) -> None:
        k = ops_a.phi.shape[1]
        if ops_b.phi.shape[1] != k:
            raise ValueError(f"the two shapes' operators have different k: {k} and {ops_b.phi.shape[1]}")
        self.weights = {"descr": w_descr, "lap": w_lap, "dcomm": w_dcomm, "orient": w_orient}
        for name, w in self.weights.items():
            if not np.isfinite(w) or w < 0:
                raise ValueError(f"w_{name} must be a finite number >= 0, got {w!r}")
        self.ops_a, self.ops_b = ops_a, ops_b
        da, db = (d if isinstance(d, DescriptorTerms) else
                  ops.terms(_descriptors(d, name, ops), orientation=bool(w_orient))
                  for d, ops, name in ((desc_a, ops_a, "desc_a"), (desc_b, ops_b, "desc_b")))
        for name, d in (("desc_a", da), ("desc_b", db)):
            if d.coefficients.shape[0] != k:
                raise ValueError(f"{name}'s DescriptorTerms are for k={d.coefficients.shape[0]}, the operators' k is {k}")
        if da.coefficients.shape[1] != db.coefficients.shape[1]:
            raise ValueError(f"desc_a and desc_b must hold the same number of descriptors (columns), got "
                             f"{da.coefficients.shape[1]} and {db.coefficients.shape[1]}")
        self.k, self.p = k, da.coefficients.shape[1]
        if w_orient and (da.orientation is None or db.orientation is None):
            raise ValueError("w_orient > 0 needs the descriptors' orientation operators: DescriptorTerms without them")
        a, b = da.coefficients, db.coefficients
        s = np.maximum(0.5 * (np.linalg.norm(a, axis=0) + np.linalg.norm(b, axis=0)), 1e-300)
        self.a, self.b = a / s, b / s
        scale = max(float(ops_a.evals[-1]), float(ops_b.evals[-1]), 1e-300)
        #: operator pairs (X_f for B, Q_f for A), each term ``Σ_f ‖C X_f − Q_f C‖²``
        self.pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {
            "lap": (np.diag(ops_b.evals / scale)[None], np.diag(ops_a.evals / scale)[None])}
        if w_dcomm:
            self.pairs["dcomm"] = _normalized(db.multiplication, da.multiplication)
        if w_orient:
            self.pairs["orient"] = _normalized(db.orientation, da.orientation)

    def _scale(self, name: str) -> float:
        return self.weights[name] / (1.0 if name == "lap" else self.p)

    def fit(self) -> np.ndarray:
        """(k, k) float64 C, the least-squares minimizer of the weighted terms (unique: the descriptor term
        alone is positive definite when the p ≥ k descriptors span B's basis)."""
        k = self.k
        # ‖C B − A‖²: normal matrix (B Bᵀ) ⊗ I, right-hand side vec(A Bᵀ)
        h = self._scale("descr") * np.kron(self.b @ self.b.T, np.eye(k))
        rhs = self._scale("descr") * (self.a @ self.b.T).reshape(-1, order="F")
        for name, (xs, qs) in self.pairs.items():
            if self.weights[name]:
                _commutator_normal(xs, qs, h, self._scale(name))
        h[np.diag_indices_from(h)] += 1e-12 * np.trace(h) / h.shape[0]  # guards a rank-deficient descriptor set
        return np.linalg.solve(h, rhs).reshape(k, k, order="F")

    def terms(self, fmap: np.ndarray) -> dict[str, float]:
        """Each term's weighted value at the (k, k) functional map ``fmap``, by name (``descr``, ``lap``,
        ``dcomm``, ``orient``), and ``orient_reversed``: the orientation term of a map that reverses orientation
        (``Σ_f ‖C O_B^f + O_A^f C‖²``), as far from zero for a map that keeps it as ``orient`` is for a mirror."""
        c = np.asarray(fmap, dtype=np.float64)
        out = {"descr": self._scale("descr") * float(np.sum((c @ self.b - self.a) ** 2))}
        for name, (xs, qs) in self.pairs.items():
            cx, qc = np.matmul(c[None], xs), np.matmul(qs, c[None])
            out[name] = self._scale(name) * float(np.sum((cx - qc) ** 2))
            if name == "orient":
                out["orient_reversed"] = self._scale(name) * float(np.sum((cx + qc) ** 2))
        return out


def functional_map(
    ops_a: SpectralOperators,
    ops_b: SpectralOperators,
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    *,
    w_descr: float = FMAP_WEIGHTS["descr"],
    w_lap: float = FMAP_WEIGHTS["lap"],
    w_dcomm: float = FMAP_WEIGHTS["dcomm"],
    w_orient: float = FMAP_WEIGHTS["orient"],
) -> np.ndarray:
    """The functional map (k, k) from B's coefficients to A's that best carries the descriptors over (see the
    module docstring for the four terms, and `FmapEnergy` for the parameters).

    Returns
    -------
    (k, k) float64 C, the least-squares minimizer (`FmapEnergy.fit`).
    """
    return FmapEnergy(ops_a, ops_b, desc_a, desc_b, w_descr=w_descr, w_lap=w_lap, w_dcomm=w_dcomm,
                      w_orient=w_orient).fit()
