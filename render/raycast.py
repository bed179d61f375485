"""Depth images of a whole triangle mesh on many local planes at once, by ray casting in Warp.

One view per row of ``centers``: an orthographic camera above the plane through ``centers[k]`` with
normal ``frames[k, 2]`` looks straight down (direction ``-n``). All views are rendered in one Warp
launch of shape ``(n, R, R)``; each thread casts one ray against a BVH (`warp.Mesh`) built once per
mesh by `DepthRenderer`. The same BVH also casts rays *into* the solid from surface points
(`DepthRenderer.inward_hits`, one launch of shape ``(n, m)``), for the local thickness. On the CPU each
launch is cut into one per core over contiguous views (`wpot._warp.launch_rows`), with the same results bit
for bit.

Conventions (for view k, with ``e1, e2, n = frames[k]``, ``c = centers[k]``, ``S = half_sizes[k]``)
------------------------------------------------------------------------------------------------------
* The image covers the square ``[-S, S] x [-S, S]`` of the plane, split into ``R x R`` square pixels of
  side ``p = 2 S / R``. Pixel centres sit at half-integer offsets from the square's edges, so for odd R
  the centre pixel ``(R // 2, R // 2)`` is exactly over ``c``.
* Axes: column ``j`` runs along ``+e1`` and row ``i`` along ``-e2`` (image rows go down), i.e. the
  pixel centre ``(i, j)`` is the point ``c + u e1 + w e2`` with
  ``u = (j - (R - 1) / 2) p`` and ``w = ((R - 1) / 2 - i) p`` (rays pass `RAY_OFFSET` from there).
  For a right-handed frame (``e1 x e2 = n``) this is the view from ``+n``, not mirrored. A joint sign
  flip of ``e1`` and ``e2`` rotates the image by 180 degrees.
* Value: the signed height ``h = (x - c) . n`` of the first surface point ``x`` met by the ray that
  comes down from ``+n`` (from above) through the pixel centre: positive above the plane, negative
  below. With the default ``ceiling=inf`` every surface counts, including surfaces above the plane
  (an overhanging part hides what lies under it). With a finite ``ceiling`` the ray starts at height
  ``ceiling * S`` above the plane, so surfaces higher than that are ignored (a near clipping plane).
* Background: pixels whose ray meets no surface get ``background`` (NaN by default).
* Ray offset: each ray passes ``RAY_OFFSET = (1e-3, 6e-4)`` pixels from its pixel centre (along
  ``+e1`` and ``+e2``). Views are usually centred on a mesh vertex, and a float32 ray-triangle test on
  a ray through a vertex exactly can miss all the triangles around it (on a bumpy sphere it did, for
  many centre pixels; the docs' Results page). The offset moves the ray off the vertex, in a direction unlikely to
  follow an edge; it changes heights by at most the surface slope times 1e-3 pixel.
* Edge pixels: a ray that passes (to float32 precision) through a triangle edge or vertex may hit
  either triangle, or, rarely, slip between them; silhouette pixels can therefore differ from an
  exact rasterizer when a ray lies within about 1e-6 (relative) of a projected edge.

Arithmetic is float32 (Warp's mesh BVH). The mesh is shifted to its bounding-box centre before it is
uploaded, so the precision does not depend on where the mesh sits in space.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from wpot._warp import launch_rows

__all__ = ["DepthRenderer", "depth_images", "inward_cone", "RAY_OFFSET"]

if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.1x: the init banner and module-load lines are INFO messages
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
# no fused multiply-add: the same depths on the CPU and CUDA up to float32 rounding of each operation
wp.set_module_options({"enable_backward": False, "fuse_fp": False})


#: rays pass this far (in pixels, along +e1 and +e2) from the pixel centres; see the module docstring
RAY_OFFSET = (1e-3, 6e-4)


@wp.kernel
def _cast_kernel(
    mesh_id: wp.uint64,
    centers: wp.array(dtype=wp.vec3),
    e1: wp.array(dtype=wp.vec3),
    e2: wp.array(dtype=wp.vec3),
    nrm: wp.array(dtype=wp.vec3),
    half: wp.array(dtype=wp.float32),
    top: wp.array(dtype=wp.float32),
    depth: wp.array(dtype=wp.float32),
    res: int,
    du: wp.float32,
    dw: wp.float32,
    background: wp.float32,
    out: wp.array3d(dtype=wp.float32),
):
    k, i, j = wp.tid()
    pix = 2.0 * half[k] / float(res)
    mid = float(res - 1) * 0.5
    u = (float(j) - mid + du) * pix
    w = (mid - float(i) + dw) * pix
    n = nrm[k]
    h0 = top[k]
    start = centers[k] + u * e1[k] + w * e2[k] + h0 * n
    q = wp.mesh_query_ray(mesh_id, start, -n, depth[k])
    if q.result:
        out[k, i, j] = h0 - q.t
    else:
        out[k, i, j] = background


@wp.kernel
def _inward_kernel(
    mesh_id: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    e1: wp.array(dtype=wp.vec3),
    e2: wp.array(dtype=wp.vec3),
    outward: wp.array(dtype=wp.vec3),
    cone: wp.array(dtype=wp.vec3),
    facing: wp.float32,
    reach: wp.float32,
    offset: wp.float32,
    first_opening: wp.int32,
    out: wp.array2d(dtype=wp.float32),
):
    i, k = wp.tid()
    n = outward[i]
    c = cone[k]
    d = c[0] * e1[i] + c[1] * e2[i] - c[2] * n
    q = wp.mesh_query_ray(mesh_id, origins[i] - offset * n, d, reach)
    t = float(wp.nan)
    # a ray that leaves the volume meets the inner side of a face: its winding normal (times `facing`, the
    # mesh's winding) points along the ray; through an opening's cap, it is only known to run at least that far
    if q.result:
        if facing * wp.dot(q.normal, d) > 0.0:
            t = q.t + offset * c[2]
            if q.face >= first_opening:
                t = -t
    out[i, k] = t


def _mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64, faces (F, 3) int64) from a `wpot.Mesh` or a (vertices, faces) pair."""
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        v, f = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v, f = mesh
    else:
        raise TypeError(f"mesh must be a wpot.Mesh or a (vertices, faces) pair, got {type(mesh).__name__}")
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"mesh vertices must have shape (N, 3) with N >= 1, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("mesh vertices contain NaN or infinite coordinates")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"mesh faces must have shape (F, 3) with F >= 1, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"mesh faces must be integer vertex indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"mesh faces index vertices outside [0, {len(v) - 1}]: range [{f.min()}, {f.max()}]")
    return v, f.astype(np.int64)


class DepthRenderer:
    """A mesh uploaded once to a Warp device as a BVH (`warp.Mesh`), ready to render depth images.

    Parameters
    ----------
    mesh : `wpot.Mesh`, or a pair ``(vertices (N, 3), faces (F, 3) 0-based)``
    device : Warp device (``"cpu"``, ``"cuda"``, ``"cuda:0"``); None means Warp's default device.

    See the module docstring for the image conventions.
    """

    def __init__(self, mesh: Any, *, device: str | None = None) -> None:
        v, f = _mesh_arrays(mesh)
        wp.init()
        self.device = wp.get_device(device)
        lo, hi = v.min(axis=0), v.max(axis=0)
        #: bounding-box centre, subtracted from every coordinate before upload
        self.origin = 0.5 * (lo + hi)
        #: radius of a ball around `origin` that holds the whole mesh
        self.radius = float(0.5 * np.linalg.norm(hi - lo))
        self.n_vertices = len(v)
        self.n_faces = len(f)
        self._points = wp.array((v - self.origin).astype(np.float32), dtype=wp.vec3, device=self.device)
        self._indices = wp.array(f.astype(np.int32).ravel(), dtype=wp.int32, device=self.device)
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)

    def render(
        self,
        centers: ArrayLike,
        frames: ArrayLike,
        half_sizes: ArrayLike,
        resolution: int = 21,
        *,
        background: float = np.nan,
        ceiling: float = np.inf,
        ray_offset: tuple[float, float] = RAY_OFFSET,
    ) -> np.ndarray:
        """Depth images, one per view: see `depth_images`. Returns (n, R, R) float32.

        ``ray_offset`` : (along e1, along -e2) in pixels, where each ray passes from its pixel centre (default
        `RAY_OFFSET`: off the exact centres, so that a ray never meets a mesh edge or vertex head-on).
        """
        c, fr, s, res = _check_views(centers, frames, half_sizes, resolution)
        off = tuple(float(x) for x in ray_offset)
        if len(off) != 2 or not all(np.isfinite(off)) or max(abs(x) for x in off) >= 0.5:
            raise ValueError(f"ray_offset must be two finite numbers of magnitude < 0.5 pixel, got {ray_offset!r}")
        ceiling = float(ceiling)
        if not ceiling > 0:
            raise ValueError(f"ceiling must be positive (a multiple of half_sizes) or inf, got {ceiling!r}")
        n = len(c)
        out = np.empty((n, res, res), dtype=np.float32)
        if n == 0:
            return out
        local = c - self.origin
        # every surface point lies within `reach` of the view centre, so it has |height| <= reach
        reach = np.linalg.norm(local, axis=1) + self.radius
        margin = 1e-3 * (reach + s) + 1e-30
        top = reach + margin if np.isposinf(ceiling) else np.minimum(ceiling * s, reach + margin)
        depth = top + reach + margin
        dev = self.device
        vec, flt = self._upload(wp.vec3), self._upload(wp.float32)
        res_wp = wp.empty((n, res, res), dtype=wp.float32, device=dev)
        views = [vec(local), vec(fr[:, 0]), vec(fr[:, 1]), vec(fr[:, 2]), flt(s), flt(top), flt(depth)]
        launch_rows(lambda lo, hi: wp.launch(
            _cast_kernel,
            dim=(hi - lo, res, res),
            inputs=[self._mesh.id, *(a[lo:hi] for a in views), int(res), off[0], off[1], float(background)],
            outputs=[res_wp[lo:hi]],
            device=dev,
        ), n, dev, cols=res * res)
        out[...] = res_wp.numpy()
        return out

    def _upload(self, dtype: Any):
        """A function that copies a float array to this renderer's device as float32 ``dtype`` (wp.vec3: rows)."""
        return lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=self.device)

    def inward_hits(self, points: ArrayLike, frames: ArrayLike, cone: ArrayLike, *, facing: int = 1,
                    first_opening: int | None = None) -> np.ndarray:
        """How far rays shot into the volume travel before they leave it: the shape diameter function's rays.

        From each point ``p`` (a surface point with frame ``e1, e2, o``, ``o`` its unit outward normal) one ray
        per cone direction ``(x, y, z)`` leaves along ``x e1 + y e2 - z o`` (``z > 0`` points inwards). A ray
        counts when the first face it meets is seen from inside (its winding normal, times ``facing``, points
        along the ray): the ray crossed the solid and left it there.

        Parameters
        ----------
        points : (n, 3) ray origins on the surface (mesh coordinates)
        frames : (n, 3, 3) orthonormal frames, rows ``e1, e2, o`` with ``o`` the outward normal (either
            handedness)
        cone : (m, 3) unit directions in the frame, every ``z > 0`` (see `inward_cone`)
        facing : +1 when the faces wind counter-clockwise seen from outside, -1 the other way
            (`wpot.mesh.winding`)
        first_opening : the faces from this index on are openings, caps over the holes of an open surface
            (`wpot.mesh.boundary_caps`); None: there are none

        Returns
        -------
        (n, m) float64 distances from each point to where each ray leaves the solid; NaN for a ray that
        meets nothing or first meets a face from outside; minus the distance for a ray that leaves through an
        opening (in the whole the surface was cut from, it runs at least that far). Rays start ``1e-5`` of the
        mesh's size inside the surface (so a face at the origin is not met at distance 0); the distance is
        counted from ``p``.
        """
        p = np.asarray(points, dtype=np.float64)
        fr = np.asarray(frames, dtype=np.float64)
        c = np.asarray(cone, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or fr.shape != (len(p), 3, 3):
            raise ValueError(f"points must have shape (n, 3) and frames (n, 3, 3), got {p.shape} and {fr.shape}")
        if c.ndim != 2 or c.shape[1] != 3 or len(c) == 0 or not np.all(c[:, 2] > 0):
            raise ValueError(f"cone must have shape (m, 3), m >= 1, with every z > 0 (inwards), got {c.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(fr))):
            raise ValueError("points and frames must be finite (got NaN or inf)")
        if facing not in (1, -1):
            raise ValueError(f"facing must be +1 or -1, got {facing!r}")
        opening = self.n_faces if first_opening is None else int(first_opening)
        if not 0 <= opening <= self.n_faces:
            raise ValueError(f"first_opening must be a face index in [0, {self.n_faces}], got {first_opening!r}")
        n, m = len(p), len(c)
        if n == 0:
            return np.empty((0, m))
        dev = self.device
        vec = self._upload(wp.vec3)
        out = wp.empty((n, m), dtype=wp.float32, device=dev)
        local = p - self.origin
        reach = float(np.linalg.norm(local, axis=1).max() + 2.0 * self.radius) * 1.01 + 1e-30
        rays = [vec(local), vec(fr[:, 0]), vec(fr[:, 1]), vec(fr[:, 2])]
        cone_wp = vec(c)
        launch_rows(lambda lo, hi: wp.launch(
            _inward_kernel, dim=(hi - lo, m),
            inputs=[self._mesh.id, *(a[lo:hi] for a in rays), cone_wp, float(facing), reach, 1e-5 * self.radius,
                    opening],
            outputs=[out[lo:hi]], device=dev,
        ), n, dev, cols=m)
        return out.numpy().astype(np.float64)


def inward_cone(n_rays: int = 32, half_angle: float = 60.0) -> np.ndarray:
    """(n_rays, 3) unit directions spread over the cap of half-angle ``half_angle`` degrees about +z.

    ``n_rays / 4`` directions of a Fibonacci spiral over the cap (equal solid angle each, ``cos θ`` uniform over
    ``[cos half_angle, 1]``), each with its mirror images ``(±x, ±y, z)``: the set does not change when the frame's
    ``e1, e2`` change sign, the ambiguity of a frame found by PCA (`wpot.signatures.local_frames`).
    """
    if isinstance(n_rays, bool) or not isinstance(n_rays, (int, np.integer)) or n_rays < 4 or n_rays % 4:
        raise ValueError(f"n_rays must be a positive multiple of 4, got {n_rays!r}")
    h = float(half_angle)
    if not 0 < h < 90:
        raise ValueError(f"half_angle must be in (0, 90) degrees, got {half_angle!r}")
    q = n_rays // 4
    i = np.arange(q) + 0.5
    cz = 1.0 - (1.0 - np.cos(np.deg2rad(h))) * i / q
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    sz = np.sqrt(1.0 - cz * cz)
    x, y = sz * np.cos(phi), sz * np.sin(phi)
    return np.concatenate([np.stack([sx * x, sy * y, cz], axis=1) for sx in (1, -1) for sy in (1, -1)])


def _check_views(centers: ArrayLike, frames: ArrayLike, half_sizes: ArrayLike, resolution: int):
    c = np.asarray(centers, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centers must have shape (n, 3), got {c.shape}")
    n = len(c)
    fr = np.asarray(frames, dtype=np.float64)
    if fr.shape != (n, 3, 3):
        raise ValueError(f"frames must have shape (n, 3, 3) = ({n}, 3, 3) (rows e1, e2, n), got {fr.shape}")
    s = np.asarray(half_sizes, dtype=np.float64)
    if s.ndim == 0:
        s = np.full(n, float(s))
    if s.shape != (n,):
        raise ValueError(f"half_sizes must have shape (n,) = ({n},), got {s.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(fr))):
        raise ValueError("centers and frames must be finite (got NaN or inf)")
    bad = np.nonzero(~(s > 0) | ~np.isfinite(s))[0]
    if bad.size:
        raise ValueError(f"half_sizes must be finite and positive; view {bad[0]} has {float(s[bad[0]])!r}")
    if n:
        gram = fr @ fr.transpose(0, 2, 1)
        err = np.abs(gram - np.eye(3)).max(axis=(1, 2))
        if err.max() > 1e-4:
            k = int(np.argmax(err))
            raise ValueError(
                f"frames must be orthonormal (rows e1, e2, n); view {k} is off by {err[k]:.3g}: {fr[k].tolist()}"
            )
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 2:
        raise ValueError(f"resolution must be an integer >= 2, got {resolution!r}")
    return c, fr, s, int(resolution)


def depth_images(
    mesh: Any,
    centers: ArrayLike,
    frames: ArrayLike,
    half_sizes: ArrayLike,
    resolution: int = 21,
    *,
    device: str | None = None,
    background: float = np.nan,
    ceiling: float = np.inf,
) -> np.ndarray:
    """Depth images of the whole ``mesh`` on n local planes (one Warp launch, ray casting on a BVH).

    Parameters
    ----------
    mesh : `wpot.Mesh`, or ``(vertices (N, 3), faces (F, 3))``
    centers : (n, 3) points ``c`` on the planes (the image centres)
    frames : (n, 3, 3) orthonormal frames, rows ``e1, e2, n``; ``n`` is the viewing axis (camera on
        the ``+n`` side looking towards ``-n``), ``e1`` the image's column axis, ``-e2`` its row axis
    half_sizes : (n,) half widths ``S`` (the image covers ``2S x 2S``), or a scalar
    resolution : R, pixels per side
    device : Warp device; None means Warp's default device
    background : value of pixels whose ray meets no surface (default NaN)
    ceiling : rays start at height ``ceiling * S`` above the plane; surfaces higher than that are
        ignored. Default inf: every surface counts.

    Returns
    -------
    (n, R, R) float32: ``img[k, i, j]`` is the signed height along ``frames[k, 2]`` of the first surface
    seen from above at the point ``c + u e1 + w e2`` with ``u = (j - (R-1)/2) 2S/R`` and
    ``w = ((R-1)/2 - i) 2S/R``, or ``background``. See the module docstring.

    For repeated calls on the same mesh, build a `DepthRenderer` once and call its ``render``.
    """
    return DepthRenderer(mesh, device=device).render(
        centers, frames, half_sizes, resolution, background=background, ceiling=ceiling
    )
