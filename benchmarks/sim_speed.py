"""Simulator speed: 10 robots x 300 s for RR, EDF and LA must each take < 3 s wall (>= 100x real time).

Run: ``.venv/bin/python benchmarks/sim_speed.py``. Prints the figures; exits 1 on a miss.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets, sim  # noqa: E402

LIMIT_S = 3.0


def main() -> None:
    targets = Targets()
    print("simulating 10 robots x 300 s (libero preset, l40s-pi05 profile):")
    for mix in ("one-fast", "half-fast"):
        for scheduler in ("rr", "edf", "lookahead"):
            r = sim(scheduler, preset="libero", mix=mix, robots=10, duration_s=300.0)
            speed = r["duration_s"] / r["wall_s"]
            print(f"    {mix:<9} {scheduler:<9} {r['wall_s']:.2f} s wall = {speed:.0f}x real time")
            targets.check(f"{mix} {scheduler} wall", r["wall_s"], LIMIT_S, "s")
    targets.finish()


if __name__ == "__main__":
    main()
