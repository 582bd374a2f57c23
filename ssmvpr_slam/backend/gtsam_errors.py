"""GTSAM's errors in a few words: its C++ exceptions reach Python as RuntimeError with messages
of up to ten lines, too long for the one-line errors and warnings users read."""

from __future__ import annotations

import re


def gtsam_reason(error: Exception) -> str:
    """GTSAM's multi-line message in a few words (its indeterminate-system text runs to ten lines)."""
    text = " ".join(str(error).split())
    symbol = re.search(r"Symbol: (\w+)", text)
    if "Indeterminate linear system" in text:
        return "indeterminate linear system" + (f" near {symbol.group(1)}" if symbol else "")
    return text[:160] or type(error).__name__
