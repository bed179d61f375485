"""The ground truth of benchmarks/partial_poses.py (issue 23) on real TOSCA shapes: parts and their index maps,
the identity match of a part onto its own source (error 0, all mass on the true region), the true region on
another pose, and the mass share over sampled cells. Skipped when ../shared/data is absent."""
from __future__ import annotations

import json

import numpy as np
import pytest

import importlib

pytestmark = pytest.mark.data


@pytest.fixture(scope="module")
def pp():
    return importlib.import_module("benchmarks.partial_poses")


@pytest.fixture(scope="module")
def cat(pp, tosca5k):
    """cat0's parts (every kind) and the meshes they are matched to here."""
    from wpot.io import load_mesh

    members = pp.class_members(tosca5k)
    lm = pp.landmarks(tosca5k, "cat", members["cat"])
    parts = pp.make_parts(tosca5k, "cat0", lm, seed=0)
    return {"lm": lm, "parts": parts, "S": load_mesh(tosca5k / "cat0.off"), "T": load_mesh(tosca5k / "cat1.off")}


def test_parts_are_deterministic_and_their_index_maps_round_trip(pp, tosca5k, cat):
    S, parts = cat["S"], cat["parts"]
    assert [p.kind for p in parts] == ["head", "head", "limb", "limb", "cut", "cut", "holes"]
    again = pp.make_parts(tosca5k, "cat0", cat["lm"], seed=0, kinds=("cut", "holes"))
    assert [p.sha() for p in again] == [p.sha() for p in parts if p.kind in ("cut", "holes")]
    other_seed = pp.make_parts(tosca5k, "cat0", cat["lm"], seed=1, kinds=("holes",))
    assert other_seed[0].sha() != parts[-1].sha()
    s_faces = {tuple(sorted(f)) for f in S.faces.tolist()}
    for p in parts:
        assert p.mesh.n_components == 1, p.name
        np.testing.assert_array_equal(p.mesh.vertices, S.vertices[p.idx])  # part vertex v is S's vertex idx[v]
        assert len(np.unique(p.idx)) == len(p.idx)
        # every triangle of the part is a triangle of S, through the index map
        assert all(tuple(sorted(f)) in s_faces for f in p.idx[p.mesh.faces].tolist()), p.name
        assert p.fraction == pytest.approx(p.mesh.area / S.area)
    frac = {(p.kind, p.size): p.fraction for p in parts}
    assert 0.20 <= frac["head", "L"] <= 0.26 and 0.08 <= frac["head", "S"] <= 0.11
    assert frac["holes", "L"] > 0.6
    # the head landmark is the snout tip of the reference cat0, at its front (-y; TOSCA's animals face -y)
    tip = S.vertices[tosca_vts_of(tosca5k, "cat0")[cat["lm"].head]]
    assert tip[1] < np.quantile(S.vertices[:, 1], 0.01)


def test_identity_match_onto_the_source_scores_zero_error_and_full_mass(pp, tosca5k, cat):
    from wpot.evaluate import GeodesicDistances

    S = cat["S"]
    geo = GeodesicDistances(S)
    va = S.vertex_areas
    # the small parts (head, limb, cut; the holes part has the same ground truth code, but 4,000 template points
    # whose geodesic rows would take most of this test's time)
    for p in (p for p in cat["parts"] if p.size == "S"):
        truth = pp.ground_truth(tosca5k, p, S, "cat0", S)
        assert len(truth.src) > 0.5 * p.fraction * 5000, p.name  # the template points in the part
        np.testing.assert_array_equal(p.idx[truth.src], truth.dst)  # the truth of the identity is itself
        rec, arrays = pp.score_map(geo, p.idx, truth)  # the identity map: part vertex v -> S vertex idx[v]
        assert rec["mean"] == 0 and rec["auc"] == 1 and rec["share"] == 1 and rec["sym_mean"] == 0, p.name
        assert not arrays["errors"].any()
        sent = np.zeros(S.n_vertices)
        sent[p.idx] = 1.0  # the identity plan's column sums
        assert pp.received_share(sent, None, truth.region) == pytest.approx(1.0)
        assert truth.uniform == pytest.approx(va[p.idx].sum() / va.sum())
        # the template route (what another pose gets) gives the same region up to the template's resolution
        vts = tosca_vts_of(tosca5k, "cat0")
        region = pp.true_region(S, vts, p.source_vertices(S.n_vertices)[vts] >= 0)
        assert va[region == truth.region].sum() / va.sum() > 0.99, p.name
        assert pp.received_share(sent, None, region) > 0.98, p.name


@pytest.mark.parametrize("remesh", ["lowres", "0.5", "1"])
def test_remeshed_parts_share_no_triangle_and_carry_the_ground_truth(pp, tosca5k, cat, remesh):
    """A part cut from a re-meshing of S (the low-res pose, or S subdivided and decimated, at its own vertex
    count too) has hardly any of S's triangles or vertices; mapped
    back onto S by nearest vertices in space, it scores the error of a mesh's spacing (not 0: the vertices
    differ), and its true region covers its own share of the area."""
    from scipy.spatial import cKDTree

    from wpot.evaluate import GeodesicDistances

    if remesh != "lowres":
        pytest.importorskip("fast_simplification", reason="fast-simplification (a dependency of wpot) is not installed")
    S = cat["S"]
    parts = pp.make_parts(tosca5k, "cat0", cat["lm"], seed=0, kinds=("head", "cut"), remesh=remesh)
    if not parts:
        pytest.skip(f"no low-res twin of cat0 beside {tosca5k}")
    assert [p.sha() for p in parts] != [p.sha() for p in cat["parts"] if p.kind in ("head", "cut")]
    s_faces = {tuple(sorted(f)) for f in S.faces.tolist()}
    geo = GeodesicDistances(S)
    spacing = S.edge_lengths.mean() / np.sqrt(S.area)
    for p in parts:
        assert p.detail["remesh"] == remesh and p.mesh.n_components == 1
        dist, near = cKDTree(S.vertices).query(p.mesh.vertices)
        same = dist < 1e-9 * np.sqrt(S.area)  # a vertex of S's, kept where it was
        assert same.mean() < 0.1, p.name
        kept = same[p.mesh.faces].all(axis=1)
        assert sum(tuple(sorted(f)) in s_faces for f in near[p.mesh.faces[kept]].tolist()) < 0.05 * p.mesh.n_faces, p.name
        truth = pp.ground_truth(tosca5k, p, S, "cat0", S)
        assert len(truth.src) > 0.3 * p.fraction * 5000, p.name
        rec, _ = pp.score_map(geo, near, truth)
        assert rec["mean"] < 1.5 * spacing, (p.name, rec["mean"], spacing)
        assert abs(truth.uniform - p.fraction) < 0.05, p.name  # up to a ring of S along the cut
    if remesh == "0.5":  # half S's vertices (quadric decimation keeps more where the surface bends)
        r, carrier = pp.remeshed(tosca5k, "cat0", remesh)
        assert 0.45 < r.n_vertices / S.n_vertices < 0.55 and carrier.shape == (S.n_vertices,)


def tosca_vts_of(folder, name):
    from wpot.datasets import tosca_vts

    return tosca_vts(folder, name)


def test_true_region_on_another_pose_and_mass_over_cells(pp, tosca5k, cat):
    from wpot.sampling import farthest_point_sampling

    S, T = cat["S"], cat["T"]
    head = cat["parts"][0]
    truth = pp.ground_truth(tosca5k, head, S, "cat1", T)
    assert truth.region[truth.dst].mean() > 0.98  # the true correspondents lie in the true region
    assert abs(truth.uniform - head.fraction) < 0.05  # a near-isometry keeps the part's share of the area
    # the region is the head of cat1: around its own head landmark
    tip = tosca_vts_of(tosca5k, "cat1")[cat["lm"].head]
    assert truth.region[tip]
    # a mirror truth exists for every evaluated point
    assert truth.sym.shape == truth.dst.shape
    # the mass T receives, spread over sampled cells: uniform mass per vertex gives the region's vertex share
    sub = farthest_point_sampling(T, 250)
    share = pp.received_share(sub.counts / T.n_vertices, sub, truth.region)
    assert share == pytest.approx(truth.region.mean())
    on = np.bincount(sub.nearest, truth.region, minlength=sub.n_samples) == sub.counts  # cells inside the region
    m = np.where(on, 1.0, 0.0)
    assert pp.received_share(m, sub, truth.region) == pytest.approx(1.0)


def test_landmarks_are_true_pairs_inside_the_part_and_spread(pp, tosca5k, cat):
    """``--landmarks``: each landmark is an evaluated vertex of the part with its true vertex of T, none on the
    part's cut (at least half the deepest evaluated vertex's distance from it), the first at an extremity and the
    second as far from it as the inside allows; a vertex whose truth is planted wrong is passed over."""
    import dataclasses

    from wpot.mesh import edge_paths

    S, T = cat["S"], cat["T"]
    limb = next(p for p in cat["parts"] if p.kind == "limb")
    truth = pp.ground_truth(tosca5k, limb, S, "cat1", T)
    marks = pp.landmarks_from(limb.mesh, T, truth, 3)
    assert marks.shape == (3, 2) and len(set(marks[:, 0])) == 3
    where = {int(v): i for i, v in enumerate(truth.src)}
    assert all(truth.dst[where[int(a)]] == b for a, b in marks)
    depth = edge_paths(limb.mesh, np.unique(limb.mesh.boundary_edges.ravel()), min_only=True)
    assert (depth[marks[:, 0]] >= 0.5 * depth[truth.src].max() - 1e-9).all() and depth[marks[0, 0]] > 0
    inner = truth.src[depth[truth.src] >= 0.5 * depth[truth.src].max()]
    d0 = edge_paths(limb.mesh, int(marks[0, 0]))
    assert d0[marks[1, 0]] == pytest.approx(d0[inner].max())
    assert pp.landmarks_from(limb.mesh, T, truth, 1).tolist() == marks[:1].tolist()
    # the first landmark's truth sent to the far end of T: the picker takes another vertex
    i = where[int(marks[0, 0])]
    far = int(np.argmax(edge_paths(T, int(truth.dst[i]))))
    wrong = dataclasses.replace(truth, dst=np.where(np.arange(len(truth.dst)) == i, far, truth.dst))
    assert not pp._truth_agrees(limb.mesh, T, wrong, i) and pp._truth_agrees(limb.mesh, T, truth, i)
    again = pp.landmarks_from(limb.mesh, T, wrong, 1)
    assert again[0, 0] != marks[0, 0] and again[0, 1] == truth.dst[where[int(again[0, 0])]]


def test_store_resumes_and_refuses_changed_parts(pp, tmp_path, cat):
    store = pp.Store(tmp_path)
    rec = {"method": "m", "part": "p", "target": "t", "relation": "same", "seconds": 0.1, "info": {"distance": 1.0}}
    store.add(rec, {"errors": np.zeros(3, np.float32), "sym_errors": np.zeros(3, np.float32)})
    with open(tmp_path / "pairs.jsonl", "a") as fh:
        fh.write('{"method": "m", "part": "q"')  # a line cut by a kill
    again = pp.Store(tmp_path)
    assert again.done == {("m", "p", "t")}
    assert again.npz_path("m", "p", "t").is_file()
    parts = cat["parts"][:2]
    pp.record_parts(tmp_path, parts)
    pp.record_parts(tmp_path, parts)  # the same parts again: accepted, not written twice
    assert len(pp.read_parts(tmp_path)) == 2
    lines = (tmp_path / "parts.jsonl").read_text().splitlines()
    assert len(lines) == 2 and json.loads(lines[0])["idx_sha"] == parts[0].sha()
    changed = pp.Part(parts[0].name, "cat0", "cat", "head", "L", 0.2, parts[0].idx[:-1], parts[0].mesh)
    with pytest.raises(SystemExit, match="differs"):
        pp.record_parts(tmp_path, [changed])


@pytest.mark.parametrize("value, says", [('{"n_refin": 3}', "n_refin"), ("{n_refine: 3}", "double quotes"),
                                         ("[96]", "JSON object"), ('{"n_refine": 1}', "n_refine must be")])
def test_bad_locate_options_are_refused_before_anything_runs(pp, tmp_path, capsys, value, says):
    with pytest.raises(SystemExit):
        pp.main(["--out", str(tmp_path / "run"), "--locate-options", value])
    err = capsys.readouterr().err
    assert "--locate-options" in err and says in err
    assert not (tmp_path / "run").exists()  # refused before the results folder is made


def test_faust_family_classes_are_people_and_its_landmarks_read_y_up(pp, shared_data):
    """faust_5k as a part family: a shape's class is its person (number div 10), and the landmarks of a person's
    reference pose are read with y up: the head is its highest point, the two feet its lowest patches."""
    from wpot.datasets import tosca_vts
    from wpot.io import load_mesh

    faust = shared_data / "faust_5k"
    if not (faust / "vtx_5k").is_dir():
        pytest.skip(f"{faust} is absent")
    assert pp.shape_class("tr_reg_037") == "person3" and pp.shape_class("cat10") == "cat"
    members = pp.class_members(faust)
    assert sorted(members) == [f"person{k}" for k in range(10)]
    assert members["person3"] == [f"tr_reg_{30 + k:03d}" for k in range(10)]
    lm = pp.landmarks(faust, "person3", members["person3"])
    mesh = load_mesh(faust / "vtx_5k" / "tr_reg_030.off")
    y = mesh.vertices[tosca_vts(faust / "vtx_5k", "tr_reg_030"), 1]
    height = np.ptp(mesh.vertices[:, 1])
    assert y[lm.head] > mesh.vertices[:, 1].max() - 0.02 * height
    feet = [lm.limbs[k] for k in lm.limbs if k.startswith("foot")]
    assert len(feet) == 2 and all(y[f] < mesh.vertices[:, 1].min() + 2 * pp.FOOT_BAND * height for f in feet)
