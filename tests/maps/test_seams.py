"""wpot.maps.seams: a planted half turn of a region is found by its seam and mapped back exactly, under relabelling
and rigid motion; a map without seams is left alone; anchors whose distances disagree are dropped."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import wpot
from wpot.mesh import Mesh
from wpot.maps.seams import SEAM_REGION, _consistent, map_regions, reanchor


@pytest.fixture(scope="module")
def body() -> Mesh:
    """An elongated blob (no symmetry), 'upright' along z."""
    m = wpot.example_mesh(700, seed=3)
    return Mesh(m.vertices * [1.0, 1.3, 3.0], m.faces)


def _half_turn(mesh: Mesh, above: float) -> tuple[np.ndarray, np.ndarray]:
    """A self-map of ``mesh``: the identity below the height quantile ``above``, and above it each vertex sent to
    the vertex nearest its image by a half turn about the vertical axis (left and right, and front and back,
    exchanged: orientation kept). Returns (map, the turned vertices as a mask)."""
    v = mesh.vertices
    top = v[:, 2] > np.quantile(v[:, 2], above)
    c = v.mean(axis=0)
    turned = (v[top] - c) * [-1.0, -1.0, 1.0] + c
    t = np.arange(mesh.n_vertices)
    t[top] = np.argmin(((turned[:, None, :] - v[None, :, :]) ** 2).sum(-1), axis=1)
    return t, top


def test_identity_has_one_region(body):
    labels, shares = map_regions(body, body, np.arange(body.n_vertices))
    assert np.all(labels == 0) and shares == pytest.approx([1.0])
    t, changed = reanchor(body, body, np.arange(body.n_vertices))
    assert not changed and np.array_equal(t, np.arange(body.n_vertices))


def test_a_half_turned_region_is_cut_off_by_its_seam(body):
    t, top = _half_turn(body, 0.7)
    labels, shares = map_regions(body, body, t)
    assert shares.sum() == pytest.approx(1.0)
    main = np.argmax(shares)
    assert np.all(labels[~top] == main)  # the identity part stays whole
    assert np.all(labels[top] != main)  # every turned vertex is cut off from it
    assert np.sum(shares >= SEAM_REGION) >= 2


def test_reanchor_undoes_a_half_turn_exactly(body):
    t, top = _half_turn(body, 0.7)
    assert np.mean(t[top] == np.flatnonzero(top)) < 0.05
    out, changed = reanchor(body, body, t)
    assert changed
    np.testing.assert_array_equal(out, np.arange(body.n_vertices))


def test_reanchor_is_invariant_to_relabelling_and_rigid_motion(body):
    t, _ = _half_turn(body, 0.7)
    rng = np.random.default_rng(0)
    perm = rng.permutation(body.n_vertices)  # B's vertex j is A's vertex perm[j]
    inv = np.argsort(perm)
    rot = Rotation.random(random_state=4).as_matrix()
    moved = Mesh(body.vertices[perm] @ rot.T + [2.0, -1.0, 0.5], inv[body.faces])
    out, changed = reanchor(body, moved, inv[t])
    assert changed
    np.testing.assert_array_equal(out, inv)  # A's vertex i is B's vertex inv[i]


def test_refine_is_applied_to_the_reanchored_map(body):
    t, _ = _half_turn(body, 0.7)
    seen = []
    out, changed = reanchor(body, body, t, refine=lambda m: seen.append(m.copy()) or m[::-1].copy())
    assert changed and len(seen) == 1
    np.testing.assert_array_equal(seen[0], np.arange(body.n_vertices))
    np.testing.assert_array_equal(out, np.arange(body.n_vertices)[::-1])


def test_inconsistent_anchors_are_dropped():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20, 3))
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    wrong = rng.normal(size=(20, 3))  # anchors 3 and 11 mapped far from where they belong
    q = p.copy()
    q[[3, 11]] = wrong[[3, 11]] * 5
    kept = _consistent(d, np.linalg.norm(q[:, None] - q[None], axis=-1))
    np.testing.assert_array_equal(kept, np.setdiff1d(np.arange(20), [3, 11]))
    np.testing.assert_array_equal(_consistent(d, d), np.arange(20))  # all agree: all kept


@pytest.mark.filterwarnings("ignore:mesh defects")
def test_bad_input_is_named(body):
    two = Mesh(np.vstack([body.vertices, body.vertices + 10]), np.vstack([body.faces, body.faces + body.n_vertices]))
    with pytest.raises(ValueError, match="mesh_a has 2 components"):
        reanchor(two, body, np.zeros(two.n_vertices, dtype=int))
    with pytest.raises(ValueError, match="correspondence"):
        map_regions(body, body, np.zeros(3, dtype=int))
