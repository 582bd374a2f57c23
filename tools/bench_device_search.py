"""Where a torch exact stage-I query spends its time: the product, the selection, the proposal.

Prints ONE JSON object to stdout (progress goes to stderr).

Usage:
  python tools/bench_device_search.py [--vectors 16000000] [--device auto|cpu|cuda] [--repeats 10]

Random unit vectors of 100 values made on the device itself (so 1M places' 16M vectors cost no
host generation or upload), one query of 16 vectors near a stored one, k = 50 and an exclusion
window of the last 100 places, as a SLAM query has. Medians of --repeats after a warm-up, the
device synchronised around each:
  product_ms          the 16 query vectors against all: float32, and from the float16 copy
                      (float16 operands, float32 sums: `device_search._float32_product`)
  selection_ms        a row's top k+: torch.topk, and the chunk-maximum selection
                      (`device_search.top_k_columns`) at chunks of 1,024 / 4,096 / 16,384
  proposal_ms         `TorchExactSearch.propose` whole, per copy (float32, float16) and selection
                      (torch.topk forced, or the device's default), with its candidates per row
tools/bench_vpr.py --only-index times the same search end to end on street-like codes, with
the exact re-scoring and the votes (and checks them against numpy); this one says which part
to work on.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a bare checkout (the GPU machine)

from loopclosure import device_search  # noqa: E402

DIM, K, PER_PLACE, EXCLUDED_PLACES = 100, 50, 16, 100


def log(message: str) -> None:
    print(f"[bench_device_search] {message}", file=sys.stderr, flush=True)


def median_ms(fn: Callable[[], object], repeats: int, sync: Callable[[], None]) -> float:
    fn()
    sync()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        samples.append((time.perf_counter() - t0) * 1e3)
    return round(float(np.median(samples)), 3)


@contextlib.contextmanager
def forced_selection(select: bool | None) -> Iterator[None]:
    """`TorchExactSearch` with the selection forced on or off (None: the device's default)."""
    original = device_search.top_k_columns
    device_search.top_k_columns = lambda sims, kk, chunk=0: original(sims, kk, chunk, select)
    try:
        yield
    finally:
        device_search.top_k_columns = original


def selections(sims, kk: int, repeats: int, sync: Callable[[], None]) -> tuple[dict, bool]:  # noqa: ANN001 - a tensor
    """The selections' times on one query's similarities, and whether the chunked one keeps
    torch.topk's values (the similarities are freed on return)."""
    import torch

    times = {"torch_topk": median_ms(lambda: torch.topk(sims, kk, dim=1, sorted=False), repeats, sync)}
    for chunk in (1024, 4096, 16384):
        times[f"chunks_{chunk}"] = median_ms(
            lambda chunk=chunk: device_search.top_k_columns(sims, kk, chunk, select=True), repeats, sync
        )
    expected = torch.topk(sims, kk, dim=1).values
    chosen = torch.sort(device_search.top_k_columns(sims, kk, select=True)[0], dim=1, descending=True).values
    return times, bool(torch.equal(expected, chosen))


def run(vectors: int, device: str, repeats: int) -> dict:
    import torch

    device = device_search.resolve_device(device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    out: dict = {"tool": "bench_device_search", "device": torch.cuda.get_device_name() if device == "cuda" else "cpu",
                 "torch": torch.__version__, "vectors": vectors, "dim": DIM, "k": K, "repeats": repeats}  # fmt: skip
    log(f"{vectors} random unit vectors on {device}")
    generator = torch.Generator(device=device).manual_seed(0)
    rows = torch.randn((vectors, DIM), generator=generator, device=device)
    rows /= rows.norm(dim=1, keepdim=True)
    query = rows[:PER_PLACE] + 0.5 * torch.randn((PER_PLACE, DIM), generator=generator, device=device)
    query /= query.norm(dim=1, keepdim=True)
    kk = K + max(8, K // 4)

    width = device_search.TorchExactSearch(DIM, device, storage="float16")._width  # padded for tensor cores
    rows16 = torch.zeros((vectors, width), dtype=torch.float16, device=device)
    rows16[:, :DIM] = rows.half()
    query16 = torch.zeros((PER_PLACE, width), dtype=torch.float16, device=device)
    query16[:, :DIM] = query.half()
    with device_search.full_float32(), torch.inference_mode():
        log("products")
        out["product_ms"] = {
            "float32": median_ms(lambda: query @ rows.T, repeats, sync),
            "float16_copy": median_ms(lambda: device_search._float32_product(query16, rows16), repeats, sync),
        }
        log("selections")
        out["selection_ms"], out["selection_equals_topk"] = selections(query @ rows.T, kk, repeats, sync)

    excluded = np.arange(vectors - EXCLUDED_PLACES * PER_PLACE, vectors)
    q = query.cpu().numpy()
    proposal: dict = {}
    for storage, held in (("float32", rows), ("float16", rows16)):
        search = device_search.TorchExactSearch(DIM, device, storage=storage)
        search._rows, search._count = held, vectors  # already on the device, as write() leaves them
        for name, select in (("torch_topk", False), ("default", None)):
            log(f"proposal, {storage} copy, selection {name}")
            with forced_selection(select):
                ms = median_ms(lambda: search.propose(q, K, vectors, excluded, 1.0), repeats, sync)
                candidates = search.propose(q, K, vectors, excluded, 1.0)
            proposal[f"{storage}_{name}"] = {"ms": ms, "candidates_per_row": round(float(np.mean([len(c) for c in candidates])), 1)}  # fmt: skip
        search._rows = None
    out["proposal_ms"] = proposal
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vectors", type=int, default=16_000_000, help="stage-I vectors (16 a place: 16M = 1M places)")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args(argv)
    if args.vectors < (EXCLUDED_PLACES + 1) * PER_PLACE:
        ap.error(f"--vectors: at least {(EXCLUDED_PLACES + 1) * PER_PLACE} (the exclusion window and a place)")
    result = run(args.vectors, args.device, args.repeats)
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
