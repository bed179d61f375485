"""Figures: class ordering, and PNGs that are written and not blank."""
from __future__ import annotations

from types import SimpleNamespace

import matplotlib.image as mpimg
import numpy as np
import pytest
import trimesh

from wpot import plot
from wpot.evaluate import correspondence_error
from wpot.mesh import Mesh, cut


def ink(path) -> float:
    """Fraction of pixels that differ from the background (the corner pixel)."""
    img = mpimg.imread(path)[..., :3]
    return float(np.mean(np.any(np.abs(img - img[0, 0]) > 0.05, axis=-1)))


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(2)
    return Mesh(s.vertices, s.faces)


def test_class_order_groups_classes_stably():
    lab = np.array(["dog", "cat", "dog", "wolf", "cat", "dog"])
    order, blocks, starts = plot.class_order(lab)
    assert blocks == ["dog", "cat", "wolf"]
    assert order.tolist() == [0, 2, 5, 1, 4, 3]
    assert starts.tolist() == [0, 3, 5, 6]
    for k, c in enumerate(blocks):
        assert set(lab[order[starts[k] : starts[k + 1]]]) == {c}
    order, blocks, _ = plot.class_order(lab, classes=["wolf", "cat", "dog", "horse"])
    assert blocks == ["wolf", "cat", "dog"] and order.tolist() == [3, 1, 4, 0, 2, 5]
    with pytest.raises(ValueError, match="does not list"):
        plot.class_order(lab, classes=["cat", "dog"])


def test_distance_matrix_png(tmp_path):
    rng = np.random.default_rng(0)
    lab = np.repeat(["a", "b", "c"], 4)[rng.permutation(12)]
    d = rng.random((12, 12)) + (lab[:, None] != lab[None]) * 2
    fig = plot.plot_distance_matrix(d, lab, title="D", path=tmp_path / "d.png")
    assert (tmp_path / "d.png").stat().st_size > 0 and ink(tmp_path / "d.png") > 0.2
    # the image shown is the class-ordered matrix
    shown = fig.axes[0].images[0].get_array()
    order, _, _ = plot.class_order(lab)
    np.testing.assert_allclose(shown, d[np.ix_(order, order)])
    with pytest.raises(ValueError, match="square"):
        plot.plot_distance_matrix(d[:3], lab)


def test_confusion_png(tmp_path):
    from wpot.evaluate import one_shot_1nn

    # "a" and "b" are far apart; "c" sits next to "b", so "c" is often taken for "b"
    x = np.array([0, 1, 2, 10, 11, 12, 12.4, 13, 30])
    lab = np.array(["a", "a", "a", "b", "b", "c", "c", "c", "d"])
    r = one_shot_1nn(np.abs(x[:, None] - x[None]), lab, n_trials=400, seed=0)
    fig = plot.plot_confusion(r, title="one-shot", path=tmp_path / "conf.png")
    assert (tmp_path / "conf.png").stat().st_size > 0
    np.testing.assert_allclose(fig.axes[0].images[0].get_array(), 100 * np.ma.masked_invalid(r.confusion))
    # one label per non-zero cell, at its (column, row), with its percentage
    cells = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in fig.axes[0].texts
             if t.get_text() != plot.ONE_MEMBER}
    nz = {(i, j) for i, j in zip(*np.nonzero(np.nan_to_num(r.confusion) > 0))}
    assert set(cells) == nz and cells[(0, 0)] == "100"
    assert r.confusion[2, 1] > 0.01 and float(cells[(2, 1)]) == pytest.approx(100 * r.confusion[2, 1], abs=0.5)
    assert np.isnan(r.confusion[3]).all()  # "d" has one shape: never tested, its row says so
    marked = [t for t in fig.axes[0].texts if t.get_text() == plot.ONE_MEMBER]
    assert len(marked) == 1 and marked[0].get_position()[1] == 3
    with pytest.raises(ValueError, match="confusion"):
        plot.plot_confusion(np.eye(3))


def test_distance_matrix_colours_span_the_off_diagonal_and_axes_name_the_shapes():
    """The zero diagonal does not set the colour range; with names, each row and column is labelled with its shape
    (in class order) and the classes name the blocks on the top and right axes."""
    rng = np.random.default_rng(2)
    lab = np.array(["b", "a", "b", "a", "c", "b"])
    d = 5.0 + rng.random((6, 6))
    d = (d + d.T) / 2
    np.fill_diagonal(d, 0.0)
    off = d[~np.eye(6, dtype=bool)]
    fig = plot.plot_distance_matrix(d, lab)
    assert fig.axes[0].images[0].get_clim() == pytest.approx((off.min(), off.max()))
    names = [f"s{k}" for k in range(6)]
    fig = plot.plot_distance_matrix(d, lab, names=names)
    ax = fig.axes[0]
    assert ax.images[0].get_clim() == pytest.approx((off.min(), off.max()))
    order, blocks, starts = plot.class_order(lab)
    shown = [names[k] for k in order]
    assert [t.get_text() for t in ax.get_xticklabels()] == shown == [t.get_text() for t in ax.get_yticklabels()]
    top, right = ax.child_axes
    assert [t.get_text() for t in top.xaxis.get_minorticklabels()] == blocks == ["b", "a", "c"]
    assert [t.get_text() for t in right.yaxis.get_minorticklabels()] == blocks
    np.testing.assert_allclose(top.get_xticks(), starts - 0.5)  # the brackets: a long tick at each boundary
    with pytest.raises(ValueError, match="one name per shape"):
        plot.plot_distance_matrix(d, lab, names=names[:5])
    # NaN entries (pairs not done) are left out of the range
    d[0, 1] = np.nan
    assert plot.plot_distance_matrix(d, lab).axes[0].images[0].get_clim()[1] == pytest.approx(np.nanmax(d))


def test_confusion_follows_a_given_class_order_and_keeps_its_title_inside():
    from wpot.evaluate import one_shot_1nn

    x = np.array([0, 1, 2, 10, 11, 12, 12.4, 13, 30])
    lab = np.array(["a", "a", "a", "b", "b", "c", "c", "c", "d"])
    r = one_shot_1nn(np.abs(x[:, None] - x[None]), lab, n_trials=200, seed=0)
    order = ["c", "d", "a", "b"]
    title = "one-shot 1-NN (%): ldsift, partial transport, cell-pooled samples of a long run name"
    fig = plot.plot_confusion(r, classes=order, title=title)
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == order == [t.get_text() for t in ax.get_xticklabels()]
    pos = [list(r.classes).index(c) for c in order]
    np.testing.assert_allclose(ax.images[0].get_array(), 100 * np.ma.masked_invalid(r.confusion[np.ix_(pos, pos)]))
    marked = [t for t in ax.texts if t.get_text() == plot.ONE_MEMBER]
    assert len(marked) == 1 and marked[0].get_position()[1] == order.index("d")
    fig.canvas.draw()
    box, inside = fig.bbox, ax.title.get_window_extent()
    assert " ".join(ax.title.get_text().split()) == title
    assert box.x0 <= inside.x0 and inside.x1 <= box.x1 and box.y0 <= inside.y0 and inside.y1 <= box.y1
    with pytest.raises(ValueError, match="classes must list"):
        plot.plot_confusion(r, classes=["a", "b"])


def test_cumulative_errors_png(tmp_path, sphere):
    truth = np.arange(sphere.n_vertices)
    rng = np.random.default_rng(1)
    e = correspondence_error(sphere, rng.integers(0, sphere.n_vertices, truth.size), truth)
    fig = plot.plot_cumulative_errors({"random": e, "manual": ([0, 0.1, 0.25], [0, 0.5, 1.0])}, path=tmp_path / "c.png")
    assert ink(tmp_path / "c.png") > 0.01
    lines = fig.axes[0].get_lines()
    np.testing.assert_allclose(lines[0].get_ydata(), 100 * e.curve)
    assert "AUC" in fig.axes[0].get_legend().get_texts()[0].get_text()
    assert fig._repr_png_().startswith(b"\x89PNG")  # shown inline by Jupyter without pyplot
    with pytest.raises(ValueError, match="curve must be"):
        plot.plot_cumulative_errors({"x": 3.0})


def test_mesh_figures_png(tmp_path, sphere):
    vals = sphere.vertices[:, 2]
    plot.plot_vertex_scalar(sphere, vals, label="z", path=tmp_path / "s.png")
    assert ink(tmp_path / "s.png") > 0.1
    with pytest.raises(ValueError, match="one per vertex"):
        plot.plot_vertex_scalar(sphere, vals[:-1])
    part, _ = cut(sphere, sphere.vertices[:, 2] > 0.3)
    plot.plot_registration(part, sphere, path=tmp_path / "r0.png")
    reg = SimpleNamespace(scale=1.5, rotation=np.eye(3), translation=np.array([0.0, 2.0, 0.0]))
    plot.plot_registration(part, sphere, reg, path=tmp_path / "r1.png")
    a, b = mpimg.imread(tmp_path / "r0.png"), mpimg.imread(tmp_path / "r1.png")
    assert ink(tmp_path / "r1.png") > 0.1 and (a.shape != b.shape or not np.allclose(a, b))
    with pytest.raises(ValueError, match="not both"):
        plot.plot_registration(part, sphere, reg, scale=2.0)
    # a part the transform puts inside the full shape is still drawn (over it), in its colour
    fig = plot.plot_registration(sphere, sphere, scale=0.5, part_color=(1.0, 0.0, 0.0))
    pix = _rgb_in(fig, fig.axes[0])
    assert np.mean((pix[..., 0] > 0.3) & (pix[..., 1] < 0.1) & (pix[..., 2] < 0.1)) > 0.05
    corr = np.arange(sphere.n_vertices)[::-1].copy()
    plot.plot_correspondence(sphere, sphere, corr, path=tmp_path / "k.png")
    assert ink(tmp_path / "k.png") > 0.1
    with pytest.raises(ValueError, match="outside"):
        plot.plot_correspondence(sphere, sphere, corr + 1)
    with pytest.raises(ValueError, match="layout"):
        plot.plot_correspondence(sphere, sphere, corr, layout="stacked")


def _rgb_in(fig, ax) -> np.ndarray:
    """(H, W, 3) pixels of the rendered figure inside ``ax``'s box."""
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(float) / 255
    x0, y0, x1, y1 = ax.get_window_extent().extents
    h = img.shape[0]
    return img[int(h - y1) : int(h - y0), int(x0) : int(x1)]


def test_correspondence_overlay_draws_b_under_a_with_a_key(sphere):
    """Default layout: one axes with A coloured through the map over B's silhouette (B moved 3 radii to the
    right, so that both show), a key axes with B in its own colours, the legend naming both, the caption."""
    b = sphere.transformed(translation=[0.0, 3.0, 0.0])  # azim 0: +y is screen right
    red = np.tile([0.9, 0.1, 0.1], (b.n_vertices, 1))
    fig = plot.plot_correspondence(sphere, b, np.arange(sphere.n_vertices), target_colors=red, titles=("A!", "B!"))
    main, key = fig.axes
    # both shapes fit in the main axes: A around y = 0, B around y = 3
    assert main.get_xlim()[0] < -1.0 and main.get_xlim()[1] > 4.0
    # B's silhouette: a grey image, covering the disc of radius 1 around (3, 0) and not A's centre
    shadow = main.images[0].get_array()
    x0, x1, y0, y1 = main.images[0].get_extent()
    covered = shadow[..., 3] > 0
    ys, xs = np.nonzero(covered)
    px = x0 + xs * (x1 - x0) / (shadow.shape[1] - 1)
    assert px.min() == pytest.approx(2.0, abs=0.1) and px.max() == pytest.approx(4.0, abs=0.1)
    area = covered.sum() * ((x1 - x0) / (shadow.shape[1] - 1)) ** 2
    assert area == pytest.approx(np.pi, rel=0.05)  # an icosphere's outline: a disc of radius ~1
    # A takes B's colour (red) through the identity map: the main axes' pixels are red, not blue or green
    pix = _rgb_in(fig, main)
    coloured = pix[(pix.max(-1) - pix.min(-1)) > 0.2]
    assert len(coloured) > 1000 and np.all(coloured[:, 0] > coloured[:, 1]) and np.all(coloured[:, 0] > coloured[:, 2])
    assert "key" in key.get_title()
    labels = [t.get_text().replace("\n", " ") for t in key.get_legend().get_texts()]
    assert labels[0] == "A!" and labels[1].startswith("B!")
    assert fig.get_supxlabel().replace("\n", " ") == plot.CORRESPONDENCE_KEY


def test_correspondence_side_by_side(sphere):
    corr = np.arange(sphere.n_vertices)
    corr[:5] = -1
    fig = plot.plot_correspondence(sphere, sphere, corr, layout="side-by-side", titles=("A!", "B!"), caption=False)
    assert [ax.get_title() for ax in fig.axes] == ["A!", "B!"]
    assert not any(ax.images for ax in fig.axes)  # no silhouette overlay
    assert fig.get_supxlabel() == ""
    fig = plot.plot_correspondence(sphere, sphere, corr)  # unmatched vertices get a legend entry
    assert "unmatched vertices of A" in [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
