"""Lookahead decision time: p99 <= 1 ms at N=10, b=5 and <= 10 ms at N=100, b=8.

The decisions are the ones a simulated fleet actually asks for (libero preset, half-fast mix,
l40s-pi05 profile, extrapolated past b=5), so the states are realistic, overloaded ones.
Run: ``.venv/bin/python benchmarks/decision_time.py``. Exits 1 on a miss.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets, sim  # noqa: E402

CASES = [(10, 5, 120.0, 1.0), (100, 8, 60.0, 10.0)]  # (robots, batch cap, simulated s, p99 limit ms)


def main() -> None:
    targets = Targets()
    for robots, cap, duration, limit in CASES:
        for scheduler in ("rr", "edf", "lookahead"):
            r = sim(scheduler, preset="libero", mix="half-fast", robots=robots, max_batch_size=cap, duration_s=duration)
            decisions = sum(r["batch_sizes"].values())
            print(
                f"    N={robots:<3d} b={cap} {scheduler:<9} decisions={decisions:<5d} "
                f"p50={r['decision_ms_p50']:.3f} ms p99={r['decision_ms_p99']:.3f} ms"
            )
            if scheduler == "lookahead":
                targets.check(f"LA p99 N={robots} b={cap}", r["decision_ms_p99"], limit, "ms")
    targets.finish()


if __name__ == "__main__":
    main()
