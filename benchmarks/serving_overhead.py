"""Serving overhead on loopback: N=10 robots, two 224x224 RGB images + state at 30 Hz.

Per delivered chunk, on one machine (robots and server share CLOCK_MONOTONIC):

    overhead = (chunk arrival at robot - observation capture) - model time - device-busy wait

where model time is the batch's inference (stack + pre-process + forward + post-process) and the
device-busy wait is the time the observation sat at the server while the *previous* batch was
still running (queueing under load, not overhead). What is left is the serving stack: robot-side
encoding, gRPC both ways, decoding and validation, the scheduler's decision and the hand-off.

Targets: p50 overhead <= 3 ms, and no observation backlog: the uplink delay (capture -> stored at
the server) over the last third of the run stays within 2x (+1 ms) of the first third, and the
robots' send queues stay short.

Run: ``.venv/bin/python benchmarks/serving_overhead.py``. Exits 1 on a miss.
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

ROBOTS = 10
FPS = 30.0
DURATION_S = 20.0
CAP = 3
TARGET_P50_MS = 3.0


def robots_process(address: str, n: int, features: dict, duration: float, out) -> None:
    """n robots pushing observations at FPS; returns per-chunk (robot, i_start, capture, arrival)."""
    import threading

    import numpy as np

    from lerobot_armory.robot.connection import Connection

    rng = np.random.default_rng(0)
    frames = [
        {
            name: (rng.integers(0, 256, shape, dtype=np.uint8) if dtype == "uint8" else rng.standard_normal(shape).astype(dtype))
            for name, (dtype, shape) in features.items()
        }
        for _ in range(4)
    ]
    records, max_queue = [], [0] * n
    lock = threading.Lock()
    conns = []
    for k in range(n):
        c = Connection(address)
        c.register(f"robot{k:02d}", features, fps=FPS, h_min=1, h_max=10)

        def on_chunk(chunk, k=k):
            with lock:
                records.append((f"robot{k:02d}", chunk.i_start, chunk.obs_capture_time, chunk.arrival_time))

        c.open_stream(on_chunk)
        conns.append(c)

    def run(k: int, c: Connection) -> None:
        period, start = 1.0 / FPS, time.monotonic() + 0.01 * k
        i = 0
        while True:
            t_next = start + i * period
            now = time.monotonic()
            if now - start > duration:
                return
            if t_next > now:
                time.sleep(t_next - now)
            t = time.monotonic()
            c.send_observation(i, frames[i % 4], capture_time=t)
            max_queue[k] = max(max_queue[k], c._outgoing.qsize())
            i += 1

    threads = [threading.Thread(target=run, args=(k, c)) for k, c in enumerate(conns)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    time.sleep(1.0)
    for c in conns:
        c.close()
    out.put((records, max_queue))


def main() -> None:
    import torch

    from lerobot_armory.schedulers import EarliestDeadlineConfig
    from lerobot_armory.entrypoints.server import ArmoryServer, tune_process
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions
    from lerobot_armory.entrypoints.grpc.service import PolicyInfo

    tune_process()
    tmp = tempfile.mkdtemp()
    make_demo_policy(DemoPolicyConfig(output=f"{tmp}/policy", cameras="front,wrist", image_size=224, state_dim=6))
    engine = PolicyEngine(PolicyOptions(f"{tmp}/policy", "cpu"))
    features = {f.name: (f.dtype, f.shape) for f in engine.wire_features}
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    print(f"policy: demo ACT, features {features}, torch threads {torch.get_num_threads()}")
    profile = engine.profile(CAP, warmup=1, reps=3, log_progress=False)
    print(profile.describe(CAP))
    server = ArmoryServer(engine, info, profile, EarliestDeadlineConfig(), CAP, port=0).start()
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=robots_process, args=(server.address, ROBOTS, features, DURATION_S, q))
    proc.start()
    records, max_queue = q.get(timeout=DURATION_S + 120)
    proc.join()
    server.stop(grace_s=1.0)

    batches = sorted(server.batch_log, key=lambda b: b.t_start)
    where = {}
    for k, b in enumerate(batches):
        prev_end = batches[k - 1].t_end if k else float("-inf")
        for rid, i, recv in zip(b.robots, b.i_starts, b.obs_recv, strict=True):
            where[(rid, i)] = (b, recv, prev_end)
    overhead, uplink, rows = [], [], []
    for rid, i, cap_t, arrival in records:
        if cap_t is None or (rid, i) not in where:
            continue
        b, recv, prev_end = where[(rid, i)]
        model = b.t_end - b.t_start
        busy_wait = max(0.0, prev_end - recv)
        overhead.append((arrival - cap_t - model - busy_wait) * 1000)
        uplink.append((cap_t, (recv - cap_t) * 1000))
        rows.append((recv - cap_t, b.t_start - max(recv, prev_end), arrival - b.t_end))
    assert overhead, "no chunk was delivered"
    uplink.sort()
    third = max(1, len(uplink) // 3)
    first = statistics.median(u for _, u in uplink[:third])
    last = statistics.median(u for _, u in uplink[-third:])
    ov = sorted(overhead)
    p = lambda xs, q: xs[min(len(xs) - 1, int(q * len(xs)))]  # noqa: E731
    comp = [sorted(1000 * r[j] for r in rows) for j in range(3)]
    sizes = dict(server.loop.stats.batch_sizes)
    print(f"{len(overhead)} chunks to {ROBOTS} robots in {DURATION_S:.0f} s, batch sizes {sizes}")
    print(f"  overhead p50 {p(ov, 0.5):.2f} ms  p90 {p(ov, 0.9):.2f} ms  p99 {p(ov, 0.99):.2f} ms")
    print(
        f"  components p50: uplink+decode {p(comp[0], 0.5):.2f} ms, dispatch gap {p(comp[1], 0.5):.2f} ms, "
        f"downlink {p(comp[2], 0.5):.2f} ms"
    )
    print(f"  uplink p50 first third {first:.2f} ms, last third {last:.2f} ms; max robot send queue {max(max_queue)}")
    targets = Targets()
    targets.check("overhead p50", p(ov, 0.5), TARGET_P50_MS, "ms")
    targets.check("uplink growth (last third p50)", last, 2 * first + 1.0, "ms")
    targets.check("robot send queue", max(max_queue), 30, "msgs")
    targets.finish()


if __name__ == "__main__":
    main()
