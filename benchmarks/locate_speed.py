"""Time of `Comparer.locate` a part, cold and after the whole's one-off set-up (`wpot.maps.locate.prepare_whole`).

Parts: the ``L`` parts (head, limb, cut, holes; ``partial_poses.make_parts``) of ``--sources`` cut from their
``tosca_lowres`` meshes (meshed apart from the library, the check set of `partial_poses.py`), those of at least 20 %
of the area; each is located in ``--target``, another 5k pose of its class. Signatures (LD-SIFT, the comparer's
defaults) and the whole's symmetry are computed before the clock starts. For each part:

* **cold**: nothing of the whole's geodesic distances kept (`wpot.maps.locate.clear_geodesics` first): the time
  a part takes when it is the first located in its whole;
* **prepared**: after `prepare_whole` (every geodesic distance of the whole computed once, timed apart).

The two maps are compared vertex by vertex: the kept distances must not change them.

Usage: ``python benchmarks/locate_speed.py [--pair david0 david6 --pair cat0 cat2 ...]``
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks import partial_poses as pp  # noqa: E402

PAIRS = [("david0", "david6"), ("cat0", "cat2"), ("horse0", "horse5"), ("michael0", "michael5")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tosca", type=Path, default=pp._tosca(Path("../shared/data/tosca_isometric_5k")))
    ap.add_argument("--pair", nargs=2, action="append", metavar=("SOURCE", "TARGET"),
                    help="a source pose (parts are cut from its low-res mesh) and the 5k pose they are located in "
                    "(repeat; default: " + ", ".join(f"{s} {t}" for s, t in PAIRS) + ")")
    a = ap.parse_args(argv)

    import wpot
    from wpot.maps.locate import clear_geodesics, prepare_whole
    from wpot.maps.symmetry import reflection_symmetry

    folder = a.tosca
    if not (folder / "vtx_5k").is_dir():
        ap.error(f"{folder}/vtx_5k not found (set --tosca)")
    members = pp.class_members(folder)
    comparer = wpot.Comparer(signature="ldsift")
    rows = []
    print("| part | vertices | cold | prepared | same map |\n| --- | --- | --- | --- | --- |", flush=True)
    for source, target in a.pair or PAIRS:
        cls = source.rstrip("0123456789")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # TOSCA low-res meshes: a few non-manifold edges
            parts = [p for p in pp.make_parts(folder, source, pp.landmarks(folder, cls, members[cls]), 0,
                                              remesh="lowres") if p.large]
        whole = wpot.load_mesh(folder / "vtx_5k" / f"{target}.off")
        for m in [whole] + [p.mesh for p in parts]:
            comparer.signatures(m)
        reflection_symmetry(whole)
        cold = {}
        for p in parts:
            clear_geodesics()
            t0 = time.perf_counter()
            cold[p.name] = (comparer.locate(p.mesh, whole), time.perf_counter() - t0)
        clear_geodesics()
        t0 = time.perf_counter()
        prepare_whole(whole)
        print(f"| {target}: prepare_whole | {whole.n_vertices} | {time.perf_counter() - t0:.2f} s (once) | | |")
        for p in parts:
            t0 = time.perf_counter()
            pm = comparer.locate(p.mesh, whole)
            t = time.perf_counter() - t0
            same = bool(np.array_equal(pm.correspondence, cold[p.name][0].correspondence))
            rows.append((cold[p.name][1], t, same))
            print(f"| {p.name} | {p.mesh.n_vertices} | {cold[p.name][1]:.2f} s | {t:.2f} s | {'yes' if same else 'NO'} |",
                  flush=True)
        clear_geodesics()
    c, w = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    print(f"\n{len(rows)} parts: cold median {np.median(c):.2f} s, max {c.max():.2f} s; prepared median "
          f"{np.median(w):.2f} s, max {w.max():.2f} s; same maps: {sum(r[2] for r in rows)} of {len(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
