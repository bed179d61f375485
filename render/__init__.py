"""render: Warp depth images of whole triangle meshes on many local planes at once.

Used by `wpot.ldsift` (paper section 3.1) and usable on its own:

* `depth_images` / `DepthRenderer` — ray casting against a Warp BVH, one launch for all views
  (conventions in `render.raycast`);
* `to_uint8`, `tile`, `save_png` — 8-bit stretching and tiled PNGs for inspection (paper Fig. 8).
"""
from __future__ import annotations

from render.png import save_png, tile, to_uint8
from render.raycast import DepthRenderer, depth_images

__all__ = ["DepthRenderer", "depth_images", "save_png", "tile", "to_uint8"]
