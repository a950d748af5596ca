"""Thread count of the OpenBLAS that numpy and scipy bundle, for dense Cholesky factors such as the reduced
camera system's (:func:`blas_threads`).

OpenBLAS's threads spin while they wait; on a loaded machine a 600 x 600 Cholesky took 15 ms with its
default threads and 2 ms with one. ``openblas_set_num_threads_local`` changes the count for the calling
thread only, so nothing else in the process is affected. Where it is not available this is a no-op.
"""
from __future__ import annotations

import ctypes
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator


@lru_cache(maxsize=1)
def _setters() -> tuple:
    try:
        with open("/proc/self/maps") as handle:
            paths = sorted({line.split()[-1] for line in handle if "openblas" in line.lower() and "/" in line})
    except OSError:
        return ()
    out = []
    for path in paths:
        try:
            fn = ctypes.CDLL(path).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        fn.argtypes = [ctypes.c_int]
        fn.restype = ctypes.c_int
        out.append(fn)
    return tuple(out)


@contextmanager
def blas_threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` OpenBLAS threads in this thread (0: leave the default)."""
    if count <= 0:
        yield
        return
    setters = _setters()
    previous = [fn(count) for fn in setters]
    try:
        yield
    finally:
        for fn, prev in zip(setters, previous):
            fn(prev)
