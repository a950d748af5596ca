"""Every numba kernel of the package compiled ahead of time, at install, so that no run pays numba's JIT.

A *kernel module* holds numba functions and nothing else a run needs: it imports only numpy and numba
(setup.py compiles it without importing scope3d, whose dependencies the build environment lacks) and
names the functions to export, with their exact argument types, in a dict ``AOT_SIGNATURES``
(``{name: numba signature string}``). :data:`KERNEL_MODULES` lists them all. ``pip install``
(setup.py's ``build_ext``) compiles each with numba's ``pycc`` into the extension module beside it,
``_<name>_aot`` (:func:`aot_module_name`), which also returns a digest of the source it was built from.
Callers get their kernels from :func:`load_kernels` and never import numba on that path: loading the
compiled module takes milliseconds, where numba cost ~8 CPU-seconds of compilation in the first bundle
adjustment (benchmarks/bench_first_run.py) and ~4 in the first localized frame.

The one fallback: without a C compiler, Python's headers or numba's pycc, the install still succeeds,
setup.py says why a module was skipped, and :func:`load_kernels` returns the kernel module itself, whose
functions numba compiles on first use (and caches on disk). It does the same when the compiled module was
built from another version of the source (an editable install whose kernels were edited since).
:func:`warm_up` compiles the JIT path's signatures beforehand (the Makefile runs it after installing).

numba's ``pycc`` is pending deprecation since numba 0.57 (still shipped in 0.68, no replacement yet);
were it removed, the build would skip the modules and the JIT path would serve.

The compiled functions release the GIL (the bundle adjuster's Schur assembly runs on several threads);
pycc has no option for that, so :func:`compile_kernels` turns numba's ``release_gil`` flag on for its
build (checked in tests/test_bundle_aot.py). Every kernel module's functions should be ``nogil`` on the
JIT path too, so that both paths behave alike.

This module imports only the standard library at the top: setup.py loads it from its file.
"""
from __future__ import annotations

import hashlib
import importlib
from pathlib import Path
from types import ModuleType

#: Every kernel module of the package (dotted names; setup.py compiles each, :func:`warm_up` warms each).
KERNEL_MODULES = (
    "scope3d.estimators.bundle.kernels",
    "scope3d.estimators.bundle.lens_kernels",
    "scope3d.estimators.pose_kernels",
    "scope3d.feature.descriptor_kernels",
    "scope3d.mvs.axial_kernels",
    "scope3d.mvs.refine_kernels",
    "scope3d.phantoms.raycast_kernels",
    "scope3d.phantoms.render_kernels",
)

_PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # src/scope3d
_PREFERENCES = ("auto", "aot", "jit")


def aot_module_name(kernel_module: str) -> str:
    """Dotted name of the compiled module of ``kernel_module``: ``a.b.kernels`` -> ``a.b._kernels_aot``."""
    package, _, name = kernel_module.rpartition(".")
    return f"{package}._{name}_aot"


def source_path(kernel_module: str) -> Path:
    """The source file of ``kernel_module`` (found from this file, without importing anything)."""
    parts = kernel_module.split(".")
    if parts[0] != "scope3d" or len(parts) < 2:
        raise ValueError(f"not a module of scope3d: {kernel_module!r}")
    return _PACKAGE_ROOT.joinpath(*parts[1:]).with_suffix(".py")


def source_digest(path: Path) -> int:
    """First 60 bits of the SHA-256 of a kernel module's source, as a non-negative int64 (what its
    compiled module's ``source_digest()`` returns)."""
    return int(hashlib.sha256(Path(path).read_bytes()).hexdigest()[:15], 16)


def load_kernels(kernel_module: str, prefer: str = "auto") -> ModuleType:
    """The module whose functions the caller runs: ``kernel_module`` compiled or as numba source.

    kernel_module : a dotted name of :data:`KERNEL_MODULES`.
    prefer : "auto" (the compiled module when installed and built from this source, else the JIT kernel
        module), "aot" (the compiled module; ImportError when missing or stale) or "jit".
    """
    if prefer not in _PREFERENCES:
        raise ValueError(f"prefer must be 'auto', 'aot' or 'jit', got {prefer!r}")
    if prefer != "jit":
        try:
            module = importlib.import_module(aot_module_name(kernel_module))
        except ImportError:
            if prefer == "aot":
                raise
        else:
            if module.source_digest() == source_digest(source_path(kernel_module)):
                return module
            if prefer == "aot":
                raise ImportError(f"{module.__file__} was built from another {source_path(kernel_module).name}; "
                                  "reinstall scope3d")
    return importlib.import_module(kernel_module)


def is_compiled(kernels: ModuleType) -> bool:
    """Whether ``kernels`` (from :func:`load_kernels`) is a module compiled ahead of time."""
    return kernels.__name__.rpartition(".")[2].endswith("_aot")


def warm_up(prefer: str = "auto") -> dict[str, bool]:
    """Load every kernel module; on the JIT path compile each exported signature now (numba caches it on
    disk), so that no later run pays it. Returns ``{kernel module: compiled ahead of time}``."""
    out = {}
    for name in KERNEL_MODULES:
        kernels = load_kernels(name, prefer)
        out[name] = is_compiled(kernels)
        if not out[name]:
            for function, signature in kernels.AOT_SIGNATURES.items():
                getattr(kernels, function).compile(signature)
    return out


def compile_kernels(kernels: ModuleType, output_path: Path, *, target_cpu: str = "") -> Path:
    """Compile the functions ``kernels.AOT_SIGNATURES`` names (numba dispatchers of the kernel module
    ``kernels``) into the extension module at ``output_path`` (a ``.so``/``.pyd`` named by the platform's
    extension suffix), with a ``source_digest()`` returning :func:`source_digest` of ``kernels``'s file.

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
    for name, signature in kernels.AOT_SIGNATURES.items():
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
