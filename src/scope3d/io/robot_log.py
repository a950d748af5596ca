"""Robot pose logs: one flange (or tool, or tracked body) pose per row with a timestamp, as robot
controllers and trackers write them, and the frame-time tables that put a scope's frames on the log's clock.

A log is a CSV file with a header. One column holds the time, the others the pose, in one of the layouts
robot software writes (:data:`POSE_FORMATS`; the column names are the defaults, and ``columns`` maps them
onto a file's own names):

=====================  ===========================================  =========================================
format                 columns                                      what they are
=====================  ===========================================  =========================================
``xyz-qxyzw``          ``x y z qx qy qz qw``                        position, unit quaternion scalar-last (ROS)
``xyz-qwxyz``          ``x y z qw qx qy qz``                        position, unit quaternion scalar-first (ABB)
``xyz-euler-AXES``     ``x y z r1 r2 r3``                           position, Euler angles in the order of
                                                                    ``AXES`` (SciPy's convention: ``xyz``
                                                                    lower case = extrinsic, ``ZYX`` upper
                                                                    case = intrinsic; KUKA's A, B, C is
                                                                    ``ZYX``), degrees unless told otherwise
``xyz-rotvec``         ``x y z rx ry rz``                           position, rotation vector (Universal
                                                                    Robots), degrees unless told otherwise
``matrix44``           ``m00 m01 ... m33``                          a row-major 4x4 homogeneous matrix
=====================  ===========================================  =========================================

Every row's pose is ``base_from_flange`` (the flange's position and orientation in the robot's base frame,
what a controller reports), in the log's length unit; the time column (``t`` by default) in the log's time
unit. Rows are validated as they are read: a non-number, NaN or infinity, a quaternion whose norm is
farther than :data:`~scope3d.geometry.rotation.ROTATION_ROUNDING_TOLERANCE` from 1, a matrix that is not a
rounded rotation (or whose last row is not ``0 0 0 1``), a time not after the previous row's: each is an
:class:`~scope3d.errors.InputError` naming the file and the row (row 1 is the header), or, with
``drop_bad_rows``, the row is left out and counted by reason.
"""
from __future__ import annotations

import csv
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from scope3d.errors import InputError
from scope3d.geometry.rotation import ROTATION_ROUNDING_TOLERANCE, nearest_rotation

LENGTH_UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3}
TIME_UNITS_TO_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ANGLE_UNITS_TO_RAD = {"deg": math.pi / 180.0, "rad": 1.0}

_MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))
#: Fixed pose formats -> their default column names (``xyz-euler-AXES`` is added by :func:`pose_columns`).
POSE_FORMATS = {
    "xyz-qxyzw": ("x", "y", "z", "qx", "qy", "qz", "qw"),
    "xyz-qwxyz": ("x", "y", "z", "qw", "qx", "qy", "qz"),
    "xyz-rotvec": ("x", "y", "z", "rx", "ry", "rz"),
    "matrix44": _MATRIX_COLUMNS,
}
_EULER = re.compile(r"xyz-euler-([xyz]{3}|[XYZ]{3})$")


def pose_columns(pose_format: str) -> tuple[str, ...]:
    """The default column names of ``pose_format`` (table in the module docstring); ValueError if unknown."""
    if pose_format in POSE_FORMATS:
        return POSE_FORMATS[pose_format]
    match = _EULER.match(pose_format)
    if match:
        axes = match.group(1)
        if axes[0] == axes[1] or axes[1] == axes[2]:
            raise ValueError(f"pose format {pose_format!r}: two successive Euler axes must differ")
        return ("x", "y", "z", "r1", "r2", "r3")
    raise ValueError(f"unknown pose format {pose_format!r}; known: {', '.join(POSE_FORMATS)}, "
                     "xyz-euler-AXES (e.g. xyz-euler-ZYX)")


@dataclass(frozen=True)
class PoseLogFormat:
    """How to read a robot log.

    pose_format : a key of :data:`POSE_FORMATS` or ``xyz-euler-AXES``. columns : default column name ->
        the file's column name, for the columns whose names differ (e.g. ``{"t": "time", "x": "X_m"}``).
    length_unit : the positions' unit (mm, cm, m, um). time_unit : the time column's (s, ms, us, ns).
    angle_unit : Euler angles' and rotation vectors' unit (deg, rad). drop_bad_rows : leave out (and
        count) rows that fail a check instead of refusing the file.
    """

    pose_format: str = "xyz-qxyzw"
    columns: dict[str, str] = field(default_factory=dict)
    length_unit: str = "mm"
    time_unit: str = "s"
    angle_unit: str = "deg"
    drop_bad_rows: bool = False

    def __post_init__(self) -> None:
        names = ("t",) + pose_columns(self.pose_format)
        unknown = sorted(set(self.columns) - set(names))
        if unknown:
            raise ValueError(f"column map names {', '.join(unknown)}, which format {self.pose_format} does not "
                             f"have (its columns: {', '.join(names)})")
        for label, value, table in (("length unit", self.length_unit, LENGTH_UNITS_TO_MM),
                                    ("time unit", self.time_unit, TIME_UNITS_TO_S),
                                    ("angle unit", self.angle_unit, ANGLE_UNITS_TO_RAD)):
            if value not in table:
                raise ValueError(f"unknown {label} {value!r}; known: {', '.join(table)}")

    def file_columns(self) -> tuple[str, ...]:
        """The columns to find in the file: the time first, then the pose's, by the file's names."""
        return tuple(self.columns.get(name, name) for name in ("t",) + pose_columns(self.pose_format))


@dataclass(frozen=True)
class PoseLog:
    """A validated robot log, in mm, seconds and rotation matrices.

    times_s : (N,) strictly increasing. rotations : (N, 3, 3) ``base_from_flange``. positions_mm : (N, 3)
    the flange in the base. rows : (N,) each pose's row in the file (1 = header). dropped : reason ->
    number of rows left out (only with ``drop_bad_rows``). first_dropped_row : reason -> the first such row.
    """

    path: Path
    times_s: np.ndarray
    rotations: np.ndarray
    positions_mm: np.ndarray
    rows: np.ndarray
    dropped: dict[str, int]
    first_dropped_row: dict[str, int]

    def __len__(self) -> int:
        return len(self.times_s)


def read_pose_log(path: str | Path, log_format: PoseLogFormat = PoseLogFormat()) -> PoseLog:
    """Read and validate a robot log (module docstring). InputError naming the file and row on a problem."""
    path = Path(path)
    header, body = _read_csv(path)
    wanted = log_format.file_columns()
    missing = [c for c in wanted if c not in header]
    if missing:
        raise InputError(f"{path}: no column {', '.join(repr(c) for c in missing)} (format {log_format.pose_format}; "
                         f"the file has {', '.join(header)}); name the file's columns with a column map")
    index = [header.index(c) for c in wanted]
    values, bad = _numbers(body, index)
    rows = np.arange(2, len(body) + 2)
    reasons = np.full(len(body), "", dtype=object)
    reasons[bad] = "not a finite number"
    is_matrix = log_format.pose_format == "matrix44"
    rotations, problem = _rotations(values[:, 1:] if is_matrix else values[:, 4:], log_format)
    reasons[(reasons == "") & (problem != "")] = problem[(reasons == "") & (problem != "")]
    positions = values[:, 1:].reshape(-1, 4, 4)[:, :3, 3] if is_matrix else values[:, 1:4]
    positions = positions * LENGTH_UNITS_TO_MM[log_format.length_unit]
    times = values[:, 0] * TIME_UNITS_TO_S[log_format.time_unit]
    if not log_format.drop_bad_rows:
        first = np.flatnonzero(reasons != "")
        if first.size:
            k = first[0]
            raise InputError(f"{path} row {rows[k]}: {reasons[k]} ({_shown(body[k], index, wanted)})")
    keep = reasons == ""
    # time must increase along the kept rows; a row at or before the last kept time is out of order
    ok_time = np.zeros(len(body), dtype=bool)
    last = -math.inf
    for k in np.flatnonzero(keep):
        if times[k] > last:
            ok_time[k], last = True, times[k]
        elif not log_format.drop_bad_rows:
            raise InputError(f"{path} row {rows[k]}: time {body[k][index[0]].strip()} is not after the previous "
                             f"row's; a log's rows must be in time order")
        else:
            reasons[k] = "time not after the previous row's"
    keep &= ok_time
    dropped = Counter(r for r in reasons if r)
    first_row = {}
    for k in np.flatnonzero(reasons != ""):
        first_row.setdefault(reasons[k], int(rows[k]))
    if keep.sum() < 2:
        raise InputError(f"{path}: {int(keep.sum())} usable pose row(s), need at least 2 to interpolate"
                         + (f" ({sum(dropped.values())} dropped)" if dropped else ""))
    return PoseLog(path, times[keep], rotations[keep], positions[keep], rows[keep], dict(dropped), first_row)


def read_frame_times(path: str | Path, time_unit: str = "s") -> dict[str, float]:
    """A frame-time table: CSV with a header ``image,t`` (more columns are ignored), one row per frame, the
    time on the robot log's clock in ``time_unit``. Returns image name -> seconds. InputError naming the
    file and row for a missing column, a non-number, a repeated image."""
    path = Path(path)
    header, body = _read_csv(path)
    for column in ("image", "t"):
        if column not in header:
            raise InputError(f"{path}: no column {column!r} (the file has {', '.join(header)}); a frame-time table "
                             "has a header 'image,t'")
    i_name, i_t = header.index("image"), header.index("t")
    if time_unit not in TIME_UNITS_TO_S:
        raise ValueError(f"unknown time unit {time_unit!r}; known: {', '.join(TIME_UNITS_TO_S)}")
    out: dict[str, float] = {}
    for row_number, row in enumerate(body, start=2):
        if len(row) <= max(i_name, i_t):
            raise InputError(f"{path} row {row_number}: {len(row)} column(s), the header has {len(header)}")
        name = row[i_name].strip()
        try:
            t = float(row[i_t])
        except ValueError:
            raise InputError(f"{path} row {row_number}: time {row[i_t].strip()!r} is not a number") from None
        if not math.isfinite(t):
            raise InputError(f"{path} row {row_number}: time {row[i_t].strip()} is not finite")
        if not name:
            raise InputError(f"{path} row {row_number}: empty image name")
        if name in out:
            raise InputError(f"{path} row {row_number}: image {name} is listed twice")
        out[name] = t * TIME_UNITS_TO_S[time_unit]
    if not out:
        raise InputError(f"{path}: no rows")
    return out


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    if not path.is_file():
        raise InputError(f"{path}: file is missing")
    try:
        # utf-8-sig: spreadsheets save CSV with a byte-order mark before the first column name
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if any(cell.strip() for cell in r)]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc})") from None
    if not rows:
        raise InputError(f"{path}: file is empty")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        repeated = sorted({h for h in header if header.count(h) > 1})
        raise InputError(f"{path} row 1: column {repeated[0]!r} appears twice")
    return header, rows[1:]


def _numbers(body: list[list[str]], index: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) floats of the wanted columns, NaN where a cell is missing or not a number, and which
    rows have any such cell (or a NaN or infinity)."""
    width = max(index) + 1
    try:  # the fast path: every row complete and numeric
        table = np.array([[r[i] for i in index] for r in body], dtype=float) if body else np.zeros((0, len(index)))
    except (ValueError, IndexError):
        table = np.full((len(body), len(index)), np.nan)
        for k, r in enumerate(body):
            if len(r) < width:
                continue
            for j, i in enumerate(index):
                try:
                    table[k, j] = float(r[i])
                except ValueError:
                    pass
    return table, ~np.all(np.isfinite(table), axis=1)


def _rotations(values: np.ndarray, log_format: PoseLogFormat) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations from the pose columns after x, y, z, and a reason per row ("" when fine);
    rows with non-finite cells get the identity (they are refused or dropped for that already)."""
    n = len(values)
    problem = np.full(n, "", dtype=object)
    finite = np.all(np.isfinite(values), axis=1) if n else np.zeros(0, dtype=bool)
    rotations = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    fmt = log_format.pose_format
    if fmt in ("xyz-qxyzw", "xyz-qwxyz"):
        q = values if fmt == "xyz-qxyzw" else values[:, [1, 2, 3, 0]]
        norm = np.linalg.norm(q, axis=1)
        bad = finite & (np.abs(norm - 1.0) > ROTATION_ROUNDING_TOLERANCE)
        problem[bad] = [f"quaternion norm {v:.6g} is not 1 (rounding explains 1 +- {ROTATION_ROUNDING_TOLERANCE:g})"
                        for v in norm[bad]]
        good = finite & ~bad
        if good.any():
            rotations[good] = Rotation.from_quat(q[good] / norm[good, None]).as_matrix()
    elif fmt == "matrix44":
        m = values.reshape(n, 4, 4)
        for k in np.flatnonzero(finite):
            if np.abs(m[k, 3] - [0.0, 0.0, 0.0, 1.0]).max() > ROTATION_ROUNDING_TOLERANCE:
                problem[k] = f"last matrix row is {m[k, 3].tolist()}, not 0 0 0 1"
                continue
            try:
                rotations[k] = nearest_rotation(m[k, :3, :3])[0]
            except ValueError as exc:
                problem[k] = f"rotation part is {exc}"
    else:
        angles = values * ANGLE_UNITS_TO_RAD[log_format.angle_unit]
        if finite.any():
            if fmt == "xyz-rotvec":
                rotations[finite] = Rotation.from_rotvec(angles[finite]).as_matrix()
            else:
                rotations[finite] = Rotation.from_euler(fmt.rsplit("-", 1)[1], angles[finite]).as_matrix()
    return rotations, problem


def _shown(row: list[str], index: list[int], names: tuple[str, ...]) -> str:
    return ", ".join(f"{n}={row[i].strip() if i < len(row) else '(missing)'}" for n, i in zip(names, index))

