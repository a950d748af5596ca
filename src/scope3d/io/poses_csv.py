"""``poses.csv``: measured camera poses with their tolerances, one row per frame."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_quaternion, normalised_quaternion, quaternion_to_matrix
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

POSE_COLUMNS = (
    "image", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz",
    "tol_x_mm", "tol_y_mm", "tol_z_mm", "tol_rx_deg", "tol_ry_deg", "tol_rz_deg",
)


#: Optional column: each frame's time in seconds on the recording's clock, strictly increasing down the file
#: (a video's frames; the phantom lab writes it for every video-rate trajectory). Readers that do not need
#: it ignore it, as every reader ignores columns it does not know.
TIME_COLUMN = "time_s"

#: Extra columns of a map's ``poses_refined.csv``: each adjusted pose's remaining standard deviation (the
#: tolerance columns there hold 3 of them); :func:`read_poses_csv` reads such a file as any poses.csv.
SIGMA_COLUMNS = ("sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_rx_deg", "sigma_ry_deg", "sigma_rz_deg")


def format_poses_csv(names: list[str], poses: list[MeasuredPose], sigmas: np.ndarray | None = None,
                     times_s: np.ndarray | None = None) -> str:
    """``poses.csv`` text. sigmas : optional (m, 6) standard deviations (rotation rad, centre mm, in the order
    of :attr:`PoseTolerance.orientation_rad`, :attr:`PoseTolerance.position_mm`) written as
    :data:`SIGMA_COLUMNS` after the tolerance columns. times_s : optional (m,) frame times, seconds,
    written as :data:`TIME_COLUMN` after those."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(POSE_COLUMNS + (SIGMA_COLUMNS if sigmas is not None else ())
                    + ((TIME_COLUMN,) if times_s is not None else ()))
    for k, (name, measured) in enumerate(zip(names, poses)):
        c = measured.pose.centre
        q = matrix_to_quaternion(measured.pose.rotation.T)  # world_from_cam, (x, y, z, w)
        tol = measured.tolerance
        extra = [] if sigmas is None else [f"{v:.9g}" for v in (*sigmas[k][3:], *np.rad2deg(sigmas[k][:3]))]
        writer.writerow(
            [name, *(f"{v:.12g}" for v in c), *(f"{v:.12g}" for v in (q[3], q[0], q[1], q[2]))]
            + [f"{v:.9g}" for v in tol.position_mm]
            + [f"{v:.9g}" for v in tol.orientation_deg]
            + extra
            + ([] if times_s is None else [f"{float(times_s[k]):.9g}"])
        )
    return out.getvalue()


def read_poses_csv(path: str | Path, length_scale_to_mm: float = 1.0) -> tuple[list[str], list[MeasuredPose]]:
    """Parse ``poses.csv``. Every problem is an InputError naming the file and the row (1 = header).

    length_scale_to_mm : the file's length unit in mm (1 for mm, 1000 for m); positions and position
    tolerances are returned in mm. Returns the image names and the measured ``cam_from_world`` poses.
    """
    names, poses, _, _ = _read_pose_rows(Path(path), length_scale_to_mm)
    return names, poses


def read_pose_times(path: str | Path) -> np.ndarray | None:
    """The :data:`TIME_COLUMN` of a ``poses.csv`` (seconds, one per frame), or None when it has none. An
    InputError names the file and row of a time that is no number, not finite, or not after the row
    above's."""
    return _read_pose_rows(Path(path), 1.0)[3]


def _read_pose_rows(path: Path, length_scale_to_mm: float
                    ) -> tuple[list[str], list[MeasuredPose], list[int], np.ndarray | None]:
    """:func:`read_poses_csv`, also returning each pose's row number in the file (for error messages) and
    the frame times (:func:`read_pose_times`)."""
    if not path.is_file():
        raise InputError(f"{path}: pose file is missing")
    try:
        # utf-8-sig: spreadsheets often save CSV with a byte-order mark before the first column name.
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc})") from None
    if not rows:
        raise InputError(f"{path}: pose file is empty")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{path} row 1: missing column(s) {', '.join(missing)}")
    timed = TIME_COLUMN in header
    number_columns = POSE_COLUMNS[1:] + ((TIME_COLUMN,) if timed else ())
    col = {name: header.index(name) for name in POSE_COLUMNS + number_columns}
    names, poses, row_numbers, times = [], [], [], []
    first_row_of = {}
    for row_number, row in enumerate(rows[1:], start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        where = f"{path} row {row_number}"
        if len(row) < len(header):
            raise InputError(f"{where}: expected {len(header)} values, found {len(row)}")
        name = row[col["image"]].strip()
        if not name:
            raise InputError(f"{where}: image name is empty")
        if "/" in name or "\\" in name or name in (".", ".."):
            raise InputError(f"{where}: image name {name!r} must be a plain file name inside frames/")
        if name in first_row_of:
            raise InputError(f"{where}: image {name} is listed twice (also on row {first_row_of[name]})")
        first_row_of[name] = row_number
        values = {}
        for column in number_columns:
            text = row[col[column]].strip()
            try:
                values[column] = float(text)
            except ValueError:
                raise InputError(f"{where}: {column} = {text!r} is not a number") from None
            # inf is allowed only as a tolerance, where it means "unknown".
            if math.isnan(values[column]) or (math.isinf(values[column]) and not column.startswith("tol_")):
                raise InputError(f"{where}: {column} is {text} (NaN or infinite)")
            if column.startswith("tol_") and values[column] < 0:
                raise InputError(f"{where}: {column} = {text} is negative (lower bound above upper bound)")
        # A robot's or a spreadsheet's quaternion may be printed with few digits: rounding is normalised away.
        try:
            q, _ = normalised_quaternion([values["qx"], values["qy"], values["qz"], values["qw"]])
        except ValueError as exc:
            raise InputError(f"{where}: quaternion (qw, qx, qy, qz) is {exc}") from None
        world_from_cam = quaternion_to_matrix(q)
        centre = np.array([values["x_mm"], values["y_mm"], values["z_mm"]]) * length_scale_to_mm
        tolerance = PoseTolerance.from_degrees(
            np.array([values["tol_x_mm"], values["tol_y_mm"], values["tol_z_mm"]]) * length_scale_to_mm,
            [values["tol_rx_deg"], values["tol_ry_deg"], values["tol_rz_deg"]],
        )
        try:
            pose = Pose.from_centre(world_from_cam.T, centre)
        except ValueError as exc:  # finite in the file's unit, beyond float64 in mm
            raise InputError(f"{where}: position in mm: {exc}") from None
        if timed:
            t = values[TIME_COLUMN]
            if times and not t > times[-1]:
                raise InputError(f"{where}: {TIME_COLUMN} = {row[col[TIME_COLUMN]].strip()} is not after the row "
                                 f"above's {times[-1]:.9g} (frames are listed in time order)")
            times.append(t)
        names.append(name)
        poses.append(MeasuredPose(pose, tolerance))
        row_numbers.append(row_number)
    if not poses:
        raise InputError(f"{path}: pose file has a header but no rows")
    return names, poses, row_numbers, (np.array(times) if timed else None)
