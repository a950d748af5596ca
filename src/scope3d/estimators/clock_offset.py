"""A camera/robot clock offset read off a map: how far the imported poses lag or lead the images.

A frame whose time on the robot's clock is off by ``dt`` gets the robot's pose at ``t + dt``: its measured
centre sits ``v dt`` along the scan's velocity ``v``. A map that corrects the poses from the images moves each
centre back by about ``-v dt``, so the adjusted minus measured centres, regressed on the velocity, give ``dt``.
The velocity comes from the measured centres themselves (central differences over the frame times), which is
what a user has; a constant shift between the two sets of centres (the map's datum) is fitted with it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClockOffsetOptions:
    """min_frames : fewer frames than this are refused (1 offset + 3 datum unknowns need a few more
    equations than 4 to leave residuals to estimate sigma from)."""

    min_frames: int = 6


@dataclass(frozen=True)
class ClockOffset:
    """offset_s : the frames' times minus the true ones, on the robot's clock (s): positive when the frame
    times given run late; add ``-offset_s`` to the frame times to correct it. sigma_s : its standard deviation
    (s). residual_mm : RMS of the 3D residual per frame after the fit (mm). speed_mm_s : median speed of the
    measured centres (mm/s). n_frames : frames used."""

    offset_s: float
    sigma_s: float
    residual_mm: float
    speed_mm_s: float
    n_frames: int


def estimate_clock_offset(measured_mm: np.ndarray, adjusted_mm: np.ndarray, times_s: np.ndarray,
                          options: ClockOffsetOptions = ClockOffsetOptions()) -> ClockOffset | str:
    """The clock offset and its sigma, or the reason it cannot be told (a string).

    measured_mm : (n, 3) camera centres as imported (mm, world). adjusted_mm : (n, 3) the same frames' centres
    after the map's adjustment (mm, same world). times_s : (n,) each frame's time on the robot's clock (s), as
    the import used it. Rows are frames in any order; they are put in time order here.

    Model: ``adjusted - measured = a - v dt + e`` with ``a`` the datum shift (3 mm) and ``e`` the map's error.
    Least squares over the centred velocity; sigma from the residuals' variance over ``3 n - 4`` degrees of
    freedom (frames treated as independent: a map's errors correlate along the scan, so this is a lower bound).
    Refused when there are too few frames, times are not strictly increasing, or the camera moves less
    between frames than the residual scatter (the differenced velocity would be noise).
    """
    measured_mm, adjusted_mm = np.asarray(measured_mm, float), np.asarray(adjusted_mm, float)
    times_s = np.asarray(times_s, float)
    n = len(times_s)
    if n < options.min_frames:
        return f"{n} frame(s) with a known time, {options.min_frames} needed to estimate a clock offset"
    order = np.argsort(times_s, kind="stable")
    t, c, r = times_s[order], measured_mm[order], (adjusted_mm - measured_mm)[order]
    dt_frames = np.diff(t)
    if not np.all(dt_frames > 0):
        return "two frames share a time: the velocity cannot be differenced"
    v = np.empty_like(c)
    v[1:-1] = (c[2:] - c[:-2]) / (t[2:] - t[:-2])[:, None]
    v[0], v[-1] = (c[1] - c[0]) / dt_frames[0], (c[-1] - c[-2]) / dt_frames[-1]
    vc, rc = v - v.mean(axis=0), r - r.mean(axis=0)
    vv = float(np.sum(vc * vc))
    speed = float(np.median(np.linalg.norm(v, axis=1)))
    if vv == 0.0:
        return "the camera does not move: a clock offset has no effect to measure"
    offset = -float(np.sum(vc * rc)) / vv
    residual = rc + vc * offset
    variance = float(np.sum(residual * residual)) / (3 * n - 4)
    rms = float(np.sqrt(3 * variance))
    step = float(np.sqrt(vv / n) * np.median(dt_frames))
    if step < rms:
        return (f"the camera moves {step:.3g} mm between frames, less than the map's {rms:.3g} mm scatter: "
                "too slow to tell a clock offset")
    return ClockOffset(offset, float(np.sqrt(variance / vv)), rms, speed, n)
