"""Every job speaks the same command-line habits (issue 15 part 3): ``--json`` prints the report on stdout,
``--quiet`` silences progress, ``--help`` states the exit codes, and the job's output folder holds
report.json and report.html."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from scope3d.cli.job_output import EXIT_CODES
from scope3d.cli.main import build_parser, main
from scope3d.io.dataset import load_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))

# The commands that do a job and write a report (not `check`, `report`, `phantom --list`...); a space
# separates a command from its sub-command.
JOBS = ["map", "bundle-adjust", "axial", "localize", "live", "track-markers", "calibrate", "calibrate-hand-eye",
        "thread-scan", "mosaic", "panorama", "phantom", "plan-scan", "batch thread-scan", "import video", "import frames", "import rosbag",
        "import middlebury", "import colmap"]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _job_parser(job: str) -> argparse.ArgumentParser:
    parser = build_parser()
    for word in job.split():
        parser = _subparsers(parser)[word]
    return parser


@pytest.mark.parametrize("job", JOBS + ["check", "report"])
def test_every_job_has_json_quiet_and_states_its_exit_codes(job):
    sub = _job_parser(job)
    options = {s for a in sub._actions for s in a.option_strings}
    assert {"--json", "--quiet"} <= options
    assert " ".join(EXIT_CODES.split()) in " ".join(sub.format_help().split())


def test_every_command_that_writes_an_output_folder_is_in_the_list():
    """A command with --out that is not a job would escape the test above."""
    def walk(parser, prefix):
        for name, sub in _subparsers(parser).items():
            words = f"{prefix} {name}".strip()
            if any(isinstance(a, argparse._SubParsersAction) for a in sub._actions):
                yield from walk(sub, words)
            elif "--out" in {s for a in sub._actions for s in a.option_strings}:
                yield words

    assert sorted(walk(build_parser(), "")) == sorted(JOBS)


@pytest.mark.parametrize("job", JOBS)
def test_one_progress_flag_the_old_one_a_hidden_alias(job):
    """--quiet is the one progress flag; --no-progress, which six commands had beside it, still parses (as
    --quiet) for old scripts but is not offered in --help."""
    sub = _job_parser(job)
    assert "--no-progress" not in sub.format_help()
    quiet = next(a for a in sub._actions if "--no-progress" in a.option_strings)
    assert quiet.dest == "quiet"


def test_check_refuses_what_map_refuses_in_the_same_line(capsys, tmp_path):
    """A one-frame dataset: `check` (for the map, by default) fails with the very line `map` fails with."""
    from scope3d import phantoms

    one = phantoms.write(phantoms.generate("dome", "grid5x6", size=(48, 48), seed=0, n_frames=1), tmp_path / "one")
    assert main(["map", str(one), "--out", str(tmp_path / "map"), "--quiet"]) == 2
    map_err = capsys.readouterr().err.strip().splitlines()
    assert main(["check", str(one)]) == 2
    check_err = capsys.readouterr().err.strip().splitlines()
    assert len(map_err) == len(check_err) == 1 and "need at least 2 frames to map, found 1" in map_err[0]
    assert check_err[0].replace("scope3d check:", "scope3d map:") == map_err[0]
    for job, message in (("panorama", "need at least 2 frames for a panorama, found 1"),
                         ("axial", "axial stereo needs at least two frames"),
                         ("thread-scan", "quadrants.json")):
        assert main(["check", str(one), "--for", job]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (job, err)
        assert main([job, str(one), "--out", str(tmp_path / job), "--quiet"]) == 2
        assert capsys.readouterr().err.strip() == err[0].replace("scope3d check:", f"scope3d {job}:")


def test_check_and_report_speak_json(capsys, small_dome_map, tmp_path):
    dataset = json.loads((small_dome_map / "report.json").read_text())["dataset"]
    assert main(["check", dataset, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["ok"] is True and printed["for"] == "map" and printed["n_frames"] == len(load_dataset(dataset))
    assert main(["report", str(small_dome_map), "--json", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["report_html"] == str(small_dome_map / "report.html")


def _json_run(capsys, argv: list[str], out: Path) -> dict:
    """Run a job with --json --quiet: stdout is its report and nothing else, the same as out/report.json,
    and out/report.html is there."""
    assert main([*argv, "--out", str(out), "--json", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((out / "report.json").read_text())
    assert (out / "report.html").is_file() and "<canvas" in (out / "report.html").read_text()
    return printed


def test_phantom_writes_its_report_into_the_dataset(capsys, tmp_path):
    report = _json_run(capsys, ["phantom", "dome", "--frames", "2", "--size", "48x48"], tmp_path / "dome")
    dataset = load_dataset(tmp_path / "dome", check_images=True)  # the report files do not disturb the dataset
    assert report["job"] == "phantom" and report["n_frames"] == len(dataset) == 2
    assert report["image_size_px"] == [48, 48] and report["ground_truth"] is True
    page = (tmp_path / "dome" / "report.html").read_text()
    assert "<title>scope3d phantom: dome</title>" in page  # the final folder's name, not the temporary one's


def test_import_video_and_rosbag_write_their_reports(capsys, tmp_path):
    from fuzz_targets import _rosbag_seed
    from scope3d.io.video import write_video

    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (24, 48, 3), dtype=np.uint8)
    video = write_video(tmp_path / "v.mp4", [base[:, k:k + 32].copy() for k in range(0, 12, 3)], 10.0)
    report = _json_run(capsys, ["import", "video", str(video), "--fov", "60"], tmp_path / "from_video")
    assert report["job"] == "import video" and report["n_frames"] == 4 and report["image_size_px"] == [32, 24]
    bag = _rosbag_seed(tmp_path / "b.bag", ros1=True)  # two frames, each with a pose 2 ms away
    report = _json_run(capsys, ["import", "rosbag", str(bag), "--image-topic", "/image", "--pose-topic", "/pose",
                                "--camera-info-topic", "/info", "--slop-ms", "5"], tmp_path / "from_bag")
    assert report["job"] == "import rosbag" and report["n_frames"] == 2 and report["source"] == str(bag)


def test_plan_scan_reports_its_plan(capsys, tmp_path):
    import trimesh

    from scope3d.io.ply import write_ply
    from scope3d.scene.mesh import Mesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    write_ply(tmp_path / "sphere.ply", Mesh(sphere.vertices, sphere.faces))
    report = _json_run(capsys, ["plan-scan", str(tmp_path / "sphere.ply"), "--standoff", "8", "--fov", "90",
                                "--overlap", "0.2"], tmp_path / "plan")
    plan = json.loads((tmp_path / "plan" / "plan.json").read_text())
    assert report["job"] == "plan-scan" and report["n_views"] == plan["n_views"] == len(plan["views"])
    assert report["coverage_fraction"] == plan["coverage_fraction"]


def test_batch_writes_the_batch_report_and_each_hole_page(capsys, tmp_path, monkeypatch):
    """The batch command's own work around the Dask run (the run itself: tests/test_thread_scan.py): a page
    per measured hole (through the hook each hole's task calls), the batch's report.json and report.html, exit status 1 when a hole failed."""
    import scope3d.pipelines.thread_batch as thread_batch

    out = tmp_path / "batch"
    (out / "hole_a").mkdir(parents=True)
    (out / "hole_a" / "report.json").write_text(json.dumps({"designation": "M8x1.25", "verdict": "GO"}))
    rows = [{"hole": "hole_a", "status": "done", "verdict": "GO"},
            {"hole": "hole_b", "status": "error", "verdict": "", "message": "no quadrants.json"}]
    def run_batch(*args, finish, **kwargs):  # a worker calls finish on the hole's folder before its rename
        finish(out / "hole_a", "hole_a")
        return thread_batch.ThreadBatchResult(rows, [], 1.5, 2)

    monkeypatch.setattr(thread_batch, "run", run_batch)
    monkeypatch.setattr(thread_batch.ThreadBatchResult, "summary", lambda self: "2 holes")
    assert main(["batch", "thread-scan", "hole_a", "hole_b", "--out", str(out), "--json", "--quiet"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report == json.loads((out / "report.json").read_text())
    assert (report["n_holes"], report["n_measured"], report["n_errors"]) == (2, 1, 1)
    assert report["holes"] == rows
    assert (out / "report.html").is_file() and (out / "hole_a" / "report.html").is_file()
    assert not (out / "hole_b").exists()


def test_job_folder_puts_the_page_in_before_the_folder_appears(tmp_path):
    """The run folder appears whole, report.html included (a kill can no longer leave a run without its
    page), or not at all when the job fails."""
    from scope3d.cli.job_output import job_folder

    out = tmp_path / "run"
    with job_folder(out) as staged:
        assert staged != out and not out.exists()
        (staged / "report.json").write_text(json.dumps({"job": "map", "n_points": 3}))
    assert (out / "report.html").is_file() and (out / "report.json").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no temporary left beside it

    with pytest.raises(RuntimeError), job_folder(out) as staged:  # a failing job keeps the previous run
        (staged / "report.json").write_text(json.dumps({"job": "map", "n_points": 99}))
        raise RuntimeError("the job failed")
    assert json.loads((out / "report.json").read_text())["n_points"] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_a_job_refuses_to_replace_a_folder_that_is_not_a_run(capsys, tmp_path):
    """The job replaces its --out folder whole: a folder of the user's own files is refused (exit 2, one
    line) and left untouched, before any work."""
    mine = tmp_path / "my_notes"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    import trimesh

    from scope3d.io.ply import write_ply
    from scope3d.scene.mesh import Mesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    write_ply(tmp_path / "sphere.ply", Mesh(sphere.vertices, sphere.faces))
    assert main(["plan-scan", str(tmp_path / "sphere.ply"), "--out", str(mine), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "my_notes" in err[0] and "not a scope3d run" in err[0]
    assert (mine / "notes.txt").read_text() == "keep me" and len(list(mine.iterdir())) == 1
