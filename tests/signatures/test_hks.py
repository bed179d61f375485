"""Heat kernel signatures: the sphere's closed form, the heat-trace normalization, the shared times (Sun et al.
2009), invariances, the registered `HKS` signature (one spectrum shared with WKS) and input errors."""
from __future__ import annotations

import math
import pickle
import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from helpers import deform_sphere
from wpot.cache import Cache
from wpot.mesh import Mesh
from wpot.signatures import WKS, get_signature, signature_options
from wpot.signatures.hks import HKS, DECAY, HKSOptions, HKSWarning, hks, hks_from_eigenpairs, hks_times
from wpot.spectral import LaplaceBeltrami, Spectrum, eigenpairs


# ------------------------------------------------------------------------------ the sphere
def test_sphere_matches_the_closed_form():
    """On a sphere of radius r the eigenvalues are l(l+1)/r² with multiplicity 2l+1, and by the addition theorem
    Σ_m Y_lm(x)² = (2l+1)/(4π r²) at every x, so k_t(x, x) = Σ_{l≥1} (2l+1)/(4π r²) exp(−l(l+1) t/r²) at every
    vertex. 100 eigenpairs hold l = 0..9 completely (100 = 10²), so the truncated sum runs over l = 1..9."""
    r = 2.0
    t = trimesh.creation.icosphere(subdivisions=4, radius=r)  # 2,562 vertices
    sphere = Mesh(t.vertices, t.faces)
    s = eigenpairs(sphere, k=100, cache=False).rescaled(normalized=False)
    # the truncation falls between the l = 9 and l = 10 eigenspaces
    assert s.evals[99] * r**2 / 90 == pytest.approx(1, abs=0.05) and s.evals[99] * r**2 < 100
    times = hks_times(s, n_times=50)
    raw = hks_from_eigenpairs(s.nonzero_evals, s.nonzero_evecs, times, normalized=False)  # k_t(x, x), (N, 50)
    ll = np.arange(1, 10)
    closed = ((2 * ll + 1)[:, None] / (4 * math.pi * r**2) * np.exp(-np.outer(ll * (ll + 1) / r**2, times))).sum(0)
    # Discretization error, O(h²): the computed l = 9 eigenvalues are 3.2 % below 90/r² (12 % on subdivision 3),
    # which the exponentials carry at the smallest times, and the icosahedral symmetry splits each eigenspace
    # slightly. Measured: spread across vertices (max − min)/mean ≤ 1.6e-3, distance to the closed form ≤ 8.2e-3
    # (4.4 times more, 6.1e-3 and 3.2e-2, on subdivision 3: the h² scaling).
    spread = (raw.max(0) - raw.min(0)) / raw.mean(0)
    assert spread.max() < 3e-3, spread.max()
    assert np.abs(raw / closed - 1).max() < 1.5e-2, np.abs(raw / closed - 1).max()
    # the signature divides by the heat trace Z(t) = Σ exp(−λ t): exactly that, and on a sphere 1/area
    z = np.exp(-np.outer(s.nonzero_evals, times)).sum(0)
    got = hks(sphere, times=times, n_eigen=100, cache=False)
    np.testing.assert_allclose(got, raw / z, rtol=1e-12, atol=0)
    assert np.abs(got * sphere.area - 1).max() < 3e-3  # measured 1.2e-3


# ------------------------------------------------------------------------------ times and the formula
def test_times_follow_sun_et_al():
    ev = np.r_[0.0, np.geomspace(10.0, 5000.0, 99)]
    s = Spectrum(evals=ev, evecs=np.zeros((3, 100)), area=1.0)
    t = hks_times(s, n_times=100)
    assert t.shape == (100,) and not t.flags.writeable
    assert t[0] == pytest.approx(4 * math.log(10) / 5000.0, rel=1e-14)
    assert t[-1] == pytest.approx(4 * math.log(10) / 10.0, rel=1e-14)
    np.testing.assert_allclose(np.diff(np.log(t)), np.log(500.0) / 99, rtol=1e-10)  # log-spaced
    # a shared grid: λ_1 the largest first nonzero eigenvalue, λ_max the smallest largest one (the common range)
    s2 = Spectrum(evals=np.r_[0.0, np.geomspace(20.0, 3000.0, 99)], evecs=np.zeros((3, 100)), area=1.0)
    shared = hks_times([s, s2], n_times=30)
    assert shared[0] == pytest.approx(DECAY / 3000.0, rel=1e-14)
    assert shared[-1] == pytest.approx(DECAY / 20.0, rel=1e-14)
    # at its own size (the default) the eigenvalues are λ/area: an area-4 shape has times 4 times longer
    s4 = Spectrum(evals=ev, evecs=np.zeros((3, 100)), area=4.0)
    np.testing.assert_allclose(hks_times(s4, n_times=100), 4 * t, rtol=1e-14)
    np.testing.assert_array_equal(hks_times(s4, n_times=100, scale_invariant=True), t)


@pytest.mark.parametrize("scale_invariant", [False, True])
def test_hks_matches_a_direct_evaluation(blob_spectrum, scale_invariant):
    s = blob_spectrum
    times = hks_times(s, n_times=20, scale_invariant=scale_invariant)
    got = hks(s, times=times, scale_invariant=scale_invariant)
    f = 1.0 if scale_invariant else 1.0 / s.area
    lam = s.evals[1:] * f
    phi2 = s.evecs[:, 1:] ** 2 * f
    ref = np.empty_like(got)
    for j, tj in enumerate(times):
        w = np.exp(-lam * tj)
        ref[:, j] = (phi2 * w).sum(1) / w.sum()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=0)
    assert got.dtype == np.float64 and got.shape == (s.n_vertices, 20)
    # the default times are this shape's own
    np.testing.assert_array_equal(hks(s, n_times=20, scale_invariant=scale_invariant), got)


def test_every_time_is_a_density_over_the_surface(blob, blob_spectrum):
    """Σ_x M_x HKS(x, t) = 1 at every time (φ_k M-orthonormal, weights summing to 1), whatever the time."""
    mass = LaplaceBeltrami(blob).mass * blob.area  # the Voronoi areas of the mesh at its own size
    with pytest.warns(HKSWarning, match="below 2 ln 10"):  # far outside the range too: no underflow
        h = hks(blob_spectrum, times=np.geomspace(1e-4, 1e3, 15))
    assert np.all(np.isfinite(h)) and np.all(h >= 0)
    np.testing.assert_allclose(mass @ h, 1.0, rtol=1e-10)


# ------------------------------------------------------------------------------ invariances
def test_rigid_motion_and_relabelling(blob):
    ref = hks(blob, n_eigen=60, n_times=40)
    rot = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    moved = blob.transformed(rotation=rot, translation=[3.0, -2.0, 0.5])
    np.testing.assert_allclose(hks(moved, n_eigen=60, n_times=40), ref, rtol=1e-7, atol=1e-9 * ref.max())
    perm = np.random.default_rng(1).permutation(blob.n_vertices)
    got = hks(blob.relabelled(perm), n_eigen=60, n_times=40)
    np.testing.assert_allclose(got, ref[perm], rtol=1e-7, atol=1e-9 * ref.max())


def test_uniform_scaling(blob):
    """Scaled by s: λ → λ/s² and φ² → φ²/s², so the times scale by s² and HKS(s² t) = HKS(t)/s² (a density);
    scale_invariant=True: the same times and the same HKS."""
    scale = 7.5
    big = blob.transformed(scale=scale)
    sa, sb = eigenpairs(blob, k=60), eigenpairs(big, k=60)
    ta, tb = hks_times(sa, n_times=40), hks_times(sb, n_times=40)
    np.testing.assert_allclose(tb, scale**2 * ta, rtol=1e-9)
    ref = hks(sa, times=ta)
    np.testing.assert_allclose(hks(sb, times=tb), ref / scale**2, rtol=1e-7, atol=1e-9 * ref.max())
    ti = hks_times(sa, n_times=40, scale_invariant=True)
    np.testing.assert_allclose(hks_times(sb, n_times=40, scale_invariant=True), ti, rtol=1e-9)
    inv = hks(sa, times=ti, scale_invariant=True)
    np.testing.assert_allclose(hks(sb, times=ti, scale_invariant=True), inv, rtol=1e-7, atol=1e-9 * inv.max())


# ------------------------------------------------------------------------------ the registered signature
def test_registered_and_built_from_flat_keywords():
    assert get_signature("hks") is HKS
    assert HKS.metric == "l2" and HKS.needs_fit and HKS.state_keys == ("times",)
    o = signature_options("hks", n_eigen=80, hks_n_times=12, scale_invariant=True, n_energies=50, ldsift_slab=0.25)
    assert o == HKSOptions(n_eigen=80, n_times=12, scale_invariant=True)
    sig = HKS(o)
    assert sig.run_key() == {"n_eigen": 80, "hks_n_times": 12, "scale_invariant": True}
    assert sig.params() == {"signature": "hks", "n_eigen": 80, "n_times": 12, "scale_invariant": True, "times": None,
                            "version": 1}


def test_a_pair_shares_its_times_and_one_spectrum_with_wks(blob):
    bigger = blob.transformed(scale=1.13)
    cache = Cache("spectrum", cache_dir=False)  # memory only (whatever $WPOT_CACHE_DIR says), counts hits and misses
    sig = HKS(HKSOptions(n_eigen=60, n_times=30), spectrum_cache=cache)
    assert not sig.fitted and sig.times is None
    sig.fit([blob, bigger])
    assert cache.misses == 2
    ref = hks_times([eigenpairs(blob, k=60), eigenpairs(bigger, k=60)], n_times=30)
    np.testing.assert_array_equal(sig.times, ref)
    for m in (blob, bigger):  # every time inside every shape's own range
        own = hks_times(eigenpairs(m, k=60), n_times=30)
        assert own[0] <= sig.times[0] and sig.times[-1] <= own[-1]
    wa, wb = sig(blob), sig(bigger)
    assert wa.shape == (blob.n_vertices, 30) and wb.shape == (bigger.n_vertices, 30)
    np.testing.assert_array_equal(wa, hks(blob, times=ref, n_eigen=60))
    # WKS with the same n_eigen and cache reads the same spectra: nothing more is computed
    wks_sig = WKS(signature_options("wks", n_eigen=60, n_energies=30), spectrum_cache=cache)
    wks_sig.fit([blob, bigger])
    wks_sig(blob)
    assert cache.misses == 2
    # the state travels as JSON-able lists (a run store) and back, and the signature pickles (worker processes)
    state = sig.state()
    assert list(state) == ["times"] and isinstance(state["times"][0], float)
    again = HKS(sig.options, state=state)
    np.testing.assert_array_equal(again.times, sig.times)
    assert again.params()["times"].tolist() == state["times"]
    portable = HKS(sig.options, state=state)  # the process-wide spectrum cache (a Cache instance holds a lock)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(portable)).times, sig.times)
    np.testing.assert_array_equal(sig.with_state(None).fit_input(blob).evals, eigenpairs(blob, k=60).evals)


# ------------------------------------------------------------------------------ bad input
def test_bad_input(blob, blob_spectrum):
    s = blob_spectrum
    with pytest.raises(ValueError, match="n_times must be an integer >= 2, got 1"):
        HKSOptions(n_times=1)
    with pytest.raises(ValueError, match="n_times must be an integer >= 2, got 1"):
        hks_times(s, n_times=1)
    with pytest.raises(ValueError, match="scale_invariant must be True or False"):
        HKSOptions(scale_invariant="yes")
    with pytest.raises(ValueError, match="HKS is not fitted: call fit"):
        HKS()(blob)
    for bad in ([1.0], [1.0, 0.5], [0.0, 1.0], [1.0, np.nan]):
        with pytest.raises(ValueError, match="times must be a finite, positive, increasing grid"):
            HKS(state={"times": bad})
    with pytest.raises(ValueError, match=r"has the keys \['times'\]"):
        HKS(state={"energies": [1.0, 2.0]})
    with pytest.raises(ValueError, match="spectra do not overlap"):
        hks_times([s, eigenpairs(blob.transformed(scale=30.0), k=60)])
    with pytest.raises(ValueError, match="strictly positive"):
        hks_from_eigenpairs(s.evals, s.evecs, [1.0])  # the zero eigenvalue is still there
    with pytest.raises(ValueError, match="times must be positive"):
        hks_from_eigenpairs(s.nonzero_evals, s.nonzero_evecs, [0.0, 1.0])
    with pytest.raises(TypeError, match="Mesh or a wpot.spectral.Spectrum"):
        hks(np.zeros((3, 3)))
    with pytest.warns(HKSWarning, match="below 2 ln 10"):
        hks(s, times=[1e-9, 1.0])
    t = trimesh.creation.icosphere(1)  # 42 vertices
    small = Mesh(deform_sphere(t.vertices), t.faces)
    with pytest.warns(HKSWarning, match="only 42 vertices"):
        h = hks(small, n_eigen=500, n_times=10)
    assert h.shape == (42, 10) and np.all(np.isfinite(h))
    with warnings.catch_warnings():
        warnings.simplefilter("error", HKSWarning)  # a fit over such a mesh uses all its eigenpairs silently
        assert HKS().fit_input(small).k == 42
