"""Every file reader, fed mutated copies of a valid file: the only outcomes are a parse or one InputError line
naming the file, in bounded memory. Short hypothesis runs here (derandomised, so a failure reproduces); the
long runs are benchmarks/bench_fuzz.py. The regression tests below are the crashes those runs found."""
import resource
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzz_targets import MUTATIONS, build_targets, huge_header, mutate
from scope3d.errors import InputError

REPO = Path(__file__).resolve().parents[1]
HANG_S = 600  # a CLI run here takes seconds: this only stops one that hangs

# 14 targets x 60 examples take ~10-20 s on the loaded 2-core machine; each example is a few ms. The
# deadline only catches a reader that parses something enormous: 60 s, far above any example's time on a
# loaded machine (2 s was a speed limit that load could reach, issue 31); speed is bench_fuzz.py's.
SHORT_RUN = settings(max_examples=60, deadline=60_000, derandomize=True, database=None,
                     suppress_health_check=[HealthCheck.too_slow])

mutation_lists = st.lists(
    st.tuples(st.sampled_from(MUTATIONS), st.floats(0, 1, exclude_max=True), st.floats(0, 1, exclude_max=True),
              st.integers(0, 999)),
    min_size=1, max_size=3,
)


@pytest.fixture(scope="module")
def targets(tmp_path_factory):
    return build_targets(tmp_path_factory.mktemp("fuzz"))


TARGET_NAMES = ["dataset.json", "poses.csv", "camera.json", "bal", "bounds", "colmap cameras.txt",
                "colmap images.txt", "colmap points3D.txt", "ply ascii", "ply binary cloud", "ply binary mesh",
                "middlebury par", "middlebury readme", "image png", "image jpeg", "tracker csv", "tracker xlsx", "rosbag ros1",
                "rosbag2 metadata.yaml", "rosbag2 storage", "video mp4", "scan plan", "intrinsic bounds", "quadrants",
                "map points", "hand-eye robot poses", "report.json", "robot log", "robot log matrix44", "frame times",
                "hand_eye.json"]
# A bag import compiles the bag's message types (rosbags) and writes a dataset: ~0.3 s an input on this
# machine, so fewer short examples there; the long run (benchmarks/bench_fuzz.py) gives them as much time.
EXAMPLES = {"rosbag ros1": 12, "rosbag2 metadata.yaml": 12, "rosbag2 storage": 12}
# Headers whose claim the parser is allowed to ignore and parse the file anyway (as long as memory stays
# bounded): the Middlebury README has no count; SQLite trusts the file's size over its header's page count;
# rosbags reads a ROS 2 bag's messages, not its metadata's message count; FFmpeg rebuilds a sample table it
# finds inconsistent; the tracker reads a workbook's rows, not its <dimension>; a robot log has no count, and
# read with drop_bad_rows it parses the seed repeated (the repeated header lines and times dropped).
HUGE_MAY_PARSE = {"middlebury readme", "rosbag2 storage", "rosbag2 metadata.yaml", "video mp4", "tracker xlsx",
                  "robot log matrix44"}


def test_the_target_list_is_complete(targets):
    assert sorted(targets) == sorted(TARGET_NAMES)
    for target in targets.values():  # every seed is a valid file: mutations start from a correct parse
        assert target.run(target.seed) == "ok", target.name


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_mutated_files_parse_or_are_refused_in_one_line(targets, name):
    target = targets[name]

    @settings(SHORT_RUN, max_examples=EXAMPLES.get(name, SHORT_RUN.max_examples))
    @given(mutation_lists)
    def check(mutations):
        data = target.seed
        for kind, a, b, pick in mutations:
            data = mutate(data, kind, a, b, pick)
        target.run(data)  # raises FuzzCrash on any other outcome

    try:
        check()
    finally:
        target.restore()


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_a_header_claiming_a_billion_elements_allocates_nothing_of_that_size(targets, name):
    """10^9 points would take 8-24 GB; the readers check the claim against the file before allocating."""
    target = targets[name]
    data = huge_header(target)
    rss_before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tracemalloc.start()
    try:
        outcome = target.run(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        target.restore()
    # the files are < 1 MB; 64 MB leaves room for parsing overheads, and is 1/100 of the claim
    assert peak < 64e6, f"{name}: {peak / 1e6:.0f} MB"
    # what tracemalloc does not see (OpenCV, FFmpeg, SQLite): the process's peak resident memory may not
    # grow by more than 100 MB (the noise of this process's own growth; the claims are 8-24 GB)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before_kb < 100_000, name
    if name not in HUGE_MAY_PARSE:
        assert outcome == "refused", name


# --- regressions: the crashes the fuzzing found, each now one line naming the file -----------------


def _expect_refusal(call, path, *fragments):
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message


def _tiny_bal(path: Path, header: str = "2 1 2", observation1: str = "1 0") -> Path:
    cameras = ["0", "0", "0", "0", "0", "-5", "500", "0", "0", "0.1", "0", "0", "1", "0", "-5", "500", "0", "0"]
    path.write_text("\n".join([header, "0 0 1.0 2.0", f"{observation1} 3.0 4.0", *cameras, "0", "0", "0"]) + "\n")
    return path


def test_bal_with_a_stray_non_utf8_byte_is_a_one_line_refusal_in_the_cli(tmp_path):
    """The known crash: ``scope3d bundle-adjust`` exited 1 with a UnicodeDecodeError traceback."""
    path = _tiny_bal(tmp_path / "p.txt")
    data = path.read_bytes()
    path.write_bytes(data[:20] + b"\xe9" + data[20:])
    proc = subprocess.run([sys.executable, "-m", "scope3d.cli.main", "bundle-adjust", str(path), "--report",
                           str(tmp_path / "r.json")], capture_output=True, text=True, cwd=REPO,
                          env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"}, timeout=HANG_S)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and str(path) in proc.stderr and "0xe9" in proc.stderr, proc.stderr
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("header, fragment", [("nan 1 2", "bad BAL header"), ("inf 1 2", "bad BAL header"),
                                              ("2.5 1 2", "bad BAL header"), ("2 0 2", "bad BAL header")])
def test_bal_header_that_is_no_count(tmp_path, header, fragment):
    from scope3d.estimators.bundle import read_bal

    path = _tiny_bal(tmp_path / "p.txt", header=header)
    _expect_refusal(lambda: read_bal(path), path, fragment)


def test_bal_observation_of_a_camera_not_in_the_file(tmp_path):
    from scope3d.estimators.bundle import read_bal

    path = _tiny_bal(tmp_path / "p.txt", observation1="2 0")
    _expect_refusal(lambda: read_bal(path), path, "observation 1 (0-based)", "2 cameras")


@pytest.mark.parametrize("rx", ["1e308", "1e200", "4.6e15"])
def test_bal_rotation_vector_too_large_to_name_a_rotation_is_refused(tmp_path, rx):
    """Found by the long random fuzz run (issue 16): a rotation vector component of 1e308 is finite, so the
    reader took it, and Rodrigues' formula overflowed: the bundle problem refused 'rotations row 0 has NaN
    or infinite values' without naming the file. Refused by the reader now, naming file and camera; an
    angle of thousands of radians (a solver's unwrapped output) is still a rotation."""
    from scope3d.estimators.bundle import bal_to_problem, read_bal

    path = _tiny_bal(tmp_path / "p.txt")
    lines = path.read_text().splitlines()
    lines[12] = rx  # camera 1's rx (header, 2 observations, camera 0's 9 numbers before it)
    path.write_text("\n".join(lines) + "\n")
    _expect_refusal(lambda: read_bal(path), path, "camera 1 (0-based)", "rotation")
    lines[12] = "6283.2"  # 1000 turns: the same rotation as 0.0147 rad
    path.write_text("\n".join(lines) + "\n")
    rotation = bal_to_problem(read_bal(path)).reference_rotations[1]
    assert np.all(np.isfinite(rotation)) and np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)


@pytest.fixture
def bal_problem(tmp_path):
    from scope3d.estimators.bundle import bal_to_problem, read_bal

    return bal_to_problem(read_bal(_tiny_bal(tmp_path / "p.txt")))


@pytest.mark.parametrize("rule, fragments", [
    (b"camera 0 all fixed \xff\n", ["0xff", "not ASCII"]),
    (b"point 0-999999999999 x fixed\n", ["line 1", "out of range [0, 1)"]),
    (b"point 99999999999999999999999 x fixed\n", ["line 1", "out of range"]),
    (b"shell * 0 0 0 5 1\n", ["line 1", "shell bound"]),
    (b"depth * 0 0 0 0 0 0 1 2\n", ["line 1", "depth bound"]),
])
def test_bounds_file_crashes_are_refusals_naming_file_and_line(tmp_path, bal_problem, rule, fragments):
    from scope3d.estimators.bundle import apply_bounds_file

    path = tmp_path / "bounds.txt"
    path.write_bytes(rule)
    tracemalloc.start()
    try:
        _expect_refusal(lambda: apply_bounds_file(bal_problem, path), path, *fragments)
        assert tracemalloc.get_traced_memory()[1] < 16e6  # '0-999999999999' was expanded before the check
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("text, fragment", [
    ('{"width": 1' + "0" * 5000 + "}", "not valid JSON"),
    ('{"width": ' + "[" * 50000 + "]" * 50000 + "}", "nested too deeply"),
    ('{"width": 32, "height": 24, "fx": 1' + "0" * 400 + ', "fy": 1, "cx": 1, "cy": 1, "k1": 0, "k2": 0}',
     "fx is too large"),
    ('{"width": 32, "height": 24, "fx": 1, "fy": 1, "cx": 1, "cy": 1, "k1": 0, "k2": 0, "mask_radius_px": 1'
     + "0" * 400 + "}", "mask_radius_px"),
])
def test_camera_json_with_enormous_numbers_or_nesting(tmp_path, text, fragment):
    from scope3d.io.camera_json import read_camera_json

    path = tmp_path / "camera.json"
    path.write_text(text)
    _expect_refusal(lambda: read_camera_json(path), path, fragment)


def test_colmap_points_with_impossible_colours_or_ids(targets):
    from scope3d.io.colmap import read_colmap_text

    target = targets["colmap points3D.txt"]
    lines = target.seed.decode().splitlines()
    row = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    tokens = lines[row].split()
    try:
        for bad, fragment in (((4, "256"), "R G B"), ((5, "-1"), "R G B"), ((6, "1.5"), "R G B"),
                              ((8, "9" * 25), "integers")):
            edited = list(tokens)
            edited[bad[0]] = bad[1]
            target.path.write_text("\n".join(lines[:row] + [" ".join(edited)] + lines[row + 1:]) + "\n")
            _expect_refusal(lambda: read_colmap_text(target.path.parent), target.path, fragment)
    finally:
        target.restore()


def test_middlebury_par_with_an_enormous_count_or_translation(tmp_path):
    from fuzz_targets import PAR_SEED
    from scope3d.io.middlebury import read_middlebury_par

    path = tmp_path / "x_par.txt"
    path.write_bytes(b"2" * 5000 + PAR_SEED[1:])
    _expect_refusal(lambda: read_middlebury_par(path), path, "line 1", "number of images")
    path.write_bytes(PAR_SEED.replace(b"0.6\n", b"1e306\n"))
    _expect_refusal(lambda: read_middlebury_par(path), path, "line 3", "t in mm")


def test_middlebury_readme_with_signs_that_are_no_numbers_has_no_box(tmp_path):
    from scope3d.io.middlebury import read_middlebury_bounding_box

    path = tmp_path / "README.txt"
    path.write_text("bounding box (-- 0 0) - (1 1 1)\n")
    assert read_middlebury_bounding_box(path) is None
    path.write_text("bounding box (-1 0 0) - (1 1 1)\n")
    np.testing.assert_array_equal(read_middlebury_bounding_box(path), [[-1, 0, 0], [1, 1, 1]])


def test_positions_finite_in_metres_but_not_in_mm_are_refused(tmp_path):
    from scope3d.io.poses_csv import POSE_COLUMNS, read_poses_csv

    path = tmp_path / "poses.csv"
    path.write_text(",".join(POSE_COLUMNS) + "\na.png,1e306,0,0,1,0,0,0,0,0,0,0,0,0\n")
    assert read_poses_csv(path)[1][0].pose.centre[0] == 1e306
    _expect_refusal(lambda: read_poses_csv(path, 1000.0), path, "row 2", "position in mm")


def test_an_image_header_claiming_400_megapixels_is_refused_before_decoding(targets, tmp_path):
    """Found by atheris: a PNG whose header claimed a size under OpenCV's 2^30-pixel limit made it allocate
    2 GB. (tracemalloc does not see OpenCV's allocations: the peak resident set size is checked.)"""
    import resource
    import struct
    import zlib

    from scope3d.io.images import read_image

    seed = targets["image png"].seed
    ihdr = bytearray(seed[8:33])
    ihdr[8:16] = struct.pack(">II", 20000, 20000)
    ihdr[21:25] = struct.pack(">I", zlib.crc32(bytes(ihdr[4:21])) & 0xFFFFFFFF)
    path = tmp_path / "huge.png"
    path.write_bytes(seed[:8] + bytes(ihdr) + seed[33:])
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _expect_refusal(lambda: read_image(path), path, "claims 400 Mpx")
    # 20000 x 20000 RGB is 1.2 GB; 100 MB is the noise of this process's own growth
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before_kb < 100_000


def test_a_png_chunk_claiming_4_gb_is_refused_before_decoding(targets, tmp_path):
    """Found by atheris: a 16x12 PNG whose IDAT chunk claimed 0xFFFFFFFF bytes made OpenCV allocate 4 GB."""
    import resource

    from scope3d.io.images import read_image

    seed = targets["image png"].seed
    idat = seed.index(b"IDAT") - 4
    path = tmp_path / "chunk.png"
    path.write_bytes(seed[:idat] + b"\xff\xff\xff\xff" + seed[idat + 4:])
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _expect_refusal(lambda: read_image(path), path, "'IDAT'", "claims 4294967295 bytes")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before_kb < 100_000  # 4 GB before the fix


def test_a_workbook_with_one_cell_on_its_last_row_and_column_is_read_in_bounded_memory(targets, tmp_path):
    """Found by the huge-header test: one cell at XFD1048576 of a 10 kB workbook made the tracker reader pad
    a million empty rows to 16,384 columns each (MemoryError after 5 GB). Rows are now as wide as their own
    cells, and a sheet may not hold more rows than the format allows."""
    import io

    import openpyxl

    from scope3d.io.tracker import read_tracker

    book = openpyxl.load_workbook(io.BytesIO(targets["tracker xlsx"].seed))
    book.active["XFD1048576"] = 1.0
    path = tmp_path / "far.xlsx"
    book.save(path)
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # the far cell's row has no frame number: refused naming it, after reading the three real rows
    _expect_refusal(lambda: read_tracker(path), path, "row 1048576", "frame is not a number")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before_kb < 100_000  # 100 MB of 137 GB
    # one row beyond the format's limit (openpyxl will not write it: the sheet's XML is edited)
    import zipfile

    beyond = tmp_path / "beyond.xlsx"
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(beyond, "w", zipfile.ZIP_DEFLATED) as dest:
        for info in source.infolist():
            data = source.read(info)
            if info.filename.startswith("xl/worksheets/"):
                data = data.replace(b"1048576", b"1048577")
            dest.writestr(info.filename, data)
    _expect_refusal(lambda: read_tracker(beyond), beyond, "row 1048577", "1,048,576 rows")


@pytest.mark.parametrize("name", ["rosbag ros1", "rosbag2 storage"])
def test_a_damaged_bag_is_refused_in_one_line(targets, name):
    """Found by the fuzzing: rosbags' errors on a truncated bag span several lines (the InputError quoted
    them whole), and a damaged message raised the library's own errors from the message loop."""
    target = targets[name]
    try:
        for cut in (0.3, 0.6, 0.9):
            assert target.run(target.seed[: int(cut * len(target.seed))]) == "refused"
    finally:
        target.restore()


@pytest.mark.parametrize("fields, fragment", [
    ({"K": 20.0}, "K has 1 values, not 9"),  # the long random run's input (below): a float64 where float64[9] was
    ({"K": "twenty"}, "not numbers"),
    ({"K": [20.0, 0, 7.5, 0, 20.0, 5.5, 0, 0, 1], "D": "plumb"}, "not numbers"),
])
def test_camera_info_whose_matrix_is_no_matrix_is_refused_naming_the_topic(fields, fragment):
    """Found by the long random fuzz run (issue 16, ROS 1 bag target, input 2,627 of seed 1): two connection
    ids swapped in a chunk's index made a message of another type be read as the camera info, whose K
    came out as one number: numpy's reshape ValueError, not a refusal."""
    from types import SimpleNamespace

    from scope3d.io.rosbag import camera_from_info

    message = SimpleNamespace(width=16, height=12, **{"D": [0.0] * 5, **fields})
    with pytest.raises(InputError) as info:
        camera_from_info(message, "scope.bag: /info")
    assert str(info.value).startswith("scope.bag: /info: ") and fragment in str(info.value), str(info.value)


@pytest.mark.parametrize("edit, fragment", [
    (lambda r: r["targets_vs_truth"][0].pop("name"), "every true target needs a name"),
    (lambda r: r["targets"][0].update(centroid_mm=[1.0, 2.0]), "targets[0]: centroid_mm must be three"),
    (lambda r: r["targets_vs_truth"][0].update(true_centre_mm=["x", 0, 0]), "true_centre_mm must be three"),
    (lambda r: r["targets"][0].update(size_mm="big"), "size_mm must be a number"),
    (lambda r: r.update(targets={"a": 1}), "targets must be a list"),
])
def test_a_report_json_with_damaged_targets_is_refused_naming_the_entry(targets, edit, fragment):
    """Found by the fuzzing: `scope3d report` on a damaged report.json raised KeyError or a numpy
    broadcasting error from the targets it draws."""
    import json

    from scope3d.report import build_page

    target = targets["report.json"]
    report = json.loads(target.seed)
    edit(report)
    target.path.write_text(json.dumps(report))
    try:
        _expect_refusal(lambda: build_page(target.path.parent), target.path, fragment)
    finally:
        target.restore()


@pytest.mark.parametrize("edit", [
    lambda r: r["targets"][0].update(size_mm=None),
    lambda r: r["targets"][0].update(area_mm2=None),
    lambda r: r["targets_vs_truth"][0].update(true_size_mm=None),
    lambda r: r.update(dataset="1" * 300),
    lambda r: r.update(dataset=[1, 2]),
    lambda r: r.update(dataset=0.41),  # the long run's lost atheris crash, reproduced on its code (TypeError)
])
def test_a_report_json_with_null_sizes_or_an_impossible_dataset_name_still_gives_its_page(targets, edit):
    """Found by the long random fuzz run (issue 16): a null size (allowed: a size the map could not
    measure) raised TypeError from float(None) and from formatting None; a dataset name longer than the
    file system allows raised OSError (ENAMETOOLONG) from is_file(). The page is built, naming what it
    could not use."""
    import json

    target = targets["report.json"]
    report = json.loads(target.seed)
    edit(report)
    target.path.write_text(json.dumps(report))
    try:
        assert target.run(target.path.read_bytes()) == "ok"
    finally:
        target.restore()


def test_a_ros2_bag_whose_metadata_names_a_topic_by_a_mapping_is_refused(targets):
    """Found by the long random fuzz run (issue 16): a topic name that is a YAML mapping raised TypeError
    (unhashable dict) while the import gathered the bag's topics."""
    import yaml

    target = targets["rosbag2 metadata.yaml"]
    metadata = yaml.safe_load(target.seed)
    info = metadata["rosbag2_bagfile_information"]
    info["topics_with_message_count"][0]["topic_metadata"]["name"] = {"a": 1}
    try:
        assert target.run(yaml.safe_dump(metadata).encode()) == "refused"
    finally:
        target.restore()


def test_map_points_with_a_member_flagged_as_encrypted_are_refused(targets):
    """Found by the long atheris run (issue 16): a flag bit set in the archive's central directory made
    zipfile raise RuntimeError ("is encrypted, password required for extraction")."""
    target = targets["map points"]
    data = bytearray(target.seed)
    central = data.index(b"PK\x01\x02")  # the first central directory entry; its flag bits at offset 8
    data[central + 8] |= 0x01
    try:
        assert target.run(bytes(data)) == "refused"
    finally:
        target.restore()


def test_map_points_whose_header_claims_a_billion_points_are_refused_before_allocating(targets):
    """Found by the huge-header test: np.load allocated the (10^9, 3) array the .npy header claimed
    (MemoryError for 22 GB). The shape is now checked against the member's size first."""
    from fuzz_targets import huge_header

    target = targets["map points"]
    try:
        with pytest.raises(InputError, match=r"header says \(1000000000, 3\) float64, its data holds 72 bytes"):
            target.path.write_bytes(huge_header(target))
            from scope3d.io.map_points import read_map_points

            read_map_points(target.path)
    finally:
        target.restore()


def test_a_corrupt_frame_is_one_line_on_stderr_without_the_decoders_own(tmp_path):
    """Found checking the CLI's stderr: libpng printed "libpng error: IDAT: ..." on file descriptor 2 before
    scope3d's refusal, two lines where one is promised."""
    from fuzz_targets import _tiny_dataset

    root = _tiny_dataset(tmp_path / "ds")
    frame = sorted((root / "frames").iterdir())[0]
    data = bytearray(frame.read_bytes())
    data[data.index(b"IDAT") + 40] ^= 0xFF  # inside the compressed stream: zlib rejects it while decoding
    frame.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, "-m", "scope3d.cli.main", "check", str(root)], capture_output=True,
                          text=True, cwd=REPO, env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"},
                          timeout=HANG_S)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and str(frame) in proc.stderr, proc.stderr


def test_a_truncated_video_is_one_line_on_stderr(targets, tmp_path):
    """Found checking the CLI's stderr: OpenCV's FFmpeg back end logged three lines ("Could not find decoder",
    "Failed to initialize VideoCapture", ...) before scope3d's refusal."""
    seed = targets["video mp4"].seed
    video = tmp_path / "cut.mp4"
    video.write_bytes(seed[: len(seed) // 2])
    proc = subprocess.run([sys.executable, "-m", "scope3d.cli.main", "import", "video", str(video), "--fov", "60",
                           "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=REPO,
                          env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"}, timeout=HANG_S)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and str(video) in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("old, new, fragment", [(b'"section": 0', b'"section": Infinity', "view 0"),
                                                (b'"section": 0', b'"section": -1e308', "view 0"),
                                                (b'"fov_deg": 70.0', b'"fov_deg": 1' + b"0" * 400, "fov_deg")])
def test_a_scan_plan_with_an_infinite_section_or_an_enormous_fov_is_refused(targets, old, new, fragment):
    """Found by the long hypothesis run: int(Infinity) and float(10^400) raised OverflowError; by the long
    random run (issue 16): int(-1e308) is a Python int the int64 section array cannot hold (OverflowError)."""
    from scope3d.io.scan_plan import read_scan_plan

    target = targets["scan plan"]
    assert old in target.seed
    target.path.write_bytes(target.seed.replace(old, new, 1))
    try:
        _expect_refusal(lambda: read_scan_plan(target.path), target.path, fragment)
    finally:
        target.restore()


def test_a_tracker_frame_number_beyond_int64_is_refused_naming_the_row(targets):
    """Found by bench_fuzz.py's random engine: a frame of -3e+27 (a whole number as a float) passed the
    whole-number check and overflowed int64 when the recording was built (OverflowError)."""
    target = targets["tracker csv"]
    lines = target.seed.decode().splitlines()
    fields = lines[1].split(",")
    fields[2] = "-3e+27"
    target.path.write_bytes("\n".join([lines[0], ",".join(fields), *lines[2:]]).encode())
    try:
        _expect_refusal(target.call, target.path, "row 2: frame number -3e+27")
    finally:
        target.restore()
