"""Dataset runs: every pair of a dataset compared, stored as it finishes, resumable.

- `wpot.runs.store`: the SQLite run store (`RunStore`), its key and lock;
- `wpot.runs.matrices`: its distances read back (D(inf), D(beta), exports);
- `wpot.runs.shapes`: the shapes of a run (folders and list files);
- `wpot.runs.workers`: what a worker does (processes and Dask), and its device;
- `wpot.runs.loop`: the run itself (`run_all_vs_all`);
- `wpot.runs.report`, `wpot.runs.history`: reports of a finished run and its D(beta) histories.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: the submodules, imported when first read as attributes (``wpot.runs.<name>``)
_MODULES = ("history", "loop", "matrices", "report", "shapes", "store", "workers")


def __getattr__(name: str) -> ModuleType:
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
