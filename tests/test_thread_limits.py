"""The ISO 965-1 class 6H limits computed in metrology/thread_tolerances.py from the standard's formulas,
checked against published limits of size, and the formulas' own steps against the standard's tables."""
from __future__ import annotations

import pytest

from scope3d.geometry.iso_thread import THREAD_SIZES
from scope3d.metrology.thread_tolerances import (TABLE_DEPARTURES_UM, diameter_range, minor_diameter_tolerance_um,
                                                 pitch_diameter_tolerance_um, r40, thread_limits)

# Published 6H limits of size (mm): D1 min, D1 max, D2 min, D2 max, D min. Source: ANSI/ASME B1.13M-1995
# "Metric screw threads - M profile", internal threads table (identical to ISO 965-2 for class 6H), as
# reproduced in Engineers Edge's "Internal Metric Thread Table Chart" M 0.25 - M 8 and M 9 - M 24.
# M6x1 is read off its table; its tolerances equal those of M10x1 (same pitch, same 5.6-11.2 mm diameter
# range: TD1 236 um, TD2 150 um), whose row there is 8.917-9.153 / 9.350-9.500, and Yamawa's tap catalogue
# (technical data, "Thread limits") gives its basic D2 5.350 and D1 4.917; its pitch diameter tolerance
# comparison gives 125 um for M5x0.8 6H.
PUBLISHED_6H = {
    "M5x0.8": (4.134, 4.334, 4.480, 4.605, 5.000),
    "M6x1": (4.917, 5.153, 5.350, 5.500, 6.000),
    "M8x1.25": (6.647, 6.912, 7.188, 7.348, 8.000),
    "M10x1.5": (8.376, 8.676, 9.026, 9.206, 10.000),
    "M12x1.75": (10.106, 10.441, 10.863, 11.063, 12.000),
}


def test_every_size_the_gauge_knows_is_checked():
    assert set(THREAD_SIZES) == set(PUBLISHED_6H)


@pytest.mark.parametrize("designation", list(PUBLISHED_6H))
def test_computed_limits_equal_the_published_ones(designation):
    limits = thread_limits(designation)
    got = (limits.d1_min_mm, limits.d1_max_mm, limits.d2_min_mm, limits.d2_max_mm, limits.d_min_mm)
    # both to the micrometre: the standard lists its limits so
    assert got == pytest.approx(PUBLISHED_6H[designation], abs=1e-9)


# ISO 965-1's grade 6 tolerances (um) of internal threads, from its tables: TD1 by pitch, TD2 by pitch
# and diameter range. Cells beyond the sizes above check the formulas and the R40 rounding on their own.
# (M16x2's TD1, M4x0.7's, M6x0.75's and M12x1's TD2 are not sizes the phantom renders.)
TD1_6 = {0.8: 200, 1.0: 236, 1.25: 265, 1.5: 300, 1.75: 335, 2.0: 375}
TD2_6 = {(0.7, 4.0): 118, (0.8, 5.0): 125, (0.75, 6.0): 132, (1.0, 6.0): 150, (1.25, 8.0): 160,
         (1.5, 10.0): 180, (1.0, 12.0): 160, (1.75, 12.0): 200}


@pytest.mark.parametrize("pitch", list(TD1_6))
def test_minor_diameter_tolerance_formula(pitch):
    assert minor_diameter_tolerance_um(pitch) == TD1_6[pitch]


@pytest.mark.parametrize("pitch,nominal", list(TD2_6))
def test_pitch_diameter_tolerance_formula(pitch, nominal):
    assert pitch_diameter_tolerance_um(nominal, pitch) == TD2_6[(pitch, nominal)]


def test_departures_are_within_one_r40_step_of_the_formula():
    # a listed departure is the table's rounding, never a different tolerance: the neighbouring R40 number
    for (quantity, grade, pitch, rng), value in TABLE_DEPARTURES_UM.items():
        assert quantity == "TD2" and grade == 6
        raw = 1.32 * 90 * pitch ** 0.4 * (rng[0] * rng[1]) ** 0.05
        assert 1 < value / r40(raw) <= 10 ** (1 / 40) + 1e-3


def test_r40_and_ranges():
    assert [r40(v) for v in (230.0, 268.9, 201.7, 1.0, 0.0123)] == [236, 265, 200, 1.0, 0.0125]
    assert diameter_range(5.6) == (2.8, 5.6) and diameter_range(6.0) == (5.6, 11.2)
    with pytest.raises(ValueError):
        thread_limits("M8x1.25", "6G")
