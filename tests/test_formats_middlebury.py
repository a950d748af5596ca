"""Middlebury multi-view import on the real templeSparseRing set (../shared/data beside the repo)."""
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.dataset import load_dataset
from scope3d.errors import InputError
from scope3d.formats.middlebury import import_middlebury, read_middlebury_par
from scope3d.pose import PoseTolerance

REPO = Path(__file__).resolve().parents[1]
TEMPLE = REPO.parent / "shared" / "data" / "middlebury_templeSparseRing"
PAR = TEMPLE / "templeSR_par.txt"
# From SOURCE.txt / README.txt of the set (metres).
BOX_M = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])


@pytest.fixture(scope="module")
def temple(tmp_path_factory):
    if not PAR.is_file():
        pytest.fail(f"real data missing: {PAR} (see /work/shared/data/README.md)")
    return load_dataset(import_middlebury(PAR, tmp_path_factory.mktemp("m") / "temple"), check_images=True)


def test_frames_and_intrinsics(temple):
    assert len(temple) == 16
    assert temple.names == [f"templeSR{i:04d}.png" for i in range(1, 17)]
    cam = temple.camera
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2) == (1520.4, 1525.9, 302.32, 246.87, 0.0, 0.0)
    assert all(m.tolerance.is_exact for m in temple.poses)
    # images copied unmodified
    assert (temple.root / "frames" / "templeSR0007.png").read_bytes() == (TEMPLE / "templeSR0007.png").read_bytes()


def test_positions_are_in_mm(temple):
    """The cameras stand ~0.56 m from the object's centre: ~560 in mm (not 0.56, not 560000)."""
    centre_mm = 1000.0 * BOX_M.mean(axis=0)
    distances = [np.linalg.norm(m.pose.centre - centre_mm) for m in temple.poses]
    assert 500.0 < min(distances) and max(distances) < 620.0
    # and the first camera's translation is the file's, times 1000
    np.testing.assert_allclose(temple.poses[0].pose.translation, [-72.6637729648, 22.3360353405, 614.604845959],
                               atol=1e-6)


def test_bounding_box_projects_inside_every_frame(temple):
    corners_mm = 1000.0 * np.array(list(itertools.product(*BOX_M.T)))
    for measured in temple.poses:
        px = temple.camera.project_world(measured.pose, corners_mm)
        assert np.all(temple.camera.in_image(px)), px
    # ...and the object is in front of every camera, its centre near the image centre
    centre = 1000.0 * BOX_M.mean(axis=0)
    for measured in temple.poses:
        u, v = temple.camera.project_world(measured.pose, centre[None])[0]
        assert abs(u - 320) < 200 and abs(v - 240) < 150


def test_provenance_and_bounding_box_in_dataset_json(temple):
    meta = json.loads((temple.root / "dataset.json").read_text())
    assert meta["format"] == "scope3d-dataset" and meta["length_unit"] == "mm"
    assert meta["source"]["format"] == "middlebury-par" and meta["source"]["world_unit"] == "m"
    assert len(meta["source"]["sha256"]) == 64
    np.testing.assert_allclose(meta["bounding_box_mm"], 1000.0 * BOX_M)


def test_tolerance_option(tmp_path):
    out = import_middlebury(PAR, tmp_path / "t", tolerance=PoseTolerance.from_degrees(0.25, 0.1))
    ds = load_dataset(out)
    np.testing.assert_allclose(ds.poses[5].tolerance.position_mm, 0.25)
    np.testing.assert_allclose(ds.poses[5].tolerance.orientation_deg, 0.1)


# --- bad input -------------------------------------------------------------------------------------


def _par_copy(tmp_path, edit) -> Path:
    """A copy of the set (images symlinked) with an edited par file."""
    lines = PAR.read_text().splitlines()
    edit(lines)
    for png in TEMPLE.glob("*.png"):
        (tmp_path / png.name).symlink_to(png)
    (tmp_path / "x_par.txt").write_text("\n".join(lines) + "\n")
    return tmp_path / "x_par.txt"


@pytest.mark.parametrize(
    "edit, fragments",
    [
        (lambda ls: ls.__setitem__(0, "17"), ["line 1", "says 17 images", "lists 16"]),
        (lambda ls: ls.__setitem__(3, ls[3].rsplit(" ", 1)[0]), ["line 4", "found 20"]),
        (lambda ls: ls.__setitem__(3, ls[3].replace("1525.900000", "nan", 1)), ["line 4", "NaN"]),
        (lambda ls: ls.__setitem__(2, ls[2].replace(" 0.000000 302.32", " 3.000000 302.32", 1)), ["line 3", "skew"]),
        (lambda ls: ls.__setitem__(5, ls[5].replace(" 0.000000 0.000000 1.000000", " 0.000000 0.000000 2.000000", 1)),
         ["line 6", "K must be"]),
        (lambda ls: ls.__setitem__(5, ls[5].replace("templeSR0005", "templeSR0004")), ["line 6", "listed twice"]),
        (lambda ls: ls.__setitem__(9, ls[9].replace("templeSR0009", "nothere")), ["nothere.png", "missing"]),
    ],
)
def test_bad_par_file(tmp_path, edit, fragments):
    (tmp_path / "in").mkdir()
    par = _par_copy(tmp_path / "in", edit)
    with pytest.raises(InputError) as info:
        import_middlebury(par, tmp_path / "out")
    for f in fragments:
        assert f in str(info.value), str(info.value)
    assert not (tmp_path / "out").exists()


def test_non_rotation_is_rejected(tmp_path):
    def scale_r(lines):
        tokens = lines[2].split()
        tokens[10] = str(2.0 * float(tokens[10]))  # r11 doubled
        lines[2] = " ".join(tokens)

    (tmp_path / "in").mkdir()
    with pytest.raises(InputError, match="line 3: R is not a rotation"):
        read_middlebury_par(_par_copy(tmp_path / "in", scale_r))


def test_corrupt_last_image_leaves_no_output(tmp_path, capsys):
    (tmp_path / "in").mkdir()
    par = _par_copy(tmp_path / "in", lambda ls: None)
    (tmp_path / "in" / "templeSR0016.png").unlink()
    (tmp_path / "in" / "templeSR0016.png").write_bytes((TEMPLE / "templeSR0016.png").read_bytes()[:5000])
    code = main(["import", "middlebury", str(par), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "templeSR0016.png" in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_cli_import_refuses_to_replace_a_foreign_folder(tmp_path, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("precious")
    assert main(["import", "middlebury", str(PAR), "--out", str(tmp_path / "mine")]) == 2
    assert "not a scope3d dataset" in capsys.readouterr().err
    assert (tmp_path / "mine" / "notes.txt").read_text() == "precious"


def test_cli_import_then_check_in_subprocess(tmp_path):
    run = [sys.executable, "-m", "scope3d.cli.main"]
    imported = subprocess.run(run + ["import", "middlebury", str(PAR), "--out", str(tmp_path / "t"),
                                     "--tolerance", "0.5"], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert imported.returncode == 0, imported.stderr
    checked = subprocess.run(run + ["check", str(tmp_path / "t")], capture_output=True, text=True, cwd=REPO,
                             timeout=60)
    assert checked.returncode == 0, checked.stderr
    assert "16 images of 640x480 px" in checked.stdout and "position +-0.5 mm" in checked.stdout
