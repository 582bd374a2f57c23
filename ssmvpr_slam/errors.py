"""The application's errors: each names the input or output a user can fix."""

from __future__ import annotations

from ssmvpr_common.errors import SsmvprError


class SlamError(SsmvprError):
    """Root of the errors `ssmvpr_slam` raises on purpose (configuration, outputs, checkpoints)."""


class OptionError(SlamError, ValueError):
    """A command-line option's value, or a combination of options, that cannot be used."""
