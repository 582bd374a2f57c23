"""The shared body of the ``tools/*_to_mcap.py`` converters: a source in, an MCAP log out."""

from __future__ import annotations

import itertools
import sys
from collections.abc import Callable
from pathlib import Path

from frontend.config import McapWriterConfig
from frontend.errors import FrontendInputError
from frontend.sources.base import Source
from frontend.sources.mcap_writer import write_frames


def convert_to_mcap(
    open_source: Callable[[], Source],
    output: str | Path,
    max_frames: int | None = None,
    image_format: str = "raw",
) -> int:
    """Open the source, print its description, write up to ``max_frames`` frames (and the
    source's camera calibration) to ``output`` and print the count. Returns the exit status: 0,
    or 2 after printing the :class:`FrontendInputError` that stopped it to stderr."""
    try:
        source = open_source()
        print(source.description)
        frames = itertools.islice(source, max_frames)
        count = write_frames(frames, output, McapWriterConfig(image_format=image_format), source.intrinsics)
    except FrontendInputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {count} frames to {output}")
    return 0
