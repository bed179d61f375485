"""wpot: compare 3D shapes (triangle meshes) by statistical-physics optimal transport.

Koehl & Orland (2023), "Partial shape matching" — per-vertex signatures (WKS or LD-SIFT), a cost
matrix between them, and a balanced or partial (unbalanced, chi^2 mass penalty) transport plan found
by annealing the inverse temperature beta. Heavy numerics run in NVIDIA Warp kernels, on "cpu" or "cuda".

Public names are imported lazily (``import wpot`` stays cheap; Warp is only loaded when a name that
needs it is first used). ``__all__`` is the explicit list; a test checks that every name resolves.
"""
from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS: dict[str, str] = {
    # mesh I/O and validation
    "Mesh": "wpot.mesh",
    "MeshWarning": "wpot.mesh",
    "cut": "wpot.mesh",
    "load_mesh": "wpot.io",
    "save_mesh": "wpot.io",
    "load_vts": "wpot.io",
    "load_vertex_map": "wpot.io",
    "save_vts": "wpot.io",
    "save_vertex_map": "wpot.io",
    "MESH_FORMATS": "wpot.io",
    # generated example shapes
    "example_mesh": "wpot.examples",
    "example_pair": "wpot.examples",
    "example_partial": "wpot.examples",
    "ExamplePair": "wpot.examples",
    "ExamplePartial": "wpot.examples",
    # spectral
    "laplace_beltrami": "wpot.spectral",
    "eigenpairs": "wpot.spectral",
    "LaplaceBeltrami": "wpot.spectral",
    "Spectrum": "wpot.spectral",
    "Cache": "wpot.cache",
    # signatures and costs
    "wks": "wpot.signatures",
    "wks_energies": "wpot.signatures",
    "wks_from_eigenpairs": "wpot.signatures",
    "wks_weights": "wpot.signatures",
    "EnergyGrid": "wpot.signatures",
    "ldsift": "wpot.signatures",
    "local_frames": "wpot.signatures",
    "hks": "wpot.signatures.hks",
    "hks_times": "wpot.signatures.hks",
    "Signature": "wpot.signatures",
    "register_signature": "wpot.signatures",
    "signature_names": "wpot.signatures",
    "get_signature": "wpot.signatures",
    "cost_matrix": "wpot.cost",
    # evaluation and datasets
    "one_shot_1nn": "wpot.evaluate",
    "leave_one_out_1nn": "wpot.evaluate",
    "leave_one_out_levels": "wpot.evaluate",
    "symmetric_flip": "wpot.evaluate",
    "SymmetricFlip": "wpot.evaluate",
    "part_retrieval": "wpot.evaluate",
    "correspondence_error": "wpot.evaluate",
    "summarize_correspondence": "wpot.evaluate",
    "GeodesicDistances": "wpot.evaluate",
    # a part located in a whole by geodesic consistency
    "locate_part": "wpot.maps.locate",
    "LocateOptions": "wpot.maps.locate",
    "PartMap": "wpot.maps.locate",
    "LocateWarning": "wpot.maps.locate",
    # a part's class looked up in a labelled library of whole shapes
    "rank_classes": "wpot.maps.retrieval",
    "RetrievalOptions": "wpot.maps.retrieval",
    "ClassRanking": "wpot.maps.retrieval",
    "RetrievalCalibration": "wpot.maps.retrieval",
    "cumulative_curve": "wpot.evaluate",
    "curve_auc": "wpot.evaluate",
    "list_shapes": "wpot.datasets",
    "class_label": "wpot.datasets",
    "read_label_csv": "wpot.datasets",
    "read_test_pairs": "wpot.datasets",
    "tosca_ground_truth": "wpot.datasets",
    "build_head_dataset": "wpot.paper.head",
    "load_head_dataset": "wpot.paper.head",
    "head_ground_truth": "wpot.paper.head",
    # optimal transport (also reachable as wpot.ot.*)
    "solve_balanced": "wpot.ot",
    "solve_partial": "wpot.ot",
    "OTResult": "wpot.ot",
    "BetaStep": "wpot.ot",
    "debiased": "wpot.ot",
    "FeatureCost": "wpot.ot",
    "SolverOptions": "wpot.ot",
    "TransportProblem": "wpot.ot",
    "make_solver": "wpot.ot",
    # comparison
    "compare": "wpot.comparison",
    "Comparison": "wpot.comparison",
    "Comparer": "wpot.comparison",
    "ComparisonConfig": "wpot.config",
    "Registration": "wpot.maps.registration",
    "fit_similarity": "wpot.maps.registration",
    "Subsample": "wpot.sampling",
    "Points": "wpot.sampling",
    "SamplerOptions": "wpot.sampling",
    "FarthestPointSampler": "wpot.sampling",
    "farthest_point_sampling": "wpot.sampling",
    "ProblemTooLargeError": "wpot.comparison",
    "solver_mass_penalty": "wpot.comparison",
    "cost_scale": "wpot.comparison",
    "DEFAULT_MASS_PENALTY": "wpot.comparison",
    "PENALTY_SCALES": "wpot.comparison",
    # refining a correspondence
    "zoomout": "wpot.maps.zoomout",
    "orientation_score": "wpot.maps.orientation",
    "reflection_symmetry": "wpot.maps.symmetry",
    # dataset runs
    "run_all_vs_all": "wpot.runs.loop",
    "RunStore": "wpot.runs.store",
    "RunMismatchError": "wpot.runs.store",
    "DaskExecutor": "wpot.runs.workers",
    "dask_executor": "wpot.runs.workers",
    "choose_worker_device": "wpot.runs.workers",
    "classify_run": "wpot.runs.report",
    "build_report": "wpot.runs.report",
}
#: submodules reachable as attributes (``wpot.ot``, ``wpot.maps.locate`` after ``wpot.maps``), name -> module
_SUBMODULES: dict[str, str] = {name: f"wpot.{name}" for name in (
    "ot", "mesh", "io", "spectral", "signatures", "cost", "comparison", "config", "sampling", "maps", "runs",
    "paper", "evaluate", "datasets", "examples", "plot", "progress", "cli")}
# modules that moved into the maps and runs packages keep their old attribute names
_SUBMODULES.update({"registration": "wpot.maps.registration", "retrieval": "wpot.maps.retrieval",
                    "refine": "wpot.maps.zoomout", "history": "wpot.runs.history", "report": "wpot.runs.report"})

__all__ = sorted(_EXPORTS) + ["ot", "__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        module = importlib.import_module(_SUBMODULES[name])
        globals()[name] = module
        return module
    raise AttributeError(f"module 'wpot' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
