"""Reading the small text files a run takes as input (calib.txt, calibration files, time.txt,
params.json) within a size limit.

Each of them is a few KiB at most; a file many times that (a sparse 2 GB ``calib.txt``) is
refused from its size, before any of it is read, with a one-line error naming it.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import DataError

#: The largest small text input read (real calib.txt files hold a few hundred bytes,
#: calibration files a few KiB).
TEXT_LIMIT = 1 << 20


def describe_size(size: int) -> str:
    """``size`` bytes for a message: ``"2.0 GiB"``, ``"300 KiB"``, ``"12 bytes"``."""
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}" if size < 10 * scale else f"{size // scale} {unit}"
    return f"{size} bytes"


def check_text_size(path: str | os.PathLike, what: str, limit: int = TEXT_LIMIT) -> None:
    """Raise :class:`DataError` when ``path`` (a ``what``, e.g. ``"calib.txt"``) is larger than
    ``limit`` bytes. A file whose size cannot be read is left to the reader to report."""
    try:
        size = os.stat(path).st_size
    except OSError:
        return
    if size > limit:
        raise DataError(f"{path}: {describe_size(size)}; a {what} is at most {describe_size(limit)}")


def read_text_limited(path: str | os.PathLike, what: str, limit: int = TEXT_LIMIT) -> str:
    """The text of ``path`` (a ``what``), refused with :class:`DataError` when it is larger than
    ``limit`` bytes: by its size before reading, and by what it yields for a file without one (a
    pipe). Raises ``OSError`` and ``UnicodeDecodeError`` as :meth:`Path.read_text` does."""
    check_text_size(path, what, limit)
    with open(Path(path), encoding="utf-8") as fh:
        text = fh.read(limit + 1)
    if len(text) > limit:
        raise DataError(f"{path}: more than {describe_size(limit)}; a {what} is at most {describe_size(limit)}")
    return text
