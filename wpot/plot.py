"""Figures of the paper's experiments (matplotlib, no pyplot state: safe under the Agg backend).

Every function returns a `matplotlib.figure.Figure` (shown inline by Jupyter) and, given ``path``, also writes
it as a PNG. Meshes are drawn by a small painter's-algorithm renderer (`draw_mesh`): triangles projected on a
view plane, sorted back to front and shaded by their normal, which is faster and more reliable in depth order
than mplot3d's ``plot_trisurf`` for meshes of thousands of faces. The view convention is z-up (TOSCA):
``azim`` turns the camera about z (0 looks along -x), ``elev`` raises it.

* `plot_distance_matrix`: a distance matrix ordered by class with class separators (paper Fig. 3, 7);
* `plot_confusion`: which classes one-shot 1-NN takes for which (from `wpot.evaluate.one_shot_1nn`);
* `plot_cumulative_errors`: cumulative geodesic-error curves of several methods (Fig. 6);
* `plot_vertex_scalar`: a shape coloured by a per-vertex value such as the matched mass;
* `plot_registration`: a part drawn on its full shape after a similarity transform (Fig. 1);
* `plot_correspondence`: a map between two shapes, shown by colours carried through it (overlaid or side by side).
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from numpy.typing import ArrayLike

from wpot.evaluate import format_percent
from wpot.mesh import Mesh

__all__ = [
    "class_order",
    "draw_mesh",
    "plot_distance_matrix",
    "plot_confusion",
    "plot_cumulative_errors",
    "plot_vertex_scalar",
    "plot_registration",
    "plot_correspondence",
]


class _Figure(Figure):
    """A pyplot-free Figure that Jupyter shows inline (``_repr_png_``) without ``%matplotlib inline``."""

    def _repr_png_(self) -> bytes:
        buf = io.BytesIO()
        self.savefig(buf, format="png", dpi=100)
        return buf.getvalue()


def _new_figure(figsize: tuple[float, float]) -> Figure:
    fig = _Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _figure_and_axes(ax: Axes | None, figsize: tuple[float, float]) -> tuple[Figure, Axes]:
    """The given axes and their figure, or a new figure of ``figsize`` with one axes."""
    if ax is not None:
        return ax.figure, ax
    fig = _new_figure(figsize)
    return fig, fig.add_subplot()


def _finish(fig: Figure, path: str | Path | None, dpi: int) -> Figure:
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=dpi, format="png")
    return fig


# ----------------------------------------------------------------------------- distance matrices
def class_order(labels: ArrayLike, *, classes: Sequence[str] | None = None) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Order shapes so that each class forms one block.

    Parameters
    ----------
    labels : (n,) class labels.
    classes : order of the blocks (default: order of first appearance); must list every label.

    Returns
    -------
    order : (n,) int64 permutation; shapes of a class keep their relative order (stable).
    block_classes : the class of each block, in order.
    starts : (n_blocks + 1,) int64 block boundaries in the ordered list (block k is ``starts[k]:starts[k+1]``).
    """
    lab = np.asarray(labels).astype(str)
    if lab.ndim != 1 or lab.size == 0:
        raise ValueError(f"labels must be a non-empty 1-d array, got shape {lab.shape}")
    if classes is None:
        _, first = np.unique(lab, return_index=True)
        classes = [str(lab[i]) for i in np.sort(first)]
    else:
        classes = [str(c) for c in classes]
        missing = sorted(set(lab.tolist()) - set(classes))
        if missing:
            raise ValueError(f"classes does not list the labels {missing}")
        if len(set(classes)) != len(classes):
            raise ValueError(f"classes repeats a class: {classes}")
    rank = {c: k for k, c in enumerate(classes)}
    key = np.array([rank[x] for x in lab])
    order = np.argsort(key, kind="stable")
    present = [c for c in classes if c in set(lab.tolist())]
    counts = np.array([int((lab == c).sum()) for c in present])
    return order.astype(np.int64), present, np.r_[0, np.cumsum(counts)].astype(np.int64)


def _off_diagonal_range(d: np.ndarray) -> tuple[float | None, float | None]:
    """The smallest and largest finite off-diagonal entries of a square matrix (None, None when there is none)."""
    off = d[~np.eye(len(d), dtype=bool)]
    off = off[np.isfinite(off)]
    if not off.size:
        return None, None
    return float(off.min()), float(off.max())


def _group_axis(ax: Axes, which: str, starts: np.ndarray, block: Sequence[str], fontsize: float) -> Axes:
    """A secondary axis (``which``: "top" or "right") naming the class of each block of rows or columns, with
    long ticks at the block boundaries as brackets."""
    sec = ax.secondary_xaxis("top") if which == "top" else ax.secondary_yaxis("right")
    axis = sec.xaxis if which == "top" else sec.yaxis
    edges = starts - 0.5
    axis.set_ticks(edges, [""] * len(edges))
    axis.set_ticks((starts[:-1] + starts[1:] - 1) / 2.0, list(block), minor=True)
    axis.set_tick_params(which="major", length=14, width=0.8)
    axis.set_tick_params(which="minor", length=0, labelsize=fontsize)
    if which == "top":
        for t in axis.get_minorticklabels():
            t.set(rotation=45, horizontalalignment="left", verticalalignment="bottom", rotation_mode="anchor")
    return sec


def plot_distance_matrix(
    distances: ArrayLike,
    labels: ArrayLike,
    *,
    names: Sequence[str] | None = None,
    classes: Sequence[str] | None = None,
    title: str | None = None,
    cmap: str = "viridis",
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """Heatmap of an (n, n) distance matrix ordered by class, with lines between classes (paper Fig. 3, 7).

    Small distances are dark blue and large ones yellow (viridis, as in the paper). The colour range spans the
    off-diagonal distances (the smallest to the largest between two different shapes): the diagonal (usually
    0, or the self-comparison value) would otherwise set one end of it and flatten every other cell; it is drawn
    in the colour of the nearest end of the range.

    ``names`` ((n,) strings, e.g. the run's shape names) labels each row and column with its shape; the classes
    then name the blocks on the opposite sides (top and right), between brackets at their boundaries. Without
    ``names`` the blocks' classes label the axes. ``classes`` orders the blocks (`class_order`).
    """
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] != d.shape[1]:
        raise ValueError(f"distances must be a square (n, n) matrix, got shape {d.shape}")
    n = d.shape[0]
    if np.asarray(labels).shape != (n,):
        raise ValueError(f"labels must have shape ({n},), got {np.asarray(labels).shape}")
    if names is not None and len(names) != n:
        raise ValueError(f"names must give one name per shape ({n}), got {len(names)}")
    order, block, starts = class_order(labels, classes=classes)
    fig, ax = _figure_and_axes(ax, (6.4, 5.6) if names is None else (7.2, 6.4))
    vmin, vmax = _off_diagonal_range(d)
    im = ax.imshow(np.ma.masked_invalid(d[np.ix_(order, order)]), cmap=cmap, interpolation="nearest",
                   vmin=vmin, vmax=vmax)
    for s in starts[1:-1]:
        ax.axhline(s - 0.5, color="w", lw=1.0)
        ax.axvline(s - 0.5, color="w", lw=1.0)
    if names is None:
        centres = (starts[:-1] + starts[1:] - 1) / 2.0
        ax.set_xticks(centres, block, rotation=60, ha="right", fontsize=8)
        ax.set_yticks(centres, block, fontsize=8)
    else:
        size = float(np.clip(300.0 / n, 3.0, 8.0))
        shown = [str(names[k]) for k in order]
        ax.set_xticks(range(n), shown, rotation=90, fontsize=size)
        ax.set_yticks(range(n), shown, fontsize=size)
        _group_axis(ax, "top", starts, block, 8)
        _group_axis(ax, "right", starts, block, 8)
    fig.colorbar(im, ax=ax, shrink=0.8, label="distance (off-diagonal range)", pad=0.08 if names is not None else 0.05)
    if title:
        ax.set_title(title)
    return _finish(fig, path, dpi)


#: how `plot_confusion` marks the row of a class it cannot score: one shape, never a test shape
ONE_MEMBER = "n/a: 1 member"


def plot_confusion(
    result: Any,
    *,
    classes: Sequence[str] | None = None,
    title: str | None = None,
    cmap: str = "Blues",
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """Heatmap of a one-shot 1-NN confusion matrix, each cell labelled with its percentage.

    ``result`` is a `wpot.evaluate.OneShotClassification` (anything with ``classes`` and a (C, C)
    ``confusion``): row = true class, column = the class its test shapes were given, each row summing to 100 %.
    ``classes`` orders the rows and columns (default: ``result.classes``); give `plot_distance_matrix`'s block
    order (`class_order`) to read the two figures side by side. Cells of 0 are left blank so that the
    confusions stand out; a class with a single shape is never tested (a NaN row) and its row says so
    (`ONE_MEMBER`). A long title is wrapped to the figure's width.
    """
    from textwrap import fill

    own = list(getattr(result, "classes", ()))
    conf = np.asarray(getattr(result, "confusion", None), dtype=np.float64)
    if not own or conf.shape != (len(own), len(own)):
        raise ValueError(
            f"result must have classes and a (C, C) confusion matrix (a wpot.evaluate.OneShotClassification), "
            f"got {type(result).__name__} with {len(own)} classes and confusion of shape {conf.shape}"
        )
    if classes is not None:
        classes = [str(x) for x in classes]
        if sorted(classes) != sorted(map(str, own)):
            raise ValueError(f"classes must list the result's classes {own} once each, in any order, got {classes}")
        pos = [list(map(str, own)).index(x) for x in classes]
        conf = conf[np.ix_(pos, pos)]
    else:
        classes = own
    c = len(classes)
    own_figure = ax is None
    fig, ax = _figure_and_axes(ax, (max(1.2 + 0.55 * c, 3.6), 1.0 + 0.5 * c))
    pct = 100 * conf
    ax.imshow(np.ma.masked_invalid(pct), cmap=cmap, vmin=0, vmax=100, interpolation="nearest")
    for a in range(c):
        if not np.isfinite(pct[a]).any():
            ax.text((c - 1) / 2.0, a, ONE_MEMBER, ha="center", va="center", fontsize=7, color="0.35", style="italic")
            continue
        for b in range(c):
            v = pct[a, b]
            if np.isfinite(v) and v > 0:
                text = format_percent(conf[a, b], decimals=0 if v >= 9.5 else 1)[:-1]
                ax.text(b, a, text, ha="center", va="center", fontsize=7, color="w" if v > 60 else "k")
    ax.set_xticks(range(c), classes, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(c), classes, fontsize=8)
    ax.set_xlabel("taken for")
    ax.set_ylabel("class")
    if title:
        # about 0.085 inch per character at 9 points: wrapped to the figure (or, in a given axes, its share of it)
        width = fig.get_figwidth() * (1.0 if own_figure else ax.get_position().width)
        ax.set_title(fill(title, max(16, int(width / 0.085))), fontsize=9)
    return _finish(fig, path, dpi)


# ----------------------------------------------------------------------------- error curves
def _curve_of(v: Any) -> tuple[np.ndarray, np.ndarray, float | None]:
    if hasattr(v, "thresholds") and hasattr(v, "curve"):
        return np.asarray(v.thresholds), np.asarray(v.curve), getattr(v, "auc", None)
    try:
        t, c = v
    except (TypeError, ValueError):
        raise ValueError(
            f"a curve must be a CorrespondenceError / CorrespondenceSummary or a (thresholds, curve) pair, got {type(v).__name__}"
        ) from None
    t, c = np.asarray(t, dtype=float), np.asarray(c, dtype=float)
    if t.shape != c.shape or t.ndim != 1:
        raise ValueError(f"thresholds and curve must be 1-d of equal length, got {t.shape} and {c.shape}")
    return t, c, None


def plot_cumulative_errors(
    curves: Mapping[str, Any],
    *,
    title: str | None = None,
    xlabel: str = "normalized geodesic error",
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """Cumulative geodesic-error curves of several methods (paper Fig. 6); the legend gives each AUC.

    ``curves`` maps a method name to a `wpot.evaluate.CorrespondenceError`, a
    `wpot.evaluate.CorrespondenceSummary`, or a ``(thresholds, curve)`` pair (fractions in [0, 1]).
    """
    if not curves:
        raise ValueError("curves is empty")
    fig, ax = _figure_and_axes(ax, (5.6, 4.2))
    tmax = 0.0
    for name, v in curves.items():
        t, c, auc = _curve_of(v)
        ax.plot(t, 100.0 * c, lw=2, label=f"{name} (AUC {auc:.3f})" if auc is not None else str(name))
        tmax = max(tmax, float(t.max()))
    ax.set_xlim(0, tmax)
    ax.set_ylim(0, 100)
    ax.grid(True, alpha=0.4)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("% correspondences")
    ax.legend(loc="lower right", fontsize=8)
    if title:
        ax.set_title(title)
    return _finish(fig, path, dpi)


# ----------------------------------------------------------------------------- mesh rendering
def _view_axes(elev: float, azim: float) -> np.ndarray:
    """(3, 3) rows: screen right, screen up, toward the camera (z-up world)."""
    e, a = np.deg2rad(elev), np.deg2rad(azim)
    toward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(toward, right)
    return np.stack([right, up, toward])


def draw_mesh(
    ax: Axes,
    meshes: Mesh | Sequence[Mesh],
    face_colors: ArrayLike | Sequence[ArrayLike],
    *,
    elev: float = 10.0,
    azim: float = 0.0,
    shade: float = 0.6,
    alpha: float = 1.0,
    depth_bias: Sequence[float] | None = None,
) -> None:
    """Draw one or several meshes on a 2-D axes (painter's algorithm, shared depth order).

    Parameters
    ----------
    ax : a plain (2-D) matplotlib axes; its frame is hidden and its aspect set equal.
    meshes : a mesh or a list of meshes drawn together (correct occlusion between them).
    face_colors : per mesh, (F, 3|4) RGB(A) in [0, 1], or one colour (3|4,) for the whole mesh.
    shade : strength of the Lambert shading (0: flat colours).
    depth_bias : per mesh, a distance added toward the camera when sorting, so that a mesh lying on another
        (a registered part on its full shape) is drawn over it instead of interleaving with it.
    """
    if isinstance(meshes, Mesh):
        meshes, face_colors = [meshes], [face_colors]
    if len(face_colors) != len(meshes):
        raise ValueError(f"need one colour array per mesh: {len(meshes)} meshes, {len(face_colors)} colour arrays")
    if not 0.0 <= shade <= 1.0:
        raise ValueError(f"shade must lie in [0, 1], got {shade}")
    view = _view_axes(elev, azim)
    if depth_bias is None:
        depth_bias = [0.0] * len(meshes)
    if len(depth_bias) != len(meshes):
        raise ValueError(f"need one depth bias per mesh: {len(meshes)} meshes, {len(depth_bias)} biases")
    polys, depth, cols = [], [], []
    for m, fc, bias in zip(meshes, face_colors, depth_bias):
        fc = np.asarray(fc, dtype=float)
        if fc.ndim == 1:
            fc = np.broadcast_to(fc, (m.n_faces, fc.size))
        if fc.shape[0] != m.n_faces or fc.shape[1] not in (3, 4):
            raise ValueError(f"face colours must have shape ({m.n_faces}, 3|4), got {fc.shape}")
        if fc.shape[1] == 3:
            fc = np.c_[fc, np.full(m.n_faces, alpha)]
        p = m.vertices @ view.T
        tri = p[m.faces]
        polys.append(tri[:, :, :2])
        depth.append(tri[:, :, 2].mean(1) + bias)
        lam = np.abs(m.face_normals @ view[2])
        c = fc.copy()
        c[:, :3] *= (1.0 - shade) + shade * lam[:, None]
        cols.append(c)
    polys, depth, cols = np.concatenate(polys), np.concatenate(depth), np.concatenate(cols)
    order = np.argsort(depth)  # far first
    ax.add_collection(PolyCollection(polys[order], facecolors=cols[order], edgecolors="none", antialiased=False))
    xy = polys.reshape(-1, 2)
    lo, hi = xy.min(0), xy.max(0)
    pad = 0.03 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_axis_off()


def _vertex_to_face(mesh: Mesh, values: np.ndarray) -> np.ndarray:
    return values[mesh.faces].mean(axis=1)


def plot_vertex_scalar(
    mesh: Mesh,
    values: ArrayLike,
    *,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    label: str | None = None,
    title: str | None = None,
    elev: float = 10.0,
    azim: float = 0.0,
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """A shape coloured by a per-vertex scalar ((N,) float, e.g. the matched mass of each vertex)."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (mesh.n_vertices,):
        raise ValueError(f"values must have shape ({mesh.n_vertices},) (one per vertex), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"values has {int((~np.isfinite(v)).sum())} NaN or infinite entries")
    fig, ax = _figure_and_axes(ax, (5.6, 4.2))
    norm = Normalize(v.min() if vmin is None else vmin, v.max() if vmax is None else vmax)
    cm = colormaps[cmap]
    draw_mesh(ax, mesh, cm(norm(_vertex_to_face(mesh, v))), elev=elev, azim=azim, shade=0.35)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cm), ax=ax, shrink=0.7, label=label)
    if title:
        ax.set_title(title)
    return _finish(fig, path, dpi)


def _transform_of(registration: Any, scale: float | None, rotation: ArrayLike | None, translation: ArrayLike | None):
    if registration is not None:
        if scale is not None or rotation is not None or translation is not None:
            raise ValueError("give either registration or scale/rotation/translation, not both")
        try:
            scale, rotation, translation = registration.scale, registration.rotation, registration.translation
        except AttributeError:
            raise ValueError(
                f"registration must have .scale, .rotation and .translation, got {type(registration).__name__}"
            ) from None
    return 1.0 if scale is None else float(scale), rotation, translation


def plot_registration(
    part: Mesh,
    full: Mesh,
    registration: Any = None,
    *,
    scale: float | None = None,
    rotation: ArrayLike | None = None,
    translation: ArrayLike | None = None,
    title: str | None = None,
    part_color: str | tuple = "tab:orange",
    full_color: str | tuple = "0.75",
    elev: float = 10.0,
    azim: float = 0.0,
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """A part (e.g. a cat's head, orange) registered onto its full shape (grey) (paper Fig. 1).

    The part is moved by the similarity ``x -> scale * rotation @ x + translation``, given by ``registration``
    (any object with ``.scale``, ``.rotation`` (3, 3) and ``.translation`` (3,), such as the registration of a
    `wpot.comparison` result) or by the keywords; with neither, the part is drawn where it is. The part is
    always drawn over the full shape, also where the transform puts it inside or behind it.
    """
    from matplotlib.colors import to_rgba

    s, r, t = _transform_of(registration, scale, rotation, translation)
    moved = part.transformed(rotation=r, translation=t, scale=s)
    fig, ax = _figure_and_axes(ax, (5.6, 4.2))
    # drawn over the full shape wherever it lands, also inside or behind it (a shrunk or misplaced part would
    # otherwise be hidden, and a poor registration would look like no part at all)
    span = np.ptp(np.concatenate([full.vertices, moved.vertices]), axis=0)
    bias = 10.0 * float(np.linalg.norm(span))
    draw_mesh(ax, [full, moved], [to_rgba(full_color), to_rgba(part_color)], elev=elev, azim=azim,
              depth_bias=[0.0, bias])
    if title:
        ax.set_title(title)
    return _finish(fig, path, dpi)


def _smooth_colours(mesh: Mesh) -> np.ndarray:
    """(N, 3) RGB in [0, 1]: each coordinate rescaled to [0.1, 0.9] (a smooth function on the shape)."""
    v = mesh.vertices
    lo, hi = v.min(0), v.max(0)
    return 0.1 + 0.8 * (v - lo) / np.where(hi > lo, hi - lo, 1.0)


def _footprint(mesh: Mesh, elev: float, azim: float, lo: np.ndarray, hi: np.ndarray,
               pixels: int = 700) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The area the mesh covers seen from (elev, azim), rasterized on the view-plane rectangle [lo, hi]:
    an (H, W) float mask in [0, 1] (row 0 at ``lo[1]``), slightly smoothed so that its 0.5 contour is the
    mesh's outline, and the ``(x0, x1, y0, y1)`` extent of its pixel centres for ``imshow``/``contour``."""
    import cv2

    step = float((hi - lo).max()) / pixels
    w, h = int(np.ceil((hi[0] - lo[0]) / step)) + 1, int(np.ceil((hi[1] - lo[1]) / step)) + 1
    p = mesh.vertices @ _view_axes(elev, azim)[:2].T
    tri = np.round((p - lo) / step * 16).astype(np.int32)[mesh.faces]  # 4 fractional bits (shift=4)
    mask = np.zeros((h, w), np.uint8)
    for t in tri:  # one convex fill per triangle: overlapping faces must not cancel (fillPoly is even-odd)
        cv2.fillConvexPoly(mask, t, 255, lineType=cv2.LINE_8, shift=4)
    mask = cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (5, 5), 1.0)
    return mask, (float(lo[0]), float(lo[0] + (w - 1) * step), float(lo[1]), float(lo[1] + (h - 1) * step))


#: how `plot_correspondence` explains its colours (the caption under the figure)
CORRESPONDENCE_KEY = (
    "Colour = position on B (x red, y green, z blue), carried to A through the map: each vertex of A takes the "
    "colour of the vertex of B it is matched to. A correct map gives A the colours that B, drawn in its own "
    "colours, has at the same places; a patch of a foreign colour is a region matched to the wrong part of B."
)


def plot_correspondence(
    source: Mesh,
    target: Mesh,
    correspondence: ArrayLike,
    *,
    layout: str = "overlay",
    target_colors: ArrayLike | None = None,
    titles: tuple[str, str] = ("A, coloured through the map", "B"),
    caption: bool = True,
    elev: float = 10.0,
    azim: float = 0.0,
    path: str | Path | None = None,
    dpi: int = 150,
) -> Figure:
    """A correspondence from a source shape A to a target shape B, seen through colours.

    B is coloured by a smooth function (default: its coordinates as RGB) and A by that function carried
    through the map: vertex ``i`` of A takes the colour of vertex ``correspondence[i]`` of B (``-1``:
    unmatched, drawn grey). Colours go from B to A because the map gives every vertex of A one vertex of B;
    the other way round, the vertices of B that no vertex of A maps to would have no colour.

    ``layout="overlay"`` (default) draws B under and around A in one axes, in the frame the meshes are given
    in: A coloured through the map, B as a grey silhouette with its outline drawn over A, and beside them a
    key, B in its own colours. Give B in A's frame (e.g. moved by the inverse of the comparison's
    registration) so that the outline shows where B lands on A. ``layout="side-by-side"`` draws A and B in
    two axes, for shapes that do not overlay (e.g. in different poses). ``titles`` names A and B (legend
    entries, or panel titles); ``caption`` adds `CORRESPONDENCE_KEY` under the figure.

    ``correspondence`` : (N_source,) int, the target vertex of each source vertex.
    """
    from textwrap import fill

    from matplotlib.legend_handler import HandlerTuple
    from matplotlib.patches import Patch

    if layout not in ("overlay", "side-by-side"):
        raise ValueError(f'layout must be "overlay" or "side-by-side", got {layout!r}')
    corr = np.asarray(correspondence)
    if corr.shape != (source.n_vertices,) or (corr.size and not np.issubdtype(corr.dtype, np.integer)):
        raise ValueError(f"correspondence must be ({source.n_vertices},) integer target vertices, got {corr.shape} {corr.dtype}")
    if corr.size and (corr.max() >= target.n_vertices or corr.min() < -1):
        raise ValueError(f"correspondence holds indices outside [-1, {target.n_vertices - 1}]: min {corr.min()}, max {corr.max()}")
    tc = _smooth_colours(target) if target_colors is None else np.asarray(target_colors, dtype=float)
    if tc.shape != (target.n_vertices, 3):
        raise ValueError(f"target_colors must have shape ({target.n_vertices}, 3), got {tc.shape}")
    sc = np.where(corr[:, None] >= 0, tc[np.maximum(corr, 0)], 0.6)
    if layout == "side-by-side":
        fig = _new_figure((10.0, 4.8 if caption else 4.2))
        ax1, ax2 = fig.subplots(1, 2)
        draw_mesh(ax1, source, _vertex_to_face(source, sc), elev=elev, azim=azim, shade=0.35)
        draw_mesh(ax2, target, _vertex_to_face(target, tc), elev=elev, azim=azim, shade=0.35)
        ax1.set_title(titles[0], fontsize=9)
        ax2.set_title(titles[1], fontsize=9)
        wrap = 150
    else:
        fig = _new_figure((9.0, 5.6 if caption else 5.0))
        ax, side = fig.subplots(1, 2, width_ratios=[3.0, 1.0])
        draw_mesh(ax, source, _vertex_to_face(source, sc), elev=elev, azim=azim, shade=0.35)
        view = _view_axes(elev, azim)
        xy = np.concatenate([source.vertices @ view[:2].T, target.vertices @ view[:2].T])
        lo, hi = xy.min(0), xy.max(0)
        pad = 0.03 * (hi - lo).max()
        lo, hi = lo - pad, hi + pad
        mask, extent = _footprint(target, elev, azim, lo, hi)
        shadow = np.zeros(mask.shape + (4,))
        shadow[..., :3] = 0.55
        shadow[..., 3] = 0.35 * (mask > 0.5)
        ax.imshow(shadow, origin="lower", extent=extent, zorder=0, interpolation="nearest")
        ax.contour(mask, levels=[0.5], origin="lower", extent=extent, colors="0.15", linewidths=1.0, zorder=3)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        draw_mesh(side, target, _vertex_to_face(target, tc), elev=elev, azim=azim, shade=0.35)
        side.set_title("key: B in its own colours", fontsize=9)
        handles = [
            (Patch(facecolor=(0.85, 0.25, 0.3)), Patch(facecolor=(0.3, 0.75, 0.35)), Patch(facecolor=(0.3, 0.35, 0.85))),
            Patch(facecolor=(0.55, 0.55, 0.55, 0.35), edgecolor="0.15"),
        ]
        labels = [fill(titles[0], 34), fill(f"{titles[1]}: silhouette and outline", 34)]
        if np.any(corr < 0):
            handles.append(Patch(facecolor="0.6"))
            labels.append("unmatched vertices of A")
        side.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=8, frameon=False,
                    handler_map={tuple: HandlerTuple(ndivide=None, pad=0)})
        wrap = 130
    if caption:
        fig.supxlabel(fill(CORRESPONDENCE_KEY, wrap), fontsize=8)
    return _finish(fig, path, dpi)
