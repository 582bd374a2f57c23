"""Errors a user can act on: each names the input that caused it."""


class FrontendInputError(ValueError):
    """A log, folder, topic, image, scan or pose that cannot be used as given."""
