"""One configuration for a comparison: which signature, sampler, transport and solver, with their options.

`ComparisonConfig` is the single description of a comparison's settings. The Python API
(`wpot.compare`, `wpot.Comparer`), the command line (its choices and defaults come from the registered
stages), the all-vs-all run key and the workers all build or read this one object:

* ``ComparisonConfig.from_keywords(**kw)`` takes the flat keywords of `wpot.compare` / `wpot.Comparer`
  (``signature="wks", n_eigen=300, max_vertices=500, transport="partial", ...``);
* ``to_dict()`` / ``from_dict()`` round-trip it through plain JSON types (what workers receive);
* ``run_key()`` is the dictionary an all-vs-all run is keyed by (`wpot.runs.store.RunStore`): every setting
  that changes a distance, and only those, so that two runs with the same key can share their results.

Stages (see `wpot.signatures`, `wpot.sampling`, `wpot.ot`) each carry their options in a frozen, validated
dataclass; this module only composes them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

from wpot import _validate
from wpot.sampling import SamplerOptions
from wpot.ot import SolverOptions, SOLVERS
from wpot.signatures import get_signature, signature_names, signature_options

__all__ = ["ComparisonConfig", "TRANSPORTS", "PENALTY_SCALES", "DEFAULT_MASS_PENALTY"]

TRANSPORTS = ("balanced", "partial")
#: how `mass_penalty` is read for partial transport (see `wpot.comparison.solver_mass_penalty`)
PENALTY_SCALES = ("relative", "paper")
#: default relative mass penalty κ (``penalty_scale="relative"``). At κ = 0.01 the region of a whole shape that
#: receives a part's mass has the part's size (benchmarks/head_partial.py); κ ≥ 1 is nearly balanced and
#: κ ≤ 0.003 collapses the plan onto a few pairs.
DEFAULT_MASS_PENALTY = 0.01
#: the comparison's default transport solver: the exact limit beta = infinity, the transport LP for balanced
#: transport and the chi^2 QP for partial transport (`wpot.ot.SOLVERS`)
DEFAULT_METHOD = "auto"

#: keywords of `ComparisonConfig.from_keywords` that are not a stage's own
_SAMPLER_KEYWORDS = tuple(f.name for f in dataclasses.fields(SamplerOptions))


@dataclass(frozen=True)
class ComparisonConfig:
    """Every setting of a comparison (frozen; validated on construction).

    Attributes
    ----------
    signature : a registered signature name (`wpot.signatures.signature_names`: "wks", "ldsift", "hks", ...)
    signature_options : that signature's options dataclass (None: its defaults)
    transport : "balanced" (paper Eq. 6–16) or "partial" (Eq. 17–26, χ² mass penalty)
    sampler : `wpot.sampling.SamplerOptions` (every vertex by default)
    mass_penalty, penalty_scale : partial transport's penalty (`wpot.comparison.solver_mass_penalty`)
    method : the transport solver (`wpot.ot.SOLVERS`: "auto", "exact", "anneal", "ipm")
    solver_options : keyword overrides of `wpot.ot.SolverOptions` (``tol``, ``max_newton``, ...), kept as
        given so that the run key names only what was changed
    match_ratio : a pair (i, j) is matched when ``G(i, j) > match_ratio · m1(i)`` (paper: 0.9)
    """

    signature: str = "wks"
    signature_options: Any = None
    transport: str = "balanced"
    sampler: SamplerOptions = field(default_factory=SamplerOptions)
    mass_penalty: float = DEFAULT_MASS_PENALTY
    penalty_scale: str = "relative"
    method: str = DEFAULT_METHOD
    solver_options: Mapping[str, Any] = field(default_factory=dict)
    match_ratio: float = 0.9

    def __post_init__(self) -> None:

        sig = get_signature(self.signature)
        opts = self.signature_options
        if opts is None:
            opts = sig.Options()
        elif isinstance(opts, Mapping):
            opts = sig.Options(**dict(opts))
        elif not isinstance(opts, sig.Options):
            raise TypeError(f"signature_options for {self.signature!r} must be a {sig.Options.__name__} or a dict, "
                            f"got {type(opts).__name__}")
        object.__setattr__(self, "signature_options", opts)
        _validate.one_of("transport", self.transport, TRANSPORTS)
        if isinstance(self.sampler, Mapping):
            object.__setattr__(self, "sampler", SamplerOptions(**dict(self.sampler)))
        elif not isinstance(self.sampler, SamplerOptions):
            raise TypeError(f"sampler must be a SamplerOptions or a dict, got {type(self.sampler).__name__}")
        object.__setattr__(self, "mass_penalty", _validate.positive_finite("mass_penalty", self.mass_penalty))
        _validate.one_of("penalty_scale", self.penalty_scale, PENALTY_SCALES)
        _validate.one_of("method", self.method, tuple(SOLVERS))
        so = dict(self.solver_options or {})
        if "method" in so:
            raise ValueError("solver_options cannot hold 'method'; give it as method= (ComparisonConfig.from_keywords "
                             "accepts it in solver_options for compatibility)")
        SolverOptions.from_dict(so)  # validates names and values
        object.__setattr__(self, "solver_options", MappingProxyType(dict(sorted(so.items()))))
        mr = _validate.positive_finite("match_ratio", self.match_ratio)
        if not mr <= 1:
            raise ValueError(f"match_ratio must be in (0, 1], got {self.match_ratio!r}")
        object.__setattr__(self, "match_ratio", mr)

    # ----------------------------------------------------------------------------------- construction
    @classmethod
    def from_keywords(cls, *, signature: str = "wks", transport: str = "balanced",
                      mass_penalty: float = DEFAULT_MASS_PENALTY, penalty_scale: str = "relative",
                      solver_options: Mapping[str, Any] | None = None, method: str | None = None,
                      match_ratio: float = 0.9, **keywords: Any) -> "ComparisonConfig":
        """The configuration from `wpot.Comparer`'s flat keywords.

        ``keywords`` holds the sampler's options (``max_vertices``, ``vertices_per_sample``, ``fps_metric``,
        ``pooling``) and the signatures' (``n_eigen``, ``ldsift_slab``, ...: `wpot.signatures.signature_options`;
        options of a signature other than ``signature`` are ignored). ``solver_options`` may hold
        ``method`` (as `wpot.ot.solve_balanced` takes it); ``method=`` wins over it.
        """

        sampler = SamplerOptions(**{k: keywords.pop(k) for k in _SAMPLER_KEYWORDS if k in keywords})
        so = dict(solver_options or {})
        m = so.pop("method", None)
        if method is None:
            method = DEFAULT_METHOD if m is None else m
        sig_opts = signature_options(signature, **keywords)
        return cls(signature=signature, signature_options=sig_opts, transport=transport, sampler=sampler,
                   mass_penalty=mass_penalty, penalty_scale=penalty_scale, method=method, solver_options=so,
                   match_ratio=match_ratio)

    def replace(self, **keyword_changes: Any) -> "ComparisonConfig":
        """A copy with some flat keywords changed (as `from_keywords` takes them)."""
        kw = self.keywords()
        unknown = sorted(set(keyword_changes) - set(kw) - _all_signature_keywords())
        if unknown:
            raise ValueError(f"unknown options {unknown}; known: {sorted(kw)}")
        if "signature" in keyword_changes and keyword_changes["signature"] != self.signature:
            kw = {k: v for k, v in kw.items() if k not in _signature_keywords(self.signature)}
        kw.update(keyword_changes)
        return ComparisonConfig.from_keywords(**kw)

    # ------------------------------------------------------------------------------------ views
    def keywords(self) -> dict[str, Any]:
        """The flat keywords that rebuild this configuration (``from_keywords(**c.keywords()) == c``)."""
        kw: dict[str, Any] = {"signature": self.signature, "transport": self.transport}
        kw.update(self.sampler.to_dict())
        kw.update(mass_penalty=self.mass_penalty, penalty_scale=self.penalty_scale, match_ratio=self.match_ratio)
        so = dict(self.solver_options)
        if self.method != DEFAULT_METHOD:
            so["method"] = self.method
        kw["solver_options"] = so
        kw.update(_flat_signature_options(self.signature, self.signature_options))
        return kw

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types, nested by stage; `from_dict` rebuilds the same configuration."""
        return {
            "signature": self.signature,
            "signature_options": dataclasses.asdict(self.signature_options),
            "transport": self.transport,
            "sampler": self.sampler.to_dict(),
            "mass_penalty": self.mass_penalty,
            "penalty_scale": self.penalty_scale,
            "method": self.method,
            "solver_options": dict(self.solver_options),
            "match_ratio": self.match_ratio,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ComparisonConfig":
        """Inverse of `to_dict`; unknown keys raise `ValueError` naming them."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown configuration keys {unknown}; known: {sorted(known)}")
        return cls(**dict(d))

    def run_key(self) -> dict[str, Any]:
        """What an all-vs-all run is keyed by: the settings that change a distance, as JSON types.

        The layout is that of every run stored so far, so they resume: options that were added later appear
        only when they differ from the value that was implicit before (``vertices_per_sample`` when set, a
        signature's options marked so, e.g. LD-SIFT's slab when not 1), sampling options only when
        sampling is on, the mass penalty only for partial transport, and the solver options as given.
        """
        s = self.sampler
        p: dict[str, Any] = {
            "signature": self.signature,
            "transport": self.transport,
            "max_vertices": s.max_vertices,
            "fps_metric": s.fps_metric if s.subsamples else None,
            "pooling": s.pooling if s.subsamples else None,
            "match_ratio": self.match_ratio,
            "solver_options": dict(sorted(self.keywords()["solver_options"].items())),
        }
        if s.vertices_per_sample is not None:
            p["vertices_per_sample"] = s.vertices_per_sample
        if self.transport == "partial":
            p["mass_penalty"] = self.mass_penalty
            p["penalty_scale"] = self.penalty_scale

        p.update(get_signature(self.signature)(self.signature_options).run_key())
        return p

    def describe(self) -> str:
        """One line for people: the signature, transport, sampling and solver."""

        s = self.sampler
        sampling = "every vertex"
        if s.subsamples:
            parts = []
            if s.max_vertices is not None:
                parts.append(f"at most {s.max_vertices}")
            if s.vertices_per_sample is not None:
                parts.append(f"1 per {s.vertices_per_sample:g} vertices")
            sampling = f"farthest-point samples ({', '.join(parts)}; pooling {s.pooling})"
        penalty = f", mass penalty {self.mass_penalty:g} ({self.penalty_scale})" if self.transport == "partial" else ""
        return (f"{get_signature(self.signature).title}, {self.transport} transport{penalty}, {sampling}, "
                f"solver {self.method}")


def _flat_signature_options(name: str, options: Any) -> dict[str, Any]:
    """A signature's options under their flat keywords (``ldsift_slab``, ``n_eigen``, ...)."""
    out = {}
    for f in dataclasses.fields(options):
        out[f.metadata.get("keyword", f.name)] = getattr(options, f.name)
    return out


def _signature_keywords(name: str) -> set[str]:

    return {f.metadata.get("keyword", f.name) for f in dataclasses.fields(get_signature(name).Options)}


def _all_signature_keywords() -> set[str]:

    out: set[str] = set()
    for n in signature_names():
        out |= _signature_keywords(n)
    return out
