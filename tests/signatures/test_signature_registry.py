"""The signature registry (`wpot.signatures.base`): its contents, options from flat keywords and CLI flags, the
run and cache keys of WKS and LD-SIFT (a compatibility contract with stored runs and caches), fitted state,
and a signature added from outside the package."""
from __future__ import annotations

import argparse
import dataclasses
import json
import pkgutil
import sys

import numpy as np
import pytest

import wpot.signatures
from wpot.cache import cache_key
from wpot.signatures import (
    LDSIFT,
    SIGNATURES,
    WKS,
    Signature,
    SignatureOptions,
    add_signature_arguments,
    get_signature,
    register_signature,
    signature_names,
    signature_options,
    signature_options_from_args,
    unregister_signature,
)
from wpot.signatures._ldsift import LDSIFTOptions
from wpot.signatures._wks import WKSOptions
from wpot.signatures.base import METRICS, option
from wpot.signatures.hks import HKS
from helpers import CoordOptions, Coordinates


# ------------------------------------------------------------------------------ contents
def test_registry_contents():
    assert signature_names() == ("wks", "ldsift", "hks")
    assert dict(SIGNATURES) == {"wks": WKS, "ldsift": LDSIFT, "hks": HKS}
    with pytest.raises(TypeError):
        SIGNATURES["x"] = WKS  # a read-only view: register_signature is the way in
    assert [(c.title, c.metric, c.needs_fit) for c in SIGNATURES.values()] == [
        ("WKS", "wks", True), ("LD-SIFT", "l2", False), ("HKS", "l2", True)]
    from wpot.cost import METRICS as COST_METRICS

    assert METRICS == COST_METRICS
    assert get_signature("ldsift") is LDSIFT
    for bad in ("WKS", "sift", None):
        with pytest.raises(ValueError, match=r"signature must be one of \('wks', 'ldsift', 'hks'\), got"):
            get_signature(bad)


def test_every_module_of_the_package_is_imported():
    """A module that registers itself needs no other edit: the package imports all its modules."""
    for m in pkgutil.iter_modules(wpot.signatures.__path__):
        assert f"wpot.signatures.{m.name}" in sys.modules
    # the names exported before the registry still resolve
    for name in ("ldsift", "local_frames", "LocalFrames", "wks", "wks_energies", "wks_from_eigenpairs", "EnergyGrid"):
        assert getattr(wpot.signatures, name) is not None


# ------------------------------------------------------------------------------ options
def test_signature_options_routes_flat_keywords():
    every = dict(n_eigen=300, n_energies=50, scale_invariant=True, ldsift_K=2, ldsift_resolution=25.0,
                 ldsift_slab=0.25, hks_n_times=10)
    assert signature_options("wks", **every) == WKSOptions(n_eigen=300, n_energies=50, scale_invariant=True)
    o = signature_options("ldsift", **every)
    assert o == LDSIFTOptions(K=2.0, resolution=25, slab=0.25)
    assert type(o.K) is float and type(o.resolution) is int  # the key types of today's keys (3.0, not 3)
    assert signature_options("ldsift", ldsift_slab=None).slab == 1.0  # None: the default slab
    assert signature_options("wks") == WKSOptions()
    with pytest.raises(ValueError, match=r"unknown signature options \['bogus', 'n_eigenn'\] for signature 'wks'; "
                                         r"its options: \['n_eigen', 'n_energies', 'scale_invariant', 'spectral_max_vertices'\]"):
        signature_options("wks", n_eigen=10, bogus=1, n_eigenn=3)
    with pytest.raises(ValueError, match="signature must be one of"):
        signature_options("nope")


def test_options_are_frozen_and_validated():
    o = WKSOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.n_eigen = 3  # type: ignore[misc]
    assert o.replace(n_eigen=40.0).n_eigen == 40 and o.to_dict() == {"n_eigen": 500, "n_energies": 200,
                                                                     "scale_invariant": False, "max_vertices": 10_000}
    assert WKSOptions.from_dict({"n_energies": 30}) == WKSOptions(n_energies=30)
    with pytest.raises(ValueError, match=r"unknown WKSOptions fields \['K'\]"):
        WKSOptions.from_dict({"K": 3})
    with pytest.raises(ValueError, match="n_energies must be an integer > 28"):
        WKSOptions(n_energies=28)
    with pytest.raises(ValueError, match="n_eigen must be an integer >= 10, got 2.5"):
        WKSOptions(n_eigen=2.5)
    with pytest.raises(ValueError, match="scale_invariant must be True or False, got 'yes'"):
        WKSOptions(scale_invariant="yes")
    for bad in (0, -1.0, float("nan"), True, "thin"):
        with pytest.raises(ValueError, match="slab must be"):
            LDSIFTOptions(slab=bad)
    with pytest.raises(ValueError, match="K must be a positive finite number, got -1"):
        LDSIFTOptions(K=-1)
    with pytest.raises(ValueError, match="resolution must be an integer >= 8, got 4"):
        LDSIFTOptions(resolution=4)


# ------------------------------------------------------------------------------ CLI
def test_cli_arguments_from_the_option_metadata():
    p = argparse.ArgumentParser()
    add_signature_arguments(p)  # argparse refuses a flag added twice: shared flags come once
    a = p.parse_args([])
    # the names and defaults today's CLI reads (a.n_eigen, ...)
    assert (a.n_eigen, a.n_energies, a.scale_invariant, a.ldsift_slab, a.hks_n_times) == (500, 200, False, 1.0, 100)
    assert not hasattr(a, "ldsift_K") and not hasattr(a, "ldsift_resolution")  # keyword-only options
    text = " ".join(p.format_help().split())
    assert "WKS, HKS: Laplace-Beltrami eigenpairs (default 500)" in text
    assert "WKS: energies (default 200)" in text and "LD-SIFT: half-thickness of the depth slab" in text
    a = p.parse_args(["--n-eigen", "120", "--scale-invariant", "--ldsift-slab", "0.25", "--hks-n-times", "12"])
    assert signature_options_from_args("wks", a) == WKSOptions(n_eigen=120, scale_invariant=True)
    assert signature_options_from_args("ldsift", a) == LDSIFTOptions(slab=0.25)
    assert signature_options_from_args("hks", a) == HKS.Options(n_eigen=120, n_times=12, scale_invariant=True)
    # defaults by keyword (the demo's smaller settings)
    demo = argparse.ArgumentParser()
    add_signature_arguments(demo, defaults={"n_eigen": 100, "n_energies": 100})
    assert "(default 100)" in demo.format_help()
    assert signature_options_from_args("wks", demo.parse_args([])) == WKSOptions(n_eigen=100, n_energies=100)
    with pytest.raises(ValueError, match=r"defaults names \['ldsift_K'\], which are not signature options with a CLI flag"):
        add_signature_arguments(argparse.ArgumentParser(), defaults={"ldsift_K": 2.0})


# ------------------------------------------------------------------------------ keys: the compatibility contract
def _json(d: dict) -> str:
    return json.dumps(d, sort_keys=True)


def test_wks_and_ldsift_keys_are_those_of_stored_runs_and_caches():
    """The literal keys (and the signature cache's hashes) of the code before the registry: stored runs resume
    and cached signatures are found. Compared as JSON, so 3 and 3.0 differ as they do in a key."""
    w = WKS()
    assert _json(w.run_key()) == '{"n_eigen": 500, "n_energies": 200, "scale_invariant": false}'
    assert _json(w.params()) == ('{"energies": null, "n_eigen": 500, "n_energies": 200, "scale_invariant": false, '
                                 '"signature": "wks", "version": 2}')
    assert cache_key("signatures", "fp", w.params()) == "4a2a9a0ecf3a876f3b785f50fbe335375c5040d7"
    w = WKS(signature_options("wks", n_eigen=30, n_energies=40, scale_invariant=True), state={"energies": [0.5, 1.25, 2.0]})
    assert _json(w.run_key()) == '{"n_eigen": 30, "n_energies": 40, "scale_invariant": true}'
    p = w.params()
    assert isinstance(p["energies"], np.ndarray) and p["energies"].tolist() == [0.5, 1.25, 2.0]
    assert _json({**p, "energies": p["energies"].tolist()}) == (
        '{"energies": [0.5, 1.25, 2.0], "n_eigen": 30, "n_energies": 40, "scale_invariant": true, "signature": "wks", '
        '"version": 2}')
    assert cache_key("signatures", "fp", p) == "4b42b17d4bbdd5df5163b43bb0b0800525fae077"
    s = LDSIFT()
    assert _json(s.run_key()) == '{"ldsift_K": 3.0, "ldsift_resolution": 21}'  # slab 1.0 (the default) is absent
    assert _json(s.params()) == '{"K": 3.0, "resolution": 21, "signature": "ldsift", "version": 1}'
    assert cache_key("signatures", "fp", s.params()) == "1feea9e3a9f9a35326fea2dc36ab4cddde4fe449"
    s = LDSIFT(signature_options("ldsift", ldsift_K=2, ldsift_resolution=25, ldsift_slab=0.25))
    assert _json(s.run_key()) == '{"ldsift_K": 2.0, "ldsift_resolution": 25, "ldsift_slab": 0.25}'
    assert _json(s.params()) == '{"K": 2.0, "resolution": 25, "signature": "ldsift", "slab": 0.25, "version": 1}'
    assert cache_key("signatures", "fp", s.params()) == "e9dcb29ce8ccdbaaec12d1cfdef37c94deb87695"
    s = LDSIFT(signature_options("ldsift", ldsift_orientation="gradient"))  # named only when not the paper's
    assert _json(s.run_key()) == '{"ldsift_K": 3.0, "ldsift_orientation": "gradient", "ldsift_resolution": 21}'
    assert _json(s.params()) == ('{"K": 3.0, "orientation": "gradient", "resolution": 21, "signature": "ldsift", '
                                 '"version": 1}')


# ------------------------------------------------------------------------------ state
def test_state_round_trip_and_validation():
    w = WKS(state={"energies": np.array([1.0, 2.0, 4.0])})
    assert w.fitted and w.state() == {"energies": [1.0, 2.0, 4.0]}
    assert not w.energies.flags.writeable
    copy = w.with_state(w.state())
    assert copy is not w and copy.options is w.options and copy.state() == w.state()
    assert copy.params()["energies"].tolist() == w.params()["energies"].tolist()
    assert copy.key() == w.key() != w.with_state({"energies": [1.0, 2.0, 4.5]}).key() != WKS().key()
    assert w.with_state(None).state() is None and not w.with_state(None).fitted
    w.set_state(None)
    assert not w.fitted and w.params()["energies"] is None
    for bad in ([1.0], [2.0, 1.0], [1.0, 1.0], [0.0, np.inf]):
        with pytest.raises(ValueError, match="energies must be a finite increasing grid of at least 2 values"):
            WKS(state={"energies": bad})
    with pytest.raises(ValueError, match=r"has the keys \['energies'\], got \['times'\]"):
        WKS(state={"times": [1.0, 2.0]})
    with pytest.raises(TypeError, match="state must be a mapping"):
        WKS(state=[1.0, 2.0])
    with pytest.raises(TypeError, match="options must be a WKSOptions, got LDSIFTOptions"):
        WKS(LDSIFTOptions())
    # nothing to fit: always fitted, no state, fitting is a no-op
    s = LDSIFT()
    s.fit([object()])
    assert s.fitted and s.state() is None and s.fit_input(object()) is None
    with pytest.raises(ValueError, match=r"has the keys \[\]"):
        LDSIFT(state={"energies": [1.0, 2.0]})


# ------------------------------------------------------------------------------ a signature from outside






def test_a_new_signature_registers_and_is_found(coords):
    from wpot.examples import example_mesh

    assert signature_names()[-1] == "coords" and get_signature("coords") is coords
    o = signature_options("coords", coord_scale=2.0, n_eigen=30, n_energies=50, ldsift_slab=0.5)
    assert o == CoordOptions(scale=2.0, n_eigen=30)
    p = argparse.ArgumentParser()
    add_signature_arguments(p)
    assert "WKS, HKS, Coordinates: Laplace-Beltrami eigenpairs" in " ".join(p.format_help().split())
    a = p.parse_args(["--coord-scale", "3"])
    assert signature_options_from_args("coords", a).scale == 3.0
    sig = coords(signature_options_from_args("coords", a))
    mesh = example_mesh(60)
    np.testing.assert_array_equal(sig(mesh), 3.0 * mesh.vertices)
    assert sig.run_key() == {"coord_scale": 3.0, "n_eigen": 500}
    assert sig.params() == {"signature": "coords", "scale": 3.0, "n_eigen": 500, "version": 1}
    # its keyword is known to the other signatures' routing (ignored there), and gone once unregistered
    assert signature_options("wks", coord_scale=2.0) == WKSOptions()


def test_unregistered_signature_is_gone():
    register_signature(Coordinates)
    assert unregister_signature("coords") is Coordinates
    assert "coords" not in SIGNATURES
    with pytest.raises(ValueError, match=r"unknown signature options \['coord_scale'\]"):
        signature_options("wks", coord_scale=2.0)
    with pytest.raises(ValueError, match="no signature named 'coords' is registered"):
        unregister_signature("coords")


def test_registration_checks(coords):
    def make(**attrs):
        return type("Bad", (Signature,), {"name": "bad", "title": "Bad", "metric": "l2", "version": 1,
                                          "Options": CoordOptions, **attrs})

    with pytest.raises(ValueError, match="metric must be one of"):
        register_signature(make(metric="cosine"))
    with pytest.raises(ValueError, match="a signature named 'wks' is already registered"):
        register_signature(make(name="wks"))
    with pytest.raises(TypeError, match="state_keys must be non-empty exactly when needs_fit"):
        register_signature(make(needs_fit=True))

    @dataclasses.dataclass(frozen=True)
    class OtherDefault(SignatureOptions):
        n_eigen: int = option(300, keyword="n_eigen", flag="--n-eigen")

    with pytest.raises(ValueError, match="keyword 'n_eigen' is shared with signature 'wks', so it must have the same"):
        register_signature(make(Options=OtherDefault))

    @dataclasses.dataclass(frozen=True)
    class FlagClash(SignatureOptions):
        slab: float = option(1.0, keyword="bad_slab", flag="--ldsift-slab")

    with pytest.raises(ValueError, match="flag '--ldsift-slab' already belongs to the keyword 'ldsift_slab'"):
        register_signature(make(Options=FlagClash))

    @dataclasses.dataclass(frozen=True)
    class Plain(SignatureOptions):
        x: int = 1

    with pytest.raises(TypeError, match=r"lacks the option metadata"):
        register_signature(make(Options=Plain))
    with pytest.raises(TypeError, match="expects a Signature subclass"):
        register_signature(object)
    assert signature_names() == ("wks", "ldsift", "hks", "coords")  # nothing half-registered
    # registering a class again under its name (a module reloaded) keeps one entry
    assert register_signature(HKS) is HKS
    assert signature_names() == ("wks", "ldsift", "hks", "coords") and get_signature("hks") is HKS
