"""Errors a user can act on: each names the input that caused it."""

from ssmvpr_common.errors import SsmvprError


class LoopClosureError(SsmvprError):
    """Root of the errors `loopclosure` raises on purpose."""


class LoopClosureInputError(LoopClosureError, ValueError):
    """An image, code array, database or configuration that cannot be used as given."""


class WeightsNotFoundError(LoopClosureError, RuntimeError):
    """No way of obtaining the VGG16 weights worked; the message lists the ways."""
