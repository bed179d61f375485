"""Fixtures of the command's tests."""
from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """Two 300-vertex triangulations of one surface, as files."""
    from wpot.examples import example_pair
    from wpot.io import save_mesh

    folder = tmp_path_factory.mktemp("pair")
    p = example_pair(300, seed=0, n_target=300)
    save_mesh(p.source, folder / "a.off")
    save_mesh(p.target, folder / "b.off")
    return folder / "a.off", folder / "b.off"
