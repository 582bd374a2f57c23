"""`loop-eval --verify` on real day/night passes (the shared Gardens Point half cut short): every
accepted loop checked by two views on the backbone's deep features, reported beside the
unverified figures; with the accept level lowered until the detector takes wrong places, the
verifier refuses them."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

pytestmark = pytest.mark.slow


def cut(source: Path, target: Path, first: int, count: int) -> Path:
    """`count` images of `source` from the `first`-th on, linked into `target`."""
    target.mkdir(parents=True)
    for path in sorted(source.iterdir())[first : first + count]:
        (target / path.name).symlink_to(path)
    return target


LOWERED = "detector:\n  calibrated: {accept: -5.0, propose: -6.0}\n"  # every winner accepted, wrong places too


def _loop_eval(*args: object, out: Path) -> tuple[dict, list[dict[str, str]]]:
    result = invoke("loop-eval", *args, "--verify", "--device", "cpu", "--out", out)
    assert result.exit_code == 0, result.output
    assert "verified by two" in result.output  # the summary's row (rich may wrap its label)
    folder = out / "latest"
    with (folder / "loops.csv").open() as f:
        rows = list(csv.DictReader(f))
    return json.loads((folder / "metrics.json").read_text()), rows


@pytest.fixture(scope="module")
def passes(shared_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    half = shared_dir / "data" / "gardens_point_half"
    root = tmp_path_factory.mktemp("gp")
    return cut(half / "day_right", root / "day", 40, 30), cut(half / "night_right", root / "night", 40, 30)


def test_verified_loops_are_reported_beside_the_detectors(
    tmp_path: Path, passes: tuple[Path, Path], weights_path: Path, shared_backbone_passes: object
) -> None:
    metrics, rows = _loop_eval(*passes, "--weights", weights_path, out=tmp_path)
    loops, verify = metrics["loops"], metrics["verify"]
    assert loops["accepted"] >= 20 and loops["precision"] == 1.0
    assert verify["checked"] == loops["accepted"]
    refused = verify["refused_right_loops"] + verify["refused_wrong_loops"]
    assert verify["verified"] + verify["kept_by_agreement"] + refused == loops["accepted"]
    assert verify["views_alone"]["accepted"] == verify["verified"] >= 0.8 * loops["accepted"]
    assert verify["loops"]["accepted"] == verify["verified"] + verify["kept_by_agreement"]
    assert verify["loops"]["precision"] == verify["views_alone"]["precision"] == 1.0
    assert verify["loops"]["pr_auc"] is None  # only accepted loops are verified: no curve of its own
    assert verify["ms_per_loop_median"] > 0
    accepted = [r for r in rows if r["accepted"] == "1"]
    assert len(accepted) == loops["accepted"]
    assert all(r["verified"] in ("0", "1") and r["verification"].startswith("fundamental matrix") for r in accepted)
    assert sum(r["verified"] == "1" for r in accepted) == verify["verified"]
    assert sum(r["kept"] == "1" for r in accepted) == verify["loops"]["accepted"]
    kept_by_agreement = [r for r in accepted if r["verified"] == "0" and r["kept"] == "1"]
    assert all("earlier verified loops of the revisit agree" in r["verification"] for r in kept_by_agreement)
    assert all(r["verified"] == r["kept"] == "" for r in rows if r["accepted"] == "0")


def test_the_verifier_refuses_the_wrong_places_a_lowered_accept_level_takes(
    tmp_path: Path, shared_dir: Path, weights_path: Path, shared_backbone_passes: object
) -> None:
    """The day walk's frames 40-69, then the night walk's frames 0-29: no place is in both passes,
    so every loop the detector accepts with its accept level lowered below any margin is a wrong
    place (a night frame matched to a day frame of another stretch of the walk)."""
    half = shared_dir / "data" / "gardens_point_half"
    day = cut(half / "day_right", tmp_path / "day", 40, 30)
    night = cut(half / "night_right", tmp_path / "night", 0, 30)
    config = tmp_path / "lowered.yaml"
    config.write_text(LOWERED)
    metrics, rows = _loop_eval(day, night, "--weights", weights_path, "-c", config, out=tmp_path / "out")
    accepted = [r for r in rows if r["accepted"] == "1"]
    assert len(accepted) >= 10 and metrics["verify"]["checked"] == len(accepted)
    verified = [r for r in accepted if r["verified"] == "1"]
    assert len(verified) <= 0.1 * len(accepted), [(r["image"], r["match_image"]) for r in verified]
    kept = [r for r in accepted if r["kept"] == "1"]  # a run of wrong places has too few verified ones to vouch
    assert len(kept) <= 0.1 * len(accepted), [(r["image"], r["match_image"]) for r in kept]
    assert all("fundamental matrix" in r["verification"] for r in accepted)
