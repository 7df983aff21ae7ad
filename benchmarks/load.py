"""Load: 64 simulated robots (light observations) against one server for 2 minutes.

Targets: no error; memory flat (server RSS end <= start + 50 MiB); every chunk a robot received
was executed from or accounted as superseded; scheduler decision CPU time p99 <= 10 ms (wall
time is printed too: on a 2-core machine shared with 64 robot threads it also counts waiting for
a core). Run: ``.venv/bin/python benchmarks/load.py [ROBOTS] [SECONDS]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))  # the repository: tests.support
from _common import Targets  # noqa: E402

from tests.support.load import run_load  # noqa: E402 - the load generator is the tests' too


def main() -> None:
    robots = int(sys.argv[1]) if len(sys.argv) > 1 else 64
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 120.0
    out = run_load(robots, seconds)
    stats = out["stats"]
    received = sum(s["chunks_received"] for s in stats)
    accounted = sum(sum(s["first_executed_index"].values()) for s in stats)
    unused = sum(s["first_executed_index"].get("unused", 0) for s in stats)
    ticks = sum(s["ticks"] for s in stats)
    starved = sum(s["starved_steps"] for s in stats)
    print(f"{robots} robots x {seconds:g} s at 10 Hz: {out['batches']} batches, sizes {out['batch_sizes']}")
    print(f"  chunks received {received}, accounted {accounted} (superseded/unused {unused}); starvation {100 * starved / max(1, ticks):.1f}%")
    print(f"  server RSS start {out['rss_start_mb']:.0f} MiB, end {out['rss_end_mb']:.0f} MiB, peak {out['rss_peak_mb']:.0f} MiB")
    print(f"  decision p99: cpu {out['decision_cpu_p99_ms']:.2f} ms, wall {out['decision_p99_ms']:.2f} ms")
    t = Targets()
    t.check("errors", len(out["errors"]), 0, "")
    t.check("unaccounted chunks", abs(received - accounted), 0, "")
    t.check("RSS growth", out["rss_end_mb"] - out["rss_start_mb"], 50, "MiB")
    t.check("decision cpu p99", out["decision_cpu_p99_ms"], 10.0, "ms")
    t.finish()


if __name__ == "__main__":
    main()
