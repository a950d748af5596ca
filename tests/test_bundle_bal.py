"""BAL problems (ladybug-49-7776) through the Python API and the ``scope3d bundle-adjust`` command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.estimators.bundle import (
    BALProblem,
    SolverOptions,
    apply_bounds_file,
    bal_to_problem,
    read_bal,
    result_to_bal,
    solve,
    write_bal,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LADYBUG = DATA / "bal_ladybug_49_7776" / "problem-49-7776-pre.txt"


@pytest.fixture(scope="module")
def ladybug() -> BALProblem:
    assert LADYBUG.exists(), f"BAL test data missing: {LADYBUG}"
    return read_bal(LADYBUG)


def test_read_bal_and_conversion_keep_the_cost(ladybug):
    assert ladybug.cameras.shape == (49, 9) and ladybug.points.shape == (7776, 3)
    assert ladybug.num_observations == 31843
    problem = bal_to_problem(ladybug)
    result = solve(problem, SolverOptions(max_iterations=0))
    # the scope3d camera (+z forward, y down) reproduces BAL's -z camera exactly
    assert result.initial_cost == pytest.approx(ladybug.cost(), rel=1e-12)
    assert result.initial_cost == pytest.approx(8.509125e5, rel=1e-6)


def test_few_iterations_on_ladybug_reduce_the_cost_and_round_trip(ladybug, tmp_path):
    problem = bal_to_problem(ladybug)
    result = solve(problem, SolverOptions(max_iterations=6))
    assert result.iterations == 6
    costs = [rec.cost for rec in result.log]
    assert all(b <= a for a, b in zip(costs, costs[1:]))
    # Ceres reaches 1.33e4 at convergence; six LM steps get within a few per cent of it
    assert result.final_cost < 1.45e4
    solved = result_to_bal(ladybug, result)
    assert solved.cost() == pytest.approx(result.final_cost, rel=1e-9)
    write_bal(tmp_path / "solved.txt", solved)
    again = read_bal(tmp_path / "solved.txt")
    assert again.cost() == pytest.approx(result.final_cost, rel=1e-6)


def test_bounds_file_rules_are_applied_in_the_bal_frame(ladybug, tmp_path):
    bounds = tmp_path / "bounds.txt"
    bounds.write_text(
        "# gauge and a box on camera 3\n"
        "camera 0 all fixed\n"
        "camera 3 ty 0.0 0.01   # BAL frame\n"
        "camera 1-2,4 k1,k2 fixed\n"
        "point 0 x +- 0.5\n"
        "shell 10-20 0 0 0 0.1 100\n"
    )
    problem = bal_to_problem(ladybug)
    assert apply_bounds_file(problem, bounds) == 5
    assert problem.pose_fixed[0].all() and problem.intrinsics_fixed[0, [0, 4, 5]].all()
    # BAL's ty is minus scope3d's (the camera frame is turned by 180 degrees about x)
    assert problem.pose_lower[3, 4] == -0.01 and problem.pose_upper[3, 4] == 0.0
    assert problem.intrinsics_fixed[[1, 2, 4]][:, 4:].all() and not problem.intrinsics_fixed[3, 4]
    assert problem.point_upper[0, 0] - problem.point_lower[0, 0] == pytest.approx(1.0)
    assert (problem.point_kind[10:21] == 1).all() and (problem.point_upper[10:21, 0] == 100).all()
    with pytest.warns(UserWarning, match="clamped"):
        result = solve(problem, SolverOptions(max_iterations=3))
    ty_bal = -result.translations[3, 1]
    assert 0.0 <= ty_bal <= 0.01
    np.testing.assert_array_equal(result.parameters.pose[0], problem.initial.pose[0])

    for text, message in (
        ("camera 99 f fixed\n", "index out of range"),
        ("camera 0 q fixed\n", "unknown camera component 'q'"),
        ("point 0 x 2 1\n", "lower bound 2 > upper bound 1"),
        ("cone 0\n", "unknown rule 'cone'"),
        ("camera 0 f 1 nan\n", "NaN"),
    ):
        bounds.write_text(text)
        with pytest.raises(InputError, match=message):
            apply_bounds_file(bal_to_problem(ladybug), bounds)


def test_cli_bundle_adjust_writes_report(tmp_path, capsys):
    """--out DIR: report.json, the solved problem and the convergence plot, as every job writes into --out."""
    report = tmp_path / "run" / "report.json"
    plot = tmp_path / "run" / "convergence.png"
    status = main(["bundle-adjust", str(LADYBUG), "--out", str(tmp_path / "run"), "--max-iterations", "4",
                   "--loss", "huber", "--loss-scale-px", "2"])
    assert status == 0
    assert len(read_bal(tmp_path / "run" / "solution.bal").cameras) == len(read_bal(LADYBUG).cameras)
    data = json.loads(report.read_text())
    for key in ("initial_cost", "final_cost", "iterations", "solve_time_s", "peak_memory_mb", "iteration_log",
                "termination"):
        assert key in data
    assert data["iterations"] == 4 and len(data["iteration_log"]) == 5
    assert data["final_cost"] < data["initial_cost"] and data["loss"] == "huber"
    assert {"cost", "damping", "active_set_size", "time_s", "projected_gradient_norm"} <= set(data["iteration_log"][1])
    assert plot.exists()
    assert "iter    1" in capsys.readouterr().err


def test_cli_bundle_adjust_old_output_flags_still_work(tmp_path, capsys):
    """--report/--output/--plot, the flags before --out, are hidden aliases for old scripts; mixed with --out
    they are refused."""
    status = main(["bundle-adjust", str(LADYBUG), "--report", str(tmp_path / "r.json"), "--max-iterations", "1",
                   "--quiet", "--output", str(tmp_path / "s.bal")])
    assert status == 0 and (tmp_path / "r.json").is_file() and (tmp_path / "s.bal").is_file()
    assert main(["bundle-adjust", str(LADYBUG), "--out", str(tmp_path / "o"), "--report", str(tmp_path / "x.json")]) == 2
    assert "not both" in capsys.readouterr().err


def test_cli_reports_bad_files_without_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("2 1 2\n0 0 1.0 2.0\n")
    status = main(["bundle-adjust", str(bad), "--report", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert status == 2 and "expected" in err and "Traceback" not in err
    assert not (tmp_path / "r.json").exists()


def _tiny_bal(path: Path, observation0: str = "0 0", camera1_rx: str = "0.1") -> Path:
    """2 cameras, 1 point, 2 observations; one number per line after the observations, as BAL files are."""
    cameras = ["0", "0", "0", "0", "0", "-5", "500", "0", "0", camera1_rx, "0", "0", "1", "0", "-5", "500", "0", "0"]
    path.write_text("\n".join(["2 1 2", f"{observation0} 1.0 2.0", "1 0 3.0 4.0", *cameras, "0", "0", "0"]) + "\n")
    return path


@pytest.mark.parametrize(
    "kwargs, fragments",
    [
        ({"camera1_rx": "nan"}, ["camera 1 (0-based)", "NaN or infinite"]),
        ({"camera1_rx": "inf"}, ["camera 1 (0-based)", "NaN or infinite"]),
        ({"observation0": "0.5 0"}, ["observation 0 (0-based)", "integers"]),
    ],
)
def test_read_bal_refuses_garbage_naming_the_file(tmp_path, kwargs, fragments):
    path = _tiny_bal(tmp_path / "p.txt", **kwargs)
    with pytest.raises(InputError) as info:
        read_bal(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)
    for f in fragments:
        assert f in str(info.value), str(info.value)
    # the same file with good numbers is read
    assert read_bal(_tiny_bal(tmp_path / "good.txt")).cameras.shape == (2, 9)
