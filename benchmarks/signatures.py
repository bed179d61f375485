"""Signature timings on real meshes: WKS split into Laplacian / eigenpairs / WKS, beside LD-SIFT.

Meshes (from ../shared/data, never copied):
* ``tosca_lowres/cat0.mat``: 3,400 vertices (the paper's resolution);
* ``tosca_isometric_5k/vtx_5k/cat0.off``: 5,000 vertices;
* ``cat0.mat`` refined by one √3-subdivision step *without smoothing* (a vertex at each face centroid,
  then every original interior edge flipped to join the two adjacent centroids): 3,400 + 6,768 = 10,168
  vertices, 20,304 triangles, the original vertices unmoved (area 0.2 % below the original's: the
  flipped edges cut across the old edges).

WKS uses the paper's parameters (500 eigenpairs, 200 energies). The eigenpair column names the solver
that ran (``"auto"`` rule of `wpot.spectral.choose_solver`); ``--solvers`` also times the other solver on
the same mesh in the same run (dense only up to 5,000 vertices), which is how the rule's threshold was
chosen. If ``benchmarks/ldsift_parts.py`` exists, its ``time_ldsift(mesh)`` figures (frames / raster /
sift) are printed in the same table.

Timings are wall-clock and, on a shared 2-core machine, noisy: OpenBLAS threads in particular slow
down badly when other processes compete for the cores (try ``OPENBLAS_NUM_THREADS=1``).

    python benchmarks/signatures.py [--solvers] [--no-ldsift] [--device cpu] [--data ../shared/data]
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
from wpot.signatures._wks import wks_energies, wks_from_eigenpairs
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


def meshes(data: Path) -> list[tuple[str, Mesh]]:
    from wpot.io import load_mesh

    low = load_mesh(data / "tosca_lowres" / "cat0.mat")
    five = load_mesh(data / "tosca_isometric_5k" / "vtx_5k" / "cat0.off")
    return [
        ("tosca_lowres cat0.mat", low),
        ("tosca 5k cat0.off", five),
        ("cat0.mat + sqrt3 refine", sqrt3_refine(low)),
    ]


def time_wks(mesh: Mesh, *, n_eigen: int = 500, n_energies: int = 200, solver: str = "auto") -> dict[str, float | str]:
    t0 = time.perf_counter()
    lb = LaplaceBeltrami(mesh)
    t1 = time.perf_counter()
    s = lb.eigenpairs(n_eigen, solver=solver)
    t2 = time.perf_counter()
    e, sigma = wks_energies(s, n_energies=n_energies)
    w = wks_from_eigenpairs(s.nonzero_evals, s.nonzero_evecs, e, sigma)
    t3 = time.perf_counter()
    assert np.all(np.isfinite(w))
    return {"laplacian": t1 - t0, "eigen": t2 - t1, "solver": s.solver, "wks": t3 - t2, "total": t3 - t0,
            "lambda_500": float(s.evals[-1])}


def load_ldsift_timer():
    path = HERE / "ldsift_parts.py"
    if not path.is_file():
        return None
    sys.path.insert(0, str(HERE))
    spec = importlib.util.spec_from_file_location("ldsift_parts", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return getattr(mod, "time_ldsift", None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("WPOT_DATA", HERE.parent.parent / "shared" / "data")))
    ap.add_argument("--solvers", action="store_true", help="also time the solver 'auto' did not pick")
    ap.add_argument("--no-ldsift", action="store_true", help="skip LD-SIFT even if ldsift_parts.py exists")
    ap.add_argument("--device", default=None, help="Warp device for LD-SIFT")
    ap.add_argument("--n-eigen", type=int, default=500)
    ap.add_argument("--only", type=int, default=None, help="only the i-th mesh (0, 1, 2)")
    args = ap.parse_args()
    if not args.data.is_dir():
        sys.exit(f"data folder not found: {args.data} (set --data or WPOT_DATA)")

    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, "
          f"{os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f} at start")
    ldsift = None if args.no_ldsift else load_ldsift_timer()
    if ldsift is not None and hasattr(sys.modules.get("ldsift_parts"), "_warm_up"):
        sys.modules["ldsift_parts"]._warm_up(args.device)
    items = meshes(args.data)
    if args.only is not None:
        items = [items[args.only]]

    cols = f"{'mesh':26s} {'N':>6s} | {'laplacian':>9s} {'eigen (solver)':>18s} {'wks':>6s} {'WKS tot':>8s}"
    if args.solvers:
        cols += f" | {'other solver':>18s}"
    if ldsift is not None:
        cols += f" | {'frames':>7s} {'raster':>7s} {'sift':>7s} {'LD tot':>7s}"
    print(cols)
    print("-" * len(cols))
    for name, mesh in items:
        r = time_wks(mesh, n_eigen=args.n_eigen)
        line = (f"{name:26s} {mesh.n_vertices:6d} | {r['laplacian']:9.3f} {r['eigen']:9.2f} ({r['solver']:>7s})"
                f" {r['wks']:6.3f} {r['total']:8.2f}")
        if args.solvers:
            other = "lanczos" if r["solver"] == "dense" else "dense"
            if other == "dense" and mesh.n_vertices > 5000:
                line += f" | {'(dense skipped)':>18s}"
            else:
                o = time_wks(mesh, n_eigen=args.n_eigen, solver=other)
                line += f" | {o['eigen']:9.2f} ({other:>7s})"
        if ldsift is not None:
            t = ldsift(mesh, device=args.device) if args.device else ldsift(mesh)
            tot = sum(t.get(k, 0.0) for k in ("frames", "raster", "sift"))
            line += f" | {t.get('frames', float('nan')):7.2f} {t.get('raster', float('nan')):7.2f} {t.get('sift', float('nan')):7.2f} {tot:7.2f}"
        print(line, flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at end; 'auto' rule: dense iff N <= max(300, 7k) or k >= N-1 "
          f"(e.g. N=5000, k={args.n_eigen}: {choose_solver(5000, args.n_eigen)})")


if __name__ == "__main__":
    main()
