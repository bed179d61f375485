"""Per-vertex shape signatures: WKS (intrinsic, spectral) and LD-SIFT (extrinsic, depth images + SIFT).

The implementation modules are private (``_wks``, ``_ldsift``) so that no submodule shares a name with a
function exported here; their Warp and OpenCV imports happen inside the functions.
"""
from __future__ import annotations

from wpot.signatures._ldsift import LocalFrames, ldsift, local_frames
from wpot.signatures._wks import EnergyGrid, wks, wks_energies, wks_from_eigenpairs

__all__ = ["EnergyGrid", "LocalFrames", "ldsift", "local_frames", "wks", "wks_energies", "wks_from_eigenpairs"]
