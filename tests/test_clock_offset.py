"""A camera/robot clock offset read off a map (issue 33): scope3d.estimators.clock_offset on synthetic
arrays, and `scope3d map` on the phantom lab's recording with its frame times 5 ms off."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.estimators.clock_offset import ClockOffset, estimate_clock_offset
from scope3d.phantoms.recording import RecordingOptions, write_recording


def _raster(n=60, speed=50.0, fps=10.0):
    """A raster scan: rows of constant speed along x, alternating direction, one row step in y between."""
    t = np.arange(n) / fps
    row = (np.arange(n) // 15)
    x = np.where(row % 2 == 0, np.arange(n) % 15, 14 - np.arange(n) % 15) * speed / fps
    return t, np.column_stack([x, 2.0 * row, np.zeros(n)])


def test_a_known_offset_is_read_back_within_its_sigma():
    rng = np.random.default_rng(0)
    t, true = _raster()
    dt = 0.005
    # the imported poses are the truth at t + dt (along each row: + v dt); the map recovers the truth up to
    # its own noise and a constant datum shift
    v = np.gradient(true, t, axis=0)
    measured = true + v * dt
    noise = 0.02
    adjusted = true + np.array([0.1, -0.05, 0.02]) + rng.normal(0.0, noise, true.shape)
    fit = estimate_clock_offset(measured, adjusted, t)
    assert isinstance(fit, ClockOffset)
    # the rows' turns make the differenced velocity wrong at a few frames: those land in the residuals
    assert abs(fit.offset_s - dt) < 4.0 * fit.sigma_s, (fit.offset_s, fit.sigma_s)
    assert fit.offset_s / fit.sigma_s > 3.0
    # frame order does not matter
    p = rng.permutation(len(t))
    assert np.isclose(estimate_clock_offset(measured[p], adjusted[p], t[p]).offset_s, fit.offset_s)


def test_no_offset_reads_zero_within_its_sigma():
    rng = np.random.default_rng(1)
    t, true = _raster()
    adjusted = true + rng.normal(0.0, 0.02, true.shape)
    fit = estimate_clock_offset(true, adjusted, t)
    assert abs(fit.offset_s) < 4.0 * fit.sigma_s


def test_refuses_what_cannot_be_told():
    t, c = _raster()
    assert "needed" in estimate_clock_offset(c[:3], c[:3], t[:3])
    assert "share a time" in estimate_clock_offset(c, c, np.r_[t[:-1], t[-2]])
    still = np.zeros_like(c)
    assert "does not move" in estimate_clock_offset(still, still, t)
    # a camera that creeps 1 um between frames under 0.1 mm of map noise
    rng = np.random.default_rng(2)
    slow = c * 1e-4
    assert "too slow" in estimate_clock_offset(slow, slow + rng.normal(0.0, 0.1, c.shape), t)


# --- `scope3d map` on the phantom lab's recording ---------------------------------------------------------


@pytest.fixture(scope="module", params=[0.0, 0.005], ids=["in_sync", "5ms_late"])
def mapped(request, tmp_path_factory):
    """docs/own_data.md's scan (exact robot, small frames) with the frame times ``param`` seconds late on the
    robot's clock, imported as the walkthrough does and mapped: (offset, report.json, printed summary)."""
    root = tmp_path_factory.mktemp("clock")
    rec = root / "rec"
    write_recording(RecordingOptions(size=(304, 304), speed_mm_s=50.0, robot_error_mm=0.0,
                                     sync_error_s=request.param), rec)
    assert main(["import", "frames", str(rec / "scan" / "video.mkv"), "--camera", str(rec / "truth" / "camera.json"),
                 "--poses", str(rec / "scan" / "robot_log.csv"), "--pose-format", "xyz-qxyzw", "--unit", "m",
                 "--frame-times", str(rec / "scan" / "frame_times.csv"),
                 "--hand-eye", str(rec / "truth" / "hand_eye.json"),
                 "--tolerance", "0.5", "--tolerance-deg", "0.25", "--every", "3",
                 "--out", str(root / "scan"), "--quiet"]) == 0
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["map", str(root / "scan"), "--out", str(root / "map"), "--no-figures"]) == 0
    return request.param, json.loads((root / "map" / "report.json").read_text()), printed.getvalue()


def test_map_reports_the_clock_offset(mapped):
    offset, report, _ = mapped
    clock = report["clock_offset"]
    assert clock["sigma_s"] > 0
    if offset:
        # detected, late (positive), and the estimate within 4 of its sigma of the 5 ms put in. The sigma
        # treats frames as independent, and the map's errors correlate along the scan, so it is a lower
        # bound: 4 rather than 3. The correction undoes it.
        assert clock["significant"]
        assert clock["s"] > 0
        assert abs(clock["s"] - offset) < 4.0 * clock["sigma_s"], clock
        assert np.isclose(clock["clock_offset_s_corrected"], -clock["s"])
    else:
        assert not clock["significant"], clock
        assert abs(clock["s"]) < 4.0 * clock["sigma_s"], clock


def test_the_summary_says_so_only_when_significant(mapped):
    offset, report, printed = mapped
    lines = [line for line in printed.splitlines() if "clocks disagree" in line]
    if offset:
        ms = f"{1e3 * report['clock_offset']['s']:+.2f} ms"
        assert len(lines) == 1 and ms in lines[0], printed
        # the fix is the import's own option, with the value that undoes the offset
        assert f"--clock-offset {report['clock_offset']['clock_offset_s_corrected']:.6g}" in lines[0]
    else:
        assert lines == [], printed
