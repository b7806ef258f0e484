"""Image files named by a station set: opened safely, sized from the header, then decoded.

A station set comes from a user, so its image names are untrusted input (issue 11):

* only regular files inside the station directory are read (subfolders allowed). An absolute
  name, a ``..`` or a symlink leading outside, a FIFO, a socket or a device is refused before it
  is opened for reading: a FIFO blocks forever, ``/dev/zero`` never ends.
* the file size and the pixel count in the PNG or JPEG header are checked before decoding: a
  20000x20000 PNG of one grey level is a few hundred kB on disk and 400 MB to 1.2 GB decoded.
* an empty, truncated or corrupt file becomes a rejected station with the reason, never an
  error of the whole calibration. The decoders' own warnings (libpng, libjpeg print them on the
  process's stderr) become that reason instead of stray lines on the terminal.
"""

from __future__ import annotations

import io
import os
import stat
import struct
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from calib import Detection

#: Default largest image, width x height (25 MP; the service's CELLCAL_MAX_IMAGE_PIXELS).
DEFAULT_MAX_PIXELS = 25_000_000
#: Largest file per allowed pixel: 8-bit RGB stored uncompressed.
MAX_FILE_BYTES_PER_PIXEL = 3

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"
#: JPEG start-of-frame markers (they carry the size): C0-CF except DHT C4, JPG C8, DAC CC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: JPEG markers without a length field: TEM and RST0-7 (SOI and EOI end the walk anyway).
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})
_JPEG_SOS = 0xDA
#: Held while file descriptor 2 is captured (``_native_stderr``): the capture is the whole
#: process's, so decoders on several threads take turns, and whoever else writes to stderr
#: meanwhile (``cellcal calibrate``'s progress bar) holds it too, or its text would be read
#: as the decoder's warning.
STDERR_LOCK = threading.Lock()


class ImageFileError(Exception):
    """A station image that cannot be used; ``str(exc)`` is the reason for the user."""


def read_station_image(directory: str | Path, name: str, *,
                       max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray | Detection:
    """The image ``directory/name`` as grey uint8, or a rejected ``Detection`` saying why not.

    Parameters
    ----------
    directory : the station directory; ``name`` must lead to a regular file inside it.
    name : the station's ``image`` entry, relative to ``directory``.
    max_pixels : largest accepted width x height, checked in the file header before decoding.
    """
    try:
        data = _read_regular_file(Path(directory), name,
                                  max_bytes=MAX_FILE_BYTES_PER_PIXEL * max_pixels)
        return _decode(data, name, max_pixels)
    except ImageFileError as exc:
        return Detection(ok=False, reason=str(exc))


def decode_image_bytes(data: bytes, name: str, *,
                       max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Grey uint8 image from PNG or JPEG bytes (e.g. an upload) with the checks of
    ``read_station_image``; ``ImageFileError`` says why not."""
    return _decode(data, name, max_pixels)


def _read_regular_file(directory: Path, name: str, *, max_bytes: int) -> bytes:
    """Bytes of ``directory/name`` if it is a regular file inside ``directory``, else refuse."""
    root = directory.resolve()
    if "\0" in name:
        raise ImageFileError(f"image path {_shown(name)} contains a NUL character")
    if Path(name).is_absolute():
        raise ImageFileError(f"image path {_shown(name)} is absolute: name files relative to the "
                             "station directory")
    path = (root / name).resolve()
    if not path.is_relative_to(root):
        raise ImageFileError(f"image path {_shown(name)} leads outside the station directory")
    try:
        before = os.stat(path)
    except OSError as exc:
        raise ImageFileError(f"cannot read image file {_shown(name)}: "
                             f"{exc.strerror or exc}") from None
    if not stat.S_ISREG(before.st_mode):
        raise ImageFileError(f"image path {_shown(name)} is {_kind(before.st_mode)}, not a "
                             "regular file")
    if before.st_size > max_bytes:
        raise ImageFileError(f"image file {_shown(name)} is {before.st_size / 1e6:.0f} MB, "
                             f"more than the {max_bytes / 1e6:.0f} MB allowed")
    # O_NONBLOCK: should the file be swapped for a FIFO after the check, open does not block;
    # fstat then shows the swap and nothing is read.
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise ImageFileError(f"cannot read image file {_shown(name)}: "
                             f"{exc.strerror or exc}") from None
    with os.fdopen(fd, "rb") as file:
        now = os.fstat(file.fileno())
        if (now.st_dev, now.st_ino) != (before.st_dev, before.st_ino) \
                or not stat.S_ISREG(now.st_mode):
            raise ImageFileError(f"image file {_shown(name)} changed while it was opened")
        data = file.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise ImageFileError(f"image file {_shown(name)} grew beyond the {max_bytes / 1e6:.0f} MB "
                             "allowed while it was read")
    return data


def _shown(name: str, limit: int = 80) -> str:
    """``name`` quoted for a message, cut short if it is long."""
    return repr(name) if len(name) <= limit else repr(name[:limit]) + "..."


def _kind(mode: int) -> str:
    """What a non-regular file is, in words."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a special file"


def _decode(data: bytes, name: str, max_pixels: int) -> np.ndarray:
    """Grey uint8 image from PNG or JPEG bytes whose header allows at most ``max_pixels``."""
    if not data:
        raise ImageFileError(f"image file {_shown(name)} is empty (0 bytes)")
    size = image_size(data)
    if size is None:
        raise ImageFileError(f"image file {_shown(name)} is not a readable image (PNG or JPEG "
                             "expected)")
    width, height = size
    if width == 0 or height == 0:
        raise ImageFileError(f"image file {_shown(name)} has a {width}x{height} header")
    if width * height > max_pixels:
        raise ImageFileError(f"image file {_shown(name)} is {width}x{height} = "
                             f"{width * height / 1e6:.0f} MP, more than the "
                             f"{max_pixels / 1e6:g} MP allowed")
    if _truncated(data):
        raise ImageFileError(f"image file {_shown(name)} is truncated (incomplete copy or "
                             "interrupted capture?)")
    with _native_stderr() as warnings:
        try:
            image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        except cv2.error:
            image = None
    why = " ".join(warnings.getvalue().split())
    if image is None or why:
        raise ImageFileError(f"image file {_shown(name)} is corrupt" + (f" ({why})" if why else ""))
    return image


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the header of PNG or JPEG bytes; None for other or broken data."""
    if data.startswith(_PNG_SIGNATURE):
        if data[12:16] != b"IHDR" or len(data) < 24:
            return None
        width, height = struct.unpack(">II", data[16:24])
        return width, height
    if data.startswith(_JPEG_SOI):
        return _jpeg_size(data)
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of the first JPEG start-of-frame segment (ITU T.81, B.2.2)."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[i + 5:i + 9])
            return width, height
        if marker == _JPEG_SOS:
            return None  # image data before any frame header
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        i += 2 + length
    return None


def _truncated(data: bytes) -> bool:
    """True for a JPEG without its end marker or a PNG without its IEND chunk.

    OpenCV decodes a truncated JPEG anyway (grey below the cut), so this is checked first.
    """
    if data.startswith(_JPEG_SOI):
        return not data.rstrip(b"\x00\r\n ").endswith(b"\xff\xd9")
    return data.startswith(_PNG_SIGNATURE) and b"IEND" not in data[-16:]


@contextmanager
def _native_stderr() -> Iterator[io.StringIO]:
    """Capture what native code (libpng, libjpeg) writes to file descriptor 2 meanwhile.

    A temporary file, not a pipe: a long message cannot block the writer. One capture at a
    time (``STDERR_LOCK``).
    """
    with STDERR_LOCK:
        sys.stderr.flush()
        captured = io.StringIO()
        saved = os.dup(2)
        try:
            with tempfile.TemporaryFile() as tmp:
                os.dup2(tmp.fileno(), 2)
                try:
                    yield captured
                finally:
                    os.dup2(saved, 2)
                tmp.seek(0)
                captured.write(tmp.read(4096).decode(errors="replace"))
        finally:
            os.close(saved)
