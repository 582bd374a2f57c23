"""What `frontend`, `loopclosure` and `ssmvpr_slam` share: a leaf that imports nothing of ours,
so the two libraries stay independent of each other while their errors have one root."""

from ssmvpr_common.errors import SsmvprError

__all__ = ["SsmvprError"]
