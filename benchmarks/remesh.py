"""Meshes re-meshed for the benchmarks: the same surface with another triangulation and density."""
from __future__ import annotations

import warnings

import numpy as np


def resized(mesh, n_vertices: int):
    """``mesh`` subdivided (each triangle into 4) at least once and until it has at least ``n_vertices`` vertices,
    then decimated to about ``n_vertices`` (quadric error, fast-simplification): another triangulation at any
    ratio, 1 included (every edge of ``mesh`` is split before the decimation)."""
    import fast_simplification
    import trimesh

    from wpot.mesh import Mesh, MeshWarning

    v, f = trimesh.remesh.subdivide(mesh.vertices, mesh.faces)
    while len(v) < n_vertices:
        v, f = trimesh.remesh.subdivide(v, f)
    if len(v) > 1.05 * n_vertices:
        v, f = fast_simplification.simplify(np.array(v, np.float32, order="C"), np.array(f, np.int32, order="C"),
                                            target_reduction=1.0 - n_vertices / len(v))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)  # pieces the decimation split off: the largest is kept
        return Mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)).cleaned(
            keep_largest_component=True)[0]
