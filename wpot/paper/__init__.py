"""The paper's datasets and tables, for reproducing its experiments; not needed by the core.

- `wpot.paper.tosca8`: TOSCA8 (§4.1.1) and random draws of it;
- `wpot.paper.head`: the HEAD dataset (§4.2);
- `wpot.paper.table1`: the paper's Table 1 figures, beside which `wpot report` prints a run's.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: the submodules, imported when first read as attributes (``wpot.paper.<name>``)
_MODULES = ("head", "table1", "tosca8")


def __getattr__(name: str) -> ModuleType:
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
