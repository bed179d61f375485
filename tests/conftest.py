"""Shared test fixtures: the real-data folder (skipped when absent) and the Warp devices to test on."""
from __future__ import annotations

import os
from pathlib import Path

# Two pytest-xdist workers on two cores: one BLAS thread each, or they oversubscribe the machine.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

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


def _meshes(shared_data: Path, folder: str, label: str) -> Path:
    p = shared_data / folder / "vtx_5k"
    if not p.is_dir():
        pytest.skip(f"{label} 5k meshes not found at {p}")
    return p


@pytest.fixture(scope="session")
def tosca5k(shared_data) -> Path:
    return _meshes(shared_data, "tosca_isometric_5k", "TOSCA")


@pytest.fixture(scope="session")
def faust5k(shared_data) -> Path:
    return _meshes(shared_data, "faust_5k", "FAUST")






@pytest.fixture(scope="module")
def blob():
    """A 642-vertex smooth blob (`deform_sphere` of an icosphere): spectral tests' generic surface."""
    import trimesh

    from wpot.mesh import Mesh

    t = trimesh.creation.icosphere(3)
    from helpers import deform_sphere

    return Mesh(deform_sphere(t.vertices), t.faces)


@pytest.fixture(scope="module")
def blob_spectrum(blob):
    from wpot.spectral import eigenpairs

    return eigenpairs(blob, k=60)


@pytest.fixture
def coords():
    """A signature defined outside the package (`helpers.Coordinates`), registered for the test."""
    from helpers import Coordinates
    from wpot.signatures import register_signature, unregister_signature

    register_signature(Coordinates)
    yield Coordinates
    unregister_signature("coords")


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """Two 300-vertex triangulations of one surface, as files."""
    from wpot.examples import example_pair
    from wpot.io import save_mesh

    folder = tmp_path_factory.mktemp("pair")
    p = example_pair(300, seed=0, n_target=300)
    save_mesh(p.source, folder / "a.off")
    save_mesh(p.target, folder / "b.off")
    return folder / "a.off", folder / "b.off"
