"""The shapes of a run: a folder of meshes or a list file (`discover_shapes`, `read_mesh_list`), each a
`ShapeSpec` that loads itself, and repeated shapes named."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence


from wpot.mesh import Mesh

__all__ = ["ShapeSpec", "discover_shapes", "read_mesh_list", "repeated_shapes", "warn_repeated_shapes"]

@dataclass(frozen=True)
class ShapeSpec:
    """One shape of a dataset: its name, where it comes from (a file, or arrays), and its labels."""

    name: str
    path: str | None = None
    mesh: Mesh | None = None
    labels: Mapping[str, str] | None = None

    def load(self, *, warn: bool = True) -> Mesh:
        """The mesh (read from ``path``; ``warn=False`` reads it without the `MeshWarning` about its defects)."""
        if self.mesh is not None:
            return self.mesh
        from wpot.io import load_mesh

        return load_mesh(self.path, warn=warn)


def read_mesh_list(path: str | Path) -> list[Path]:
    """The mesh paths a list file names: one per line, ``#`` starts a comment, a relative path is relative to
    the list's folder."""
    p = Path(path)
    out = []
    for line in p.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            q = Path(line)
            out.append(q if q.is_absolute() else p.parent / q)
    return out


def discover_shapes(
    source: str | Path | Sequence[str | Path | Mesh], *, labels: str | Path | None = None
) -> list[ShapeSpec]:
    """The shapes of a dataset, in a stable order, with their labels (through `wpot.datasets.list_shapes`).

    ``source`` is a folder (mesh files in natural name order, not recursive), a text file listing one mesh
    path per line (relative paths are relative to the list; ``#`` starts a comment), or a sequence of paths
    or `Mesh` objects (meshes are named ``shape0000``, ... and have no labels). ``labels`` is a label CSV
    (`wpot.datasets.read_label_csv`); without it the level "class" comes from the file names.
    """
    from wpot.datasets import MESH_EXTENSIONS, list_shapes

    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS:
            raise ValueError(f"an all-vs-all needs a folder or a list of meshes, got the single mesh {str(p)!r}")
        if p.is_file():
            source = read_mesh_list(p)
        elif not p.is_dir():
            raise FileNotFoundError(f"no such folder or list file: {str(p)!r}")
    else:
        source = list(source)
    if not isinstance(source, (str, Path)) and source and all(isinstance(m, Mesh) for m in source):
        if labels is not None:
            raise ValueError("labels from a CSV need named shapes (files); got Mesh objects")
        specs = [ShapeSpec(f"shape{k:04d}", None, m, {}) for k, m in enumerate(source)]
    else:
        if not isinstance(source, (str, Path)) and any(isinstance(m, Mesh) for m in source):
            raise ValueError("give either mesh files or Mesh objects, not a mix")
        ss = list_shapes(source, labels=labels)
        specs = [
            ShapeSpec(name, str(Path(path).resolve()), None, {lv: str(lab[k]) for lv, lab in ss.labels.items()})
            for k, (name, path) in enumerate(zip(ss.names, ss.paths))
        ]
    if len(specs) < 2:
        raise ValueError(f"an all-vs-all needs at least 2 shapes, got {len(specs)}")
    return specs


# ----------------------------------------------------------------------------------------------- store


def repeated_shapes(names: Sequence[str], fingerprints: Sequence[str]) -> list[list[str]]:
    """The groups of ``names`` whose meshes are the same (equal `Mesh.fingerprint`: the same vertices and
    triangles), in order; [] when every mesh is distinct. TOSCA's low-resolution set has two such pairs,
    victoria0 / victoria1 and victoria13 / victoria22."""
    groups: dict[str, list[str]] = {}
    for name, fp in zip(names, fingerprints):
        groups.setdefault(fp, []).append(name)
    return [g for g in groups.values() if len(g) > 1]


def warn_repeated_shapes(names: Sequence[str], fingerprints: Sequence[str]) -> None:
    """Warn about the `repeated_shapes` among ``names``: their distance is 0, so each is the other's nearest
    neighbour and classification scores come out flattered (said by `run_all_vs_all` and by `wpot classify`)."""
    groups = repeated_shapes(names, fingerprints)
    if groups:
        warnings.warn(f"these shapes are the same mesh (the same vertices and triangles): "
                      f"{'; '.join(' = '.join(g) for g in groups)}. Their distance is 0, so each is the other's "
                      "nearest neighbour, which flatters leave-one-out and one-shot scores; leave out all but one "
                      "of each", UserWarning, stacklevel=3)
