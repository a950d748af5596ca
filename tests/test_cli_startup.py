"""The ``scope3d`` parser builds without the heavy libraries: ``--version`` and ``--help`` start fast because
nothing numerical is imported until a command runs (a property, checked on ``sys.modules``, not a timing)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
HEAVY = ("numpy", "scipy", "cv2", "numba", "trimesh", "matplotlib", "PIL", "pycolmap", "open3d")


def _modules_after(code: str) -> list[str]:
    env = dict(os.environ, PYTHONPATH=str(SRC))
    out = subprocess.run([sys.executable, "-c", code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"],
                         check=True, capture_output=True, text=True, env=env).stdout
    return json.loads(out.splitlines()[-1])


def _heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if m.split(".")[0] in HEAVY]


def test_importing_the_cli_imports_no_heavy_library():
    assert _heavy(_modules_after("import scope3d.cli.main")) == []


def test_importing_the_package_with_its_jobs_imports_no_heavy_library():
    """The jobs and options the package exports load on first use, not with ``import scope3d``."""
    assert _heavy(_modules_after("import scope3d\nscope3d.JOBS, scope3d.__all__")) == []


def test_building_the_parser_and_help_import_no_heavy_library():
    code = ("import contextlib, io\nfrom scope3d.cli.main import build_parser\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    build_parser().format_help()\n")
    assert _heavy(_modules_after(code)) == []


def test_lazy_choices_still_validate_and_list():
    from scope3d.cli.main import build_parser

    parser = build_parser()
    args = parser.parse_args(["map", "somewhere", "--out", "x", "--pose-mode", "free"])
    assert args.pose_mode == "free"
    subparsers = next(a for a in parser._actions if a.dest == "command")
    help_text = subparsers.choices["map"].format_help()
    assert "fixed, free, bounded" in help_text


def test_package_types_load_on_first_use():
    import scope3d
    from scope3d.geometry.pose import Pose

    assert scope3d.Pose is Pose
