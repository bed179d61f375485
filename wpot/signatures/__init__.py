"""Per-vertex shape signatures: WKS (intrinsic, spectral), LD-SIFT (extrinsic, depth images + SIFT), HKS
(intrinsic, spectral), and the registry through which the rest of the package finds them (`base`).

Every module of this package is imported here, so a module that defines a `Signature` subclass and calls
`register_signature` is all it takes to add a signature (see `wpot.signatures.base`).

The WKS and LD-SIFT implementation modules are private (``_wks``, ``_ldsift``) so that no submodule shares a name
with a function exported here; their Warp and OpenCV imports happen inside the functions.
"""
from __future__ import annotations

import importlib
import pkgutil

from wpot.signatures.base import (
    SIGNATURES,
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
# WKS first, then LD-SIFT: the registration order is the order of `signature_names` (and of the CLI's choices)
from wpot.signatures._wks import WKS, EnergyGrid, wks, wks_energies, wks_from_eigenpairs, wks_weights
from wpot.signatures._ldsift import LDSIFT, LocalFrames, ldsift, local_frames
from wpot.signatures._thickness import ThicknessField, thickness, thickness_field

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
del _module

__all__ = [
    "EnergyGrid", "LocalFrames", "ldsift", "local_frames", "wks", "wks_energies", "wks_from_eigenpairs", "wks_weights",
    "Signature", "SignatureOptions", "SIGNATURES", "get_signature", "signature_names", "register_signature",
    "unregister_signature", "signature_options", "add_signature_arguments", "signature_options_from_args",
    "WKS", "LDSIFT", "ThicknessField", "thickness", "thickness_field",
]
