"""Builders shared by the tests: generated meshes and datasets, random rotations, small transport problems and an
independent QP solve of partial transport. Fixtures live in conftest.py."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from wpot.mesh import Mesh
from wpot.signatures import Signature, SignatureOptions
from wpot.signatures.base import option


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation (3, 3) (QR of a Gaussian matrix, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def deform_sphere(p: np.ndarray) -> np.ndarray:
    """A smooth, asymmetric star-shaped surface over the unit sphere (no eigenvalue degeneracies)."""
    p = p / np.linalg.norm(p, axis=1, keepdims=True)
    r = 1 + 0.25 * np.exp(-8 * ((p - [0.6, 0.6, 0.5]) ** 2).sum(1)) + 0.1 * p[:, 0] * p[:, 1]
    return p * r[:, None] * [1.6, 1.0, 0.7]


def partial_qp(C: np.ndarray, r1: np.ndarray, r2: np.ndarray, mass_penalty: float):
    """The chi^2 partial transport problem (Eq. 17-18) on the whole dense plan, by cvxpy (an independent
    formulation: the masses are the plan's sums, no duals, no support): (optimum, m1, m2)."""
    import cvxpy as cp

    G = cp.Variable(C.shape, nonneg=True)
    m1, m2 = cp.sum(G, axis=1), cp.sum(G, axis=0)
    obj = (cp.sum(cp.multiply(C, G)) + cp.sum(cp.multiply(mass_penalty / r1**2, cp.square(m1)))
           + cp.sum(cp.multiply(mass_penalty / r2**2, cp.square(m2))))
    prob = cp.Problem(cp.Minimize(obj), [cp.sum(G) == 1])
    prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
    return prob.value, m1.value, m2.value


#: small spectral settings for real runs in tests
FAST = {"n_eigen": 30, "n_energies": 30}
FAST_CLI = ["--n-eigen", "30", "--n-energies", "30"]


def make_dataset(folder: Path, n_per_class: int = 3, n: int = 100) -> Path:
    """Two classes of small meshes: 'blob' (the example surface) and 'flat' (the same surface stretched), each
    a different triangulation (seed)."""
    from wpot.examples import example_mesh
    from wpot.io import save_mesh

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n_per_class):
        m = example_mesh(n + 7 * k, seed=k)
        save_mesh(m, folder / f"blob{k + 1}.off")
        save_mesh(Mesh(m.vertices * np.array([1.8, 0.6, 1.0]), m.faces), folder / f"flat{k + 1}.off")
    return folder


#: bumps (centre, height, width) that make `mirror_symmetric`'s surface symmetric under x -> -x alone
BUMPS = (((0.7, 0.5, 0.3), 0.8, 0.35), ((0.0, -0.6, 0.8), 0.5, 0.4), ((0.4, -0.3, -0.85), 0.45, 0.3),
         ((0.0, 0.9, -0.4), 0.3, 0.45))


def sphere_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    f = ConvexHull(u).simplices.astype(np.int64)
    nrm = np.cross(u[f[:, 1]] - u[f[:, 0]], u[f[:, 2]] - u[f[:, 0]])
    flip = np.einsum("ij,ij->i", nrm, u[f].sum(axis=1)) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return u, f


def mirror_symmetric(n: int = 900, seed: int = 0) -> Mesh:
    """A closed, outward-wound surface whose only symmetry is the reflection x -> -x (not mirror-symmetric
    in its triangulation: the sphere points are random)."""
    u, f = sphere_points(n, seed)
    return Mesh(u * sphere_radius(u)[:, None] * np.array([1.0, 1.3, 0.8]), f)


def points_cost(n1, n2, d=8, seed=0):
    rng = np.random.default_rng(seed)
    X, Y = rng.random((n1, d)), rng.random((n2, d))
    C = np.linalg.norm(X[:, None] - Y[None], axis=-1)
    return C / C.max()


def masses(n, seed):
    m = np.random.default_rng(seed).random(n) + 0.2
    return m / m.sum()


def sphere_radius(u: np.ndarray) -> np.ndarray:
    r = np.ones(len(u))
    for c, a, w in BUMPS:
        for cx in {c[0], -c[0]}:
            cc = np.array([cx, c[1], c[2]]) / np.linalg.norm(c)
            r += a * np.exp((u @ cc - 1.0) / w ** 2)
    return r


@dataclasses.dataclass(frozen=True)
class CoordOptions(SignatureOptions):
    scale: float = option(1.0, keyword="coord_scale", flag="--coord-scale", help="factor (default {default})")
    n_eigen: int = option(500, keyword="n_eigen", flag="--n-eigen", help="unused here")


class Coordinates(Signature):
    """Vertex coordinates times a factor: a signature defined outside the package."""

    name = "coords"
    title = "Coordinates"
    metric = "l2"
    version = 1
    Options = CoordOptions

    def __call__(self, mesh):
        return np.asarray(mesh.vertices, dtype=np.float64) * self.options.scale


def cli(capsys, *args) -> tuple[int, str, str]:
    """Run the `wpot` command in this process: exit code, stdout, stderr (without Warp's own start-up notices)."""
    from wpot.cli import main

    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    strip = lambda text: "\n".join(ln for ln in text.splitlines() if not ln.startswith("Warp "))
    return code, strip(out), strip(err)


def one_line_error(code: int, err: str) -> str:
    """The command's one-line error (exit code 2), or a failed assertion."""
    lines = [ln for ln in err.splitlines() if ln.startswith("wpot: error:")]
    assert code == 2 and len(lines) == 1, (code, err)
    return lines[0]


class Clock:
    """A clock that advances one second per reading: every progress stage takes 1.0 s."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        self.t += 1.0
        return self.t
