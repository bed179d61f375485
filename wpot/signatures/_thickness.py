"""Local thickness of a solid shape at each vertex: the shape diameter function (Shapira, Shamir & Cohen-Or 2008).

Why LD-SIFT needs it: LD-SIFT is scale-free by construction (the image of a vertex covers ``2 K D(v)``, a
multiple of the local edge length, and SIFT normalises its descriptor), so two shapes made from one template
at two sizes get the same signatures. TOSCA's David and Michael are such a pair (Michael is the larger),
and they are most of LD-SIFT's classification errors on TOSCA (paper Table 1). A vertex's
thickness is in absolute units (it scales with the shape), it hardly moves with the pose (a limb keeps its
girth when it bends), and it is local, so a part cut from a shape keeps it away from the cut. `LDSIFT`
appends ``log`` thickness as one more signature column when ``thickness`` (``ldsift_thickness``) is set.

Definition: from vertex v, `N_RAYS` rays are cast into the solid within a cone of half-angle `CONE_ANGLE`
degrees about the inward normal (`render.raycast.DepthRenderer.inward_hits`, one Warp launch), laid out in the
vertex's frame (the vertex normal, and the LD-SIFT frame's e1 made tangent, `local_frames`) and symmetric under
that frame's sign ambiguity, so that the rays and their median do not depend on how the shape is posed in space.
A ray counts when it leaves the solid through a face seen from inside; the thickness is the median length of
those rays.

A part cut from a whole (a surface with holes) is closed for the rays by the caps over its holes
(`wpot.mesh.boundary_caps`). A ray that leaves through a cap would, in the whole, have gone on: it is only
known to be at least that long. Dropping such rays, or reading them at the cap, keeps the short rays and
loses the long ones, and reads a part thinner than its whole. So a vertex keeps its own value only when its
median does not depend on how far its escaped rays would have run: when the median is the same with them at
their lower bound and at infinity. Otherwise the two medians still bound its value.
A vertex with no value of its own (fewer than `MIN_RAYS` rays that count, as on a thin fin or where the surface
crosses itself, or a median its escaped rays could move) takes the mean of its neighbours' values, spread along
the edges from the vertices that have one (kept within its own bounds). When no vertex has a value of its own
(every vertex sees an opening, as on half a shape), the medians with the escaped rays at their bound are used:
lower bounds, and the warning says the column is not to be trusted there.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from wpot.mesh import Mesh, boundary_caps, winding
from wpot.signatures._frames import local_frames

__all__ = ["thickness", "thickness_field", "ThicknessField", "N_RAYS", "CONE_ANGLE", "MIN_RAYS", "VERSION"]

#: bumped whenever `thickness` changes its values; part of LD-SIFT's cache key when its thickness column is on
VERSION = 2
#: rays per vertex, and the half-angle of their cone in degrees about the inward normal (Shapira et al.: 30
#: rays in a 120 degree cone); a multiple of 4 (`render.raycast.inward_cone`)
N_RAYS = 32
CONE_ANGLE = 60.0
#: a vertex's own value needs at least this many rays that cross the solid
MIN_RAYS = 3
#: warn when fewer than this share of the vertices have a value of their own
MIN_MEASURED = 0.5


def _spread(values: np.ndarray, known: np.ndarray, mesh: Mesh) -> np.ndarray:
    """Fill the unknown entries of ``values`` (N,) ring by ring with the mean of their known neighbours."""
    a = (mesh.adjacency != 0).astype(np.float64).tocsr()
    out = np.where(known, values, 0.0)
    known = known.copy()
    while not known.all():
        num = a @ np.where(known, out, 0.0)
        den = a @ known.astype(np.float64)
        new = ~known & (den > 0)
        if not new.any():  # a component without a measured vertex
            out[~known] = np.median(out[known])
            break
        out[new] = num[new] / den[new]
        known |= new
    return out


def _ray_frames(outward: np.ndarray, e1: np.ndarray) -> np.ndarray:
    """(N, 3, 3) frames of the rays: rows ``e1`` made tangent to the outward normal, ``o x e1``, ``o``.

    The axis is the vertex normal, not the LD-SIFT frame's PCA normal: that one is fitted over a ball of radius
    S(v), which on a finger or an ear thinner than S(v) takes in both sides and tilts along the part (the
    vertex normal classifies TOSCA8 and TOSCA 5k better; the docs' Results page).
    """
    t = e1 - np.einsum("ij,ij->i", e1, outward)[:, None] * outward
    norm = np.linalg.norm(t, axis=1)
    flat = norm < 1e-6  # e1 along the normal (a degenerate frame): any tangent will do
    if flat.any():
        helper = np.where(np.abs(outward[flat, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t[flat] = np.cross(outward[flat], helper)
        norm[flat] = np.linalg.norm(t[flat], axis=1)
    t /= norm[:, None]
    return np.stack([t, np.cross(outward, t), outward], axis=1)


@dataclass(frozen=True)
class ThicknessField:
    """`thickness_field`'s result, for N vertices.

    values : (N,) float64, the thickness (`thickness`), in the mesh's units.
    own : (N,) bool, True where the value is the vertex's own median: enough rays cross the solid and none of the
        rays that leave through an opening could move it. False where it was filled in from the neighbours.
    low, high : (N,) float64, the vertex's median with its escaped rays at their bound and with them endless:
        what its own rays allow (equal where ``own``; NaN without a ray that counts; ``high`` may be inf).
    """

    values: np.ndarray
    own: np.ndarray
    low: np.ndarray
    high: np.ndarray


def thickness(
    mesh: Mesh, *, n_rays: int = N_RAYS, cone_angle: float = CONE_ANGLE, frames: Any = None, device: str | None = None
) -> np.ndarray:
    """The local thickness (shape diameter function) at every vertex: (N,) float64, in the mesh's units.
    `thickness_field` (same arguments) also says which vertices have a value of their own.

    Parameters
    ----------
    mesh : `wpot.Mesh`; it must enclose a volume (a closed surface, or an open one whose holes are small:
        a cut part, a scan), with consistently wound faces; either winding is read (`wpot.mesh.winding`).
    n_rays, cone_angle : rays per vertex and their cone's half-angle in degrees (`N_RAYS`, `CONE_ANGLE`).
    frames : the mesh's `wpot.signatures.LocalFrames` when already computed (default: `local_frames` at K = 3).
    device : Warp device for the ray casting; None is Warp's default device.

    Scales with the mesh (``thickness(s M) = s thickness(M)``) and does not change under rigid motions.
    See the module docstring for the definition and for the vertices whose value is filled in.
    """
    return _field(mesh, n_rays, cone_angle, frames, device).values


def thickness_field(
    mesh: Mesh, *, n_rays: int = N_RAYS, cone_angle: float = CONE_ANGLE, frames: Any = None, device: str | None = None
) -> ThicknessField:
    """`thickness`, with which vertices have a value of their own and the bounds their rays give
    (`ThicknessField`). On a part cut from a whole, the ``own`` vertices are those whose thickness the part
    shows; the others' is the whole's, which the part does not hold."""
    return _field(mesh, n_rays, cone_angle, frames, device)


def _field(mesh: Mesh, n_rays: int, cone_angle: float, frames: Any, device: str | None) -> ThicknessField:
    """`thickness_field`, called from it or from `thickness` (its warning names their caller's line)."""
    from render.raycast import DepthRenderer, inward_cone

    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a wpot.Mesh, got {type(mesh).__name__}")
    facing = winding(mesh)
    if facing == 0:
        raise ValueError(
            "the mesh encloses no volume (a flat or nearly flat patch), so it has no thickness; LD-SIFT's "
            "thickness column needs solid shapes: leave ldsift_thickness at 0 for this data"
        )
    fr = _ray_frames(mesh.vertex_normals * facing, (local_frames(mesh) if frames is None else frames).frames[:, 0])
    centres, caps = boundary_caps(mesh)
    closed = (np.concatenate([mesh.vertices, centres]), np.concatenate([mesh.faces, caps]))
    hits = DepthRenderer(closed, device=device).inward_hits(
        mesh.vertices, fr, inward_cone(n_rays, cone_angle), facing=facing, first_opening=mesh.n_faces
    )
    med, med_high, counted = _median_bounds(hits)
    censored = (counted > 0) & (med_high != med)
    measured = counted >= min(MIN_RAYS, n_rays)
    known = measured & ~censored
    if not measured.any():
        raise ValueError(
            "no ray cast into the mesh leaves it through a face seen from inside, so its thickness cannot be "
            "measured (is the surface open or inconsistently wound?); leave ldsift_thickness at 0"
        )
    if known.mean() < MIN_MEASURED:
        why = (f"rays from {censored.mean():.0%} of them leave through the mesh's {len(centres)} open boundary "
               f"loop{'s' if len(centres) != 1 else ''} (a part cut from a whole: its thickness there is the "
               "whole's, which the part does not show)" if censored.sum() >= (~known & ~censored).sum()
               else "a very open surface, or inconsistently wound faces?")
        warnings.warn(
            f"the thickness of LD-SIFT's thickness column (ldsift_thickness) was measured at only {known.mean():.0%} "
            f"of the mesh's vertices and filled in from their neighbours at the rest: {why}. Lower ldsift_thickness, "
            "or set it to 0, for such meshes (wpot.signatures.thickness_field says which vertices were measured)",
            stacklevel=3,
        )
    if not known.any():  # every vertex sees an opening (half a shape): its lower bounds are all there is
        values = _spread(med, measured, mesh)
    else:
        filled = _spread(med, known, mesh)
        # a vertex whose escaped rays could move its median still bounds it: its rays read at the caps from
        # below, and with the escaped ones taken as endless from above; its filled-in value stays between the two
        values = np.where(censored, np.clip(filled, med, med_high), filled)
    return ThicknessField(values, known, med, med_high)


def _median_bounds(hits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bounds on each row's median ray length, from `render.raycast.DepthRenderer.inward_hits`' (N, m) distances
    (NaN: the ray does not count; negative: it left through an opening and runs at least that far).

    Returns the (N,) medians with the escaped rays at their bound and (N,) with them endless (equal where the
    escaped rays cannot move the median; both NaN for a row without a ray that counts), and the (N,) counts of
    rays that count.
    """
    low = np.abs(hits)
    high = np.where(hits < 0, np.inf, hits)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows; inf - inf in a median of two infinities
        med_low, med_high = np.nanmedian(low, axis=1), np.nanmedian(high, axis=1)
    return med_low, med_high, np.isfinite(low).sum(axis=1)
