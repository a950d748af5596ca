"""The printed sheet's size option (a larger sheet carries the long surveys of bench_map_scaling.py)."""
import numpy as np
import pytest

from scope3d.phantoms.scenes import SHEET_SIZE_MM, build_sheet


def test_sheet_mesh_spans_the_requested_size():
    # a coarse texel keeps the test fast; the mesh does not depend on it
    sheet = build_sheet(size_mm=90.0, mm_per_texel=0.5)
    v = sheet.mesh.vertices
    assert np.allclose(v.min(axis=0), [-45.0, -45.0, 0.0]) and np.allclose(v.max(axis=0), [45.0, 45.0, 0.0])
    assert sheet.info["sheet"]["size_mm"] == 90.0


def test_default_sheet_is_the_reference_sheet():
    assert build_sheet(mm_per_texel=0.5).info["sheet"]["size_mm"] == SHEET_SIZE_MM == 60.0


@pytest.mark.parametrize("size", [0.0, -5.0, float("nan")])
def test_sheet_size_must_be_positive(size):
    with pytest.raises(ValueError, match="sheet size"):
        build_sheet(size_mm=size, mm_per_texel=0.5)
