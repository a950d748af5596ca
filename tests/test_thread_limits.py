"""The ISO 965-1 class 6H limits tabulated in metrology/thread_gauge.py, checked two ways: against the
published limits of size, and against the ISO 724 basic sizes plus the ISO 965-1 tolerance formulas."""
from __future__ import annotations

import math

import pytest

from scope3d.metrology.thread_gauge import ISO_965_6H, THREAD_SIZES, thread_limits

# Published 6H limits of size (mm): D1 min, D1 max, D2 min, D2 max, D min. Source: ANSI/ASME B1.13M-1995
# "Metric screw threads - M profile", internal threads table (identical to ISO 965-2 for class 6H), as
# reproduced in Engineers Edge's "Internal Metric Thread Table Chart" M 0.25 - M 8 and M 9 - M 24.
# M6x1 is read off its table; its tolerances equal those of M10x1 (same pitch, same 5.6-11.2 mm diameter
# range: TD1 236 um, TD2 150 um), whose row there is 8.917-9.153 / 9.350-9.500, and Yamawa's tap catalogue
# (technical data, "Thread limits") gives its basic D2 5.350 and D1 4.917.
PUBLISHED_6H = {
    "M6x1": (4.917, 5.153, 5.350, 5.500, 6.000),
    "M8x1.25": (6.647, 6.912, 7.188, 7.348, 8.000),
    "M10x1.5": (8.376, 8.676, 9.026, 9.206, 10.000),
}


@pytest.mark.parametrize("designation", list(PUBLISHED_6H))
def test_table_equals_the_published_limits(designation):
    limits = thread_limits(designation)
    got = (limits.d1_min_mm, limits.d1_max_mm, limits.d2_min_mm, limits.d2_max_mm, limits.d_min_mm)
    assert got == pytest.approx(PUBLISHED_6H[designation], abs=1e-9)
    assert set(ISO_965_6H) == set(PUBLISHED_6H)


@pytest.mark.parametrize("designation", list(PUBLISHED_6H))
def test_table_follows_the_iso_formulas(designation):
    d1_min, d1_max, d2_min, d2_max, d_min = ISO_965_6H[designation]
    nominal, pitch = THREAD_SIZES[designation]
    # H: fundamental deviation EI = 0, so the lower limits are the ISO 724 basic sizes (H = sqrt(3)/2 P):
    # D1 = D - 2 * 5/8 H, D2 = D - 2 * 3/8 H; the tables give them to the micrometre.
    h = math.sqrt(3) / 2 * pitch
    assert d_min == nominal
    assert abs(d1_min - (nominal - 1.25 * h)) <= 0.0005 + 1e-9
    assert abs(d2_min - (nominal - 0.75 * h)) <= 0.0005 + 1e-9
    # Tolerance grade 6 (ISO 965-1, sec. 9): TD1(6) = 230 P^0.7 um for P >= 1 mm; TD2(6) = 1.32 Td2(6) with
    # Td2(6) = 90 P^0.4 d^0.1 um, d the geometric mean of the 5.6-11.2 mm diameter range. The standard's
    # tabulated tolerances are these values rounded to the R40 series of preferred numbers, so they may
    # differ from the formula by up to one R40 step (ratio 10^(1/40) = 1.059; M10x1.5's TD2 is 180 um
    # against the formula's 172 um, the largest gap).
    r40_step = 10 ** (1 / 40)
    td1 = 230 * pitch ** 0.7 / 1000
    td2 = 1.32 * 90 * pitch ** 0.4 * math.sqrt(5.6 * 11.2) ** 0.1 / 1000
    assert 1 / r40_step <= (d1_max - d1_min) / td1 <= r40_step
    assert 1 / r40_step <= (d2_max - d2_min) / td2 <= r40_step
