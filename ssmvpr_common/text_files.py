"""Reading a file that must be text: a binary or non-UTF-8 file given where text is expected is
one line naming the file, in the caller's error type, never a UnicodeDecodeError traceback."""

from __future__ import annotations

import os
from pathlib import Path


def read_text(path: str | os.PathLike[str], error: type[Exception], encoding: str = "utf-8") -> str:
    """The file's text; `error` (naming the file) when it cannot be read or is not UTF-8 text.

    A NUL byte is valid UTF-8 but never part of a text file: it is refused too, so a zero-filled
    or binary file that happens to decode is not parsed as if it were empty lines."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise error(
            f"{path}: not UTF-8 text (byte {exc.start} is 0x{data[exc.start]:02x}); a text file is expected"
        ) from None
    nul = text.find("\0")
    if nul >= 0:
        raise error(f"{path}: not UTF-8 text (a NUL byte at {nul}, a binary file); a text file is expected")
    return text
