"""Build step: the bundle adjuster's kernels compiled ahead of time (scope3d.estimators.bundle.aot).

Everything else is in pyproject.toml. ``build_ext`` compiles src/scope3d/estimators/bundle/kernels.py with
numba's pycc into the extension module ``scope3d.estimators.bundle._kernels_aot``. When that is not
possible (no C compiler, no Python headers, numba without pycc) the install goes on without it, says
so, and the kernels are compiled by numba's JIT on first use instead.

Set SCOPE3D_AOT=0 to skip the step, SCOPE3D_AOT_CPU=host to tune the code for the building machine
(default: a generic CPU of the architecture, so that a wheel runs on any machine of it).
"""
from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

BUNDLE = Path(__file__).resolve().parent / "src" / "scope3d" / "estimators" / "bundle"
AOT_NAME = "scope3d.estimators.bundle._kernels_aot"


def _load(name: str, path: Path):
    """Import one file as a module without importing the scope3d package (its dependencies may be
    missing from the build environment; kernels.py and aot.py need only numpy and numba)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


class BuildKernels(build_ext):
    """build_ext for the one pycc module: compiled by numba, skipped with a message when that fails."""

    def build_extension(self, ext: Extension) -> None:
        if ext.name != AOT_NAME:
            super().build_extension(ext)
            return
        target = Path(self.get_ext_fullpath(ext.name))
        target.unlink(missing_ok=True)  # never ship a module left by an earlier build
        if os.environ.get("SCOPE3D_AOT", "1") == "0":
            print("scope3d: SCOPE3D_AOT=0, bundle-adjustment kernels left to numba's JIT", file=sys.stderr)
            return
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(prefix="scope3d-numba-cache-") as cache:
                # a numba cache beside the sources (a JIT run's) would name the installed package, which
                # the build environment cannot import: compile from scratch in an empty one
                os.environ["NUMBA_CACHE_DIR"] = cache
                kernels = _load("scope3d_build_kernels", BUNDLE / "kernels.py")
                aot = _load("scope3d_build_aot", BUNDLE / "aot.py")
                aot.compile_kernels(kernels, target, target_cpu=os.environ.get("SCOPE3D_AOT_CPU", ""))
        except Exception as exc:  # noqa: BLE001 - any failure leaves the JIT path, which always works
            print(f"scope3d: ahead-of-time compilation of the bundle-adjustment kernels failed "
                  f"({type(exc).__name__}: {exc}); numba will compile them on first use instead",
                  file=sys.stderr)

    def get_outputs(self) -> list[str]:
        # a skipped module is not an output (the wheel and editable installs must not expect it)
        return [path for path in super().get_outputs() if os.path.exists(path)]


setup(
    ext_modules=[Extension(AOT_NAME, sources=[], optional=True)],
    cmdclass={"build_ext": BuildKernels},
)
