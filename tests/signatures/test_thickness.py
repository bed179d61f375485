"""Local thickness (shape diameter function) and LD-SIFT's thickness column."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from helpers import random_rotation
from render.raycast import DepthRenderer, inward_cone
from wpot.mesh import Mesh, boundary_rings
from wpot.signatures import _ldsift as L
from wpot.signatures import get_signature
from wpot.signatures import _thickness as T
from wpot.signatures._thickness import thickness


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    s = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    return Mesh(s.vertices, s.faces)


def test_rays_in_a_sphere_travel_its_chords(sphere, device):
    """A ray entering a sphere of radius r at angle θ to the inward normal leaves it after the chord 2 r cos θ."""
    cone = inward_cone(32, 60.0)
    assert np.allclose(np.linalg.norm(cone, axis=1), 1) and np.all(cone[:, 2] >= 0.5 - 1e-12)
    # the set is its own image under the frame's sign flips (e1, e2) -> (±e1, ±e2)
    for flip in ([-1, -1, 1], [1, -1, 1]):
        assert {tuple(np.round(r, 12)) for r in cone * flip} == {tuple(np.round(r, 12)) for r in cone}
    frames = T._ray_frames(sphere.vertex_normals, L.local_frames(sphere).frames[:, 0])
    assert np.allclose(frames @ frames.transpose(0, 2, 1), np.eye(3))
    hits = DepthRenderer(sphere, device=device).inward_hits(sphere.vertices, frames, cone)
    chords = 2 * 2.0 * cone[:, 2]
    assert np.isfinite(hits).all()
    # the icosphere's flat faces sit inside the true sphere: chords within 0.6 % of the diameter
    np.testing.assert_allclose(hits, np.broadcast_to(chords, hits.shape), atol=0.006 * 4.0)
    np.testing.assert_allclose(thickness(sphere, device=device), np.median(chords), rtol=0.01)


def test_invariant_under_winding_rigid_motion_relabelling_and_covariant_under_scale(sphere):
    v = sphere.vertices * (1 + 0.2 * np.sin(2 * sphere.vertices[:, [0]]))  # no symmetry
    mesh = Mesh(v, sphere.faces)
    t0 = thickness(mesh)
    inside_out = Mesh(v, sphere.faces[:, ::-1])
    np.testing.assert_allclose(thickness(inside_out), t0, rtol=1e-5)
    rng = np.random.default_rng(3)
    perm = rng.permutation(mesh.n_vertices)
    moved = mesh.transformed(random_rotation(rng), np.array([5.0, -3.0, 40.0]), 3.5).relabelled(perm)
    np.testing.assert_allclose(thickness(moved)[np.argsort(perm)], 3.5 * t0, rtol=1e-4)
    assert t0.max() / t0.min() > 1.3  # the shape's thickness varies: the comparison above is not of constants


def test_vertices_without_rays_take_their_neighbours_values():
    """On a path 0-1-2-3-4 with values at 0 and 4 only: 1 and 3 take their known neighbour's value, then 2 the
    mean of 1 and 3. A component with no value at all takes the median of the known values."""
    path = [(0, 1, 5), (1, 2, 5), (2, 3, 5), (3, 4, 5)]  # a fan around vertex 5 links 0-1-2-3-4 in a path
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0], [2, 1, 0], [9, 9, 9], [10, 9, 9], [9, 10, 9]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # two components
        mesh = Mesh(v.astype(float), np.array(path + [(6, 7, 8)]))
    vals = np.array([1.0, 0, 0, 0, 5.0, 0, 0, 0, 0])
    known = np.array([True, False, False, False, True, True, False, False, False])
    vals[5] = 3.0
    out = T._spread(vals, known, mesh)
    # 1 sees 0 and 5 (and 2, unknown): (1 + 3) / 2; 3 sees 4 and 5: (5 + 3) / 2; 2 then sees 1, 3, 5
    np.testing.assert_allclose(out[:6], [1.0, 2.0, (2.0 + 4.0 + 3.0) / 3, 4.0, 5.0, 3.0])
    np.testing.assert_allclose(out[6:], 3.0)


def _open_part(mesh: Mesh, keep_faces: np.ndarray) -> tuple[Mesh, np.ndarray]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Mesh(mesh.vertices, mesh.faces[keep_faces]).cleaned()


def test_a_cut_sphere_keeps_the_sphere_thickness(sphere):
    """Closed form: every chord from a sphere's surface at angle θ to the inward normal is 2 r cos θ, so the
    thickness is 2 r median(cos θ) everywhere. A sphere with a cap cut off keeps that value at its vertices a few
    rings from the cut, although the rays of many of them leave through the opening."""
    cone = inward_cone()
    exact = 2 * 2.0 * np.median(cone[:, 2])
    cut, _ = _open_part(sphere, sphere.vertices[sphere.faces].mean(axis=1)[:, 2] < 1.2)
    with pytest.warns(UserWarning, match="open boundary loop.*ldsift_thickness"):
        t = thickness(cut)
    far = boundary_rings(cut) >= 2
    np.testing.assert_allclose(t[far], exact, rtol=0.05)
    # not vacuous: the escaped rays are many, and the rays that stay in the part alone read it thinner
    frames = T._ray_frames(cut.vertex_normals, L.local_frames(cut).frames[:, 0])
    from wpot.mesh import boundary_caps

    centres, caps = boundary_caps(cut)
    hits = DepthRenderer((np.r_[cut.vertices, centres], np.r_[cut.faces, caps])).inward_hits(
        cut.vertices, frames, cone, first_opening=cut.n_faces)
    escaped = (hits < 0).any(axis=1)
    assert escaped[far].mean() > 0.3
    # an escaped ray's bound is its distance to the cap: below the chord it would have run in the whole sphere
    chords = np.broadcast_to(2 * 2.0 * cone[:, 2], hits.shape)
    assert np.all(-hits[hits < 0] <= chords[hits < 0] * 1.01)
    for bad in (-1, cut.n_faces + len(caps) + 1):
        with pytest.raises(ValueError, match="first_opening"):
            DepthRenderer(cut).inward_hits(cut.vertices, frames, cone, first_opening=bad)


def test_half_a_sphere_reads_lower_bounds_and_says_so(sphere):
    """Every vertex of a hemisphere sees the opening, so no median is known: the values are the medians with the
    escaped rays at the cap, below the sphere's, and a warning names the boundary and the option."""
    half, _ = _open_part(sphere, sphere.vertices[sphere.faces].mean(axis=1)[:, 2] < 0)
    with pytest.warns(UserWarning, match="open boundary loop.*ldsift_thickness"):
        t = thickness(half)
    assert np.isfinite(t).all() and t.min() > 0
    assert np.all(t <= 2 * 2.0 * np.median(inward_cone()[:, 2]) * 1.01)


def _tube(length: float, radius: float, n_z: int, n_theta: int, capped: bool) -> Mesh:
    """A cylinder along z, a grid of n_z rings of n_theta vertices, open or closed by two fans."""
    th = 2 * np.pi * np.arange(n_theta) / n_theta
    z = np.linspace(-length / 2, length / 2, n_z)
    v = np.stack([np.tile(radius * np.cos(th), n_z), np.tile(radius * np.sin(th), n_z), np.repeat(z, n_theta)], 1)
    i, j = np.meshgrid(np.arange(n_z - 1), np.arange(n_theta), indexing="ij")
    a, b = i * n_theta + j, i * n_theta + (j + 1) % n_theta
    f = np.concatenate([np.stack([a, b, b + n_theta], -1).reshape(-1, 3), np.stack([a, b + n_theta, a + n_theta], -1).reshape(-1, 3)])
    if capped:
        bottom, top = len(v), len(v) + 1
        v = np.r_[v, [[0, 0, -length / 2], [0, 0, length / 2]]]
        ring = np.arange(n_theta)
        last = (n_z - 1) * n_theta
        f = np.r_[f, np.stack([np.full(n_theta, bottom), (ring + 1) % n_theta, ring], 1),
                  np.stack([np.full(n_theta, top), last + ring, last + (ring + 1) % n_theta], 1)]
    return Mesh(v, f)


def test_a_cut_cylinder_keeps_the_thickness_of_its_whole():
    """An open stretch of a long closed cylinder: a few rings in from either cut, the thickness is the
    whole's (the rays of the vertices near the cuts run along the axis out of the part)."""
    whole = _tube(12.0, 1.0, 73, 48, capped=True)
    middle = np.abs(whole.vertices[whole.faces][:, :, 2]).max(axis=1) <= 3.0 + 1e-9
    part, index = _open_part(whole, middle)
    assert len(part.boundary_edges) == 2 * 48
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # most of the part's vertices see an opening
        t = thickness(part)
    t_whole = thickness(whole)[index]
    far = boundary_rings(part) >= 3
    assert far.mean() > 0.8
    # within 1 %: the rays that stay in the part alone (dropping the escaped ones, the long ones along the
    # axis) read up to 3 % thinner here
    np.testing.assert_allclose(t[far], t_whole[far], rtol=0.01)


def test_the_field_says_which_vertices_the_part_measures():
    """`thickness_field` on the open cylinder: a vertex with a value of its own has the whole's within 1 %, the
    vertices next to a cut (whose rays run out along the axis) have none, every value lies within its own
    rays' bounds, and on the closed whole every vertex has its own value."""
    whole = _tube(12.0, 1.0, 73, 48, capped=True)
    middle = np.abs(whole.vertices[whole.faces][:, :, 2]).max(axis=1) <= 3.0 + 1e-9
    part, index = _open_part(whole, middle)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # most of the part's vertices see an opening
        f = T.thickness_field(part)
        np.testing.assert_array_equal(f.values, thickness(part))
    w = T.thickness_field(whole)
    assert w.own.all() and np.array_equal(w.low, w.high)
    assert 0.05 < f.own.mean() < 0.95  # neither all nor none
    np.testing.assert_allclose(f.values[f.own], w.values[index][f.own], rtol=0.01)
    assert not f.own[boundary_rings(part) == 0].any()
    assert np.all(f.low <= f.values + 1e-12) and np.all(f.values <= f.high + 1e-12)


def test_a_flat_patch_has_no_thickness():
    g = trimesh.creation.box(extents=(4.0, 4.0, 1.0))
    top = g.vertices[g.faces].mean(axis=1)[:, 2] > 0.4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        patch, _ = Mesh(g.vertices, g.faces[top]).cleaned()
    with pytest.raises(ValueError, match="ldsift_thickness"):
        thickness(patch)


def test_ldsift_thickness_column(sphere):
    mesh = Mesh(sphere.vertices * (1 + 0.2 * np.sin(2 * sphere.vertices[:, [0]])), sphere.faces)
    sig = get_signature("ldsift")
    plain = sig()(mesh)
    withcol = sig(sig.Options(thickness=2.0))(mesh)
    assert plain.shape == (mesh.n_vertices, 128) and withcol.shape == (mesh.n_vertices, 129)
    np.testing.assert_array_equal(withcol[:, :128], plain)
    np.testing.assert_allclose(withcol[:, 128], 2.0 * L.THICKNESS_UNIT * np.log(thickness(mesh)))
    # the column moves by w 512 log s when the shape is scaled by s; the descriptor does not
    big = sig(sig.Options(thickness=2.0))(mesh.transformed(scale=1.25))
    np.testing.assert_allclose(big[:, 128] - withcol[:, 128], 2.0 * L.THICKNESS_UNIT * np.log(1.25), atol=0.05)
    # the flat keyword reaches the signature through a Comparer, and with_options switches it
    from wpot import Comparer

    c = Comparer(signature="ldsift", cache_dir=False)
    np.testing.assert_array_equal(c.with_options(ldsift_thickness=2.0).signatures(mesh), withcol)
    assert c.signatures(mesh).shape == (mesh.n_vertices, 128)
    # cached piece by piece: the descriptor under the key it has without the column, so every weight shares it
    assert sig(sig.Options(thickness=2.0)).pieces()["descriptor"] == sig().params() == sig().pieces()["descriptor"]
    assert len(c.source.signature_cache) == 2  # the descriptor and the thickness, not one entry per weight
    half = c.with_options(ldsift_thickness=0.5).signatures(mesh)
    assert len(c.source.signature_cache) == 2 and not half.flags.writeable
    np.testing.assert_array_equal(half, sig(sig.Options(thickness=0.5))(mesh))
    with pytest.raises(ValueError, match="'descriptor' and 'thickness'"):
        sig().compute_pieces(mesh, ["signature"])
    # the option is keyed only when set, so runs and caches made without it keep their keys
    keyed = sig(sig.Options(thickness=2.0)).params()
    assert "thickness" not in sig().params() and keyed["thickness"] == 2.0 and keyed["thickness_version"] == T.VERSION
    for bad in (-1.0, float("nan"), True, "2"):
        with pytest.raises(ValueError, match="thickness must be a finite number >= 0"):
            sig.Options(thickness=bad)


def test_tosca_david_and_michael_differ_by_their_size(shared_data):
    """One template at two sizes: the thickness ratio is the size ratio, and every David is thinner than
    every Michael (LD-SIFT alone cannot tell them apart)."""
    folder = shared_data / "tosca_lowres"
    if not folder.is_dir():
        pytest.skip(f"TOSCA low-resolution meshes not found at {folder}")
    from wpot.io import load_mesh

    med, size = {}, {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TOSCA's few non-manifold edges
        for name in ("david0", "david2", "michael0", "michael3"):
            m = load_mesh(folder / f"{name}.mat")
            med[name], size[name] = np.median(thickness(m)), np.sqrt(m.area)
    for d, mi in (("david0", "michael0"), ("david2", "michael3")):
        np.testing.assert_allclose(med[mi] / med[d], size[mi] / size[d], rtol=0.03)
    assert max(med["david0"], med["david2"]) < min(med["michael0"], med["michael3"])
