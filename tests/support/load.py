"""Load: many light robots (a 4-float state, no camera) against one server with the echo engine.

The echo engine (``tests/support/echo.py``) is the tests' double: no model, each chunk echoes its
robot's first state value. :func:`run_load` starts an in-process server with it and a *separate* process of
robots (``python tests/support/load.py ADDRESS ROBOTS SECONDS FPS OUT.json``), so that the robots'
Python threads do not share the server's interpreter: the server is measured, not the load
generator. Each robot runs the real client loop. Used by the load test and ``benchmarks/load.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, when run as a script
from tests.support.echo import FEATURES, echo_server  # noqa: E402


def rss_mb() -> float:
    """This process's resident memory, MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def run_load(robots: int, seconds: float, fps: float = 10.0) -> dict[str, Any]:
    """``robots`` light robots against one Lookahead server (cap 8); returns the figures."""
    server = echo_server(cap=8, max_robots=robots + 8)
    out_path = os.path.join(tempfile.mkdtemp(), "load.json")
    rss_start = rss_mb()
    gen = subprocess.Popen(
        [sys.executable, os.path.abspath(__file__), server.address, str(robots), str(seconds), str(fps), out_path],
        env={**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])},
    )
    samples = []
    while gen.poll() is None:
        samples.append(rss_mb())
        time.sleep(0.5)
    rss_end = rss_mb()
    if gen.returncode != 0:
        server.stop(0.5)
        raise RuntimeError(f"load generator failed with exit code {gen.returncode}")
    with open(out_path) as f:
        data = json.load(f)
    stats = server.loop.stats
    wall = sorted(stats.decision_ms)
    cpu = sorted(stats.decision_cpu_ms)
    server.stop(0.5)

    def p99(xs: list[float]) -> float:
        return xs[int(0.99 * (len(xs) - 1))] if xs else 0.0

    return {
        "errors": data["errors"],
        "stats": data["stats"],
        "rss_start_mb": rss_start,
        "rss_end_mb": rss_end,
        "rss_peak_mb": max(samples, default=rss_end),
        "decision_p99_ms": p99(wall),
        "decision_cpu_p99_ms": p99(cpu),
        "batches": stats.batches,
        "batch_sizes": dict(stats.batch_sizes),
    }


def generate(address: str, robots: int, seconds: float, fps: float, out: str) -> None:
    clients = []
    for k in range(robots):
        state = np.array([float(k), 0, 0, 0], np.float32)
        clients.append(
            ArmoryClient(
                address, RobotIdentity(f"load{k:03d}", fps=fps, h_min=2, h_max=8), FEATURES,
                observe=lambda s=state: {"observation.state": s}, act=lambda a: None, backoff=Backoff(0.2, 1.0, 20.0),
            )  # fmt: skip
        )
    for c in clients:
        c.connect()
    errors: list[str] = []

    def run(c: ArmoryClient) -> None:
        try:
            c.run(seconds)
        except Exception as exc:  # reported in the output
            errors.append(f"{c.identity.robot_id}: {exc}")

    threads = [threading.Thread(target=run, args=(c,)) for c in clients]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for c in clients:
        c.close()  # retires still-buffered chunks as unused, so every chunk is accounted for
    with open(out, "w") as f:
        json.dump({"errors": errors, "stats": [c.stats() for c in clients]}, f)


if __name__ == "__main__":
    generate(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), sys.argv[5])
