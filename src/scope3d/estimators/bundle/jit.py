"""When the bundle adjuster's numba kernels compile (how they are written: :mod:`.kernels`).

The kernels are cached on disk (``cache=True``): beside the sources, or in NUMBA_CACHE_DIR. A fresh
install has no cache, and the first run compiles every kernel it calls. Measured on BAL ladybug-49
(benchmarks/bench_first_run.py, docs/report.md, "First run after pip install"): 24 CPU-seconds, of which
the parallel Schur assembly (``assemble_reduced_system_parallel``, numba's parfors) is about a quarter.

:func:`parallel_assembly_ready` lets a command avoid that wait: when the parallel kernel is not in the
cache, it starts one detached background process that compiles every kernel into the cache
(:func:`scope3d.estimators.bundle.warm_up`, on the machine's other core) and says no, so the run uses
the one-thread assembly (same results, and cheaper to compile); the next run finds the parallel kernel
cached. The other kernels still compile in the first run. Library functions never start processes: the
command line decides.
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# A warm-up process older than this is taken as dead (the full warm-up takes ~30 s of CPU).
STALE_LOCK_S = 600.0


def kernel_cached(dispatcher) -> bool:
    """Whether numba's on-disk cache holds a compiled version of ``dispatcher`` for this machine's CPU
    (the index entry for this source file and code generator). True when numba's cache cannot be
    inspected (then behave as if cached: compile on call, as numba does)."""
    try:
        cache = dispatcher._cache
        index = cache._cache_file._load_index()  # {} when missing or the source changed
        magic = dispatcher.targetctx.codegen().magic_tuple()
    except Exception:  # numba internals differ: no opinion
        return True
    return any(len(key) > 1 and key[1] == magic for key in index)


def _lock_path() -> Path:
    """One lock per cache location (NUMBA_CACHE_DIR or the in-tree one), in the temporary folder."""
    from scope3d.estimators.bundle import kernels

    try:
        where = str(kernels.assemble_reduced_system_parallel._cache._cache_path)
    except Exception:
        where = os.environ.get("NUMBA_CACHE_DIR", str(Path(kernels.__file__).parent))
    digest = hashlib.sha1(where.encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"scope3d-numba-warm-up-{digest}.lock"


def start_background_warm_up() -> bool:
    """Start one detached process compiling every kernel into the cache, unless one is running (a lock
    younger than STALE_LOCK_S). Returns whether a process was started."""
    lock = _lock_path()
    try:
        if lock.exists() and time.time() - lock.stat().st_mtime < STALE_LOCK_S:
            return False
        lock.unlink(missing_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except OSError:
        return False
    os.close(fd)
    code = ("import pathlib, scope3d.estimators.bundle as b\n"
            f"try:\n    b.warm_up()\nfinally:\n    pathlib.Path({str(lock)!r}).unlink(missing_ok=True)\n")
    subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True, env=dict(os.environ))
    return True


def parallel_assembly_ready(*, start_warm_up: bool = True) -> bool:
    """True when the parallel Schur assembly is compiled and cached for this machine; otherwise starts
    the background warm-up (when ``start_warm_up``) and returns False: use ``num_threads=1`` this run."""
    from scope3d.estimators.bundle import kernels

    if kernel_cached(kernels.assemble_reduced_system_parallel):
        return True
    if start_warm_up:
        start_background_warm_up()
    return False
