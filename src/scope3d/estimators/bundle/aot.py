"""The bundle adjuster's kernels compiled ahead of time, at install, so that no run pays numba's JIT.

:mod:`.kernels` is the one source of the kernels. ``pip install`` (setup.py's ``build_ext``) compiles it
with numba's ``pycc`` into the extension module ``scope3d.estimators.bundle._kernels_aot``; the solver
then calls that module and never imports numba. Loading it takes milliseconds, where a fresh numba
cache cost ~8 CPU-seconds of compilation (~27 with the old parfors assembly) in the first bundle
adjustment (benchmarks/bench_first_run.py).

The build needs numba and a C compiler (pycc links the module with the Python toolchain). Without them
the install still succeeds, setup.py says why the module was skipped, and the kernels are compiled
by numba on first use (the JIT path, cached on disk as before). :func:`load_kernels` also falls back to
the JIT when the compiled module was built from another version of kernels.py (an editable install
whose kernels were edited since): the module stores a digest of the source it was built from.

numba's ``pycc`` is pending deprecation since numba 0.57 (still shipped in 0.68, no replacement yet);
were it removed, the build would skip the module and the JIT path would serve.

The compiled functions release the GIL (the Schur assembly runs on several threads, see
:func:`scope3d.estimators.bundle.kernels.assemble_point_range`); pycc has no option for that, so
:func:`compile_kernels` turns numba's ``release_gil`` flag on for its build (checked in the tests).
"""
from __future__ import annotations

import hashlib
import importlib
from pathlib import Path
from types import ModuleType

AOT_MODULE = "_kernels_aot"
KERNELS_SOURCE = Path(__file__).with_name("kernels.py")

_F2 = "f8[:, ::1]"
_F3 = "f8[:, :, ::1]"
_I1 = "i8[::1]"
_I2 = "i8[:, ::1]"
# Exact argument types the solver passes (all arrays C-contiguous): an exported function does not
# dispatch on types, it converts its arguments to these or raises TypeError.
SIGNATURES = {
    "residuals_and_jacobians": f"void(f8[:, ::1], {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F3}, b1, {_F2}, {_F3}, "
                               f"{_F2}, b1, {_F2}, {_F3}, {_F3})",
    "squared_residuals": f"void({_F2}, {_I1}, {_I1}, {_I1}, {_F3}, {_F2}, {_F2}, {_F2}, b1, f8[::1])",
    "gradient_and_diagonal": f"Tuple((f8[::1], f8[::1], {_F2}, {_F2}))({_F2}, {_F3}, {_F3}, {_I2}, {_I1}, i8, i8)",
    "zero_frozen_columns": f"void({_F3}, {_F3}, {_I2}, {_I1}, b1[::1], b1[:, ::1])",
    "block_structure_keys": f"{_I1}({_I2}, {_I1}, i8)",
    "pair_slots": f"Tuple((i4[::1], {_I1}))({_I2}, {_I1}, {_I1}, {_I1})",
    "assemble_reduced_system": f"b1({_F2}, {_F3}, {_F3}, {_I2}, {_I1}, f8[::1], {_F2}, {_I1}, {_I1}, {_F3}, "
                               f"f8[::1], {_F3}, {_F2}, {_I1}, i4[::1])",
    "add_diagonal": f"void({_I1}, {_I1}, {_F3}, f8[::1])",
    "assemble_point_range": f"b1(i8, i8, i8, {_F2}, {_F3}, {_F3}, {_I2}, {_I1}, {_F2}, {_F3}, f8[::1], {_F3}, "
                            f"{_F2}, {_I1}, i4[::1])",
    "back_substitute": f"{_F2}({_F3}, {_F3}, {_I2}, {_I1}, {_F3}, {_F2}, f8[::1])",
    "jacobian_step_norm2": f"f8({_F3}, {_F3}, {_I2}, {_I1}, f8[::1], {_F2})",
    "bsr_to_dense": f"{_F2}({_I1}, {_I1}, {_F3})",
    "scale_rows": f"void({_F2}, {_F3}, {_F3}, f8[::1])",
}


def source_digest(path: Path = KERNELS_SOURCE) -> int:
    """First 60 bits of the SHA-256 of kernels.py, as a non-negative int64 the compiled module returns."""
    return int(hashlib.sha256(Path(path).read_bytes()).hexdigest()[:15], 16)


def load_kernels(prefer: str = "auto") -> ModuleType:
    """The module whose functions the solver calls.

    prefer : "auto" (the compiled module when installed and built from this kernels.py, else the JIT
        kernels), "aot" (the compiled module; ImportError when missing or stale) or "jit".
    """
    if prefer not in ("auto", "aot", "jit"):
        raise ValueError(f"prefer must be 'auto', 'aot' or 'jit', got {prefer!r}")
    if prefer != "jit":
        try:
            module = importlib.import_module(f"{__package__}.{AOT_MODULE}")
        except ImportError:
            if prefer == "aot":
                raise
        else:
            if module.source_digest() == source_digest():
                return module
            if prefer == "aot":
                raise ImportError(f"{module.__file__} was built from another kernels.py; reinstall scope3d")
    return importlib.import_module(f"{__package__}.kernels")


def compile_kernels(kernels: ModuleType, output_path: Path, *, target_cpu: str = "") -> Path:
    """Compile the numba functions of ``kernels`` (the module :mod:`.kernels`) into the extension module
    at ``output_path`` (a ``.so``/``.pyd`` named by the platform's extension suffix).

    target_cpu : LLVM CPU name; "" (numba's default for pycc) is a generic CPU of the architecture, so
        that a wheel runs on any machine of it; "host" tunes for the building machine.
    Needs numba (pycc) and a C compiler; raises what they raise otherwise (setup.py catches it).
    """
    import warnings

    from numba.core.errors import NumbaPendingDeprecationWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaPendingDeprecationWarning)  # said in this module's docstring
        import numba.pycc.compiler as pycc_compiler
        from numba.pycc import CC

    output_path = Path(output_path)
    cc = CC(output_path.name.split(".")[0], source_module=kernels)
    cc.output_dir = str(output_path.parent)
    cc.output_file = output_path.name
    cc.target_cpu = target_cpu
    for name, signature in SIGNATURES.items():
        cc.export(name, signature)(getattr(kernels, name).py_func)
    digest = source_digest(Path(kernels.__file__))
    namespace: dict = {}
    exec(f"def source_digest():\n    return {digest}\n", namespace)  # a constant the module returns
    cc.export("source_digest", "i8()")(namespace["source_digest"])

    base_flags = pycc_compiler.Flags

    class ReleasingGil(base_flags):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    pycc_compiler.Flags = ReleasingGil
    try:
        cc.compile()
    finally:
        pycc_compiler.Flags = base_flags
    return output_path
