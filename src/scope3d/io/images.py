"""Image files: read (colour or grey) and write atomically."""
from __future__ import annotations

import contextlib
import os
import sys
import threading
from pathlib import Path

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.utils.atomic import atomic_file

# Larger images are refused before decoding: 100 Mpx is 300 MB of RGB, beyond any endoscope or borescope
# sensor, while a damaged header can claim up to OpenCV's own limit of 2^30 px (3 GB) and have it allocated.
MAX_IMAGE_PIXELS = 100_000_000


def read_image(path: str | Path, *, grey: bool = False) -> np.ndarray:
    """Read an image as RGB uint8 (H, W, 3), or grey (H, W). A missing or corrupt file is an InputError.

    The file is decoded from its bytes (not ``cv2.imread``) so that non-ASCII paths work and OpenCV's
    decoder warnings are not printed: the caller reports the problem in one line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: image file is missing")
    try:
        data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror})") from None
    img = decode_image_data(data, path, cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    return img if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_image_data(data: np.ndarray, where: str | Path, flag: int) -> np.ndarray:
    """OpenCV's decoding (``cv2.imdecode`` with ``flag``: BGR, grey, or as stored) of an encoded image's bytes
    (uint8 (N,)), after the checks that keep a damaged header from allocating what it claims. Any problem
    is one InputError naming ``where`` (a file, or a message in a bag)."""
    bad_chunk = _png_chunk_overrun(data)
    if bad_chunk:
        raise InputError(f"{where}: not a readable image ({bad_chunk})")
    pixels = _claimed_pixels(data)
    if pixels is not None and pixels > MAX_IMAGE_PIXELS:
        raise InputError(f"{where}: the image header claims {pixels / 1e6:.0f} Mpx, more than scope3d reads "
                         f"({MAX_IMAGE_PIXELS / 1e6:.0f} Mpx; a damaged header?)")
    try:
        with quiet_decoders():
            img = cv2.imdecode(data, flag) if data.size else None
    except cv2.error:
        img = None
    if img is None:
        raise InputError(f"{where}: not a readable image (corrupt or unsupported format)")
    return img


class _StderrSilencer:
    """libpng, libjpeg and FFmpeg print their complaints about a damaged file ("libpng error: IDAT: incorrect data
    check") straight to file descriptor 2, past OpenCV's log level: the CLI's one-line refusal would come
    with a second line. While any thread decodes, fd 2 points to a file in memory; the first decoder in
    saves fd 2, the last one out restores it (a count, so that threads decoding at once never restore each
    other's). A window may ask for the lines written while it was open (FFmpeg's say which frame was
    damaged); with several threads decoding at once, it also gets the others' lines of that time."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved: int | None = None
        self._sink: int | None = None

    @contextlib.contextmanager
    def __call__(self, messages: list[str] | None = None):
        with self._lock:
            if self._users == 0:
                sys.stderr.flush()
                self._saved = os.dup(2)
                self._sink = _memory_file()
                os.dup2(self._sink, 2)
            self._users += 1
            start = os.lseek(self._sink, 0, os.SEEK_END)
        try:
            yield
        finally:
            with self._lock:
                if messages is not None:
                    end = os.lseek(self._sink, 0, os.SEEK_END)
                    text = os.pread(self._sink, end - start, start).decode("utf-8", errors="replace")
                    messages.extend(line for line in text.splitlines() if line.strip())
                self._users -= 1
                if self._users == 0:
                    os.dup2(self._saved, 2)
                    os.close(self._saved)
                    os.close(self._sink)
                    self._saved = self._sink = None


def _memory_file() -> int:
    """A file descriptor of an anonymous file (in memory on Linux), gone when closed."""
    if hasattr(os, "memfd_create"):
        return os.memfd_create("scope3d-decoder-stderr")
    import tempfile

    handle = tempfile.TemporaryFile()
    descriptor = os.dup(handle.fileno())
    handle.close()
    return descriptor


_decoder_stderr_silenced = _StderrSilencer()


@contextlib.contextmanager
def quiet_decoders(messages: list[str] | None = None):
    """While decoding a file that may be damaged: OpenCV's log silenced, and what libpng, libjpeg or FFmpeg
    print on stderr themselves kept from the terminal (the caller reports the problem in one line).
    messages : if given, the non-empty lines the decoders printed while this block ran are appended to it."""
    old_level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with _decoder_stderr_silenced(messages):
            yield
    finally:
        cv2.utils.logging.setLogLevel(old_level)

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_chunk_overrun(data: np.ndarray) -> str | None:
    """What is wrong when a PNG chunk claims more bytes than the file holds, else None. OpenCV's PNG reader
    allocates a chunk's claimed length before reading it: a damaged length (up to 4 GB) must not reach it."""
    raw = data.tobytes()
    if not raw.startswith(_PNG_SIGNATURE):
        return None
    position = len(_PNG_SIGNATURE)
    while position + 8 <= len(raw):
        length = int.from_bytes(raw[position:position + 4], "big")
        kind = raw[position + 4:position + 8]
        if position + 12 + length > len(raw):
            return (f"PNG chunk {kind.decode('latin-1')!r} at byte {position} claims {length} bytes, "
                    f"the file has {len(raw) - position - 12} left")
        if kind == b"IEND":
            return None
        position += 12 + length
    return None


def _claimed_pixels(data: np.ndarray) -> int | None:
    """Width x height from the file's header without decoding it (Pillow reads headers lazily), or None
    when Pillow does not know the format (OpenCV then decodes it, or refuses it)."""
    import io
    import re
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DecompressionBombWarning: the size is checked by the caller
            with Image.open(io.BytesIO(data.tobytes())) as image:
                return image.size[0] * image.size[1]
    except Image.DecompressionBombError as exc:  # beyond twice Pillow's own limit; its message has the count
        found = re.search(r"\((\d+) pixels\)", str(exc))
        return int(found[1]) if found else MAX_IMAGE_PIXELS + 1
    except Exception:  # not a format Pillow knows, or a damaged file: OpenCV has the last word
        return None


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image; the format follows the suffix."""
    path = Path(path)
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise InputError(f"{path}: cannot encode image")
    with atomic_file(path, "wb") as fh:
        fh.write(buf.tobytes())
