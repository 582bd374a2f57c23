"""Errors a user can act on: each names the input that caused it."""


class LoopClosureInputError(ValueError):
    """An image, code array, database or configuration that cannot be used as given."""


class WeightsNotFoundError(RuntimeError):
    """No way of obtaining the VGG16 weights worked; the message lists the ways."""
