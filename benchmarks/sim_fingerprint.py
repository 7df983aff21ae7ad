"""A fingerprint of the simulator's results: proof that a refactor changed no decision.

Runs the ``demo`` sweep (RR, EDF, Lookahead w = 1/3/5 over fleet sizes, network jitter and batch
caps), Rollout on two fleets and the mixed-policy fleet file (two policies sharing one device
through the arbiter), each seed in this process, drops the wall-clock fields (run time, decision
time) and prints the SHA-256 of what is left. Two commits that print the same hash took the same
decision at every simulated step of every run.

    python benchmarks/sim_fingerprint.py                # prints the hash
    python benchmarks/sim_fingerprint.py --expect=HASH  # exits 1 when it differs
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

from lerobot_armory.schedulers.rollout import RolloutConfig
from lerobot_armory.sim.run import SimConfig, simulate, simulate_fleet_file
from lerobot_armory.sim.sweep import SweepConfig, _run_job, plan

ROOT = Path(__file__).resolve().parent.parent
# Keys whose values are wall-clock measurements, not simulated outcomes.
WALL_KEYS = {"wall_s", "decision_ms_p50", "decision_ms_p99", "decision_ms"}


def _strip(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items() if k not in WALL_KEYS and not k.startswith("decision_")}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def records() -> list[dict[str, Any]]:
    """Every run's record, in a fixed order."""
    out = [_run_job(job) for job in plan(SweepConfig(profile="demo"))]
    for mix, robots in (("half-fast", 8), ("one-fast", 12)):
        cfg = SimConfig(preset="libero", mix=mix, robots=robots, scheduler=RolloutConfig(), duration_s=30.0).resolved()
        out += [simulate(cfg, seed) for seed in (0, 1)]
    fleet = SimConfig(fleet=str(ROOT / "examples/fleets/libero-mixed-policies-20.yaml"), duration_s=30.0).resolved()
    out += [simulate_fleet_file(fleet, seed) for seed in (0, 1)]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--expect", help="the hash a reference commit printed: exit 1 when this one differs")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    runs = _strip(records())
    digest = hashlib.sha256(json.dumps(runs, sort_keys=True).encode()).hexdigest()
    print(f"{len(runs)} simulated runs in {time.perf_counter() - start:.1f} s; fingerprint {digest}")
    if args.expect and args.expect != digest:
        print(f"MISS: expected {args.expect}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
