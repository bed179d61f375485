"""Signature time per shape on real meshes (issue 20, "signatures once": goal <= 10 s each on this CPU).

Meshes (from ../shared/data, never copied):
* ``tosca_lowres/cat0.mat``: 3,400 vertices (the paper's TOSCA8 resolution);
* ``tosca_isometric_5k/vtx_5k/cat0.off``: 5,000 vertices;
* with ``--scan``: the 5,000-vertex cat refined by midpoint subdivision (19,994 vertices) then by one √3 step
  (below), 59,978 vertices (issue 21's scan size: eigenpairs <= 60 s at 60,000 vertices), and refined twice by
  midpoint subdivision, 79,970 vertices;
* with ``--refined``: ``cat0.mat`` refined by one √3-subdivision step *without smoothing* (a vertex at each
  face centroid, then every original interior edge flipped to join the two adjacent centroids): 3,400 +
  6,768 = 10,168 vertices, 20,304 triangles, the original vertices unmoved.

Per mesh, cold (no cache: every spectrum is computed here), the paper's parameters (500 eigenpairs, 200
energies; LD-SIFT K = 3, 21 x 21 images):

* WKS split into Laplacian / eigenpairs / WKS (the eigenpair column names the solver the ``"auto"`` rule of
  `wpot.spectral.choose_solver` picked), then ``wpot.wks(mesh, cache=False)``, the call a user makes
  (spectrum included): this is the figure held against the goal. Its peer in the same run: plain
  ``scipy.sparse.linalg.eigsh(W, 500, M, sigma=DEFAULT_SHIFT)`` on the same matrices (scipy's own
  factorization, no guard band, random start), i.e. the eigenpairs alone as any scipy user would get them.
  ``--solvers`` also times the other wpot solvers on the same mesh (dense only up to 5,000 vertices).
* LD-SIFT split into frames / raster / sift (``benchmarks/ldsift_parts.py``'s ``time_ldsift``), then
  ``wpot.ldsift(mesh)`` (the figure held against the goal); its peer in the same run: the vectorized numpy
  z-buffer of ``ldsift_parts.py`` for the raster stage (50 views, extrapolated to all vertices). Beside it, the
  thickness column's extra time (``ldsift_thickness > 0``: frames again, then 32 Warp rays per vertex), and
  ``wpot.ldsift(mesh, orientation="gradient")`` (images with a margin, 31 x 31, and each one's gradient angle).

Timings are wall-clock and, on a shared 2-core machine, noisy: OpenBLAS threads in particular slow
down badly when other processes compete for the cores (try ``OPENBLAS_NUM_THREADS=1``).

    python benchmarks/signatures.py [--solvers] [--refined] [--scan] [--no-ldsift] [--no-peers] [--device cpu] [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

from wpot.mesh import Mesh
from wpot.signatures._wks import wks
from wpot.spectral import LaplaceBeltrami, choose_solver

HERE = Path(__file__).resolve().parent


def sqrt3_refine(mesh: Mesh) -> Mesh:
    """One √3-subdivision step without smoothing (Kobbelt 2000, no vertex relaxation): N + F vertices."""
    v, f = mesh.vertices, mesh.faces
    n, nf = len(v), len(f)
    centroids = v[f].mean(axis=1)
    # half-edge (a -> b) of face t; its twin (b -> a) belongs to the neighbouring face
    a = f.ravel()
    b = np.roll(f, -1, axis=1).ravel()
    face_of = np.repeat(np.arange(nf), 3)
    key = a * n + b
    twin_key = b * n + a
    order = np.argsort(key)
    pos = np.searchsorted(key[order], twin_key)
    pos = np.minimum(pos, len(key) - 1)
    has_twin = key[order][pos] == twin_key
    twin_face = np.where(has_twin, face_of[order][pos], -1)
    tris = []
    interior = has_twin & (a < b)  # each interior edge once
    ca, cg = n + face_of[interior], n + twin_face[interior]
    # quad a, c_g, b, c_f (counter-clockwise) split along the new edge c_f - c_g
    tris.append(np.c_[a[interior], cg, ca])
    tris.append(np.c_[cg, b[interior], ca])
    boundary = ~has_twin  # boundary edges keep their triangle with the centroid
    tris.append(np.c_[a[boundary], b[boundary], n + face_of[boundary]])
    return Mesh(np.vstack([v, centroids]), np.vstack(tris))


def meshes(data: Path, *, refined: bool = False, scan: bool = False) -> list[tuple[str, Mesh]]:
    from wpot.io import load_mesh

    low = load_mesh(data / "tosca_lowres" / "cat0.mat")
    five = load_mesh(data / "tosca_isometric_5k" / "vtx_5k" / "cat0.off")
    out = [("tosca_lowres cat0.mat", low), ("tosca 5k cat0.off", five)]
    if refined:
        out.append(("cat0.mat + sqrt3 refine", sqrt3_refine(low)))
    if scan:
        mid = midpoint_refine(five)
        out.append(("cat0.off midpoint+sqrt3", sqrt3_refine(mid)))
        out.append(("cat0.off midpoint x2", midpoint_refine(mid)))
    return out


def midpoint_refine(mesh: Mesh) -> Mesh:
    """Each triangle split into four at its edge midpoints (no smoothing): about 4x the vertices, the surface
    unchanged; twice on the 5,000-vertex cat, 79,970 vertices (a real scan's size)."""
    e = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = mesh.n_vertices + inv.reshape(-1, 3)  # (F, 3): midpoints of edges (0,1), (1,2), (2,0)
    v = np.vstack([mesh.vertices, 0.5 * (mesh.vertices[uniq[:, 0]] + mesh.vertices[uniq[:, 1]])])
    f = mesh.faces
    faces = np.vstack([np.c_[f[:, 0], mid[:, 0], mid[:, 2]], np.c_[f[:, 1], mid[:, 1], mid[:, 0]],
                       np.c_[f[:, 2], mid[:, 2], mid[:, 1]], mid])
    return Mesh(v, faces)


def time_wks(mesh: Mesh, *, n_eigen: int = 500, n_energies: int = 200, solver: str = "auto") -> dict[str, float | str]:
    t0 = time.perf_counter()
    lb = LaplaceBeltrami(mesh)
    t1 = time.perf_counter()
    s = lb.eigenpairs(n_eigen, solver=solver)
    t2 = time.perf_counter()
    w = wks(s, n_energies=n_energies)  # from the Spectrum: the energy grid of the scale wpot.wks uses
    t3 = time.perf_counter()
    assert np.all(np.isfinite(w))
    return {"laplacian": t1 - t0, "eigen": t2 - t1, "solver": s.solver, "wks": t3 - t2, "total": t3 - t0,
            "lambda_500": float(s.evals[-1])}


def time_wks_api(mesh: Mesh, *, n_eigen: int = 500) -> float:
    """Seconds of ``wpot.wks(mesh, cache=False)``: what a user's call costs with nothing cached."""
    t0 = time.perf_counter()
    w = wks(mesh, n_eigen=n_eigen, cache=False)
    dt = time.perf_counter() - t0
    assert np.all(np.isfinite(w))
    return dt


def time_scipy_eigsh(mesh: Mesh, *, n_eigen: int = 500) -> float:
    """Peer: seconds of plain ``scipy.sparse.linalg.eigsh`` (shift-invert, scipy's own factorization) for the
    same generalized problem W φ = λ M φ that wpot solves, Laplacian assembly excluded."""
    import scipy.sparse.linalg as sla

    from wpot.spectral import DEFAULT_SHIFT

    lb = LaplaceBeltrami(mesh)
    t0 = time.perf_counter()
    w, _ = sla.eigsh(lb.W, k=n_eigen, M=lb.M.tocsr(), sigma=DEFAULT_SHIFT, which="LM")
    dt = time.perf_counter() - t0
    assert np.all(np.isfinite(w))
    return dt


def time_ldsift_api(mesh: Mesh, device: str | None = None, orientation: str = "frame") -> float:
    """Seconds of ``wpot.ldsift(mesh, orientation=...)`` (kernel already loaded by the parts timing)."""
    from wpot.signatures import ldsift

    t0 = time.perf_counter()
    d = ldsift(mesh, device=device, orientation=orientation)
    dt = time.perf_counter() - t0
    assert d.shape == (mesh.n_vertices, 128)
    return dt


def time_thickness(mesh: Mesh, device: str | None = None) -> float:
    """Seconds of LD-SIFT's thickness column (``ldsift_thickness > 0``): frames, then the Warp rays."""
    from wpot.signatures._thickness import thickness

    t0 = time.perf_counter()
    t = thickness(mesh, device=device)
    dt = time.perf_counter() - t0
    assert t.shape == (mesh.n_vertices,) and np.all(t > 0)
    return dt


def load_ldsift_parts():
    """``benchmarks/ldsift_parts.py`` as a module (its ``time_ldsift`` and peers), or None if absent."""
    path = HERE / "ldsift_parts.py"
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location("ldsift_parts", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["ldsift_parts"] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("WPOT_DATA", HERE.parent.parent / "shared" / "data")))
    ap.add_argument("--solvers", action="store_true", help="also time the solver 'auto' did not pick")
    ap.add_argument("--refined", action="store_true", help="also the 10,168-vertex refined cat0")
    ap.add_argument("--scan", action="store_true",
                    help="also the 5,000-vertex cat refined to 59,978 and 79,970 vertices (see the docstring)")
    ap.add_argument("--no-ldsift", action="store_true", help="skip LD-SIFT even if ldsift_parts.py exists")
    ap.add_argument("--no-peers", action="store_true", help="skip the peers (scipy eigsh, numpy z-buffer)")
    ap.add_argument("--device", default=None, help="Warp device for LD-SIFT")
    ap.add_argument("--n-eigen", type=int, default=500)
    ap.add_argument("--goal", type=float, default=10.0, help="seconds per shape and signature to compare against")
    ap.add_argument("--only", type=int, default=None,
                    help="only mesh i: 0, 1 the TOSCA meshes, 2 the --refined one, 3 the two --scan ones")
    args = ap.parse_args()
    if not args.data.is_dir():
        sys.exit(f"data folder not found: {args.data} (set --data or WPOT_DATA)")

    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, "
          f"{os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f} at start; seconds, wall clock, cold")
    parts = None if args.no_ldsift else load_ldsift_parts()
    ldsift = getattr(parts, "time_ldsift", None)
    if ldsift is not None and hasattr(parts, "_warm_up"):
        parts._warm_up(args.device)
    items = meshes(args.data, refined=args.refined or args.only == 2, scan=args.scan or args.only == 3)
    if args.only is not None:  # 0, 1: the two TOSCA meshes; 2: the refined one; 3: the two scan-size ones
        groups = [items[:1], items[1:2], [x for x in items[2:] if "sqrt3 refine" in x[0]],
                  [x for x in items[2:] if "midpoint" in x[0]]]
        items = groups[min(max(args.only, 0), 3)]

    cols = (f"{'mesh':24s} {'N':>6s} | {'laplacian':>9s} {'eigen (solver)':>18s} {'wks':>6s} {'parts':>6s}"
            f" {'wpot.wks':>8s}")
    if not args.no_peers:
        cols += f" {'scipy eigsh':>11s}"
    if args.solvers:
        cols += f" | {'other solvers':>39s}"
    if ldsift is not None:
        cols += (f" | {'frames':>6s} {'raster':>6s} {'sift':>6s} {'parts':>6s} {'wpot.ldsift':>11s} {'gradient':>8s}"
                 f" {'thickness':>9s}")
        if not args.no_peers:
            cols += f" {'numpy raster':>12s}"
    print(cols)
    print("-" * len(cols))
    verdicts = []
    for name, mesh in items:
        r = time_wks(mesh, n_eigen=args.n_eigen)
        api = time_wks_api(mesh, n_eigen=args.n_eigen)
        line = (f"{name:24s} {mesh.n_vertices:6d} | {r['laplacian']:9.3f} {r['eigen']:9.2f} ({r['solver']:>7s})"
                f" {r['wks']:6.3f} {r['total']:6.2f} {api:8.2f}")
        verdicts.append(f"{name} ({mesh.n_vertices} vertices): WKS {api:.1f} s "
                        f"({'within' if api <= args.goal else 'OVER'} {args.goal:g} s)")
        if not args.no_peers:
            line += f" {time_scipy_eigsh(mesh, n_eigen=args.n_eigen):11.2f}"
        if args.solvers:
            for other in (x for x in ("dense", "lanczos", "sliced") if x != r["solver"]):
                if other == "dense" and mesh.n_vertices > 5000:
                    line += f" | {'(dense skipped)':>18s}"
                else:
                    o = time_wks(mesh, n_eigen=args.n_eigen, solver=other)
                    line += f" | {o['eigen']:9.2f} ({other:>7s})"
        if ldsift is not None:
            t = ldsift(mesh, device=args.device) if args.device else ldsift(mesh)
            tot = sum(t.get(k, 0.0) for k in ("frames", "raster", "sift"))
            lapi = time_ldsift_api(mesh, args.device)
            line += (f" | {t.get('frames', float('nan')):6.2f} {t.get('raster', float('nan')):6.2f}"
                     f" {t.get('sift', float('nan')):6.2f} {tot:6.2f} {lapi:11.2f}"
                     f" {time_ldsift_api(mesh, args.device, 'gradient'):8.2f} {time_thickness(mesh, args.device):9.2f}")
            verdicts[-1] += f", LD-SIFT {lapi:.1f} s ({'within' if lapi <= args.goal else 'OVER'} {args.goal:g} s)"
            if not args.no_peers and hasattr(parts, "_peer_numpy_zbuffer"):
                from wpot.signatures._ldsift import local_frames

                per_view = parts._peer_numpy_zbuffer(mesh, local_frames(mesh), 21)
                line += f" {per_view * mesh.n_vertices:12.1f}"
        print(line, flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at end; 'auto' picks (N=3400 / 5000 / 80000, k={args.n_eigen}): "
          f"{choose_solver(3400, args.n_eigen)} / {choose_solver(5000, args.n_eigen)} / "
          f"{choose_solver(80000, args.n_eigen)}")
    print("goal per shape, cold: " + "; ".join(verdicts))


if __name__ == "__main__":
    main()
