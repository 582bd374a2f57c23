"""tools/device_checks.py: the GPU session's prepared steps run here in rehearsal (the CPU, small
sizes), each leaving one JSON with its measurements; a kit folder the call did not carry is named."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from kiss_icp.config import KISSConfig

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "device_checks.py"


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=timeout,
                          check=False)  # fmt: skip


@pytest.mark.slow
def test_every_step_runs_and_leaves_its_measurements(tmp_path: Path, weights_path: Path, corridor_dir: Path) -> None:
    out = tmp_path / "out"
    proc = _run("--kit", str(tmp_path / "kit"), "run", "stage1", "backbone", "simulate", "odometry", "slam", "threads",
                "--device", "cpu",
                "--quick",
                "--weights", str(weights_path), "--images", str(corridor_dir / "ref"), "--out", str(out))  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert all(step["ok"] for step in summary["steps"].values())

    stage1_results = json.loads((out / "stage1.json").read_text())["results"]
    stage1 = stage1_results["stage1_2000"]["stage1_index"]["sizes"]["2000"]
    assert stage1["exact_search"] == {"backend": "torch", "device": "cpu", "storage": "float32"}
    assert stage1["exact_equals_numpy"] == {"queries": 3, "equal": 3}
    assert stage1["exact_query_ms"]["median"] > 0
    breakdown = stage1_results["stage1_breakdown"]  # where a query's time goes
    assert breakdown["vectors"] == 20000 and breakdown["selection_equals_topk"] is True

    backbone_results = json.loads((out / "backbone.json").read_text())["results"]
    backbone = backbone_results["backbone"]
    assert backbone["machine"]["device"] == "cpu" and backbone["weights"]["random_weights"] is False
    for precision in ("fp32", "auto"):
        assert backbone["precisions"][precision]["batch_1"]["ms_per_image"] > 0
    assert backbone["precisions"]["auto"]["agreement_with_fp32"]["stage1"]["cosine_min"] > 0.999
    projection = backbone_results["projection"]  # the cubes and PCA on the device against the host
    assert projection["device"] == "cpu" and projection["weights"]["random_weights"] is False
    assert projection["numpy_ms"]["median"] > 0 and projection["torch_ms"]["median"] > 0
    assert max(projection["agreement"].values()) < 1e-4

    simulate = json.loads((out / "simulate.json").read_text())
    assert [(c["name"], c["returncode"]) for c in simulate["commands"]] == [("simulate", 0)]
    odometry = json.loads((out / "odometry.json").read_text())["results"]  # the front end's pace, 5 ways
    for threads in (8, 16):
        for ahead in (0, 1):
            run = odometry[f"odometry_t{threads}_ahead{ahead}"]
            assert run["frames"] == 8 and run["own_process"] is True and run["ahead"] == ahead
            assert run["kiss_icp"]["max_num_threads"] == threads and run["front_end_ms_per_frame"] > 0
            assert (run["kiss_icp"]["max_points_per_voxel"], run["kiss_icp"]["convergence_criterion"]) == (10, 1e-3)
    own = odometry["odometry_t8_ahead1_kiss_own"]  # the same, with kiss-icp's own settings
    assert (own["kiss_icp"]["max_points_per_voxel"], own["kiss_icp"]["convergence_criterion"]) == (20, 1e-4)
    kiss = KISSConfig()  # which are kiss-icp's defaults, not a copy that could drift from them
    assert (kiss.mapping.max_points_per_voxel, kiss.registration.convergence_criterion) == (20, 1e-4)
    assert own["kiss_icp"]["max_num_threads"] == 8 and own["ahead"] == 1 and own["front_end_ms_per_frame"] > 0
    slam = json.loads((out / "slam.json").read_text())
    names = [(c["name"], c["returncode"]) for c in slam["commands"]]
    assert names == [("bench_slam", 0), ("bench_slam_fast", 0)]
    bench, fast = slam["results"]["bench_slam"], slam["results"]["bench_slam_fast"]  # the simulated log, overlapped
    for run in (bench, fast):
        assert run["frames"] == 8 and run["keyframes"] >= 2 and run["error"] is None
        assert run["settings"]["overlap"] is True
    assert fast["machine"]["omp_wait_policy"] == "PASSIVE"
    # the default preset also ran one stage after another, in the same process
    assert bench["serial"]["keyframes"] == bench["keyframes"] and bench["serial"]["settings"]["overlap"] is False
    assert bench["same_loops"] is True and bench["speedup"] > 0
    assert bench["settings"]["kiss_icp_max_num_threads"] == 8 and bench["settings"]["read_ahead_frames"] == 2
    threads = json.loads((out / "threads.json").read_text())["results"]["bench_slam_threads16"]
    assert threads["settings"]["kiss_icp_max_num_threads"] == 16 and threads["keyframes"] == bench["keyframes"]


def test_a_kit_folder_the_call_did_not_carry_is_named(tmp_path: Path) -> None:
    kit = tmp_path / "kit"
    (kit / "weights").mkdir(parents=True)  # an empty folder is not the weights

    def errors() -> dict[str, str]:
        proc = _run("--kit", str(kit), "run", "stage1", "slam", "--out", str(tmp_path / "out"), timeout=60)
        assert proc.returncode == 1
        return {step: record["error"] for step, record in json.loads(proc.stdout)["steps"].items()}

    assert errors() == {"stage1": "carry .device/core .device/faiss (made by `prepare`)",
                        "slam": "carry .device/core .device/slam .device/faiss .device/weights (made by `prepare`)"}  # fmt: skip
    (kit / "weights" / "vgg16_fp16.pth").write_bytes(b"the second call's weights")
    for group in ("core", "slam", "faiss"):  # what the first call installed
        (kit / "site").mkdir(exist_ok=True)
        (kit / "site" / f".installed-{group}").write_text("")
    assert errors()["slam"] == f"no demo.mcap in {kit}: run the simulate step first on this machine"
    assert json.loads((tmp_path / "out" / "slam.json").read_text())["ok"] is False


def test_a_command_past_its_limit_is_killed_and_named(tmp_path: Path, monkeypatch, capsys) -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    import device_checks

    monkeypatch.setitem(device_checks.TIMEOUT_S, "simulate", 1)  # the city alone takes longer
    started = time.monotonic()
    code = device_checks.main(["--kit", str(tmp_path / "kit"), "run", "simulate", "slam", "--device", "cpu",
                               "--quick", "--weights", "unused", "--out", str(tmp_path / "out")])  # fmt: skip
    assert code == 1 and time.monotonic() - started < 30
    record = json.loads((tmp_path / "out" / "simulate.json").read_text())
    assert record["error"] == "simulate: timed out after 1 s"
    assert [c["returncode"] for c in record["commands"]] == [None]
    steps = json.loads(capsys.readouterr().out)["steps"]
    assert steps["simulate"]["ok"] is False
    assert "run the simulate step first" in steps["slam"]["error"]  # no half-written log was taken for one


def test_votes_that_differ_from_numpy_or_schedules_that_differ_in_loops_fail_the_step() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    import device_checks

    sizes = {"1000000": {"exact_equals_numpy": {"queries": 3, "equal": 2}}}
    assert "differ from numpy" in device_checks._verdict("stage1", {"stage1_index": {"sizes": sizes}})
    sizes["1000000"]["exact_equals_numpy"]["equal"] = 3
    assert device_checks._verdict("stage1", {"stage1_index": {"sizes": sizes}}) is None
    assert "chunk selection" in device_checks._verdict("stage1", {"selection_equals_topk": False})
    assert device_checks._verdict("stage1", {"selection_equals_topk": True}) is None
    assert "different loops" in device_checks._verdict("slam", {"same_loops": False})
    assert device_checks._verdict("slam", {"same_loops": True}) is None


def test_the_kit_and_the_gpu_image_cover_every_dependency() -> None:
    """A dependency added to pyproject.toml but neither in the GPU image nor in a carried kit
    fails there on import, after a machine's start was paid for."""
    import re
    import tomllib

    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import device_checks
    finally:
        sys.path.remove(str(SCRIPT.parent))
    project = tomllib.loads((SCRIPT.parents[1] / "pyproject.toml").read_text())["project"]
    needed = {re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0].lower() for d in project["dependencies"]}
    carried = {name.lower() for names in device_checks.WHEELS.values() for name in names}
    assert needed - device_checks.IMAGE_HAS - carried == set()
