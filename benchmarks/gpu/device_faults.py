"""Device faults on a real GPU: CUDA's own out-of-memory and a real sticky CUDA error, served.

The CPU tests (``tests/serving/test_device_faults.py``) inject torch's exception types; this
checks that what a GPU really raises is taken the same way by the serving loop:

1. **Out of memory.** An engine double (the tests' echo engine) that, per batch, allocates and
   writes ``--gib_per_row`` GiB a robot on the GPU, with a ballast holding all but
   ``--free_gib`` of the GPU's free memory: a batch of 3 or more cannot fit, one of 1 or 2 can.
   Four robots at cap 4: the loop must lower the cap to 2 on CUDA's own ``OutOfMemoryError`` and
   keep serving every robot without an error notice.
2. **A lost device.** An engine double that, from its third batch on, indexes a GPU tensor out of
   bounds (``device-side assert triggered``: a sticky error, the CUDA context is unusable after
   it). The loop must stop with "the device is lost" in its error within seconds; the server's
   main then exits non-zero (``lerobot_armory.entrypoints.server.serve``, tested on the CPU).

Writes ``$OUT/device_faults.json`` (or ``--out``) and exits 1 on a miss.

    python3 benchmarks/gpu/device_faults.py --out=$OUT/device_faults.json
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lerobot_armory.robot.client import ArmoryClient, RobotIdentity  # noqa: E402
from lerobot_armory.schedulers import EarliestDeadlineConfig  # noqa: E402
from tests.support.echo import FEATURES, EchoEngine, echo_robots, echo_server  # noqa: E402

GIB = 1 << 30


class CudaMemoryPerRow(EchoEngine):
    """The echo engine, writing ``gib_per_row`` GiB of GPU memory per robot in each batch."""

    def __init__(self, gib_per_row: float) -> None:
        super().__init__(0.01)
        self.bytes_per_row = int(gib_per_row * GIB)
        self.sizes: list[int] = []
        self.errors: list[str] = []

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        if not self.sizes:
            time.sleep(0.3)  # a slow first batch: every robot queues, so the next batch holds them all
        self.sizes.append(len(observations))
        try:
            block = torch.empty(self.bytes_per_row * len(observations), dtype=torch.uint8, device="cuda")
            block.fill_(1)
            torch.cuda.synchronize()
            del block
        except Exception as exc:
            self.errors.append(f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}")
            raise
        return super().infer(observations, tasks, noise_seeds)


class CudaAssertFrom(EchoEngine):
    """The echo engine, indexing a GPU tensor out of bounds from batch ``first`` on."""

    def __init__(self, first: int) -> None:
        super().__init__(0.01)
        self.first, self.batches = first, 0
        self.raised: str = ""
        self.raised_at: float | None = None

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        self.batches += 1
        if self.batches >= self.first:
            x = torch.zeros(4, device="cuda")
            try:
                x[torch.tensor([1 << 20], device="cuda")].sum().item()  # device-side assert
                torch.cuda.synchronize()
            except Exception as exc:
                self.raised = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
                self.raised_at = time.monotonic()
                raise
        return super().infer(observations, tasks, noise_seeds)


def out_of_memory(args: argparse.Namespace) -> dict[str, Any]:
    free, total = torch.cuda.mem_get_info()
    ballast = torch.empty(max(0, free - int(args.free_gib * GIB)), dtype=torch.uint8, device="cuda")
    engine = CudaMemoryPerRow(args.gib_per_row)
    server = echo_server(engine, cap=4, scheduler=EarliestDeadlineConfig())
    try:
        clients = echo_robots(server, 4, args.seconds)
        stats = server.loop.stats
        notices = [n for c in clients for n in c.notices if "inference failed" in n]
        record = {
            "gpu": torch.cuda.get_device_name(),
            "total_gib": round(total / GIB, 1),
            "free_left_gib": args.free_gib,
            "gib_per_row": args.gib_per_row,
            "batch_sizes_tried": dict(sorted((b, engine.sizes.count(b)) for b in set(engine.sizes))),
            "cuda_errors": sorted(set(engine.errors)),
            "oom_batches": stats.oom_batches,
            "failed_batches": stats.failed_batches,
            "batch_cap_after": stats.batch_cap,
            "chunks_per_robot": [c.chunks_received for c in clients],
            "error_notices": len(notices),
            "loop_alive": server.loop.alive,
        }
    finally:
        for c in clients:
            c.close()
        server.stop(0.5)
        del ballast
        torch.cuda.empty_cache()
    tried_big = any(b >= 3 for b in engine.sizes)
    record["passed"] = bool(
        tried_big and stats.oom_batches >= 1 and stats.batch_cap == 2 and stats.failed_batches == 0
        and not notices and server.loop.error is None and min(record["chunks_per_robot"]) > 10
    )  # fmt: skip
    return record


def device_lost(args: argparse.Namespace) -> dict[str, Any]:
    engine = CudaAssertFrom(first=3)
    server = echo_server(engine, cap=2, scheduler=EarliestDeadlineConfig())
    state = np.zeros(4, np.float32)
    client = ArmoryClient(
        server.address, RobotIdentity("r0", 20.0, 2, 10), FEATURES,
        observe=lambda: {"observation.state": state}, act=lambda a: None,
    )  # fmt: skip
    runner = threading.Thread(target=client.run, args=(args.seconds,), daemon=True)
    runner.start()
    deadline = time.monotonic() + 30
    while server.loop.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    stopped_at = time.monotonic()
    while server.loop.alive and time.monotonic() < deadline:
        time.sleep(0.01)
    error = str(server.loop.error or "")
    record = {
        "cuda_error": engine.raised,
        "loop_error": error[:300],
        "seconds_from_error_to_loop_error": None if engine.raised_at is None else round(stopped_at - engine.raised_at, 3),
        "loop_alive_after": server.loop.alive,
        "failed_batches": server.loop.stats.failed_batches,
    }
    client.close()
    server.stop(0.5)
    record["passed"] = bool(engine.raised and "the device is lost" in error and not server.loop.alive
                            and record["seconds_from_error_to_loop_error"] is not None
                            and record["seconds_from_error_to_loop_error"] < 5)  # fmt: skip
    return record


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--free_gib", type=float, default=2.5, help="GPU memory left free beside the ballast")
    ap.add_argument("--gib_per_row", type=float, default=1.0, help="GPU memory one robot's row writes per batch")
    ap.add_argument("--seconds", type=float, default=6.0, help="robots run this long in each part")
    ap.add_argument("--out", default="device_faults.json")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("device_faults: no CUDA device here; this check runs on a GPU machine only", file=sys.stderr)
        return 2
    results = {"out_of_memory": out_of_memory(args)}
    print(json.dumps(results["out_of_memory"], indent=1), flush=True)
    results["device_lost"] = device_lost(args)  # last: the CUDA context is unusable after it
    print(json.dumps(results["device_lost"], indent=1), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    misses = [name for name, r in results.items() if not r["passed"]]
    print(f"wrote {args.out}; " + (f"MISS: {', '.join(misses)}" if misses else "both faults taken as designed"))
    return 1 if misses else 0


if __name__ == "__main__":
    sys.exit(main())
