"""Every file reader, fed mutated copies of a valid file: the only outcomes are a parse or one InputError line
naming the file, in bounded memory. Short hypothesis runs here (derandomised, so a failure reproduces); the
long runs are benchmarks/bench_fuzz.py. The regression tests below are the crashes those runs found."""
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

# 14 targets x 60 examples take ~10-20 s on the loaded 2-core machine; each example is a few ms, the
# deadline only catches a reader that loops or parses something enormous.
SHORT_RUN = settings(max_examples=60, deadline=2000, derandomize=True, database=None,
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
                "middlebury par", "middlebury readme", "image png"]


def test_the_target_list_is_complete(targets):
    assert sorted(targets) == sorted(TARGET_NAMES)
    for target in targets.values():  # every seed is a valid file: mutations start from a correct parse
        assert target.run(target.seed) == "ok", target.name


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_mutated_files_parse_or_are_refused_in_one_line(targets, name):
    target = targets[name]

    @SHORT_RUN
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
    tracemalloc.start()
    try:
        outcome = target.run(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        target.restore()
    # the files are < 1 MB; 64 MB leaves room for parsing overheads, and is 1/100 of the claim
    assert peak < 64e6, f"{name}: {peak / 1e6:.0f} MB"
    if name != "middlebury readme":  # its reader answers "no box found", not an error
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
                          env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"}, timeout=120)
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
