"""wpot.maps.registration.fit_similarity_robust: closed form with gross outliers, invariances, bad input, units."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import wpot
from wpot.maps.registration import fit_similarity, fit_similarity_robust


def _angle(r: np.ndarray) -> float:
    return float(Rotation.from_matrix(r).magnitude())


def _outlier_problem(seed: int, fraction: float, n: int = 300, noise: float = 0.0):
    """n pairs q = s R p + t (+ noise), of which ``fraction`` are replaced by random points of the target's box."""
    rng = np.random.default_rng(seed)
    scale, rot, t = float(rng.uniform(0.3, 3.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3) * 5
    p = rng.normal(size=(n, 3)) * [3.0, 2.0, 1.0]
    q = scale * p @ rot.T + t + rng.normal(scale=noise, size=(n, 3))
    bad = rng.permutation(n)[: int(round(fraction * n))]
    q[bad] = rng.uniform(q.min(0), q.max(0), size=(bad.size, 3))
    good = np.ones(n, dtype=bool)
    good[bad] = False
    return p, q, scale, rot, t, good


@pytest.mark.parametrize("seed, fraction", [(0, 0.3), (1, 0.35), (2, 0.4), (3, 0.4)])
def test_exact_pairs_among_gross_outliers_are_recovered_exactly(seed, fraction):
    p, q, scale, rot, t, good = _outlier_problem(seed, fraction)
    reg = fit_similarity_robust(p, q)
    # the inliers are exactly the uncorrupted pairs, and least squares on them is exact
    np.testing.assert_array_equal(reg.inliers, good)
    assert reg.n_inliers == good.sum() and reg.inlier_fraction == pytest.approx(1 - fraction, abs=0.01)
    assert reg.scale == pytest.approx(scale, rel=1e-9)
    assert _angle(reg.rotation @ rot.T) < 1e-9
    np.testing.assert_allclose(reg.translation, t, atol=1e-8 * (1 + np.abs(t).max()))
    assert reg.rms < 1e-8 * scale and reg.method == "robust" and reg.n_pairs == len(p)
    # the least-squares fit of the same pairs is pulled far off
    plain = fit_similarity(p, q)
    assert abs(plain.scale / scale - 1) > 0.1 or _angle(plain.rotation @ rot.T) > 0.1


def test_noisy_pairs_among_outliers_agree_with_least_squares_on_the_true_inliers():
    p, q, scale, rot, t, good = _outlier_problem(4, 0.35, n=1000, noise=0.01)
    reg = fit_similarity_robust(p, q)
    oracle = fit_similarity(p[good], q[good])  # an independent fit that knows the outliers
    assert reg.scale == pytest.approx(oracle.scale, rel=2e-3)
    assert _angle(reg.rotation @ oracle.rotation.T) < 2e-3
    assert _angle(reg.rotation @ rot.T) < 5e-3 and reg.scale == pytest.approx(scale, rel=5e-3)
    # a handful of true pairs in the noise tail may be left out; no outlier far from the truth is kept
    assert np.mean(reg.inliers[good]) > 0.85
    true_res = np.linalg.norm(scale * p @ rot.T + t - q, axis=1)
    assert np.all(true_res[reg.inliers] < 0.1)


def test_relabelling_the_pairs_gives_the_same_fit():
    p, q, *_ = _outlier_problem(5, 0.4, noise=0.02)
    w = np.random.default_rng(0).uniform(0.5, 1.5, len(p))
    reg = fit_similarity_robust(p, q, w)
    perm = np.random.default_rng(1).permutation(len(p))
    again = fit_similarity_robust(p[perm], q[perm], w[perm])
    assert again.scale == pytest.approx(reg.scale, rel=1e-12)
    np.testing.assert_allclose(again.rotation, reg.rotation, atol=1e-12)
    np.testing.assert_allclose(again.translation, reg.translation, atol=1e-10)
    np.testing.assert_array_equal(again.inliers, reg.inliers[perm])


def test_a_rigid_motion_of_the_inputs_moves_the_fit_accordingly():
    p, q, *_ = _outlier_problem(6, 0.35, noise=0.02)
    reg = fit_similarity_robust(p, q)
    ga, ta = Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix(), np.array([10.0, -3.0, 2.0])
    gb, tb = Rotation.from_rotvec([-2.1, 0.3, 0.9]).as_matrix(), np.array([-1.0, 7.0, 0.5])
    moved = fit_similarity_robust(p @ ga.T + ta, q @ gb.T + tb)
    # x -> gb (s R ga^T (x - ta) + t) + tb
    assert moved.scale == pytest.approx(reg.scale, rel=1e-9)
    np.testing.assert_allclose(moved.rotation, gb @ reg.rotation @ ga.T, atol=1e-9)
    np.testing.assert_allclose(moved.translation, gb @ (reg.translation - reg.scale * reg.rotation @ ga.T @ ta) + tb,
                               atol=1e-8)
    np.testing.assert_array_equal(moved.inliers, reg.inliers)
    assert moved.rms == pytest.approx(reg.rms, rel=1e-9)


def test_rigid_fit_and_determinism():
    p, q, scale, rot, t, good = _outlier_problem(7, 0.3)
    q = (q - t) / scale + t  # a rigid motion for the good pairs (outliers stay outliers)
    reg = fit_similarity_robust(p, q, with_scale=False)
    assert reg.scale == 1.0 and _angle(reg.rotation @ rot.T) < 1e-9
    np.testing.assert_array_equal(reg.inliers, good)
    again = fit_similarity_robust(p, q, with_scale=False)
    np.testing.assert_array_equal(again.rotation, reg.rotation)


def test_few_pairs_try_every_triple():
    p, q, scale, rot, t, _ = _outlier_problem(8, 0.0, n=8)
    q[:3] += 50.0  # 3 of 8 wrong: every one of the 56 triples is tried
    reg = fit_similarity_robust(p, q)
    assert reg.n_inliers == 5 and reg.scale == pytest.approx(scale, rel=1e-9)
    exact = fit_similarity_robust(p[3:6], q[3:6])  # three pairs: the exact fit
    assert exact.scale == pytest.approx(scale, rel=1e-9) and exact.n_inliers == 3


@pytest.mark.parametrize("args, kwargs, match", [
    ((np.zeros((2, 3)), np.zeros((2, 3))), {}, "at least 3 point pairs"),
    ((np.zeros((5, 3)), np.zeros((4, 3))), {}, "shape"),
    ((np.c_[np.arange(6.0), 2 * np.arange(6.0), np.zeros(6)],) * 2, {}, "collinear"),
    ((np.random.default_rng(0).normal(size=(6, 3)),) * 2, {"n_samples": 0}, "n_samples"),
    ((np.random.default_rng(0).normal(size=(6, 3)),) * 2, {"quantile": 1.0}, "quantile"),
    ((np.random.default_rng(0).normal(size=(6, 3)),) * 2, {"confidence": 0.0}, "confidence"),
    ((np.random.default_rng(0).normal(size=(6, 3)),) * 2, {"weights": -np.ones(6)}, "non-negative"),
])
def test_degenerate_input_is_an_error(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_similarity_robust(*args, **kwargs)


def test_rms_text_gives_the_unit_and_sizes_of_the_target():
    mesh = wpot.example_mesh(200, seed=0)
    p = mesh.vertices
    q = p + np.random.default_rng(0).normal(scale=0.01, size=p.shape)
    reg = fit_similarity_robust(p, q).with_target(mesh)
    text = reg.rms_text()
    assert text.startswith(f"{reg.rms:.4g} (mesh units; ")
    assert f"{reg.rms / mesh.mean_edge_length:.2g} mean edge lengths of B" in text
    assert f"{100 * reg.rms / mesh.bounding_box_diagonal:.2g} % of B's bounding-box diagonal" in text
    assert fit_similarity(p, q).rms_text() == f"{fit_similarity(p, q).rms:.4g} (mesh units)"
    inv = reg.inverse()  # in A's units: B's sizes no longer apply
    assert inv.target_edge_length is None and inv.n_inliers == reg.n_inliers
    np.testing.assert_allclose(inv.apply(reg.apply(p)), p, atol=1e-12)


def test_a_given_scale_fits_only_the_rotation_and_translation():
    p, q, scale, rot, t, good = _outlier_problem(4, 0.3)
    reg = fit_similarity_robust(p, q, scale=scale)
    assert reg.scale == scale and reg.scale_from == "given"
    np.testing.assert_array_equal(reg.inliers, good)
    assert _angle(reg.rotation @ rot.T) < 1e-9
    np.testing.assert_allclose(reg.translation, t, atol=1e-8 * (1 + np.abs(t).max()))
    # a wrong given scale is kept as given (the rotation and translation fit around it)
    assert fit_similarity_robust(p, q, scale=2 * scale).scale == 2 * scale
    assert fit_similarity_robust(p, q).scale_from == "fit"
    for bad in (0.0, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="scale must be a positive finite number"):
            fit_similarity_robust(p, q, scale=bad)


def test_area_scale_is_the_size_ratio():
    from wpot.examples import example_pair
    from wpot.maps.registration import area_scale

    mesh = example_pair(300, seed=0).source
    rot = Rotation.from_euler("xyz", [20, -40, 75], degrees=True).as_matrix()
    big = mesh.transformed(rot, np.array([1.0, -2.0, 0.5]), 1.7)
    assert area_scale(mesh, big) == pytest.approx(1.7, rel=1e-12)
    assert area_scale(big, mesh) == pytest.approx(1 / 1.7, rel=1e-12)
    half = mesh.vertices[:, 0] < np.median(mesh.vertices[:, 0])
    assert area_scale(mesh, big, half, half) == pytest.approx(1.7, rel=1e-12)  # the same region on both
    assert area_scale(mesh, mesh, half, None) > 1.2  # the whole against about half of it: ~sqrt(2)
    with pytest.raises(ValueError, match="no area"):
        area_scale(mesh, big, np.zeros(mesh.n_vertices, bool))
    with pytest.raises(ValueError, match="bool mask"):
        area_scale(mesh, big, half[:-1])


def test_a_comparison_registers_a_moved_and_scaled_copy_exactly():
    from wpot.examples import example_pair

    mesh = example_pair(300, seed=1).source
    rot = Rotation.from_euler("xyz", [10, 30, -50], degrees=True).as_matrix()
    moved = mesh.transformed(rot, np.array([3.0, 0.0, -1.0]), 0.6)
    c = wpot.compare(mesh, moved, n_eigen=40, n_energies=40, device="cpu", scale_invariant=True)
    reg = c.registration
    assert reg.scale_from == "given" and reg.scale == pytest.approx(0.6, rel=1e-12)
    assert _angle(reg.rotation @ rot.T) < 1e-6
    np.testing.assert_allclose(reg.apply(mesh.vertices), moved.vertices, atol=1e-6 * moved.bounding_box_diagonal)
    # partial transport matches regions, not whole shapes: its scale is fitted
    part = wpot.compare(mesh, moved, transport="partial", n_eigen=40, n_energies=40, device="cpu",
                        scale_invariant=True)
    assert part.registration.scale_from == "fit" and part.registration.scale == pytest.approx(0.6, rel=0.05)


def test_wrong_pairs_sent_to_one_point_do_not_make_a_hypothesis():
    """Wrong matches that all land on one vertex (a map collapsed there) are outliers, never a transform: the
    triples drawn among them have a target at one point, whose fit is rounding noise, and are set aside."""
    rng = np.random.default_rng(7)
    p = rng.normal(size=(30, 3))
    rot = Rotation.random(random_state=7).as_matrix()
    q = 1.7 * p @ rot.T + np.array([0.2, 3.0, -1.0])
    bad = np.arange(12)
    q[bad] = q[20]
    reg = fit_similarity_robust(p, q)
    assert reg.scale == pytest.approx(1.7, rel=1e-9)
    np.testing.assert_allclose(reg.rotation, rot, atol=1e-9)
    assert not reg.inliers[bad].any()
    with pytest.raises(ValueError, match="target\\s+points are .*collinear or coincident"):
        fit_similarity_robust(p, np.tile(q[20], (30, 1)))
