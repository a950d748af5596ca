"""Write outputs so that a crash, a kill or a user error never leaves a half-written file or folder behind.

Every temporary file or folder is a hidden sibling of its destination whose name carries the writing
process's id: ``.NAME.PID.XXXXXXXX.tmp``. A process killed with SIGKILL cannot clean up after itself,
so the next write to the same destination removes the temporaries of writers that are no longer running
(:func:`remove_stale_temporaries`); the destination itself only ever holds a complete previous or new
result. A folder is swapped into place with one atomic ``renameat2(RENAME_EXCHANGE)`` on Linux, so that
at no moment is the destination missing; elsewhere (or on file systems without it) the old folder is
first moved aside, leaving a window of two renames in which the destination is absent.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import secrets
import shutil
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator, Sequence

_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[^.]+\.(tmp|old)(\.[^.]*)?$")


def _prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}."


def _new_temporary(path: Path, suffix: str, *, directory: bool = False) -> Path:
    """Create a new hidden sibling ``.NAME.PID.XXXXXXXX<suffix>`` of ``path`` (a file, or a folder) and
    return it.

    Created with the permissions a plain ``open`` or ``mkdir`` gives (0o666 or 0o777 less the umask), not
    ``tempfile``'s owner-only 0o600 / 0o700: the temporary is renamed onto the destination, so those would
    leave every output readable by its owner alone (a report served by a web server, results a Dask worker
    writes for a colleague, a folder shared on a lab machine)."""
    for _ in range(100):
        name = path.parent / f"{_prefix(path)}{secrets.token_hex(4)}{suffix}"
        try:
            if directory:
                os.mkdir(name, 0o777)
            else:
                os.close(os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return name
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: could not create a temporary beside it")


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    # a killed process stays a zombie until its parent reaps it (a Dask nanny can take its time): it still
    # answers signal 0 but will never finish its temporary (the batch test's leftover .hole_a...tmp)
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return fh.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):  # no /proc (macOS): signal 0 is all there is
        return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries that writers of ``path`` killed before they finished left beside it.

    Only names of the form ``.NAME.PID.*.tmp`` / ``.NAME.PID.*.old`` whose process no longer runs are
    removed (a concurrent writer's are kept). Returns what was removed.
    """
    path = Path(path)
    removed = []
    try:
        siblings = list(path.parent.iterdir())
    except OSError:
        return removed
    for sibling in siblings:
        match = _TEMPORARY.match(sibling.name)
        # a temporary of this destination, or of one of its temporaries (a writer given a staged path)
        ours = match and (match["name"] == path.name or match["name"].startswith(f".{path.name}."))
        if not ours or _process_alive(int(match["pid"])):
            continue
        if sibling.is_dir() and not sibling.is_symlink():
            shutil.rmtree(sibling, ignore_errors=True)
        else:
            sibling.unlink(missing_ok=True)
        removed.append(sibling)
    return removed


def _remove_own_temporaries(path: Path) -> None:
    """Remove this process's ``.tmp`` temporaries of ``path``.

    The writers below create their temporary inside their ``try``, so that a Ctrl-C landing between the
    creation and the first statement that would remember its name (the moment a watcher sees the file
    appear) still cleans it up: the name is found again from the process id it carries.
    """
    try:
        siblings = list(path.parent.iterdir())
    except OSError:
        return
    for sibling in siblings:
        match = _TEMPORARY.match(sibling.name)
        if match and match["name"] == path.name and int(match["pid"]) == os.getpid() and match[3] == "tmp":
            if sibling.is_dir() and not sibling.is_symlink():
                shutil.rmtree(sibling, ignore_errors=True)
            else:
                sibling.unlink(missing_ok=True)


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "w", **open_kwargs) -> Iterator:
    """Open a temporary file beside ``path``; rename it onto ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    try:
        tmp = _new_temporary(path, ".tmp")
        with open(tmp, mode, **open_kwargs) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        _remove_own_temporaries(path)
        raise


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a writer that takes a file name (cv2.imwrite, savefig).

    The temporary keeps ``path``'s suffix, from which such writers choose the format.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    try:
        name = _new_temporary(path, f".tmp{path.suffix}")
        yield name
        os.replace(name, path)
    except BaseException:
        _remove_own_temporaries(path)
        raise


@contextmanager
def atomic_files(paths: Sequence[str | os.PathLike]) -> Iterator[list[Path]]:
    """Temporary paths for several output files that belong together (a solution and its report).

    All are renamed onto their destinations only once the block has written every one of them, one
    rename after another: a kill can then only fall in the microseconds between those renames, never
    while a file is being written. Destinations must differ.
    """
    paths = [Path(p) for p in paths]
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError("output files must be different paths")
    with ExitStack() as stack:
        tmps = [stack.enter_context(atomic_path(p)) for p in paths]
        yield tmps
        # ExitStack renames in reverse order of entry: the first path given is renamed last


def _rename_exchange():
    """libc's renameat2 with RENAME_EXCHANGE, or None where it is unavailable."""
    if not hasattr(os, "uname") or os.uname().sysname != "Linux":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        function = libc.renameat2
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one atomic step; False if the system cannot (then nothing changed)."""
    function = _rename_exchange()
    if function is None:
        return False
    status = function(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    return status == 0


@contextmanager
def atomic_directory(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Build a whole output folder in a temporary sibling and move it into place at the end.

    If ``path`` exists and ``overwrite`` is true, it is replaced only once the new folder is complete,
    by an atomic exchange where the system offers one (see the module docstring).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    try:
        tmp = _new_temporary(path, ".tmp", directory=True)
        yield tmp
        if path.exists():
            if not overwrite:
                raise FileExistsError(path)
            if _exchange(tmp, path):
                shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the previous result
                return
            old = _new_temporary(path, ".old", directory=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        _remove_own_temporaries(path)  # the .tmp folder only: a moved-aside .old one holds the previous result
        raise
