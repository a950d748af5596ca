"""Fixtures shared by several test files."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_dome_map(tmp_path_factory):
    """The output folder of ``scope3d map`` (through the command line, so report.html is written as every
    job writes it) on 12 frames of the dome at 320x240: the smallest grid on which the map finds
    fluorescent targets (6 frames found none), so a report's targets table has rows."""
    from scope3d import phantoms
    from scope3d.cli.main import main

    seq = phantoms.generate("dome", "grid5x6", size=(320, 240), seed=0, n_frames=12)
    dataset = phantoms.write(seq, tmp_path_factory.mktemp("dome") / "dome")
    out = tmp_path_factory.mktemp("map") / "run"
    assert main(["map", str(dataset), "--out", str(out), "--quiet"]) == 0
    return out
