"""render: Warp depth images of whole triangle meshes on many local planes at once.

Used by `wpot.ldsift` (paper section 3.1) and usable on its own:

* `depth_images` / `DepthRenderer` — ray casting against a Warp BVH, one launch for all views
  (conventions in `render.raycast`);
* `DepthRenderer.inward_hits`, `inward_cone` — rays cast into the solid from surface points, the shape diameter
  function behind LD-SIFT's thickness column (`wpot.signatures._thickness`);
* `to_uint8`, `tile`, `save_png` — 8-bit stretching and tiled PNGs for inspection (paper Fig. 8).
"""
from __future__ import annotations

from render.png import save_png, tile, to_uint8
from render.raycast import DepthRenderer, depth_images, inward_cone

__all__ = ["DepthRenderer", "depth_images", "inward_cone", "save_png", "tile", "to_uint8"]
