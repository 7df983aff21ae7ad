"""``lerobot-armory-sim``: simulate a fleet under one scheduler and print per-tier starvation.

Example::

    lerobot-armory-sim --preset=libero --mix=one-fast --robots=10 \\
        --scheduler.type=lookahead --fast_weight=3 --seeds=3 --output=results.json

or a fleet file, whose robots may be served by several policies sharing the device::

    lerobot-armory-sim --fleet=examples/fleets/libero-mixed-policies-20.yaml --seeds=3
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.sim.run import SimConfig, fleet_table, simulate, simulate_fleet_file, table


def run(cfg: SimConfig) -> list[dict]:
    """Run every seed of ``cfg`` and print the table; returns the run records."""
    cfg = cfg.resolved()
    if cfg.fleet:
        return _run_fleet(cfg)
    profile = load_profile(cfg.latency_profile)
    assert cfg.max_batch_size is not None
    if profile.is_extrapolated(cfg.max_batch_size):
        print(
            f"note: profile {profile.name} is measured up to b={profile.measured_sizes}; "
            f"larger batches are extrapolated linearly from the last two points",
            file=sys.stderr,
        )
    runs = _every_seed(cfg, simulate)
    print(table(runs))
    _write(cfg, runs)
    return runs


def _run_fleet(cfg: SimConfig) -> list[dict]:
    """Every seed of a fleet file (one or several policies on one device), with its table."""
    runs = _every_seed(cfg, simulate_fleet_file)
    print(fleet_table(runs))
    _write(cfg, runs)
    return runs


def _every_seed(cfg: SimConfig, run: Callable[[SimConfig, int], dict]) -> list[dict]:
    """``run(cfg, seed)`` for each of the ``cfg.seeds`` seeds, with a progress line each."""
    runs = []
    for k in range(cfg.seeds):
        record = run(cfg, cfg.seed + k)
        runs.append(record)
        print(
            f"[{k + 1}/{cfg.seeds}] seed={cfg.seed + k} {record['label']}: avg starvation "
            f"{record['avg_starvation_pct']:.2f}% ({record['wall_s']:.2f} s wall)",
            file=sys.stderr,
        )
    return runs


def _write(cfg: SimConfig, runs: list[dict]) -> None:
    if cfg.output:
        Path(cfg.output).parent.mkdir(parents=True, exist_ok=True)
        Path(cfg.output).write_text(json.dumps({"runs": runs}, indent=2) + "\n")
        print(f"wrote {len(runs)} runs to {cfg.output}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(SimConfig, argv, "lerobot-armory-sim")
    run_or_exit(run, cfg, "lerobot-armory-sim")


if __name__ == "__main__":
    main()
