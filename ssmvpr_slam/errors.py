"""The application's errors: each names the input or output a user can fix."""

from __future__ import annotations


class SlamError(Exception):
    """Root of the errors `ssmvpr_slam` raises on purpose (configuration, outputs, checkpoints)."""
