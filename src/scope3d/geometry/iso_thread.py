"""ISO metric threads: the sizes (ISO 261) and the basic profile (ISO 68-1, ISO 724), in one place for the
phantom lab, which builds threaded holes, and the metrology, which gauges them.

The basic profile of an ISO metric (M) thread: a fundamental triangle of height H = sqrt(3)/2 P with 60°
flanks, cut to a crest flat P/4 wide at the internal thread's minor diameter D1 = D - 2 (5/8) H and a root
flat P/8 wide at the major diameter D; the tooth is half a pitch wide at the pitch diameter
D2 = D - 0.6495 P (ISO 724). The tolerance classes (ISO 965-1) are metrology's
(:mod:`scope3d.metrology.thread_gauge`).
"""
from __future__ import annotations

import numpy as np

from scope3d.errors import InputError

# Nominal diameter D (mm) and pitch P (mm) of the ISO 261 coarse threads the lab builds and the gauge knows.
THREAD_SIZES = {"M5x0.8": (5.0, 0.8), "M6x1": (6.0, 1.0), "M8x1.25": (8.0, 1.25), "M10x1.5": (10.0, 1.5),
                "M12x1.75": (12.0, 1.75)}

# ISO 68-1: every ISO metric (M) thread has a symmetric profile with a 60° included flank angle.
ISO_METRIC_FLANK_ANGLE_DEG = 60.0


def iso_thread_profile(major_mm: float, pitch_mm: float) -> dict:
    """ISO 68-1 basic profile of an internal thread. Returns the named dimensions (mm).

    H = sqrt(3)/2 P; the minor diameter D1 = D - 2 (5/8) H; the crest flat (at D1) is P/4 wide, the
    root flat (at D) P/8; each 60° flank spans 5P/16 axially.
    """
    h = np.sqrt(3.0) / 2.0 * pitch_mm
    return {
        "major_diameter_mm": major_mm,
        "minor_diameter_mm": major_mm - 1.25 * h,
        "pitch_mm": pitch_mm,
        "fundamental_triangle_height_mm": h,
        "thread_depth_mm": 0.625 * h,
        "crest_flat_mm": pitch_mm / 4,
        "root_flat_mm": pitch_mm / 8,
        "flank_angle_deg": ISO_METRIC_FLANK_ANGLE_DEG,
    }


def basic_thread_depth(pitch_mm: float) -> float:
    """ISO 68-1 basic thread depth 5/8 H (mm), as the gauge computes it: (5/8 sqrt(3) / 2) P. The
    profile's ``thread_depth_mm`` is 5/8 of its own H; the two orders of the same product differ by at most
    a unit in the last place (M10x1.5: 2e-16 mm), and each is kept so that the gauge's fits and the phantom's
    ground truth stay bit for bit what they were."""
    return 0.625 * np.sqrt(3) / 2 * pitch_mm


def basic_pitch_diameter(major_mm: float, pitch_mm: float) -> float:
    """ISO 724 basic pitch diameter D2 = D - 0.6495 P (mm; 0.649519 = 3 sqrt(3) / 8)."""
    return major_mm - 0.649519 * pitch_mm


def tooth_half_width(radius_mm, pitch_mm: float, pitch_radius_mm: float, half_angle_rad: float):
    """Half the axial width of a symmetric tooth at ``radius_mm``: half a pitch wide at the pitch radius,
    its flanks ``half_angle_rad`` from the radial direction (30° for the ISO profile), so narrower towards
    the internal thread's crest (the minor radius) and wider towards its root."""
    return 0.25 * pitch_mm + (radius_mm - pitch_radius_mm) * np.tan(half_angle_rad)


def profile_segments(pitch: float, r_minor: float, r_major: float, r_pitch: float | None = None):
    """One pitch of the profile as straight segments in s (axial phase), each (s0, s1, r0, r1, n_rows).
    Crest (minor) flat centred at s = P/8, falling 60° flank, root (major) flat, rising flank. The tooth is
    half a pitch wide at the pitch radius ``r_pitch`` (None: the basic one, which gives the ISO 68-1 crest
    P/4 and root P/8 at the basic diameters). ``n_rows``: grid rows the phantom gives each segment."""
    p = pitch
    tan30 = np.tan(np.pi / 6)
    if r_pitch is None:
        r_pitch = r_minor + 0.25 * p / (2 * tan30)
    crest = p / 2 - 2 * (r_pitch - r_minor) * tan30
    root = p / 2 - 2 * (r_major - r_pitch) * tan30
    if crest <= 0 or root <= 0:
        raise InputError(f"thread profile impossible: crest flat {crest:.3f} mm, root flat {root:.3f} mm "
                         "(pitch diameter offset too large)")
    a0 = p / 8 - crest / 2
    a1 = a0 + crest
    a2 = a1 + (r_major - r_minor) * tan30
    a3 = a2 + root
    return [
        (a0, a1, r_minor, r_minor, 4),
        (a1, a2, r_minor, r_major, 10),
        (a2, a3, r_major, r_major, 2),
        (a3, a0 + p, r_major, r_minor, 10),
    ]
