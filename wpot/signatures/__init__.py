"""Per-vertex shape signatures: WKS (intrinsic, spectral) and LD-SIFT (extrinsic, depth images + SIFT).

The functions are imported eagerly (their modules load Warp and OpenCV only inside the functions), so
that importing a submodule can never shadow a function of the same name on this package.
"""
from __future__ import annotations

from wpot.signatures.ldsift import LocalFrames, ldsift, local_frames
from wpot.signatures.wks import wks, wks_energies

__all__ = ["LocalFrames", "ldsift", "local_frames", "wks", "wks_energies"]
