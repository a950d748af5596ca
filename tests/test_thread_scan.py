"""The thread-scan pipeline, its CLI and the Dask production line on one small rendered hole: an M8x1.25
scanned in 12 quadrants of 3 frames (320x256 px), the camera 0.22 mm off and 0.5° tilted from the
rotation axis, unknown to the stage."""
from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time

import pytest

from kill_harness import Job, environment, kill_the_leader_when, left_alive, scope3d
from scope3d.cli.main import main
from scope3d.metrology.thread_scan_plan import matched_frame_gap, plan_quadrant_scan
from scope3d.phantoms.lab import BORESCOPE_FOV_DEG
from scope3d.sensor.camera import Camera
from scope3d.phantoms import generate, write


@pytest.fixture(scope="module")
def hole(tmp_path_factory):
    root = tmp_path_factory.mktemp("thread")
    seq = generate("thread", "quadrants", n_frames=36, size=(320, 256), quadrant_mount=(0.2, -0.1, 0.5),
                   thread_offsets_mm=(0.132, 0.08, 0.05))
    return write(seq, root / "hole_a")


def test_thread_scan_registers_the_quadrants(hole, tmp_path, capsys):
    out = tmp_path / "scan"
    assert main(["thread-scan", str(hole), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "thread gauge" in printed and "against the truth" in printed
    report = json.loads((out / "report.json").read_text())
    reg = report["registration"]
    # the mount's 0.22 mm offset and 0.5° tilt put the stacked quadrants ~0.2 mm and ~1.5° apart; the
    # registration must remove most of it (the targets, 0.5° and 0.02 mm, are met on finer
    # frames in benchmarks/bench_thread.py; 320 px frames with 0.2 mm baselines give ~0.1 mm points)
    assert reg["offset_error_mm"] < reg["stacked_offset_error_mm"] / 4
    assert reg["rotation_error_deg"] < reg["stacked_rotation_error_deg"]
    assert reg["loop_closure_residual_deg"] is not None and len(reg["pairs"]) == 12
    assert report["gauge"]["verdict"] in ("pass", "fail", "indeterminate")
    # the frame gap comes from the scan itself (0.1 mm steps, 45° view, the scan plan's half-overlap
    # rule), not from a size-specific argument
    scan = plan_quadrant_scan(Camera.from_fov(320, 256, BORESCOPE_FOV_DEG), "M8x1.25", 45.0)
    assert report["scan"]["frame_gap"] == [matched_frame_gap(0.1, scan.view_extent_mm)] * 12
    # 3 frames 0.1 mm apart (the Python API's default step) see each wall point 3 times, not the plan's 8:
    # no thread is gauged, and the verdict's line says what the scan showed and what the plan would do
    coverage = report["scan"]["coverage"]
    assert coverage["views_per_point"] == 3 < coverage["needed_views_per_point"]
    assert coverage["plan"]["step_mm"] == scan.step_mm and f"{scan.frames_per_quadrant} frames per quadrant" in coverage["message"]
    assert report["gauge"]["verdict"] == "indeterminate" and coverage["message"] in report["gauge"]["message"]
    assert coverage["message"] in printed.splitlines()[0]
    assert (out / "cloud.ply").is_file() and (out / "registration.png").is_file()
    assert len(list((out / "quadrants").glob("q*.ply"))) == 12


def test_thread_scan_names_the_missing_layout(hole, tmp_path, capsys):
    bad = tmp_path / "no_layout"
    shutil.copytree(hole, bad)
    (bad / "quadrants.json").unlink()
    assert main(["thread-scan", str(bad), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "quadrants.json" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    assert main(["thread-scan", str(hole), "--frame-gap", "0", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "--frame-gap" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_batch_survives_a_killed_worker_and_resumes(hole, tmp_path):
    """A worker SIGKILLed mid-hole: the scheduler runs the hole again on a worker alive, finished holes are kept,
    and a rerun skips both. The kill lands mid-hole by construction, not by a sleep (which could end after the
    hole did, issue 31): hole_a's first attempt holds in the page hook, its folder complete but still
    temporary, until the test kills its worker; only another attempt can put hole_a's result in place."""
    from distributed import Client, LocalCluster

    from scope3d.cli.commands_thread import hole_page
    from scope3d.pipelines import thread_batch
    from scope3d.pipelines.thread_scan import ThreadScanOptions

    second = tmp_path / "hole_b"
    shutil.copytree(hole, second)
    out = tmp_path / "line"
    held = tmp_path / "held"  # the process id of the worker holding hole_a's first attempt

    def finish(folder, name):  # the CLI's page hook, holding hole_a's first attempt (pickled by value)
        if name == "hole_a" and not held.exists():
            (tmp_path / "held.tmp").write_text(str(os.getpid()))
            (tmp_path / "held.tmp").rename(held)
            for _ in range(9000):  # until killed; 900 s only ends a test that never kills
                time.sleep(0.1)
            raise RuntimeError("the held worker was never killed")
        hole_page(folder, name)

    killed, batch_done = [], threading.Event()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        pids = set(client.run(os.getpid).values())

        def kill_the_held_worker():
            while not held.exists() and not batch_done.wait(0.05):
                pass
            if held.exists() and int(held.read_text()) in pids:  # a worker process this test started
                os.kill(int(held.read_text()), signal.SIGKILL)
                killed.append(int(held.read_text()))

        killer = threading.Thread(target=kill_the_held_worker)
        killer.start()
        try:
            result = thread_batch.run(ThreadScanOptions(), [hole, second], out, client=client, finish=finish)
        finally:
            batch_done.set()
            killer.join()
    assert killed == [int(held.read_text())], "the held worker was not killed"
    assert [r["status"] for r in result.rows] == ["done", "done"]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # the killed attempt's folder removed
    for name in ("hole_a", "hole_b"):
        assert (out / name / "report.json").is_file() and (out / name / "report.html").is_file()
    assert "hole_a" in (out / "summary.csv").read_text()
    again = thread_batch.run(ThreadScanOptions(), [hole, second], out, n_workers=1)
    assert [r["status"] for r in again.rows] == ["skipped", "skipped"]


def test_a_killed_batch_leaves_no_worker_behind(hole, tmp_path):
    # issue 39's question for the other job that starts processes: SIGKILL the batch alone (not its process
    # group) while a worker of its local Dask cluster scans a hole. Dask's worker processes watch a pipe
    # from their parent and exit on its end-of-file; this checks they, and multiprocessing's
    # resource tracker, do not outlive the batch.
    out = tmp_path / "line"
    job = Job("batch", scope3d("batch", "thread-scan", str(hole), "--out", str(out), "--workers", "2",
                               "--no-progress"), out)

    def scanning(batch, others):  # a worker has started the hole: its temporary folder is there
        return len(others) >= 2 and out.is_dir() and any(p.name.startswith(f".{hole.name}.") for p in out.iterdir())

    session = kill_the_leader_when(job, environment(), scanning)
    assert session is not None, "5 batches ended before a worker started the hole"
    assert left_alive(session) == {}


def test_a_scan_that_hides_parts_of_the_profile_says_which_and_what_scan_shows_them():
    # the one line thread-scan gives when the cloud lacks profile parts (a 45° view: one flank, no root)
    from types import SimpleNamespace

    from scope3d.phantoms.lab import borescope_camera
    from scope3d.pipelines.thread_scan import unseen_message

    camera = borescope_camera(size=(400, 320))
    gauge = SimpleNamespace(unseen_parts=("flank towards -z", "root"))
    line = unseen_message(gauge, SimpleNamespace(camera=camera), "M6x1", [SimpleNamespace(side_view_deg=45.0)] * 12)
    plan = plan_quadrant_scan(camera, "M6x1", 90.0)
    assert "\n" not in line
    assert line.startswith("flank towards -z and root not in the cloud: major diameter and pitch diameter not measured")
    assert "(a 45° side view)" in line
    assert line.endswith(f"{plan.frames_per_quadrant} frames per quadrant {plan.step_mm:g} mm apart, frame gap "
                         f"{plan.frame_gap}")
