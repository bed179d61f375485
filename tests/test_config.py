"""wpot.config.ComparisonConfig: one configuration for the Python API, the CLI, the run key and the workers;
and a signature added from outside the package, used by every entry point without editing them."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from wpot.config import ComparisonConfig
from wpot.sampling import SamplerOptions

KEYWORD_SETS = [
    {},
    dict(signature="wks", transport="partial", max_vertices=200, pooling="cell", n_eigen=300, n_energies=100,
         scale_invariant=True, mass_penalty=0.05),
    dict(signature="ldsift", transport="partial", vertices_per_sample=20, pooling="cell", ldsift_slab=0.25,
         solver_options={"tol": 1e-8}),
    dict(signature="ldsift", max_vertices=400, solver_options={"method": "ipm"}, match_ratio=0.8),
    dict(signature="hks", hks_n_times=40, n_eigen=120, fps_metric="euclidean", max_vertices=50,
         solver_options={"max_newton": 50, "topk": 6}),
]

#: the run keys the code before ComparisonConfig stored for KEYWORD_SETS[:4] (`Comparer(**kw).params()`), as
#: JSON: runs stored with them must resume, so the layout is a compatibility contract
STORED_RUN_KEYS = [
    '{"fps_metric": null, "match_ratio": 0.9, "max_vertices": null, "n_eigen": 500, "n_energies": 200, "pooling": null, '
    '"scale_invariant": false, "signature": "wks", "solver_options": {}, "transport": "balanced"}',
    '{"fps_metric": "geodesic", "mass_penalty": 0.05, "match_ratio": 0.9, "max_vertices": 200, "n_eigen": 300, '
    '"n_energies": 100, "penalty_scale": "relative", "pooling": "cell", "scale_invariant": true, "signature": "wks", '
    '"solver_options": {}, "transport": "partial"}',
    '{"fps_metric": "geodesic", "ldsift_K": 3.0, "ldsift_resolution": 21, "ldsift_slab": 0.25, "mass_penalty": 0.01, '
    '"match_ratio": 0.9, "max_vertices": null, "penalty_scale": "relative", "pooling": "cell", "signature": "ldsift", '
    '"solver_options": {"tol": 1e-08}, "transport": "partial", "vertices_per_sample": 20.0}',
    '{"fps_metric": "geodesic", "ldsift_K": 3.0, "ldsift_resolution": 21, "match_ratio": 0.8, "max_vertices": 400, '
    '"pooling": "none", "signature": "ldsift", "solver_options": {"method": "ipm"}, "transport": "balanced"}',
]


@pytest.mark.parametrize("kw", KEYWORD_SETS)
def test_round_trips_through_dict_json_and_keywords(kw):
    c = ComparisonConfig.from_keywords(**kw)
    assert ComparisonConfig.from_dict(c.to_dict()) == c
    assert ComparisonConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c  # what workers receive
    assert ComparisonConfig.from_keywords(**c.keywords()) == c
    assert json.loads(json.dumps(c.run_key())) == c.run_key()
    assert c.replace() == c and dataclasses.replace(c) == c


@pytest.mark.parametrize("kw, stored", list(zip(KEYWORD_SETS, STORED_RUN_KEYS)))
def test_run_key_is_the_layout_of_stored_runs(kw, stored):
    assert json.dumps(ComparisonConfig.from_keywords(**kw).run_key(), sort_keys=True) == stored


def test_run_key_tells_apart_what_changes_a_distance_and_nothing_else():
    base = ComparisonConfig.from_keywords(signature="hks", max_vertices=100)
    key = base.run_key()
    for change in (dict(hks_n_times=50), dict(n_eigen=200), dict(max_vertices=120), dict(pooling="cell"),
                   dict(transport="partial"), dict(solver_options={"tol": 1e-8}), dict(match_ratio=0.5),
                   dict(signature="wks")):
        assert base.replace(**change).run_key() != key, change
    # options of another signature do not enter an HKS run's key; a partial-only option not a balanced one's
    assert base.replace(ldsift_slab=0.5).run_key() == key
    assert base.replace(mass_penalty=0.5).run_key() == key
    assert base.replace(transport="partial", mass_penalty=0.5).run_key() != base.replace(transport="partial").run_key()


def test_bad_input_names_the_option():
    with pytest.raises(ValueError, match="unknown configuration keys \\['colour'\\]"):
        ComparisonConfig.from_dict({**ComparisonConfig().to_dict(), "colour": 1})
    with pytest.raises(ValueError, match="transport must be one of"):
        ComparisonConfig(transport="full")
    with pytest.raises(ValueError, match="method must be one of"):
        ComparisonConfig(method="simplex")
    with pytest.raises(ValueError, match="tol"):
        ComparisonConfig(solver_options={"tol": -1.0})
    with pytest.raises(ValueError, match="unknown keys \\['tolerance'\\]|tolerance"):
        ComparisonConfig(solver_options={"tolerance": 1e-8})
    with pytest.raises(ValueError, match="match_ratio must be in \\(0, 1\\]"):
        ComparisonConfig(match_ratio=1.5)
    with pytest.raises(ValueError, match="mass_penalty must be a positive finite number"):
        ComparisonConfig(mass_penalty="0.1")
    with pytest.raises(ValueError, match="signature must be one of"):
        ComparisonConfig(signature="sift")
    with pytest.raises(ValueError, match="max_vertices must be an integer >= 3"):
        ComparisonConfig(sampler=SamplerOptions(max_vertices=2))
    with pytest.raises(TypeError, match="signature_options for 'wks' must be a WKSOptions"):
        ComparisonConfig(signature="wks", signature_options=3)
    with pytest.raises(ValueError, match="unknown options"):
        ComparisonConfig().replace(n_eigens=3)


def test_the_cli_builds_the_same_configuration_as_the_python_keywords():
    from wpot.cli import build_parser, config_from_args

    args = build_parser().parse_args(["compare", "a.off", "b.off", "--signature", "hks", "--hks-n-times", "50",
                                      "--max-vertices", "100", "--pooling", "cell", "--transport", "partial",
                                      "--mass-penalty", "0.1", "--n-eigen", "80", "--ot-method", "auto"])
    assert config_from_args(args) == ComparisonConfig.from_keywords(
        signature="hks", hks_n_times=50, max_vertices=100, pooling="cell", transport="partial", mass_penalty=0.1,
        n_eigen=80)
    demo = build_parser().parse_args(["demo"])  # the demo's smaller spectrum comes in as defaults
    assert config_from_args(demo).signature_options.n_eigen == 100


# ------------------------------------------------------------------------- a signature from outside
def test_a_registered_signature_works_everywhere_without_editing_them(coords, tmp_path):
    import wpot
    from wpot.cli import main
    from wpot.examples import example_pair

    pair = example_pair(80, seed=1, n_target=80)
    # Python: compare, Comparer; the option reaches the signature and the cost is the L2 between coordinates
    c = wpot.compare(pair.source, pair.target, signature="coords", coord_scale=2.0, device="cpu", cache_dir=False)
    half = wpot.compare(pair.source, pair.target, signature="coords", device="cpu", cache_dir=False)
    assert c.signature == "coords" and c.result.converged
    assert c.distance == pytest.approx(2.0 * half.distance, rel=1e-6)  # the optimal plan is scale-free in C
    comparer = wpot.Comparer(signature="coords", coord_scale=2.0, device="cpu", cache_dir=False)
    np.testing.assert_array_equal(comparer.signatures(pair.source), 2.0 * pair.source.vertices)
    assert comparer.params()["signature"] == "coords"
    # the CLI: --signature coords and its flag exist, and compare runs
    for i, m in enumerate((pair.source, pair.target)):
        wpot.save_mesh(m, tmp_path / f"s{i}.ply")
    assert main(["compare", str(tmp_path / "s0.ply"), str(tmp_path / "s1.ply"), "--signature", "coords",
                 "--coord-scale", "2", "--device", "cpu", "--out", str(tmp_path / "cmp")]) == 0
    saved = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert saved["signature"] == "coords" and saved["distance"] == pytest.approx(c.distance, rel=1e-9)
    # all-vs-all: the distance of the pair is the comparison's
    store = wpot.run_all_vs_all(tmp_path, tmp_path / "run", signature="coords", coord_scale=2.0, device="cpu",
                                progress=False)
    with store:
        assert store.params["signature"] == "coords" and store.params["coord_scale"] == 2.0
        assert store.distance_matrix()[0, 1] == pytest.approx(c.distance, rel=1e-9)


def test_a_run_stored_with_the_earlier_key_layout_resumes(tmp_path):
    import wpot
    from wpot.examples import example_mesh
    from wpot.runs.store import RunStore

    meshes = [example_mesh(60, seed=s) for s in range(3)]
    for i, m in enumerate(meshes):
        wpot.save_mesh(m, tmp_path / f"blob{i}.ply")
    folder = tmp_path / "run"
    kw = dict(signature="ldsift", max_vertices=400, solver_options={"method": "ipm"}, match_ratio=0.8)
    # a store as the earlier code left it: its key (STORED_RUN_KEYS[3]) and its shapes, no pair done yet
    specs = wpot.runs.shapes.discover_shapes(tmp_path)
    with RunStore(folder, create=True) as s:
        s.initialize(json.loads(STORED_RUN_KEYS[3]), [(sp.name, sp.path, m.fingerprint, m.n_vertices)
                                                     for sp, m in zip(specs, (sp.load() for sp in specs))], {})
    with wpot.run_all_vs_all(tmp_path, folder, device="cpu", progress=False, **kw) as store:  # no RunMismatchError
        assert len(store.done()) == 3 and store.n_computations == 3
    with pytest.raises(wpot.RunMismatchError, match="match_ratio: stored 0.8, requested 0.9"):
        wpot.run_all_vs_all(tmp_path, folder, device="cpu", progress=False, **{**kw, "match_ratio": 0.9})
