"""tools/device_checks.py: the GPU session's prepared steps run here in rehearsal (the CPU, small
sizes), each leaving one JSON with its measurements; a kit folder the call did not carry is named."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "device_checks.py"


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=timeout,
                          check=False)  # fmt: skip


@pytest.mark.slow
def test_every_step_runs_and_leaves_its_measurements(tmp_path: Path, weights_path: Path, corridor_dir: Path) -> None:
    out = tmp_path / "out"
    proc = _run("--kit", str(tmp_path / "kit"), "run", "stage1", "backbone", "slam", "--device", "cpu", "--quick",
                "--weights", str(weights_path), "--images", str(corridor_dir / "ref"), "--out", str(out))  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert all(step["ok"] for step in summary["steps"].values())

    stage1 = json.loads((out / "stage1.json").read_text())["result"]["stage1_index"]["sizes"]["2000"]
    assert stage1["exact_search"] == {"backend": "torch", "device": "cpu"}
    assert stage1["exact_equals_numpy"] == {"queries": 3, "equal": 3}
    assert stage1["exact_query_ms"]["median"] > 0

    backbone = json.loads((out / "backbone.json").read_text())["result"]
    assert backbone["machine"]["device"] == "cpu" and backbone["weights"]["random_weights"] is False
    for precision in ("fp32", "auto"):
        assert backbone["precisions"][precision]["batch_1"]["ms_per_image"] > 0
    assert backbone["precisions"]["auto"]["agreement_with_fp32"]["stage1"]["cosine_min"] > 0.999

    slam = json.loads((out / "slam.json").read_text())
    assert [c["returncode"] for c in slam["commands"]] == [0, 0]  # simulated the log, then ran on it
    assert slam["result"]["frames"] == 12 and slam["result"]["keyframes"] >= 2 and slam["result"]["error"] is None
    assert slam["result"]["settings"]["overlap"] is True


def test_a_kit_folder_the_call_did_not_carry_is_named(tmp_path: Path) -> None:
    (tmp_path / "kit" / "weights").mkdir(parents=True)  # the first call's weights, but no wheels
    proc = _run("--kit", str(tmp_path / "kit"), "run", "stage1", "slam", "--out", str(tmp_path / "out"), timeout=60)
    assert proc.returncode == 1
    steps = json.loads(proc.stdout)["steps"]
    assert steps["stage1"]["error"] == "carry .device/core (made by `prepare`)"
    assert steps["slam"]["error"] == "carry .device/core .device/slam (made by `prepare`)"
    assert json.loads((tmp_path / "out" / "slam.json").read_text())["ok"] is False
