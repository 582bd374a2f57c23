"""Quoting an offending input in an error message, at a length a terminal can show.

An error quotes the line (or token, or cell) it could not read so the user can find it; a file
that is not what it claims to be may hold a line of megabytes, and echoing it whole buries the
message (a 30 MB line of a bad g2o file once was the error). Every reader quotes through here."""

from __future__ import annotations

QUOTE_LIMIT = 200
"""Characters of an input quoted in an error: enough to recognise a line, short enough to read."""


def shortened(text: str, limit: int = QUOTE_LIMIT) -> str:
    """`text`, or its first `limit` characters, an ellipsis and how long it was."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text):,} characters)"


def quoted(text: str, limit: int = QUOTE_LIMIT) -> str:
    """``repr(text)``, cut as `shortened` cuts: ``'EDGE_SE2 0 1 xxxx…' (31,457,280 characters)``."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit] + '…'!r} ({len(text):,} characters)"
