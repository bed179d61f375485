"""A small content-keyed cache for per-shape results (spectra, signatures, symmetries).

Entries are dictionaries of NumPy arrays (scalars are stored as 0-d arrays), keyed by a mesh's content
`Mesh.fingerprint` plus a canonical JSON of the parameters that produced them, so a result is reused
only for the same shape *and* the same settings.

Two levels:

* memory: a bounded LRU (by entry count and by total bytes), always on;
* disk (optional): one ``.npz`` file per entry under ``<cache_dir>/<namespace>/``, read with
  ``allow_pickle=False`` (a cache never unpickles).

Where the disk cache lives
--------------------------
``cache_dir`` argument if given; otherwise the environment variable ``WPOT_CACHE_DIR``; otherwise
**no disk cache** (memory only). Decision: nothing is written to the user's home directory unless
asked for, so tests, CI and one-off scripts leave no files behind; dataset runs set ``WPOT_CACHE_DIR``
(or pass ``cache_dir``) to reuse spectra across processes. ``cache_dir=False`` disables the disk level
even when the variable is set.

Safety
------
Writes are atomic: the entry is written to a temporary file in the same folder and moved into place
with `os.replace`, so an interrupted run never leaves a half-written entry under the final name.
Each file stores its namespace, key and parameter JSON; an entry that cannot be read, or whose stored
key does not match, is reported with a `CacheWarning`, deleted, and recomputed by the caller.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
import warnings
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

__all__ = ["Cache", "Kept", "CacheWarning", "cache_key", "canonical_json", "digest", "default_cache_dir", "FORMAT_VERSION"]

#: bumped when the stored layout changes; part of every key, so old entries are simply not found
FORMAT_VERSION = 1
#: environment variable naming the on-disk cache folder
ENV_VAR = "WPOT_CACHE_DIR"
_META = "__wpot_cache_meta__"


class CacheWarning(UserWarning):
    """A cache entry was unreadable or inconsistent; it was discarded and will be recomputed."""


def _canon(obj: Any) -> Any:
    """Turn parameters into plain JSON types (NumPy scalars/arrays, tuples, paths) deterministically."""
    if isinstance(obj, Mapping):
        return {str(k): _canon(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_canon(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            return [float.hex(float(x)) for x in obj.ravel()] + [list(obj.shape)]
        return _canon(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        # exact and platform independent: 0.1 and 0.1000000000000001 are different keys
        return float.hex(float(obj))
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cache parameters must be JSON-like (numbers, strings, lists, dicts), got {type(obj).__name__}: {obj!r}")


def canonical_json(params: Mapping[str, Any]) -> str:
    """Deterministic JSON of ``params``: sorted keys, no spaces, floats written exactly (hex)."""
    return json.dumps(_canon(params), sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def digest(obj: Any, length: int = 16) -> str:
    """A short SHA-1 hex digest of ``obj``'s `canonical_json`: equal for equal parameters, whatever their key
    order or NumPy types (the one hasher of wpot's keys: caches, self-comparisons, worker set-ups)."""
    return hashlib.sha1(canonical_json(obj).encode()).hexdigest()[:length]


def cache_key(namespace: str, fingerprint: str, params: Mapping[str, Any]) -> str:
    """SHA-1 hex key of (format version, namespace, content fingerprint, canonical parameters)."""
    h = hashlib.sha1()
    h.update(f"wpot-cache-v{FORMAT_VERSION}\0{namespace}\0{fingerprint}\0".encode())
    h.update(canonical_json(params).encode())
    return h.hexdigest()


def default_cache_dir() -> Path | None:
    """``$WPOT_CACHE_DIR`` if set and non-empty, else None (no disk cache)."""
    d = os.environ.get(ENV_VAR, "").strip()
    return Path(d).expanduser() if d else None


def _nbytes(entry: Mapping[str, np.ndarray]) -> int:
    return int(sum(np.asarray(v).nbytes for v in entry.values()))


class Cache:
    """Bounded in-memory LRU plus an optional atomic ``.npz`` store on disk.

    Parameters
    ----------
    namespace : a short name for the kind of result (e.g. ``"spectrum"``); a sub-folder on disk.
    max_entries : most entries kept in memory (default 32).
    max_bytes : most bytes of array data kept in memory (default 1 GiB). An entry larger than this is
        not kept in memory (it still goes to disk when a disk cache is configured).
    cache_dir : folder for the disk cache; None reads ``$WPOT_CACHE_DIR`` each time the cache is used
        (unset: memory only); False disables the disk level.

    Entries are ``dict[str, np.ndarray]``; arrays handed out are read-only views of the cached data.
    """

    def __init__(
        self,
        namespace: str,
        *,
        max_entries: int = 32,
        max_bytes: int = 1 << 30,
        cache_dir: str | os.PathLike | None | bool = None,
    ) -> None:
        if not namespace or not namespace.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"namespace must be a non-empty alphanumeric name (with - or _), got {namespace!r}")
        if int(max_entries) < 0 or int(max_bytes) < 0:
            raise ValueError(f"max_entries and max_bytes must be >= 0, got {max_entries} and {max_bytes}")
        if cache_dir is True:
            raise ValueError("cache_dir=True is ambiguous: pass a folder, None (use $WPOT_CACHE_DIR) or False")
        self.namespace = namespace
        self.max_entries = int(max_entries)
        self.max_bytes = int(max_bytes)
        self._cache_dir = cache_dir
        self._mem: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()
        self._mem_bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    # ------------------------------------------------------------------ locations
    @property
    def directory(self) -> Path | None:
        """The folder holding this namespace's files, or None when there is no disk cache."""
        if self._cache_dir is False:
            return None
        base = Path(self._cache_dir).expanduser() if self._cache_dir is not None else default_cache_dir()
        return None if base is None else base / self.namespace

    def path_for(self, key: str) -> Path | None:
        d = self.directory
        return None if d is None else d / f"{key}.npz"

    def key(self, fingerprint: str, params: Mapping[str, Any]) -> str:
        return cache_key(self.namespace, fingerprint, params)

    # ------------------------------------------------------------------ memory level
    def _mem_put(self, key: str, entry: dict[str, np.ndarray]) -> None:
        size = _nbytes(entry)
        with self._lock:
            old = self._mem.pop(key, None)
            if old is not None:
                self._mem_bytes -= _nbytes(old)
            if size > self.max_bytes or self.max_entries == 0:
                return
            self._mem[key] = entry
            self._mem_bytes += size
            while self._mem and (len(self._mem) > self.max_entries or self._mem_bytes > self.max_bytes):
                _, ev = self._mem.popitem(last=False)
                self._mem_bytes -= _nbytes(ev)

    def _mem_get(self, key: str) -> dict[str, np.ndarray] | None:
        with self._lock:
            entry = self._mem.get(key)
            if entry is not None:
                self._mem.move_to_end(key)
            return entry

    # ------------------------------------------------------------------ disk level
    def _disk_get(self, key: str, params_json: str) -> dict[str, np.ndarray] | None:
        path = self.path_for(key)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                entry = {name: z[name] for name in z.files}  # reads (and CRC-checks) every member
            meta = json.loads(str(entry.pop(_META)[()]))
            if meta != {"namespace": self.namespace, "key": key, "params": params_json, "version": FORMAT_VERSION}:
                raise ValueError(f"stored metadata {meta} does not match the requested entry")
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
            warnings.warn(
                f"corrupt cache entry {path} ({type(exc).__name__}: {exc}); deleting it and recomputing",
                CacheWarning,
                stacklevel=4,
            )
            try:
                path.unlink()
            except OSError:
                pass
            return None
        return entry

    def _disk_put(self, key: str, params_json: str, entry: Mapping[str, np.ndarray]) -> None:
        path = self.path_for(key)
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = json.dumps({"namespace": self.namespace, "key": key, "params": params_json, "version": FORMAT_VERSION})
        arrays = {name: np.asarray(v) for name, v in entry.items()}
        for name, v in arrays.items():
            if v.dtype == object:
                raise TypeError(f"cache entry field {name!r} has dtype object; only plain arrays are cached")
        arrays[_META] = np.array(meta)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise

    # ------------------------------------------------------------------ public
    def get(self, fingerprint: str, params: Mapping[str, Any]) -> dict[str, np.ndarray] | None:
        """The cached entry for (fingerprint, params), or None. Looks in memory, then on disk."""
        key = self.key(fingerprint, params)
        entry = self._mem_get(key)
        if entry is None:
            entry = self._disk_get(key, canonical_json(params))
            if entry is not None:
                entry = _frozen(entry)
                self._mem_put(key, entry)
        if entry is None:
            self.misses += 1
        else:
            self.hits += 1
        return entry

    def put(self, fingerprint: str, params: Mapping[str, Any], entry: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """Store ``entry`` (arrays or scalars) and return the frozen copy kept in the cache."""
        key = self.key(fingerprint, params)
        frozen = _frozen(entry)
        self._mem_put(key, frozen)
        self._disk_put(key, canonical_json(params), frozen)
        return frozen

    def get_or_compute(
        self, fingerprint: str, params: Mapping[str, Any], compute: Callable[[], Mapping[str, Any]]
    ) -> dict[str, np.ndarray]:
        """Return the cached entry, computing and storing it on a miss."""
        entry = self.get(fingerprint, params)
        if entry is None:
            entry = self.put(fingerprint, params, compute())
        return entry

    def clear(self, *, disk: bool = False) -> None:
        """Empty the memory level; with ``disk=True`` also delete this namespace's ``.npz`` files."""
        with self._lock:
            self._mem.clear()
            self._mem_bytes = 0
        if disk and self.directory is not None and self.directory.is_dir():
            for p in self.directory.glob("*.npz"):
                p.unlink(missing_ok=True)

    def __len__(self) -> int:
        return len(self._mem)

    def __repr__(self) -> str:
        return (
            f"Cache({self.namespace!r}, entries={len(self._mem)}/{self.max_entries}, "
            f"bytes={self._mem_bytes}/{self.max_bytes}, directory={self.directory})"
        )


class Kept:
    """The last ``keep`` objects made, by key, in memory only: for objects that are not dictionaries of arrays
    (a `Cache` entry), such as a mesh's simplified copy or its geodesic distances. The least recently used goes
    first."""

    def __init__(self, keep: int) -> None:
        self.keep = int(keep)
        self._items: OrderedDict[Any, Any] = OrderedDict()

    def get(self, key: Any, make: Callable[[], Any]) -> Any:
        """The object kept under ``key``, or ``make()``, kept."""
        item = self._items.pop(key) if key in self._items else make()
        self._items[key] = item
        while len(self._items) > self.keep:
            self._items.popitem(last=False)
        return item

    def clear(self) -> None:
        """Forget every kept object."""
        self._items.clear()


def _frozen(entry: Mapping[str, Any]) -> dict[str, np.ndarray]:
    out = {}
    for name, v in entry.items():
        if name == _META:
            raise ValueError(f"{_META!r} is a reserved field name")
        a = np.array(v)  # copy: the cache owns its data
        if a.dtype == object:
            raise TypeError(f"cache entry field {name!r} has dtype object; only plain arrays are cached")
        a.setflags(write=False)
        out[name] = a
    return out
