"""ISO 965-1 tolerances of internal ISO metric threads, computed from the standard's formulas.

The limits of size of an internal thread of tolerance class ``6H`` are its ISO 724 basic sizes
(D1 = D - 2 (5/8) H, D2 = D - 2 (3/8) H, H = sqrt(3)/2 P) raised by the fundamental deviation EI of its
tolerance position, plus the tolerance of its grade:

* fundamental deviation (ISO 965-1, sec. 6): EI = 0 for position H (position G's +(15 + 11 P) um is
  tabulated rounded in ways the formula does not give, e.g. +28 um for P = 1.25 mm, so it is left out
  until a test holds it to the table);
* minor diameter tolerance, grade 6 (sec. 9.1): TD1(6) = 433 P - 190 P^1.22 um for P from 0.2 to 0.8 mm,
  230 P^0.7 um for P >= 1 mm;
* pitch diameter tolerance, grade 6 (sec. 9.2): TD2(6) = 1.32 Td2(6) with Td2(6) = 90 P^0.4 d^0.1 um, d the
  geometric mean of the limits of the nominal diameter range the thread's D falls in (ISO 965-1 table 1:
  1.4-2.8, 2.8-5.6, 5.6-11.2, 11.2-22.4, ... mm);
* the standard tabulates these values rounded to the nearest number of the R40 series of preferred numbers
  (ISO 3) and its limits of size (ISO 965-2) to the micrometre.

The major diameter of an internal thread has a lower limit only (D + EI): its maximum is set by the tap.
Where the standard's table departs from its own formula the table governs (the standard says so);
:data:`TABLE_DEPARTURES_UM` lists the known cells, each with the formula's value for the record.
tests/test_thread_limits.py checks the computed limits against published limits of size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from scope3d.geometry.iso_thread import THREAD_SIZES, basic_pitch_diameter

# ISO 965-1 table 1: limits of the basic major diameter ranges (mm); a diameter belongs to the range
# (lower, upper].
DIAMETER_RANGES_MM = (0.99, 1.4, 2.8, 5.6, 11.2, 22.4, 45.0, 90.0, 180.0, 355.0, 600.0)

# Cells of ISO 965-1's tolerance tables that are not the formula's value rounded to R40:
# (quantity, grade, pitch mm, diameter range) -> the table's value (um). TD2(6) of P = 1.5 mm in the
# 5.6-11.2 mm range: the formula gives 171.9 um (R40: 170), the table 180 um (an M10x1.5 6H hole's D2 is
# 9.026-9.206 mm in ISO 965-2 and ASME B1.13M alike). The tables depart from the nearest R40 number in other
# cells too, none of them a size here (TD1(6) of P = 0.5 mm: 140 um, the formula 134.9 um), so a size added
# to THREAD_SIZES needs its limits checked against the published ones (tests/test_thread_limits.py).
TABLE_DEPARTURES_UM = {("TD2", 6, 1.5, (5.6, 11.2)): 180.0}

FUNDAMENTAL_POSITIONS = ("H",)
GRADES = (6,)
TOLERANCE_CLASSES = tuple(f"{g}{p}" for g in GRADES for p in FUNDAMENTAL_POSITIONS)


@dataclass(frozen=True)
class ThreadLimits:
    """Limits of size of one internal thread class (mm): minor diameter D1 in [d1_min, d1_max], pitch
    diameter D2 in [d2_min, d2_max] (the virtual D2 for the go side), major diameter D >= d_min."""

    designation: str
    tolerance_class: str
    d1_min_mm: float
    d1_max_mm: float
    d2_min_mm: float
    d2_max_mm: float
    d_min_mm: float
    source: str = "ISO 965-1 formulas (ISO 965-2 limits of size), class 6H"


def r40(value: float) -> float:
    """``value`` rounded to the nearest (in ratio) number of the R40 series of preferred numbers (ISO 3),
    as ISO 965-1 rounds its tolerances. The series' numbers are themselves rounded (R40: 100, 106, 112, 118,
    125, 132, 140, 150, 160, 170, 180, 190, 200, 212, 224, 236, 250, 265, 280, 300, 315, 335, 355, 375, 400,
    425, 450, 475, 500, 530, 560, 600, 630, 670, 710, 750, 800, 850, 900, 950 per decade), so they are
    listed rather than computed as 10^(k/40)."""
    if not value > 0:
        raise ValueError(f"R40 rounding needs a positive value, got {value}")
    decade = 10.0 ** math.floor(math.log10(value) - 2)
    candidates = [m * decade * f for f in (1, 10) for m in _R40_MANTISSAS]
    return min(candidates, key=lambda c: abs(math.log(c / value)))


_R40_MANTISSAS = (100, 106, 112, 118, 125, 132, 140, 150, 160, 170, 180, 190, 200, 212, 224, 236, 250, 265, 280,
                  300, 315, 335, 355, 375, 400, 425, 450, 475, 500, 530, 560, 600, 630, 670, 710, 750, 800, 850,
                  900, 950)


def diameter_range(nominal_mm: float) -> tuple[float, float]:
    """The ISO 965-1 nominal diameter range (lower, upper] (mm) ``nominal_mm`` falls in."""
    for lo, hi in zip(DIAMETER_RANGES_MM[:-1], DIAMETER_RANGES_MM[1:]):
        if lo < nominal_mm <= hi:
            return lo, hi
    raise ValueError(f"no ISO 965-1 diameter range holds {nominal_mm} mm")


def fundamental_deviation_um(position: str, pitch_mm: float) -> float:
    """ISO 965-1 fundamental deviation EI (um) of an internal thread's tolerance position (H: none,
    whatever the pitch)."""
    if position == "H":
        return 0.0
    raise ValueError(f"no fundamental deviation for position {position!r} (have {', '.join(FUNDAMENTAL_POSITIONS)})")


def minor_diameter_tolerance_um(pitch_mm: float, grade: int = 6) -> float:
    """ISO 965-1 TD1 (um) of grade ``grade``, rounded to R40 as the standard's table."""
    if grade != 6:
        raise ValueError(f"tolerance grade {grade} not implemented (have {GRADES})")
    if 0.2 <= pitch_mm <= 0.8:
        raw = 433.0 * pitch_mm - 190.0 * pitch_mm ** 1.22
    elif pitch_mm >= 1.0:
        raw = 230.0 * pitch_mm ** 0.7
    else:
        raise ValueError(f"ISO 965-1 gives TD1 for P from 0.2 to 0.8 mm and from 1 mm, not {pitch_mm} mm")
    return TABLE_DEPARTURES_UM.get(("TD1", grade, pitch_mm, None), r40(raw))


def pitch_diameter_tolerance_um(nominal_mm: float, pitch_mm: float, grade: int = 6) -> float:
    """ISO 965-1 TD2 (um) of grade ``grade``, rounded to R40 as the standard's table (or its listed
    departure)."""
    if grade != 6:
        raise ValueError(f"tolerance grade {grade} not implemented (have {GRADES})")
    lo, hi = diameter_range(nominal_mm)
    raw = 1.32 * 90.0 * pitch_mm ** 0.4 * math.sqrt(lo * hi) ** 0.1
    return TABLE_DEPARTURES_UM.get(("TD2", grade, pitch_mm, (lo, hi)), r40(raw))


def thread_limits(designation: str, tolerance_class: str = "6H") -> ThreadLimits:
    """The limits of size of ``designation`` (one of :data:`scope3d.geometry.iso_thread.THREAD_SIZES`) in
    ``tolerance_class`` (``6H``), to the micrometre as ISO 965-2 lists them."""
    if designation not in THREAD_SIZES or tolerance_class not in TOLERANCE_CLASSES:
        raise ValueError(f"no limits for {designation} {tolerance_class} (have {', '.join(THREAD_SIZES)}, "
                         f"class {', '.join(TOLERANCE_CLASSES)})")
    nominal, pitch = THREAD_SIZES[designation]
    grade, position = int(tolerance_class[:-1]), tolerance_class[-1]
    ei = fundamental_deviation_um(position, pitch) / 1000.0
    td1 = minor_diameter_tolerance_um(pitch, grade) / 1000.0
    td2 = pitch_diameter_tolerance_um(nominal, pitch, grade) / 1000.0
    d1_min = round(nominal - 1.25 * math.sqrt(3) / 2 * pitch + ei, 3)
    d2_min = round(basic_pitch_diameter(nominal, pitch) + ei, 3)
    return ThreadLimits(designation, tolerance_class, d1_min, round(d1_min + td1, 3), d2_min,
                        round(d2_min + td2, 3), round(nominal + ei, 3),
                        source=f"ISO 965-1 formulas (ISO 965-2 limits of size), class {tolerance_class}")
