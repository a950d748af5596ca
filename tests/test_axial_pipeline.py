"""End to end on a small rendered threaded hole: depth against ground truth, CLI files, CLI errors."""
import json
import pickle

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.cli.main import main
from scope3d.io.dataset import load_dataset
from scope3d.mvs.axial import make_axial_pair
from scope3d.pipelines.axial import AxialOptions, run


@pytest.fixture(scope="module")
def thread_dataset(tmp_path_factory):
    seq = phantoms.generate("thread", "axial", seed=0, n_frames=6, size=(256, 256))
    return phantoms.write(seq, tmp_path_factory.mktemp("axial") / "thread")


def test_two_view_depth_against_ground_truth(thread_dataset):
    ds = load_dataset(thread_dataset)
    result = run(AxialOptions(method="sgm", frames=(2, 3)), ds, None)
    assert pickle.loads(pickle.dumps(result)).summary() == result.summary()  # results travel to cluster workers
    assert result.points is result.cloud.points and result.colors.shape == result.points.shape
    depth = result.depths[0]
    truth = ds.ground_truth.depth(3)
    ok = depth.valid & np.isfinite(truth)
    assert ok.sum() > 2000
    err = np.abs(depth.z_depth_mm[ok] - truth[ok])
    # Bound from the physics, set before looking at the result. Eq. 7.3 on the log-polar grid,
    # Z = b / (exp(d s) - 1), gives sigma_Z = Z^2 s sigma_d / b (to first order, Z >> b), with s the
    # grid's log-radius step (1 / 126 at 256 px: 1 / mask radius) and b = 0.25 mm. With an a-priori
    # matching accuracy of a quarter column (sigma_d = 0.25, SGM with sub-pixel refinement) the predicted
    # sigma at each kept pixel follows from its true depth; |error| then has median 0.674 sigma. The
    # z-depth here is the coordinate along the baseline (the scope moves along its optical axis).
    ds_pair = make_axial_pair(ds.camera, ds.ground_truth.poses[2], ds.ground_truth.poses[3])
    sigma_z = truth[ok] ** 2 * ds_pair.grid.log_rho_step * 0.25 / ds_pair.baseline_mm
    bound = 0.674 * np.median(sigma_z)
    assert np.median(err) < bound
    # The distance to the surface is the error's normal component: never more than the error itself.
    assert result.report["surface_error_mm"]["median"] < bound


def test_cli_end_to_end(thread_dataset, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["axial", str(thread_dataset), "--out", str(out), "--frames", "1", "2"]) == 0
    for name in ("cloud.ply", "mesh.ply", "depth.png", "report.json", "error_histogram.png"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert report["n_points"] > 1000 and report["time_s"] > 0
    assert {"mean", "median", "p95"} <= set(report["surface_error_mm"])


def test_cli_rejects_zero_step(thread_dataset, tmp_path, capsys):
    assert main(["axial", str(thread_dataset), "--out", str(tmp_path / "o"), "--frames", "2", "2"]) == 2
    assert "apart" in capsys.readouterr().err


def test_multiview_is_less_noisy_than_two_view(thread_dataset):
    ds = load_dataset(thread_dataset)
    two = run(AxialOptions(method="sgm", frames=(4, 5)), ds, None).report["surface_error_mm"]
    multi = run(AxialOptions(method="multiview"), ds, None).report["surface_error_mm"]
    assert multi["mean"] < two["mean"]
