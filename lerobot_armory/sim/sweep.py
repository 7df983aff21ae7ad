"""``lerobot-armory-sweep``: the reference experiments of docs/spec.md §5 in the simulator.

Three experiment groups, each a grid of :class:`~lerobot_armory.sim.run.SimConfig` runs:

- ``fleet``: fleet sizes × mixes × schedulers (RR, EDF, LA w=1/3/5) × seeds, per preset;
- ``net_sigma`` / ``net_median``: network jitter σ at m = 50 ms, and median m at σ = 0;
- ``batch_cap``: all-fast fleet, batch cap b = 1..10 (chosen batch sizes per scheduler).

Runs go to a process pool with a progress bar; the results land in ``OUT_DIR/sweep.csv``,
``OUT_DIR/sweep.json`` and PNG figures, and the per-tier table at N = 10 is printed.

Profiles: ``demo`` (small, well under a minute), ``full`` (the whole reference sweep).
"""

from __future__ import annotations

import csv
import json
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import TIERS
from lerobot_armory.schedulers import EarliestDeadlineConfig, LookaheadConfig, RoundRobinConfig, SchedulerConfig
from lerobot_armory.sim.presets import MIXES
from lerobot_armory.sim.run import SimConfig, simulate, table

# (scheduler config, fast weight) compared everywhere: RR, EDF, LA w = 1, 3, 5 (docs/spec.md §5).
SCHEDULERS: list[tuple[SchedulerConfig, float]] = [
    (RoundRobinConfig(), 1.0),
    (EarliestDeadlineConfig(), 1.0),
    (LookaheadConfig(), 1.0),
    (LookaheadConfig(), 3.0),
    (LookaheadConfig(), 5.0),
]


@dataclass
class SweepProfile:
    """Grid sizes of one sweep profile."""

    presets: tuple[str, ...]
    fleet_sizes: tuple[int, ...]
    seeds: int
    duration_s: float
    net_mix: str
    net_robots: int
    net_sigmas: tuple[float, ...]
    net_medians_ms: tuple[float, ...]
    caps: tuple[int, ...]
    cap_robots: int


PROFILES: dict[str, SweepProfile] = {
    "demo": SweepProfile(("libero",), (2, 6, 10), 2, 120.0, "one-fast", 6, (0.0, 0.5, 1.0), (25.0, 100.0, 300.0), (1, 2, 3, 5), 10),
    "full": SweepProfile(
        ("libero", "piper"),
        (2, 4, 6, 8, 10),
        3,
        300.0,
        "one-fast",
        10,
        (0.0, 0.25, 0.5, 0.75, 1.0, 1.5),
        (25.0, 50.0, 100.0, 200.0, 350.0, 500.0),
        tuple(range(1, 11)),
        10,
    ),
}


@dataclass
class SweepConfig:
    """Options of ``lerobot-armory-sweep``.

    Attributes:
        profile: ``demo`` (small, < 1 min) or ``full`` (the whole reference sweep).
        out_dir: where the CSV, JSON and figures go.
        workers: parallel simulator processes (default: number of CPUs).
        duration_s: override the profile's simulated seconds per run.
        seeds: override the profile's number of seeds.
        groups: comma-separated subset of fleet,net_sigma,net_median,batch_cap.
    """

    profile: str = "demo"
    out_dir: str = "out/sweep"
    workers: int | None = None
    duration_s: float | None = None
    seeds: int | None = None
    groups: str = "fleet,net_sigma,net_median,batch_cap"


GROUPS = ("fleet", "net_sigma", "net_median", "batch_cap")


def plan(cfg: SweepConfig) -> list[tuple[str, SimConfig, int]]:
    """Every (group, config, seed) of the sweep."""
    if cfg.profile not in PROFILES:
        raise ConfigError("profile", f"unknown sweep profile {cfg.profile!r}; known: {', '.join(PROFILES)}")
    prof = PROFILES[cfg.profile]
    groups = [g.strip() for g in cfg.groups.split(",") if g.strip()]
    for g in groups:
        if g not in GROUPS:
            raise ConfigError("groups", f"unknown group {g!r}; known: {', '.join(GROUPS)}")
    seeds = cfg.seeds if cfg.seeds is not None else prof.seeds
    duration = cfg.duration_s if cfg.duration_s is not None else prof.duration_s
    if seeds < 1:
        raise ConfigError("seeds", f"must be >= 1, got {seeds}")
    if not duration > 0:
        raise ConfigError("duration_s", f"must be > 0, got {duration}")

    def each(group: str, base: SimConfig) -> list[tuple[str, SimConfig, int]]:
        out = []
        for sched, weight in SCHEDULERS:
            c = replace(base, scheduler=sched, fast_weight=weight, duration_s=duration).resolved()
            out += [(group, c, seed) for seed in range(seeds)]
        return out

    jobs: list[tuple[str, SimConfig, int]] = []
    if "fleet" in groups:
        for preset in prof.presets:
            for mix in MIXES:
                for n in prof.fleet_sizes:
                    jobs += each("fleet", SimConfig(preset=preset, mix=mix, robots=n))
    net_base = SimConfig(preset="libero", mix=prof.net_mix, robots=prof.net_robots)
    if "net_sigma" in groups:
        for sigma in prof.net_sigmas:
            jobs += each("net_sigma", replace(net_base, net_median_ms=50.0, net_sigma=sigma))
    if "net_median" in groups:
        for median in prof.net_medians_ms:
            jobs += each("net_median", replace(net_base, net_median_ms=median, net_sigma=0.0))
    if "batch_cap" in groups:
        for cap in prof.caps:
            jobs += each("batch_cap", SimConfig(preset="libero", mix="all-fast", robots=prof.cap_robots, max_batch_size=cap))
    return jobs


def _run_job(job: tuple[str, SimConfig, int]) -> dict[str, Any]:
    group, cfg, seed = job
    record = simulate(cfg, seed)
    record["group"] = group
    return record


CSV_FIELDS = [
    "group", "preset", "mix", "robots", "scheduler", "label", "fast_weight", "depth", "max_batch_size",
    "latency_profile", "net_median_ms", "net_sigma", "seed", "duration_s", "avg_starvation_pct",
    "fast_starvation_pct", "slow_starvation_pct", "fast_executed_s", "slow_executed_s", "executed_s",
    "weighted_executed_s", "mean_batch_size", "decision_ms_p50", "decision_ms_p99", "wall_s",
]  # fmt: skip


def csv_row(r: dict[str, Any]) -> dict[str, Any]:
    """Flatten a run record into one CSV row."""
    sizes = {int(k): v for k, v in r["batch_sizes"].items()}
    total = sum(sizes.values())
    row = {k: r.get(k, "") for k in CSV_FIELDS}
    for tier in TIERS:
        t = r["tiers"].get(tier)
        row[f"{tier}_starvation_pct"] = "" if t is None else round(t["starvation_pct"], 4)
        row[f"{tier}_executed_s"] = "" if t is None else round(t["executed_s"], 3)
    row["mean_batch_size"] = round(sum(k * v for k, v in sizes.items()) / total, 4) if total else ""
    return row


def run(cfg: SweepConfig) -> list[dict[str, Any]]:
    """Run the sweep, write CSV/JSON/figures, print the N=10 tables."""
    jobs = plan(cfg)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    workers = cfg.workers or os.cpu_count() or 1
    print(f"sweep profile={cfg.profile}: {len(jobs)} simulated runs on {workers} worker(s) -> {out}/", file=sys.stderr)
    start = time.perf_counter()
    records: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for record in tqdm(
            pool.map(_run_job, jobs, chunksize=1),
            total=len(jobs),
            desc="simulating",
            unit="run",
            mininterval=0.2 if sys.stderr.isatty() else 10.0,  # keep CI logs short
        ):
            records.append(record)
    elapsed = time.perf_counter() - start

    with open(out / "sweep.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(csv_row(r) for r in records)
    (out / "sweep.json").write_text(json.dumps({"runs": records}) + "\n")
    command = "lerobot-armory-sweep " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    from lerobot_armory.sim.sweep_plots import plot_all  # matplotlib import is slow; only here

    figures = plot_all(records, out)
    (out / "COMMAND.md").write_text(
        f"# How these results were made\n\n```\n{command}\n```\n\n"
        f"{len(records)} runs, {elapsed:.0f} s wall on {workers} worker(s).\n"
    )
    text = summary(records)
    (out / "summary.txt").write_text(text.lstrip("\n") + "\n")
    print(text)
    print(f"\n{len(records)} runs in {elapsed:.1f} s. Results: {out / 'sweep.csv'}, {out / 'sweep.json'}")
    print("Figures:\n" + "\n".join(f"  {p}" for p in figures))
    return records


def summary(records: list[dict[str, Any]]) -> str:
    """Per-tier starvation tables of the largest fleet, one-fast and half-fast, per preset."""
    fleet = [r for r in records if r["group"] == "fleet"]
    if not fleet:
        return table(records)
    n_max = max(r["robots"] for r in fleet)
    parts = []
    for preset in sorted({r["preset"] for r in fleet}):
        for mix in ("one-fast", "half-fast"):
            rows = [r for r in fleet if r["preset"] == preset and r["mix"] == mix and r["robots"] == n_max]
            if rows:
                parts.append(f"\n== {preset}, {mix}, N={n_max}: per-tier starvation (mean over seeds) ==\n" + table(rows))
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(SweepConfig, argv, "lerobot-armory-sweep")
    run_or_exit(run, cfg, "lerobot-armory-sweep")


if __name__ == "__main__":
    main()
