#!/usr/bin/env python3
"""A wheel install behaves like the editable one: the presets ship inside the package.

Run from a directory outside the checkout with the unpacked wheel first on PYTHONPATH (as
.ci/run does); compares every preset against the checkout's configs/ and prints JSON.

    PYTHONPATH=WHEEL_DIR python tools/check_wheel_install.py CHECKOUT
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    checkout = Path(argv[1]).resolve()
    import ssmvpr_slam
    from ssmvpr_slam.config.slam import PRESETS_DIR, available_presets, load_config

    installed = Path(ssmvpr_slam.__file__).resolve().parent
    expected = sorted(p.stem for p in (checkout / "configs").glob("*.yaml"))
    report = {
        "package": str(installed),
        "presets_dir": str(PRESETS_DIR),
        "presets": available_presets(),
        "expected": expected,
        "problems": [],
    }
    if checkout in installed.parents:
        report["problems"].append("ssmvpr_slam was imported from the checkout, not from the wheel")
    if available_presets() != expected:
        report["problems"].append("the wheel's presets differ from configs/")
    for name in expected:  # each preset loads and equals its YAML (one key checked by value)
        shipped = (PRESETS_DIR / f"{name}.yaml").read_text()
        if shipped != (checkout / "configs" / f"{name}.yaml").read_text():
            report["problems"].append(f"preset {name}: shipped text differs")
        load_config(name)
    default = load_config()
    if default.detector.accept_score != load_config("default").detector.accept_score:
        report["problems"].append("no config given does not mean the default preset")
    report["default_detector_accept_score"] = default.detector.accept_score
    print(json.dumps(report, indent=2))
    return 1 if report["problems"] else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
