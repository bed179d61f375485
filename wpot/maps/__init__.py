"""After the transport: maps between shapes.

- `wpot.maps.fmap`: functional maps (spectral bases, point-to-point conversion);
- `wpot.maps.zoomout`: ZoomOut refinement of a correspondence (`zoomout`), oriented or not;
- `wpot.maps.orientation`: symmetry and orientation (winding, orientation score);
- `wpot.maps.seams`: a map's seams, and the regions they cut off mapped again (`reanchor`);
- `wpot.maps.locate`: a part located in a whole by geodesic consistency (`locate_part`);
- `wpot.maps.registration`: similarity transforms fitted to matched pairs;
- `wpot.maps.retrieval`: a part's class looked up in a labelled library (`rank_classes`).
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: the submodules, imported when first read as attributes (``wpot.maps.<name>``)
_MODULES = ("fmap", "locate", "orientation", "registration", "retrieval", "seams", "zoomout")


def __getattr__(name: str) -> ModuleType:
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
