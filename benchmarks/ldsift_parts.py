"""LD-SIFT timing, split into frames (Eq. 1, 28), rasterization (Warp ray casting) and SIFT (OpenCV).

`time_ldsift(mesh, device=...)` is imported by benchmarks/signatures.py. Run as a script to print the
split for real meshes at about 3,400, 5,000 and 13,600 vertices, beside two peers measured in the same
run: a vectorized numpy z-buffer on 50 of the views (extrapolated to all views), and one OpenCV
call on a tiled image of all depth images instead of one call per image (with its descriptor error).

    python benchmarks/ldsift_parts.py [--device cpu|cuda] [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from wpot.mesh import Mesh

from wpot.signatures import _ldsift as L  # the module, for its internals


def _warm_up(device: str | None) -> None:
    """Load (compile once, then from Warp's kernel cache) the ray-casting kernel outside the timings."""
    from render.raycast import DepthRenderer

    tri = (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    DepthRenderer(tri, device=device).render(np.zeros((1, 3)), np.eye(3)[None], [1.0], 4)


def time_ldsift(mesh: Mesh, *, device: str | None = None, K: float = 3.0, resolution: int = 21) -> dict[str, float]:
    """Wall-clock seconds of the LD-SIFT stages for ``mesh`` (kernel loading excluded, done before).

    Returns ``{"frames", "raster", "sift", "total"}``: frames = neighbourhoods, covariances and eigen
    frames; raster = BVH build + depth images of all vertices (including the copy back to the host) +
    slab clipping; sift = 8-bit stretch + OpenCV SIFT; total = their sum. The result equals
    ``wpot.ldsift(mesh)``.
    """
    from render.png import to_uint8
    from render.raycast import DepthRenderer

    _warm_up(device)
    t0 = time.perf_counter()
    fr = L.local_frames(mesh, K=K)
    t1 = time.perf_counter()
    raw = DepthRenderer(mesh, device=device).render(mesh.vertices, fr.frames, fr.half_sizes, resolution, ceiling=L.SLAB)
    images = L.to_slab(raw, fr.half_sizes)
    t2 = time.perf_counter()
    L.sift_at_center(to_uint8(images))
    t3 = time.perf_counter()
    return {"frames": t1 - t0, "raster": t2 - t1, "sift": t3 - t2, "total": t3 - t0}


# ---------------------------------------------------------------------------- peers (script only)
def _peer_numpy_zbuffer(mesh: Mesh, fr, resolution: int, n_views: int = 50) -> float:
    """Seconds per view of a vectorized numpy z-buffer (triangles culled to the image square and slab,
    barycentric test at every pixel centre, highest surface kept) on a sample of the views."""
    v, f = mesh.vertices, mesh.faces
    idx = np.random.default_rng(0).choice(mesh.n_vertices, min(n_views, mesh.n_vertices), replace=False)
    g = np.arange(resolution) - (resolution - 1) / 2
    t = time.perf_counter()
    for k in idx:
        s = fr.half_sizes[k]
        loc = (v - v[k]) @ fr.frames[k].T
        tri = loc[f]  # (F, 3 corners, u w h)
        lo, hi = tri.min(axis=1), tri.max(axis=1)
        keep = (hi[:, 0] >= -s) & (lo[:, 0] <= s) & (hi[:, 1] >= -s) & (lo[:, 1] <= s) & (lo[:, 2] <= L.SLAB * s)
        a, b, c = tri[keep, 0], tri[keep, 1], tri[keep, 2]
        uu, ww = np.meshgrid(g * 2 * s / resolution, -g * 2 * s / resolution)
        q = np.c_[uu.ravel(), ww.ravel()][:, None, :] - a[None, :, :2]
        d1, d2 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2]
        det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            l1 = (q[..., 0] * d2[:, 1] - q[..., 1] * d2[:, 0]) / det
            l2 = (d1[:, 0] * q[..., 1] - d1[:, 1] * q[..., 0]) / det
        h = (1 - l1 - l2) * a[:, 2] + l1 * b[:, 2] + l2 * c[:, 2]
        inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1) & (h <= L.SLAB * s)
        np.where(inside, h, -np.inf).max(axis=1)
    return (time.perf_counter() - t) / len(idx)


def _peer_tiled_sift(images_u8: np.ndarray, ref: np.ndarray, pad: int = 10) -> tuple[float, float]:
    """One OpenCV call on all images tiled with reflected padding: (seconds, max |descriptor difference|)."""
    import cv2

    n, r, _ = images_u8.shape
    t = time.perf_counter()
    side = r + 2 * pad
    cols = int(np.ceil(np.sqrt(n)))
    rows = -(-n // cols)
    big = np.zeros((rows * side, cols * side), np.uint8)
    kps = []
    size = L.keypoint_size(r)
    mid = (r - 1) / 2
    for k in range(n):
        i, j = divmod(k, cols)
        big[i * side : (i + 1) * side, j * side : (j + 1) * side] = cv2.copyMakeBorder(
            images_u8[k], pad, pad, pad, pad, cv2.BORDER_REFLECT_101
        )
        for a in (0.0, 180.0):
            kps.append(cv2.KeyPoint(j * side + pad + mid, i * side + pad + mid, size, a))
    _, d = cv2.SIFT_create().compute(big, kps)
    d = d.reshape(n, 2, 128).mean(axis=1)
    dt = time.perf_counter() - t
    return dt, float(np.abs(d - ref).max())


def _meshes(data: Path) -> list[tuple[str, Mesh]]:
    import trimesh

    from wpot.io import load_mesh

    cat_low = load_mesh(data / "tosca_lowres" / "cat0.mat")
    cat_5k = load_mesh(data / "tosca_isometric_5k" / "vtx_5k" / "cat0.off")
    sub = trimesh.Trimesh(cat_low.vertices, cat_low.faces, process=False).subdivide_loop(1)
    cat_sub = Mesh(sub.vertices, sub.faces)
    return [
        ("tosca_lowres/cat0.mat", cat_low),
        ("tosca_isometric_5k cat0.off", cat_5k),
        ("cat0.mat, 1 loop subdivision", cat_sub),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    here = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("WPOT_DATA", here.parent / "shared" / "data")))
    ap.add_argument("--no-peers", action="store_true", help="skip the peer measurements")
    args = ap.parse_args()
    import warp as wp

    wp.init()
    dev = str(wp.get_device(args.device))
    print(f"LD-SIFT parts on Warp device {dev!r} (K=3, 21x21); seconds, wall clock, machine shared: noisy")
    head = f"{'mesh':32s} {'N':>6s} {'frames':>7s} {'raster':>7s} {'sift':>7s} {'total':>7s}"
    if not args.no_peers:
        head += f" | {'numpy z-buffer (extrap.)':>24s} {'tiled SIFT':>10s} {'tiled err':>9s}"
    print(head)
    for name, mesh in _meshes(args.data):
        t = time_ldsift(mesh, device=args.device)
        line = f"{name:32s} {mesh.n_vertices:6d} {t['frames']:7.2f} {t['raster']:7.2f} {t['sift']:7.2f} {t['total']:7.2f}"
        if not args.no_peers:
            from render.png import to_uint8

            fr = L.local_frames(mesh)
            per_view = _peer_numpy_zbuffer(mesh, fr, 21)
            u8 = to_uint8(L.ldsift_images(mesh, device=args.device, frames=fr))
            ref = L.sift_at_center(u8)
            dt, err = _peer_tiled_sift(u8, ref)
            line += f" | {per_view * mesh.n_vertices:24.1f} {dt:10.2f} {err:9.1f}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
