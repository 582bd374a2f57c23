"""Errors a user can act on: each names the input that caused it."""

from ssmvpr_common.errors import SsmvprError


class FrontendError(SsmvprError):
    """Root of the errors `frontend` raises on purpose."""


class FrontendInputError(FrontendError, ValueError):
    """A log, folder, topic, image, scan or pose that cannot be used as given."""
