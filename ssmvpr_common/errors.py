"""The root of every error the project raises on purpose.

Each package derives its own (`frontend.errors.FrontendError`, `loopclosure.errors.
LoopClosureError`, `ssmvpr_slam.errors.SlamError`), so a caller can catch one package's errors
or all of them (``except SsmvprError``) without knowing every class. Input errors also derive
from ValueError, as they did before the root existed."""

from __future__ import annotations


class SsmvprError(Exception):
    """An error a user can act on; the message names the input, file or option concerned."""
