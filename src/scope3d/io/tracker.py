"""Optical tracker exports: NDI Track's per-frame CSV (or the ``.xlsx`` some set-ups save; first sheet).

Columns by position, with or without a header row: port, tool, frame, face, state, q0, qx, qy, qz,
tx, ty, tz (mm), rms error (mm), number of markers, then per marker: state, x, y, z (mm). The quaternion
(scalar first) and translation give the tool's pose in tracker coordinates, ``tracker_from_tool``.

A row whose state is not ``OK`` ("Too Few Markers", "Missing", ...) holds garbage in its pose fields
(quaternions of norm 1e28 occur): they are never parsed. The same holds for a marker whose state is not
``OK``. Anything else malformed — a short row, a number that is not one, an ``OK`` quaternion that is not
a unit one — is refused with one :class:`~scope3d.errors.InputError` naming the file and the row.
"""
from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scope3d.errors import InputError

TOOL_COLUMNS = 14  # port .. number of markers
MARKER_COLUMNS = 4  # state, x, y, z
XLSX_MAX_ROWS = 1_048_576  # a worksheet's limit (Excel's, and the format's)
_UNIT_QUATERNION_SLACK = 1e-3  # NDI writes 4 decimals: a unit quaternion's norm is 1 within ~2e-4


@dataclass
class TrackerRecording:
    """One tool's recording.

    frame : (F,) int64, the tracker's frame numbers, in file order.
    tool_ok : (F,) bool, the tracker's own tool pose is valid.
    tool_quaternion_wxyz : (F, 4) float, ``tracker_from_tool`` rotation (NaN where not ok).
    tool_translation_mm : (F, 3) float (NaN where not ok).
    rms_mm : (F,) float, the tracker's fit error (NaN where not ok).
    markers_mm : (F, M, 3) float, marker positions in tracker coordinates, NaN where the marker is missing.
    rows : (F,) int, the file's row number (1-based, the header counted) of each frame, for messages.
    """

    frame: np.ndarray
    tool_ok: np.ndarray
    tool_quaternion_wxyz: np.ndarray
    tool_translation_mm: np.ndarray
    rms_mm: np.ndarray
    markers_mm: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def n_markers(self) -> int:
        return self.markers_mm.shape[1]


def _rows(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(row number, cells) of every row with a cell, the cells stripped and without trailing empty ones."""
    if path.suffix.lower() != ".xlsx":
        try:
            with open(path, newline="", encoding="utf-8-sig") as handle:
                for number, raw in enumerate(csv.reader(handle), start=1):
                    yield number, _trimmed(raw)
        except UnicodeDecodeError:
            raise InputError(f"{path}: not a text CSV file") from None
        except csv.Error as exc:  # a field over csv's size limit, a stray quote character
            raise InputError(f"{path}: not a CSV file ({exc})") from None
        return
    import openpyxl

    try:
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to open is the file's fault
        raise InputError(f"{path}: not a readable .xlsx workbook ({exc.__class__.__name__})") from None
    try:
        sheet = book.worksheets[0]
        # The sheet's <dimension> is a claim; believed, every row would be padded to its width (a 10 kB file
        # saying A1:XFD1048576 is 1.7e10 cells). Without it, a row is as wide as its last cell.
        sheet.reset_dimensions()
        for number, values in enumerate(sheet.iter_rows(values_only=True), start=1):
            if number > XLSX_MAX_ROWS:
                raise InputError(f"{path}: row {number}: beyond a worksheet's {XLSX_MAX_ROWS:,} rows")
            if values:
                yield number, _trimmed(["" if v is None else str(v) for v in values])
    except InputError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - the sheet is parsed lazily, row by row: its faults surface here
        raise InputError(f"{path}: not a readable .xlsx workbook ({exc.__class__.__name__})") from None
    finally:
        book.close()


def _trimmed(raw: list[str]) -> list[str]:
    row = [c.strip() for c in raw]
    while row and row[-1] == "":
        row.pop()
    return row


def _float(text: str, path: Path, row: int, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{path}: row {row}: {what} is not a number ({text!r})") from None
    if not np.isfinite(value):
        raise InputError(f"{path}: row {row}: {what} is not finite ({text!r})")
    return value


def read_tracker(path: str | Path) -> TrackerRecording:
    """Read an NDI Track export (``.csv`` or ``.xlsx``), see the module docstring."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: tracker file is missing")
    records = []
    for number, row in _rows(path):
        if not row:
            continue
        if number == 1 and len(row) > 2:
            try:
                float(row[2])
            except ValueError:
                continue  # a header row: its frame column holds a name, every data row a number
        if len(row) < TOOL_COLUMNS:
            raise InputError(f"{path}: row {number}: {len(row)} columns, a tool row needs at least {TOOL_COLUMNS}")
        frame = _float(row[2], path, number, "frame")
        n_markers = _float(row[13], path, number, "number of markers")
        if frame != int(frame) or n_markers != int(n_markers) or n_markers < 0:
            raise InputError(f"{path}: row {number}: frame and number of markers must be whole numbers")
        if abs(frame) >= 2**63:  # frame numbers are held as int64
            raise InputError(f"{path}: row {number}: frame number {row[2]} is beyond any frame counter")
        n_markers = int(n_markers)
        if len(row) < TOOL_COLUMNS + MARKER_COLUMNS * n_markers:
            raise InputError(f"{path}: row {number}: {n_markers} markers announced but only "
                             f"{(len(row) - TOOL_COLUMNS) // MARKER_COLUMNS} present")
        ok = row[4].upper() == "OK"
        t = np.full(3, np.nan)
        quat, rms = np.full(4, np.nan), np.nan
        if ok:
            quat = np.array([_float(row[5 + k], path, number, name) for k, name in enumerate(("q0", "qx", "qy", "qz"))])
            t = np.array([_float(row[9 + k], path, number, name) for k, name in enumerate(("tx", "ty", "tz"))])
            rms = _float(row[12], path, number, "rms error")
            if abs(np.linalg.norm(quat) - 1.0) > _UNIT_QUATERNION_SLACK:
                raise InputError(f"{path}: row {number}: the tool is OK but its quaternion has norm "
                                 f"{np.linalg.norm(quat):.6g}, not 1")
        markers = np.full((n_markers, 3), np.nan)
        for m in range(n_markers):
            base = TOOL_COLUMNS + MARKER_COLUMNS * m
            if row[base].upper() == "OK":
                markers[m] = [_float(row[base + 1 + k], path, number, f"marker {m + 1} {axis}")
                              for k, axis in enumerate("xyz")]
        records.append((int(frame), ok, quat, t, rms, markers, number))
    if not records:
        raise InputError(f"{path}: no tracker rows")
    width = max(len(r[5]) for r in records)
    markers = np.full((len(records), width, 3), np.nan)
    for k, r in enumerate(records):
        markers[k, :len(r[5])] = r[5]
    return TrackerRecording(np.array([r[0] for r in records], np.int64), np.array([r[1] for r in records]),
                            np.stack([r[2] for r in records]), np.stack([r[3] for r in records]),
                            np.array([r[4] for r in records]), markers, np.array([r[6] for r in records]))
