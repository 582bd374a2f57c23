"""A disk that fills at a run's final write: one error line naming the file, the room left and
how to resume; the run's last checkpoint is left as it was and `--resume` finishes the run.

Before: `OSError: [Errno None] 84800 requested and 65504 written: .../database/stage1.npy`, a
traceback: numpy writes an array to a real file with fwrite and reports the short write without
an errno. Here numpy's writer writes the array's header and part of its data to the file, then
raises what numpy raises, while the results are published (the checkpoints before it are
written whole); 16 frames of a simulated street, every frame a keyframe, a checkpoint every 2
keyframes after a 10-keyframe PCA warm-up."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from small_logs import EVERY_FRAME, small_camera_log

import ssmvpr_slam.app.runner as runner_module
from ssmvpr_slam.checkpoint.loading import load_checkpoint


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    settings = (
        "detector: {pca_warmup_keyframes: 10}\n"
        "results: {plots: false, mcap: false, checkpoint_every_keyframes: 2, checkpoint_every_s: null}\n" + EVERY_FRAME
    )
    return small_camera_log(tmp_path_factory.mktemp("disk_full"), settings, max_frames=16)


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file under `folder` (links followed) with its SHA-256, and where each link points."""
    seen = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        if path.is_symlink():
            seen[key] = "-> " + str(path.readlink())
        elif path.is_file():
            seen[key] = hashlib.sha256(path.read_bytes()).hexdigest()
    return seen


def test_a_disk_full_at_the_final_write_is_one_line_and_the_checkpoint_resumes(
    tmp_path: Path, small_log: SimpleNamespace, weights_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    state: dict[str, Any] = {"full": False, "short_writes": 0}
    real_write_array = np.lib.format.write_array
    real_publish = runner_module.publish_results

    def write_array(fp: Any, array: np.ndarray, *args: Any, **kwargs: Any) -> None:
        # a real file (numpy's fwrite path) on a full disk: the header and part of the data, then numpy's error
        if not (state["full"] and isinstance(fp, (io.FileIO, io.BufferedWriter))):
            return real_write_array(fp, array, *args, **kwargs)
        np.lib.format.write_array_header_2_0(fp, np.lib.format.header_data_from_array_1_0(array))
        fp.write(np.ascontiguousarray(array).tobytes()[: array.nbytes // 2])
        state["short_writes"] += 1
        raise OSError(f"{array.size} requested and {array.size // 2} written")

    def publish_on_a_full_disk(run_folder: Any, *args: Any, **kwargs: Any) -> Any:
        state["run_folder"] = run_folder.path
        state["before"] = _snapshot(run_folder.path)
        state["full"] = True
        return real_publish(run_folder, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", write_array)
    monkeypatch.setattr(runner_module, "publish_results", publish_on_a_full_disk)
    result = invoke("run", small_log.log, "-c", small_log.config, "--odometry", "logged", "--weights", weights_path,
                    "--out", out)  # fmt: skip
    run_folder: Path = state["run_folder"]
    assert run_folder is not None and state["short_writes"] == 1
    line = assert_user_error(
        result, "database/stage1.npy: disk full while writing it (short write: ", " free on ",
        f"the last checkpoint, kept in {run_folder}: ssmvpr-slam run {small_log.log} --resume {run_folder}",
    )  # fmt: skip
    assert "Errno" not in line and "requested and" not in line
    # the checkpoint folder is as the run left it before the final write; nothing else was published
    assert _snapshot(run_folder) == state["before"] and (run_folder / "checkpoint").is_symlink()
    assert sorted(p.name for p in out.iterdir()) == [run_folder.name]  # no staging folder, no `latest`
    checkpoint = load_checkpoint(run_folder)
    assert len(checkpoint.result.keyframes) >= 10

    monkeypatch.undo()  # room again
    resumed = invoke("run", small_log.log, "--resume", run_folder, "--weights", weights_path)
    assert resumed.exit_code == 0, resumed.output
    metrics = json.loads((run_folder / "metrics.json").read_text())
    assert metrics["frames"] == 16 and metrics["resumed_from"]["keyframes"] == len(checkpoint.result.keyframes)
    assert (out / "latest").resolve() == run_folder.resolve()
