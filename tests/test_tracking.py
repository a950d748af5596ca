"""Marker tracking (NDI exports, plate fit, Kalman filter) and pose fusion, against known motions.

Noise levels and tolerances come from the simulated sensors: markers with sigma = 0.25 mm per axis (NDI
Polaris Spectra's stated RMS); a four-marker plate of ~50 mm then fits to ~0.13 mm in position per frame
(sigma / sqrt(4)), and a constant-velocity filter averaging over its time constant must do better.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.estimators.kalman import KalmanOptions, PoseKalmanFilter, tolerance_covariance
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_quaternion, rotvec_to_matrix
from scope3d.io.tracker import read_tracker
from scope3d.phantoms.trajectories import approach_trajectory
from scope3d.sensor.pose_tolerance import PoseTolerance, perturb_poses_uniform

RATE_HZ = 60.0
MARKER_SIGMA_MM = 0.25
PLATE_MM = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 40.0, 0.0], [30.0, 30.0, 10.0]])


def _truth(n=240):
    """A plate gliding on a smooth curve at 60 Hz (constant-velocity model is only approximately right)."""
    t = np.arange(n) / RATE_HZ
    centre = np.stack([300 + 40 * np.sin(0.5 * t), -20 + 30 * t, -1500 + 5 * np.cos(t)], 1)
    rotations = [rotvec_to_matrix(np.array([0.2 * np.sin(0.3 * s), 0.1 * s, 0.05])) for s in t]
    return [Pose.from_centre(r, c) for r, c in zip(rotations, centre)]  # plate_from_tracker


def _markers(truth, seed):
    rng = np.random.default_rng(seed)
    return np.stack([p.inverse().transform(PLATE_MM) for p in truth]) + rng.normal(0, MARKER_SIGMA_MM, (len(truth), 4, 3))


def _position_errors(estimates, truth):
    return np.array([np.linalg.norm(e.centre - t.centre) for e, t in zip(estimates, truth)])


def test_kalman_on_a_known_motion_beats_the_raw_measurements():
    truth = _truth()
    rng = np.random.default_rng(0)
    sigma = 0.3  # mm per axis on the measured centre, 0.3 deg on the orientation
    cov = np.diag(np.r_[np.full(3, np.deg2rad(0.3) ** 2), np.full(3, sigma**2)])
    kf = PoseKalmanFilter(KalmanOptions())
    raw, filt = [], []
    for k, p in enumerate(truth):
        m = Pose.from_centre(rotvec_to_matrix(rng.normal(0, np.deg2rad(0.3), 3)) @ p.rotation,
                             p.centre + rng.normal(0, sigma, 3))
        if k:
            kf.predict(1 / RATE_HZ)
        kf.update(m, cov)
        raw.append(m)
        filt.append(kf.pose)
    e_raw, e_filt = _position_errors(raw, truth)[30:], _position_errors(filt, truth)[30:]  # after settling
    # raw 3-D error of N(0, 0.3) per axis: mean ~0.48 mm; the filter averages several frames
    assert np.mean(e_filt) < 0.6 * np.mean(e_raw)
    # the filter's covariance is honest: its sigma is within a factor 2 of the actual error spread
    sd = np.sqrt(np.diag(kf.pose_covariance)[3:])
    assert 0.5 < np.sqrt(np.mean(e_filt**2) / 3) / sd.mean() < 2.0
    with pytest.raises(ValueError):
        kf.predict(-1.0)


def _write_ndi(path, truth, markers, *, header=True, missing=(), drop_markers=()):
    tool_from_plate = Pose.from_rotvec(np.array([0.1, -0.2, 0.3]), np.array([5.0, -3.0, 12.0]))
    lines = []
    if header:
        lines.append("Port,Tool,Frame,Face,State,Q0,Qx,Qy,Qz,Tx,Ty,Tz,Error,Markers," +
                     ",".join("State,Tx,Ty,Tz" for _ in range(4)))
    for k, p in enumerate(truth):
        tracker_from_tool = (tool_from_plate @ p).inverse()
        q = matrix_to_quaternion(tracker_from_tool.rotation)
        state = "Missing" if k in missing else "OK"
        pose = ([q[3], q[0], q[1], q[2], *tracker_from_tool.translation] if k not in missing
                else [1e28, -3e27, 0, 0, 123456.0, 0, 0])
        cells = ["1", "plate", str(1000 + k), "1", state, *(f"{v:.6f}" for v in pose), "0.12", "4"]
        for m in range(4):
            if k in drop_markers and m < 2:
                cells += ["Missing", "nan", "", "-1e30"]
            else:
                cells += ["OK", *(f"{v:.4f}" for v in markers[k, m])]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def test_tracker_csv_with_missing_rows_and_markers(tmp_path, capsys):
    truth = _truth(120)
    markers = _markers(truth, seed=1)
    missing, dropped = set(range(20, 26)), set(range(40, 46))
    csv = tmp_path / "ndi.csv"
    _write_ndi(csv, truth, markers, missing=missing, drop_markers=dropped)
    rec = read_tracker(csv)
    assert len(rec) == 120 and rec.tool_ok.sum() == 114 and rec.n_markers == 4
    assert np.isnan(rec.markers_mm[40, :2]).all() and np.isfinite(rec.markers_mm[20]).all()
    out = tmp_path / "out"
    assert main(["track-markers", str(csv), "--out", str(out), "--json"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert json.loads(capsys.readouterr().out) == report  # --json: the report and nothing else on stdout
    assert (out / "report.html").is_file()
    assert report["n_frames"] == 120 and report["n_fitted"] == 114 and report["n_predicted"] == 6
    assert [f["frame"] - 1000 for f in report["frames"] if f["predicted"]] == sorted(dropped)
    # agreement with the tracker's own (noise-free) tool pose after one constant transform: the filtered
    # plate is good to ~0.1-0.2 mm (a 0.25 mm marker noise, several frames averaged)
    assert report["median_position_diff_mm"] < 0.25 and report["median_orientation_diff_deg"] < 0.3
    assert len((out / "poses.csv").read_text().splitlines()) == 121
    # the same without a header, and as a workbook's first sheet
    _write_ndi(csv, truth, markers, header=False, missing=missing, drop_markers=dropped)
    assert len(read_tracker(csv)) == 120
    import openpyxl

    book = openpyxl.Workbook()
    for line in csv.read_text().splitlines():
        book.active.append([float(c) if c.replace(".", "", 1).replace("-", "", 1).isdigit() else c for c in line.split(",")])
    book.save(tmp_path / "ndi.xlsx")
    rec_x = read_tracker(tmp_path / "ndi.xlsx")
    np.testing.assert_allclose(rec_x.markers_mm, rec.markers_mm, atol=1e-4)


def test_filter_beats_the_raw_plate_fit(tmp_path):
    """The file's tool pose is the noise-free truth (a constant transform away from the plate's frame), so
    the report's agreement with it is the error; the filter must lower it (the brief's 'with and without')."""
    truth = _truth(240)
    csv = tmp_path / "ndi.csv"
    _write_ndi(csv, truth, _markers(truth, seed=2), header=False)
    assert main(["track-markers", str(csv), "--out", str(tmp_path / "raw"), "--no-filter"]) == 0
    assert main(["track-markers", str(csv), "--out", str(tmp_path / "kf")]) == 0
    raw = json.loads((tmp_path / "raw" / "report.json").read_text())
    kf = json.loads((tmp_path / "kf" / "report.json").read_text())
    # a raw four-marker fit: ~sigma * sqrt(3 / 4) = 0.22 mm in 3-D
    assert 0.1 < raw["median_position_diff_mm"] < 0.35
    assert kf["median_position_diff_mm"] < 0.8 * raw["median_position_diff_mm"]
    assert kf["median_orientation_diff_deg"] < raw["median_orientation_diff_deg"]


@pytest.mark.parametrize("row, message", [
    ("1,plate,1000,1,OK,1,0,0", "row 1: 8 columns"),
    ("1,plate,1000,1,OK,abc,0,0,0,1,2,3,0.1,0", "row 1: q0 is not a number"),
    ("1,plate,1000,1,OK,2,0,0,0,1,2,3,0.1,0", "row 1: the tool is OK but its quaternion has norm 2"),
    ("1,plate,1000,1,OK,1,0,0,0,1,2,3,0.1,2,OK,1,2,3", "row 1: 2 markers announced but only 1"),
    ("1,plate,1000,1,OK,1,0,0,0,1,2,3,0.1,1,OK,1,x,3", "row 1: marker 1 y is not a number"),
])
def test_malformed_rows_are_refused_naming_the_row(tmp_path, row, message):
    path = tmp_path / "bad.csv"
    path.write_text(row + "\n")
    with pytest.raises(InputError, match=message):
        read_tracker(path)
    assert main(["track-markers", str(path), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()


def test_fusion_beats_every_single_source():
    """Robot (uniform +-1 mm, +-0.5 deg box), tracker (0.2/0.2/0.5 mm, 0.5 deg: the reference's Table 4.1)
    and vision (0.1 mm, 0.3 deg: the localization's error on the dome), each drawn from its own noise on a
    30-frame approach at 10 Hz; fused by one filter, the error is below every source's."""
    truth = approach_trajectory(60, [5.5, 0.0, -6.0]).poses
    rng = np.random.default_rng(7)
    robot = perturb_poses_uniform(truth, 1.0, np.deg2rad(0.5), seed=8)
    tracker_sd = np.r_[np.full(3, np.deg2rad(0.5)), 0.2, 0.2, 0.5]
    vision_sd = np.r_[np.full(3, np.deg2rad(0.3)), np.full(3, 0.1)]

    def draw(p, sd):
        return Pose.from_centre(rotvec_to_matrix(rng.normal(0, sd[:3])) @ p.rotation, p.centre + rng.normal(0, sd[3:]))

    tracker = [draw(p, tracker_sd) for p in truth]
    vision = [draw(p, vision_sd) for p in truth]
    kf = PoseKalmanFilter(KalmanOptions(acceleration_sigma_mm_s2=20.0))
    fused = []
    for k in range(len(truth)):
        if k:
            kf.predict(0.1)
        kf.update_measured(robot[k])
        kf.update(tracker[k], np.diag(tracker_sd**2))
        kf.update(vision[k], np.diag(vision_sd**2))
        fused.append(kf.pose)
    err = {name: np.median(_position_errors(p, truth)) for name, p in
           (("robot", [m.pose for m in robot]), ("tracker", tracker), ("vision", vision), ("fused", fused))}
    assert err["fused"] < min(err["robot"], err["tracker"], err["vision"]), err
    rot = {name: np.median([np.linalg.norm(np.rad2deg(Pose(a.rotation @ b.rotation.T, np.zeros(3)).rotvec))
                            for a, b in zip(p, truth)]) for name, p in
           (("robot", [m.pose for m in robot]), ("tracker", tracker), ("vision", vision), ("fused", fused))}
    assert rot["fused"] < min(rot["robot"], rot["tracker"], rot["vision"]), rot
    # and the fused covariance is a tighter box for BCBA than the robot's own
    assert np.all(np.sqrt(np.diag(kf.pose_covariance)[3:]) * 3 < 1.0)
    np.testing.assert_allclose(np.diag(tolerance_covariance(PoseTolerance(np.ones(3), np.zeros(3))))[3:], 1 / 3)
