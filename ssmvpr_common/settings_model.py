"""The one policy every settings model follows, in every package: an unknown key is an error (a
typo in a preset or a user's file must not be silently ignored), a value set after loading is
checked as one loaded is, and NaN or infinity is refused (NaN passes every bound, since it
compares false, and means nothing as a setting)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class SettingsModel(BaseModel):
    """Base of the settings models (`frontend`, `loopclosure`, `ssmvpr_slam`)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
