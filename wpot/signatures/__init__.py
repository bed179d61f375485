"""Per-vertex shape signatures: WKS (intrinsic, spectral) and LD-SIFT (extrinsic, depth images + SIFT)."""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "wks": "wpot.signatures.wks",
    "wks_energies": "wpot.signatures.wks",
    "ldsift": "wpot.signatures.ldsift",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'wpot.signatures' has no attribute {name!r}")
