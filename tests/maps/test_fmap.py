"""wpot.maps.fmap: the operators' closed forms (a function against itself, mirror images, similarity invariance) and
the functional map of an exact isometry."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import wpot
from wpot.maps.fmap import FmapEnergy, SpectralOperators, functional_map, point_map, pseudoscalars
from wpot.mesh import Mesh
from wpot.signatures import wks
from wpot.signatures._wks import wks_energies

from helpers import mirror_symmetric, sphere_points


def _descriptors(spec_a, spec_b, p: int = 40) -> tuple[np.ndarray, np.ndarray]:
    grid = wks_energies([spec_a, spec_b], n_energies=2 * p, scale_invariant=True)
    return tuple(wks(s, energies=grid.energies, sigma=grid.sigma, scale_invariant=True, cache=False)[:, ::2]
                 for s in (spec_a, spec_b))


def _rel(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.linalg.norm(x - y) / np.linalg.norm(y))


def test_operators_closed_forms():
    m = wpot.example_mesh(400)
    spec = wpot.eigenpairs(m, 40, cache=False)
    ops = SpectralOperators(m, spec, 20)
    f = ops.phi[:, 1:4]
    orient = ops.orientation(f)
    # <n, ∇f x ∇f> = 0: the operator of a basis function sends that function to 0
    for j in range(3):
        assert np.linalg.norm(orient[j][:, 1 + j]) < 1e-12 * np.linalg.norm(orient[j])
    assert min(np.linalg.norm(o) for o in orient) > 0.1
    # the product by the constant 1 is the identity (Φ is orthonormal for the normalized mass)
    np.testing.assert_allclose(ops.multiplication(np.ones((m.n_vertices, 1)))[0], np.eye(20), atol=1e-10)
    # the mirror image (faces re-wound so that they face outward again) has the same Laplacian and spectrum,
    # and the opposite orientation operators; a rotated, scaled copy has the same ones
    mirror = Mesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, [0, 2, 1]])
    assert _rel(SpectralOperators(mirror, spec, 20).orientation(f), -orient) < 1e-10
    moved = Mesh(3.0 * m.vertices @ Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix().T + 5.0, m.faces)
    assert _rel(SpectralOperators(moved, spec, 20).orientation(f), orient) < 1e-10
    # so does the inward-wound file of the same surface (normals are taken outward)
    inward = Mesh(m.vertices, m.faces[:, [0, 2, 1]])
    assert _rel(SpectralOperators(inward, spec, 20).orientation(f), orient) < 1e-10


def test_fit_recovers_a_relabelled_rotated_scaled_copy():
    a = wpot.example_mesh(700)
    rng = np.random.default_rng(3)
    perm = rng.permutation(a.n_vertices)  # vertex i of b is vertex perm[i] of a
    inv = np.argsort(perm)
    rot = Rotation.from_euler("xyz", [1.0, 0.2, -0.7]).as_matrix()
    b = Mesh(2.5 * a.vertices[perm] @ rot.T, inv[a.faces])
    sa, sb = wpot.eigenpairs(a, 60, cache=False), wpot.eigenpairs(b, 60, cache=False)
    da, db = _descriptors(sa, sb)
    oa, ob = SpectralOperators(a, sa, 30), SpectralOperators(b, sb, 30)
    for w_orient in (0.0, 1.0):
        c = functional_map(oa, ob, da, db, w_orient=w_orient)
        # an exact isometry: C is orthogonal (the eigenfunctions' signs and rotations within eigenspaces)
        assert np.abs(c.T @ c - np.eye(30))[:20, :20].max() < 0.05
        t = point_map(oa.phi, ob.phi, c)
        assert np.mean(t == inv) > 0.95


def test_fit_is_the_stationary_point_of_the_terms_it_reports():
    # the energy is quadratic in C, so at its minimizer the linear part vanishes: E(C + D) = E(C - D) > E(C) for
    # any D. The fit builds its normal matrix from Kronecker identities (a diagonal one for the Laplacian's term),
    # `terms` evaluates each term directly: the two must agree
    a, b = mirror_symmetric(500, seed=0), mirror_symmetric(600, seed=5)
    sa, sb = wpot.eigenpairs(a, 40, cache=False), wpot.eigenpairs(b, 40, cache=False)
    da, db = _descriptors(sa, sb, p=20)
    energy = FmapEnergy(SpectralOperators(a, sa, 10), SpectralOperators(b, sb, 10), da, db)
    c = energy.fit()

    def total(x: np.ndarray) -> float:
        return sum(v for name, v in energy.terms(x).items() if name != "orient_reversed")

    rng = np.random.default_rng(0)
    for _ in range(3):
        d = 0.05 * rng.standard_normal(c.shape)
        up, down, at = total(c + d), total(c - d), total(c)
        assert up == pytest.approx(down, rel=1e-9) and min(up, down) > at


def test_orientation_term_keeps_left_from_right():
    # a shape whose only symmetry is a reflection, and another triangulation of it: the intrinsic terms are
    # met as well by the true map as by its mirror; the orientation term must pick the true one
    a = mirror_symmetric(900, seed=0)
    b = mirror_symmetric(1100, seed=5)
    sa, sb = wpot.eigenpairs(a, 60, cache=False), wpot.eigenpairs(b, 60, cache=False)
    da, db = _descriptors(sa, sb)
    oa, ob = SpectralOperators(a, sa, 20), SpectralOperators(b, sb, 20)
    t = point_map(oa.phi, ob.phi, functional_map(oa, ob, da, db))
    truth = np.argmin(((a.vertices[:, None, :] - b.vertices[None, :, :]) ** 2).sum(-1), axis=1)
    mirror = np.argmin(((a.vertices[:, None, :] * np.array([-1.0, 1.0, 1.0]) - b.vertices[None, :, :]) ** 2)
                       .sum(-1), axis=1)
    err = np.linalg.norm(b.vertices[t] - b.vertices[truth], axis=1) / np.sqrt(b.area)
    err_mirror = np.linalg.norm(b.vertices[t] - b.vertices[mirror], axis=1) / np.sqrt(b.area)
    assert np.median(err) < 0.05 < 0.2 < np.median(err_mirror)


def test_bad_input():
    m = wpot.example_mesh(200)
    spec = wpot.eigenpairs(m, 30, cache=False)
    ops = SpectralOperators(m, spec, 10)
    d = np.ones((200, 12))
    with pytest.raises(ValueError, match="fewer than k=40"):
        SpectralOperators(m, spec, 40)
    with pytest.raises(ValueError, match="different k"):
        functional_map(ops, SpectralOperators(m, spec, 12), d, d)
    with pytest.raises(ValueError, match=r"desc_a and desc_b must hold the same number of descriptors"):
        functional_map(ops, ops, d, d[:, :5])
    with pytest.raises(ValueError, match=r"desc_b must be \(200, p\) vertex descriptors, got shape \(199, 12\)"):
        functional_map(ops, ops, d, d[1:])
    with pytest.raises(ValueError, match="desc_a's DescriptorTerms are for k=12, the operators' k is 10"):
        functional_map(ops, ops, SpectralOperators(m, spec, 12).terms(d), d)
    with pytest.raises(ValueError, match="w_orient > 0 needs the descriptors' orientation operators"):
        functional_map(ops, ops, ops.terms(d, orientation=False), d)
    with pytest.raises(ValueError, match="w_lap must be a finite number >= 0"):
        functional_map(ops, ops, d, d, w_lap=-1.0)
    flat = Mesh(np.c_[m.vertices[:, :2], np.zeros(200)], m.faces)
    flat_ops = SpectralOperators(flat, wpot.eigenpairs(flat, 30, cache=False), 10)
    with pytest.raises(ValueError, match="encloses no volume"):
        functional_map(flat_ops, flat_ops, d, d)
    functional_map(flat_ops, flat_ops, d + np.arange(12), d + np.arange(12), w_orient=0.0)  # no outside needed


def test_wks_terms_from_the_squared_eigenfunctions():
    """The terms are linear in the descriptors and the WKS is linear in the squared eigenfunctions, so the
    per-shape table of the φ_i² weighed by `wks_weights` gives the terms of the WKS descriptors themselves, on
    any energy grid (two grids here), and an energy of the same functional map."""
    from wpot.maps.fmap import FmapEnergy, squared_eigenfunction_terms, terms_cache
    from wpot.signatures import wks_weights

    a = wpot.example_mesh(500)
    b = Mesh(a.vertices * np.array([1.0, 1.3, 0.8]), a.faces)  # not an isometry: the terms are not zero
    sa, sb = wpot.eigenpairs(a, 60, cache=False), wpot.eigenpairs(b, 60, cache=False)
    oa, ob = SpectralOperators(a, sa, 20), SpectralOperators(b, sb, 20)
    terms_cache.clear()
    table = [squared_eigenfunction_terms(o, s) for o, s in ((oa, sa), (ob, sb))]
    assert squared_eigenfunction_terms(oa, sa).orientation is table[0].orientation  # cached
    # another spectrum of the same mesh, the same eigenvalues, one eigenvector turned around: not that entry
    turned = dataclasses.replace(sa, evecs=sa.evecs * np.where(np.arange(sa.k) == 7, -1.0, 1.0))
    assert squared_eigenfunction_terms(oa, turned).orientation is not table[0].orientation
    for p, spectra in ((20, (sa, sb)), (16, (sa.first(30), sb.first(30)))):
        direct = FmapEnergy(oa, ob, *_descriptors(*spectra, p=p))
        grid = wks_energies(spectra, n_energies=2 * p, scale_invariant=True)
        combined = []
        for t, s in zip(table, spectra):
            w = wks_weights(s.nonzero_evals, grid.energies, grid.sigma)[:, ::2]
            combined.append(t.combined(np.pad(w, ((0, t.coefficients.shape[1] - len(w)), (0, 0)))))
        weighed = FmapEnergy(oa, ob, *combined)
        c = direct.fit()
        assert _rel(weighed.fit(), c) < 1e-9
        for name, value in direct.terms(c).items():
            assert abs(weighed.terms(c)[name] - value) <= 1e-9 * abs(value)


def test_pseudoscalars_closed_form_on_a_sphere_and_their_turn_under_a_reflection():
    # on the unit sphere, with f = y and g = z: <n, grad f x grad g> = n_x = x; the mesh is read at area 1, so
    # both gradients carry sqrt(area), and h = area * x (a random triangulation: per-vertex averages of flat faces)
    u, f = sphere_points(3000, seed=1)
    sphere = Mesh(u, f)
    h = pseudoscalars(sphere, u[:, 1:])[:, 0] / sphere.area
    assert np.sqrt(np.mean((h - u[:, 0]) ** 2)) < 0.03 and np.abs(h - u[:, 0]).max() < 0.15
    h *= sphere.area
    # the faces' winding does not matter (the outward normal is read), a reflection of the mesh turns the sign
    np.testing.assert_allclose(pseudoscalars(Mesh(u, f[:, ::-1].copy()), u[:, 1:]), h[:, None], atol=1e-12)
    m = mirror_symmetric()
    x = m.vertices * np.array([-1.0, 1.0, 1.0])
    mirrored = Mesh(x, m.faces[:, ::-1].copy())
    vals = np.c_[m.vertices[:, 1], m.vertices[:, 2] ** 2, m.vertices[:, 0] ** 2]  # even in x
    np.testing.assert_allclose(pseudoscalars(mirrored, vals), -pseudoscalars(m, vals), atol=1e-10)
    with pytest.raises(ValueError, match="outward|outside|closed"):
        pseudoscalars(Mesh(np.c_[u[:, :2], np.zeros(len(u))], f), u[:, 1:])
