"""A live policy swap under a running fleet: swap time, robots' starvation, peak memory.

    python benchmarks/swap.py [--robots=6] [--window_s=8] [--out=docs/results/swap/run.json]
    # on a GPU, two checkpoints of armory_sim's features (benchmarks/gpu/run.sh swap):
    python benchmarks/swap.py --old=/tmp/pi05-sim --new=/tmp/pi05-sim-b --device=cuda --max_batch_size=8 \
        --image_size=64 --robots=8 --out=$OUT/swap_gpu.json

The real server (build_server, EDF, b = ``--max_batch_size``; by default the tiny ACT on the CPU,
two seeds built here) serves ``--robots`` armory_sim robots running the real client loop at
20 fps. Four windows of ``--window_s`` each:

    A  no swap            (baseline)
    B  swap to another checkpoint at the window's start (beside the old one)
    C  no swap            (baseline)
    D  swap back with --drain=true at the window's start (old released first; service pauses)

Starvation of a window is the fleet's starved ticks over all ticks in it (robots' own counters).
Exits 1 if B's starvation exceeds the mean of A and C by more than 2 pp (D is reported, not
gated: a drain pauses service by design). RSS is sampled at 50 Hz (VmRSS of this process, which
holds the server, the robots and both checkpoints during B); on a CUDA device each window also
records the peak GPU memory PyTorch allocated (both checkpoints during B).
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import draccus  # noqa: E402
import torch  # noqa: E402

from lerobot_armory.engine.options import PolicyOptions  # noqa: E402
from lerobot_armory.entrypoints.admin import AdminConfig, SwapTarget, call  # noqa: E402
from lerobot_armory.entrypoints.server import build_server  # noqa: E402
from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy  # noqa: E402
from lerobot_armory.schedulers import EarliestDeadlineConfig  # noqa: E402
from lerobot_armory.serving.config import ServerConfig  # noqa: E402
from tests.support.cluster import sim_robot  # noqa: E402 - the tests' armory_sim robot on a thread

TINY = dict(chunk_size=10, state_dim=2, cameras="front", image_size=32, dim_model=32, n_encoder_layers=1)
OPERATOR = "bench-operator-token-0123456789"
TOLERANCE_PP = 2.0


@dataclass
class Options:
    robots: int = 6
    window_s: float = 8.0
    out: str | None = None
    old: str = ""  # checkpoint served first ("": a tiny ACT built here)
    new: str = ""  # checkpoint swapped to ("": another tiny ACT built here)
    device: str = "cpu"
    max_batch_size: int = 3
    image_size: int = 32  # the robots' camera: the checkpoints' image feature


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class RssSampler:
    def __init__(self) -> None:
        self.peak = 0.0
        self._stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self.peak = max(self.peak, rss_mib())

    def window(self) -> float:
        peak, self.peak = self.peak, rss_mib()
        return max(peak, self.peak)


def counters(robots) -> tuple[int, int]:
    return sum(r.client.starved for r in robots), sum(r.client.executed for r in robots)


def main() -> None:
    opts = draccus.parse(Options)
    tmp = Path(tempfile.mkdtemp(prefix="armory-swap-"))
    old, new = Path(opts.old or tmp / "act-seed0"), Path(opts.new or tmp / "act-seed1")
    if not opts.old:
        make_demo_policy(DemoPolicyConfig(output=str(old), seed=0, **{**TINY, "image_size": opts.image_size}))
    if not opts.new:
        make_demo_policy(DemoPolicyConfig(output=str(new), seed=1, **{**TINY, "image_size": opts.image_size}))
    gpu = opts.device.startswith("cuda")
    (tmp / "operator.txt").write_text(OPERATOR + "\n")
    cfg = ServerConfig(
        policy=PolicyOptions(str(old), opts.device), scheduler=EarliestDeadlineConfig(), max_batch_size=opts.max_batch_size, port=0,
        status_interval_s=0.0, log_level="warning", operator_token_file=str(tmp / "operator.txt"),
    )  # fmt: skip
    rss = RssSampler()
    rss_before_server = rss_mib()
    server, _ = build_server(cfg)
    robots = [sim_robot(server.address, f"robot{k}", fast=k % 2 == 0, seed=k, image_size=opts.image_size) for k in range(opts.robots)]
    total = 4 * opts.window_s + 3.0
    for r in robots:
        r.start(total)
    time.sleep(3.0)  # registration, clock sync, first chunks
    rss.window()
    windows: dict[str, dict] = {}
    swaps: dict[str, dict] = {}

    def admin(path: Path, drain: bool, label: str) -> None:
        t0 = time.monotonic()
        code, line = call("swap", AdminConfig(address=server.address, operator_token_file=str(tmp / "operator.txt"),
                                              policy=SwapTarget(str(path)), drain=drain))  # fmt: skip
        swaps[label] = {"exit": code, "line": line, "wall_s": time.monotonic() - t0}

    for label, swap in (("A", None), ("B", (new, False)), ("C", None), ("D", (old, True))):
        s0, e0 = counters(robots)
        if gpu:
            torch.cuda.reset_peak_memory_stats()
        end = time.monotonic() + opts.window_s
        worker = None
        if swap is not None:
            worker = threading.Thread(target=admin, args=(*swap, label))
            worker.start()
        time.sleep(max(0.0, end - time.monotonic()))
        if worker is not None:
            worker.join()
        s1, e1 = counters(robots)
        ticks = (s1 - s0) + (e1 - e0)
        windows[label] = {"starvation_pct": 100.0 * (s1 - s0) / max(1, ticks), "ticks": ticks, "peak_rss_mib": rss.window()}
        if gpu:
            windows[label]["peak_gpu_gib"] = torch.cuda.max_memory_allocated() / 2**30
    for r in robots:
        r.join()
    server.stop(grace_s=0.5)
    base = statistics.mean([windows["A"]["starvation_pct"], windows["C"]["starvation_pct"]])
    excess = windows["B"]["starvation_pct"] - base
    result = {
        "robots": opts.robots, "window_s": opts.window_s, "windows": windows, "swaps": swaps,
        "old": str(old), "new": str(new), "device": opts.device, "max_batch_size": opts.max_batch_size,
        "baseline_starvation_pct": base, "swap_excess_pp": excess,
        "drain_excess_pp": windows["D"]["starvation_pct"] - windows["C"]["starvation_pct"],
        "rss_before_server_mib": rss_before_server,
    }  # fmt: skip
    served = "tiny ACT" if not (opts.old or opts.new) else f"{old.name} -> {new.name}"
    print(f"{opts.robots} armory_sim robots at 20 fps, {served} on {opts.device}, EDF b={opts.max_batch_size}, windows of {opts.window_s:g} s")
    for label, w in windows.items():
        what = {"A": "no swap", "B": "swap beside", "C": "no swap", "D": "swap with drain"}[label]
        gpu_peak = f"  peak GPU {w['peak_gpu_gib']:.2f} GiB" if gpu else ""
        print(f"  {label} {what:<16} starvation {w['starvation_pct']:5.2f} %  ({w['ticks']} ticks)  peak RSS {w['peak_rss_mib']:.0f} MiB{gpu_peak}")
    for label, s in swaps.items():
        print(f"  swap {label}: exit {s['exit']}, {s['wall_s']:.2f} s wall: {s['line']}")
    print(f"  swap beside: {excess:+.2f} pp over the no-swap windows (tolerance {TOLERANCE_PP:g} pp); "
          f"drain: {result['drain_excess_pp']:+.2f} pp over C")  # fmt: skip
    if opts.out:
        Path(opts.out).parent.mkdir(parents=True, exist_ok=True)
        Path(opts.out).write_text(json.dumps(result, indent=2) + "\n")
    failed = any(s["exit"] != 0 for s in swaps.values()) or excess > TOLERANCE_PP
    print("FAIL" if failed else "PASS")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
