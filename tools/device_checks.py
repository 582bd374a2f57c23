"""The GPU measurements of issues 10 and 41, prepared on this machine and run on a lent GPU machine.

A session is lent a GPU only now and then, for 15 minutes in all, and that machine has torch
with CUDA but none of this project's other dependencies, no shared weights, and no network.
So everything it needs is made ready here, and each call there runs prepared steps with a
timeout each, writing one JSON per step:

    python tools/device_checks.py prepare            # here: wheels for its Python, fp16 weights, images

    device run, call 1 (carry .device/core .device/slam):
        python3 tools/device_checks.py run simulate odometry --out $OUT
    device run, call 2, at once on the same warm machine (carry .device/faiss .device/weights):
        python3 tools/device_checks.py run slam threads --out $OUT
    (stage1 and backbone, measured in earlier sessions, take a call of their own: stage1 carries
    .device/core .device/faiss, backbone .device/core .device/weights .device/images)

Steps:
  simulate  the demo traverse simulated into a log (.device/demo.mcap), for `slam`.
  slam      the whole pipeline on that log with the backbone on the GPU (tools/bench_slam.py
            --device cuda --precision auto): by default pipelined against --serial (keyframes
            per second, the stages' latency, speedup and same_loops), then -c fast with
            --omp-wait-policy PASSIVE. On its 16 cores `auto` turns on the registration worker
            and the encoder's thread (pipeline.encode_ahead): backbone_ahead is then the
            backbone's time, in the encoder's thread, and critical_path names the thread that
            sets the pace.
  odometry  the front end's pace with kiss-icp in its own process (tools/bench_odometry.py
            --own-process, 200 demo frames): on 8 and 16 threads, frames handed over one at a
            time against one ahead (pipeline.odometry_ahead_frames), the default preset; then on 8
            threads, one ahead, with kiss-icp's own settings (20 points a voxel, a 1e-4 stop).
  threads   the default preset pipelined with kiss-icp on 16 threads (the odometry's and the loop
            registration's max_num_threads; 8 by default): after slam in call 2, which writes its
            JSON first, or in a call of its own carrying what slam carries.
  stage1    stage I exact search as torch matrix products on the GPU at 100k and 1M places
            (tools/bench_vpr.py --only-index --exact-backend torch --torch-device cuda): query ms,
            build seconds, and whether its votes equal numpy brute force on 3 queries; then
            where a 1M query's time goes (tools/bench_device_search.py).
  backbone  VGG16 to conv5_2 on the GPU at fp32 and auto (bf16 on a card that has it):
            ms per image at batch 1 and 8, agreement with fp32 (tools/bench_backbone.py); then a
            keyframe's two images to codes with the cubes and PCA on the host against on the GPU
            (tools/bench_projection.py: ms and agreement).

The wheels and weights of the slam measurement together are too large for one call's carry
(64 MiB: gtsam alone is 35 MB, the weights 29 MB), so the first call simulates with what it
carries, and the second relies on what the first installed under .device/site and on the log it
left in .device/; if the machine was given back in between, `run` says what to carry or to run
again. `--device cpu --quick` runs the same steps small on this machine (the test does), so a
GPU session spends its minutes measuring: 2000 places, 20000 search vectors, the backbone at
112 px, an 8-frame log (3 keyframes).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # on the device nothing is installed: the checkout is the package

from ssmvpr_common.atomic import atomic_write_text  # noqa: E402  (the standard library only)

KIT = REPO / ".device"
SITE = KIT / "site"
SHARED = REPO.parent / "shared"
DEVICE_PYTHON = "3.12"  # the GPU image's python3 (.library/device/KINDS.md)
CARRY_LIMIT_BYTES = 64 << 20
WEIGHTS_FILE = "vgg16_fp16.pth"

# What the GPU image holds of this project's dependencies (.library/device/KINDS.md) ...
IMAGE_HAS = {"torch", "numpy", "scipy", "scikit-learn", "opencv-python-headless", "matplotlib", "typer", "rich",
             "pyyaml", "threadpoolctl", "onnxruntime"}  # fmt: skip
# ... and what it lacks, by the call that carries it (a test checks that the two cover pyproject's
# dependencies: a log reader's import missing there cost a GPU session a call).
WHEELS = {
    "core": ["pydantic", "pydantic-core", "annotated-types", "typing-inspection", "typing-extensions",
             "pydantic-settings", "python-dotenv", "packaging"],
    "faiss": ["faiss-cpu"],
    "slam": ["gtsam", "kiss-icp", "natsort", "pyquaternion", "mcap", "mcap-ros2-support", "zstandard", "lz4",
             "rosbags", "ruamel.yaml", "apsw", "backports.zstd"],
}  # fmt: skip
# "log": the simulate step's output, left on the machine for the slam step of the next call.
NEEDS = {"stage1": ["core", "faiss"], "backbone": ["core", "weights", "images"], "simulate": ["core", "slam"],
         "odometry": ["core", "slam"], "slam": ["core", "slam", "faiss", "weights", "log"], "threads": ["core", "slam", "faiss", "weights", "log"]}  # fmt: skip
# Each command's limit. A call has 600 s; call 2's limits add up to more (slam's 530 s, then
# threads' 150 s), but slam took 339 s on the H200, and its JSON is written before threads starts,
# so a call cut short by the device loses only threads. On an H200 simulating took 80-92 s, one default bench_slam 52-80 s before the
# pipelined schedule.
TIMEOUT_S = {"stage1_100000": 100, "stage1_1000000": 240, "stage1_2000": 60, "stage1_breakdown": 90, "backbone": 140, "projection": 90,
             "simulate": 200, "bench_slam": 330, "bench_slam_fast": 200, "bench_slam_threads16": 150,
             "odometry_t8_ahead0": 60, "odometry_t8_ahead1": 60, "odometry_t16_ahead0": 60, "odometry_t16_ahead1": 60,
             "odometry_t8_ahead1_kiss_own": 60}  # fmt: skip
KISS_ICP_OWN = ["MAX_POINTS_PER_VOXEL=20", "CONVERGENCE_CRITERION=0.0001"]
"""kiss-icp's own settings where the default preset's differ (frontend.odometry.kiss_icp)."""
PLATFORMS = ["manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_24_x86_64", "manylinux_2_27_x86_64",
             "manylinux_2_28_x86_64", "manylinux_2_31_x86_64", "manylinux_2_34_x86_64", "manylinux_2_35_x86_64"]  # fmt: skip


def log(message: str) -> None:
    print(f"[device_checks] {message}", file=sys.stderr, flush=True)


# ---- here: make the kit ------------------------------------------------------------------------
def _pinned(name: str) -> str:
    """name==the version this checkout is tested with, when installed here (else the newest)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"{name}=={version(name)}"
    except PackageNotFoundError:
        return name


def _fill(name: str, fill) -> None:  # noqa: ANN001 - fill(folder) writes the folder's files
    """Make .device/`name` whole or not at all: filled beside it, then renamed into place (an
    interrupted `prepare` leaves no half folder that `run` would take for the kit)."""
    staged = KIT / f".{name}.partial"
    shutil.rmtree(staged, ignore_errors=True)
    staged.mkdir(parents=True)
    fill(staged)
    shutil.rmtree(KIT / name, ignore_errors=True)
    os.replace(staged, KIT / name)


def _download(group: str, python: str) -> None:
    platforms = [arg for p in PLATFORMS for arg in ("--platform", p)]

    def fill(folder: Path) -> None:
        command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
                   "--python-version", python, "--implementation", "cp", *platforms, "-d", str(folder),
                   *(_pinned(n) for n in WHEELS[group])]  # fmt: skip
        subprocess.run(command, check=True)

    _fill(group, fill)


def _weights(source: Path) -> None:
    """The VGG16 conv weights as float16 (half the bytes; the backbone loads them as float32)."""
    import torch

    from loopclosure.weights import load_state_dict

    half = {k: v.half() for k, v in load_state_dict(source).items()}
    _fill("weights", lambda folder: torch.save(half, folder / WEIGHTS_FILE))


def _images(source: Path, count: int = 16) -> None:
    from loopclosure.backbone_input import list_images

    def fill(folder: Path) -> None:
        for path in list_images(source)[:count]:
            shutil.copy2(path, folder / path.name)

    _fill("images", fill)


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.exists() else 0


def prepare(args: argparse.Namespace) -> dict:
    for group in WHEELS:
        log(f"downloading the {group} wheels for Python {args.python}")
        _download(group, args.python)
    _weights(Path(args.weights))
    _images(Path(args.images))
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    repo_bytes = sum((REPO / f).stat().st_size for f in tracked.decode().split("\0") if f and (REPO / f).is_file())
    calls = {"1": ["core", "slam"], "2": ["faiss", "weights", "images"]}
    out: dict = {"kit": str(KIT), "repo_bytes": repo_bytes, "calls": {}}
    for name, folders in calls.items():
        total = repo_bytes + sum(_size(KIT / f) for f in folders)
        out["calls"][name] = {"carry": [f".device/{f}" for f in folders], "bytes": total,
                              "fits": total < CARRY_LIMIT_BYTES}  # fmt: skip
    out["commands"] = {
        "1": "python3 tools/device_checks.py run simulate --out $OUT",
        "2": "python3 tools/device_checks.py run slam --out $OUT",
    }
    return out


# ---- there: run the steps ------------------------------------------------------------------------
def _install(groups: list[str]) -> None:
    """pip-install the carried wheels of `groups` into .device/site (once per machine)."""
    for group in groups:
        marker = SITE / f".installed-{group}"
        wheels = sorted((KIT / group).glob("*.whl"))  # there: `_missing` checked before
        listed = " ".join(w.name for w in wheels) + "\n"
        # Installed already, unless the carried kit differs from what was (a wheel added since).
        if marker.exists() and (not wheels or marker.read_text() == listed):
            continue
        log(f"installing {len(wheels)} {group} wheels into {SITE}")
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                        "--no-cache-dir", "--upgrade", "--target", str(SITE), *map(str, wheels)], check=True)  # fmt: skip
        atomic_write_text(marker, listed)


def _environment(local: bool) -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if not local:
        env["PYTHONPATH"] = os.pathsep.join([str(SITE), str(REPO)])
    return env


def _step_commands(step: str, args: argparse.Namespace) -> list[tuple[str, list[str], bool]]:
    """(name, command, whether its stdout is a JSON result) in order; each has its own timeout."""
    py, tools, quick, device = sys.executable, REPO / "tools", args.quick, args.device
    weights = args.weights or str(KIT / "weights" / WEIGHTS_FILE)
    images = args.images or str(KIT / "images")
    if step == "stage1":  # a size per command: a slow 1M run keeps the 100k result
        return [(f"stage1_{size}", [py, str(tools / "bench_vpr.py"), "--only-index", "--index-sizes", str(size),
                 "--nprobes", "", "--exact-backend", "torch", "--torch-device", device, "--exact-repeats", "8",
                 "--repeats", "8", "--check-votes", "3", "--append-places", "0"], True)
                for size in ((2000,) if quick else (100_000, 1_000_000))] + [
                ("stage1_breakdown", [py, str(tools / "bench_device_search.py"), "--device", device,
                 *(["--vectors", "20000", "--repeats", "1"] if quick else [])], True)]  # fmt: skip
    if step == "backbone":
        return [("backbone", [py, str(tools / "bench_backbone.py"), "--device", device, "--precisions", "fp32,auto",
                  "--batch-sizes", "1" if quick else "1,8", "--repeats", "2" if quick else "9",
                  "--weights", weights, "--images", images,
                  *(["--quick", "--no-gemm", "--input-size", "112"] if quick else [])], True),
                ("projection", [py, str(tools / "bench_projection.py"), "--device", device, "--precision", "auto",
                  "--weights", weights, "--images", images, *(["--quick"] if quick else [])], True)]  # fmt: skip
    log_path = _log_path(quick)
    if step == "simulate":
        simulate = [py, "-c", "from ssmvpr_slam.cli import app; app()", "simulate", "--out", str(log_path)]
        return [("simulate", [*simulate, *(["--frames", "8"] if quick else [])], False)]
    if step == "slam":
        bench = [py, str(tools / "bench_slam.py"), "--log", str(log_path), "--device", device, "--precision", "auto",
                 "--overlap", "--weights", weights]  # fmt: skip
        # the pipelined schedule and, in the same process, the one-after-another one (--serial);
        # then -c fast with idle threads asleep: the H200 run's odometry child spun 16 cores
        fast = [*bench, "--config", "fast", "--omp-wait-policy", "PASSIVE"]
        return [("bench_slam", [*bench, "--serial"], True), ("bench_slam_fast", fast, True)]
    if step == "odometry":  # the front end's pace: kiss-icp in its process, frames handed over ahead or not

        def odometry(name: str, threads: int, ahead: int, *kiss: str) -> tuple[str, list[str], bool]:
            return (name, ["env", f"SSMVPR_FRONTEND__ODOMETRY__KISS_ICP__MAX_NUM_THREADS={threads}", *kiss, py,
                           str(tools / "bench_odometry.py"), "--frames", "8" if quick else "200", "--own-process",
                           "--ahead", str(ahead)], True)  # fmt: skip

        # and kiss-icp's own settings (the default's until 2026-11-29), against the H200's 55 ms a scan
        own = [f"SSMVPR_FRONTEND__ODOMETRY__KISS_ICP__{key}" for key in KISS_ICP_OWN]
        return [*(odometry(f"odometry_t{threads}_ahead{ahead}", threads, ahead) for threads in (8, 16) for ahead in (0, 1)),
                odometry("odometry_t8_ahead1_kiss_own", 8, 1, *own)]  # fmt: skip
    if step == "threads":  # the default preset with kiss-icp on 16 threads, odometry and loop registration alike
        threads = [f"SSMVPR_{key}__MAX_NUM_THREADS=16" for key in ("FRONTEND__ODOMETRY__KISS_ICP",
                                                                   "BACKEND__REGISTRATION__LIDAR")]  # fmt: skip
        return [("bench_slam_threads16", ["env", *threads, py, str(tools / "bench_slam.py"), "--log", str(log_path),
                 "--device", device, "--precision", "auto", "--overlap", "--weights", weights], True)]  # fmt: skip
    raise AssertionError(step)  # argparse allows only the steps of NEEDS


def _log_path(quick: bool) -> Path:
    return KIT / ("quick.mcap" if quick else "demo.mcap")


def _missing(step: str, args: argparse.Namespace, local: bool) -> list[str]:
    """The kit's folders `step` needs that are neither here nor installed already."""
    out = []
    for need in NEEDS[step]:
        if need == "log":  # made there by the simulate step, not carried (400 MB)
            continue
        if need in WHEELS:
            installed = (SITE / f".installed-{need}").exists() or any((KIT / need).glob("*.whl"))
            if not local and not installed:  # a rehearsal here uses this machine's packages
                out.append(need)
        elif getattr(args, need) is None and not _kit_has(need):
            out.append(need)
    return out


def _kit_has(need: str) -> bool:
    if need == "weights":
        return (KIT / "weights" / WEIGHTS_FILE).is_file()
    return (KIT / need).is_dir() and any((KIT / need).iterdir())


def _execute(command: list[str], env: dict[str, str], timeout: float) -> tuple[int | None, str, str]:
    """(return code or None on timeout, stdout, stderr). The command gets a process group of its
    own, killed whole at the timeout: bench_slam's odometry child holds the pipes too."""
    proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)  # fmt: skip
    try:
        out, err = proc.communicate(timeout=timeout)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = None
    return code, out.decode(errors="replace"), err.decode(errors="replace")


def _verdict(step: str, result: dict) -> str | None:
    """A reason the measurement itself is wrong, though the command succeeded."""
    if step == "stage1":
        for size, entry in result.get("stage1_index", {}).get("sizes", {}).items():
            check = entry.get("exact_equals_numpy", {})
            if check.get("equal") != check.get("queries"):
                return f"{size} places: the exact votes differ from numpy's on {check} queries"
        if result.get("selection_equals_topk") is False:
            return "the chunk selection kept other values than torch.topk"
    if step == "slam" and result.get("same_loops") is False:  # the stages in flight must not change a loop
        return "the pipelined and the serial schedule accepted different loops"
    return None


def run_step(step: str, args: argparse.Namespace, out_dir: Path) -> dict:
    local = args.device == "cpu" and not args.use_kit  # this machine's own packages: nothing to install
    missing = _missing(step, args, local)
    if missing:
        return {"step": step, "ok": False,
                "error": f"carry {' '.join('.device/' + m for m in missing)} (made by `prepare`)"}  # fmt: skip
    if "log" in NEEDS[step] and not _log_path(args.quick).is_file():
        return {"step": step, "ok": False,
                "error": f"no {_log_path(args.quick).name} in {KIT}: run the simulate step first on this machine"}  # fmt: skip
    if not local:
        _install([g for g in NEEDS[step] if g in WHEELS])
    env = _environment(local)
    record: dict = {"step": step, "ok": True, "commands": [], "results": {}}
    for name, command, gives_json in _step_commands(step, args):
        t0 = time.monotonic()
        code, stdout, stderr = _execute(command, env, TIMEOUT_S[name])
        record["commands"].append({"name": name, "returncode": code, "seconds": round(time.monotonic() - t0, 1)})
        with (out_dir / f"{step}.log").open("a") as handle:  # appended as it goes: a log, not a result
            handle.write(stderr)
        if code != 0:
            last = (stderr.strip().splitlines() or ["?"])[-1]
            record.update(
                ok=False, error=f"{name}: timed out after {TIMEOUT_S[name]} s" if code is None else f"{name}: {last}"
            )
            break
        if gives_json:
            try:
                record["results"][name] = json.loads(stdout)
            except ValueError:
                record.update(ok=False, error=f"{name}: its output is not one JSON object: {stdout[-300:]!r}")
                break
            if (problem := _verdict(step, record["results"][name])) is not None:
                record.update(ok=False, error=f"{name}: {problem}")
    return record


def run(args: argparse.Namespace) -> dict:
    out_dir = Path(args.out or os.environ.get("OUT") or KIT / "out")
    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict = {"steps": {}}
    for step in args.steps:
        log(f"step {step}")
        record = run_step(step, args, out_dir)
        atomic_write_text(out_dir / f"{step}.json", json.dumps(record, indent=1) + "\n")
        summary["steps"][step] = {k: record[k] for k in ("ok", "commands", "error") if k in record}
        log(f"step {step}: {'ok' if record['ok'] else record.get('error')}")
    return summary


def main(argv: list[str] | None = None) -> int:
    global KIT, SITE
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("prepare", help="here: wheels, fp16 weights and images into .device/")
    p.add_argument("--python", default=DEVICE_PYTHON, help="the device's Python (wheels are built per version)")
    p.add_argument("--weights", default=str(SHARED / "weights" / "vgg16_imagenet_conv.pth"))
    p.add_argument("--images", default=str(SHARED / "data" / "corridor" / "ref"))
    r = sub.add_parser("run", help="there: run steps, one JSON each under --out")
    r.add_argument("steps", nargs="+", choices=sorted(NEEDS))
    r.add_argument("--out", default=None, help="folder for the JSON and logs (default: $OUT)")
    r.add_argument("--device", choices=("cuda", "cpu"), default="cuda", help="cpu: a rehearsal on this machine")
    r.add_argument("--quick", action="store_true", help="small sizes (a rehearsal)")
    r.add_argument(
        "--use-kit", action="store_true", help="with --device cpu: install and use the kit's wheels as the device does"
    )
    r.add_argument("--weights", default=None, help="default: .device/weights/vgg16_fp16.pth")
    r.add_argument("--images", default=None, help="default: .device/images")
    ap.add_argument("--kit", default=str(KIT), help="the kit's folder (default: .device in the checkout)")
    args = ap.parse_args(argv)
    KIT = Path(args.kit).resolve()
    SITE = KIT / "site"
    result = prepare(args) if args.verb == "prepare" else run(args)
    print(json.dumps(result, indent=1))
    ok = args.verb == "prepare" or all(s["ok"] for s in result["steps"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
