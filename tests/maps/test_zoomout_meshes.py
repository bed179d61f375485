"""wpot.zoomout on meshes as users have them: triangles wound against their neighbours, several components,
non-manifold edges. Each either gets the oriented refinement or says, naming the mesh and the repair, why left and
right were not weighed; none gives a silent answer."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from helpers import mirror_symmetric
from wpot.maps.orientation import OrientationWarning
from wpot.maps.zoomout import zoomout
from wpot.mesh import Mesh, repair_mesh


def _nearest(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    return np.argmin(((queries[:, None, :] - points[None, :, :]) ** 2).sum(-1), axis=1)


@pytest.fixture(scope="module")
def planted():
    """Two triangulations of a mirror-symmetric surface, the true map and a start 70 % on the mirror side."""
    a, b = mirror_symmetric(700, seed=0), mirror_symmetric(800, seed=5)
    truth = _nearest(b.vertices, a.vertices)
    mirror = _nearest(b.vertices, a.vertices * np.array([-1.0, 1.0, 1.0]))
    start = np.where(np.random.default_rng(2).random(a.n_vertices) < 0.7, mirror, truth)
    return a, b, truth, start


def _error(b: Mesh, t: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(b.vertices[t] - b.vertices[truth], axis=1).mean() / np.sqrt(b.area))


def _rewound(m: Mesh, faces: np.ndarray, name: str | None = None) -> Mesh:
    f = m.faces.copy()
    f[faces] = f[faces][:, [0, 2, 1]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Mesh(m.vertices, f, name=name)


def test_misoriented_faces_are_found_exactly_and_rewound_by_the_repair(planted):
    a = planted[0]
    assert a.misoriented_faces.size == 0
    bad = np.array([3, 50, 51, 200, 401])
    with pytest.warns(UserWarning, match=r"b\.off: mesh defects: 5 triangles wound against their neighbours"):
        m = Mesh(a.vertices, _rewound(a, bad).faces, name="b.off")
    np.testing.assert_array_equal(np.sort(m.misoriented_faces), bad)
    # flipping more than half of a surface: the fewest (by area) are the ones named, the other side
    most = np.setdiff1d(np.arange(a.n_faces), bad)
    np.testing.assert_array_equal(np.sort(_rewound(a, most).misoriented_faces), bad)
    fixed, index_map, removed = repair_mesh(m)
    assert removed == "5 triangles rewound"
    np.testing.assert_array_equal(fixed.faces, a.faces)
    np.testing.assert_array_equal(index_map, np.arange(a.n_vertices))


def test_zoomout_names_a_mesh_wound_inconsistently_and_the_repair_restores_the_oriented_result(planted):
    a, b, truth, start = planted
    good = zoomout(a, b, start, k_end=40)
    broken = _rewound(b, np.arange(0, b.n_faces, 7), name="scan.off")
    with pytest.warns(OrientationWarning, match=r"scan\.off: mesh_b has \d+ triangles wound against their "
                                               r"neighbours \(Mesh\.cleaned\(\) rewinds them\)"):
        res = zoomout(a, broken, start, k_end=40)
    assert np.isnan(res.orientation_confidence) and res.candidate == "given"
    repaired = repair_mesh(broken)[0]
    again = zoomout(a, repaired, start, k_end=40)
    np.testing.assert_array_equal(again.map, good.map)
    assert again.orientation_confidence == pytest.approx(good.orientation_confidence)
    assert _error(b, again.map, truth) < 0.03


def test_zoomout_on_several_components_says_so_and_keeps_each_component_mapped(planted):
    a, b, truth, start = planted
    # a second, far away copy of each shape: two components, mapped component to component
    shift = np.array([10.0, 0.0, 0.0])
    with pytest.warns(UserWarning, match="2 connected components"):
        a2 = Mesh(np.r_[a.vertices, a.vertices + shift], np.r_[a.faces, a.faces + a.n_vertices])
    with pytest.warns(UserWarning, match="2 connected components"):
        b2 = Mesh(np.r_[b.vertices, b.vertices + shift], np.r_[b.faces, b.faces + b.n_vertices])
    start2 = np.r_[truth, truth + b.n_vertices]
    with pytest.warns(OrientationWarning, match="mesh_a has 2 connected components"):
        res = zoomout(a2, b2, start2, k_end=40)
    assert np.isnan(res.orientation_confidence)
    assert np.all(res.map[:a.n_vertices] < b.n_vertices)  # each component stays on its own
    assert np.all(res.map[a.n_vertices:] >= b.n_vertices)


def test_a_few_non_manifold_edges_do_not_change_the_oriented_choice(planted):
    a, b, truth, start = planted
    good = zoomout(a, b, start, k_end=40)
    # fins: a new vertex on three edges of B, each edge then shared by three triangles
    e = b.edges[[10, 400, 900]]
    tip = b.vertices[e].mean(axis=1) + 1e-3 * np.sqrt(b.area)
    fins = np.c_[e, b.n_vertices + np.arange(3)]
    with pytest.warns(UserWarning, match="3 non-manifold edges"):
        finned = Mesh(np.r_[b.vertices, tip], np.r_[b.faces, fins])
    assert finned.misoriented_faces.size == 0
    res = zoomout(a, finned, start, k_end=40)
    assert res.candidate == good.candidate and res.orientation_confidence > 0
    assert _error(finned, res.map, truth) < 0.03
