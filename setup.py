"""Build step: every numba kernel module of the package compiled ahead of time (scope3d.utils.aot).

Everything else is in pyproject.toml. ``build_ext`` compiles each kernel module that
``scope3d.utils.aot.KERNEL_MODULES`` lists (e.g. src/scope3d/estimators/bundle/kernels.py) with numba's pycc
into the extension module beside it (``scope3d.estimators.bundle._kernels_aot``). When that is not possible
(no C compiler, no Python headers, numba without pycc) the install goes on without it, says so, and those
kernels are compiled by numba's JIT on first use instead.

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

PACKAGE = Path(__file__).resolve().parent / "src" / "scope3d"


def _load(name: str, path: Path):
    """Import one file as a module without importing the scope3d package (its dependencies may be
    missing from the build environment; aot.py and the kernel modules need only numpy and numba)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


aot = _load("scope3d_build_aot", PACKAGE / "utils" / "aot.py")
# extension module name -> its kernel module's name
COMPILED = {aot.aot_module_name(name): name for name in aot.KERNEL_MODULES}


class BuildKernels(build_ext):
    """build_ext for the pycc modules: each compiled by numba, skipped with a message when that fails."""

    def build_extension(self, ext: Extension) -> None:
        if ext.name not in COMPILED:
            super().build_extension(ext)
            return
        kernel_module = COMPILED[ext.name]
        target = Path(self.get_ext_fullpath(ext.name))
        target.unlink(missing_ok=True)  # never ship a module left by an earlier build
        if os.environ.get("SCOPE3D_AOT", "1") == "0":
            print(f"scope3d: SCOPE3D_AOT=0, {kernel_module} left to numba's JIT", file=sys.stderr)
            return
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(prefix="scope3d-numba-cache-") as cache:
                # a numba cache beside the sources (a JIT run's) would name the installed package, which
                # the build environment cannot import: compile from scratch in an empty one
                os.environ["NUMBA_CACHE_DIR"] = cache
                kernels = _load("scope3d_build_" + kernel_module.replace(".", "_"), aot.source_path(kernel_module))
                aot.compile_kernels(kernels, target, target_cpu=os.environ.get("SCOPE3D_AOT_CPU", ""))
        except Exception as exc:  # noqa: BLE001 - any failure leaves the JIT path, which always works
            print(f"scope3d: ahead-of-time compilation of {kernel_module} failed "
                  f"({type(exc).__name__}: {exc}); numba will compile it on first use instead",
                  file=sys.stderr)

    def get_outputs(self) -> list[str]:
        # a skipped module is not an output (the wheel and editable installs must not expect it)
        return [path for path in super().get_outputs() if os.path.exists(path)]


setup(
    ext_modules=[Extension(name, sources=[], optional=True) for name in COMPILED],
    cmdclass={"build_ext": BuildKernels},
)
