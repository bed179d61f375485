"""Shared test fixtures: the real-data folder (skipped when absent) and the Warp devices to test on."""
from __future__ import annotations

import os
from pathlib import Path

# Two pytest-xdist workers on two cores: one BLAS thread each, or they oversubscribe the machine.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
#: real shape data sits beside the project (../shared/data); WPOT_DATA overrides
DATA = Path(os.environ.get("WPOT_DATA", ROOT.parent / "shared" / "data"))


def _cuda_available() -> bool:
    try:
        import warp as wp

        from wpot._warp import init

        init()  # as wpot starts Warp: no banner, no "no CUDA driver" line on a CPU machine
        return wp.is_cuda_available()
    except Exception:  # pragma: no cover - no usable warp at all
        return False


#: devices every device-parametrized test runs on: always "cpu", and "cuda" when present
DEVICES = ["cpu"] + (["cuda"] if _cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The `../shared/data` folder; tests that use it are skipped with a reason when it is absent."""
    if not DATA.is_dir():
        pytest.skip(f"real shape data not found at {DATA} (set WPOT_DATA or place ../shared/data beside the project)")
    return DATA


@pytest.fixture(scope="session")
def tosca5k(shared_data) -> Path:
    p = shared_data / "tosca_isometric_5k" / "vtx_5k"
    if not p.is_dir():
        pytest.skip(f"TOSCA 5k meshes not found at {p}")
    return p


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


@pytest.fixture(scope="module")
def blob():
    """A 642-vertex smooth blob (`deform_sphere` of an icosphere): spectral tests' generic surface."""
    import trimesh

    from wpot.mesh import Mesh

    t = trimesh.creation.icosphere(3)
    return Mesh(deform_sphere(t.vertices), t.faces)


@pytest.fixture(scope="module")
def blob_spectrum(blob):
    from wpot.spectral import eigenpairs

    return eigenpairs(blob, k=60)


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


def load_benchmark(name: str):
    """``benchmarks/<name>.py`` as a module, registered in ``sys.modules`` under ``name`` (dataclasses look their
    module up by name)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
