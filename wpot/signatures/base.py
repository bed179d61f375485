"""What a per-vertex signature is, the registry of signatures, and their options as flat keywords and CLI flags.

A signature is a class derived from `Signature` that calls `register_signature` when its module is imported.
`wpot.signatures` imports every module of its package, so one new file is all it takes to add a signature:
`wpot.compare(a, b, signature=name)`, `wpot.Comparer`, the CLI (``--signature name`` and the signature's flags)
and all-vs-all runs find it through `get_signature`.

Options
-------
Each signature has a frozen ``Options`` dataclass (derived from `SignatureOptions`, validated in
``__post_init__``). Every field is made with `option`, whose metadata says how the rest of the package spells it:

* ``keyword``: the flat keyword of `wpot.Comparer` and `wpot.compare` (``"n_eigen"``, ``"ldsift_K"``). Two
  signatures may share one keyword (WKS and HKS share ``n_eigen`` and ``scale_invariant``); they must then
  share its flag and its default too, checked by `register_signature`, so a flat keyword and a flag mean one
  thing whatever the signature;
* ``flag``: the CLI flag (``"--n-eigen"``), or None for options that are keyword-only;
* ``help``: one line for the CLI; ``{default}`` in it is replaced by the default in force;
* ``key_omit_default``: the run key (`Signature.run_key`) and the cache key (`Signature.params`) carry the
  option only when it differs from its default, so runs and caches made before the option existed keep
  their keys.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
from types import MappingProxyType
from typing import Any, ClassVar, Iterable, Mapping, Sequence

import numpy as np
from wpot.cache import Cache, canonical_json

__all__ = [
    "Signature",
    "SignatureOptions",
    "option",
    "option_fields",
    "register_signature",
    "unregister_signature",
    "SIGNATURES",
    "get_signature",
    "signature_names",
    "signature_options",
    "add_signature_arguments",
    "signature_options_from_args",
    "METRICS",
]

#: the cost metrics a signature may name; the same names as `wpot.cost.METRICS` (not imported here: that module
#: imports Warp, and a signature's module must stay cheap to import)
METRICS = ("wks", "l2", "l1")

_META_KEYS = ("keyword", "flag", "help", "key_omit_default")


def option(default: Any, *, keyword: str, flag: str | None = None, help: str = "", key_omit_default: bool = False) -> Any:
    """A field of a signature's ``Options`` dataclass, with the metadata described in the module docstring.

    Parameters
    ----------
    default : the value used when the option is not given (an immutable value: int, float, bool, str, None).
    keyword : the flat keyword (`wpot.Comparer`, `wpot.compare`, `signature_options`).
    flag : the CLI flag, e.g. ``"--n-eigen"``; None for no flag. A bool option with a flag is a switch
        (``action="store_true"``); other flags take a value of the default's type.
    help : the CLI help line; ``{default}`` is replaced by the default in force.
    key_omit_default : the run and cache keys carry the option only when it differs from ``default``.
    """
    if not isinstance(keyword, str) or not keyword.isidentifier():
        raise ValueError(f"keyword must be a Python identifier, got {keyword!r}")
    if flag is not None and (not isinstance(flag, str) or not flag.startswith("--")):
        raise ValueError(f"flag must be None or a string starting with '--', got {flag!r}")
    return dataclasses.field(
        default=default,
        metadata={"keyword": keyword, "flag": flag, "help": str(help), "key_omit_default": bool(key_omit_default)},
    )


@dataclasses.dataclass(frozen=True)
class SignatureOptions:
    """Base class of the signatures' frozen option dataclasses (fields made with `option`)."""

    def replace(self, **changes: Any) -> "SignatureOptions":
        """A copy with some fields changed (by field name), validated again."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every field by field name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "SignatureOptions":
        """Options from a mapping by field name; a `ValueError` names unknown keys and lists the known ones."""
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"unknown {cls.__name__} fields {unknown}; known: {known}")
        return cls(**values)


def option_fields(options_cls: type) -> tuple[dataclasses.Field, ...]:
    """The fields of an ``Options`` dataclass, checked to carry the metadata of `option`."""
    if not (isinstance(options_cls, type) and dataclasses.is_dataclass(options_cls)):
        raise TypeError(f"Options must be a dataclass, got {options_cls!r}")
    out = dataclasses.fields(options_cls)
    for f in out:
        missing = [k for k in _META_KEYS if k not in f.metadata]
        if missing:
            raise TypeError(f"{options_cls.__name__}.{f.name} lacks the option metadata {missing}; declare it with option()")
    return out


class Signature:
    """A per-vertex shape signature: a callable ``mesh -> (N, d) float64``, plus what the rest of the package
    needs to cache, compare and configure it.

    Class attributes (set by each subclass)
    ---------------------------------------
    name : the registry key, e.g. ``"wks"``.
    title : the printed name, e.g. ``"WKS"``.
    metric : the cost between two vertices' signatures, for `wpot.cost.cost_matrix` and ``FeatureCost``:
        ``"wks"`` (paper Eq. 29), ``"l2"`` or ``"l1"``.
    version : bumped whenever the signature's values change; part of the cache key (`params`), so cached
        signatures of an older version are not reused.
    Options : the frozen `SignatureOptions` dataclass of the signature's settings.
    needs_fit : True when the signature has dataset-wide state (WKS's energy grid, HKS's times) that must be
        fitted (`fit`, `fit_from`) or given (``state``) before it is evaluated.
    state_keys : the keys of `state` (e.g. ``("energies",)``); empty when ``needs_fit`` is False.

    Parameters
    ----------
    options : an instance of ``Options``; None uses the defaults.
    device : the Warp device for signatures computed with Warp (None: Warp's default device).
    spectrum_cache : where Laplace-Beltrami spectra are cached, as the ``cache`` argument of
        `wpot.spectral.eigenpairs` (True: the process-wide cache; a `wpot.cache.Cache`; False: none).
    state : the fitted state, as returned by `state` (e.g. ``{"energies": [...]}``), or None (not fitted).

    Fitting
    -------
    Dataset-wide state is fitted from one small summary per shape: `fit_input` (computed where the mesh is,
    e.g. in a worker process; picklable) and `fit_from` (over all summaries). `fit` does both. For a signature
    with nothing to fit, all three are no-ops and `fitted` is always True.
    """

    name: ClassVar[str]
    title: ClassVar[str]
    metric: ClassVar[str]
    version: ClassVar[int]
    Options: ClassVar[type]
    needs_fit: ClassVar[bool] = False
    state_keys: ClassVar[tuple[str, ...]] = ()

    def __init__(self, options: Any = None, *, device: str | None = None, spectrum_cache: Any = True,
                 state: Mapping[str, Any] | None = None) -> None:
        if options is None:
            options = self.Options()
        elif not isinstance(options, self.Options):
            raise TypeError(f"options must be a {self.Options.__name__}, got {type(options).__name__}")
        if device is not None and not isinstance(device, str):
            raise TypeError(f"device must be a string such as 'cpu' or 'cuda:0', or None, got {type(device).__name__}")
        if not isinstance(spectrum_cache, bool):

            if not isinstance(spectrum_cache, Cache):
                raise TypeError(f"spectrum_cache must be True, False or a wpot.cache.Cache, got {type(spectrum_cache).__name__}")
        self.options = options
        self.device = device
        self.spectrum_cache = spectrum_cache
        self._state: dict[str, np.ndarray] | None = None
        self.set_state(state)

    # ------------------------------------------------------------------------------ state
    @classmethod
    def check_state(cls, state: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """``state`` validated and converted (read-only float64 arrays by key); a `ValueError` otherwise.

        The base checks the keys against ``state_keys``; subclasses check the values (calling this first).
        """
        if not isinstance(state, Mapping):
            raise TypeError(f"state must be a mapping such as {{{', '.join(repr(k) + ': [...]' for k in cls.state_keys)}}}, "
                            f"got {type(state).__name__}")
        if set(state) != set(cls.state_keys):
            raise ValueError(f"the state of {cls.title} has the keys {list(cls.state_keys)}, got {sorted(state)}")
        out = {}
        for k in cls.state_keys:
            a = np.asarray(state[k], dtype=np.float64).ravel().copy()
            a.setflags(write=False)
            out[k] = a
        return out

    @property
    def fitted(self) -> bool:
        """True when the signature can be evaluated: nothing to fit, or the state is set."""
        return not self.needs_fit or self._state is not None

    def set_state(self, state: Mapping[str, Any] | None) -> None:
        """Set the fitted state (validated by `check_state`), or clear it with None."""
        self._state = None if state is None else self.check_state(state)

    def state_array(self, key: str) -> np.ndarray | None:
        """One entry of the fitted state, a read-only float64 array, or None when unfitted."""
        if key not in self.state_keys:
            raise ValueError(f"the state of {self.title} has the keys {list(self.state_keys)}, got {key!r}")
        return None if self._state is None else self._state[key]

    def state(self) -> dict[str, list[float]] | None:
        """The fitted state as JSON-able lists by key (what a run stores), or None (unfitted, or nothing to fit)."""
        if self._state is None:
            return None
        return {k: v.tolist() for k, v in self._state.items()}

    def with_state(self, state: Mapping[str, Any] | None) -> "Signature":
        """A copy with the same options, device and spectrum cache, carrying ``state`` (validated; None: unfitted)."""
        return type(self)(self.options, device=self.device, spectrum_cache=self.spectrum_cache, state=state)

    def fit_input(self, mesh: Any) -> Any:
        """The per-shape summary `fit_from` needs (small and picklable); None for a signature with nothing to fit."""
        return None

    def fit_from(self, inputs: Sequence[Any]) -> None:
        """Set the fitted state from the `fit_input` summaries of every shape of a dataset; a no-op by default."""
        return None

    def fit(self, meshes: Iterable[Any]) -> None:
        """Fit the dataset-wide state to ``meshes``: ``fit_from([fit_input(m) for m in meshes])``."""
        if not self.needs_fit:
            return
        self.fit_from([self.fit_input(m) for m in meshes])

    def check_fitted(self) -> None:
        """A `ValueError` saying how to fit, when the signature needs a fit and has none."""
        if not self.fitted:
            raise ValueError(
                f"{self.title} is not fitted: call fit(meshes), or fit_from(...) with the fit_input of every shape, "
                f"or pass state={{{', '.join(repr(k) + ': ...' for k in self.state_keys)}}}"
            )

    # ------------------------------------------------------------------------------ keys
    def params(self) -> dict[str, Any]:
        """The signature cache key's parameters: ``signature`` (the name), every option by field name (those with
        ``key_omit_default`` only when not at their default), the state arrays by key (None when unfitted) and
        ``version``."""
        p: dict[str, Any] = {"signature": self.name}
        for f in option_fields(self.Options):
            value = getattr(self.options, f.name)
            if not (f.metadata["key_omit_default"] and value == f.default):
                p[f.name] = value
        for k in self.state_keys:
            p[k] = None if self._state is None else self._state[k]
        p["version"] = self.version
        return p

    def key(self) -> str:
        """`params` as canonical JSON (`wpot.cache.canonical_json`, floats exact): equal strings exactly when two
        signatures compute the same values. Compare these, not `params` dicts, whose state arrays do not compare
        with ``==``."""

        return canonical_json(self.params())

    def run_key(self) -> dict[str, Any]:
        """The signature's entries in a run's parameter key: every option by flat keyword (those with
        ``key_omit_default`` only when not at their default)."""
        p: dict[str, Any] = {}
        for f in option_fields(self.Options):
            value = getattr(self.options, f.name)
            if not (f.metadata["key_omit_default"] and value == f.default):
                p[f.metadata["keyword"]] = value
        return p

    # ------------------------------------------------------------------------------ evaluation
    def __call__(self, mesh: Any) -> np.ndarray:
        """(N, d) float64 signatures of every vertex of ``mesh`` (uncached); a `ValueError` when not fitted."""
        raise NotImplementedError

    # ------------------------------------------------------------------------------ cached pieces
    def pieces(self) -> dict[str, dict[str, Any]]:
        """The pieces the signature is cached as, by name, each with its own cache key (the ``params`` of
        `wpot.cache.Cache`). `wpot.Comparer.signatures` caches each piece under its key, computes the missing
        ones in one `compute_pieces` call and joins them (`assemble`), so that settings that only change how
        the pieces are joined reuse the cached pieces: LD-SIFT with and without its thickness column, or at two
        weights of it, shares one descriptor. The default is one piece, ``"signature"``: the whole signature
        under `params`."""
        return {"signature": self.params()}

    def compute_pieces(self, mesh: Any, names: Sequence[str]) -> dict[str, np.ndarray]:
        """The pieces ``names`` (keys of `pieces`) of ``mesh``, uncached, by name; in one call, so that work the
        pieces share is done once. By default the whole signature."""
        if list(names) != ["signature"]:
            raise ValueError(f"{self.title} has one cached piece, 'signature'; got {list(names)}")
        return {"signature": self(mesh)}

    def assemble(self, pieces: Mapping[str, np.ndarray]) -> np.ndarray:
        """The (N, d) signature from its pieces by name (as `pieces` names them); by default the one piece."""
        return pieces["signature"]

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.to_dict().items())
        fit = ""
        if self.needs_fit:
            fit = ", not fitted" if self._state is None else ", fitted: " + ", ".join(
                f"{len(v)} {k}" for k, v in self._state.items())
        dev = "" if self.device is None else f", device={self.device!r}"
        return f"{type(self).__name__}({opts}{dev}{fit})"

    def __copy__(self) -> "Signature":
        return self.with_state(None if self._state is None else dict(self._state))

    def __deepcopy__(self, memo: dict) -> "Signature":
        return copy.copy(self)


# ---------------------------------------------------------------------------------------------- registry
_REGISTRY: dict[str, type[Signature]] = {}
#: the registered signature classes by name, in registration order (a read-only view; use `register_signature`)
SIGNATURES: Mapping[str, type[Signature]] = MappingProxyType(_REGISTRY)


def _keyword_table(exclude: str | None = None) -> dict[str, tuple[str, dataclasses.Field]]:
    """keyword -> (signature name, field) over the registered signatures (the first that declares it)."""
    table: dict[str, tuple[str, dataclasses.Field]] = {}
    for name, cls in _REGISTRY.items():
        if name == exclude:
            continue
        for f in option_fields(cls.Options):
            table.setdefault(f.metadata["keyword"], (name, f))
    return table


def register_signature(cls: type[Signature]) -> type[Signature]:
    """Add a `Signature` subclass to `SIGNATURES` under ``cls.name`` and return it (usable as a decorator).

    Checked here, so that a bad signature fails at import: the class attributes (``name`` an identifier not yet
    taken by another class, ``metric`` one of `METRICS`, an int ``version``, ``Options`` a frozen dataclass
    whose fields carry `option` metadata, ``state_keys`` non-empty exactly when ``needs_fit``), and that a
    keyword or flag shared with another registered signature means the same option (same keyword, flag,
    default). Registering a class again under its name (a module reloaded) replaces it.
    """
    if not (isinstance(cls, type) and issubclass(cls, Signature)):
        raise TypeError(f"register_signature expects a Signature subclass, got {cls!r}")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{cls.__qualname__}.name must be an identifier such as 'wks', got {name!r}")
    for attr in ("title", "metric", "version", "Options"):
        if not hasattr(cls, attr):
            raise TypeError(f"{cls.__qualname__} lacks the class attribute {attr!r}")
    if cls.metric not in METRICS:
        raise ValueError(f"{cls.__qualname__}.metric must be one of {METRICS}, got {cls.metric!r}")
    if isinstance(cls.version, bool) or not isinstance(cls.version, int):
        raise TypeError(f"{cls.__qualname__}.version must be an int, got {cls.version!r}")
    if not (dataclasses.is_dataclass(cls.Options) and cls.Options.__dataclass_params__.frozen):
        raise TypeError(f"{cls.__qualname__}.Options must be a frozen dataclass")
    fields = option_fields(cls.Options)
    if bool(cls.needs_fit) != bool(cls.state_keys):
        raise TypeError(f"{cls.__qualname__}: state_keys must be non-empty exactly when needs_fit is True")
    old = _REGISTRY.get(name)
    if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"a signature named {name!r} is already registered ({old.__module__}.{old.__qualname__})")
    seen: set[str] = set()
    others = _keyword_table(exclude=name)
    flags = {f.metadata["flag"]: (n, f) for n, f in others.values() if f.metadata["flag"] is not None}
    for f in fields:
        kw, flag = f.metadata["keyword"], f.metadata["flag"]
        if kw in seen:
            raise ValueError(f"{cls.__qualname__}.Options declares the keyword {kw!r} twice")
        seen.add(kw)
        if kw in others:
            other, g = others[kw]
            if g.metadata["flag"] != flag or g.default != f.default or type(g.default) is not type(f.default):
                raise ValueError(
                    f"{cls.__qualname__}: the keyword {kw!r} is shared with signature {other!r}, so it must have the same "
                    f"flag and default there (got flag {flag!r}, default {f.default!r}; {other!r} has flag "
                    f"{g.metadata['flag']!r}, default {g.default!r})"
                )
        elif flag is not None and flag in flags:
            other, g = flags[flag]
            raise ValueError(f"{cls.__qualname__}: the flag {flag!r} already belongs to the keyword "
                             f"{g.metadata['keyword']!r} of signature {other!r}")
    _REGISTRY[name] = cls
    return cls


def unregister_signature(name: str) -> type[Signature]:
    """Remove a signature from `SIGNATURES` and return its class (the seam that lets a test or a plugin add a
    signature for a while and take it away); a `ValueError` when no signature has that name."""
    if name not in _REGISTRY:
        raise ValueError(f"no signature named {name!r} is registered; registered: {signature_names()}")
    return _REGISTRY.pop(name)


def signature_names() -> tuple[str, ...]:
    """The registered signature names, in registration order (``"wks"`` first)."""
    return tuple(_REGISTRY)


def get_signature(name: str) -> type[Signature]:
    """The registered class called ``name``; a `ValueError` that lists the registered names otherwise."""
    cls = _REGISTRY.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ValueError(f"signature must be one of {signature_names()}, got {name!r}")
    return cls


def signature_options(name: str, **flat_keywords: Any) -> SignatureOptions:
    """The ``Options`` of signature ``name`` from flat keywords (`wpot.Comparer`'s, e.g. ``n_eigen=300``,
    ``ldsift_slab=0.25``).

    Keywords of the other registered signatures are ignored (so a caller may pass every setting whatever the
    signature); a keyword no registered signature declares is a `ValueError` that lists this signature's.
    """
    cls = get_signature(name)
    own = {f.metadata["keyword"]: f.name for f in option_fields(cls.Options)}
    others = set(_keyword_table(exclude=name))
    unknown = sorted(set(flat_keywords) - set(own) - others)
    if unknown:
        raise ValueError(f"unknown signature options {unknown} for signature {name!r}; its options: {sorted(own)}"
                         + (f"; other signatures': {sorted(others - set(own))}" if others - set(own) else ""))
    return cls.Options(**{own[k]: v for k, v in flat_keywords.items() if k in own})


def _flags(defaults: Mapping[str, Any]) -> dict[str, tuple[dataclasses.Field, list[str], Any]]:
    """flag -> (field, titles of the signatures using it, default in force), in registration order."""
    out: dict[str, tuple[dataclasses.Field, list[str], Any]] = {}
    for cls in _REGISTRY.values():
        for f in option_fields(cls.Options):
            flag = f.metadata["flag"]
            if flag is None:
                continue
            if flag not in out:
                out[flag] = (f, [], defaults.get(f.metadata["keyword"], f.default))
            out[flag][1].append(cls.title)
    return out


def add_signature_arguments(parser: argparse.ArgumentParser, *, defaults: Mapping[str, Any] = MappingProxyType({})) -> None:
    """Add the CLI flags of every registered signature to ``parser`` (a flag shared by several signatures once).

    Each flag stores into the option's keyword (``--n-eigen`` into ``n_eigen``); its help line names the
    signatures that use it. ``defaults`` overrides defaults by keyword (e.g. ``{"n_eigen": 100}`` for a demo);
    a keyword that has no flag is a `ValueError`. Read the values back with `signature_options_from_args`.
    """
    table = _flags(defaults)
    flagged = {f.metadata["keyword"] for f, _, _ in table.values()}
    unknown = sorted(set(defaults) - flagged)
    if unknown:
        raise ValueError(f"defaults names {unknown}, which are not signature options with a CLI flag; those are {sorted(flagged)}")
    for flag, (f, titles, default) in table.items():
        text = f"{', '.join(titles)}: {f.metadata['help'].format(default=default)}"
        kw = f.metadata["keyword"]
        if isinstance(f.default, bool):
            parser.add_argument(flag, dest=kw, action="store_true", default=bool(default), help=text)
        else:
            parser.add_argument(flag, dest=kw, type=type(f.default), default=default, help=text)


def signature_options_from_args(name: str, namespace: argparse.Namespace) -> SignatureOptions:
    """The ``Options`` of signature ``name`` from parsed arguments (`add_signature_arguments`): options with a flag
    take the parsed value, the others their default."""
    cls = get_signature(name)
    values = {}
    for f in option_fields(cls.Options):
        kw = f.metadata["keyword"]
        if f.metadata["flag"] is not None and hasattr(namespace, kw):
            values[kw] = getattr(namespace, kw)
    return signature_options(name, **values)
