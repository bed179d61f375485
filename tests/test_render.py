"""render: Warp ray-cast depth images against closed forms, an independent numpy z-buffer, invariances,
CPU/CUDA agreement, PNG round trips and input errors."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import render
from wpot.mesh import Mesh
from helpers import random_rotation


def _frame_with_normal(n: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random right-handed orthonormal frame (rows e1, e2, n) with the given unit normal."""
    n = n / np.linalg.norm(n)
    a = rng.normal(size=3)
    e1 = a - a.dot(n) * n
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1), n])


def _pixel_coords(res: int, half: float) -> tuple[np.ndarray, np.ndarray]:
    """(u, w) plane coordinates where the rays pass, per the documented convention."""
    from render.raycast import RAY_OFFSET

    p = 2.0 * half / res
    mid = (res - 1) / 2.0
    u = (np.arange(res) - mid + RAY_OFFSET[0]) * p
    w = (mid - np.arange(res) + RAY_OFFSET[1]) * p
    return np.meshgrid(u, w)  # U[i, j] = u_j, W[i, j] = w_i


def _grid_plane(n: int = 12, size: float = 10.0, z: float = 0.0) -> Mesh:
    x = np.linspace(-size / 2, size / 2, n)
    xx, yy = np.meshgrid(x, x)
    v = np.c_[xx.ravel(), yy.ravel(), np.full(n * n, z)]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return Mesh(v, f)


@pytest.fixture(scope="module")
def sphere() -> tuple[Mesh, float]:
    r = 2.0
    s = trimesh.creation.icosphere(subdivisions=4, radius=r)
    return Mesh(s.vertices, s.faces), r


# ------------------------------------------------------------------ closed forms
def test_plane_constant_depth_and_tilted_ramp(device):
    rng = np.random.default_rng(0)
    z0 = 0.3
    mesh = _grid_plane(z=z0)
    res, half = 11, 1.5
    c = np.array([[0.2, -0.4, 1.0], [1.0, 1.0, -0.5]])
    # face-on view: every pixel sees the plane at height z0 - c_z (above or below the view centre)
    up = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    img = render.depth_images(mesh, c, np.stack([up, up]), [half, half], res, device=device)
    # float32: rays start above the whole mesh (about 10 units away), so errors of ~1e-6 of that
    np.testing.assert_allclose(img[0], z0 - c[0, 2], atol=1e-5)
    np.testing.assert_allclose(img[1], z0 - c[1, 2], atol=1e-5)  # plane above the view plane: it counts
    assert np.ptp(img) > 1.0  # the two views differ: a constant image is not trivially right
    # tilted view: the ray c + u e1 + w e2 + h n meets z = z0 at h = (z0 - c_z - u e1_z - w e2_z) / n_z
    fr = _frame_with_normal(np.array([0.3, -0.2, 1.0]), rng)
    img = render.depth_images(mesh, c[:1], fr[None], [half], res, device=device)[0]
    U, W = _pixel_coords(res, half)
    h = (z0 - c[0, 2] - U * fr[0, 2] - W * fr[1, 2]) / fr[2, 2]
    np.testing.assert_allclose(img, h, atol=1e-5)


def test_sphere_cap_from_tangent_plane(sphere, device):
    """From the tangent plane at a pole: height -(R - sqrt(R^2 - u^2 - w^2)) inside the disc, background outside."""
    mesh, r = sphere
    rng = np.random.default_rng(1)
    poles = rng.normal(size=(3, 3))
    poles /= np.linalg.norm(poles, axis=1, keepdims=True)
    frames = np.stack([_frame_with_normal(p, rng) for p in poles])
    res, half = 25, 1.2 * r
    img = render.depth_images(mesh, r * poles, frames, np.full(3, half), res, device=device, background=-99.0)
    U, W = _pixel_coords(res, half)
    rho2 = U**2 + W**2
    inside = rho2 < (0.9 * r) ** 2
    exact = -(r - np.sqrt(np.clip(r**2 - rho2, 0, None)))
    # inscribed polyhedron: radial gap <= (longest edge)^2 / (2R); along the ray it is at most that / cos(slope)
    sag = mesh.edge_lengths.max() ** 2 / (2 * r) / np.sqrt(1 - 0.9**2)
    for k in range(3):
        err = np.abs(img[k] - exact)[inside]
        assert err.max() <= sag, (k, err.max(), sag)
        assert np.all(img[k][rho2 > r**2] == -99.0)  # outside the disc: no surface
        assert np.all(img[k][rho2 < (0.95 * r) ** 2] > -r - 1e-6)  # inside: a hit, on the near cap
    assert sag < 0.05 * r  # the test has teeth: the tolerance is much smaller than the depth range


def test_ceiling_decides_whether_surfaces_above_count(sphere, device):
    """View plane through the sphere's centre: the whole mesh (ceiling inf) shows the upper cap at
    +sqrt(R^2 - rho^2); with the rays starting inside the sphere, the lower cap at -sqrt(R^2 - rho^2)."""
    mesh, r = sphere
    res, half = 15, 1.0
    fr = np.eye(3)[None]
    U, W = _pixel_coords(res, half)
    cap = np.sqrt(r**2 - U**2 - W**2)
    tol = mesh.edge_lengths.max() ** 2 / (2 * r) / 0.7
    top = render.depth_images(mesh, np.zeros((1, 3)), fr, [half], res, device=device)[0]
    np.testing.assert_allclose(top, cap, atol=tol)
    low = render.depth_images(mesh, np.zeros((1, 3)), fr, [half], res, device=device, ceiling=1.0)[0]
    np.testing.assert_allclose(low, -cap, atol=tol)


# ------------------------------------------------------------------ independent numpy z-buffer
def _numpy_zbuffer(v, f, c, fr, half, res, ceiling=np.inf, eps=1e-7):
    """Rasterize every triangle onto the view plane (barycentric test at pixel centres) and keep the
    highest surface point below the ceiling. Returns heights (NaN = background) and a mask of pixels
    whose centre lies within eps (barycentric) of some triangle's edge, where ray casting may differ."""
    U, W = _pixel_coords(res, half)
    P = np.c_[U.ravel(), W.ravel()]
    loc = (v - c) @ fr.T  # (u, w, h) per vertex
    a, b, cc = loc[f[:, 0]], loc[f[:, 1]], loc[f[:, 2]]
    d1, d2 = b[:, :2] - a[:, :2], cc[:, :2] - a[:, :2]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    ok = np.abs(det) > 1e-14
    q = P[:, None, :] - a[None, :, :2]
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (q[..., 0] * d2[:, 1] - q[..., 1] * d2[:, 0]) / det
        l2 = (d1[:, 0] * q[..., 1] - d1[:, 1] * q[..., 0]) / det
    l0 = 1 - l1 - l2
    lmin = np.minimum(np.minimum(l0, l1), l2)
    h = l0 * a[:, 2] + l1 * b[:, 2] + l2 * cc[:, 2]
    top = ceiling * half
    hit = ok & (lmin >= 0) & (h <= top)
    z = np.where(hit, h, -np.inf).max(axis=1)
    z[~hit.any(axis=1)] = np.nan
    edge = (ok & (np.abs(lmin) < eps) & (h <= top + eps)).any(axis=1)
    return z.reshape(res, res), edge.reshape(res, res)


@pytest.mark.parametrize("ceiling", [np.inf, 0.5])
def test_matches_numpy_zbuffer(device, ceiling):
    rng = np.random.default_rng(2)
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    v = s.vertices * (1 + 0.25 * rng.standard_normal((len(s.vertices), 1)))  # bumpy, self-occluding
    keep = v[:, 0] < 0.6  # an open mesh: boundary, so some rays see through to background
    from wpot.mesh import cut

    mesh, _ = cut(Mesh(v, s.faces), keep)
    n_views, res = 12, 13
    idx = rng.choice(mesh.n_vertices, n_views, replace=False)
    c = mesh.vertices[idx] + 0.05 * rng.standard_normal((n_views, 3))
    frames = np.stack([_frame_with_normal(rng.normal(size=3), rng) for _ in range(n_views)])
    half = rng.uniform(0.2, 0.8, n_views)
    img = render.depth_images(mesh, c, frames, half, res, device=device, ceiling=ceiling)
    n_edge = n_bg = 0
    for k in range(n_views):
        ref, edge = _numpy_zbuffer(mesh.vertices, mesh.faces, c[k], frames[k], half[k], res, ceiling)
        good = ~edge
        np.testing.assert_array_equal(np.isnan(img[k][good]), np.isnan(ref[good]))
        both = good & ~np.isnan(ref)
        np.testing.assert_allclose(img[k][both], ref[both], atol=1e-5)  # float32
        n_edge += int(edge.sum())
        n_bg += int(np.isnan(ref).sum())
    assert n_edge <= 0.01 * n_views * res * res  # edge pixels are rare: the comparison covers nearly all
    assert 0 < n_bg < 0.9 * n_views * res * res  # both hits and background pixels were compared


def test_cpu_and_device_agree(sphere, device):
    mesh, r = sphere
    rng = np.random.default_rng(3)
    idx = rng.choice(mesh.n_vertices, 40, replace=False)
    v = mesh.vertices * (1 + 0.1 * np.sin(5 * mesh.vertices[:, :1]))
    m = Mesh(v, mesh.faces)
    frames = np.stack([_frame_with_normal(rng.normal(size=3), rng) for _ in idx])
    half = np.full(len(idx), 0.6)
    a = render.depth_images(m, m.vertices[idx], frames, half, 21, device="cpu")
    b = render.DepthRenderer(m, device=device).render(m.vertices[idx], frames, half, 21)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, atol=1e-5, equal_nan=True)


# ------------------------------------------------------------------ invariances
def test_rigid_motion_and_scaling(device):
    rng = np.random.default_rng(4)
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    v = s.vertices * (1 + 0.2 * rng.standard_normal((len(s.vertices), 1)))
    mesh = Mesh(v, s.faces)
    n = 10
    c = mesh.vertices[:n]
    frames = np.stack([_frame_with_normal(rng.normal(size=3), rng) for _ in range(n)])
    half = np.full(n, 0.5)
    img = render.depth_images(mesh, c, frames, half, 15, device=device)
    rot, t, sc = random_rotation(rng), np.array([100.0, -50.0, 7.0]), 3.0
    moved = mesh.transformed(rot, t, sc)
    img2 = render.depth_images(moved, sc * c @ rot.T + t, frames @ rot.T, sc * half, 15, device=device)
    np.testing.assert_array_equal(np.isnan(img), np.isnan(img2))
    np.testing.assert_allclose(img2 / sc, img, atol=2e-5, equal_nan=True)


def test_joint_flip_of_e1_e2_turns_image_by_180(device):
    """Flipping e1 and e2 turns the image by 180 degrees (odd R: centre fixed), the ray offset turning with it."""
    import render.raycast as rc

    rng = np.random.default_rng(5)
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mesh = Mesh(s.vertices * (1 + 0.2 * rng.standard_normal((len(s.vertices), 1))), s.faces)
    c = mesh.vertices[:8]
    frames = np.stack([_frame_with_normal(rng.normal(size=3), rng) for _ in range(8)])
    flipped = frames * np.array([-1.0, -1.0, 1.0])[None, :, None]
    img = render.depth_images(mesh, c, flipped, np.full(8, 0.5), 15, device=device)
    turned = (-rc.RAY_OFFSET[0], -rc.RAY_OFFSET[1])
    ref = rc.DepthRenderer(mesh, device=device).render(c, frames, np.full(8, 0.5), 15, ray_offset=turned)[:, ::-1, ::-1]
    np.testing.assert_array_equal(np.isnan(img), np.isnan(ref))
    np.testing.assert_allclose(img, ref, atol=1e-6, equal_nan=True)


def test_accepts_vertices_faces_pair():
    mesh = _grid_plane()
    args = (np.array([[0.0, 0, 1]]), np.eye(3)[None], [1.0], 7)
    np.testing.assert_array_equal(render.depth_images(mesh, *args), render.depth_images((mesh.vertices, mesh.faces), *args))


# ------------------------------------------------------------------ PNG
def test_to_uint8_and_png_round_trip(tmp_path):
    import cv2

    a = np.array([[[0.0, 1.0], [2.0, np.nan]], [[5.0, 5.0], [5.0, 5.0]]])
    g = render.to_uint8(a)
    np.testing.assert_array_equal(g[0], [[0, 128], [255, 0]])  # NaN takes the lowest value
    np.testing.assert_array_equal(g[1], 0)  # a constant image
    np.testing.assert_array_equal(render.to_uint8(a, background=2.0)[0], [[0, 128], [255, 255]])
    grid = render.tile(g, columns=2, pad=1)
    assert grid.shape == (4, 7)
    np.testing.assert_array_equal(grid[1:3, 1:3], g[0])
    np.testing.assert_array_equal(grid[1:3, 4:6], g[1])
    path = tmp_path / "depth.png"
    written = render.save_png(a, path, columns=2, scale=3)
    np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), written)
    np.testing.assert_array_equal(written[::3, ::3], grid)


# ------------------------------------------------------------------ bad input
def test_bad_input_errors():
    mesh = _grid_plane()
    c, fr, s = np.zeros((1, 3)), np.eye(3)[None], np.ones(1)
    with pytest.raises(ValueError, match=r"centers must have shape"):
        render.depth_images(mesh, np.zeros(3), fr, s)
    with pytest.raises(ValueError, match=r"frames must have shape"):
        render.depth_images(mesh, c, np.eye(3), s)
    with pytest.raises(ValueError, match=r"orthonormal.*view 0"):
        render.depth_images(mesh, c, 2 * fr, s)
    with pytest.raises(ValueError, match=r"half_sizes must be finite and positive; view 0 has -1"):
        render.depth_images(mesh, c, fr, -s)
    with pytest.raises(ValueError, match=r"half_sizes must have shape"):
        render.depth_images(mesh, c, fr, np.ones(2))
    with pytest.raises(ValueError, match=r"resolution must be an integer >= 2, got 1"):
        render.depth_images(mesh, c, fr, s, 1)
    with pytest.raises(ValueError, match=r"finite"):
        render.depth_images(mesh, np.full((1, 3), np.nan), fr, s)
    with pytest.raises(ValueError, match=r"ceiling must be positive"):
        render.depth_images(mesh, c, fr, s, ceiling=0.0)
    with pytest.raises(TypeError, match=r"wpot.Mesh or a \(vertices, faces\) pair, got str"):
        render.depth_images("mesh.off", c, fr, s)
    with pytest.raises(ValueError, match=r"outside \[0, 143\]"):
        render.depth_images((mesh.vertices, mesh.faces + 1), c, fr, s)
    with pytest.raises(ValueError, match=r"uint8"):
        render.tile(np.zeros((2, 3, 3)))
