"""SSM-VPR (Camara & Preucil, ECMR 2019) place recognition, usable on its own.

The names a user needs import from here; torch loads on first use of one that needs it:

    from loopclosure import LoopDetector, PlaceRecognizer, list_images, read_image
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ssmvpr_common.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from loopclosure.backbone_input import list_images, read_image
    from loopclosure.config import DetectorConfig, VPRConfig
    from loopclosure.database import PlaceDatabase
    from loopclosure.detector import LoopDetector, LoopProposal
    from loopclosure.errors import LoopClosureError, LoopClosureInputError
    from loopclosure.place_recognizer import PlaceRecognizer
    from loopclosure.two_stage import Recognition

_EXPORTS = {
    "DetectorConfig": "loopclosure.config",
    "VPRConfig": "loopclosure.config",
    "PlaceDatabase": "loopclosure.database",
    "LoopDetector": "loopclosure.detector",
    "LoopProposal": "loopclosure.detector",
    "LoopClosureError": "loopclosure.errors",
    "LoopClosureInputError": "loopclosure.errors",
    "list_images": "loopclosure.backbone_input",
    "read_image": "loopclosure.backbone_input",
    "PlaceRecognizer": "loopclosure.place_recognizer",
    "Recognition": "loopclosure.two_stage",
}
__all__ = [
    "DetectorConfig",
    "LoopClosureError",
    "LoopClosureInputError",
    "LoopDetector",
    "LoopProposal",
    "PlaceDatabase",
    "PlaceRecognizer",
    "Recognition",
    "VPRConfig",
    "list_images",
    "read_image",
]


__getattr__ = lazy_exports("loopclosure", _EXPORTS)
