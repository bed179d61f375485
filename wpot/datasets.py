"""Datasets for the paper's experiments (§4): shape lists with class labels, TOSCA ground truth, and HEAD.

* Class labels come from file names (`class_label`: the name without its trailing digits, ``cat10`` ->
  ``cat``) or from a CSV file with a ``name`` column and one or more label levels (`read_label_csv`,
  e.g. genus / family / superfamily for the anatomical datasets of Tables 2-4).
* TOSCA ground truth (`tosca_ground_truth`): line ``i`` of ``corres/A.vts`` and line ``i`` of
  ``corres/B.vts`` (1-based vertex indices) are corresponding vertices, for shapes of one class and also
  for david/michael, which share a template (`correspondence_group`) but are different classes.
* TOSCA8 (`tosca8`, paper §4.1.1): eight classes of TOSCA's low-resolution set, six shapes each, chosen by
  a fixed rule (the paper does not say which six), plus the full set of those classes; `tosca8_draws`
  scores many random choices of six from the full set's distance matrix, so the choice does not drive a
  reported accuracy.
* HEAD (`build_head_dataset`, paper §4.2): the head of every cat and horse of ``tosca_isometric_5k``,
  cut with `wpot.cut` at a region chosen once on a reference shape per class and transferred to the
  other shapes through the ground truth, so that every head of a class is the same part.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from wpot.io import MESH_FORMATS, load_vts

__all__ = [
    "MESH_EXTENSIONS",
    "ShapeSet",
    "LabelTable",
    "class_label",
    "correspondence_group",
    "list_shapes",
    "read_label_csv",
    "read_test_pairs",
    "tosca_vts",
    "tosca_ground_truth",
    "write_shape_list",
]

#: file extensions `list_shapes` picks up in a folder: those `load_mesh` reads
MESH_EXTENSIONS = MESH_FORMATS

#: TOSCA classes that share a correspondence template (``.vts`` lines match across them)
TOSCA_TEMPLATE_GROUPS: dict[str, str] = {"david": "human_male", "michael": "human_male"}

_TRAILING_DIGITS = re.compile(r"[\s_\-.]*\d+$")


# ----------------------------------------------------------------------------- labels and lists
def class_label(name: str | Path) -> str:
    """Class of a shape from its name: the name (no folder, no extension) without trailing digits.

    ``cat10`` -> ``cat``; ``cat_head3`` -> ``cat_head``; ``camel-gallop-01`` -> ``camel-gallop`` (a
    separator ``_``, ``-``, ``.`` or space right before the digits is dropped too).
    """
    stem = Path(str(name)).name
    for ext in MESH_EXTENSIONS:
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    label = _TRAILING_DIGITS.sub("", stem)
    if not label:
        raise ValueError(f"cannot derive a class label from the name {str(name)!r}: it has no non-digit prefix")
    return label


def correspondence_group(name: str) -> str:
    """The ground-truth template a TOSCA shape belongs to: its class, except david/michael share one."""
    label = class_label(name)
    return TOSCA_TEMPLATE_GROUPS.get(label, label)


@dataclass(frozen=True)
class LabelTable:
    """Labels for named shapes at one or more levels (e.g. genus, family).

    ``levels[level][k]`` is the label of ``names[k]``.
    """

    names: tuple[str, ...]
    levels: dict[str, tuple[str, ...]]

    def for_names(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """Labels at every level, reordered to follow ``names``: ``{level: (len(names),) str array}``."""
        pos = {n: k for k, n in enumerate(self.names)}
        missing = [n for n in names if n not in pos]
        if missing:
            raise ValueError(f"{len(missing)} shapes have no row in the label table, e.g. {missing[:5]}")
        idx = np.array([pos[n] for n in names], dtype=np.int64)
        return {lvl: np.asarray(lab, dtype=str)[idx] for lvl, lab in self.levels.items()}


def read_label_csv(path: str | Path) -> LabelTable:
    """Read a label CSV: a header row with a ``name`` column (a shape's file name, with or without its
    extension) and one column per label level; one row per shape.
    """
    path = Path(path)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"label CSV {path} is empty")
    header = [h.strip() for h in rows[0]]
    if "name" not in header:
        raise ValueError(f"label CSV {path} needs a 'name' column in its header row, got columns {header}")
    if len(header) < 2:
        raise ValueError(f"label CSV {path} needs at least one label column besides 'name', got {header}")
    if len(set(header)) != len(header):
        raise ValueError(f"label CSV {path} repeats a column name: {header}")
    ni = header.index("name")
    names: list[str] = []
    cols: dict[str, list[str]] = {h: [] for k, h in enumerate(header) if k != ni}
    for line, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise ValueError(f"label CSV {path} line {line} has {len(r)} fields, expected {len(header)}: {r}")
        names.append(_strip_ext(r[ni].strip()))
        for k, h in enumerate(header):
            if k != ni:
                cols[h].append(r[k].strip())
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"label CSV {path} lists shapes more than once: {dup[:5]}")
    return LabelTable(tuple(names), {h: tuple(v) for h, v in cols.items()})


def _strip_ext(name: str) -> str:
    for ext in MESH_EXTENSIONS:
        if name.lower().endswith(ext):
            return name[: -len(ext)]
    return name


def natural_key(s: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


@dataclass(frozen=True)
class ShapeSet:
    """An ordered list of mesh files with labels.

    ``paths[k]`` has name ``names[k]`` (file name without extension) and label ``labels[level][k]``;
    the level ``"class"`` is always there (from the CSV's first label column, or from the file names).
    """

    paths: tuple[Path, ...]
    names: tuple[str, ...]
    labels: dict[str, np.ndarray] = field(repr=False)

    @property
    def classes(self) -> np.ndarray:
        """(n,) str: the labels at level ``"class"``."""
        return self.labels["class"]

    def __len__(self) -> int:
        return len(self.paths)


def list_shapes(source: str | Path | Iterable[str | Path], *, labels: str | Path | None = None) -> ShapeSet:
    """List the meshes of a dataset, in natural name order (``cat2`` before ``cat10``) for a folder, or in
    the given order for a list, with their class labels.

    Parameters
    ----------
    source : a folder (its files with an extension in `MESH_EXTENSIONS`; not recursive) or a list of paths.
    labels : optional CSV (see `read_label_csv`); its first label column becomes level ``"class"`` as well as
        keeping its own name. Without it the class is `class_label` of each file name.
    """
    if isinstance(source, (str, Path)):
        folder = Path(source)
        if not folder.is_dir():
            raise ValueError(f"shape source must be a folder or a list of mesh files, got {str(source)!r} (not a folder)")
        paths = sorted((p for p in folder.iterdir() if p.suffix.lower() in MESH_EXTENSIONS and p.is_file()),
                       key=lambda p: natural_key(p.stem))
        if not paths:
            raise ValueError(f"no mesh files ({', '.join(MESH_EXTENSIONS)}) in folder {folder}")
    else:
        paths = [Path(p) for p in source]
        if not paths:
            raise ValueError("empty list of meshes")
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise ValueError(f"{len(missing)} mesh files do not exist, e.g. {missing[:3]}")
    names = tuple(p.stem for p in paths)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"several files share a name (shapes are identified by name): {dup[:5]}")
    if labels is None:
        lab = {"class": np.array([class_label(n) for n in names], dtype=str)}
    else:
        table = read_label_csv(labels)
        lab = table.for_names(names)
        first = next(iter(table.levels))
        lab = {"class": lab[first], **lab}
    return ShapeSet(tuple(paths), names, lab)


def read_test_pairs(path: str | Path) -> list[tuple[str, str]]:
    """Read a pair list: one pair of shape names per line, separated by a tab (or other whitespace)."""
    pairs = []
    for line_no, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split("\t") if "\t" in line else line.split()
        parts = [p.strip() for p in parts if p.strip()]
        if len(parts) != 2:
            raise ValueError(f"{path} line {line_no}: expected two shape names, got {line!r}")
        pairs.append((parts[0], parts[1]))
    return pairs


# ----------------------------------------------------------------------------- TOSCA ground truth
def _load_vts(path: Path) -> np.ndarray:
    """A ``.vts`` file as a (K,) int64 array of 0-based vertex indices."""
    return load_vts(path)


def tosca_vts(folder: str | Path, name: str, *, symmetric: bool = False) -> np.ndarray:
    """The correspondence template of a TOSCA shape: (K,) int64, 0-based vertex of ``name`` at template
    point ``i``. ``folder`` is the ``vtx_5k`` folder (with ``corres/``) or its parent. ``symmetric`` reads the
    left/right-flipped template (``<name>.sym.vts``).
    """
    folder = Path(folder)
    corres = folder / "corres" if (folder / "corres").is_dir() else folder / "vtx_5k" / "corres"
    path = corres / f"{name}{'.sym' if symmetric else ''}.vts"
    if not path.is_file():
        raise ValueError(f"no ground-truth file for shape {name!r}: {path} does not exist")
    return _load_vts(path)


def tosca_ground_truth(folder: str | Path, source: str, target: str, *, symmetric: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth vertex pairs between two TOSCA shapes of the same template.

    Returns
    -------
    src, dst : (K,) int64 each; vertex ``src[k]`` of ``source`` corresponds to vertex ``dst[k]`` of ``target``
        (K = 5,000 template points for ``tosca_isometric_5k``; a vertex may appear several times).
        With ``symmetric=True``, ``dst`` is the left/right mirror of the true correspondent.
    """
    ga, gb = correspondence_group(source), correspondence_group(target)
    if ga != gb:
        raise ValueError(f"{source!r} ({ga}) and {target!r} ({gb}) share no correspondence template")
    src = tosca_vts(folder, source)
    dst = tosca_vts(folder, target, symmetric=symmetric)
    if src.shape != dst.shape:
        raise ValueError(f"ground-truth files of {source!r} and {target!r} differ in length: {src.shape} vs {dst.shape}")
    return src, dst


# ----------------------------------------------------------------------------- TOSCA8
#: TOSCA8's classes, in the paper's order (§4.1.1): its four- and two-legged classes and the seahorse
def write_shape_list(shapes: ShapeSet, out: str | Path, stem: str) -> tuple[Path, Path]:
    """Write ``out/<stem>.txt`` (one absolute mesh path per line, the order of ``shapes``) and
    ``out/<stem>_labels.csv`` (``name`` and every label level of ``shapes``), the two files
    ``wpot all-vs-all out/<stem>.txt --labels out/<stem>_labels.csv`` reads. The meshes stay where they are
    (absolute paths, so the list can live anywhere). Returns the two paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lst, lab = out / f"{stem}.txt", out / f"{stem}_labels.csv"
    lst.write_text("".join(f"{Path(p).resolve()}\n" for p in shapes.paths))
    levels = list(shapes.labels)
    with open(lab, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", *levels])
        for k, name in enumerate(shapes.names):
            w.writerow([name, *(str(shapes.labels[lv][k]) for lv in levels)])
    return lst, lab
