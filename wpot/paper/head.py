"""HEAD (paper §4.2): the head of every cat and horse of ``tosca_isometric_5k``, cut with `wpot.cut` at a region
chosen once on a reference shape per class and transferred to the other shapes through the ground truth, so
that every head of a class is the same part."""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from wpot.io import load_mesh, load_vertex_map, save_mesh
from wpot.mesh import Mesh, cut

from wpot.datasets import class_label, correspondence_group, natural_key, read_label_csv, tosca_vts
from wpot.evaluate import GeodesicDistances

__all__ = ["HEAD_AREA_FRACTION", "HEAD_REFERENCES", "HeadDataset", "build_head_dataset", "head_ground_truth", "load_head_dataset",
           "check_twin", "lowres_template", "twin_offset", "TWIN_TOL"]

# ----------------------------------------------------------------------------- mesh files
def _load_mesh(path: Path) -> Mesh:
    return load_mesh(path)


def _save_mesh(mesh: Mesh, path: Path) -> None:
    save_mesh(mesh, path)


# ----------------------------------------------------------------------------- HEAD dataset
#: HEAD: the reference shape per class and the fraction of its area that the head covers. The head
#: is the geodesic ball around the snout tip (the reference's vertex of smallest y: TOSCA cats and horses
#: face -y) holding that area fraction; the paper's heads have about 700 of 3,400 vertices (~20 %).
HEAD_REFERENCES: dict[str, str] = {"cat": "cat0", "horse": "horse0"}
HEAD_AREA_FRACTION = 0.2


@dataclass(frozen=True)
class HeadDataset:
    """The HEAD dataset (paper §4.2): full shapes and their heads.

    ``names[k]`` / ``meshes[k]`` / ``labels[k]`` (``"cat"``, ``"cat_head"``, ``"horse"``, ``"horse_head"``)
    and ``species[k]`` (``"cat"`` / ``"horse"``). For a head, ``parent[name]`` is the full shape it was cut
    from and ``parent_map[name]`` ((N_head,) int64) the vertex of the parent each head vertex is
    (part vertex -> full-shape vertex). ``template[name]`` ((K,) int64, -1 where absent) is the head vertex at
    each TOSCA template point, so heads map to every shape of their class (`head_ground_truth`).
    ``full_template[name]`` ((K,) int64) is a full shape's vertex at each template point where the full shapes
    are not ``tosca_isometric_5k``'s own meshes (the low-resolution HEAD: ``build_head_dataset(lowres=)``);
    empty otherwise (the ``.vts`` files serve).
    """

    names: tuple[str, ...]
    meshes: tuple[Mesh, ...] = field(repr=False)
    labels: np.ndarray = field(repr=False)
    species: np.ndarray = field(repr=False)
    parent: dict[str, str] = field(repr=False)
    parent_map: dict[str, np.ndarray] = field(repr=False)
    template: dict[str, np.ndarray] = field(repr=False)
    landmark: dict[str, int] = field(repr=False)
    radius: dict[str, float] = field(repr=False)
    full_template: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.names)

    def mesh(self, name: str) -> Mesh:
        return self.meshes[self.names.index(name)]


def geodesic_from(mesh: Mesh, vertex: int) -> np.ndarray:
    """(N,) geodesic distances from ``vertex`` to every vertex (heat method, `wpot.evaluate.GeodesicDistances`)."""
    return GeodesicDistances(mesh).from_sources(np.array([vertex]))[0].astype(np.float64)


def _transfer_scalar(mesh: Mesh, vts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Carry a function on the template points onto every vertex of ``mesh``: a vertex that template points
    land on gets their mean; the others take the value of the nearest such vertex (Euclidean)."""
    n = mesh.n_vertices
    tot = np.bincount(vts, values, minlength=n)
    cnt = np.bincount(vts, minlength=n)
    hit = cnt > 0
    out = np.empty(n)
    out[hit] = tot[hit] / cnt[hit]
    if not hit.all():
        hit_idx = np.nonzero(hit)[0]
        _, nn = cKDTree(mesh.vertices[hit_idx]).query(mesh.vertices[~hit])
        out[~hit] = out[hit_idx[nn]]
    return out


def clean_region(mesh: Mesh, mask: np.ndarray, seed: int) -> np.ndarray:
    """The connected component of ``mask`` (N,) bool holding vertex ``seed``, with holes (components of the
    complement that do not hold the complement's largest component) filled: a region cut out in one piece, as
    the HEAD builder and `benchmarks/partial_poses.py` cut parts."""
    adj = mesh.adjacency

    def components(keep: np.ndarray) -> np.ndarray:
        a = sp.diags(keep.astype(float)) @ adj @ sp.diags(keep.astype(float))
        _, lab = sp.csgraph.connected_components(a, directed=False)
        return lab

    if not mask[seed]:
        raise ValueError(f"the seed vertex {seed} is outside the region (mask[seed] is False)")
    lab = components(mask)
    region = mask & (lab == lab[seed])
    rest = ~region
    lab = components(rest)
    big = np.bincount(lab[rest]).argmax()
    return region | (rest & (lab != big))


def region_fraction_radius(mesh: Mesh, dist: np.ndarray, fraction: float) -> float:
    """Smallest radius r whose ball {dist <= r} holds ``fraction`` of the area (vertex areas = 1/3 of faces)."""
    va = mesh.vertex_areas
    order = np.argsort(dist)
    cum = np.cumsum(va[order]) / va.sum()
    return float(dist[order[np.searchsorted(cum, fraction)]])


#: the most a low-resolution TOSCA shape may lie from its ``tosca_isometric_5k`` namesake (`twin_offset`) for the
#: namesake's ground truth to be carried to it by nearest vertices. One edge length: the namesakes that are one
#: pose lie 0-0.31 apart, and ``tosca_lowres``'s victoria0, a copy of its victoria1 (another pose), 1.6
TWIN_TOL = 1.0


def twin_offset(mesh: Mesh, mesh_5k: Mesh) -> float:
    """How far a low-resolution shape lies from its ``tosca_isometric_5k`` namesake: the median distance from
    the vertices of ``mesh`` to the nearest vertex of ``mesh_5k``, in ``mesh_5k``'s mean edge lengths. Below
    `TWIN_TOL` the two are one pose meshed apart; above it, not the same pose (``tosca_lowres`` holds two pairs
    of identical files, victoria0 = victoria1 and victoria13 = victoria22, so its victoria0 is not the 5k
    victoria0)."""
    d, _ = cKDTree(mesh_5k.vertices).query(mesh.vertices)
    return float(np.median(d) / mesh_5k.mean_edge_length)


def check_twin(mesh: Mesh, mesh_5k: Mesh) -> None:
    """Raise ValueError when the low-resolution shape ``mesh`` is not the pose of its ``tosca_isometric_5k``
    namesake ``mesh_5k`` (`twin_offset` above `TWIN_TOL`), so that the namesake's ground truth does not carry to
    it."""
    offset = twin_offset(mesh, mesh_5k)
    if offset > TWIN_TOL:
        raise ValueError(f"the low-resolution shape lies {offset:.2f} edge lengths from its tosca_isometric_5k "
                         f"namesake (at most {TWIN_TOL:g} when they are one pose): it is another pose, and the "
                         "namesake's ground truth does not carry to it")


def lowres_template(mesh: Mesh, mesh_5k: Mesh, vts_5k: np.ndarray) -> np.ndarray:
    """The TOSCA template carried to a low-resolution shape: (K,) int64, the vertex of ``mesh`` nearest to
    the template point's vertex ``vts_5k`` of the same-named ``tosca_isometric_5k`` shape ``mesh_5k`` (the two
    sets share coordinates and poses: nearest neighbours are 0.1-0.25 of an edge apart, see the data README).
    Raises ValueError when ``mesh`` is not ``mesh_5k``'s pose (`check_twin`)."""
    check_twin(mesh, mesh_5k)
    _, nn = cKDTree(mesh.vertices).query(mesh_5k.vertices[vts_5k])
    return nn.astype(np.int64)


def build_head_dataset(
    tosca: str | Path,
    out: str | Path | None = None,
    *,
    classes: Sequence[str] = ("cat", "horse"),
    area_fraction: float = HEAD_AREA_FRACTION,
    lowres: str | Path | None = None,
    per_class: int | None = None,
) -> HeadDataset:
    """Build HEAD (paper §4.2): every cat and horse of ``tosca_isometric_5k`` and its head.

    The head is chosen once per class on the reference shape (`HEAD_REFERENCES`): the geodesic ball
    (heat method) around the snout tip holding ``area_fraction`` of the area. Its geodesic distance function
    is carried to the other shapes of the class through the ``.vts`` ground truth (`_transfer_scalar`), and
    thresholded at the same radius, so every head is the same part; the region is then made one connected
    piece without holes and cut out with `wpot.cut`. For ``tosca_isometric_5k`` that is 11 cats + 8 horses =
    19 full shapes and 19 heads: 38 shapes.

    With ``lowres`` (the ``tosca_lowres`` folder), the full shapes are the low-resolution meshes of the same
    names (about 3,400 vertices, heads about 700: the paper's HEAD), and the template is carried to each by
    nearest neighbours (`lowres_template`), so the same head region and the same ground truth follow. Only
    names in both sets qualify: TOSCA8's cats (cat0-cat5) are, but its horses horse2-horse4 have no
    ``tosca_isometric_5k`` counterpart, hence no ground truth and no way to place their head; with
    ``per_class=6`` the horses are the six lowest-numbered ones that have one (horse0, 5, 6, 7, 10, 14).

    Parameters
    ----------
    tosca : the ``tosca_isometric_5k`` folder or its ``vtx_5k`` folder.
    lowres : optional ``tosca_lowres`` folder (see above).
    per_class : keep each class's first ``per_class`` shapes by shape number (None: all).
    out : optional folder (created; never inside the repository) where the shapes are written as
        ``<name>.off`` beside ``labels.csv`` (name, class, species), ``<head>.parent.txt`` (one 0-based
        vertex of the parent per head vertex) and ``<head>.template.txt`` (the head vertex at each template
        point, -1 where absent), and ``manifest.json``. `load_head_dataset` reads it back.
    """
    tosca = Path(tosca)
    folder = tosca / "vtx_5k" if (tosca / "vtx_5k").is_dir() else tosca
    if not (folder / "corres").is_dir():
        raise ValueError(f"{tosca} is not a tosca_isometric_5k folder (no vtx_5k/corres)")
    if not 0.0 < area_fraction < 1.0:
        raise ValueError(f"area_fraction must lie in (0, 1), got {area_fraction}")
    if per_class is not None and per_class < 1:
        raise ValueError(f"per_class must be >= 1 (or None), got {per_class}")
    all_names = [p.stem for p in sorted(folder.glob("*.off"), key=lambda p: natural_key(p.stem))]
    low: dict[str, Path] = {}
    if lowres is not None:
        lowres = Path(lowres)
        if (lowres / "tosca_lowres").is_dir():
            lowres = lowres / "tosca_lowres"
        low = {p.stem: p for p in lowres.glob("*.mat")}
        if not low:
            raise ValueError(f"lowres={str(lowres)!r} holds no TOSCA low-resolution shapes (*.mat)")
    names, meshes, labels, species = [], [], [], []
    parent, parent_map, template, landmark, radius, full_template = {}, {}, {}, {}, {}, {}
    heads: list[tuple[str, Mesh, str]] = []
    for cls in classes:
        members = [n for n in all_names if class_label(n) == cls and (not low or n in low)]
        members = members[:per_class] if per_class is not None else members
        ref = HEAD_REFERENCES.get(cls, members[0] if members else None)
        if ref not in members:
            raise ValueError(f"no shapes of class {cls!r} (reference {ref!r}) in {folder}")
        ref_mesh = _load_mesh(folder / f"{ref}.off")
        ref_vts = tosca_vts(folder, ref)
        tip = int(np.argmin(ref_mesh.vertices[:, 1]))
        # the template point closest (on the reference) to the snout tip: the landmark carried to each shape
        t_land = int(np.argmin(np.linalg.norm(ref_mesh.vertices[ref_vts] - ref_mesh.vertices[tip], axis=1)))
        dist = geodesic_from(ref_mesh, int(ref_vts[t_land]))
        r = region_fraction_radius(ref_mesh, dist, area_fraction)
        f_template = dist[ref_vts]
        landmark[cls], radius[cls] = t_land, r
        for name in members:
            mesh = ref_mesh if name == ref else _load_mesh(folder / f"{name}.off")
            vts = tosca_vts(folder, name)
            if low:
                mesh_5k, mesh = mesh, _load_mesh(low[name])
                vts = full_template[name] = lowres_template(mesh, mesh_5k, vts)
            f = _transfer_scalar(mesh, vts, f_template)
            region = clean_region(mesh, f <= r, int(vts[t_land]))
            head, pmap = cut(mesh, region)
            hname = f"{cls}_head{name[len(cls):]}"
            inv = np.full(mesh.n_vertices, -1, dtype=np.int64)
            inv[pmap] = np.arange(len(pmap))
            names.append(name), meshes.append(mesh), labels.append(cls), species.append(cls)
            heads.append((hname, head, cls))
            parent[hname], parent_map[hname], template[hname] = name, pmap, inv[vts]
        for hname, head, _ in heads:  # order: cat, cat_head, horse, horse_head (paper Fig. 7)
            names.append(hname), meshes.append(head), labels.append(f"{cls}_head"), species.append(cls)
        heads.clear()
    ds = HeadDataset(tuple(names), tuple(meshes), np.array(labels), np.array(species), parent, parent_map, template,
                     landmark, radius, full_template)
    if out is not None:
        _write_head_dataset(ds, Path(out))
    return ds


def _write_head_dataset(ds: HeadDataset, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, mesh in zip(ds.names, ds.meshes):
        _save_mesh(mesh, out / f"{name}.off")
    with open(out / "labels.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "class", "species"])
        w.writerows(zip(ds.names, ds.labels.tolist(), ds.species.tolist()))
    for h in ds.parent:
        np.savetxt(out / f"{h}.parent.txt", ds.parent_map[h], fmt="%d")
        np.savetxt(out / f"{h}.template.txt", ds.template[h], fmt="%d")
    for name, t in ds.full_template.items():
        np.savetxt(out / f"{name}.template.txt", t, fmt="%d")
    manifest = {
        "description": "HEAD dataset (Koehl & Orland 2023, section 4.2) built by wpot.paper.head.build_head_dataset",
        "index_base": 0,
        "names": list(ds.names),
        "parent": ds.parent,
        "landmark_template_point": ds.landmark,
        "radius": ds.radius,
        "full_template": sorted(ds.full_template),
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))


def load_head_dataset(folder: str | Path) -> HeadDataset:
    """Read a HEAD dataset written by `build_head_dataset` (``out=``)."""
    folder = Path(folder)
    mf = folder / "manifest.json"
    if not mf.is_file():
        raise ValueError(f"{folder} holds no HEAD dataset (no manifest.json)")
    manifest = json.loads(mf.read_text())
    table = read_label_csv(folder / "labels.csv").for_names(manifest["names"])
    names = tuple(manifest["names"])
    meshes = tuple(_load_mesh(folder / f"{n}.off") for n in names)
    nv = dict(zip(names, (m.n_vertices for m in meshes)))
    pm = {h: load_vertex_map(folder / f"{h}.parent.txt", base=0, n_vertices=nv[p]) for h, p in manifest["parent"].items()}
    tp = {h: np.loadtxt(folder / f"{h}.template.txt", dtype=np.int64, ndmin=1) for h in manifest["parent"]}
    ft = {n: np.loadtxt(folder / f"{n}.template.txt", dtype=np.int64, ndmin=1)
          for n in manifest.get("full_template", [])}
    return HeadDataset(names, meshes, table["class"], table["species"], dict(manifest["parent"]), pm, tp,
                       {k: int(v) for k, v in manifest["landmark_template_point"].items()},
                       {k: float(v) for k, v in manifest["radius"].items()}, ft)


def head_ground_truth(ds: HeadDataset, head: str, target: str, tosca: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth pairs from a head to a full shape of its class (its parent or another pose).

    Returns ``src, dst`` ((K,) int64): head vertex ``src[k]`` corresponds to vertex ``dst[k]`` of ``target``,
    through the TOSCA template (template points that fall outside the head are left out).
    """
    if head not in ds.template:
        raise ValueError(f"{head!r} is not a head of this dataset; heads: {sorted(ds.template)}")
    tmpl = ds.template[head]
    if ds.full_template and target not in ds.full_template:
        raise ValueError(f"{target!r} is not a full shape of this low-resolution HEAD dataset; full shapes: "
                         f"{sorted(ds.full_template)}")
    dst_all = ds.full_template[target] if ds.full_template else tosca_vts(tosca, target)
    if correspondence_group(ds.parent[head]) != correspondence_group(target):
        raise ValueError(f"{head!r} (cut from {ds.parent[head]!r}) and {target!r} share no correspondence template")
    keep = tmpl >= 0
    return tmpl[keep], dst_all[keep]
