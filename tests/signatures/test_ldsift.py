"""LD-SIFT: frames (Eq. 1, 28), the 180-degree averaging, invariance under rigid motion and scaling,
CPU/CUDA agreement, the true match's rank on a real TOSCA pair, and input errors."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from wpot.mesh import Mesh
from helpers import random_rotation

from wpot.signatures import _ldsift as L  # the module, for its internals


@pytest.fixture(scope="module")
def bumpy() -> Mesh:
    """A closed, irregular surface (no symmetry, so frames are well defined): 642 vertices."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = s.vertices
    r = 1 + 0.15 * np.sin(3 * v[:, 0] + 1) * np.cos(2 * v[:, 1]) + 0.1 * v[:, 2] ** 3
    return Mesh(v * r[:, None], s.faces)


def test_frames_on_a_sphere_follow_the_outward_normal():
    s = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    mesh = Mesh(s.vertices, s.faces)
    fr = L.local_frames(mesh, K=3.0)
    f = fr.frames
    np.testing.assert_allclose(f @ f.transpose(0, 2, 1), np.broadcast_to(np.eye(3), f.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(f), 1.0, atol=1e-12)  # right-handed: n = e1 x e2
    radial = mesh.vertices / 2.0
    assert np.min(np.sum(f[:, 2] * radial, axis=1)) > 0.999  # the dominant plane is the tangent plane, n outward
    np.testing.assert_allclose(fr.half_sizes, 3.0 * mesh.one_ring_mean_edge_length)
    # the ball of radius 3 D(v) holds the one ring and more; counts agree with a brute-force search
    d = np.linalg.norm(mesh.vertices[:, None] - mesh.vertices[None], axis=2)
    np.testing.assert_array_equal(fr.n_neighbours, (d <= fr.half_sizes[:, None]).sum(1) - 1)
    assert not fr.grown.any() and not fr.degenerate.any()


def test_small_K_grows_the_neighbourhood_to_three_nearest():
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mesh = Mesh(s.vertices, s.faces)
    fr = L.local_frames(mesh, K=0.5)  # the ball holds only v itself
    assert fr.grown.all()
    np.testing.assert_array_equal(fr.n_neighbours, L.MIN_NEIGHBOURS)
    np.testing.assert_allclose(fr.half_sizes, 0.5 * mesh.one_ring_mean_edge_length)  # image size unchanged
    assert np.min(np.sum(fr.frames[:, 2] * mesh.vertices, axis=1)) > 0.95  # 4 nearby points still give the plane


def test_collinear_neighbourhood_falls_back_to_vertex_normal_with_warning():
    """A strip of slivers 1e-7 wide: neighbours are collinear to 1e-14, no dominant plane."""
    n = 12
    x = np.arange(n, dtype=float)
    v = np.r_[np.c_[x, np.zeros(n), np.zeros(n)], np.c_[x, np.full(n, 1e-7), np.zeros(n)]]
    f = np.r_[[[i, i + 1, n + i] for i in range(n - 1)], [[i + 1, n + i + 1, n + i] for i in range(n - 1)]]
    mesh = Mesh(v, f, warn=False)
    with pytest.warns(UserWarning, match=r"rank-deficient .* vertex normal"):
        fr = L.local_frames(mesh, K=3.0)
    assert fr.degenerate.all()
    np.testing.assert_allclose(fr.frames[:, 2], mesh.vertex_normals, atol=1e-12)
    np.testing.assert_allclose(fr.frames[:, 0], np.tile([1.0, 0, 0], (2 * n, 1)), atol=1e-6)  # the strip's axis
    np.testing.assert_allclose(np.linalg.det(fr.frames), 1.0, atol=1e-12)


def test_sift_average_is_invariant_under_180_degreerandom_rotation():
    rng = np.random.default_rng(0)
    from scipy.ndimage import gaussian_filter

    img = np.stack([gaussian_filter(rng.random((21, 21)), 2) for _ in range(6)])
    g = (255 * (img - img.min()) / np.ptp(img)).round().astype(np.uint8)
    a = L.sift_at_center(g)
    b = L.sift_at_center(np.ascontiguousarray(g[:, ::-1, ::-1]))
    np.testing.assert_array_equal(a, b)
    # ...and it is not invariant under a 90-degree turn (the test can fail)
    c = L.sift_at_center(np.ascontiguousarray(np.rot90(g, axes=(1, 2))))
    assert np.linalg.norm(a - c) > 0.1 * np.linalg.norm(a)
    assert L.keypoint_size(21) == 3.5  # 12 sigma = 21 pixels: the window covers the whole image


def test_gradient_angle_closed_forms_and_turns():
    """A linear ramp's gradient has one direction: its angle, in OpenCV's keypoint convention (from the columns'
    axis towards the rows', rows down). An image turned by a quarter turn (an exact permutation of its pixels) has
    its angle moved by 90 degrees, and the descriptor at that angle is the same, pixel for pixel, while the paper's
    (0 and 180 degrees averaged) changes."""
    from scipy.ndimage import gaussian_filter

    y, x = np.mgrid[0:31, 0:31].astype(float)
    for deg in (0.0, 30.0, 90.0, 200.0):
        t = np.radians(deg)
        ramp = 100 + 3 * (np.cos(t) * x + np.sin(t) * y)
        assert L.gradient_angles(ramp[None], window=5.0)[0] == pytest.approx(deg, abs=1e-6)
    rng = np.random.default_rng(0)
    img = np.stack([gaussian_filter(rng.random((31, 31)), 2) for _ in range(6)])
    g = (255 * (img - img.min()) / np.ptp(img)).round().astype(np.uint8)
    window = L.GRADIENT_WINDOW * 21
    a_g = L.gradient_angles(g, window=window)
    a = L.sift_at_center(g, angles=a_g, window=21)
    for k in (1, 2, 3):
        turned = np.ascontiguousarray(np.rot90(g, k, axes=(1, 2)))  # counter-clockwise as drawn: -90 k degrees
        a_t = L.gradient_angles(turned, window=window)
        np.testing.assert_allclose((a_t - a_g + 90 * k) % 360, 0.0, atol=1e-6)
        np.testing.assert_array_equal(L.sift_at_center(turned, angles=a_t, window=21), a)
        paper = L.sift_at_center(turned, window=21)
        assert np.median(np.linalg.norm(paper - a, axis=1) / np.linalg.norm(a, axis=1)) > 0.2
    assert L.margin_resolution(21) == 31 and L.margin_resolution(8) == 12  # 21 √2 = 29.7; 8 √2 = 11.3
    assert L.gradient_angles(np.full((1, 9, 9), 7.0), window=2.0)[0] == 0.0  # no gradient


def test_gradient_orientation_does_not_follow_the_frames_first_axis(bumpy):
    """The frames' e1 and e2 turned by 40 degrees about n (as another meshing or pose turns them where the
    neighbours spread alike both ways): the paper's descriptors change, SIFT's own orientation keeps them (up to
    the rays meeting the surface at other points). The margin image holds the plain one at its centre."""
    import dataclasses

    fr = L.local_frames(bumpy)
    c, s = np.cos(np.radians(40)), np.sin(np.radians(40))
    f = fr.frames.copy()
    f[:, 0], f[:, 1] = c * fr.frames[:, 0] + s * fr.frames[:, 1], -s * fr.frames[:, 0] + c * fr.frames[:, 1]
    turned = dataclasses.replace(fr, frames=f)

    def moved(orientation):
        d0 = L.ldsift(bumpy, device="cpu", frames=fr, orientation=orientation)
        d1 = L.ldsift(bumpy, device="cpu", frames=turned, orientation=orientation)
        return np.median(np.linalg.norm(d0 - d1, axis=1) / np.linalg.norm(d0, axis=1))

    assert moved("gradient") < 0.1 and moved("frame") > 0.25
    wide, plain = L.ldsift_images(bumpy, device="cpu", margin=True), L.ldsift_images(bumpy, device="cpu")
    assert wide.shape[1:] == (31, 31)
    np.testing.assert_allclose(wide[:, 5:26, 5:26], plain, atol=1e-5 * fr.half_sizes.max())


@pytest.mark.parametrize("orientation", ["frame", "gradient"])
def test_invariant_under_rigid_motion_scaling_and_relabelling(bumpy, orientation):
    rng = np.random.default_rng(1)
    d0 = L.ldsift(bumpy, device="cpu", orientation=orientation)
    assert d0.shape == (bumpy.n_vertices, 128) and d0.dtype == np.float64
    rot, t, s = random_rotation(rng), np.array([30.0, -5.0, 12.0]), 7.5
    perm = rng.permutation(bumpy.n_vertices)
    moved = bumpy.transformed(rot, t, s).relabelled(perm)
    d1 = L.ldsift(moved, device="cpu", orientation=orientation)[np.argsort(perm)]
    rel = np.linalg.norm(d1 - d0, axis=1) / np.linalg.norm(d0, axis=1)
    # float32 rays and 8-bit levels may move a grey level by one here and there: tiny differences
    assert np.median(rel) < 0.01, np.median(rel)
    assert np.quantile(rel, 0.99) < 0.1, np.quantile(rel, 0.99)
    # while descriptors of different vertices differ a lot (the tolerance is meaningful)
    other = np.linalg.norm(d0 - d0[rng.permutation(len(d0))], axis=1) / np.linalg.norm(d0, axis=1)
    assert np.median(other) > 0.3


def test_one_edge_length_makes_the_images_independent_of_the_density(bumpy):
    """The same surface meshed at 4x the density (each triangle cut into four: the original vertices and the
    surface are unchanged). With one edge length for both meshes (``edge``, `common_edge` of the two) every image
    has the same size S on both, and an original vertex seen in the same frame gets the same image (the depth
    image depends on the surface alone); with each mesh's own D(v), the paper's, S halves on the fine mesh. The
    descriptors follow, where the two meshes' frames agree (the frames come from the covariance of the vertices
    within S, which the new vertices move a little; where the neighbourhood is near-isotropic, e1 turns)."""
    import dataclasses

    from wpot.signatures._frames import common_edge

    v, f = trimesh.remesh.subdivide(bumpy.vertices, bumpy.faces)
    fine, n = Mesh(v, f), bumpy.n_vertices
    np.testing.assert_array_equal(fine.vertices[:n], bumpy.vertices)
    edge = common_edge([bumpy, fine])
    coarse_fr, fine_fr = L.local_frames(bumpy, edge=edge), L.local_frames(fine, edge=edge)
    np.testing.assert_allclose(fine_fr.half_sizes, 3.0 * edge)
    np.testing.assert_allclose(coarse_fr.half_sizes, 3.0 * edge)
    own = L.local_frames(fine).half_sizes[:n] / L.local_frames(bumpy).half_sizes
    assert 0.4 < np.median(own) < 0.6
    # the original vertices in the coarse mesh's frames: the same images on both meshes
    shared = dataclasses.replace(fine_fr, frames=np.concatenate([coarse_fr.frames, fine_fr.frames[n:]]))
    a = L.ldsift_images(bumpy, device="cpu", frames=coarse_fr)
    b = L.ldsift_images(fine, device="cpu", frames=shared)[:n]
    assert np.abs(a - b).max() < 1e-4 * edge

    def moved(**kw) -> np.ndarray:
        d0, d1 = L.ldsift(bumpy, device="cpu", **kw), L.ldsift(fine, device="cpu", **kw)[:n]
        return np.linalg.norm(d0 - d1, axis=1) / np.linalg.norm(d0, axis=1)

    agree = np.abs(np.einsum("ij,ij->i", coarse_fr.frames[:, 0], fine_fr.frames[:n, 0])) > 0.98
    assert agree.sum() > 50
    same, paper = np.median(moved(edge=edge)[agree]), np.median(moved()[agree])
    assert same < 0.08 and paper > 3 * same, (same, paper)
    with pytest.raises(ValueError, match="edge"):
        L.local_frames(fine, edge=0.0)
    with pytest.raises(ValueError, match="edge"):
        L.LDSIFTOptions(edge=-1.0)


def test_cpu_and_device_agree(bumpy, device):
    a = L.ldsift_images(bumpy, device="cpu")
    b = L.ldsift_images(bumpy, device=device)
    np.testing.assert_allclose(a, b, atol=1e-5)
    s = L.local_frames(bumpy).half_sizes
    assert np.all(np.abs(a) <= L.SLAB * s[:, None, None] * (1 + 1e-6))  # heights lie in the slab [-t S, t S]


def _two_floors(h_over_s: float) -> tuple[Mesh, int, float]:
    """A flat 13 x 13 grid (z = 0, faces up) and, above its centre vertex c, a small 5 x 5 grid at
    height h = h_over_s * S(c), with S(c) = 3 D(c) computed from the lower grid alone."""
    def grid(n, z, x0):
        xs = x0 + np.arange(n, dtype=float)
        v = np.array([(x, y, z) for y in xs for x in xs])
        f = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1) for i in range(n - 1) for j in range(n - 1)]
        f += [(i * n + j, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]
        return v, np.array(f)

    v0, f0 = grid(13, 0.0, -6.0)
    c = 6 * 13 + 6
    s = L.local_frames(Mesh(v0, f0)).half_sizes[c]
    v1, f1 = grid(5, h_over_s * s, -2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # two connected components, on purpose
        return Mesh(np.vstack([v0, v1]), np.vstack([f0, f1 + len(v0)])), c, s


@pytest.mark.parametrize("h_over_s", [0.4, 0.8])
def test_slab_decides_whether_a_surface_above_the_plane_counts(h_over_s):
    """Closed form: a surface at height h above the centre vertex's plane is what its centre pixel sees
    when h < slab S(v) (the ray starts above it), and is ignored when h > slab S(v) (the ray starts below
    it and meets the vertex's own plane, height 0). Every height stays in [-slab S, slab S]."""
    mesh, c, s = _two_floors(h_over_s)
    fr = L.local_frames(mesh)
    assert abs(abs(fr.frames[c, 2, 2]) - 1) < 1e-6  # the upper floor does not tilt the dominant plane
    mid = 10  # centre pixel of the 21 x 21 image
    for slab in (0.25, 0.5, 1.0, 2.0):
        img = L.ldsift_images(mesh, slab=slab, device="cpu")[c]
        seen = img[mid, mid]
        if h_over_s < slab:
            assert seen == pytest.approx(h_over_s * s, rel=1e-5)
        else:
            assert seen == pytest.approx(0.0, abs=1e-5 * s)
        assert np.all(np.abs(img) <= slab * s * (1 + 1e-6))
    with pytest.raises(ValueError, match="slab must be"):
        L.ldsift_images(mesh, slab=0.0)


def test_true_match_ranks_high_on_tosca(tosca5k):
    """cat0 vs cat1 (independent remeshings, different poses): rank percentile of the true match by L2
    cost among all 5,000 vertices of cat1, for 200 sampled vertices of cat0. Chance is 0.5.
    Measured when written: median 0.20 (LD-SIFT is extrinsic: weaker than WKS under bending)."""
    from wpot.io import load_mesh, load_vts

    a, b = load_mesh(tosca5k / "cat0.off"), load_mesh(tosca5k / "cat1.off")
    ga, gb = load_vts(tosca5k / "corres" / "cat0.vts"), load_vts(tosca5k / "corres" / "cat1.vts")
    rng = np.random.default_rng(2)
    sel = rng.choice(len(ga), 200, replace=False)
    fa = L.local_frames(a)
    from render.png import to_uint8
    from render.raycast import DepthRenderer

    # images of the WHOLE mesh, only for the sampled vertices of A
    raw = DepthRenderer(a).render(a.vertices[ga[sel]], fa.frames[ga[sel]], fa.half_sizes[ga[sel]], 21, ceiling=L.SLAB)
    da = L.sift_at_center(to_uint8(L.to_slab(raw, fa.half_sizes[ga[sel]])))
    db = L.ldsift(b)
    from scipy.spatial.distance import cdist

    dist = cdist(da, db)
    true = dist[np.arange(len(sel)), gb[sel]]
    pct = (dist < true[:, None]).sum(1) / len(db)
    print(f"LD-SIFT cat0->cat1: median rank percentile {np.median(pct):.3f}, top-1 {np.mean(pct == 0):.3f}")
    assert np.median(pct) < 0.3


def test_registered_signature_is_ldsift(bumpy):
    from wpot.signatures import get_signature, signature_options

    sig = get_signature("ldsift")(signature_options("ldsift", ldsift_K=2.5, ldsift_slab=0.5), device="cpu")
    assert isinstance(sig, L.LDSIFT) and sig.metric == "l2" and sig.fitted
    got = sig(bumpy)
    assert got.dtype == np.float64 and got.shape == (bumpy.n_vertices, 128)
    np.testing.assert_array_equal(got, L.ldsift(bumpy, K=2.5, slab=0.5, device="cpu"))


def test_bad_input_errors(bumpy):
    with pytest.raises(TypeError, match=r"wpot.Mesh, got tuple"):
        L.ldsift((bumpy.vertices, bumpy.faces))
    with pytest.raises(ValueError, match=r"K must be a positive finite number, got -1"):
        L.ldsift(bumpy, K=-1)
    with pytest.raises(ValueError, match=r"K must be a positive number, got 'a'"):
        L.local_frames(bumpy, K="a")
    with pytest.raises(ValueError, match=r"resolution must be an integer >= 8 .*got 4"):
        L.ldsift(bumpy, resolution=4)
    with pytest.raises(ValueError, match=r"uint8"):
        L.sift_at_center(np.zeros((2, 21, 21)))
    with pytest.raises(ValueError, match=r"orientation must be one of \('frame', 'gradient'\), got 'pca'"):
        L.LDSIFTOptions(orientation="pca")
    with pytest.raises(ValueError, match=r"angles must be 2 finite numbers"):
        L.sift_at_center(np.zeros((2, 21, 21), np.uint8), angles=[0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lonely = Mesh(np.r_[bumpy.vertices, [[5.0, 5, 5]]], bumpy.faces)  # an unreferenced vertex
    with pytest.raises(ValueError, match=r"1 vertices have no edge .*\[642\]"):
        L.ldsift(lonely)
