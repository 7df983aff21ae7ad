"""Configuring and running simulated fleets; the JSON run records and the readable table."""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.robot_spec import TIERS
from lerobot_armory.schedulers import LookaheadConfig, SchedulerConfig
from lerobot_armory.sim.fleet_file import Fleet, load_fleet
from lerobot_armory.sim.presets import MIXES, fleet_specs, get_preset
from lerobot_armory.sim.simulator import FleetSimulator, SimResult


@dataclass
class SimConfig:
    """One simulated experiment (``--seeds`` runs of it).

    Attributes:
        preset: reference setup, ``libero`` or ``piper`` (docs/spec.md §5).
        mix: which robots are fast: ``all-fast``, ``one-fast``, ``half-fast``.
        robots: fleet size N.
        scheduler: ``--scheduler.type=rr|edf|lookahead`` and its knobs (``--scheduler.depth``...).
        fast_weight: weight w of fast robots (slow robots weigh 1).
        max_batch_size: batch cap b (default: the preset's cap for the mix).
        latency_profile: built-in profile name or JSON file (default: the preset's).
        net_median_ms: median one-way network delay, ms (default: the preset's).
        net_sigma: log-normal shape of the network delay (default: the preset's).
        duration_s: simulated seconds per run.
        warmup_s: the first seconds are not scored (steady state, no cold start); 0 scores all.
        seeds: number of seeds (runs seed, seed+1, ...).
        seed: first seed.
        output: write the runs as JSON here.
        fleet: a fleet file (YAML/JSON, possibly several policies sharing the device) or
            ``preset:NAME:MIX:N[:FAST_WEIGHT]``; when given, the file sets the robots, profiles,
            batch caps, scheduler and network, and only duration, warm-up, seeds and output apply.
    """

    preset: str = "libero"
    mix: str = "one-fast"
    robots: int = 10
    scheduler: SchedulerConfig = field(default_factory=LookaheadConfig)
    fast_weight: float = 1.0
    max_batch_size: int | None = None
    latency_profile: str | None = None
    net_median_ms: float | None = None
    net_sigma: float | None = None
    duration_s: float = 300.0
    warmup_s: float = 0.0
    seeds: int = 1
    seed: int = 0
    output: str | None = None
    fleet: str | None = None

    def resolved(self) -> SimConfig:
        """Fill preset defaults and check every field (ConfigError names the bad one)."""
        preset = get_preset(self.preset)
        if self.mix not in MIXES:
            raise ConfigError("mix", f"unknown mix {self.mix!r}; known: {', '.join(MIXES)}")
        if self.robots < 1:
            raise ConfigError("robots", f"must be >= 1, got {self.robots}")
        if self.seeds < 1:
            raise ConfigError("seeds", f"must be >= 1, got {self.seeds}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ConfigError("duration_s", f"must be > 0, got {self.duration_s}")
        if not (math.isfinite(self.warmup_s) and 0 <= self.warmup_s < self.duration_s):
            raise ConfigError("warmup_s", f"must be in [0, duration_s), got {self.warmup_s}")
        if self.fleet:
            load_fleet(self.fleet)  # the fleet file checks itself field by field
            return self
        cfg = replace(
            self,
            max_batch_size=preset.default_batch_cap(self.mix) if self.max_batch_size is None else self.max_batch_size,
            latency_profile=self.latency_profile or preset.latency_profile,
            net_median_ms=preset.net_median_ms if self.net_median_ms is None else self.net_median_ms,
            net_sigma=preset.net_sigma if self.net_sigma is None else self.net_sigma,
        )
        if cfg.max_batch_size < 1:
            raise ConfigError("max_batch_size", f"must be >= 1, got {cfg.max_batch_size}")
        # Build once to validate the profile, the network and the scheduler's own knobs.
        cfg.scheduler.make(load_profile(cfg.latency_profile), cfg.max_batch_size)
        cfg.network()
        fleet_specs(preset, cfg.mix, cfg.robots, cfg.fast_weight)
        return cfg

    def network(self) -> LogNormalDelay:
        """The one-way delay model (used for uplink and downlink alike)."""
        return LogNormalDelay((self.net_median_ms or 0.0) / 1000.0, self.net_sigma or 0.0)


def simulate(cfg: SimConfig, seed: int) -> dict[str, Any]:
    """Run one seed of a resolved config; returns its JSON run record."""
    preset = get_preset(cfg.preset)
    profile = load_profile(cfg.latency_profile)
    assert cfg.max_batch_size is not None
    scheduler = cfg.scheduler.make(profile, cfg.max_batch_size)
    specs = fleet_specs(preset, cfg.mix, cfg.robots, cfg.fast_weight)
    net = cfg.network()
    start = time.perf_counter()
    result = FleetSimulator(specs, scheduler, cfg.duration_s, net, net, seed, warmup_s=cfg.warmup_s).run()
    return run_record(cfg, seed, result, time.perf_counter() - start, profile.is_extrapolated(cfg.max_batch_size))


def fleet_simulator(
    fleet: Fleet, duration_s: float, seed: int, warmup_s: float = 0.0, trace: bool = False
) -> FleetSimulator:
    """The simulator of ``fleet`` on one device: its scheduler built for its profile and cap, or,
    when several policies share the device, one per policy (same type and knobs) built for that
    policy's profile and cap, arbitrated."""
    net = fleet.network()
    if not fleet.is_mixed:
        scheduler = fleet.scheduler.make(fleet.profile(), fleet.max_batch_size)
        return FleetSimulator(fleet.specs(), scheduler, duration_s, net, net, seed, warmup_s=warmup_s, trace=trace)
    schedulers = {p.name: fleet.scheduler.make(p.profile(), p.max_batch_size) for p in fleet.policies}
    return FleetSimulator(
        fleet.specs(), schedulers, duration_s, net, net, seed,
        warmup_s=warmup_s, policy_of=fleet.policy_of(), trace=trace,
    )  # fmt: skip


def simulate_fleet_file(cfg: SimConfig, seed: int) -> dict[str, Any]:
    """Run one seed of ``cfg.fleet``; returns its JSON run record (:func:`fleet_record`)."""
    assert cfg.fleet
    fleet = load_fleet(cfg.fleet)
    start = time.perf_counter()
    result = fleet_simulator(fleet, cfg.duration_s, seed, cfg.warmup_s).run()
    return fleet_record(fleet, seed, result, time.perf_counter() - start, cfg.warmup_s)


def fleet_record(fleet: Fleet, seed: int, result: SimResult, wall_s: float, warmup_s: float = 0.0) -> dict[str, Any]:
    """A fleet-file run as JSON: the whole fleet's starvation, per tier, and per policy (each
    policy's profile, cap, tiers, batch sizes and the device seconds its batches took)."""
    policies = fleet.policies or ()
    per_policy = {}
    for p in policies:
        rows = [r for r in result.robots if r.policy == p.name]
        per_policy[p.name] = {
            "latency_profile": p.latency_profile,
            "max_batch_size": p.max_batch_size,
            "robots": len(rows),
            "starvation_pct": result.policy_starvation_pct(p.name) if rows else None,
            "tiers": {
                t: result.policy_starvation_pct(p.name, t) for t in TIERS if any(r.tier == t for r in rows)
            },
            "device_s": result.device_s.get(p.name, 0.0),
            "batch_sizes": {str(b): c for b, c in sorted(result.policy_batch_sizes.get(p.name, {}).items())},
        }
    return {
        "fleet": fleet.source,
        "label": fleet.scheduler.label(),
        "scheduler": fleet.scheduler.type,
        "robots": fleet.robots,
        "seed": seed,
        "latency_profile": None if fleet.is_mixed else fleet.latency_profile,
        "max_batch_size": None if fleet.is_mixed else fleet.max_batch_size,
        "net_median_ms": fleet.net_median_ms,
        "net_sigma": fleet.net_sigma,
        "duration_s": result.duration_s,
        "warmup_s": warmup_s,
        "avg_starvation_pct": result.avg_starvation_pct,
        "tiers": {
            t: {"robots": len(result.tier(t)), "starvation_pct": result.tier_starvation_pct(t)}
            for t in TIERS
            if result.tier(t)
        },
        "policies": per_policy,
        "executed_s": result.executed_s,
        "batch_sizes": {str(b): c for b, c in sorted(result.batch_sizes.items())},
        "decision_ms_p99": result.decision_ms(99),
        "held_s": result.held_s,
        "wall_s": wall_s,
    }


def fleet_table(runs: list[dict[str, Any]]) -> str:
    """Readable table of fleet-file runs: one row per policy (and one for the whole fleet),
    averaged over seeds."""
    header = (
        f"{'fleet / policy':<28} {'robots':>6} {'seeds':>5} {'fast starv%':>11} {'slow starv%':>11} "
        f"{'avg starv%':>10} {'device s':>9}"
    )
    lines = [header, "-" * len(header)]
    n = len(runs)

    def mean(values: list[float]) -> str:
        values = [v for v in values if v is not None and not math.isnan(v)]
        return f"{np.mean(values):.2f}" if values else "-"

    first = runs[0]
    lines.append(
        f"{first['label'] + ' (all)':<28} {first['robots']:>6} {n:>5} "
        f"{mean([r['tiers'].get('fast', {}).get('starvation_pct') for r in runs]):>11} "
        f"{mean([r['tiers'].get('slow', {}).get('starvation_pct') for r in runs]):>11} "
        f"{mean([r['avg_starvation_pct'] for r in runs]):>10} {'':>9}"
    )
    for name, info in first["policies"].items():
        rows = [r["policies"][name] for r in runs]
        lines.append(
            f"{'  ' + name:<28} {info['robots']:>6} {n:>5} "
            f"{mean([r['tiers'].get('fast') for r in rows]):>11} {mean([r['tiers'].get('slow') for r in rows]):>11} "
            f"{mean([r['starvation_pct'] for r in rows]):>10} {np.mean([r['device_s'] for r in rows]):>9.1f}"
        )
    return "\n".join(lines)


def run_record(cfg: SimConfig, seed: int, result: SimResult, wall_s: float, extrapolated: bool) -> dict[str, Any]:
    """The JSON schema of ``--output`` (the live benchmark writes the same)."""
    sched = cfg.scheduler
    tiers = {}
    for tier in TIERS:
        rows = result.tier(tier)
        if rows:
            tiers[tier] = {
                "robots": len(rows),
                "starvation_pct": result.tier_starvation_pct(tier),
                "executed_s": sum(r.executed_s for r in rows),
            }
    return {
        "scheduler": sched.type,
        "label": run_label(sched.type, cfg.fast_weight, getattr(sched, "depth", 1)) + sched.timing_label(),
        "wait_ms": sched.wait_ms,
        "depth": getattr(sched, "depth", None),
        "preset": cfg.preset,
        "mix": cfg.mix,
        "robots": cfg.robots,
        "seed": seed,
        "max_batch_size": cfg.max_batch_size,
        "fast_weight": cfg.fast_weight,
        "latency_profile": cfg.latency_profile,
        "latency_extrapolated": extrapolated,
        "net_median_ms": cfg.net_median_ms,
        "net_sigma": cfg.net_sigma,
        "duration_s": cfg.duration_s,
        "warmup_s": cfg.warmup_s,
        "avg_starvation_pct": result.avg_starvation_pct,
        "tiers": tiers,
        "executed_s": result.executed_s,
        "weighted_executed_s": result.weighted_executed_s,
        "batch_sizes": {str(b): c for b, c in sorted(result.batch_sizes.items())},
        "first_executed_index": dict(sorted(result.first_executed_index().items(), key=_index_key)),
        "decision_ms_p50": result.decision_ms(50),
        "decision_ms_p99": result.decision_ms(99),
        "decision_cpu_ms_p50": result.decision_cpu_ms(50),
        "decision_cpu_ms_p99": result.decision_cpu_ms(99),
        "held_s": result.held_s,
        "mirror_index_error_p99": float(np.percentile(result.mirror_index_error, 99)) if result.mirror_index_error else 0.0,
        "per_robot": [
            {"robot_id": r.robot_id, "tier": r.tier, "starvation_pct": r.starvation_pct, "executed_s": r.executed_s}
            for r in result.robots
        ],
        "wall_s": wall_s,
    }


def _index_key(item: tuple[str, int]) -> tuple[int, int]:
    key = item[0]
    return (1, 0) if key == "unused" else (0, int(key))


def run_label(scheduler: str, fast_weight: float, depth: int | None = 1) -> str:
    """Short human label: ``RR``, ``EDF``, ``LA w=3`` (``L=2`` when not default)."""
    if scheduler == "rr":
        return "RR"
    if scheduler == "edf":
        return "EDF"
    if scheduler == "lookahead":
        label = f"LA w={fast_weight:g}"
        if depth and depth != 1:
            label += f" L={depth}"
        return label
    return f"{scheduler} w={fast_weight:g}"


def table(runs: list[dict[str, Any]]) -> str:
    """Readable table, one row per (preset, mix, N, b, network, scheduler) averaged over seeds."""
    groups: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in runs:
        key = (r["preset"], r["mix"], r["robots"], r["max_batch_size"], r["net_median_ms"], r["net_sigma"], r["label"])
        groups[key].append(r)
    header = (
        f"{'preset':<7} {'mix':<9} {'N':>3} {'b':>2} {'net ms/σ':>9} {'scheduler':<14} {'seeds':>5} "
        f"{'fast starv%':>11} {'slow starv%':>11} {'avg starv%':>10} {'exec s':>8} {'mean b':>6} {'dec p99 ms':>10}"
    )
    lines = [header, "-" * len(header)]
    for key, rows in groups.items():
        preset, mix, n, b, med, sig, label = key
        fast = _mean_tier(rows, "fast")
        slow = _mean_tier(rows, "slow")
        avg = np.mean([r["avg_starvation_pct"] for r in rows])
        executed = np.mean([r["executed_s"] for r in rows])
        sizes = defaultdict(int)
        for r in rows:
            for k, v in r["batch_sizes"].items():
                sizes[int(k)] += v
        total = sum(sizes.values())
        mean_b = sum(k * v for k, v in sizes.items()) / total if total else 0.0
        p99 = max(r["decision_ms_p99"] for r in rows)
        lines.append(
            f"{preset:<7} {mix:<9} {n:>3} {b:>2} {med:>5g}/{sig:<3g} {label:<14} {len(rows):>5} "
            f"{fast:>11} {slow:>11} {avg:>10.2f} {executed:>8.1f} {mean_b:>6.2f} {p99:>10.3f}"
        )
    return "\n".join(lines)


def _mean_tier(rows: list[dict[str, Any]], tier: str) -> str:
    values = [r["tiers"][tier]["starvation_pct"] for r in rows if tier in r["tiers"]]
    return f"{np.mean(values):.2f}" if values else "-"
