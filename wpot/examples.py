"""Generated example shapes with known ground truth, for the demo, the notebooks and the tests.

No data files are needed. Every shape is the same smooth, non-symmetric closed surface, a "blob with
limbs": the unit sphere pushed out radially by a few Gaussian bumps of different sizes, then stretched
along the axes,

    S(u) = A · u · (1 + Σ_k a_k exp((u·c_k − 1) / w_k²)),   u ∈ S²,   A = diag(1.3, 1.0, 0.8).

A triangulation of S comes from points ``u_i`` on the sphere (a Fibonacci lattice, optionally rotated
and jittered), meshed by their convex hull (the spherical Delaunay triangulation) and mapped by S.
Because S is a radial graph followed by a linear map, the mesh is a closed, embedded, outward-oriented
genus-0 surface. Two different point sets give two *different triangulations of the same surface*,
and the sphere parameters ``u`` give the ground truth between them.

Everything is deterministic for a given ``n`` and ``seed``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.transform import Rotation

from wpot.mesh import Mesh, cut

__all__ = ["ExamplePair", "ExamplePartial", "example_mesh", "example_pair", "example_partial"]

# limbs: (direction, amplitude a_k, width w_k); irregular on purpose (no mirror or rotational symmetry)
_BUMPS = (
    ((0.9, 0.3, 0.2), 0.85, 0.32),
    ((-0.5, 0.8, 0.1), 0.55, 0.28),
    ((-0.3, -0.6, 0.7), 0.40, 0.38),
    ((0.1, -0.2, -1.0), 0.30, 0.45),
)
_STRETCH = np.array([1.3, 1.0, 0.8])


def _shape(u: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors -> (n, 3) points on the example surface S."""
    r = np.ones(len(u))
    for c, a, w in _BUMPS:
        c = np.asarray(c) / np.linalg.norm(c)
        r += a * np.exp((u @ c - 1.0) / w**2)
    return u * r[:, None] * _STRETCH


def _fibonacci(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def _sphere_points(n: int, rng: np.random.Generator | None, jitter: float) -> np.ndarray:
    u = _fibonacci(n)
    if rng is not None:
        u = u @ Rotation.random(random_state=rng).as_matrix().T
        if jitter > 0:
            spacing = np.sqrt(4.0 * np.pi / n)
            u = u + jitter * spacing * rng.standard_normal(u.shape)
            u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u


def _sphere_triangulation(u: np.ndarray) -> np.ndarray:
    """(F, 3) outward-oriented triangles of the convex hull of points on the unit sphere."""
    hull = ConvexHull(u)
    if len(hull.vertices) != len(u):  # pragma: no cover - only for pathological (coincident) points
        raise ValueError(f"{len(u) - len(hull.vertices)} sphere points are not hull vertices; change seed")
    f = hull.simplices.astype(np.int64)
    nrm = np.cross(u[f[:, 1]] - u[f[:, 0]], u[f[:, 2]] - u[f[:, 0]])
    flip = np.einsum("ij,ij->i", nrm, u[f].sum(axis=1)) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return f


def _check_n(n: int) -> int:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 50:
        raise ValueError(f"n must be an integer >= 50, got {n!r}")
    return int(n)


def _mesh_on_sphere(u: np.ndarray) -> Mesh:
    return Mesh(_shape(u), _sphere_triangulation(u))


def example_mesh(n: int = 1000, *, seed: int | None = None, jitter: float = 0.3) -> Mesh:
    """The example surface triangulated with ``n`` vertices.

    ``seed=None``: the plain Fibonacci lattice; an integer: a randomly rotated lattice whose points
    are jittered by ``jitter`` times the mean spacing (a different triangulation of the same surface).
    """
    n = _check_n(n)
    rng = None if seed is None else np.random.default_rng(seed)
    return _mesh_on_sphere(_sphere_points(n, rng, jitter))


@dataclass(frozen=True, eq=False)
class ExamplePair:
    """Two triangulations of the same surface, the second rigidly moved.

    Attributes
    ----------
    source : Mesh, ``n`` vertices (Fibonacci lattice)
    target : Mesh, about ``1.15 n`` vertices (rotated, jittered lattice), then moved:
        ``target.vertices = S(u') @ rotation.T + translation``
    rotation : (3, 3) float64, proper rotation
    translation : (3,) float64
    correspondence : (N_target,) int64, the ground truth: the source vertex nearest (in the source
        frame) to the point of the surface that each target vertex samples
    target_in_source_frame : (N_target, 3) float64, target vertices with the rigid motion undone
    """

    source: Mesh
    target: Mesh
    rotation: np.ndarray
    translation: np.ndarray
    correspondence: np.ndarray
    target_in_source_frame: np.ndarray


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a)
    a.setflags(write=False)
    return a


def example_pair(n: int = 1000, *, seed: int = 0, n_target: int | None = None, jitter: float = 0.3) -> ExamplePair:
    """Two meshes of the same smooth non-symmetric shape with different triangulations.

    Parameters
    ----------
    n : vertices of the source (>= 50); about 500-2,000 keeps tests fast
    seed : drives the target's lattice rotation and jitter and the rigid motion
    n_target : vertices of the target (default ``round(1.15 n)``, so the vertex counts differ too)
    jitter : target point jitter, in units of the mean point spacing

    Returns
    -------
    ExamplePair, with the ground-truth correspondence target -> source.
    """
    n = _check_n(n)
    n_t = _check_n(int(round(1.15 * n)) if n_target is None else n_target)
    rng = np.random.default_rng(seed)
    source = _mesh_on_sphere(_sphere_points(n, None, 0.0))
    u_t = _sphere_points(n_t, rng, jitter)
    pts = _shape(u_t)
    rotation = Rotation.random(random_state=rng).as_matrix()
    translation = rng.normal(scale=0.5, size=3)
    target = Mesh(pts @ rotation.T + translation, _sphere_triangulation(u_t))
    _, corr = cKDTree(source.vertices).query(pts)
    return ExamplePair(
        source=source,
        target=target,
        rotation=_frozen(rotation),
        translation=_frozen(translation),
        correspondence=_frozen(corr.astype(np.int64)),
        target_in_source_frame=_frozen(pts),
    )


@dataclass(frozen=True, eq=False)
class ExamplePartial:
    """A part of one triangulation of the example surface, and the whole surface differently meshed.

    Attributes
    ----------
    full : Mesh, the complete shape (the pair's source)
    part : Mesh, a cap of the pair's target, cut with `wpot.cut` (rigidly moved like the target)
    target : Mesh, the complete target that ``part`` was cut from
    index_map : (N_part,) int64, ``index_map[i]`` is the target vertex that part vertex ``i`` came from
    correspondence : (N_part,) int64, ground truth part -> full (source) vertex
    rotation, translation : the rigid motion applied to the target (and so to the part)
    """

    full: Mesh
    part: Mesh
    target: Mesh
    index_map: np.ndarray
    correspondence: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


def example_partial(
    n: int = 1000,
    *,
    seed: int = 0,
    fraction: float = 0.5,
    direction: tuple[float, float, float] = (1.0, 0.2, 0.1),
) -> ExamplePartial:
    """A partial shape: the cap of the pair's target facing ``direction`` (in sphere parameters).

    Parameters
    ----------
    n, seed : as in `example_pair`
    fraction : share of the target's vertices kept, in (0, 1]
    direction : (3,) the cap's centre direction; the cap is one connected disc

    Returns
    -------
    ExamplePartial, with ``part`` = ``wpot.cut(target, mask)`` and its index map.
    """
    if not (0.0 < fraction <= 1.0):
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or not np.linalg.norm(d) > 0:
        raise ValueError(f"direction must be a nonzero finite 3-vector, got {direction!r}")
    pair = example_pair(n, seed=seed)
    # sphere parameter of each target vertex, recovered from the shape coordinates: S(u) is a
    # positive multiple of A u, so u is the normalised A^{-1} S(u)
    u = pair.target_in_source_frame / _STRETCH
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    proj = u @ (d / np.linalg.norm(d))
    mask = proj >= np.quantile(proj, 1.0 - fraction)
    part, index_map = cut(pair.target, mask)
    return ExamplePartial(
        full=pair.source,
        part=part,
        target=pair.target,
        index_map=_frozen(index_map),
        correspondence=_frozen(pair.correspondence[index_map]),
        rotation=pair.rotation,
        translation=pair.translation,
    )
